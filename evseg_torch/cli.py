"""The ``evseg`` command line: wiring over the pipeline, io, synthetic scenes and evaluation only."""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
from contextlib import nullcontext
from pathlib import Path

import numpy as np

from evseg_torch import __version__
from evseg_torch.errors import EvsegError

log = logging.getLogger("evseg")


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``evseg``; returns the exit status.

    0 ok; 1 some inputs failed (``--keep-going``); 2 our errors; 130 stopped by SIGINT (Ctrl-C), 143
    by SIGTERM (128 + the signal's number, as shells report it).
    """
    from evseg_torch.runs import Stopped, one_line, stop_on_signals, stopped_by

    parser = _parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO, format="%(message)s")
    try:
        with stop_on_signals():
            _set_threads(args.threads)
            try:
                return args.run(args) or 0
            except Exception as err:
                # A signal that lands inside an import (or other code that wraps what it catches)
                # arrives as that code's own error, caused by our Stopped.
                stop = stopped_by(err)
                if stop is None:
                    raise
                raise stop from err
    except (EvsegError, OSError) as err:
        print(f"evseg: error: {one_line(err)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as err:
        signum = err.signum if isinstance(err, Stopped) else signal.SIGINT
        resumable = " (resume with --resume)" if getattr(args, "run", None) is _segment else ""
        print(f"evseg: stopped by {signal.Signals(signum).name}{resumable}", file=sys.stderr)
        return 128 + signum


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="evseg",
        description="Event-camera motion segmentation by cascaded two-level multi-model fitting (IROS 2021).",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "--quiet", action="store_true", default=argparse.SUPPRESS, help="no progress bars or log lines"
    )
    common.add_argument(
        "--threads",
        type=int,
        default=argparse.SUPPRESS,
        help="CPU threads per process, torch's and OpenCV's (default 1: on shared CPUs more threads wait "
        "on each other)",
    )
    # Accepted before or after the command alike: the commands' parsers set them only when given there.
    parser.add_argument("--quiet", action="store_true", help="no progress bars or log lines")
    parser.add_argument("--threads", type=int, default=1, help=common._actions[1].help)
    commands = parser.add_subparsers(title="commands", required=True, metavar="COMMAND")

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
    segment.add_argument("inputs", nargs="+", metavar="INPUT", help=_inputs_help())
    segment.add_argument("--out", required=True, type=Path, help="output folder")
    segment.add_argument(
        "--config",
        type=_config_file,
        help=f"{_config_help()} (default: the built-in defaults, listed in configs/default.yaml)",
    )
    segment.add_argument(
        "--sensor-size",
        type=_sensor_size,
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
    _add_device(segment)
    segment.set_defaults(run=_segment)

    demo = commands.add_parser(
        "demo",
        parents=[common],
        help="segment a synthetic scene and draw it",
        description="Generate a synthetic scene, segment it, and write demo.png (the paper's Fig. 1 panels) "
        "and metrics.json with the metrics against ground truth.",
    )
    demo.add_argument("--out", type=Path, default=Path("demo_out"), help="output folder (default: demo_out)")
    demo.add_argument("--seed", type=int, default=1, help="scene seed")
    demo.set_defaults(run=_demo)

    simulate = commands.add_parser(
        "simulate",
        parents=[common],
        help="write synthetic scenes with ground truth",
        description="Write synthetic event scenes as .npz files (events t_us/x/y/p, per-event labels as "
        "`labels` and `label`, `ambiguous` flags, motions, sensor size): the layout of "
        "../shared/data/synthetic_probe, which `evseg evaluate labelled` scores.",
    )
    simulate.add_argument("--out", required=True, type=Path, help="output folder")
    simulate.add_argument("--seeds", type=_seed_range, default=[0], help="seeds, e.g. 0-9 or 3")
    simulate.add_argument(
        "--sensor-size", type=_sensor_size, default=(180, 240), help="HxW (default 180x240)"
    )
    simulate.add_argument("--duration-ms", type=float, default=30.0, help="scene length (default 30 ms)")
    simulate.add_argument("--objects", type=int, default=2, help="number of moving objects (default 2)")
    simulate.add_argument("--motion-model", default="affine4", help="translation, affine4 or rotation3d")
    simulate.add_argument(
        "--family",
        help="a named scene family instead (hard: known failure modes); ignores --objects and --motion-model",
    )
    simulate.set_defaults(run=_simulate)

    evaluate = commands.add_parser(
        "evaluate",
        parents=[common],
        help="evaluate against ground truth",
        description="Evaluation protocols of the paper.",
    )
    protocols = evaluate.add_subparsers(title="protocols", required=True, metavar="PROTOCOL")
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
    synthetic.add_argument("--seeds", type=_seed_range, help="seeds (default 0-19, and 0-59 for a family)")
    synthetic.add_argument("--config", type=_config_file, help=_config_help())
    synthetic.add_argument(
        "--pipeline-seeds",
        type=_seed_range,
        help="run the benchmark once per pipeline seed (the config's `seed`), e.g. 0-2, and average over all "
        "runs (default: the config's seed)",
    )
    synthetic.add_argument("--json", type=Path, help="also write the results as JSON")
    _add_device(synthetic)
    synthetic.set_defaults(run=_evaluate_synthetic)
    eed = protocols.add_parser(
        "eed",
        parents=[common],
        help="EED detection rate (paper Table I)",
        description="Detection rate on EED sequences: for each GT box, segment the window centred on its "
        "time "
        "and count the object as detected when the best non-background cluster's box has IoU > 0.5.",
    )
    eed.add_argument("folders", nargs="+", type=Path, metavar="FOLDER", help="EED sequence folders")
    eed.add_argument("--config", type=_config_file, help=f"{_config_help()} (default: eed)")
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
    _add_device(eed)
    eed.set_defaults(run=_evaluate_eed)
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
    evimo.add_argument("--config", type=_config_file, help=_config_help())
    evimo.add_argument("--window-ms", type=float, help="window length (default from the config)")
    evimo.add_argument("--json", type=Path, help="also write the results as JSON")
    _add_device(evimo)
    evimo.set_defaults(run=_evaluate_evimo)
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
    labelled.add_argument("--config", type=_config_file, help=f"{_config_help()} (not with --predictions)")
    labelled.add_argument(
        "--sensor-size", type=_sensor_size, help="HxW (default: the file's sensor_size, height and width)"
    )
    labelled.add_argument("--json", type=Path, help="also write the results as JSON")
    _add_device(labelled)
    labelled.set_defaults(run=_evaluate_labelled)
    return parser


def _segment(args) -> int:
    from evseg_torch.cluster import connect
    from evseg_torch.config import SegmenterConfig, load_config
    from evseg_torch.io import reader_for, resolve_sensor_size, scan_sensor_size
    from evseg_torch.runs import Job, failure, output_folders, segment_files, with_window

    config = load_config(args.config) if args.config else SegmenterConfig()
    _check_counts(args, "batch_size", "workers", "max_windows", "chunk_size", "events_per_window")
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
    device = _device(args.device)
    config = with_window(config, args.window_ms, args.stride_ms, args.events_per_window)
    workers_per_file = 1
    if len(args.inputs) == 1 and args.workers > 1:
        if args.batch_size < args.workers:
            log.warning(
                "evseg: --workers %d has nothing to share with --batch-size %d on one input: one process "
                "runs (pass --batch-size %d or more to share each batch's windows)",
                args.workers,
                args.batch_size,
                args.workers,
            )
        else:
            workers_per_file = args.workers
    jobs, failed = [], []
    folders = output_folders(args.inputs, args.out)
    for name, out in zip(args.inputs, folders, strict=True):
        try:
            reader_for(name)  # a file of a known format or a folder of a known layout
            path = Path(name)
            sensor_size = resolve_sensor_size(path, args.sensor_size, topic=args.topic)
            if sensor_size is None:
                sensor_size = scan_sensor_size(path, args.chunk_size, topic=args.topic)
                log.info(
                    "%s stores no sensor size: %dx%d, the smallest that holds its events (or pass "
                    "--sensor-size HxW)",
                    path.name,
                    *sensor_size,
                )
        except (EvsegError, OSError) as err:
            if not args.keep_going:
                raise
            failed.append(failure(name, err))
            continue
        jobs.append(
            Job(
                path=path,
                out=out,
                sensor_size=sensor_size,
                config=config,
                start_s=args.start,
                end_s=args.end,
                max_windows=args.max_windows,
                batch_size=args.batch_size,
                workers=workers_per_file,
                save_images=args.save_images,
                video=args.video,
                overwrite=args.overwrite,
                resume=args.resume,
                chunk_size=args.chunk_size,
                topic=args.topic,
                device=device,
            )
        )
    with connect(args.scheduler) if args.scheduler and jobs else nullcontext() as client:
        outcomes = segment_files(
            jobs, workers=args.workers, keep_going=args.keep_going, progress=not args.quiet, client=client
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


def _check_counts(args, *names: str) -> None:
    """Counts given on the command line must be positive."""
    for name in names:
        value = getattr(args, name)
        if value is not None and value < 1:
            raise EvsegError(f"--{name.replace('_', '-')} must be at least 1, got {value}")


def _add_device(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--device", default="cpu", help="torch device of level two, e.g. cpu (default), cuda, cuda:1, mps"
    )


def _device(name: str) -> str:
    """``name`` if torch has such a device here, else a one-line error."""
    import torch

    try:
        device = torch.device(name)
    except RuntimeError:
        raise EvsegError(f"--device {name}: not a torch device name (e.g. cpu, cuda, cuda:0)") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise EvsegError(f"--device {name}: this torch ({torch.__version__}) sees no CUDA device")
    if device.type == "cuda" and (device.index or 0) >= torch.cuda.device_count():
        raise EvsegError(f"--device {name}: only {torch.cuda.device_count()} CUDA devices here")
    if device.type == "mps" and not torch.backends.mps.is_available():
        raise EvsegError(f"--device {name}: no MPS device here")
    if device.type not in ("cpu", "cuda", "mps"):
        raise EvsegError(f"--device {name}: only cpu, cuda and mps are supported")
    return name


def _inputs_help() -> str:
    from evseg_torch.io.dispatch import SUPPORTED_FOLDERS, SUPPORTED_SUFFIXES

    folders = "; ".join(SUPPORTED_FOLDERS)
    return f"event files ({' '.join(SUPPORTED_SUFFIXES)}) or sequence folders ({folders})"


def _set_threads(threads: int) -> None:
    if threads < 1:
        raise EvsegError(f"--threads must be at least 1, got {threads}")
    from evseg_torch.threads import set_threads

    set_threads(threads)


def _demo(args) -> int:
    from evseg_torch.evaluation.metrics import labelling_accuracy, match_clusters, per_object_iou
    from evseg_torch.pipeline import CascadedSegmenter
    from evseg_torch.synthetic import make_scene
    from evseg_torch.viz.panels import render_fig1, write_png

    args.out.mkdir(parents=True, exist_ok=True)
    scene = make_scene(sensor_size=(180, 240), duration=0.03, n_objects=2, rng=args.seed)
    segmenter = CascadedSegmenter(sensor_size=scene.sensor_size)
    result = segmenter(scene.events)
    ious = per_object_iou(result.labels, scene.labels)
    metrics = {
        "events": len(scene.events),
        "clusters": result.n_clusters,
        "true_clusters": len(scene.motions),
        "accuracy": labelling_accuracy(result.labels, scene.labels),
        "mean_imo_iou": float(np.mean(list(ious.values()))),
        "time_ms": result.timings_ms["total"],
    }
    # Draw each true layer in the colour of the cluster matched to it, so the two panels compare at a glance.
    layer_to_id = {
        layer: int(result.object_ids[cluster])
        for cluster, layer in match_clusters(result.labels, scene.labels).items()
    }
    first_spare = int(result.object_ids.max(initial=-1)) + 1
    spare = iter(range(first_spare, first_spare + len(scene.motions)))
    colour_of = {layer: layer_to_id.get(layer, next(spare)) for layer in range(len(scene.motions))}
    shown = np.array([colour_of.get(int(v), -1) for v in range(-1, len(scene.motions))])[scene.labels + 1]
    shown_metrics = {
        "clusters": f"{result.n_clusters} (true {len(scene.motions)})",
        "accuracy": metrics["accuracy"],
        "mean IMO IoU": metrics["mean_imo_iou"],
        "time": f"{metrics['time_ms']:.0f} ms",
    }
    image = render_fig1(
        result,
        title=f"evseg demo: synthetic scene, seed {args.seed}",
        metrics=shown_metrics,
        ground_truth=shown,
        ids=result.object_ids,
    )
    path = write_png(image, args.out / "demo.png")
    (args.out / "metrics.json").write_text(json.dumps({**metrics, "timings_ms": result.timings_ms}, indent=2))
    log.info("wrote %s", path)
    for key, value in metrics.items():
        log.info("%-13s %s", key, f"{value:.3f}" if isinstance(value, float) else value)
    return 0


def _simulate(args) -> int:
    from evseg_torch.synthetic import make_scene
    from evseg_torch.synthetic.families import make_family_scene

    args.out.mkdir(parents=True, exist_ok=True)
    for seed in args.seeds:
        if args.family:
            scene = make_family_scene(args.family, seed, args.sensor_size, args.duration_ms / 1000)
        else:
            scene = make_scene(
                sensor_size=args.sensor_size,
                duration=args.duration_ms / 1000,
                n_objects=args.objects,
                motion_model=args.motion_model,
                rng=seed,
            )
        path = args.out / f"scene_{seed:04d}.npz"
        np.savez_compressed(
            path,
            t_us=scene.events["t"],
            x=scene.events["x"],
            y=scene.events["y"],
            p=scene.events["p"],
            labels=scene.labels,
            label=scene.labels,
            ambiguous=scene.ambiguous,
            height=scene.sensor_size[0],
            width=scene.sensor_size[1],
            sensor_size=np.array(scene.sensor_size, dtype=np.int32),
            motion_models=np.array([m.model.name for m in scene.motions]),
            motion_params=np.array([np.pad(m.params, (0, 4 - len(m.params))) for m in scene.motions]),
        )
        log.info("wrote %s (%d events)", path, len(scene.events))
    return 0


def _evaluate_synthetic(args) -> int:
    from evseg_torch.config import SegmenterConfig, load_config, replace_config
    from evseg_torch.evaluation.synthetic import evaluate_synthetic, summarize
    from evseg_torch.pipeline import CascadedSegmenter

    config = load_config(args.config) if args.config else SegmenterConfig()
    seeds = args.seeds or list(range(60 if args.family else 20))
    runs = {}
    for pipeline_seed in args.pipeline_seeds or [config.seed]:
        segmenter = CascadedSegmenter((180, 240), replace_config(config, seed=pipeline_seed))
        segmenter = segmenter.to(_device(args.device))
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
    print(_summary_line(summary))
    print(_misses_line(summary))
    _write_json(
        args.json,
        {
            "summary": summary,
            "runs": {seed: [vars(s) for s in run] for seed, run in runs.items()},
        },
    )
    return 0


def _evaluate_eed(args) -> int:
    from evseg_torch.config import bundled_config, load_config
    from evseg_torch.evaluation.eed import PAPER_TABLE_I, detection_rate, evaluate_sequence, load_eed_sequence
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
            device=_device(args.device),
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
    _write_json(args.json, rows)
    return 0


def _evaluate_evimo(args) -> int:
    from evseg_torch.config import SegmenterConfig, load_config
    from evseg_torch.evaluation.evimo import evaluate_evimo, summarize_evimo
    from evseg_torch.io import load_evimo, load_evimo2
    from evseg_torch.pipeline import CascadedSegmenter

    config = load_config(args.config) if args.config else SegmenterConfig()
    load = load_evimo2 if args.path.is_dir() else load_evimo
    sequence = load(args.path, trusted=args.trusted)
    segmenter = CascadedSegmenter(sequence.sensor_size, config).to(_device(args.device))
    results = evaluate_evimo(
        segmenter, sequence, window_ms=args.window_ms or config.window.window_ms, progress=not args.quiet
    )
    summary = summarize_evimo(results)
    for key, value in summary.items():
        print(f"{key:<28} {value}")
    _write_json(args.json, summary)
    return 0


def _evaluate_labelled(args) -> int:
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
            device=_device(args.device),
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
    line = _summary_line(summary)
    # Predictions carry no time, so their summary ends before the (NaN) median time.
    print(line if args.predictions is None else line.rsplit(", median", 1)[0])
    print(_misses_line(summary))
    dynamic = summarize_dynamic(scores)
    print("dynamic class: " + ", ".join(f"{name} {value:.3f}" for name, value in dynamic.items()))
    summary |= dynamic
    _write_json(args.json, {"method": method, "summary": summary, "files": [vars(s) for s in scores]})
    return 0


def _summary_line(summary: dict) -> str:
    """The ``mean:`` line of a scene benchmark, from :func:`~evseg_torch.evaluation.synthetic.summarize`."""
    return (
        f"mean: accuracy {summary['accuracy']:.3f}, IMO IoU {summary['iou']:.3f}, "
        f"detection {summary['detection']:.3f}, "
        f"cluster-count error {summary['count_error']:+.2f} (|.| {summary['abs_count_error']:.2f}), "
        f"median {summary['time_ms_median']:.0f} ms per window"
    )


def _misses_line(summary: dict) -> str:
    """How many objects were missed, and why (:func:`~evseg_torch.evaluation.metrics.object_outcomes`)."""
    from evseg_torch.evaluation.metrics import OUTCOMES

    misses = {outcome: int(summary[f"missed_{outcome}"]) for outcome in OUTCOMES[1:]}
    reasons = ", ".join(f"{count} {reason}" for reason, count in misses.items() if count)
    return f"missed objects: {sum(misses.values())}" + (f" ({reasons})" if reasons else "")


def _write_json(path: Path | None, data) -> None:
    if path is not None:
        path.write_text(json.dumps(data, indent=2, default=_json_default))
        log.info("wrote %s", path)


def _json_default(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"cannot write {type(value).__name__} as JSON")


def _config_help() -> str:
    from evseg_torch.config import shipped_configs

    return f"YAML config, or a bundled config's name: {', '.join(shipped_configs())}"


def _config_file(text: str) -> Path:
    """A ``--config`` value: a YAML file, or where no file has that name, a bundled config
    (:func:`~evseg_torch.config.bundled_config`), so that ``--config fast`` works wherever the package is
    installed. A name that is neither stays a path, which ``load_config`` reports as missing."""
    path = Path(text)
    from evseg_torch.config import bundled_config, shipped_configs

    if path.exists() or text.removesuffix(".yaml") not in shipped_configs():
        return path
    return bundled_config(text)


def _sensor_size(text: str) -> tuple[int, int]:
    try:
        height, width = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"sensor size must be HxW, e.g. 180x240, got {text!r}") from None
    if height <= 0 or width <= 0:
        raise argparse.ArgumentTypeError(f"sensor size must be positive, got {text!r}")
    return height, width


def _seed_range(text: str) -> list[int]:
    try:
        if "-" in text:
            first, last = (int(v) for v in text.split("-"))
            return list(range(first, last + 1))
        return [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"seeds must look like 0-19 or 1,2,5, got {text!r}") from None


if __name__ == "__main__":
    sys.exit(main())
