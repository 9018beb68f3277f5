"""Benchmark level two on batches of windows: events per second for B windows segmented together.

Windows are 30 ms synthetic scenes (``make_scene((180, 240), 0.03, n_objects=2, rng=seed)``) of about
``--events`` events, affine4 motions; each window's pool is its true models perturbed by about a pixel of
displacement plus one spurious model, as level one would hand it over. The ``--windows`` windows are
segmented in batches of B (a list of B windows per call, see ``GraphCutContrastSegmenter.forward``) for
every B of ``--batch-sizes``; the batch sizes take turns within each repeat, so that the load of a shared
machine falls on all alike, and medians over the repeats are reported. A batch's results equal those of
its windows one by one (on CPU bit for bit), so every B does the same work.

Prints one row per B: milliseconds per window and events per second, then each stage of
``LevelTwoResult.timings_ms`` in milliseconds per window (a stage run for several windows at once is
shared evenly by them). On CUDA the device is synchronised before each clock reading.

    .venv/bin/python benchmarks/bench_batched.py [--windows 32 --batch-sizes 1 8 32 --device cpu]

Threads: ``--threads 1`` by default, and ``OMP_WAIT_POLICY=PASSIVE`` in the environment, as for
``bench_level_two.py`` (spinning OpenMP workers on a loaded machine slow every op).
"""

import argparse
import statistics
import time

import numpy as np
import torch

from evseg_torch.app.threads import set_threads
from evseg_torch.events import to_torch
from evseg_torch.level_two.descent.segmenter import GraphCutContrastSegmenter
from evseg_torch.synthetic import make_scene

STAGES = ("graph", "data_term", "labelling", "refit", "discovery", "images")


def make_windows(count, n_events, device):
    """``count`` windows and pools, and the motion model."""
    windows, pools = [], []
    for seed in range(count):
        scene = make_scene((180, 240), 0.03, n_objects=2, n_events=n_events, rng=seed)
        model = scene.motions[0].model
        truth = np.stack([motion.params for motion in scene.motions])
        rng = np.random.default_rng(seed)
        init = truth + rng.normal(0, 1.0, truth.shape) / model.displacement_scale(0.03)
        spurious = rng.normal(0, 1, (1, truth.shape[1])) * np.array([600.0, 600.0, 3.0, 3.0])
        windows.append(to_torch(scene.events, device=device))
        pools.append(torch.as_tensor(np.concatenate([init, spurious]), dtype=torch.float32, device=device))
    return windows, pools, model


def run(segmenter, windows, pools, batch_size, device):
    """Segment all windows in batches of ``batch_size``; the wall-clock seconds and the results."""
    results = []
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    start = time.perf_counter()
    for first in range(0, len(windows), batch_size):
        batch = slice(first, first + batch_size)
        results += segmenter(windows[batch], pools[batch])
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter() - start, results


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--windows", type=int, default=32, help="windows in all (a multiple of every B)")
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 8, 32])
    parser.add_argument("--events", type=int, default=40_000, help="events per window, about")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=1, help="torch and OpenCV threads (0: their defaults)")
    args = parser.parse_args()
    if args.threads:
        set_threads(args.threads)
    device = torch.device(args.device)
    sizes = [size for size in args.batch_sizes if size <= args.windows]
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, device {device}")

    windows, pools, model = make_windows(args.windows, args.events, device)
    n_events = sum(len(window) for window in windows)
    print(f"{len(windows)} windows, {n_events / len(windows):.0f} events per window on average")
    segmenter = GraphCutContrastSegmenter(model, (180, 240))
    run(segmenter, windows[:2], pools[:2], 2, device)  # warm-up

    seconds = {size: [] for size in sizes}
    stages = {size: {stage: [] for stage in STAGES} for size in sizes}
    for _ in range(args.repeats):
        for size in sizes:
            elapsed, results = run(segmenter, windows, pools, size, device)
            seconds[size].append(elapsed)
            for stage in STAGES:
                stages[size][stage].append(sum(result.timings_ms[stage] for result in results) / len(results))

    header = f"{'B':>3} {'ms/window':>10} {'events/s':>10} " + " ".join(f"{stage:>10}" for stage in STAGES)
    print(header)
    for size in sizes:
        elapsed = statistics.median(seconds[size])
        per_stage = " ".join(f"{statistics.median(stages[size][stage]):10.1f}" for stage in STAGES)
        print(f"{size:>3} {1e3 * elapsed / len(windows):10.1f} {n_events / elapsed:10.0f} {per_stage}")


if __name__ == "__main__":
    main()
