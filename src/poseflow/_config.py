"""What every configuration dataclass shares: dicts in and out, and overrides by dotted keys.

:func:`apply_overrides` is public as :func:`poseflow.models.apply_overrides`; it serves
:class:`~poseflow.models.FunFlow6DConfig`, :class:`~poseflow.baselines.BaselineConfig` and
:class:`~poseflow.verify.VerifierConfig` alike.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, TypeVar

from poseflow.errors import ValueRangeError

__all__ = ["apply_overrides", "config_from_dict", "config_to_dict"]

_C = TypeVar("_C")


def config_to_dict(config: Any) -> dict[str, Any]:
    """The fields of a configuration as a JSON-ready dict: tuples as lists, nested ones as dicts."""
    out = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            value = value.to_dict()  # type: ignore[union-attr]
        elif isinstance(value, tuple):
            value = list(value)
        out[f.name] = value
    return out


def config_from_dict(cls: type[_C], data: Mapping[str, Any]) -> _C:
    """``cls(**data)`` after checking that every key is a field of ``cls``.

    Raises:
        ValueRangeError: an unknown key; the message lists the known ones.
    """
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueRangeError(f"unknown {cls.__name__} fields: {unknown}; known: {sorted(names)}")
    return cls(**data)


def apply_overrides(config: _C, overrides: Mapping[str, Any]) -> _C:
    """A copy of a configuration with ``overrides`` applied in order, merged into nested ones.

    A key names a field, or with dots a field of a nested configuration
    (``"verifier.rank_top_k"``, ``"net.dit.depth"``). A mapping given for a nested configuration
    changes the fields it names and keeps the others; a nested configuration that is None (off)
    is first built from its default. Any other value replaces the field. Each changed
    configuration is validated by its class.

    Args:
        config: a configuration dataclass.
        overrides: ``{key: value}``, e.g. what ``--set KEY=VALUE`` parses to.

    Raises:
        ValueRangeError: an unknown field (the message names the key and the known fields), or a
            value the configuration does not accept.

    Example:
        >>> from poseflow.models import FunFlow6DConfig
        >>> cfg = apply_overrides(FunFlow6DConfig(), {"verifier": {"rank_top_k": 4}, "steps": 2})
        >>> cfg.steps, cfg.verifier.rank_top_k, cfg.verifier.crop_size  # crop_size kept
        (2, 4, 64)
        >>> apply_overrides(cfg, {"verifier.refine_top_k": 1}).verifier.rank_top_k
        4
    """
    for key, value in overrides.items():
        config = _override(config, key, key.split("."), value)
    return config


def _override(config: _C, key: str, path: list[str], value: Any) -> _C:
    """``config`` with the field at ``path`` (the parts of ``key``) set or merged."""
    fields = {f.name: f for f in dataclasses.fields(config)}  # type: ignore[arg-type]
    name = path[0]
    if name not in fields:
        raise ValueRangeError(
            f"unknown {type(config).__name__} field {name!r} in {key!r}; known: "
            f"{', '.join(sorted(fields))}"
        )
    nested = getattr(config, name)
    if nested is None and (len(path) > 1 or isinstance(value, Mapping)):
        nested = _default(fields[name])
    if len(path) > 1 or (isinstance(value, Mapping) and dataclasses.is_dataclass(nested)):
        if not dataclasses.is_dataclass(nested):
            raise ValueRangeError(f"{key!r}: {type(config).__name__}.{name} has no fields")
        if len(path) > 1:
            value = _override(nested, key, path[1:], value)
        else:
            for inner, v in value.items():
                nested = _override(nested, f"{key}.{inner}", inner.split("."), v)
            value = nested
    return dataclasses.replace(config, **{name: value})  # type: ignore[type-var]


def _default(f: dataclasses.Field[Any]) -> Any:
    """The default value of a dataclass field (None without one)."""
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None if f.default is dataclasses.MISSING else f.default
