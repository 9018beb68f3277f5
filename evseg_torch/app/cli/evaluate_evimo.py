"""``evseg evaluate evimo``: the EV-IMO IoU protocol."""

from __future__ import annotations

import argparse
from pathlib import Path

from evseg_torch.app.cli.options import add_device, config_file, config_help, device
from evseg_torch.app.cli.reports import write_json


def add_parser(protocols, common: argparse.ArgumentParser) -> None:
    """Add the ``evimo`` protocol to ``protocols`` (a subparsers action), with ``common``\'s options."""
    evimo = protocols.add_parser(
        "evimo",
        parents=[common],
        help="EV-IMO IoU (convex-hull, event-wise, and learned maskers' mIoU, pIoU, SR@0.5, event IoU)",
        description="EV-IMO protocol: windows at the mask timestamps; reports the convex-hull mask IoU "
        "(IROS/EMSGC definition), the event-wise IoU (MOMS/0-MMS/SpikeMS definition), the learned maskers' "
        "mIoU, pIoU and SR@0.5 (event_suppression) and the event-level IoU (EVIMO2).",
    )
    evimo.add_argument(
        "path", type=Path, metavar="PATH", help="EV-IMO 1 .npz sequence, or an EVIMO2v2 sequence folder"
    )
    evimo.add_argument(
        "--trusted", action="store_true", help="allow unpickling the file's meta (mask timestamps)"
    )
    evimo.add_argument("--config", type=config_file, help=config_help())
    evimo.add_argument("--window-ms", type=float, help="window length (default from the config)")
    evimo.add_argument("--json", type=Path, help="also write the results as JSON")
    add_device(evimo)
    evimo.set_defaults(run=run)


def run(args) -> int:
    from evseg_torch.config import SegmenterConfig, load_config
    from evseg_torch.evaluation.evimo import evaluate_evimo, summarize_evimo
    from evseg_torch.io import load_evimo, load_evimo2
    from evseg_torch.pipeline import CascadedSegmenter

    config = load_config(args.config) if args.config else SegmenterConfig()
    load = load_evimo2 if args.path.is_dir() else load_evimo
    sequence = load(args.path, trusted=args.trusted)
    segmenter = CascadedSegmenter(sequence.sensor_size, config).to(device(args.device))
    results = evaluate_evimo(
        segmenter, sequence, window_ms=args.window_ms or config.window.window_ms, progress=not args.quiet
    )
    summary = summarize_evimo(results)
    for key, value in summary.items():
        print(f"{key:<28} {value}")
    write_json(args.json, summary)
    return 0
