"""Helpers shared by the subcommands.

- help: :class:`DefaultsHelpFormatter` (every option's help ends with its default) and
  :func:`with_defaults`;
- output: :func:`add_output_arguments` (``--no-progress``, ``--quiet``), :func:`show_progress`,
  :func:`command_output` (status lines and warnings through :mod:`logging`, written around the
  progress bars), :func:`check_writable` (an output path is checked before any work);
- option types: :func:`positive_int`, :func:`nonnegative_int`, :func:`solver_name`;
- option values: :func:`option_values` (options passed on as keywords of the same names);
- models: :func:`add_model_argument` (``--model``), :func:`resolve_model` (its value: a folder,
  ``demo``, or by default the shipped demo model), :func:`load_model` (a clear error for a
  truncated or malformed checkpoint) and :func:`add_cache_argument` (``--cache``);
- ``--device``: :func:`add_device_argument` and :func:`resolve_device`;
- ``--threads``: :func:`add_threads_argument` (every subcommand has it), :func:`command_threads`
  and :func:`image_workers` (the processes of a command over many images);
- ``--seed``: :func:`add_seed_argument`, with one default for every command (:data:`DEFAULT_SEED`).

The model configuration and inference options are in :mod:`poseflow.cli.options`.

The objects of a BOP dataset folder (the folder's check, loading, fingerprints, the object cache)
are library code: :mod:`poseflow.data.object_folder`.

Everything heavy (torch, the model) is imported inside the functions, so that registering the
subcommands stays cheap.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
import tempfile
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

__all__ = [
    "DEFAULT_SEED",
    "LOG",
    "DefaultsHelpFormatter",
    "add_cache_argument",
    "add_device_argument",
    "add_model_argument",
    "add_output_arguments",
    "add_seed_argument",
    "add_threads_argument",
    "check_writable",
    "command_output",
    "command_threads",
    "image_workers",
    "load_model",
    "nonnegative_int",
    "option_values",
    "positive_int",
    "resolve_device",
    "resolve_model",
    "show_progress",
    "solver_name",
    "with_defaults",
]

#: The logger of the command line's status lines (stderr; silenced by ``--quiet``).
LOG = logging.getLogger("poseflow.cli")

# ------------------------------------------------------------------------------ help


class DefaultsHelpFormatter(argparse.HelpFormatter):
    """A help formatter that ends each option's help with its default: ``(default: X)``.

    Not where the help already speaks of a default (a default of None that means something is
    said in words there), nor for a default of None, False, ``[]`` or ``SUPPRESS`` (the option is
    off or unset without it). A list is shown as typed (``3 6``), True as ``on``.
    """

    def _get_help_string(self, action: argparse.Action) -> str:
        text, value = action.help or "", action.default
        unset = value is None or value is False or value is argparse.SUPPRESS or value == []
        if unset or "default" in text:
            return text
        if value is True:
            shown = "on"
        elif isinstance(value, list):
            shown = " ".join(map(str, value))
        else:
            shown = str(value)
        return f"{text} (default: {shown.replace('%', '%%')})"


def with_defaults(formatter: type[argparse.HelpFormatter]) -> type[argparse.HelpFormatter]:
    """``formatter`` (e.g. ``argparse.RawDescriptionHelpFormatter``) with the defaults shown.

    Example:
        >>> parser = argparse.ArgumentParser(formatter_class=with_defaults(argparse.HelpFormatter))
        >>> _ = parser.add_argument("--steps", type=int, default=10, help="optimiser steps")
        >>> "optimiser steps (default: 10)" in parser.format_help()
        True
    """
    if issubclass(formatter, DefaultsHelpFormatter):
        return formatter
    return type(f"{formatter.__name__}WithDefaults", (DefaultsHelpFormatter, formatter), {})


# ------------------------------------------------------------------------------ output


def add_output_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--no-progress`` and ``-q/--quiet`` to ``parser`` (every subcommand has both)."""
    group = parser.add_argument_group("output")
    group.add_argument(
        "--no-progress",
        action="store_true",
        help="hide progress (a bar on a terminal, a status line every 30 s in a log)",
    )
    group.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        help="print only warnings, errors and the results (implies --no-progress)",
    )


def show_progress(args: argparse.Namespace) -> bool:
    """Whether to show progress: not asked away with ``--no-progress`` or ``--quiet``.

    On a terminal a bar; redirected to a file or a CI log, a plain status line at least every
    30 s (:mod:`poseflow._progress`).
    """
    return not (getattr(args, "no_progress", False) or getattr(args, "quiet", False))


class _BarSafeHandler(logging.Handler):
    """Writes records to stderr through ``tqdm.write``, so that open progress bars stay intact."""

    def emit(self, record: logging.LogRecord) -> None:
        from tqdm.auto import tqdm

        try:
            tqdm.write(self.format(record), file=sys.stderr)
        except Exception:
            self.handleError(record)


class _Formatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        text = record.getMessage()
        if record.levelno >= logging.ERROR:
            return f"error: {text}"
        if record.levelno >= logging.WARNING:
            return f"warning: {text}"
        return text


@contextlib.contextmanager
def command_output(args: argparse.Namespace) -> Iterator[None]:
    """Route the status lines of ``poseflow``'s loggers to stderr for a run; format warnings.

    Status lines (level INFO of the ``poseflow`` loggers) and logged warnings are written as one
    line each, through ``tqdm.write`` so that they do not break a progress bar; ``--quiet``
    keeps the warnings only. Python warnings are printed as one ``warning: ...`` line rather
    than with the file and source line of their origin. Everything is restored on exit; a
    command run inside another keeps the outer one's set-up.

    Args:
        args: the parsed arguments (``quiet`` is read).
    """
    logger = logging.getLogger("poseflow")
    if any(isinstance(h, _BarSafeHandler) for h in logger.handlers):
        yield  # a command run by another (``poseflow onboard``): its output is set up
        return
    handler = _BarSafeHandler()
    handler.setFormatter(_Formatter())
    saved = (logger.level, logger.propagate, warnings.formatwarning)
    logger.addHandler(handler)
    logger.setLevel(logging.WARNING if getattr(args, "quiet", False) else logging.INFO)
    logger.propagate = False

    def one_line(message: Any, category: Any, filename: str, lineno: int, line: Any = None) -> str:
        return f"warning: {message}\n"

    warnings.formatwarning = one_line
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(saved[0])
        logger.propagate = saved[1]
        warnings.formatwarning = saved[2]


def check_writable(path: str | Path, *, flag: str = "--out", folder: bool = False) -> Path:
    """Check, before any work, that an output file (or folder) can be written.

    The parent folders are created; a file is created and removed in the folder that will hold
    the output, so a read-only place, a path under a file or a full disk fail now rather than
    after hours of work.

    Args:
        path: the output file, or folder when ``folder``.
        flag: the option that named it, for the message.
        folder: ``path`` is a folder to write into.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        NotWritableError: the path cannot be written.

    Example:
        >>> d = Path(tempfile.mkdtemp())
        >>> check_writable(d / "sub" / "r.csv").parent.is_dir()
        True
    """
    from poseflow.errors import NotWritableError

    path = Path(path)
    if not folder and path.is_dir():
        raise NotWritableError(f"{flag} {path} is a folder; give the path of a file")
    where = path if folder else path.parent
    try:
        where.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=where, prefix=".poseflow-write-check-"):
            pass
    except OSError as exc:
        reason = exc.strerror or str(exc)
        raise NotWritableError(f"{flag} {path}: cannot write in {where} ({reason})") from None
    if not folder and path.exists() and not os.access(path, os.W_OK):
        raise NotWritableError(f"{flag} {path}: the file exists and is read-only")
    return path


# ------------------------------------------------------------------------------ option types


def _int_at_least(text: str, minimum: int) -> int:
    """``text`` as an integer of at least ``minimum``, or an ``ArgumentTypeError``."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < minimum:
        raise argparse.ArgumentTypeError(f"must be at least {minimum}, got {value}")
    return value


def positive_int(text: str) -> int:
    """An ``argparse`` type: an integer of at least 1.

    Example:
        >>> positive_int("3")
        3
    """
    return _int_at_least(text, 1)


def nonnegative_int(text: str) -> int:
    """An ``argparse`` type: an integer of at least 0.

    Example:
        >>> nonnegative_int("0")
        0
    """
    return _int_at_least(text, 0)


def solver_name(text: str) -> str:
    """An ``argparse`` type: the name of an ODE solver of :data:`poseflow.flows.SAMPLERS`.

    Example:
        >>> solver_name("heun")
        'heun'
    """
    from poseflow.flows import SAMPLERS

    if text not in SAMPLERS:
        raise argparse.ArgumentTypeError(f"{text!r} is not one of {', '.join(SAMPLERS)}")
    return text


def option_values(args: argparse.Namespace, *names: str) -> dict[str, Any]:
    """The values of the options ``names`` (their ``dest``), to pass on as keywords of those names.

    Example:
        >>> option_values(argparse.Namespace(seed=3, split="test", quiet=False), "split", "seed")
        {'split': 'test', 'seed': 3}
    """
    return {name: getattr(args, name) for name in names}


# ------------------------------------------------------------------------------ models


def add_model_argument(
    parser: Any, *, default: str | None = None, without: str = "the demo model, with a note"
) -> None:
    """Add ``--model MODEL_DIR`` (read by :func:`resolve_model`) to a parser or argument group.

    Args:
        parser: a parser or an argument group.
        default: the value without the option (None: :func:`resolve_model` notes the demo model).
        without: what the command uses without the option, for the help.
    """
    parser.add_argument(
        "--model",
        default=default,
        metavar="MODEL_DIR",
        help="FunFlow6D model folder written by `poseflow train`, or demo for the one shipped "
        f"with poseflow (default: {without})",
    )


def add_cache_argument(parser: Any, *, without: str) -> None:
    """Add ``--cache DIR``, the folder of the prepared objects (``objects/``), to a parser.

    Args:
        parser: a parser or an argument group.
        without: the folder used without the option, for the help.
    """
    parser.add_argument(
        "--cache",
        default=None,
        metavar="DIR",
        help=f"folder holding the prepared objects (objects/) (default: {without})",
    )


def resolve_model(value: str | None) -> Path:
    """The model folder that ``--model VALUE`` names.

    ``demo`` and a missing option name the demo model shipped with poseflow (trained on its
    three demo objects only); without the option a note says so.

    Args:
        value: the option's value, or None when it was not given.

    Returns:
        The folder.

    Example:
        >>> resolve_model("demo").name
        'demo_model'
        >>> resolve_model("runs/x/model")
        PosixPath('runs/x/model')
    """
    from poseflow.assets import DEMO_CHECKPOINT

    if value is None:
        LOG.info(
            "note: no --model given: using the demo model shipped with poseflow (trained on its "
            "three demo objects only); pass --model MODEL_DIR for a model of your objects"
        )
        return Path(DEMO_CHECKPOINT)
    if value == "demo":
        return Path(DEMO_CHECKPOINT)
    return Path(value)


def load_model(
    folder: str | Path, *, device: Any = "cpu", inference: dict[str, Any] | None = None
) -> Any:
    """Load a FunFlow6D model folder, with errors that say what is wrong and what to do.

    Args:
        folder: the model folder (``config.json`` + ``model.safetensors``).
        device: where to put the model.
        inference: inference settings to change
            (:func:`~poseflow.cli.options.inference_changes`), checked here,
            before any work (:meth:`~poseflow.models.FunFlow6DConfig.with_inference`).

    Returns:
        The :class:`~poseflow.models.FunFlow6D`.

    Raises:
        MissingWeightsError: the folder holds no checkpoint.
        CheckpointError: ``config.json`` is not valid JSON or holds a value of the wrong type,
            or ``model.safetensors`` is truncated or corrupt.
        ValueRangeError: ``inference`` changes a setting that is not an inference setting, or to
            a value of the wrong kind.
    """
    from poseflow.errors import MissingWeightsError, ValueRangeError
    from poseflow.models import FunFlow6D
    from poseflow.models.checkpoint import is_checkpoint

    folder = Path(folder)
    if not is_checkpoint(folder):
        raise MissingWeightsError(
            f"{folder} holds no FunFlow6D checkpoint (config.json + model.safetensors); train "
            "one with `poseflow train`, or pass --model demo for the shipped demo model"
        )
    model = FunFlow6D.load(folder, device=device)
    if inference is not None:
        try:
            model.config = model.config.with_inference(inference)
        except TypeError as exc:  # a value of the wrong kind reaching the dataclass
            raise ValueRangeError(f"invalid --set: {exc}") from None
    return model


# ------------------------------------------------------------------------------ device


def add_device_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--device`` (``auto``, ``cpu``, ``cuda``, ``cuda:1``, ...) to ``parser``."""
    parser.add_argument(
        "--device",
        default="auto",
        help="torch device: auto (this process's GPU when there is one, else cpu), cpu, cuda, "
        "cuda:N (default: auto)",
    )


def resolve_device(name: str) -> Any:
    """The ``torch.device`` that ``--device NAME`` asks for.

    ``auto`` and a bare ``cuda`` pick the GPU of this process (``cuda:LOCAL_RANK`` under
    ``torchrun``); ``auto`` falls back to the CPU.

    Args:
        name: the option's value.

    Returns:
        The ``torch.device``.

    Raises:
        UsageError: a malformed name, or a GPU asked for where CUDA is not available.

    Example:
        >>> resolve_device("cpu")
        device(type='cpu')
    """
    import torch

    from poseflow.errors import UsageError

    local = int(os.environ.get("LOCAL_RANK", "0") or 0)
    if name == "auto":
        return torch.device(f"cuda:{local}" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, ValueError) as exc:
        raise UsageError(f"--device {name!r} is not a torch device ({exc})") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise UsageError(
                f"--device {name}: CUDA is not available here; use --device cpu (or auto)"
            )
        if device.index is None:
            device = torch.device(f"cuda:{local}")
        if device.index >= torch.cuda.device_count():
            raise UsageError(
                f"--device {device}: only {torch.cuda.device_count()} CUDA device(s) here"
            )
    return device


# ------------------------------------------------------------------------------ threads


def add_threads_argument(parser: argparse.ArgumentParser, *, nested: bool = False) -> None:
    """Add ``--threads N`` to ``parser`` (every subcommand has it; :func:`command_threads` uses it).

    Args:
        parser: a subcommand's parser.
        nested: ``parser`` is a subcommand of a subcommand (``demo registration``): its option
            then only overrides the parent's when given.
    """
    group = parser.add_argument_group("threads")
    group.add_argument(
        "--threads",
        type=positive_int,
        default=argparse.SUPPRESS if nested else None,
        metavar="N",
        help="CPU threads of every pool poseflow runs work in: torch, numba, BLAS/OpenMP and "
        "Open3D's ray casting; predict and demo estimate their images in N processes of one "
        "thread each instead (default: $OMP_NUM_THREADS if set, else 1)",
    )


@contextlib.contextmanager
def command_threads(args: argparse.Namespace) -> Iterator[int]:
    """Run a command on ``--threads`` threads, else :func:`~poseflow._threads.default_num_threads`.

    Sets every pool through :func:`poseflow.num_threads` and restores them on exit, so that a
    command run in-process (tests, benchmarks) leaves its caller's settings as they were.

    Yields:
        The number of threads.

    Raises:
        ValueRangeError: no ``--threads`` and ``OMP_NUM_THREADS`` is not a positive integer.
    """
    from poseflow import num_threads
    from poseflow._threads import default_num_threads

    threads = getattr(args, "threads", None)
    threads = default_num_threads() if threads is None else threads
    with num_threads(threads):
        yield threads


@contextlib.contextmanager
def image_workers(device: Any) -> Iterator[int]:
    """The worker processes of a command over many images, the command's thread count on the CPU.

    Whole images in processes of one thread each (``poseflow._workers.map_forked``)
    use a few cores better than threads within an image, and stay as fast under a competing
    load, where threads wait on each other; so with more than one worker the rest of the
    command (loading, rendering, scoring) runs on one thread too. On a GPU: one process, the
    command's threads unchanged.

    Yields:
        The number of worker processes.
    """
    import torch

    from poseflow import get_num_threads, num_threads

    workers = get_num_threads() if torch.device(device).type == "cpu" else 1
    if workers == 1:
        yield 1
        return
    with num_threads(1):
        yield workers


# ------------------------------------------------------------------------------ seed

#: The default ``--seed`` of every command (but ``bench``'s, whose generated split is that of its
#: recorded figures: :data:`poseflow.cli.bench.BENCH_SEED`).
DEFAULT_SEED = 0


def add_seed_argument(parser: Any, *, draws: str, default: int = DEFAULT_SEED) -> None:
    """Add ``--seed N`` to a parser or argument group.

    Args:
        parser: a parser or an argument group.
        draws: what the seed seeds, for the help (e.g. ``"the noise, sampling and RANSAC"``).
        default: the seed without the option.
    """
    parser.add_argument(
        "--seed", type=int, default=default, help=f"seed of {draws} (default: {default})"
    )
