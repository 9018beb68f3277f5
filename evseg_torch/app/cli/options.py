"""What the commands share: the options accepted before or after any command, and argument types."""

from __future__ import annotations

import argparse
from pathlib import Path

from evseg_torch.errors import EvsegError

THREADS_HELP = (
    "CPU threads per process, torch's and OpenCV's (default 1: on shared CPUs more threads wait "
    "on each other)"
)


def common_options() -> argparse.ArgumentParser:
    """The parent parser of every command: ``--quiet`` and ``--threads``, set only when given there."""
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "--quiet", action="store_true", default=argparse.SUPPRESS, help="no progress bars or log lines"
    )
    common.add_argument("--threads", type=int, default=argparse.SUPPRESS, help=THREADS_HELP)
    return common


def check_counts(args, *names: str) -> None:
    """Counts given on the command line must be positive."""
    for name in names:
        value = getattr(args, name)
        if value is not None and value < 1:
            raise EvsegError(f"--{name.replace('_', '-')} must be at least 1, got {value}")


def add_device(parser: argparse.ArgumentParser) -> None:
    """Add ``--device`` (checked by :func:`device`)."""
    parser.add_argument(
        "--device", default="cpu", help="torch device of level two, e.g. cpu (default), cuda, cuda:1, mps"
    )


def device(name: str) -> str:
    """``name`` if torch has such a device here, else a one-line error."""
    import torch

    try:
        parsed = torch.device(name)
    except RuntimeError:
        raise EvsegError(f"--device {name}: not a torch device name (e.g. cpu, cuda, cuda:0)") from None
    if parsed.type == "cuda" and not torch.cuda.is_available():
        raise EvsegError(f"--device {name}: this torch ({torch.__version__}) sees no CUDA device")
    if parsed.type == "cuda" and (parsed.index or 0) >= torch.cuda.device_count():
        raise EvsegError(f"--device {name}: only {torch.cuda.device_count()} CUDA devices here")
    if parsed.type == "mps" and not torch.backends.mps.is_available():
        raise EvsegError(f"--device {name}: no MPS device here")
    if parsed.type not in ("cpu", "cuda", "mps"):
        raise EvsegError(f"--device {name}: only cpu, cuda and mps are supported")
    return name


def inputs_help() -> str:
    """The help of ``segment``'s INPUT: the formats and folder layouts the readers know."""
    from evseg_torch.io.dispatch import SUPPORTED_FOLDERS, SUPPORTED_SUFFIXES

    folders = "; ".join(SUPPORTED_FOLDERS)
    return f"event files ({' '.join(SUPPORTED_SUFFIXES)}) or sequence folders ({folders})"


def use_threads(threads: int) -> None:
    """``--threads``: this process's CPU threads (:func:`evseg_torch.app.threads.set_threads`)."""
    if threads < 1:
        raise EvsegError(f"--threads must be at least 1, got {threads}")
    from evseg_torch.app.threads import set_threads

    set_threads(threads)


def config_help() -> str:
    """The help of ``--config``: a file, or the name of a bundled config."""
    from evseg_torch.config import shipped_configs

    return f"YAML config, or a bundled config's name: {', '.join(shipped_configs())}"


def config_file(text: str) -> Path:
    """A ``--config`` value: a YAML file, or where no file has that name, a bundled config
    (:func:`~evseg_torch.config.bundled_config`), so that ``--config fast`` works wherever the package is
    installed. A name that is neither stays a path, which ``load_config`` reports as missing."""
    path = Path(text)
    from evseg_torch.config import bundled_config, shipped_configs

    if path.exists() or text.removesuffix(".yaml") not in shipped_configs():
        return path
    return bundled_config(text)


def sensor_size(text: str) -> tuple[int, int]:
    """A ``--sensor-size`` value, ``HxW``, as ``(H, W)``."""
    try:
        height, width = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"sensor size must be HxW, e.g. 180x240, got {text!r}") from None
    if height <= 0 or width <= 0:
        raise argparse.ArgumentTypeError(f"sensor size must be positive, got {text!r}")
    return height, width


def seed_range(text: str) -> list[int]:
    """Seeds given as ``0-19`` (both ends included) or ``1,2,5``."""
    try:
        if "-" in text:
            first, last = (int(v) for v in text.split("-"))
            return list(range(first, last + 1))
        return [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"seeds must look like 0-19 or 1,2,5, got {text!r}") from None
