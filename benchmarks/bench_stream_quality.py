"""Streams against cold windows: per-window quality of ``CascadedSegmenter.stream`` over continuous scenes.

Each scene of the ``hard`` family (:mod:`evseg_torch.synthetic.families`) is generated 0.3 s long and
streamed in 30 ms windows (model reuse and guided tracking on, as in ``evseg segment``); every window is
also segmented on its own, cold. Both are scored like the probe scenes (ambiguous and noise events left
out; detection by percentile boxes) and the means over the windows with a moving object are printed,
with the median milliseconds per window of each mode. ``--set`` overrides apply to both modes; with
``--pipeline-seeds 0-2`` each figure is the mean over the pipeline seeds.

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/bench_stream_quality.py [--seeds 0-7] \
        [--pipeline-seeds 0-2] [--set initial_models=replace]
"""

import argparse
import time

import numpy as np
from bench_quality import add_overrides

from evseg_torch.app.cli.options import seed_range
from evseg_torch.app.threads import set_threads
from evseg_torch.config import SegmenterConfig, replace_config
from evseg_torch.errors import ConfigError
from evseg_torch.evaluation.labelled import score_labelling
from evseg_torch.pipeline import CascadedSegmenter
from evseg_torch.synthetic.families import make_family_scene

METRICS = ("accuracy", "iou", "detection")


def score_scene(scene, config, cold: bool) -> dict[str, list]:
    """Per-window scores and milliseconds of one scene, streamed and (``cold``) cold."""
    segmenter = CascadedSegmenter(scene.sensor_size, config)
    xy = np.column_stack([scene.events["x"], scene.events["y"]])
    out = {"stream": [], "cold": [], "stream_ms": [], "cold_ms": []}
    stream = segmenter.stream(scene.events, window_ms=30.0)
    while True:
        start = time.perf_counter()
        streamed = next(stream, None)
        if streamed is None:
            return out
        out["stream_ms"].append(1e3 * (time.perf_counter() - start))
        modes = [("stream", streamed.labels)]
        if cold:
            start = time.perf_counter()
            modes.append(("cold", segmenter(streamed.events).labels))
            out["cold_ms"].append(1e3 * (time.perf_counter() - start))
        window = slice(streamed.offset, streamed.offset + len(streamed.labels))
        for mode, labels in modes:
            score = score_labelling(
                labels,
                scene.labels[window],
                xy[window],
                ignore=scene.ambiguous[window],
                n_layers=len(scene.motions),
            )
            if score.n_objects:
                out[mode].append(score)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=seed_range, default=list(range(8)), help="scene seeds (default 0-7)")
    parser.add_argument("--duration-ms", type=float, default=300.0, help="scene length (default 300 ms)")
    parser.add_argument(
        "--pipeline-seeds", type=seed_range, default=[0], help="pipeline seeds, e.g. 0-2 (default 0)"
    )
    add_overrides(parser, "flat config override, e.g. initial_models=replace")
    parser.add_argument("--no-cold", action="store_true", help="stream only (compare variants' streams)")
    args = parser.parse_args()
    set_threads(1)
    scenes = []
    for seed in args.seeds:
        try:
            scenes.append(make_family_scene("hard", seed, duration=args.duration_ms * 1e-3))
        except ConfigError as error:
            print(f"seed {seed}: skipped, {error}")
    base = replace_config(SegmenterConfig(), **dict(args.set))
    runs = {"stream": [], "cold": [], "stream_ms": [], "cold_ms": []}
    for pipeline_seed in args.pipeline_seeds:
        config = replace_config(base, seed=pipeline_seed)
        scored = [score_scene(scene, config, not args.no_cold) for scene in scenes]
        for key in runs:
            runs[key].append([row for scene in scored for row in scene[key]])
    if not runs["stream"][0]:
        raise SystemExit("no window with a moving object to score")
    print(
        f"{len(runs['stream'][0])} windows with a moving object in {len(scenes)} scenes, "
        f"pipeline seeds {args.pipeline_seeds}, overrides {dict(args.set)}"
    )
    for mode in ("stream",) if args.no_cold else ("stream", "cold"):
        means = {
            name: np.mean([np.mean([getattr(s, name) for s in run]) for run in runs[mode]])
            for name in METRICS
        }
        ms = np.median(np.concatenate(runs[f"{mode}_ms"]))
        print(
            f"{mode:>6}: accuracy {means['accuracy']:.3f}, IMO IoU {means['iou']:.3f}, "
            f"detection {means['detection']:.3f}, {ms:.0f} ms per window (median)"
        )


if __name__ == "__main__":
    main()
