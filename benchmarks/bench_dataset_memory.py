"""Peak resident memory of a DataLoader over a whole recording, for the recording and a longer copy.

For each length, a child process builds :class:`~evseg_torch.data.EventWindowDataset` (30 ms windows)
over the recording, iterates it once with a DataLoader (2 workers, batch size 8,
:func:`~evseg_torch.data.collate_events`) and reports its peak resident memory: the parent's own
``ru_maxrss`` and the largest of its workers' (``RUSAGE_CHILDREN``, read after the workers are
joined). The longer copies repeat the recording end to end, each repeat shifted in time past the one
before, and are written as canonical ``.npy`` files in a temporary directory. Memory is flat when the
peaks are about the same for every length.

    .venv/bin/python benchmarks/bench_dataset_memory.py [--recording PATH] [--repeats 1 4]
"""

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from evseg_torch.events import EVENT_DTYPE
from evseg_torch.io import load_events, read_sensor_size

HERE = Path(__file__).resolve().parent
RECORDING = (
    HERE.parents[1] / "shared" / "data" / "real" / "dvs128_person_walking" / "alex_walking_for_10secs.aedat"
)

# The child measures itself, so each length starts from a fresh process.
CHILD = """
import json, resource, sys, time
from torch.utils.data import DataLoader
from evseg_torch.data import EventWindowDataset, collate_events

kib = lambda who: resource.getrusage(who).ru_maxrss
baseline = kib(resource.RUSAGE_SELF)
start = time.perf_counter()
path, height, width, chunk_size = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
options = {"chunk_size": int(chunk_size)} if chunk_size != "default" else {}
dataset = EventWindowDataset(path, window_ms=30, sensor_size=(height, width), **options)
built = time.perf_counter()
loader = DataLoader(dataset, batch_size=8, num_workers=2, collate_fn=collate_events)
batches = events = 0
for batch in loader:
    batches += 1
    events += int(batch["events"].lengths.sum())
del loader  # joins the workers, so that RUSAGE_CHILDREN counts them
print(json.dumps({
    "events": events, "windows": len(dataset), "batches": batches,
    "build_s": built - start, "iterate_s": time.perf_counter() - built,
    "baseline_mib": baseline / 1024, "parent_mib": kib(resource.RUSAGE_SELF) / 1024,
    "worker_mib": kib(resource.RUSAGE_CHILDREN) / 1024,
}))
"""


def write_repeated(events: np.ndarray, repeats: int, path: Path) -> Path:
    """The events ``repeats`` times end to end, each repeat 1 ms after the previous one's last event."""
    span = int(events["t"][-1] - events["t"][0]) + 1000
    out = np.lib.format.open_memmap(path, mode="w+", dtype=EVENT_DTYPE, shape=(repeats * len(events),))
    for repeat in range(repeats):
        block = out[repeat * len(events) : (repeat + 1) * len(events)]
        block[:] = events
        block["t"] += repeat * span
    out.flush()
    del out
    return path


def measure(path: Path, sensor_size: tuple[int, int], chunk_size: int | None) -> dict:
    child = subprocess.run(
        [sys.executable, "-c", CHILD, str(path), *map(str, sensor_size), str(chunk_size or "default")],
        check=True,
        capture_output=True,
        text=True,
    )
    return json.loads(child.stdout.splitlines()[-1])


# (heading, key of a child's result, decimals)
COLUMNS = [
    ("events", "events", 0),
    ("windows", "windows", 0),
    ("file MiB", "file_mib", 2),
    ("imports MiB", "baseline_mib", 1),
    ("parent MiB", "parent_mib", 1),
    ("worker MiB", "worker_mib", 1),
    ("build s", "build_s", 2),
    ("iterate s", "iterate_s", 2),
]
WIDTH = 12


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--recording", type=Path, default=RECORDING)
    parser.add_argument("--repeats", type=int, nargs="+", default=[1, 4])
    parser.add_argument("--chunk-size", type=int, help="events per chunk of the dataset's construction pass")
    args = parser.parse_args()
    if not args.recording.is_file():
        print(f"skipped: recording not found at {args.recording}")
        return
    events = load_events(args.recording)
    sensor_size = read_sensor_size(args.recording) or (int(events["y"].max()) + 1, int(events["x"].max()) + 1)
    seconds = (events["t"][-1] - events["t"][0]) * 1e-6
    print(f"{args.recording.name}: {len(events)} events, {seconds:.2f} s, sensor (H, W) {sensor_size}")
    print(
        "DataLoader of 2 workers, batch size 8, 30 ms windows; peak RSS of the parent and its largest worker"
    )
    print(f"{'length':>6}" + "".join(f"{heading:>{WIDTH}}" for heading, _, _ in COLUMNS))
    with tempfile.TemporaryDirectory() as folder:
        for repeats in args.repeats:
            path = args.recording
            if repeats != 1:
                path = write_repeated(events, repeats, Path(folder) / f"x{repeats}.npy")
            result = measure(path, sensor_size, args.chunk_size) | {"file_mib": path.stat().st_size / 2**20}
            print(
                f"{repeats:>5}x" + "".join(f"{result[key]:>{WIDTH}.{digits}f}" for _, key, digits in COLUMNS)
            )


if __name__ == "__main__":
    main()
