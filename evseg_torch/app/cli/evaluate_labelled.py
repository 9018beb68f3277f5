"""``evseg evaluate labelled``: files with per-event labels, segmented here, or another method's
predictions on them."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from evseg_torch.app.cli.options import add_device, config_file, config_help, device, sensor_size
from evseg_torch.app.cli.reports import misses_line, summary_line, write_json
from evseg_torch.errors import EvsegError


def add_parser(protocols, common: argparse.ArgumentParser) -> None:
    """Add the ``labelled`` protocol to ``protocols`` (a subparsers action), with ``common``\'s options."""
    labelled = protocols.add_parser(
        "labelled",
        parents=[common],
        help="accuracy, IoU and detection on files with per-event labels",
        description="Segment each labelled .npz FILE as one window and score it against its per-event "
        "labels (0 background, 1..K moving objects, -1 noise), e.g. ../shared/data/synthetic_probe/*.npz. "
        "Noise and ignored events are left out of every metric. With --predictions, score another "
        "method's output on the FILEs instead, with the same metrics.",
    )
    labelled.add_argument("files", nargs="+", type=Path, metavar="FILE", help="labelled .npz event files")
    labelled.add_argument(
        "--predictions",
        nargs="+",
        type=Path,
        metavar="PRED",
        help="score these instead of segmenting (give them after the FILEs): one per FILE, in order, or one "
        "folder holding <FILE stem>.npz or .npy for each. A PRED is per-event integer labels (.npy (N,), "
        "or the --prediction-field of an .npz; negative = no cluster) or an .npz of per-pixel layer ids "
        "'masks' (T, H, W) with 'mask_times' in seconds (or 'mask_times_us'), events' time base: each "
        "event takes its pixel's id in the mask nearest in time (midway: the earlier)",
    )
    labelled.add_argument(
        "--prediction-field", default="labels", help="per-event labels in a PRED .npz (default: labels)"
    )
    labelled.add_argument(
        "--method",
        help="the method's name in the table and JSON (default: evseg; with --predictions, the name of the "
        "PRED folder or of the folder holding the PREDs, or a lone PRED file's stem)",
    )
    labelled.add_argument("--label-field", default="label", help="per-event label array (default: label)")
    labelled.add_argument(
        "--ignore-field",
        default="ambiguous",
        help="per-event mask of events to leave out (default: ambiguous); a file without the field ignores "
        "none, so e.g. `--ignore-field none` scores every event but noise",
    )
    labelled.add_argument("--config", type=config_file, help=f"{config_help()} (not with --predictions)")
    labelled.add_argument(
        "--sensor-size", type=sensor_size, help="HxW (default: the file's sensor_size, height and width)"
    )
    labelled.add_argument("--json", type=Path, help="also write the results as JSON")
    add_device(labelled)
    labelled.set_defaults(run=run)


def run(args) -> int:
    from evseg_torch.config import SegmenterConfig, load_config
    from evseg_torch.evaluation.labelled import evaluate_labelled, summarize_dynamic
    from evseg_torch.evaluation.predictions import evaluate_predictions
    from evseg_torch.evaluation.synthetic import summarize

    fields = {
        "sensor_size": args.sensor_size,
        "label_field": args.label_field,
        "ignore_field": args.ignore_field,
    }
    if args.predictions is not None:
        if args.config is not None:
            raise EvsegError("--config has no effect with --predictions: the FILEs are not segmented")
        scores = evaluate_predictions(
            args.files, args.predictions, method=args.method, prediction_field=args.prediction_field, **fields
        )
    else:
        config = load_config(args.config) if args.config else SegmenterConfig()
        scores = evaluate_labelled(
            args.files,
            config,
            method=args.method or "evseg",
            progress=not args.quiet,
            device=device(args.device),
            **fields,
        )
    method = scores[0].method
    width = max(len(method), 6)

    def row(name, who, events, objects, accuracy, iou, detection, count, ms) -> str:
        return (
            f"{name:<20} {who:<{width}} {events:>7} {objects:>4} {accuracy:>8} {iou:>6} {detection:>6} "
            f"{count:>5} {ms:>7}"
        )

    def milliseconds(value: float) -> str:
        # Another method's predictions come without a time.
        return "-" if np.isnan(value) else f"{value:.0f}"

    print(row("file", "method", "events", "IMOs", "accuracy", "IoU", "detect", "count", "ms"))
    for s in scores:
        print(
            row(
                s.name,
                s.method,
                s.n_events,
                s.n_objects,
                f"{s.accuracy:.3f}",
                f"{s.iou:.3f}",
                f"{s.detection:.2f}",
                f"{s.count_error:+d}",
                milliseconds(s.time_ms),
            )
        )
    summary = summarize(scores)
    print(
        row(
            "mean",
            method,
            f"{np.mean([s.n_events for s in scores]):.0f}",
            f"{np.mean([s.n_objects for s in scores]):.1f}",
            f"{summary['accuracy']:.3f}",
            f"{summary['iou']:.3f}",
            f"{summary['detection']:.2f}",
            f"{summary['count_error']:+.2f}",
            milliseconds(np.mean([s.time_ms for s in scores])),
        )
    )
    line = summary_line(summary)
    # Predictions carry no time, so their summary ends before the (NaN) median time.
    print(line if args.predictions is None else line.rsplit(", median", 1)[0])
    print(misses_line(summary))
    dynamic = summarize_dynamic(scores)
    print("dynamic class: " + ", ".join(f"{name} {value:.3f}" for name, value in dynamic.items()))
    summary |= dynamic
    write_json(args.json, {"method": method, "summary": summary, "files": [vars(s) for s in scores]})
    return 0
