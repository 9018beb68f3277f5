"""The ``evseg`` entry point: the parser, assembled from one module per command, and :func:`main`."""

from __future__ import annotations

import argparse
import logging
import signal
import sys

from evseg_torch.app.cli import (
    demo,
    evaluate,
    segment,
    simulate,
)
from evseg_torch.app.cli.options import THREADS_HELP, common_options, use_threads
from evseg_torch.errors import EvsegError
from evseg_torch.version import __version__


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``evseg``; returns the exit status.

    0 ok; 1 some inputs failed (``--keep-going``); 2 our errors; 130 stopped by SIGINT (Ctrl-C), 143
    by SIGTERM (128 + the signal's number, as shells report it).
    """
    from evseg_torch.app.jobs import one_line
    from evseg_torch.app.signals import Stopped, stop_on_signals, stopped_by

    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO, format="%(message)s")
    try:
        with stop_on_signals():
            use_threads(args.threads)
            try:
                return args.run(args) or 0
            except Exception as err:
                # A signal that lands inside an import (or other code that wraps what it catches)
                # arrives as that code's own error, caused by our Stopped.
                stop = stopped_by(err)
                if stop is None:
                    raise
                raise stop from err
    except (EvsegError, OSError) as err:
        print(f"evseg: error: {one_line(err)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as err:
        signum = err.signum if isinstance(err, Stopped) else signal.SIGINT
        resumable = " (resume with --resume)" if getattr(args, "run", None) is segment.run else ""
        print(f"evseg: stopped by {signal.Signals(signum).name}{resumable}", file=sys.stderr)
        return 128 + signum


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``evseg`` and its commands; each command's ``run(args)`` is ``args.run``."""
    parser = argparse.ArgumentParser(
        prog="evseg",
        description="Event-camera motion segmentation by cascaded two-level multi-model fitting (IROS 2021).",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    common = common_options()
    # Accepted before or after the command alike: the commands' parsers set them only when given there.
    parser.add_argument("--quiet", action="store_true", help="no progress bars or log lines")
    parser.add_argument("--threads", type=int, default=1, help=THREADS_HELP)
    commands = parser.add_subparsers(title="commands", required=True, metavar="COMMAND")
    for command in (segment, demo, simulate, evaluate):
        command.add_parser(commands, common)
    return parser
