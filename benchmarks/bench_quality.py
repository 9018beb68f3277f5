"""Quality of one config on three sets in one run, to compare a change before and after.

* probe: the 24 labelled scenes of ``../shared/data/synthetic_probe`` from another scene generator
  (as ``evseg evaluate labelled``): mean accuracy, IMO IoU, detection, mean |cluster-count error|,
  median ms per window;
* synthetic: the project's synthetic benchmark over ``--seeds`` (as ``evseg evaluate synthetic``),
  the same columns;
* EED ``what_is_background`` and ``occlusions`` from ``../shared/data/real`` (as ``evseg evaluate eed``,
  from the bundled ``eed.yaml``): detection rates (%) under IoU > 0.5, intersection over the GT box,
  over the predicted box, nested boxes, and the mean IoU.

``--config`` is the base of the first two sets, ``--eed-config`` of EED's; the ``--set`` overrides
apply to all three. A set whose data is absent is skipped with a message.

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/bench_quality.py [--set lambda_smooth=40 ...]
"""

import argparse
import json
import sys
import time
from pathlib import Path

import torch
import yaml

from evseg_torch.cli import _seed_range
from evseg_torch.config import SegmenterConfig, bundled_config, load_config, replace_config
from evseg_torch.errors import EvsegError
from evseg_torch.evaluation.eed import detection_rate, evaluate_sequence, load_eed_sequence
from evseg_torch.evaluation.labelled import evaluate_labelled
from evseg_torch.evaluation.synthetic import evaluate_synthetic, summarize
from evseg_torch.pipeline import CascadedSegmenter

ROOT = Path(__file__).resolve().parents[1]
PROBE = ROOT.parent / "shared" / "data" / "synthetic_probe"
REAL = ROOT.parent / "shared" / "data" / "real"
EED_SEQUENCES = ("what_is_background", "occlusions")
# Column title and key of the scene sets' summaries and of EED's detection rates.
SCENE_COLUMNS = {"accuracy": "accuracy", "IoU": "iou", "detect": "detection", "|count|": "abs_count_error"}
EED_COLUMNS = {
    "IoU>0.5": "detection_rate",
    "I/GT": "detection_rate_overlap",
    "I/pred": "detection_rate_over_predicted",
    "nested": "detection_rate_nested",
    "mean IoU": "mean_iou",
}


def override(text: str) -> tuple[str, object]:
    """``key=value`` with the value read as YAML (``40``, ``null``, ``[1, 2]``...)."""
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"overrides must look like key=value, got {text!r}")
    return key, yaml.safe_load(value)


def measure(args) -> dict:
    """The three sets' results, each ``None`` when its data is absent."""
    overrides = dict(args.set)
    config = replace_config(load_config(args.config) if args.config else SegmenterConfig(), **overrides)
    eed_config = replace_config(load_config(args.eed_config), **overrides)
    results = {"overrides": overrides, "probe": None, "synthetic": None, "eed": {}}
    scenes = sorted(PROBE.glob("*.npz"))
    if scenes:
        scores = evaluate_labelled(scenes, config)
        results["probe"] = {"summary": summarize(scores), "files": [vars(s) for s in scores]}
    else:
        print(f"probe: skipped, no scenes in {PROBE}")
    scores = evaluate_synthetic(CascadedSegmenter((180, 240), config), args.seeds)
    results["synthetic"] = {"summary": summarize(scores), "scenes": [vars(s) for s in scores]}
    for name in EED_SEQUENCES:
        folder = REAL / f"eed_{name}"
        if folder.is_dir():
            results["eed"][name] = detection_rate(evaluate_sequence(load_eed_sequence(folder), eed_config))
        else:
            print(f"eed {name}: skipped, {folder} not found")
    return results


def table(results: dict) -> str:
    """One table: a row per scene set (median ms per window last), then a row per EED sequence."""
    lines = [_row("set", "n", [*SCENE_COLUMNS, "ms"])]
    for name in ("probe", "synthetic"):
        if results[name] is not None:
            summary = results[name]["summary"]
            values = [f"{summary[key]:.3f}" for key in SCENE_COLUMNS.values()]
            lines.append(_row(name, summary["scenes"], [*values, f"{summary['time_ms_median']:.0f}"]))
    lines.append(_row("EED detection (%)", "n", EED_COLUMNS))
    for name, row in results["eed"].items():
        lines.append(_row(name, row["evaluable"], [f"{row[key]:.2f}" for key in EED_COLUMNS.values()]))
    return "\n".join(lines)


def _row(name, n, cells) -> str:
    return f"{name:<20} {n:>3} " + " ".join(f"{cell:>8}" for cell in cells)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, help="YAML config of the probe and synthetic sets")
    parser.add_argument(
        "--eed-config",
        type=Path,
        default=bundled_config("eed"),
        help="YAML config of the EED set (default: the bundled eed.yaml)",
    )
    parser.add_argument(
        "--set",
        type=override,
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="flat config override of every set, e.g. lambda_smooth=40; repeatable",
    )
    parser.add_argument(
        "--seeds", type=_seed_range, default=list(range(20)), help="synthetic scene seeds (default 0-19)"
    )
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--json", type=Path, metavar="OUT", help="also write the results as JSON")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    start = time.perf_counter()
    try:
        results = measure(args)
    except EvsegError as err:
        print(f"bench_quality: error: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    print(table(results))
    print(f"{time.perf_counter() - start:.0f} s, overrides {results['overrides'] or 'none'}")
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
