"""Benchmark level two per window: graph build, data term, α-expansion and refits.

Windows are 30 ms synthetic scenes (``evseg_torch.synthetic.make_scene``) of about ``--events`` events on a
180 x 240 sensor with ``--objects`` moving objects, affine4 motions. The pool is the true models perturbed by
about a pixel of displacement plus ``--spurious`` random models (3-4 models in all by default), as level one
would hand it over. Prints, per stage, the median over windows and repeats of the time per window (summed
over the outer iterations), the median number of outer iterations, the graph's size in events and in
sites, and ``torch.get_num_threads()``.

Threads: level two's tensors are small (K x 30k events, K images of 180 x 240), so intra-op threads gain
little, and on a loaded machine (other processes on the 2 cores) OpenMP's spinning workers make every op
wait for a descheduled thread: measured 3.8 s per window with 2 threads against 0.6 s with 1 (single ops
up to 100x slower). Hence ``--threads 1`` by default; ``OMP_WAIT_POLICY=PASSIVE`` in the environment (set
before Python starts) removes most of the penalty for 2 threads (0.8 s).

    .venv/bin/python benchmarks/bench_level_two.py [--events 30000 --windows 3 --repeats 2 --threads 1]

The ``graph`` stage includes the site graph and the graph cut's node numbering (once per window).
Comparisons: ``--site-time-slices 0`` labels events (EMSGC's graph), ``--warm-max-iter 10`` refits fully
every round, ``--n-iter-labeling 1`` runs one α-expansion cycle per labelling.
"""

import argparse
import time

import numpy as np
import torch

from evseg_torch.app.threads import set_threads
from evseg_torch.events import to_torch
from evseg_torch.level_two.descent.segmenter import GraphCutContrastSegmenter
from evseg_torch.level_two.energy.graph import event_graph, site_graph
from evseg_torch.synthetic import make_scene


def make_window(n_events, n_objects, n_spurious, seed):
    scene = make_scene((180, 240), duration=0.03, n_objects=n_objects, n_events=n_events, rng=seed)
    model = scene.motions[0].model
    truth = np.stack([motion.params for motion in scene.motions])
    rng = np.random.default_rng(seed)
    init = truth + rng.normal(0, 1.0, truth.shape) / model.displacement_scale(0.03)
    spurious = rng.normal(0, 1, (n_spurious, truth.shape[1])) * np.array([600.0, 600.0, 3.0, 3.0])
    return scene, model, torch.as_tensor(np.concatenate([init, spurious]), dtype=torch.float32)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--events", type=int, default=30_000)
    parser.add_argument("--objects", type=int, default=2)
    parser.add_argument("--spurious", type=int, default=1)
    parser.add_argument("--windows", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads (0: torch's default)")
    parser.add_argument("--max-iter", type=int, default=10, help="first refit's iterations (L-BFGS)")
    parser.add_argument("--warm-max-iter", type=int, default=3, help="later refits' iterations")
    parser.add_argument("--n-iter-labeling", type=int, default=2, help="α-expansion cycles per labelling")
    parser.add_argument(
        "--site-time-slices", type=int, default=1, help="time slices of the graph-cut sites (0: events)"
    )
    args = parser.parse_args()
    if args.threads:
        set_threads(args.threads)
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, device cpu")

    stages = ("graph", "data_term", "labelling", "refit", "images")
    per_stage = {name: [] for name in stages}
    totals, rounds, graph_only, site_only, cost_only = [], [], [], [], []
    for window in range(args.windows):
        scene, model, pool = make_window(args.events, args.objects, args.spurious, seed=window)
        events = to_torch(scene.events)
        segmenter = GraphCutContrastSegmenter(
            model,
            (180, 240),
            max_iter=args.max_iter,
            warm_max_iter=args.warm_max_iter,
            n_iter_labeling=args.n_iter_labeling,
            site_time_slices=args.site_time_slices or None,
        )
        edges, weights = event_graph(events)
        sites, site_edges, _ = site_graph(events, time_slices=max(args.site_time_slices, 1))
        print(
            f"window {window}: N={len(events)} K={pool.shape[0]} edges={len(edges)} "
            f"(weight sum {weights.sum():.0f}, {len(edges) / len(events):.2f} edges per event); "
            f"{sites.max() + 1} sites, {len(site_edges)} site edges"
        )
        segmenter(events, pool)  # warm-up
        for _ in range(args.repeats):
            start = time.perf_counter()
            result = segmenter(events, pool)
            totals.append(1e3 * (time.perf_counter() - start))
            rounds.append(len(result.energy_history))
            for name in stages:
                per_stage[name].append(result.timings_ms[name])
            start = time.perf_counter()
            event_graph(events)
            graph_only.append(1e3 * (time.perf_counter() - start))
            start = time.perf_counter()
            site_graph(events, time_slices=max(args.site_time_slices, 1))
            site_only.append(1e3 * (time.perf_counter() - start))
            start = time.perf_counter()
            with torch.no_grad():
                segmenter.data_term(events, pool)
            cost_only.append(1e3 * (time.perf_counter() - start))
        print(
            f"  final models {result.params.shape[0]}, energies {[round(e) for e in result.energy_history]}"
        )

    print(f"median per window over {len(totals)} runs (ms), median outer rounds {np.median(rounds):.0f}:")
    for name in stages:
        print(f"  {name:<10} {np.median(per_stage[name]):8.1f}")
    print(f"  {'total':<10} {np.median(totals):8.1f}")
    print(
        f"one event_graph call: {np.median(graph_only):.1f} ms; one site_graph call: "
        f"{np.median(site_only):.1f} ms; one data-term call (K={pool.shape[0]}): "
        f"{np.median(cost_only):.1f} ms"
    )


if __name__ == "__main__":
    main()
