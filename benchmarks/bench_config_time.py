"""Time per window of the default config against a config before a change, side by side in one process.

Each window is segmented twice in a row, once with the default config and once with the ``--before``
overrides (by default ``objects=false``, the paper's per-motion clusters), alternating which goes
first, so that both see the same machine load. Windows: the 24 probe scenes, ``hard`` seeds
``--hard``, and the windows of EED's ``occlusions`` centred on its boxes (with the bundled
``eed.yaml``). Prints the median ms per window of each, and the median of the per-window ratios.

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/bench_config_time.py [--hard 0-19] \
        [--before data_floor_quantile=null --before data_pool_floor_quantile=0.9]
"""

import argparse
import platform
import time
from pathlib import Path

import numpy as np
import torch
from bench_quality import override  # the benchmarks' one KEY=VALUE parser (run as a script)

from evseg_torch.app.cli.options import seed_range
from evseg_torch.app.threads import set_threads
from evseg_torch.config import SegmenterConfig, bundled_config, load_config, replace_config
from evseg_torch.evaluation.eed import load_eed_sequence
from evseg_torch.evaluation.labelled import load_labelled
from evseg_torch.pipeline import CascadedSegmenter
from evseg_torch.synthetic.families import make_family_scene

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def windows(hard_seeds) -> list[tuple[str, np.ndarray, tuple[int, int], bool]]:
    """``(set, events, sensor size, EED?)`` of every window timed."""
    found = [
        ("probe", load_labelled(path)[0], (180, 240), False)
        for path in sorted((SHARED / "synthetic_probe").glob("*.npz"))
    ]
    found += [("hard", make_family_scene("hard", seed).events, (180, 240), False) for seed in hard_seeds]
    folder = SHARED / "real" / "eed_occlusions"
    if folder.is_dir():
        sequence = load_eed_sequence(folder)
        for box_time in sequence.box_times_s:
            middle = int(box_time * 1e6)
            chosen = sequence.events[np.abs(sequence.events["t"] - middle) <= 15_000]
            if len(chosen) >= 200:
                found.append(("eed occlusions", chosen, sequence.sensor_size, True))
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hard", type=seed_range, default=list(range(20)), help="hard-family seeds")
    parser.add_argument(
        "--before",
        type=override,
        action="append",
        metavar="KEY=VALUE",
        help="flat config override of the config timed against the default (repeatable; objects=false)",
    )
    args = parser.parse_args()
    before = dict(args.before or [("objects", False)])
    set_threads(1)
    configs = {"default": SegmenterConfig(), "eed": load_config(bundled_config("eed"))}
    times = {}
    for index, (name, events, size, eed) in enumerate(windows(args.hard)):
        base = configs["eed" if eed else "default"]
        segmenters = {
            "default": CascadedSegmenter(size, base),
            "before": CascadedSegmenter(size, replace_config(base, **before)),
        }
        order = list(segmenters) if index % 2 == 0 else list(segmenters)[::-1]
        for key in order:
            start = time.perf_counter()
            segmenters[key](events)
            times.setdefault(name, {}).setdefault(key, []).append(1e3 * (time.perf_counter() - start))
    print(
        f"{platform.processor() or platform.machine()}, threads {torch.get_num_threads()} (torch and OpenCV)"
    )
    print(f"before: {before}")
    print(f"{'windows':<16} {'n':>3} {'default ms':>10} {'before ms':>10} {'ratio':>6}")
    for name, pair in times.items():
        on, off = np.array(pair["default"]), np.array(pair["before"])
        ratio = np.median(on / off)
        print(f"{name:<16} {len(on):>3} {np.median(on):>10.0f} {np.median(off):>10.0f} {ratio:>6.2f}")


if __name__ == "__main__":
    main()
