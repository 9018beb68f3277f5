"""Streams against cold windows: per-window quality of ``CascadedSegmenter.stream`` over continuous scenes.

Each scene of the ``hard`` family (:mod:`evseg_torch.synthetic_families`) is generated 0.3 s long and
streamed in 30 ms windows (model reuse and guided tracking on, as in ``evseg segment``); every window is
also segmented on its own, cold. Both are scored like the probe scenes (ambiguous and noise events left
out; detection by percentile boxes) and the means over the windows with a moving object are printed.

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/bench_stream_quality.py [--seeds 0-7]
"""

import argparse

import numpy as np
import torch

from evseg_torch.cli import _seed_range
from evseg_torch.errors import ConfigError
from evseg_torch.evaluation.labelled import score_labelling
from evseg_torch.pipeline import CascadedSegmenter
from evseg_torch.synthetic_families import make_family_scene


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=_seed_range, default=list(range(8)), help="scene seeds (default 0-7)")
    parser.add_argument("--duration-ms", type=float, default=300.0, help="scene length (default 300 ms)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    scores = {"stream": [], "cold": []}
    for seed in args.seeds:
        try:
            scene = make_family_scene("hard", seed, duration=args.duration_ms * 1e-3)
        except ConfigError as error:
            print(f"seed {seed}: skipped, {error}")
            continue
        segmenter = CascadedSegmenter(scene.sensor_size)
        xy = np.column_stack([scene.events["x"], scene.events["y"]])
        for streamed in segmenter.stream(scene.events, window_ms=30.0):
            window = slice(streamed.offset, streamed.offset + len(streamed.labels))
            for mode, labels in (("stream", streamed.labels), ("cold", segmenter(streamed.events).labels)):
                score = score_labelling(
                    labels,
                    scene.labels[window],
                    xy[window],
                    ignore=scene.ambiguous[window],
                    n_layers=len(scene.motions),
                )
                if score.n_objects:
                    scores[mode].append(score)
    print(f"{len(scores['stream'])} windows of {len(args.seeds)} scenes")
    if not scores["stream"]:
        raise SystemExit("no window with a moving object to score")
    for mode, rows in scores.items():
        means = {name: np.mean([getattr(s, name) for s in rows]) for name in ("accuracy", "iou", "detection")}
        print(
            f"{mode:>6}: accuracy {means['accuracy']:.3f}, IMO IoU {means['iou']:.3f}, "
            f"detection {means['detection']:.3f}"
        )


if __name__ == "__main__":
    main()
