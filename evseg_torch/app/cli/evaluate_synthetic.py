"""``evseg evaluate synthetic``: accuracy, IoU and detection on seeded synthetic scenes."""

from __future__ import annotations

import argparse
from pathlib import Path

from evseg_torch.app.cli.options import add_device, config_file, config_help, device, seed_range
from evseg_torch.app.cli.reports import misses_line, summary_line, write_json


def add_parser(protocols, common: argparse.ArgumentParser) -> None:
    """Add the ``synthetic`` protocol to ``protocols`` (a subparsers action), with ``common``\'s options."""
    synthetic = protocols.add_parser(
        "synthetic",
        parents=[common],
        help="accuracy, IoU and detection on synthetic scenes",
        description="Synthetic benchmark.",
    )
    synthetic.add_argument(
        "--family",
        help="score a named scene family instead of the default scenes: hard (similar motions, rotating and "
        "scaling objects, small fast objects in sparse windows, weak textures), scored as the probe scenes",
    )
    synthetic.add_argument("--seeds", type=seed_range, help="seeds (default 0-19, and 0-59 for a family)")
    synthetic.add_argument("--config", type=config_file, help=config_help())
    synthetic.add_argument(
        "--pipeline-seeds",
        type=seed_range,
        help="run the benchmark once per pipeline seed (the config's `seed`), e.g. 0-2, and average over all "
        "runs (default: the config's seed)",
    )
    synthetic.add_argument("--json", type=Path, help="also write the results as JSON")
    add_device(synthetic)
    synthetic.set_defaults(run=run)


def run(args) -> int:
    from evseg_torch.config import SegmenterConfig, load_config, replace_config
    from evseg_torch.evaluation.synthetic import evaluate_synthetic, summarize
    from evseg_torch.pipeline import CascadedSegmenter

    config = load_config(args.config) if args.config else SegmenterConfig()
    seeds = args.seeds or list(range(60 if args.family else 20))
    runs = {}
    for pipeline_seed in args.pipeline_seeds or [config.seed]:
        segmenter = CascadedSegmenter((180, 240), replace_config(config, seed=pipeline_seed))
        segmenter = segmenter.to(device(args.device))
        runs[pipeline_seed] = evaluate_synthetic(
            segmenter, seeds, family=args.family, progress=not args.quiet
        )
    kinds = "  kinds" if args.family else ""
    print(
        f"{'run':>3} {'seed':>4} {'IMOs':>4} {'events':>7} {'accuracy':>8} {'IoU':>6} {'detect':>6} "
        f"{'count':>5} {'ms':>7}{kinds}"
    )
    for pipeline_seed, scores in runs.items():
        for s in scores:
            print(
                f"{pipeline_seed:>3} {s.seed:>4} {s.n_objects:>4} {s.n_events:>7} {s.accuracy:>8.3f} "
                f"{s.iou:>6.3f} {s.detection:>6.2f} {s.count_error:>+5d} {s.time_ms:>7.0f}"
                + (f"  {s.kinds}" if kinds else "")
            )
    scores = [score for run in runs.values() for score in run]
    summary = summarize(scores)
    for row, suffix in (("mean", ""), ("p10", "_p10")):
        print(
            f"{row:>8} {'':>4} {'':>7} {summary['accuracy' + suffix]:>8.3f} {summary['iou' + suffix]:>6.3f} "
            f"{summary['detection' + suffix]:>6.2f}"
        )
    print(summary_line(summary))
    print(misses_line(summary))
    write_json(
        args.json,
        {
            "summary": summary,
            "runs": {seed: [vars(s) for s in run] for seed, run in runs.items()},
        },
    )
    return 0
