"""Per-module time of the whole pipeline per window, like the paper's Table III.

Synthetic: ``--windows`` 30 ms scenes (180 x 240, 1-3 objects), each segmented cold (level one from
scratch) and, as the second window of a 60 ms scene, with the previous window's models reused.
EED: the 30 ms windows of ``eed_occlusions`` streamed with model reuse (skipped if the recording is
absent). Prints the median milliseconds of features, level one, level two and the total, the CPU and
the torch thread count.

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/bench_pipeline.py [--windows 10 --threads 1]
        [--events 40000] [--set n_iter_segmentation=2]

``--set`` changes the default config (flat keys, repeatable), e.g. to time a variant beside the default
in another process at the same time.
"""

import argparse
import platform
from pathlib import Path

import numpy as np
import torch
from bench_quality import add_overrides  # the benchmarks' one KEY=VALUE option (run as a script)

from evseg_torch import CascadedSegmenter
from evseg_torch.app.threads import set_threads
from evseg_torch.config import SegmenterConfig, replace_config
from evseg_torch.evaluation.eed import load_eed_sequence
from evseg_torch.synthetic import make_scene

EED = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "eed_occlusions"
STAGES = ("features", "level_one", "level_two", "total")


def row(name: str, timings: list[dict], events: list[int]) -> str:
    medians = [np.median([t[s] for t in timings]) for s in STAGES]
    return f"{name:<28} {len(timings):>4} {int(np.median(events)):>7} " + " ".join(
        f"{m:>9.1f}" for m in medians
    )


def cpu_name() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines() if Path("/proc/cpuinfo").exists() else []:
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown CPU"


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--windows", type=int, default=10)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--events", type=int, help="signal events per 30 ms window (default: generator's)")
    add_overrides(parser, "flat override of the default config, e.g. n_iter_segmentation=2")
    args = parser.parse_args()
    set_threads(args.threads)
    config = replace_config(SegmenterConfig(), **dict(args.set))
    overrides = dict(args.set) or "none"
    print(f"{cpu_name()}, threads {torch.get_num_threads()} (torch and OpenCV), overrides {overrides}")
    header = ("features", "level one", "level two", "total")
    print(f"{'windows':<28} {'n':>4} {'events':>7} " + " ".join(f"{h:>9}" for h in header))
    cold, reuse, sizes_cold, sizes_reuse = [], [], [], []
    for seed in range(args.windows):
        size = {} if args.events is None else {"n_events": 2 * args.events}
        scene = make_scene((180, 240), 0.06, 1 + seed % 3, rng=seed, **size)
        segmenter = CascadedSegmenter(scene.sensor_size, config)
        first, second = list(segmenter.stream(scene.events, window_ms=30))[:2]
        cold.append(first.timings_ms)
        sizes_cold.append(len(first.labels))
        reuse.append(second.timings_ms)
        sizes_reuse.append(len(second.labels))
    print(row("synthetic, cold", cold, sizes_cold))
    print(row("synthetic, with model reuse", reuse, sizes_reuse))
    if EED.is_dir():
        sequence = load_eed_sequence(EED)
        results = list(CascadedSegmenter(sequence.sensor_size, config).stream(sequence.events, window_ms=30))
        print(
            row("eed_occlusions, streamed", [r.timings_ms for r in results], [len(r.labels) for r in results])
        )
    print("paper (i7-8700K, 1 thread):          3       110 (15)   250    363 (268)")


if __name__ == "__main__":
    main()
