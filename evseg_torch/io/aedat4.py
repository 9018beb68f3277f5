"""Reader of iniVation AEDAT 4 files (``.aedat4``) through the ``aedat`` package's decoder.

The first event stream of the file is read (frames, IMU samples and triggers are skipped); its
packets are structured arrays with fields ``t`` (µs), ``x``, ``y`` and ``on``, and the stream
declares the sensor's width and height. Packets are decoded one at a time, so chunks stream.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import aedat
import numpy as np

from evseg_torch.errors import ReaderError
from evseg_torch.io.packets import concatenate, regroup


def read(path: Path) -> np.ndarray:
    """All events of the first event stream, as one structured array."""
    return concatenate(_packets(path))


def chunks(path: Path, chunk_size: int) -> Iterator[np.ndarray]:
    """Consecutive blocks of at most ``chunk_size`` events, regrouped from the decoder's packets."""
    return regroup(_packets(path), chunk_size)


def sensor_size(path: Path) -> tuple[int, int]:
    """``(H, W)`` declared by the first event stream."""
    stream = _event_stream(aedat.Decoder(str(path)))[1]
    return int(stream["height"]), int(stream["width"])


def _packets(path: Path) -> Iterator[np.ndarray]:
    decoder = aedat.Decoder(str(path))
    stream_id = _event_stream(decoder)[0]
    for packet in decoder:
        if packet["stream_id"] == stream_id and "events" in packet:
            yield packet["events"]


def _event_stream(decoder) -> tuple[int, dict]:
    streams = {key: value for key, value in decoder.id_to_stream().items() if value["type"] == "events"}
    if not streams:
        raise ReaderError("the file holds no event stream")
    first = min(streams)
    return first, streams[first]
