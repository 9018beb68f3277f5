"""Ground truth of the Extreme Event Dataset (EED, Mitrokhin et al., IROS 2018): boxes and frame lists.

``boundingbox.txt`` holds one hand-labelled box of the independently moving object per line::

    1519689694.996659517, x= 2, y= 36, w= 24, h= 22

with ``(x, y)`` the top-left corner (column, row) and ``w``, ``h`` the size in pixels. ``images.txt``
lists the APS frames as ``t relative/path.png``. Times stay in seconds in the file's own time base:
absolute in the original files, where they match the absolute times of the sequence's ``events.txt``;
relative to the first box in the ``boundingbox_rel.txt`` of ``eed_what_is_background``, whose
``events.txt`` starts at 0 at that first box. Float64 keeps absolute times to about 0.24 µs.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from evseg_torch.errors import ReaderError
from evseg_torch.io.guard import existing_file, reading

_NUMBER = r"([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)"
_BOX_LINE = re.compile(
    rf"^{_NUMBER}\s*,\s*x=\s*{_NUMBER}\s*,\s*y=\s*{_NUMBER}\s*,\s*w=\s*{_NUMBER}\s*,\s*h=\s*{_NUMBER}$"
)
_FRAME_LINE = re.compile(rf"^{_NUMBER}\s+(\S.*)$")


def load_eed_boxes(path) -> tuple[np.ndarray, np.ndarray]:
    """Read an EED ``boundingbox.txt`` (or ``boundingbox_rel.txt``).

    Args:
        path: the text file, one ``t, x= X, y= Y, w= W, h= H`` box per line; blank lines and ``#``
            comments are skipped.

    Returns:
        ``(times_s, boxes)``: float64 :math:`(M,)` seconds in the file's time base, and float64
        :math:`(M, 4)` ``[x, y, w, h]`` in pixels, ``(x, y)`` the top-left corner.

    Raises:
        ReaderError: the file is missing, holds no box, or a line does not match (its number is named).
    """
    path = existing_file(path)
    with reading(path, "EED bounding-box file"):
        rows = []
        for number, line in _content_lines(path):
            match = _BOX_LINE.match(line)
            if match is None:
                raise ReaderError(f"line {number}: expected 't, x= X, y= Y, w= W, h= H', got {line!r}")
            rows.append([float(value) for value in match.groups()])
        if not rows:
            raise ReaderError("no bounding boxes in the file")
        table = np.array(rows, dtype=np.float64)
        return table[:, 0], table[:, 1:]


def load_frame_list(path) -> tuple[np.ndarray, list[str]]:
    """Read an ``images.txt`` frame list (EED, rpg / ECD layout).

    Args:
        path: the text file, one ``t relative/path.png`` per line; blank lines and ``#`` comments
            are skipped.

    Returns:
        ``(times_s, files)``: float64 :math:`(F,)` seconds in the file's time base, and the image
        paths as written, relative to the folder holding ``path``.

    Raises:
        ReaderError: the file is missing, lists no frame, or a line is not ``time path``.
    """
    path = existing_file(path)
    with reading(path, "frame list"):
        times, files = [], []
        for number, line in _content_lines(path):
            match = _FRAME_LINE.match(line)
            if match is None:
                raise ReaderError(f"line {number}: expected 'time path', got {line!r}")
            times.append(float(match.group(1)))
            files.append(match.group(2))
        if not files:
            raise ReaderError("no frames in the file")
        return np.array(times, dtype=np.float64), files


def _content_lines(path: Path) -> list[tuple[int, str]]:
    """Numbered lines with comments and surrounding blanks removed, empty ones dropped."""
    with open(path, encoding="utf-8") as file:
        stripped = ((number, line.split("#", 1)[0].strip()) for number, line in enumerate(file, start=1))
        return [(number, line) for number, line in stripped if line]
