"""Synthetic events and writers of every supported format, for round-trip tests of the readers."""

import h5py
import numpy as np

from evseg_torch.events import EVENT_DTYPE

HEIGHT, WIDTH = 120, 128  # fits the DVS128 AEDAT 2.0 layout too
T0_US = 1_519_689_694_766_017  # an absolute EED-like time: float seconds must keep the microseconds


def make_events(n: int = 500, seed: int = 0, t0_us: int = T0_US) -> np.ndarray:
    rng = np.random.default_rng(seed)
    events = np.empty(n, dtype=EVENT_DTYPE)
    events["t"] = t0_us + np.cumsum(rng.integers(0, 40, n))  # zero steps: equal timestamps occur
    events["x"] = rng.integers(0, WIDTH, n)
    events["y"] = rng.integers(0, HEIGHT, n)
    events["p"] = rng.choice(np.array([-1, 1], dtype=np.int8), n)
    return events


def as_seconds_array(events: np.ndarray) -> np.ndarray:
    return np.column_stack([events["t"] * 1e-6, events["x"], events["y"], events["p"] > 0]).astype(np.float64)


def write_txt(path, events):
    seconds, micro = np.divmod(events["t"], 1_000_000)
    lines = [
        f"{s}.{u:06d}000 {x} {y} {int(p > 0)}\n"
        for s, u, x, y, p in zip(seconds, micro, events["x"], events["y"], events["p"], strict=True)
    ]
    path.write_text("# t x y p\n" + "".join(lines))


def write_npy(path, events):
    np.save(path, as_seconds_array(events))


def write_npy_structured(path, events):
    data = np.zeros(len(events), dtype=[("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "u1")])
    data["t"], data["x"], data["y"], data["p"] = events["t"], events["x"], events["y"], events["p"] > 0
    np.save(path, data)


def write_npz_columns(path, events):
    np.savez(
        path,
        t_us=events["t"],
        x=events["x"].astype(np.uint16),
        y=events["y"].astype(np.uint16),
        p=(events["p"] > 0).astype(np.int8),
        width=np.int32(WIDTH),
        height=np.int32(HEIGHT),
    )


def write_npz_events(path, events):
    np.savez_compressed(path, events=as_seconds_array(events), K=np.eye(3), D=np.zeros(4))


def write_h5_event_utils(path, events):
    with h5py.File(path, "w") as file:
        file.create_dataset("events/xs", data=events["x"].astype(np.int16))
        file.create_dataset("events/ys", data=events["y"].astype(np.int16))
        file.create_dataset("events/ts", data=events["t"] * 1e-6)
        file.create_dataset("events/ps", data=events["p"] > 0)
        file.attrs["sensor_resolution"] = np.array([HEIGHT, WIDTH])


def write_h5_dsec(path, events, t_offset=T0_US - 1000):
    with h5py.File(path, "w") as file:
        file.create_dataset("events/x", data=events["x"].astype(np.uint16), chunks=True)
        file.create_dataset("events/y", data=events["y"].astype(np.uint16), chunks=True)
        file.create_dataset("events/t", data=(events["t"] - t_offset).astype(np.uint32), chunks=True)
        file.create_dataset("events/p", data=(events["p"] > 0).astype(np.uint8), chunks=True)
        file.create_dataset("t_offset", data=np.int64(t_offset))
        file.create_dataset("ms_to_idx", data=np.zeros(3, dtype=np.uint64))


def aedat2_bytes(events, chip=b"ch.unizh.ini.jaer.chip.retina.DVS128", version=b"#!AER-DAT2.0"):
    header = version + b"\r\n# This is a raw AE data file\r\n# AEChip: " + chip + b"\r\n# end\r\n"
    records = np.empty(len(events), dtype=[("address", ">i4"), ("t", ">i4")])
    x, y = events["x"].astype(np.int32), events["y"].astype(np.int32)
    records["address"] = ((127 - y) << 8) | ((127 - x) << 1) | (events["p"] < 0)
    records["t"] = events["t"]  # jAER stores 32-bit microseconds
    return header + records.tobytes()


# name -> (file name, writer, stored sensor size)
WRITERS = {
    "txt": ("events.txt", write_txt, None),
    "npy": ("events.npy", write_npy, None),
    "npy_structured": ("events.npy", write_npy_structured, None),
    "npz_columns": ("events.npz", write_npz_columns, (HEIGHT, WIDTH)),
    "npz_events": ("events.npz", write_npz_events, None),
    "h5_event_utils": ("events.h5", write_h5_event_utils, (HEIGHT, WIDTH)),
    "hdf5_dsec": ("events.hdf5", write_h5_dsec, None),
}
