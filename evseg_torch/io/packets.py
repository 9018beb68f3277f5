"""Regrouping of a decoder's packets into chunks of a chosen size, for the readers that decode in packets.

AEDAT 4 packets, ROS event-array messages and the RAW decoder's blocks each hold however many events the
recording or the decoder chose; :func:`iter_event_chunks` promises chunks of at most ``chunk_size``
events instead. Only the pending remainder (less than one chunk) and the current packet are held, so a
recording of any length streams in bounded memory.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator

import numpy as np

from evseg_torch.errors import ReaderError


def regroup(packets: Iterable[np.ndarray], chunk_size: int) -> Iterator[np.ndarray]:
    """Consecutive blocks of exactly ``chunk_size`` events, then the remainder, from packets of any size.

    Args:
        packets: arrays :math:`(n_i,)` of one dtype, in order; empty ones are allowed.
        chunk_size: the events of every block but the last.

    Yields:
        Non-empty arrays :math:`(\\le chunk\\_size,)`, whose concatenation is that of the packets.
    """
    pending, count = [], 0
    for packet in packets:
        pending.append(packet)
        count += len(packet)
        if count >= chunk_size:
            merged = np.concatenate(pending)
            full = count - count % chunk_size
            for begin in range(0, full, chunk_size):
                yield merged[begin : begin + chunk_size]
            pending, count = [merged[full:]], count - full
    if count:
        yield np.concatenate(pending)


def concatenate(packets: Iterable[np.ndarray], what: str = "the event stream") -> np.ndarray:
    """All packets as one array; :class:`ReaderError` naming ``what`` when there are none."""
    packets = list(packets)
    if not packets:
        raise ReaderError(f"{what} holds no events")
    return np.concatenate(packets)
