"""Reader of text events in the rpg / ECD / EED layout: one event ``t x y p`` per line.

``t`` is in seconds (relative, or absolute such as ``1519689694.766017193``), ``x`` the column, ``y``
the row, ``p`` 0/1 or -1/+1. Blank lines and ``#`` comments are skipped. The file stores no sensor size.

Values are parsed as float64 by :func:`numpy.loadtxt` and times rounded to the microsecond by
:func:`evseg_torch.events.as_events`; at absolute times near 1.5e9 s float64 resolves 0.24 µs, so the
rounded microseconds are exact unless a timestamp's sub-microsecond part lies within about 0.25 µs of
one half.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterator
from itertools import islice
from pathlib import Path

import numpy as np

from evseg_torch.errors import ReaderError

_COLUMNS = 4
# The last event is parsed from this many bytes at the file's end.
_TAIL_BYTES = 1 << 16


def read(path: Path) -> np.ndarray:
    """All events of the file as a float64 array :math:`(N, 4)` ``[t_seconds, x, y, p]``."""
    with open(path, "rb") as file:
        return _parse(file.readlines(), first_line=1)


def chunks(path: Path, chunk_size: int) -> Iterator[np.ndarray]:
    """Blocks of at most ``chunk_size`` lines, parsed; blocks holding only comments are skipped."""
    with open(path, "rb") as file:
        first_line = 1
        while lines := list(islice(file, chunk_size)):
            block = _parse(lines, first_line)
            first_line += len(lines)
            if len(block):
                yield block


def ends(path: Path) -> np.ndarray | None:
    """The first and the last event, the last parsed from the file's end; ``None`` if either is missing."""
    first = next(chunks(path, 1000), None)
    with open(path, "rb") as file:
        start = file.seek(max(file.seek(0, os.SEEK_END) - _TAIL_BYTES, 0))
        tail = file.read().splitlines()
    if start > 0:
        tail = tail[1:]  # the first line read may be cut
    last = _parse(tail, first_line=1) if tail else None
    if first is None or last is None or not len(last):
        return None
    return np.stack([first[0], last[-1]])


def sensor_size(path: Path) -> None:
    """Text files store no sensor size."""
    return None


def _parse(lines: list[bytes], first_line: int) -> np.ndarray:
    try:
        with warnings.catch_warnings():
            # loadtxt warns on a block of comments only; an empty block is a valid result here.
            warnings.filterwarnings("ignore", "loadtxt: input contained no data", UserWarning)
            data = np.loadtxt(lines, dtype=np.float64, comments="#", ndmin=2)
    except ValueError:
        raise ReaderError(_first_malformed(lines, first_line)) from None
    if data.size == 0:
        return np.empty((0, _COLUMNS), dtype=np.float64)
    if data.shape[1] != _COLUMNS:
        raise ReaderError(_first_malformed(lines, first_line))
    return data


def _first_malformed(lines: list[bytes], first_line: int) -> str:
    """Describe the first line that is not four numbers (only run once parsing has failed)."""
    for number, line in enumerate(lines, start=first_line):
        tokens = line.split(b"#", 1)[0].split()
        if not tokens:
            continue
        text = line.decode("utf-8", errors="replace").strip()
        if len(tokens) != _COLUMNS:
            return f"line {number}: expected 4 values 't x y p', found {len(tokens)}: {text!r}"
        try:
            for token in tokens:
                float(token)
        except ValueError:
            return f"line {number}: not a number in {text!r}"
    return f"lines {first_line}..{first_line + len(lines) - 1}: cannot parse as 't x y p'"
