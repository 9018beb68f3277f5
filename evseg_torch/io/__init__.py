"""Event files and ground truth: one reader per format, chosen by the file's suffix or the folder's contents.

:func:`load_events` reads a whole file, :func:`iter_event_chunks` streams it, :func:`read_sensor_size`
reads the ``(H, W)`` a file stores, :func:`read_time_span` its first and last timestamps where that is
cheap, :func:`reader_for` names the reader of a path. Every reader returns
canonical events (see :mod:`evseg_torch.events`) and raises :class:`~evseg_torch.errors.ReaderError`
with a one-line message naming the file for a missing, unknown, corrupt or truncated file.
"""

from evseg_torch.io.dispatch import (
    SUPPORTED_SUFFIXES,
    iter_event_chunks,
    load_events,
    read_sensor_size,
    read_time_span,
    reader_for,
    resolve_sensor_size,
    scan_sensor_size,
)
from evseg_torch.io.eed import load_eed_boxes, load_frame_list
from evseg_torch.io.evimo import EvimoSequence, load_evimo, save_evimo
from evseg_torch.io.evimo2 import load_evimo2

__all__ = [
    "SUPPORTED_SUFFIXES",
    "EvimoSequence",
    "iter_event_chunks",
    "load_eed_boxes",
    "load_events",
    "load_evimo",
    "load_evimo2",
    "load_frame_list",
    "read_sensor_size",
    "read_time_span",
    "reader_for",
    "resolve_sensor_size",
    "save_evimo",
    "scan_sensor_size",
]
