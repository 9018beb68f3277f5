"""``evseg evaluate eed``: the EED detection rate (the paper's Table I)."""

from __future__ import annotations

import argparse
from pathlib import Path

from evseg_torch.app.cli.options import add_device, config_file, config_help, device
from evseg_torch.app.cli.reports import write_json


def add_parser(protocols, common: argparse.ArgumentParser) -> None:
    """Add the ``eed`` protocol to ``protocols`` (a subparsers action), with ``common``\'s options."""
    eed = protocols.add_parser(
        "eed",
        parents=[common],
        help="EED detection rate (paper Table I)",
        description="Detection rate on EED sequences: for each GT box, segment the window centred on its "
        "time "
        "and count the object as detected when the best non-background cluster's box has IoU > 0.5.",
    )
    eed.add_argument("folders", nargs="+", type=Path, metavar="FOLDER", help="EED sequence folders")
    eed.add_argument("--config", type=config_file, help=f"{config_help()} (default: eed)")
    eed.add_argument(
        "--window-ms", type=float, help="window length centred on each box (default from the config)"
    )
    eed.add_argument(
        "--reference",
        choices=["box", "window-start"],
        default="box",
        help="time the clusters are compensated to: the box time (default) or the window's first event, "
        "EMSGC's and the paper's convention",
    )
    eed.add_argument("--json", type=Path, help="also write the results as JSON")
    eed.add_argument(
        "--figures",
        type=Path,
        metavar="DIR",
        help="write DIR/<sequence>.png: each window's compensated clusters with the GT box (red) and the "
        "matched cluster's box (dashed)",
    )
    add_device(eed)
    eed.set_defaults(run=run)


def run(args) -> int:
    from evseg_torch.config import bundled_config, load_config
    from evseg_torch.evaluation.eed import (
        BOX_OUTCOMES,
        PAPER_TABLE_I,
        detection_rate,
        evaluate_sequence,
        load_eed_sequence,
    )
    from evseg_torch.viz.figures import boxes_figure, save_figure
    from evseg_torch.viz.render import render_labels

    config = load_config(args.config or bundled_config("eed"))
    window_ms = args.window_ms or config.window.window_ms
    reference = args.reference.replace("-", "_")
    compensated = "the box time" if reference == "box" else "the window's first event"
    rows = {}
    for folder in args.folders:
        sequence = load_eed_sequence(folder)
        panels = []

        def draw(result, segmentation, panels=panels):
            panels.append(
                {
                    "image": render_labels(
                        segmentation.warped_xy, segmentation.labels, segmentation.sensor_size
                    ),
                    "gt_box": result.gt_box,
                    "predicted_box": result.predicted_box,
                    "title": f"box {len(panels)}: IoU {result.iou:.2f}",
                }
            )

        results = evaluate_sequence(
            sequence,
            config,
            window_ms=window_ms,
            reference=reference,
            progress=not args.quiet,
            on_window=draw if args.figures else None,
            device=device(args.device),
        )
        rows[sequence.name] = {
            **detection_rate(results),
            "reference": reference,
            "paper": PAPER_TABLE_I.get(sequence.name, {}),
        }
        if panels:
            args.figures.mkdir(parents=True, exist_ok=True)
            title = f"EED {sequence.name}: {window_ms:g} ms windows centred on the GT boxes, at {compensated}"
            save_figure(boxes_figure(panels, title), args.figures / f"{sequence.name}.png")
    print(
        f"EED detection rate (%), IoU > 0.5 (I/GT, I/pred: intersection over the GT or the predicted box's "
        f"area > 0.5; nested: over the smaller box's area > 0.5 with the areas within 4x), windows of "
        f"{window_ms:g} ms centred on each box, clusters compensated to {compensated}"
    )
    print(
        f"{'sequence':<20} {'boxes':>5} {'ours':>7} {'I/GT':>7} {'I/pred':>7} {'nested':>7} {'IoU':>5} | "
        f"{'EED':>6} {'EMSMC':>6} {'EMSGC':>6} {'IROS21':>6}"
    )
    for name, row in rows.items():
        paper = row["paper"]
        print(
            f"{name:<20} {row['evaluable']:>5} {row['detection_rate']:>7.2f} "
            f"{row.get('detection_rate_overlap', 0):>7.2f} "
            f"{row.get('detection_rate_over_predicted', 0):>7.2f} "
            f"{row.get('detection_rate_nested', 0):>7.2f} "
            f"{row.get('mean_iou', 0):>5.2f} | "
            + " ".join(f"{paper.get(k, float('nan')):>6.2f}" for k in ("EED", "EMSMC", "EMSGC", "IROS 2021"))
        )
    print("missed boxes (nested reading) by reason, and level one's tracks on the boxes:")
    print(
        f"{'sequence':<20} {'boxes':>5} "
        + " ".join(f"{outcome:>10}" for outcome in BOX_OUTCOMES[1:])
        + f" {'tracks':>7} {'own model':>9}"
    )
    for name, row in rows.items():
        if row["evaluable"]:
            print(
                f"{name:<20} {row['evaluable']:>5} "
                + " ".join(f"{row[f'missed_{outcome}']:>10}" for outcome in BOX_OUTCOMES[1:])
                + f" {row['boxes_with_tracks']:>7} {row['boxes_with_own_model']:>9}"
            )
    write_json(args.json, rows)
    return 0
