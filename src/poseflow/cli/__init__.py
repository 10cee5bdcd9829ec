"""The ``poseflow`` command line.

Each subcommand lives in its own module, imported only when listed in :data:`SUBCOMMANDS`, which
defines ``HELP`` (its line in ``poseflow --help``), ``DESCRIPTION`` (its own ``--help``; kept as
written where the module sets ``FORMATTER = argparse.RawDescriptionHelpFormatter``), optionally
``EPILOG``, ``add_arguments(parser)`` (its options) and ``run(args)``; :func:`add_command`
registers it. The heavy imports happen inside ``run`` so that ``poseflow --help`` stays fast.

Exit codes: 0 on success, 1 when the run fails (a :class:`~poseflow.errors.PoseflowError`: a
missing or malformed file, implausible units, a failed write), 2 for usage errors (argparse's, a
:class:`~poseflow.errors.UsageError`, or a plain ``ValueRangeError``: an argument's value out of
its range) and when no subcommand is given. Every subcommand takes ``--no-progress`` and
``--quiet`` (:func:`~poseflow.cli.common.add_output_arguments`) and ``--threads N``
(:func:`~poseflow.cli.common.add_threads_argument`), set through :func:`poseflow.num_threads`
for the whole command. Status lines and warnings go through
:mod:`logging` to stderr, written around the progress bars; results go to stdout.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Iterator, Sequence

from poseflow import __version__
from poseflow.errors import PoseflowError, UsageError, ValueRangeError

__all__ = [
    "EXIT_FAILED",
    "EXIT_USAGE",
    "add_command",
    "build_parser",
    "is_usage_error",
    "main",
    "subcommand_parsers",
]

#: Subcommands (modules of ``poseflow.cli``, ``-`` for ``_``) in the order ``--help`` lists them.
SUBCOMMANDS = (
    "demo",
    "estimate",
    "onboard",
    "calibrate",
    "synth",
    "prepare",
    "train-surface",
    "train",
    "train-detector",
    "detect",
    "predict",
    "eval",
    "view",
    "bench",
)

#: Exit code of a run that failed.
EXIT_FAILED = 1

#: Exit code of a usage error (as argparse's own).
EXIT_USAGE = 2


def subcommand_parsers(parser: argparse.ArgumentParser) -> Iterator[argparse.ArgumentParser]:
    """Every subcommand's parser under ``parser``, subcommands of subcommands included."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for command in action.choices.values():
                yield command
                yield from subcommand_parsers(command)


def add_command(subparsers: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    """Register the subcommand of module ``poseflow.cli.NAME`` on ``subparsers``.

    The module of a hyphenated name has underscores (``train-detector``: ``train_detector``).

    Its parser takes the module's ``HELP``, ``DESCRIPTION``, ``EPILOG`` and ``FORMATTER`` (the
    last two optional), the options of its ``add_arguments``, then ``--no-progress`` and
    ``--quiet``; the parsed arguments' ``run`` is the module's ``run``. Its help, and that of its
    own subcommands, ends each option's text with the option's default
    (:func:`~poseflow.cli.common.with_defaults`).

    Returns:
        The subcommand's parser.
    """
    from poseflow.cli.common import add_output_arguments, with_defaults

    module = importlib.import_module(f"poseflow.cli.{name.replace('-', '_')}")
    parser = subparsers.add_parser(
        name,
        help=module.HELP,
        description=module.DESCRIPTION,
        epilog=getattr(module, "EPILOG", None),
        formatter_class=getattr(module, "FORMATTER", argparse.HelpFormatter),
    )
    module.add_arguments(parser)
    add_output_arguments(parser)
    for command in (parser, *subcommand_parsers(parser)):
        command.formatter_class = with_defaults(command.formatter_class)
    parser.set_defaults(run=module.run)
    return parser


def build_parser() -> argparse.ArgumentParser:
    """Build the argument parser with every subcommand registered (each with ``--threads``)."""
    from poseflow.cli.common import add_threads_argument

    parser = argparse.ArgumentParser(
        prog="poseflow",
        description="6D object pose estimation from RGBD images (FunFlow6D) and its parts.",
        epilog="Run `poseflow COMMAND --help` for the options of a command.",
    )
    parser.add_argument("--version", action="version", version=f"poseflow {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in SUBCOMMANDS:
        add_command(sub, name)
    for command in sub.choices.values():
        command.set_defaults(parser=command)  # for the usage line of a usage error
        add_threads_argument(command)
        for nested in subcommand_parsers(command):
            add_threads_argument(nested, nested=True)
    return parser


def is_usage_error(exc: BaseException) -> bool:
    """Whether ``exc`` is a usage error (exit code 2).

    A :class:`UsageError`, or a plain ``ValueRangeError`` (an argument outside its range, such
    as an unknown solver name); its subclasses that describe data (``UnitsError``,
    ``ResultsFormatError``) and every other error are failed runs.

    Example:
        >>> is_usage_error(UsageError("--images must be at least 1"))
        True
        >>> is_usage_error(PoseflowError("the file is truncated"))
        False
    """
    return isinstance(exc, UsageError) or type(exc) is ValueRangeError


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the process exit code (see the module's docstring)."""
    from poseflow.cli.common import command_output, command_threads

    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help(sys.stderr)
        return EXIT_USAGE
    with command_output(args):
        try:
            with command_threads(args):
                return int(args.run(args) or 0)
        except (PoseflowError, OSError) as exc:
            usage = is_usage_error(exc)
            if usage:
                args.parser.print_usage(sys.stderr)
            print(f"poseflow {args.command}: error: {exc}", file=sys.stderr)
            return EXIT_USAGE if usage else EXIT_FAILED
        except KeyboardInterrupt:
            print(f"poseflow {args.command}: interrupted", file=sys.stderr)
            return 130


if __name__ == "__main__":
    sys.exit(main())
