"""The model configuration and inference options of the subcommands.

- the model configuration: :func:`add_config_arguments` registers ``--config`` (a recipe name or a
  JSON file of :class:`~poseflow.models.FunFlow6DConfig` fields), ``--preset`` and a few common
  fields as flags, and ``--set KEY=VALUE`` for any field; :func:`build_config` turns them into a
  config;
- inference: :func:`add_inference_arguments` (``--hypotheses``, ``--steps``, ``--solver``,
  ``--verify/--no-verify``, ``--set``) and :func:`inference_changes`, their one check.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from poseflow.cli.common import solver_name

__all__ = [
    "CONFIG_FLAGS",
    "add_config_arguments",
    "add_inference_arguments",
    "add_set_argument",
    "build_config",
    "config_requested",
    "inference_changes",
    "parse_set",
]

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
        help="dsift, dinov2:NAME_OR_PATH, learned[:FOLDER], surface:FOLDER or none "
        "(appearance_encoder)",
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
