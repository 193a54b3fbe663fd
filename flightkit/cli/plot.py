"""``flightkit plot LOG``: PNG plots of a flight log (top view, tracking error against time)."""

from __future__ import annotations

import argparse
from typing import Any

__all__ = ["register", "run"]


def register(subparsers: Any) -> None:
    p = subparsers.add_parser("plot", help="plot a flight log (top view and tracking error, PNG)")
    p.add_argument("log", help="flight log CSV written by 'flightkit fly'")
    p.add_argument("--out", default=None, help="folder for the PNG files (default: next to the log)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from flightkit.apps.flight import plot_log

    for p in plot_log(args.log, args.out):
        print(p)
    return 0
