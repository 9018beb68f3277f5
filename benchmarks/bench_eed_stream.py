"""Stream the EED sequences in ``../shared`` window after window, as ``evseg segment`` does, and report
whether objects seen together are apart (each its own id) and the time per window.

At every GT box time with two or more boxes that a window holds, the objects are *apart* when each box's
events belong to a cluster of its own, none the background
(:func:`evseg_torch.evaluation.eed.separate_in_stream`). The EED sequences with one object report their
box times in view as 0.

    .venv/bin/python benchmarks/bench_eed_stream.py [--pipeline-seeds 0-2] [--config eed] [--set KEY=VALUE]
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
from evseg_torch.evaluation.eed import load_eed_sequence, separate_in_stream
from evseg_torch.pipeline import CascadedSegmenter


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--config", default="eed", help="YAML config or a bundled config's name (default eed)"
    )
    add_overrides(parser, "flat config override, e.g. lambda_label=3000")
    parser.add_argument("--pipeline-seeds", type=seed_range, default=[0], help="e.g. 0-2 (default 0)")
    args = parser.parse_args()
    set_threads(1)
    path = Path(args.config) if Path(args.config).is_file() else bundled_config(args.config)
    base = replace_config(load_config(path), **dict(args.set))
    print(f"{'sequence':<36} {'windows':>7} {'in view':>7} {'apart':>6} {'ms/window':>9}")
    for name in EED_SEQUENCES:
        sequence = load_eed_sequence(REAL / f"eed_{name}")
        in_view, apart, per_window, n_windows = [], [], [], []
        for seed in args.pipeline_seeds:
            segmenter = CascadedSegmenter(sequence.sensor_size, replace_config(base, seed=seed))
            start = time.perf_counter()
            windows = list(segmenter.stream(sequence.events))
            per_window.append(1e3 * (time.perf_counter() - start) / max(len(windows), 1))
            seen, together = separate_in_stream(windows, sequence.box_times_s, sequence.boxes)
            in_view.append(seen)
            apart.append(together)
            n_windows.append(len(windows))
        print(
            f"{name:<36} {np.mean(n_windows):7.0f} {np.mean(in_view):7.1f} {np.mean(apart):6.1f} "
            f"{statistics.median(per_window):9.1f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
