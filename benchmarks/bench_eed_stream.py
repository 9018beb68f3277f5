"""Stream the EED sequences in ``../shared`` window after window, as ``evseg segment`` does, and report
the detection rates, whether objects seen together are apart (each its own id) and the time per window,
beside the same windows segmented cold (``--cold``).

Each GT box is scored on the streamed window holding its time, its clusters compensated to the box time
(:func:`evseg_torch.evaluation.eed.evaluate_stream_boxes`): ``I/pred`` and ``nested`` are the protocol's
readings (percent of the boxes a window holds); the cold columns score every streamed window segmented
again on its own, with no models carried in.

At every GT box time with two or more boxes that a window holds, the objects are *apart* when each box's
events belong to a cluster of its own, none the background
(:func:`evseg_torch.evaluation.eed.separate_in_stream`). The EED sequences with one object report their
box times in view as 0.

    .venv/bin/python benchmarks/bench_eed_stream.py [--pipeline-seeds 0-2] [--config eed] \
        [--set KEY=VALUE] [--cold]
"""

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from bench_quality import EED_SEQUENCES, REAL, add_overrides  # the benchmarks' sets and options

from evseg_torch.app.cli.options import seed_range
from evseg_torch.app.threads import set_threads
from evseg_torch.config import bundled_config, load_config, replace_config
from evseg_torch.evaluation.eed import (
    detection_rate,
    evaluate_stream_boxes,
    load_eed_sequence,
    separate_in_stream,
)
from evseg_torch.pipeline import CascadedSegmenter


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--config", default="eed", help="YAML config or a bundled config's name (default eed)"
    )
    add_overrides(parser, "flat config override, e.g. lambda_label=3000")
    parser.add_argument("--pipeline-seeds", type=seed_range, default=[0], help="e.g. 0-2 (default 0)")
    parser.add_argument("--cold", action="store_true", help="also segment every window cold")
    args = parser.parse_args()
    set_threads(1)
    path = Path(args.config) if Path(args.config).is_file() else bundled_config(args.config)
    base = replace_config(load_config(path), **dict(args.set))
    modes = ("stream", "cold") if args.cold else ("stream",)
    header = "".join(f" {mode + ' I/pred':>12} {'nested':>6} {'ms/window':>9}" for mode in modes)
    print(f"{'sequence':<36} {'windows':>7} {'in view':>7} {'apart':>6}{header}")
    for name in EED_SEQUENCES:
        sequence = load_eed_sequence(REAL / f"eed_{name}")
        rows = {key: [] for key in ("in_view", "apart", "windows")}
        for seed in args.pipeline_seeds:
            segmenter = CascadedSegmenter(sequence.sensor_size, replace_config(base, seed=seed))
            start = time.perf_counter()
            windows = list(segmenter.stream(sequence.events))
            timed = {"stream": (windows, 1e3 * (time.perf_counter() - start) / max(len(windows), 1))}
            if args.cold:
                start = time.perf_counter()
                cold = [segmenter(window.events) for window in windows]
                timed["cold"] = (cold, 1e3 * (time.perf_counter() - start) / max(len(windows), 1))
            for mode, (segmentations, ms) in timed.items():
                boxes = evaluate_stream_boxes(
                    segmentations, sequence.box_times_s, sequence.boxes, segmenter.motion
                )
                rates = detection_rate(boxes)
                for key in ("detection_rate_over_predicted", "detection_rate_nested"):
                    rows.setdefault((mode, key), []).append(rates.get(key, float("nan")))
                rows.setdefault((mode, "ms"), []).append(ms)
            seen, together = separate_in_stream(windows, sequence.box_times_s, sequence.boxes)
            rows["in_view"].append(seen)
            rows["apart"].append(together)
            rows["windows"].append(len(windows))
        cells = "".join(
            f" {np.mean(rows[mode, 'detection_rate_over_predicted']):12.1f}"
            f" {np.mean(rows[mode, 'detection_rate_nested']):6.1f}"
            f" {statistics.median(rows[mode, 'ms']):9.1f}"
            for mode in modes
        )
        print(
            f"{name:<36} {np.mean(rows['windows']):7.0f} {np.mean(rows['in_view']):7.1f} "
            f"{np.mean(rows['apart']):6.1f}{cells}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
