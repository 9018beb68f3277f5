"""The ``evseg`` command line: wiring over the pipeline, io, synthetic scenes and evaluation only."""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from evseg_torch.errors import EvsegError

log = logging.getLogger("evseg")


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``evseg``; returns the exit status (0 ok, 2 for our errors)."""
    parser = _parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO, format="%(message)s")
    try:
        return args.run(args) or 0
    except (EvsegError, OSError) as err:
        print(f"evseg: error: {_one_line(err)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("evseg: interrupted", file=sys.stderr)
        return 130


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="evseg",
        description="Event-camera motion segmentation by cascaded two-level multi-model fitting (IROS 2021).",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bars or log lines")
    commands = parser.add_subparsers(title="commands", required=True, metavar="COMMAND")

    segment = commands.add_parser(
        "segment",
        help="segment recordings window by window",
        description="Segment each INPUT window by window; writes labels.npz, models.jsonl, summary.json and "
        "config.yaml (and Fig. 1 PNGs with --save-images) into OUT/<input name>/.",
    )
    segment.add_argument(
        "inputs", nargs="+", metavar="INPUT", help="event files (.txt .npy .npz .h5 .aedat4 ...)"
    )
    segment.add_argument("--out", required=True, type=Path, help="output folder")
    segment.add_argument(
        "--config", type=Path, help="YAML config (default: built-in defaults = configs/default.yaml)"
    )
    segment.add_argument(
        "--sensor-size", type=_sensor_size, help="HxW, e.g. 180x240 (default: from the file)"
    )
    size = segment.add_mutually_exclusive_group()
    size.add_argument("--window-ms", type=float, help="window length in ms (default from the config)")
    size.add_argument("--events-per-window", type=int, help="windows of this many events instead")
    segment.add_argument(
        "--stride-ms", type=float, help="step between windows in ms (default: window length)"
    )
    segment.add_argument("--save-images", action="store_true", help="write one Fig. 1 PNG per window")
    segment.add_argument("--workers", type=int, default=1, help="process this many files in parallel")
    segment.add_argument("--overwrite", action="store_true", help="replace existing output")
    segment.add_argument("--chunk-size", type=int, default=1_000_000, help="events read at a time")
    segment.set_defaults(run=_segment)

    demo = commands.add_parser(
        "demo",
        help="segment a synthetic scene and draw it",
        description="Generate a synthetic scene, segment it, and write demo.png (the paper's Fig. 1 panels) "
        "and metrics.json with the metrics against ground truth.",
    )
    demo.add_argument("--out", type=Path, default=Path("demo_out"), help="output folder (default: demo_out)")
    demo.add_argument("--seed", type=int, default=1, help="scene seed")
    demo.set_defaults(run=_demo)

    simulate = commands.add_parser(
        "simulate",
        help="write synthetic scenes with ground truth",
        description="Write synthetic event scenes as .npz files "
        "(events t_us/x/y/p, labels, motions, sensor size).",
    )
    simulate.add_argument("--out", required=True, type=Path, help="output folder")
    simulate.add_argument("--seeds", type=_seed_range, default=[0], help="seeds, e.g. 0-9 or 3")
    simulate.add_argument(
        "--sensor-size", type=_sensor_size, default=(180, 240), help="HxW (default 180x240)"
    )
    simulate.add_argument("--duration-ms", type=float, default=30.0, help="scene length (default 30 ms)")
    simulate.add_argument("--objects", type=int, default=2, help="number of moving objects (default 2)")
    simulate.add_argument("--motion-model", default="affine4", help="translation, affine4 or rotation3d")
    simulate.set_defaults(run=_simulate)

    evaluate = commands.add_parser(
        "evaluate", help="evaluate against ground truth", description="Evaluation protocols of the paper."
    )
    protocols = evaluate.add_subparsers(title="protocols", required=True, metavar="PROTOCOL")
    synthetic = protocols.add_parser(
        "synthetic",
        help="accuracy, IoU and detection on synthetic scenes",
        description="Synthetic benchmark.",
    )
    synthetic.add_argument("--seeds", type=_seed_range, default=list(range(20)), help="seeds (default 0-19)")
    synthetic.add_argument("--config", type=Path, help="YAML config")
    synthetic.add_argument("--json", type=Path, help="also write the results as JSON")
    synthetic.set_defaults(run=_evaluate_synthetic)
    return parser


def _segment(args) -> int:
    from evseg_torch.config import SegmenterConfig, load_config
    from evseg_torch.io import SUPPORTED_SUFFIXES, read_sensor_size

    config = load_config(args.config) if args.config else SegmenterConfig()
    jobs = []
    for name in args.inputs:
        path = Path(name)
        if not path.is_file():
            raise EvsegError(f"{path}: no such file")
        if path.suffix.lower() not in SUPPORTED_SUFFIXES:
            raise EvsegError(
                f"{path}: unknown format {path.suffix!r}; supported: {' '.join(SUPPORTED_SUFFIXES)}"
            )
        sensor_size = args.sensor_size or read_sensor_size(path)
        if sensor_size is None:
            raise EvsegError(f"{path}: the file does not store the sensor size; pass --sensor-size HxW")
        out = args.out / path.stem
        if out.exists() and any(out.iterdir()) and not args.overwrite:
            raise EvsegError(f"output folder {out} is not empty; pass --overwrite to replace it")
        jobs.append((path, tuple(sensor_size), out))
    options = {
        "window_ms": args.window_ms,
        "stride_ms": args.stride_ms,
        "events_per_window": args.events_per_window,
        "save_images": args.save_images,
        "overwrite": args.overwrite,
        "chunk_size": args.chunk_size,
        "progress": not args.quiet and args.workers <= 1,
    }
    from tqdm.auto import tqdm

    if args.workers <= 1:
        summaries = [
            segment_file(path, out, sensor_size, config, **options) for path, sensor_size, out in jobs
        ]
    else:
        with ProcessPoolExecutor(max_workers=args.workers, initializer=_single_thread) as pool:
            futures = [pool.submit(segment_file, p, o, s, config, **options) for p, s, o in jobs]
            summaries = [f.result() for f in tqdm(futures, desc="files", disable=args.quiet)]
    for (path, _, out), summary in zip(jobs, summaries, strict=True):
        log.info(
            "%s: %d events, %d windows, %.0f events/s -> %s",
            path.name,
            summary["events"],
            summary["windows"],
            summary["events_per_s"] or 0,
            out,
        )
    return 0


def segment_file(
    path,
    out,
    sensor_size,
    config,
    *,
    window_ms=None,
    stride_ms=None,
    events_per_window=None,
    save_images=False,
    overwrite=False,
    chunk_size=1_000_000,
    progress=False,
) -> dict:
    """Segment one recording window by window and write its results (see :mod:`evseg_torch.output`)."""
    from tqdm.auto import tqdm

    from evseg_torch.config import replace_config
    from evseg_torch.io import iter_event_chunks
    from evseg_torch.output import SegmentationWriter
    from evseg_torch.pipeline import CascadedSegmenter

    overrides = {k: v for k, v in {"window_ms": window_ms, "stride_ms": stride_ms}.items() if v is not None}
    if events_per_window is not None:
        overrides["events_per_window"] = events_per_window
    config = replace_config(config, **overrides)
    segmenter = CascadedSegmenter(sensor_size, config)
    writer = SegmentationWriter(out, config, save_images=save_images, overwrite=overwrite)
    counted = _CountingChunks(iter_event_chunks(path, chunk_size, sensor_size=sensor_size))
    start = time.perf_counter()
    windows = segmenter.stream(counted)
    for result in tqdm(windows, desc=path.name, unit=" windows", disable=not progress):
        writer.add(result)
    if counted.n_events == 0:
        raise EvsegError(f"{path}: the recording holds no events")
    return writer.close(
        counted.n_events, time.perf_counter() - start, {"input": str(path), "sensor_size": list(sensor_size)}
    )


class _CountingChunks:
    """Pass chunks through while counting events, so the stream is read once."""

    def __init__(self, chunks):
        self.chunks = chunks
        self.n_events = 0

    def __iter__(self):
        for chunk in self.chunks:
            self.n_events += len(chunk)
            yield chunk


def _single_thread() -> None:
    import torch

    torch.set_num_threads(1)


def _demo(args) -> int:
    from evseg_torch.metrics import labelling_accuracy, per_object_iou
    from evseg_torch.pipeline import CascadedSegmenter
    from evseg_torch.synthetic import make_scene
    from evseg_torch.viz import fig1_figure, save_figure

    args.out.mkdir(parents=True, exist_ok=True)
    scene = make_scene(sensor_size=(180, 240), duration=0.03, n_objects=2, rng=args.seed)
    segmenter = CascadedSegmenter(sensor_size=scene.sensor_size)
    result = segmenter(scene.events)
    ious = per_object_iou(result.labels, scene.labels)
    metrics = {
        "events": len(scene.events),
        "clusters": f"{result.n_clusters} (true {len(scene.motions)})",
        "accuracy": labelling_accuracy(result.labels, scene.labels),
        "mean IMO IoU": float(np.mean(list(ious.values()))),
        "time": f"{result.timings_ms['total']:.0f} ms",
    }
    figure = fig1_figure(result, title=f"synthetic scene, seed {args.seed}", metrics=metrics)
    path = save_figure(figure, args.out / "demo.png")
    (args.out / "metrics.json").write_text(json.dumps({**metrics, "timings_ms": result.timings_ms}, indent=2))
    log.info("wrote %s", path)
    for key, value in metrics.items():
        log.info("%-13s %s", key, value)
    return 0


def _simulate(args) -> int:
    from evseg_torch.synthetic import make_scene

    args.out.mkdir(parents=True, exist_ok=True)
    for seed in args.seeds:
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
            height=scene.sensor_size[0],
            width=scene.sensor_size[1],
            motion_models=np.array([m.model.name for m in scene.motions]),
            motion_params=np.array([np.pad(m.params, (0, 4 - len(m.params))) for m in scene.motions]),
        )
        log.info("wrote %s (%d events)", path, len(scene.events))
    return 0


def _evaluate_synthetic(args) -> int:
    return 0


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


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split()) or type(err).__name__


if __name__ == "__main__":
    sys.exit(main())
