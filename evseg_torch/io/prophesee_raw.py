"""Reader of Prophesee RAW (EVT 2.0, EVT 3.0) and DAT files through the ``expelliarmus`` decoder.

A RAW file is a text header of ``% key value`` lines followed by binary event words; a DAT file has the
same kind of header followed by fixed-size CD events. expelliarmus (C decoder, NumPy output) decodes
them to a structured array with ``t`` (int64 µs), ``x``, ``y`` and ``p`` (0/1), and reads a file in
chunks, so :func:`chunks` streams in bounded memory.

Why expelliarmus rather than evlib (both ship manylinux wheels): on the shared EVT 3.0 sample it matches
its reference decoding event for event and is several times faster, needs only NumPy (evlib brings
polars, pyarrow and pandera, hundreds of MB), and reads in chunks (evlib returns the whole recording).

The decoder needs to be told the encoding and gives no sensor size, so the header is read here (plain
``% key value`` lines). The encoding comes from ``% evt 2.0`` / ``% evt 3.0`` or ``% format EVT3;...``
(a ``.dat`` suffix means DAT). The sensor size comes from, in this order: ``% geometry WxH``, the
``height=``/``width=`` of ``% format``, DAT's ``% Height``/``% Width``, else the camera named by
``% plugin_name`` (Gen3 and Gen3.1: 640 x 480; Gen4, Gen4.1 and IMX636: 1280 x 720); an unknown camera
gives no size. A header cut off mid-line is refused here: the decoder would loop forever on it.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np
from expelliarmus import Wizard

from evseg_torch.errors import ReaderError
from evseg_torch.io.packets import regroup

_MAX_HEADER_LINE = 4096
_DECODER_BLOCK = 65_536  # events per decoder call when streaming; regrouped to the caller's chunk size
_EVT_VERSIONS = {"2.0": "evt2", "3.0": "evt3"}
_FORMAT_NAMES = {"EVT2": "evt2", "EVT3": "evt3"}
# Sensor (H, W) of the camera plugins whose name alone fixes the resolution, by name prefix.
_PLUGIN_SIZES = (
    ("hal_plugin_gen31", (480, 640)),
    ("hal_plugin_gen3", (480, 640)),
    ("hal_plugin_gen41", (720, 1280)),
    ("hal_plugin_gen4", (720, 1280)),
    ("hal_plugin_imx636", (720, 1280)),
)


class Header(NamedTuple):
    """What the text header says: the decoder's encoding name and the sensor ``(H, W)`` if known."""

    encoding: str
    sensor_size: tuple[int, int] | None


def read(path: Path) -> np.ndarray:
    """All events of the file as a structured array (``t`` µs, ``x``, ``y``, ``p`` 0/1)."""
    header = read_header(path)
    return _checked(Wizard(encoding=header.encoding, fpath=path).read())


def chunks(path: Path, chunk_size: int) -> Iterator[np.ndarray]:
    """Consecutive blocks of at most ``chunk_size`` events, decoded a block at a time."""
    header = read_header(path)
    wizard = Wizard(encoding=header.encoding, fpath=path, chunk_size=min(chunk_size, _DECODER_BLOCK))
    return regroup((_checked(block) for block in wizard.read_chunk()), chunk_size)


def sensor_size(path: Path) -> tuple[int, int] | None:
    """``(H, W)`` from the header (module doc), or ``None`` when it does not say."""
    return read_header(path).sensor_size


def read_header(path: Path) -> Header:
    """Parse the ``% key value`` lines at the start of the file.

    Raises:
        ReaderError: the file ends inside its header, holds no event data, or names no encoding the
            decoder reads.
    """
    fields: dict[str, str] = {}
    with open(path, "rb") as file:
        while (line := file.readline(_MAX_HEADER_LINE)).startswith(b"%"):
            if not line.endswith(b"\n"):
                raise ReaderError("the file ends inside its text header (truncated)")
            key, _, value = line[1:].decode("ascii", errors="replace").strip().partition(" ")
            if key == "end":
                line = file.read(1)
                break
            fields.setdefault(key.lower(), value.strip())
        if not line:
            raise ReaderError("the file holds a header and no event data")
    return Header(_encoding(path, fields), _header_size(fields))


def _encoding(path: Path, fields: dict[str, str]) -> str:
    if path.suffix.lower() == ".dat":
        return "dat"
    name = _FORMAT_NAMES.get(fields.get("format", "").split(";")[0].strip().upper())
    name = name or _EVT_VERSIONS.get(fields.get("evt", ""))
    if name is None:
        found = fields.get("format") or fields.get("evt") or "none"
        raise ReaderError(
            f"the header names no event encoding the decoder reads (EVT 2.0 or 3.0), found {found!r}"
        )
    return name


def _header_size(fields: dict[str, str]) -> tuple[int, int] | None:
    try:
        if "geometry" in fields:
            width, height = fields["geometry"].lower().split("x")
            return int(height), int(width)
        options = dict(part.split("=", 1) for part in fields.get("format", "").split(";")[1:] if "=" in part)
        if "height" in options and "width" in options:
            return int(options["height"]), int(options["width"])
        if "height" in fields and "width" in fields:
            return int(fields["height"]), int(fields["width"])
    except ValueError:
        raise ReaderError(f"the header's sensor size is not numbers: {fields}") from None
    plugin = fields.get("plugin_name", "")
    return next((size for prefix, size in _PLUGIN_SIZES if plugin.startswith(prefix)), None)


def _checked(block) -> np.ndarray:
    # The decoder prints its complaint and returns None on data it cannot decode.
    if block is None:
        raise ReaderError("the decoder found no decodable events (empty or corrupt event data)")
    return block
