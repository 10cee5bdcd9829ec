"""On-disk cache of per-object query features (safetensors), so that inference only loads them.

A cache entry is one ``.safetensors`` file under ``root/<object>/``, named by a hash of everything
that determines its content: the object key, a fingerprint of the model points, the encoder's
``repr`` (its kind and settings) and the lifting settings. The same hash is stored in the file's
metadata with the readable settings, so a stale or foreign file is never used.
"""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from poseflow._cache import atomic_write
from poseflow.errors import ValueRangeError
from poseflow.features.lifting import QueryFeatureBank, lift_query_features

__all__ = ["FeatureCache", "cached_query_features"]


def _fingerprint(points: torch.Tensor) -> str:
    data = points.detach().cpu().double().contiguous().numpy().tobytes()
    return hashlib.sha1(data).hexdigest()[:16]


class FeatureCache:
    """A directory of cached :class:`~poseflow.features.lifting.QueryFeatureBank` entries.

    Args:
        root: the cache directory (created on first write).

    Example:
        >>> import tempfile
        >>> cache = FeatureCache(tempfile.mkdtemp())
        >>> vis = torch.ones(4, 2, dtype=torch.bool)
        >>> poses = torch.eye(4).expand(2, 4, 4)
        >>> bank = QueryFeatureBank(torch.rand(4, 3), torch.rand(4, 2, 8), vis, poses)
        >>> key = cache.key("obj_1", bank.points, "Toy()", {"num_views": 2})
        >>> _ = cache.save(key, bank)
        >>> cache.load(key).features.shape
        torch.Size([4, 2, 8])
    """

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)

    def key(
        self, object_key: str, points: torch.Tensor, encoder: Any, settings: dict[str, Any]
    ) -> dict[str, str]:
        """The identity of an entry: readable fields plus their hash.

        Args:
            object_key: the object's name (e.g. ``"ycbv-obj_000005"``).
            points: the model's query points ``(N, 3)`` (fingerprinted).
            encoder: the appearance encoder, or its description as a string.
            settings: the lifting settings (JSON-serialisable).
        """
        if not re.fullmatch(r"[A-Za-z0-9_.\-]+", object_key):
            raise ValueRangeError(f"object_key must be a plain file name, got {object_key!r}")
        fields = {
            "object": object_key,
            "points": _fingerprint(points),
            "encoder": encoder if isinstance(encoder, str) else repr(encoder),
            "settings": json.dumps(settings, sort_keys=True),
        }
        fields["hash"] = hashlib.sha1(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:20]
        return fields

    def path(self, key: dict[str, str]) -> Path:
        """Where the entry of ``key`` lives."""
        return self.root / key["object"] / f"query-{key['hash']}.safetensors"

    def load(self, key: dict[str, str]) -> QueryFeatureBank | None:
        """The cached bank of ``key``, or None when absent or written for other settings."""
        from safetensors import safe_open

        path = self.path(key)
        if not path.is_file():
            return None
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
            if meta.get("hash") != key["hash"]:
                return None
            state = {name: f.get_tensor(name) for name in f.keys()}
        return QueryFeatureBank.from_state(state)

    def save(self, key: dict[str, str], bank: QueryFeatureBank) -> Path:
        """Write ``bank`` under ``key`` (atomically: a temporary file renamed into place)."""
        from safetensors.torch import save_file

        path = self.path(key)
        path.parent.mkdir(parents=True, exist_ok=True)
        return atomic_write(path, lambda tmp: save_file(bank.state(), tmp, metadata=dict(key)))

    def get_or_compute(
        self, key: dict[str, str], compute: Callable[[], QueryFeatureBank]
    ) -> QueryFeatureBank:
        """Load the entry of ``key``, or compute, save and return it."""
        bank = self.load(key)
        if bank is None:
            bank = compute()
            self.save(key, bank)
        return bank


def cached_query_features(
    cache: FeatureCache | str | Path,
    object_key: str,
    encoder: Any,
    mesh: Any,
    points: torch.Tensor,
    diameter: float,
    **settings: Any,
) -> QueryFeatureBank:
    """:func:`~poseflow.features.lifting.lift_query_features`, computed once per object and cached.

    Args:
        cache: a :class:`FeatureCache` or its root directory.
        object_key: the object's name, part of the cache key.
        encoder: the appearance encoder.
        mesh: the textured model.
        points: the model's query points ``(N, 3)``.
        diameter: the object diameter in metres.
        **settings: keyword settings of ``lift_query_features`` (part of the key).

    Returns:
        The bank (features in float32, stored so: a cached bank equals a fresh one exactly).
    """
    cache = cache if isinstance(cache, FeatureCache) else FeatureCache(cache)
    key_settings = {k: v for k, v in settings.items() if k != "renderer"}
    key_settings["diameter"] = float(diameter)
    key = cache.key(object_key, points, encoder, key_settings)
    return cache.get_or_compute(
        key, lambda: lift_query_features(encoder, mesh, points, diameter, **settings)
    )
