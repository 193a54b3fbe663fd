"""The ``flightkit`` command.

Each subcommand lives in its own module under ``flightkit/cli/`` and exposes
``register(subparsers)``, which adds its parser and sets ``func`` to a ``run(args) -> int``.
Commands stay thin: parse, load config, call a library function, map errors to exit codes
(0 ok, 1 runtime error, 2 usage or config error). Heavy imports happen inside ``run``.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
from collections.abc import Sequence

from flightkit import __version__

# flightkit's numerics are small products (poses, N x 3 point sets), where OpenBLAS's worker threads
# cost more than they give: the simulated camera's (76800 x 3) @ (3 x 3) ray rotation took 5-16 ms
# with two threads on a busy 2-core machine and 0.3 ms with one (same result). Set before numpy is
# imported (heavy imports happen inside each command's run); a value the user sets wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
from flightkit.errors import ConfigError, FlightkitError

__all__ = ["COMMAND_MODULES", "build_parser", "main"]

logger = logging.getLogger(__name__)

# Modules under flightkit.cli that provide subcommands, in help order.
COMMAND_MODULES = (
    "demo",
    "sim",
    "vehicle",
    "fly",
    "plot",
    "record",
    "capture",
    "export",
    "vo",
    "calibrate",
    "report",
    "mapserver",
)

EXIT_OK = 0
EXIT_RUNTIME = 1
EXIT_USAGE = 2


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="flightkit",
        description="Flight scripts, capture and onboard estimation for motion-capture drone labs.",
    )
    parser.add_argument("--version", action="version", version=f"flightkit {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks and debug logs")
    parser.add_argument("-v", "--verbose", action="store_true", help="show info logs")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(f"flightkit.cli.{name}").register(sub)
    return parser


def _configure_logging(debug: bool, verbose: bool) -> None:
    level = logging.DEBUG if debug else logging.INFO if verbose else logging.WARNING
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns the exit code (so tests can call it in-process)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    _configure_logging(args.debug, args.verbose)
    func = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return EXIT_USAGE
    try:
        return int(func(args) or 0)
    except ConfigError as exc:
        if args.debug:
            raise
        print(f"flightkit: config error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except FlightkitError as exc:
        if args.debug:
            raise
        print(f"flightkit: error: {exc}", file=sys.stderr)
        return EXIT_RUNTIME
    except KeyboardInterrupt:
        print("flightkit: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
