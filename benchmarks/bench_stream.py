"""Stream a long synthetic recording through ``evseg segment`` and report throughput and peak memory.

The recording (``--minutes`` long, written chunk by chunk to an ``.npy`` file so that making it needs
little memory) repeats a handful of distinct synthetic 30 ms scenes one after another, shifted in time.
``evseg segment`` runs in a child process; its peak resident memory (the largest ``ru_maxrss`` of the
child and its workers) is reported for each length, so one can check that memory does not grow with the
recording's length. By default each scene lasts one 30 ms window, so every window is another scene than
the one before and the models a stream carries forward never fit the next window: guided tracking falls
back to cold tracking, and reuse only adds models to the pool. That is the worst case for a stream's
carried models. ``--scene-ms 150`` makes each scene last 5 windows, continuous within, as a recording
is between its cuts. Over longer scenes the objects leave the view (1.5 clusters per window in 600 ms
scenes, 2.3 in 30 and 150 ms ones), so they are simpler recordings as well.

    .venv/bin/python benchmarks/bench_stream.py [--minutes 1 2] [--scenes 8] [--events-per-scene 2500]
        [--scene-ms 30] [--config CONFIG.yaml] [--workers 2] [--batch-size 8]

With more than one worker the batch size defaults to 8: ``evseg segment`` shares out each batch's windows,
and with a batch smaller than the workers one process would run.

Real time means the wall time stays under the recording's length (the ``x real time`` column: its length
over the wall time, above 1 when faster).
"""

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from evseg_torch.events import EVENT_DTYPE
from evseg_torch.synthetic import make_scene

SENSOR = (180, 240)
SCENE_US = 30_000
# The stages of summary.json's timings_ms that the table shows.
STAGES = ("features", "level_one", "level_two")


def write_recording(
    path: Path,
    minutes: float,
    n_scenes: int,
    events_per_scene: int,
    scene_us: int = SCENE_US,
    **scene_options,
) -> int:
    """Write a recording of ``minutes``: ``n_scenes`` synthetic scenes of ``scene_us`` each, in turn.

    Args:
        path: the ``.npy`` file to write (chunk by chunk, through a memory map).
        minutes: length of the recording.
        n_scenes: distinct scenes, drawn with seeds 0, 1, ...
        events_per_scene: about how many signal events each scene has (noise comes on top).
        scene_us: length of each scene in microseconds.
        **scene_options: more keywords of :func:`~evseg_torch.synthetic.make_scene`, e.g. ``noise_rate_hz``.

    Returns:
        The number of events written.
    """
    duration = scene_us / 1e6
    scenes = [
        make_scene(SENSOR, duration, 1 + s % 3, n_events=events_per_scene, rng=s, **scene_options).events
        for s in range(n_scenes)
    ]
    n_slots = round(minutes * 60e6 / scene_us)
    total = sum(len(scenes[slot % n_scenes]) for slot in range(n_slots))
    out = np.lib.format.open_memmap(path, mode="w+", dtype=EVENT_DTYPE, shape=(total,))
    position = 0
    for slot in range(n_slots):
        chunk = scenes[slot % n_scenes].copy()
        chunk["t"] = chunk["t"] - chunk["t"][0] + slot * scene_us
        out[position : position + len(chunk)] = chunk
        position += len(chunk)
    out.flush()
    del out
    return total


# The child reports its peak resident memory (its own, or its largest worker's), so each length is measured
# on its own.
CHILD = (
    "import atexit, resource, sys\n"
    "who = (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)\n"
    "peak = lambda: max(resource.getrusage(w).ru_maxrss for w in who)\n"
    "atexit.register(lambda: print('MAXRSS_KIB', peak(), file=sys.stderr))\n"
    "from evseg_torch.app.cli import main\n"
    "sys.exit(main(sys.argv[1:]))"
)


def run(path: Path, out: Path, config: Path | None = None, workers: int = 1, batch_size: int = 1) -> dict:
    args = ["--quiet", "segment", str(path), "--out", str(out), "--sensor-size", f"{SENSOR[0]}x{SENSOR[1]}"]
    args += ["--workers", str(workers), "--batch-size", str(batch_size)]
    if config is not None:
        args += ["--config", str(config)]
    start = time.perf_counter()
    child = subprocess.run(
        [sys.executable, "-c", CHILD, *args, "--window-ms", "30", "--overwrite"],
        check=True,
        capture_output=True,
        text=True,
    )
    wall = time.perf_counter() - start
    peak_kib = int(child.stderr.split("MAXRSS_KIB")[-1].split()[0])
    summary = json.loads((out / path.stem / "summary.json").read_text())
    return {"wall_s": wall, "peak_rss_mib": peak_kib / 1024, **summary}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, nargs="+", default=[1.0, 2.0])
    parser.add_argument("--scenes", type=int, default=8)
    parser.add_argument(
        "--events-per-scene", type=int, default=2500, help="signal events per 30 ms of a scene (default 2500)"
    )
    parser.add_argument(
        "--scene-ms", type=float, default=30.0, help="length of each scene (default 30: one window)"
    )
    parser.add_argument("--config", type=Path, help="YAML config for evseg segment (default: its own)")
    parser.add_argument("--workers", type=int, default=1, help="evseg segment --workers")
    parser.add_argument(
        "--batch-size",
        type=int,
        help="evseg segment --batch-size (default 8 with more than one worker, which share out each batch's "
        "windows, else 1)",
    )
    args = parser.parse_args()
    if args.batch_size is None:
        args.batch_size = 8 if args.workers > 1 else 1
    if not args.scene_ms >= 30.0:
        parser.error(f"--scene-ms must be at least one 30 ms window, got {args.scene_ms:g}")
    scene_us = round(args.scene_ms * 1e3)
    events_per_scene = round(args.events_per_scene * scene_us / SCENE_US)
    print(f"workers {args.workers}, batch size {args.batch_size}, scenes of {args.scene_ms:g} ms")
    print(
        f"{'minutes':>7} {'events':>10} {'windows':>7} {'wall s':>8} {'events/s':>9} {'windows/s':>9} "
        f"{'x real time':>11} {'peak RSS MiB':>12}  median ms per window: features / level one / level two"
    )
    with tempfile.TemporaryDirectory() as tmp:
        for minutes in args.minutes:
            path = Path(tmp) / f"stream_{minutes:g}min.npy"
            n_events = write_recording(path, minutes, args.scenes, events_per_scene, scene_us)
            result = run(path, Path(tmp) / "out", args.config, args.workers, args.batch_size)
            wall, windows = result["wall_s"], result["windows"]
            print(
                f"{minutes:>7g} {n_events:>10} {windows:>7} {wall:>8.1f} {n_events / wall:>9.0f} "
                f"{windows / wall:>9.1f} {minutes * 60 / wall:>11.2f} {result['peak_rss_mib']:>12.0f}  "
                + " / ".join(f"{result['timings_ms'][stage]['median']:.1f}" for stage in STAGES)
            )
            path.unlink()


if __name__ == "__main__":
    main()
