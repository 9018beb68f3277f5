"""``evseg segment``: recordings segmented window by window into result folders."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

from evseg_torch.app.cli.options import (
    add_device,
    check_counts,
    config_file,
    config_help,
    device,
    inputs_help,
    sensor_size,
)
from evseg_torch.errors import EvsegError

log = logging.getLogger("evseg")


def add_parser(commands, common: argparse.ArgumentParser) -> None:
    """Add ``segment`` to ``commands`` (a subparsers action), with the shared options of ``common``."""
    segment = commands.add_parser(
        "segment",
        parents=[common],
        help="segment recordings window by window",
        description="Segment each INPUT window by window into OUT/<name>/: labels.npz, models.jsonl, "
        "summary.json and config.yaml (one figure per window in images/ with --save-images, video.mp4 with "
        "--video); see the "
        "README's Output section. <name> is the input's stem; inputs whose stems collide are named by their "
        "parent folders too (a/x/events.txt and b/y/events.txt give x-events and y-events). Results are "
        "written into OUT/<name>/.partial/ with a checkpoint after every batch of windows and appear only "
        "when complete; a stopped run (Ctrl-C, SIGTERM, a crash) continues with --resume.",
    )
    segment.add_argument("inputs", nargs="+", metavar="INPUT", help=inputs_help())
    segment.add_argument("--out", required=True, type=Path, help="output folder")
    segment.add_argument(
        "--config",
        type=config_file,
        help=f"{config_help()} (default: the built-in defaults, listed in configs/default.yaml)",
    )
    segment.add_argument(
        "--sensor-size",
        type=sensor_size,
        help="HxW, e.g. 180x240, for files that store none (a file's stored size wins: a different size "
        "given here is an error); with neither, the smallest size that holds the events (one extra pass)",
    )
    size = segment.add_mutually_exclusive_group()
    size.add_argument("--window-ms", type=float, help="window length in ms (default from the config)")
    size.add_argument("--events-per-window", type=int, help="windows of this many events instead")
    segment.add_argument(
        "--stride-ms", type=float, help="step between time windows in ms (default: window length)"
    )
    segment.add_argument(
        "--start", type=float, metavar="S", help="segment from S seconds after the recording's first event"
    )
    segment.add_argument(
        "--end", type=float, metavar="S", help="segment up to S seconds after the recording's first event"
    )
    segment.add_argument(
        "--max-windows", type=int, metavar="N", help="segment at most the first N windows (of the range)"
    )
    segment.add_argument("--save-images", action="store_true", help="write one figure per window")
    segment.add_argument(
        "--video",
        action="store_true",
        help="write video.mp4 beside the results: one frame per window, its events coloured by cluster, raw "
        "and compensated (needs the video extra)",
    )
    segment.add_argument(
        "--workers",
        type=int,
        default=1,
        help="processes, one core each: several inputs are shared out among them file by file; one input's "
        "windows are shared out batch by batch, so with one input --workers needs --batch-size of at least "
        "as many (otherwise one process runs). The results do not change with --workers",
    )
    segment.add_argument("--topic", help="ROS bags: the topic of event arrays (default: the first by name)")
    segment.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="segment each input as one task on a Dask cluster: a scheduler's address (tcp://host:8786) or "
        "local:N for N single-threaded worker processes here (needs the dask extra; paths must be the same "
        "on every worker). Results equal a run here",
    )
    segment.add_argument(
        "--batch-size",
        type=int,
        default=1,
        help="windows segmented together by one batched level two (default 1); each window of a batch "
        "starts from the models of the previous batch's last window, so the batch size changes results",
    )
    again = segment.add_mutually_exclusive_group()
    again.add_argument("--overwrite", action="store_true", help="replace this run's inputs' existing results")
    again.add_argument(
        "--resume",
        action="store_true",
        help="continue stopped runs from their last checkpoint (same inputs, config and options) and skip "
        "finished ones; the results equal an uninterrupted run's",
    )
    segment.add_argument(
        "--keep-going",
        action="store_true",
        help="report an input that fails (one line) and segment the others; exit status 1 if any failed",
    )
    segment.add_argument("--chunk-size", type=int, default=1_000_000, help="events read at a time")
    add_device(segment)
    segment.set_defaults(run=run)


def run(args) -> int:
    from evseg_torch.app.cluster import connect, segment_on_cluster
    from evseg_torch.app.jobs import plan_jobs, with_window
    from evseg_torch.app.runs import segment_files
    from evseg_torch.config import SegmenterConfig, load_config

    config = load_config(args.config) if args.config else SegmenterConfig()
    check_counts(args, "batch_size", "workers", "max_windows", "chunk_size", "events_per_window")
    if args.events_per_window is not None and args.stride_ms is not None:
        raise EvsegError("--stride-ms applies to time windows, not to --events-per-window")
    for name in ("start", "end"):
        value = getattr(args, name)
        if value is not None and not (np.isfinite(value) and value >= 0):
            raise EvsegError(f"--{name} must be a number of seconds of at least 0, got {value:g}")
    if args.start is not None and args.end is not None and args.end <= args.start:
        raise EvsegError(f"--end ({args.end:g} s) must come after --start ({args.start:g} s)")
    if args.scheduler is not None and args.workers > 1:
        raise EvsegError(
            "--workers applies without --scheduler (with it, the cluster's workers share out inputs)"
        )
    torch_device = device(args.device)
    config = with_window(config, args.window_ms, args.stride_ms, args.events_per_window)
    jobs, failed = plan_jobs(
        args.inputs,
        args.out,
        config,
        sensor_size=args.sensor_size,
        topic=args.topic,
        chunk_size=args.chunk_size,
        workers=args.workers,
        keep_going=args.keep_going,
        start_s=args.start,
        end_s=args.end,
        max_windows=args.max_windows,
        batch_size=args.batch_size,
        save_images=args.save_images,
        video=args.video,
        overwrite=args.overwrite,
        resume=args.resume,
        device=torch_device,
    )
    if args.scheduler and jobs:
        with connect(args.scheduler) as client:
            outcomes = segment_on_cluster(client, jobs, keep_going=args.keep_going, progress=not args.quiet)
    else:
        outcomes = segment_files(
            jobs, workers=args.workers, keep_going=args.keep_going, progress=not args.quiet
        )
    for job, summary, error in outcomes:
        if error is not None:
            failed.append(error)
            continue
        log.info(
            "%s: %d events, %d windows, %.0f events/s -> %s",
            job.path.name,
            summary["events"],
            summary["windows"],
            summary["events_per_s"] or 0,
            job.out,
        )
    if failed:
        print(f"evseg: {len(failed)} of {len(args.inputs)} inputs failed:", file=sys.stderr)
        for line in failed:
            print(f"  {line}", file=sys.stderr)
        return 1
    return 0
