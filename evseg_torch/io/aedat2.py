"""Reader of jAER AEDAT 2.0 files (``.aedat``) recorded with a DVS128.

Layout: header lines starting with ``#`` (the first is ``#!AER-DAT2.0``, one names the ``AEChip``),
then one big-endian int32 address and one int32 timestamp (µs) per event. The DVS128 address holds
the polarity in bit 0, x in bits 1-7 and y in bits 8-14, both mirrored by the chip; bit 15 marks an
external (special) event, which is dropped. Decoded as jAER does, with ``y = 0`` the top row::

    x = 127 - ((address >> 1) & 0x7F)    y = 127 - ((address >> 8) & 0x7F)    p = 1 - (address & 1)

The sensor size is 128 x 128. The body is memory-mapped, so chunks stream from disk. Other chips
(DAVIS, cochlea) and AEDAT 1.0 / 3.x files are refused; the 32-bit timestamps are not unwrapped, so
a recording longer than 35 minutes fails the time-order check.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from evseg_torch.errors import ReaderError

SENSOR_SIZE = (128, 128)

_RECORD = np.dtype([("address", ">i4"), ("t", ">i4")])
_SPECIAL_EVENT_BIT = 0x8000


def read(path: Path) -> np.ndarray:
    """All events, as a structured array with ``t`` in µs."""
    return _decode(_records(path))


def chunks(path: Path, chunk_size: int) -> Iterator[np.ndarray]:
    """Consecutive blocks of at most ``chunk_size`` records, decoded (special events dropped)."""
    records = _records(path)
    for begin in range(0, len(records), chunk_size):
        events = _decode(records[begin : begin + chunk_size])
        if len(events):
            yield events


def sensor_size(path: Path) -> tuple[int, int]:
    """``(128, 128)``, after checking that the file is a DVS128 AEDAT 2.0 recording."""
    _header_length(path)
    return SENSOR_SIZE


def _records(path: Path) -> np.ndarray:
    start = _header_length(path)
    body = path.stat().st_size - start
    if body % _RECORD.itemsize:
        raise ReaderError(f"truncated: {body} bytes after the header is not a whole number of 8-byte events")
    if body == 0:
        return np.zeros(0, dtype=_RECORD)
    return np.memmap(path, dtype=_RECORD, mode="r", offset=start)


def _header_length(path: Path) -> int:
    """Bytes taken by the ``#`` header lines, after checking version and chip."""
    with open(path, "rb") as file:
        version = file.readline()
        if not version.startswith(b"#!AER-DAT2"):
            found = version[:16].decode("ascii", errors="replace").strip()
            raise ReaderError(f"not a jAER AEDAT 2.0 file (first line {found!r}); only version 2.0 is read")
        chip = None
        while True:
            start = file.tell()
            line = file.readline()
            if not line.startswith(b"#"):
                break
            if b"AEChip:" in line:
                chip = line.split(b"AEChip:", 1)[1].decode("ascii", errors="replace").strip()
    if chip is None or not chip.endswith("DVS128"):
        raise ReaderError(f"AEChip {chip!r} is not supported; only DVS128 recordings are decoded")
    return start


def _decode(records: np.ndarray) -> np.ndarray:
    address = records["address"]
    keep = (address & _SPECIAL_EVENT_BIT) == 0
    address = address[keep]
    out = np.empty(len(address), dtype=[("t", np.int64), ("x", np.int16), ("y", np.int16), ("p", np.int8)])
    out["t"] = records["t"][keep]
    out["x"] = 127 - ((address >> 1) & 0x7F)
    out["y"] = 127 - ((address >> 8) & 0x7F)
    out["p"] = 1 - (address & 1)
    return out
