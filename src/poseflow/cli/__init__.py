"""The ``poseflow`` command line.

Each subcommand lives in its own module that exposes ``add_parser(subparsers)``; the module is
imported only when listed here, and its heavy imports happen inside its ``run`` function so that
``poseflow --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from poseflow import __version__
from poseflow.errors import PoseflowError

__all__ = ["build_parser", "main"]

#: Subcommand modules under ``poseflow.cli``, in the order ``--help`` lists them.
SUBCOMMANDS = ("demo", "synth", "prepare", "train", "predict", "eval", "bench")


def build_parser() -> argparse.ArgumentParser:
    """Build the argument parser with every subcommand registered."""
    parser = argparse.ArgumentParser(
        prog="poseflow",
        description="6D object pose estimation from RGBD images (FunFlow6D) and its parts.",
    )
    parser.add_argument("--version", action="version", version=f"poseflow {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in SUBCOMMANDS:
        importlib.import_module(f"poseflow.cli.{name}").add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    try:
        return int(args.run(args) or 0)
    except PoseflowError as exc:
        print(f"poseflow {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
