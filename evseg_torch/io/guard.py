"""One place that turns whatever a file-reading library raises into one of our exception types.

Every public reader runs inside :func:`reading`, so a caller sees a :class:`ReaderError` (or, for events
that parse but are out of order or out of range, an :class:`EventFormatError`) whose one-line message
starts with the file's path, never a raw traceback from NumPy, h5py, zipfile or the aedat decoder.
"""

from __future__ import annotations

import pickle
import tokenize
import zipfile
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from evseg_torch.errors import EvsegError, ReaderError

# What NumPy, h5py, zipfile, zlib, pickle and the Rust aedat decoder raise on a missing, truncated or
# corrupt file; all of it means "this file cannot be read" to our callers.
_LIBRARY_ERRORS = (
    OSError,
    ValueError,
    EOFError,
    KeyError,
    RuntimeError,
    zipfile.BadZipFile,
    tokenize.TokenError,  # numpy parses .npy headers with the tokenize module
    zlib.error,
    pickle.UnpicklingError,
)


def existing_file(path) -> Path:
    """Return ``path`` as a :class:`~pathlib.Path`, or raise :class:`ReaderError` if it is not a file."""
    path = Path(path)
    if not path.exists():
        raise ReaderError(f"{path}: no such file")
    if not path.is_file():
        raise ReaderError(f"{path}: not a regular file")
    return path


@contextmanager
def reading(path: Path, what: str) -> Iterator[None]:
    """Prefix ``path`` to our own errors and convert library errors to :class:`ReaderError`.

    Args:
        path: the file being read; it starts every message.
        what: the kind of file, e.g. ``"HDF5 events file"``, used in converted messages.
    """
    try:
        yield
    except EvsegError as err:
        raise type(err)(f"{path}: {_one_line(err)}") from None
    except _LIBRARY_ERRORS as err:
        raise ReaderError(f"{path}: cannot read {what}: {type(err).__name__}: {_one_line(err)}") from None


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split()) or "no details"
