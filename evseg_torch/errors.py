"""Exception types of evseg_torch.

Every error that bad input can cause is one of these, with a message that names the problem, so that
callers (and the CLI) can catch :class:`EvsegError` and report one clear line.
"""


class EvsegError(Exception):
    """Base class of every error raised on purpose by evseg_torch."""


class EventFormatError(EvsegError, ValueError):
    """Events have the wrong shape, dtype, values or order."""


class ConfigError(EvsegError, ValueError):
    """A configuration file or keyword names an unknown key or holds an invalid value."""


class ReaderError(EvsegError, OSError):
    """A file is missing, of an unknown format, corrupt or truncated."""


class ModelError(EvsegError, ValueError):
    """Motion-model parameters or correspondences are malformed."""


class ShapeError(EvsegError, ValueError):
    """A tensor or array argument has the wrong shape."""


class ResultsError(EvsegError, ValueError):
    """A folder is not a readable ``evseg segment`` result (missing, unfinished, newer schema, corrupt)."""
