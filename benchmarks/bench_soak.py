"""Soak test: does ``evseg segment`` keep its memory and its speed over a long recording?

A synthetic recording of ``--minutes`` (20 by default: 40,000 windows of 30 ms) is written chunk by chunk
(:func:`bench_stream.write_recording`) and segmented by ``evseg segment`` in a child process
(``--workers 2 --batch-size 2`` by default). While it runs, the resident memory of the child and all its
descendants (the window workers) is summed every ``--sample-s`` with psutil; every ``--every-s`` of wall
time a row records the largest of those sums in that interval and the windows done, counted as the lines
of the growing ``OUT/<name>/.partial/models.jsonl`` (one line per segmented window). The verdict compares
the second row with the last one that ends before the last window (memory growth, MiB; the first row holds
start-up, the last rows the closing of the run), and the windows per second of the first and second
halves of the rows between, and their CPU milliseconds per window, which other processes' load on the
cores changes far less than it changes windows per second.

The scenes are sparse (about 300 signal events and 0.05 noise events per pixel per second: ~350 events
per 30 ms window, above ``window.min_events``; level one proposes 1-4 models, level two keeps one) so that
the 20 minutes are segmented in roughly a quarter of an hour on 2 free cores: on the shared 2-core VM
(other jobs running) they took 22-30 CPU ms per window against 39-42 for 400 events and 0.1 noise events
per pixel per second (~520 events), measured one after the other, and 41 windows/s (1.2x real time) over
10 s in which the run got 1.4 cores. The ``cores`` column (CPU seconds of the tree per wall second) shows
how much of the machine the run got. Summed RSS counts the pages the processes share (torch's libraries)
once per process: it is for watching growth, not a total. Samples can miss a spike shorter than
``--sample-s``.

    .venv/bin/python benchmarks/bench_soak.py [--minutes 20] [--every-s 60] [--json soak.json]
        [--window-ms 30] [--events-per-scene 300] [--noise-hz 0.05] [--workers 2] [--batch-size 2]

The recording (~210 MB for 20 minutes) and the results (twice that) go to a temporary folder.
"""

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import psutil
from bench_stream import SENSOR, write_recording

MIB = 2**20


class ProcessTree:
    """A process and its descendants, sampled: resident memory now and CPU time so far.

    Attributes:
        cpu_s: user and system CPU seconds of every member seen so far, up to its last sample.
    """

    def __init__(self, pid: int) -> None:
        self.root = psutil.Process(pid)
        self.cpu_by_pid: dict[int, float] = {}

    @property
    def cpu_s(self) -> float:
        return sum(self.cpu_by_pid.values())

    def sample(self) -> int:
        """Resident bytes of the members now (one that ends meanwhile counts 0); updates ``cpu_s``."""
        try:
            members = [self.root, *self.root.children(recursive=True)]
        except psutil.NoSuchProcess:
            return 0
        rss = 0
        for member in members:
            try:
                with member.oneshot():
                    rss += member.memory_info().rss
                    times = member.cpu_times()
            except psutil.NoSuchProcess:
                continue
            self.cpu_by_pid[member.pid] = times.user + times.system
        return rss


class WindowCounter:
    """Windows done so far: lines of ``models.jsonl``, read on from where the last call stopped.

    The run writes ``folder/.partial/models.jsonl`` and, when finished, renames it to
    ``folder/models.jsonl``; the same file, so the count carries on.
    """

    def __init__(self, folder: Path) -> None:
        self.paths = (folder / ".partial" / "models.jsonl", folder / "models.jsonl")
        self.read_bytes = self.lines = 0

    def __call__(self) -> int:
        for path in self.paths:
            try:
                with open(path, "rb") as rows:
                    rows.seek(self.read_bytes)
                    fresh = rows.read()
            except FileNotFoundError:
                continue
            complete = fresh[: fresh.rfind(b"\n") + 1]  # a line being written counts when it ends
            self.read_bytes += len(complete)
            self.lines += complete.count(b"\n")
            break
        return self.lines


def soak(path: Path, out: Path, args: argparse.Namespace) -> tuple[list[dict], float]:
    """Segment ``path`` in a child process and sample it; returns the rows and the wall time."""
    command = [sys.executable, "-m", "evseg_torch.app.cli", "segment", str(path)]
    command += ["--out", str(out), "--quiet"]
    command += ["--sensor-size", f"{SENSOR[0]}x{SENSOR[1]}", "--window-ms", f"{args.window_ms:g}"]
    command += ["--workers", str(args.workers), "--batch-size", str(args.batch_size)]
    if args.config is not None:
        command += ["--config", str(args.config)]
    count = WindowCounter(out / path.stem)
    rows: list[dict] = []
    with tempfile.TemporaryFile("w+") as errors:
        start = time.perf_counter()
        child = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=errors)
        tree = ProcessTree(child.pid)
        row_start, row_cpu_s, peak = start, 0.0, None
        try:
            while True:
                finished = child.poll() is not None
                if not finished:
                    peak = max(peak or 0, tree.sample())
                now = time.perf_counter()
                if finished or now - row_start >= args.every_s:
                    done = count()
                    new = done - (rows[-1]["windows"] if rows else 0)
                    row = {
                        "interval": len(rows) + 1,
                        "t_s": now - start,
                        "seconds": now - row_start,
                        "windows": done,
                        "new_windows": new,
                        "windows_per_s": new / (now - row_start),
                        "cpu_s": tree.cpu_s - row_cpu_s,
                        "rss_mib": None if peak is None else peak / MIB,
                    }
                    rows.append(row)
                    print_row(row)
                    row_start, row_cpu_s, peak = now, tree.cpu_s, None
                if finished:
                    break
                time.sleep(min(args.sample_s, max(row_start + args.every_s - now, 0.0)))
        finally:
            if child.poll() is None:
                child.terminate()
                child.wait()
        wall = time.perf_counter() - start
        if child.returncode != 0:
            errors.seek(0)
            sys.exit(f"evseg segment failed (exit status {child.returncode}):\n{errors.read()[-2000:]}")
    return rows, wall


HEADER = f"{'interval':>8} {'t s':>7} {'windows':>8} {'windows/s':>9} {'cores':>5} {'RSS MiB':>8}"


def print_row(row: dict) -> None:
    """One line of the table under :data:`HEADER`; ``cores`` is the CPU seconds of the tree per second."""
    rss = "-" if row["rss_mib"] is None else f"{row['rss_mib']:.0f}"
    print(
        f"{row['interval']:>8} {row['t_s']:>7.0f} {row['windows']:>8} {row['windows_per_s']:>9.1f} "
        f"{row['cpu_s'] / row['seconds']:>5.2f} {rss:>8}",
        flush=True,
    )


def rate(rows: list[dict]) -> float | None:
    """Windows per second over some rows; ``None`` for none."""
    seconds = sum(row["seconds"] for row in rows)
    return sum(row["new_windows"] for row in rows) / seconds if seconds > 0 else None


def cpu_ms_per_window(rows: list[dict]) -> float | None:
    """CPU milliseconds of the tree per window over some rows, which other processes' load changes little."""
    windows = sum(row["new_windows"] for row in rows)
    return 1e3 * sum(row["cpu_s"] for row in rows) / windows if windows else None


def verdict(rows: list[dict]) -> dict:
    """Memory growth from the second row to the last; speed in each half of the rows after the first.

    Only the rows that end before the last window: in the row that counts it the workers may be gone
    already, and after it the run writes ``labels.npz``; neither says anything about a long run's steady
    state.
    """
    steady = [row for row in rows[1:] if row["windows"] < rows[-1]["windows"]]
    halves = (steady[: len(steady) // 2], steady[len(steady) // 2 :]) if len(steady) >= 2 else ([], [])
    sampled = [row["rss_mib"] for row in steady if row["rss_mib"] is not None]
    return {
        "memory_growth_mib": sampled[-1] - sampled[0] if len(sampled) >= 2 else None,
        "windows_per_s_halves": [rate(half) for half in halves],
        "cpu_ms_per_window_halves": [cpu_ms_per_window(half) for half in halves],
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=20.0, help="length of the recording")
    parser.add_argument("--every-s", type=float, default=60.0, help="wall seconds per row")
    parser.add_argument("--sample-s", type=float, default=1.0, help="wall seconds between memory samples")
    parser.add_argument("--json", type=Path, default=Path("soak.json"), metavar="OUT", help="results as JSON")
    parser.add_argument("--window-ms", type=float, default=30.0, help="scene and window length")
    parser.add_argument("--scenes", type=int, default=8, help="distinct scenes, repeated in turn")
    parser.add_argument("--events-per-scene", type=int, default=300, help="signal events per scene")
    parser.add_argument("--noise-hz", type=float, default=0.05, help="noise events per pixel per second")
    parser.add_argument("--config", type=Path, help="YAML config for evseg segment (default: its own)")
    parser.add_argument("--workers", type=int, default=2, help="evseg segment --workers")
    parser.add_argument("--batch-size", type=int, default=2, help="evseg segment --batch-size")
    args = parser.parse_args()
    for name in ("minutes", "every_s", "sample_s", "window_ms"):
        if getattr(args, name) <= 0:
            parser.error(f"--{name.replace('_', '-')} must be positive")
    if not args.json.parent.is_dir():  # found out now rather than after the run
        parser.error(f"--json: no folder {args.json.parent}")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "soak.npy"
        n_events = write_recording(
            path,
            args.minutes,
            args.scenes,
            args.events_per_scene,
            round(1e3 * args.window_ms),
            noise_rate_hz=args.noise_hz,
        )
        print(
            f"{args.minutes:g} min recording, {n_events} events, {args.window_ms:g} ms windows; "
            f"evseg segment --workers {args.workers} --batch-size {args.batch_size}",
            flush=True,
        )
        print(HEADER, flush=True)
        rows, wall = soak(path, Path(tmp) / "out", args)
        summary = json.loads((Path(tmp) / "out" / path.stem / "summary.json").read_text())
    result = verdict(rows)
    growth = "n/a" if result["memory_growth_mib"] is None else f"{result['memory_growth_mib']:+.0f} MiB"
    speeds = "/".join("n/a" if v is None else f"{v:.1f}" for v in result["windows_per_s_halves"])
    costs = "/".join("n/a" if v is None else f"{v:.0f}" for v in result["cpu_ms_per_window_halves"])
    print(
        f"{summary['windows']} windows in {wall:.0f} s ({args.minutes * 60 / wall:.2f}x real time). Verdict: "
        f"memory growth from row 2 to the last before the end {growth}; "
        f"after row 1, first/second half: {speeds} windows/s, {costs} CPU ms per window"
    )
    settings = {key: str(value) if isinstance(value, Path) else value for key, value in vars(args).items()}
    record = {"settings": settings, "events": n_events, "windows": summary["windows"], "wall_s": wall}
    args.json.write_text(json.dumps({**record, **result, "rows": rows}, indent=2))
    print(f"JSON: {args.json}")


if __name__ == "__main__":
    main()
