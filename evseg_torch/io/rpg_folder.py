"""Sequence folders of the rpg / ECD / EED layout: ``events.txt``, with ``images.txt`` and ``images/``.

The Event Camera Dataset (Mueggler et al., IJRR 2017) and the text release of EED (Mitrokhin et al.,
IROS 2018) keep each sequence in a folder: the events in ``events.txt`` (read by :mod:`.text`), the APS
frames listed in ``images.txt``, and ground truth beside them. The text stores no sensor size, but a
DAVIS's frames have the sensor's: the folder's size is its first listed frame's ``(H, W)``; a folder
without ``images.txt`` stores none, like a lone ``.txt`` file.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from evseg_torch.errors import ReaderError
from evseg_torch.io.eed import load_frame_list
from evseg_torch.io.text import chunks as text_chunks
from evseg_torch.io.text import ends as text_ends
from evseg_torch.io.text import read as read_text

WHAT = "rpg / ECD / EED sequence folder"
EVENTS = "events.txt"
FRAMES = "images.txt"


def is_sequence(folder: Path) -> bool:
    """Whether a folder holds the layout's ``events.txt``."""
    return (folder / EVENTS).is_file()


def read(folder: Path) -> np.ndarray:
    """All events, as float64 :math:`(N, 4)` rows ``[t_seconds, x, y, p]``."""
    return read_text(folder / EVENTS)


def chunks(folder: Path, chunk_size: int) -> Iterator[np.ndarray]:
    """Blocks of at most ``chunk_size`` lines of ``events.txt``, parsed."""
    return text_chunks(folder / EVENTS, chunk_size)


def ends(folder: Path) -> np.ndarray | None:
    """The first and the last event of ``events.txt`` (see :func:`.text.ends`)."""
    return text_ends(folder / EVENTS)


def sensor_size(folder: Path) -> tuple[int, int] | None:
    """The first listed frame's ``(H, W)``, or ``None`` without ``images.txt``."""
    if not (folder / FRAMES).is_file():
        return None
    _, files = load_frame_list(folder / FRAMES)
    frame = cv2.imread(str(folder / files[0]), cv2.IMREAD_UNCHANGED)
    if frame is None:
        raise ReaderError(f"{FRAMES} lists {files[0]!r} first, which is not a readable image")
    return int(frame.shape[0]), int(frame.shape[1])
