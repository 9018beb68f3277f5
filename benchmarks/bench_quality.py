"""Quality of one config on four sets in one run, to compare a change before and after.

* probe: the 24 labelled scenes of ``../shared/data/synthetic_probe`` from another scene generator
  (as ``evseg evaluate labelled``): mean accuracy, IMO IoU, detection, mean |cluster-count error|,
  median ms per window, and how many objects were missed and why (held by the background, merged with
  another object, split over clusters, their own cluster's box stretched; means over the pipeline seeds);
* hard: the ``hard`` family's scenes ``--hard-seeds`` (as ``evseg evaluate synthetic --family hard``),
  the same columns;
* synthetic: the project's synthetic benchmark over ``--seeds`` (as ``evseg evaluate synthetic``),
  the same columns;
* EED ``what_is_background`` and ``occlusions`` from ``../shared/data/real`` (as ``evseg evaluate eed``,
  from the bundled ``eed.yaml``): detection rates (%) under IoU > 0.5, intersection over the GT box,
  over the predicted box, nested boxes, and the mean IoU.

``--config`` is the base of the first two sets, ``--eed-config`` of EED's; the ``--set`` overrides
apply to all. With ``--pipeline-seeds 0-2`` every set runs once per pipeline seed (the config's
``seed``) and each figure is the mean over the runs (one seed moves detection by about 0.03). A set whose
data is absent is skipped with a message.

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/bench_quality.py --pipeline-seeds 0-2 \
        [--set lambda_smooth=40 ...]
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from evseg_torch.app.cli.options import seed_range
from evseg_torch.app.threads import set_threads
from evseg_torch.config import SegmenterConfig, bundled_config, load_config, replace_config
from evseg_torch.errors import EvsegError
from evseg_torch.evaluation.eed import detection_rate, evaluate_sequence, load_eed_sequence
from evseg_torch.evaluation.labelled import evaluate_labelled
from evseg_torch.evaluation.metrics import OUTCOMES
from evseg_torch.evaluation.synthetic import evaluate_synthetic, summarize
from evseg_torch.pipeline import CascadedSegmenter

ROOT = Path(__file__).resolve().parents[1]
PROBE = ROOT.parent / "shared" / "data" / "synthetic_probe"
REAL = ROOT.parent / "shared" / "data" / "real"
EED_SEQUENCES = ("what_is_background", "occlusions", "multiple_objects_2objs_first_half")
# Column title and key of the scene sets' summaries and of EED's detection rates.
SCENE_COLUMNS = {"accuracy": "accuracy", "IoU": "iou", "detect": "detection", "|count|": "abs_count_error"}
# Why objects were missed (evseg_torch.evaluation.metrics.object_outcomes).
MISS_COLUMNS = OUTCOMES[1:]
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


def add_overrides(parser: argparse.ArgumentParser, what: str) -> None:
    """The benchmarks' ``--set KEY=VALUE`` option (repeatable; ``args.set`` is a list of pairs)."""
    parser.add_argument(
        "--set", type=override, action="append", default=[], metavar="KEY=VALUE", help=f"{what}; repeatable"
    )


def measure(args) -> dict:
    """The sets' results, means over the pipeline seeds; a set is ``None`` when its data is absent."""
    overrides = dict(args.set)
    base = replace_config(load_config(args.config) if args.config else SegmenterConfig(), **overrides)
    eed_base = replace_config(load_config(args.eed_config), **overrides)
    seeds = args.pipeline_seeds or [base.seed]
    results = {
        "overrides": overrides,
        "pipeline_seeds": seeds,
        "probe": None,
        "hard": None,
        "synthetic": None,
    }
    results["eed"] = {}
    scenes = sorted(PROBE.glob("*.npz"))
    if not scenes:
        print(f"probe: skipped, no scenes in {PROBE}")
    runs = {"probe": [], "hard": [], "synthetic": []}
    eed_runs = {name: [] for name in EED_SEQUENCES if (REAL / f"eed_{name}").is_dir()}
    for name in set(EED_SEQUENCES) - set(eed_runs):
        print(f"eed {name}: skipped, {REAL / f'eed_{name}'} not found")
    for seed in seeds:
        config, eed_config = replace_config(base, seed=seed), replace_config(eed_base, seed=seed)
        if scenes:
            runs["probe"].append(evaluate_labelled(scenes, config))
        segmenter = CascadedSegmenter((180, 240), config)
        runs["hard"].append(evaluate_synthetic(segmenter, args.hard_seeds, family="hard"))
        runs["synthetic"].append(evaluate_synthetic(segmenter, args.seeds))
        for name in eed_runs:
            sequence = load_eed_sequence(REAL / f"eed_{name}")
            eed_runs[name].append(detection_rate(evaluate_sequence(sequence, eed_config)))
    for name, scores in runs.items():
        if scores:
            summaries = [summarize(run) for run in scores]
            results[name] = {
                "summary": {key: float(np.mean([s[key] for s in summaries])) for key in summaries[0]},
                "runs": [[vars(s) for s in run] for run in scores],
            }
    for name, rates in eed_runs.items():
        results["eed"][name] = {key: float(np.mean([rate[key] for rate in rates])) for key in rates[0]}
    return results


def table(results: dict) -> str:
    """One table: a row per scene set (median ms per window last), then a row per EED sequence."""
    lines = [_row("set", "n", [*SCENE_COLUMNS, "ms"])]
    for name in ("probe", "hard", "synthetic"):
        if results[name] is not None:
            summary = results[name]["summary"]
            values = [f"{summary[key]:.3f}" for key in SCENE_COLUMNS.values()]
            lines.append(_row(name, int(summary["scenes"]), [*values, f"{summary['time_ms_median']:.0f}"]))
    lines.append(_row("missed objects", "", MISS_COLUMNS))
    for name in ("probe", "hard", "synthetic"):
        if results[name] is not None:
            summary = results[name]["summary"]
            misses = [f"{summary[f'missed_{kind}']:.1f}" for kind in MISS_COLUMNS]
            lines.append(_row(name, "", misses))
    lines.append(_row("EED detection (%)", "n", EED_COLUMNS))
    for name, row in results["eed"].items():
        lines.append(_row(name, int(row["evaluable"]), [f"{row[key]:.2f}" for key in EED_COLUMNS.values()]))
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
    add_overrides(parser, "flat config override of every set, e.g. lambda_smooth=40")
    parser.add_argument(
        "--seeds", type=seed_range, default=list(range(20)), help="synthetic scene seeds (default 0-19)"
    )
    parser.add_argument(
        "--hard-seeds", type=seed_range, default=list(range(60)), help="hard-family seeds (default 0-59)"
    )
    parser.add_argument(
        "--pipeline-seeds",
        type=seed_range,
        help="run every set once per pipeline seed, e.g. 0-2, and report the means (default: the config's)",
    )
    parser.add_argument("--threads", type=int, default=1, help="torch and OpenCV threads (default 1)")
    parser.add_argument("--json", type=Path, metavar="OUT", help="also write the results as JSON")
    args = parser.parse_args()
    set_threads(args.threads)
    start = time.perf_counter()
    try:
        results = measure(args)
    except EvsegError as err:
        print(f"bench_quality: error: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    print(table(results))
    print(
        f"{time.perf_counter() - start:.0f} s, pipeline seeds {results['pipeline_seeds']}, "
        f"overrides {results['overrides'] or 'none'}"
    )
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
