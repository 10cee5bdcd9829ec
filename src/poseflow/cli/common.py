"""Helpers shared by the subcommands.

- output: :func:`add_output_arguments` (``--no-progress``, ``--quiet``), :func:`show_progress`,
  :func:`command_output` (status lines and warnings through :mod:`logging`, written around the
  progress bars), :func:`check_writable` (an output path is checked before any work);
- option types: :func:`positive_int`, :func:`nonnegative_int`, :func:`solver_name`;
- models: :func:`add_model_argument` (``--model``), :func:`resolve_model` (its value: a folder,
  ``demo``, or by default the shipped demo model) and :func:`load_model` (a clear error for a
  truncated or malformed checkpoint);
- ``--device``: :func:`add_device_argument` and :func:`resolve_device`;
- ``--threads``: :func:`add_threads_argument` (every subcommand has it) and :func:`command_threads`;
- ``--seed``: :func:`add_seed_argument`, with one default for every command (:data:`DEFAULT_SEED`);
- inference: :func:`add_inference_arguments` (``--hypotheses``, ``--steps``, ``--solver``,
  ``--verify/--no-verify``, ``--set``) and :func:`inference_changes`, their one check;
- the model configuration: :func:`add_config_arguments` registers ``--config`` (a JSON file of
  :class:`~poseflow.models.FunFlow6DConfig` fields), ``--preset`` and a few common fields as
  flags, and ``--set KEY=VALUE`` for any field; :func:`build_config` turns them into a config.

The objects of a BOP dataset folder (the folder's check, loading, fingerprints, the object cache)
are library code: :mod:`poseflow.data.object_folder`.

Everything heavy (torch, the model) is imported inside the functions, so that registering the
subcommands stays cheap.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import sys
import tempfile
import warnings
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

__all__ = [
    "CONFIG_FLAGS",
    "DEFAULT_SEED",
    "LOG",
    "add_config_arguments",
    "add_device_argument",
    "add_inference_arguments",
    "add_model_argument",
    "add_output_arguments",
    "add_seed_argument",
    "add_threads_argument",
    "build_config",
    "check_writable",
    "command_output",
    "command_threads",
    "config_requested",
    "inference_changes",
    "load_model",
    "nonnegative_int",
    "parse_set",
    "positive_int",
    "resolve_device",
    "resolve_model",
    "show_progress",
    "solver_name",
]

#: The logger of the command line's status lines (stderr; silenced by ``--quiet``).
LOG = logging.getLogger("poseflow.cli")

#: ``--flag`` name -> :class:`~poseflow.models.FunFlow6DConfig` field set by it.
CONFIG_FLAGS: dict[str, str] = {
    "preset": "dit_preset",
    "num_points": "num_points",
    "geometric_encoder": "geometric_encoder",
    "appearance_encoder": "appearance_encoder",
    "reducer": "reducer",
    "fusion": "fusion",
    "crop_size": "crop_size",
    "query_views": "query_views",
}


# ------------------------------------------------------------------------------ output


def add_output_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--no-progress`` and ``-q/--quiet`` to ``parser`` (every subcommand has both)."""
    group = parser.add_argument_group("output")
    group.add_argument(
        "--no-progress",
        action="store_true",
        help="hide the progress bars (they are shown only when stderr is a terminal)",
    )
    group.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        help="print only warnings, errors and the results (implies --no-progress)",
    )


def show_progress(args: argparse.Namespace) -> bool:
    """Whether to draw progress bars: not asked away and stderr is a terminal.

    Redirected to a file or a CI log, a bar is a stream of carriage returns; the status lines of
    :data:`LOG` say how far a run got instead.
    """
    if getattr(args, "no_progress", False) or getattr(args, "quiet", False):
        return False
    return sys.stderr.isatty()


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
    than with the file and source line of their origin. Everything is restored on exit.

    Args:
        args: the parsed arguments (``quiet`` is read).
    """
    logger = logging.getLogger("poseflow")
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
        inference: inference settings to change (:func:`inference_changes`), checked here,
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
        "Open3D's ray casting (default: $OMP_NUM_THREADS if set, else 1; more threads are "
        "faster only on cores that no other process is using)",
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


# ------------------------------------------------------------------------------ configuration


def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--config``, ``--preset``, the common field flags and ``--set`` to ``parser``."""
    group = parser.add_argument_group(
        "model configuration",
        "Start from --config (a recipe name or a JSON file of FunFlow6DConfig fields; default: "
        "the offline defaults FPFH + dense SIFT + PCA, gated fusion, small DiT), then apply the "
        "flags below and every --set in order.",
    )
    group.add_argument(
        "--config",
        type=Path,
        default=None,
        metavar="NAME|JSON",
        help="a recipe (demo_small, learned_small) or a FunFlow6DConfig JSON file",
    )
    group.add_argument(
        "--preset", default=None, help="DiT preset: paper, small or tiny (dit_preset)"
    )
    group.add_argument("--num-points", type=int, default=None, help="points per cloud N")
    group.add_argument(
        "--geometric-encoder", default=None, help="fpfh, gedi:PATH or none (geometric_encoder)"
    )
    group.add_argument(
        "--appearance-encoder",
        default=None,
        help="dsift, dinov2:NAME_OR_PATH or none (appearance_encoder)",
    )
    group.add_argument("--reducer", default=None, help="umap, pca or identity")
    group.add_argument("--fusion", default=None, help="gated, cross, concat_mlp or sum")
    group.add_argument("--crop-size", type=int, default=None, help="appearance crop side, px")
    group.add_argument("--query-views", type=int, default=None, help="views rendered per object")
    add_set_argument(
        group,
        "any config field, VALUE read as JSON when it parses; a dotted KEY or a JSON object "
        "changes fields of a nested part and keeps the others (e.g. --set steps=10 --set "
        "net.fusion_heads=2 --set icp_distances=[]); repeatable",
    )


def add_set_argument(parser: Any, help: str) -> None:
    """Add the repeatable ``--set KEY=VALUE`` option, stored in ``set_fields``.

    Args:
        parser: a parser or an argument group.
        help: what the option changes in this command (:func:`parse_set` reads the items).
    """
    parser.add_argument(
        "--set", dest="set_fields", action="append", default=[], metavar="KEY=VALUE", help=help
    )


def parse_set(items: Iterable[str]) -> dict[str, Any]:
    """Parse ``--set KEY=VALUE`` items; a VALUE that is valid JSON is decoded, else kept a string.

    Raises:
        UsageError: an item without ``=`` or with an empty key.

    Example:
        >>> parse_set(["steps=10", "fusion=sum", 'net={"fusion_heads": 2}'])
        {'steps': 10, 'fusion': 'sum', 'net': {'fusion_heads': 2}}
    """
    from poseflow.errors import UsageError

    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise UsageError(f"--set takes KEY=VALUE, got {item!r}")
        try:
            out[key] = json.loads(raw)
        except json.JSONDecodeError:
            out[key] = raw
    return out


def config_requested(args: argparse.Namespace) -> bool:
    """Whether the command line names any part of the configuration."""
    flags = any(getattr(args, f, None) is not None for f in CONFIG_FLAGS)
    return args.config is not None or flags or bool(args.set_fields)


def build_config(args: argparse.Namespace) -> Any:
    """The :class:`~poseflow.models.FunFlow6DConfig` described by the configuration options.

    Args:
        args: parsed arguments of a parser given :func:`add_config_arguments`.

    Returns:
        The validated configuration.

    Raises:
        MissingFileError: ``--config`` names neither a recipe nor a file.
        UsageError: the file is not valid JSON, or a field name or value is invalid.
    """
    from poseflow.errors import MissingFileError, UsageError, ValueRangeError
    from poseflow.models import FunFlow6DConfig, apply_overrides

    try:
        config = FunFlow6DConfig() if args.config is None else FunFlow6DConfig.load(args.config)
    except MissingFileError as exc:
        raise MissingFileError(f"--config {exc}") from None
    except ValueRangeError as exc:
        raise UsageError(f"--config {exc}") from None
    flags = {name: getattr(args, flag, None) for flag, name in CONFIG_FLAGS.items()}
    overrides = {name: value for name, value in flags.items() if value is not None}
    overrides.update(parse_set(args.set_fields))
    try:
        return apply_overrides(config, overrides)
    except (TypeError, ValueRangeError) as exc:  # TypeError: a value of the wrong kind
        raise UsageError(f"invalid FunFlow6D configuration: {exc}") from None


# ------------------------------------------------------------------------------ inference


def add_inference_arguments(
    parser: argparse.ArgumentParser, *, set_help: str, sampler: bool = True
) -> None:
    """Add the inference options (read by :func:`inference_changes`) to ``parser``.

    ``--hypotheses``, with ``sampler`` ``--steps`` and ``--solver``, ``--verify/--no-verify``
    and ``--set``.

    Args:
        parser: a subcommand's parser.
        set_help: what ``--set`` changes in this command.
        sampler: add ``--steps`` and ``--solver`` (``bench`` sets the sampler otherwise).
    """
    group = parser.add_argument_group(
        "inference", "What a trained model may change at inference (default: its own settings)."
    )
    group.add_argument(
        "--hypotheses", type=int, default=None, metavar="H", help="noise samples per instance"
    )
    if sampler:
        group.add_argument(
            "--steps", type=int, default=None, metavar="K", help="integration steps K"
        )
        group.add_argument(
            "--solver",
            type=solver_name,
            default=None,
            help="ODE solver: euler, midpoint, heun, rk4",
        )
    group.add_argument(
        "--verify",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="check every pose by rendering and comparing, and score it so (default: on)",
    )
    add_set_argument(group, set_help)


def inference_changes(args: argparse.Namespace, *, method: str = "funflow6d") -> dict[str, Any]:
    """The inference settings that the options of :func:`add_inference_arguments` change.

    ``--set`` items first, then ``--hypotheses``, ``--steps`` and ``--solver``; ``--no-verify``
    drops the verifier, whatever ``--set`` says of it. The model's settings are checked where
    they are applied (:func:`load_model`); the classic baseline's verifier, the one thing
    ``--set`` changes for it, is checked here and returned built.

    Args:
        args: the parsed arguments.
        method: ``funflow6d``, ``hybrid`` (both the model's settings) or ``baseline``.

    Returns:
        ``{key: value}`` for :meth:`~poseflow.models.FunFlow6DConfig.with_inference`, or for the
        baseline ``{"verifier": VerifierConfig | None}``.

    Raises:
        UsageError: ``--no-verify`` with ``hybrid`` (it chooses by verification), or a ``--set``
            item that is not ``KEY=VALUE``.
        ValueRangeError: with ``baseline``, a ``--set`` key outside the verifier.
    """
    from poseflow.baselines import BaselineConfig
    from poseflow.errors import UsageError, ValueRangeError
    from poseflow.models import apply_overrides

    changes = parse_set(args.set_fields)
    if method == "hybrid" and not args.verify:
        raise UsageError("--method hybrid chooses by verification: --no-verify does not apply")
    if not args.verify:  # off, whatever --set says of the verifier
        changes = {k: v for k, v in changes.items() if k.split(".")[0] != "verifier"}
    changes.setdefault("verifier", {} if args.verify else None)
    if method == "baseline":
        other = sorted(key for key in changes if key.split(".")[0] != "verifier")
        if other:
            raise ValueRangeError(
                f"--set can change only verifier with --method baseline; got {', '.join(other)}"
            )
        return {"verifier": apply_overrides(BaselineConfig(), changes).verifier}
    for name, flag in (("num_hypotheses", "hypotheses"), ("steps", "steps"), ("solver", "solver")):
        value = getattr(args, flag, None)
        if value is not None:
            changes[name] = value
    return changes
