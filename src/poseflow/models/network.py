"""The trainable part of FunFlow6D: input adapters, fusion, positional encoder and DiT.

Shape letters: ``B`` instances, ``N`` points per cloud, ``L = 2N`` tokens ``[Q ; T]``, ``Dg`` /
``Ds`` channels of the frozen geometric / semantic descriptors, ``D`` fused channels, ``d_P``
positional channels.

The fusion block is applied to the query and the target clouds independently, as in the paper:
``[Q ; T]`` is folded to ``(2B, N, D)`` so that one call fuses both without letting points of one
cloud attend to the other. None of this depends on the flow state, so
:meth:`FunFlow6DNet.condition` is computed once per estimate and the sampler calls only the DiT.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Self

import torch
from torch import nn

from poseflow._checks import check_mask, check_tensor
from poseflow._precision import precision_autocast
from poseflow.errors import ShapeError, ValueRangeError
from poseflow.eval.timing import stage, timed
from poseflow.flows.dit import PointDiT
from poseflow.flows.positional import PointPositionalEncoder
from poseflow.flows.samplers import ODESampler, initial_noise
from poseflow.fusion import build_fusion
from poseflow.models.config import NetConfig

__all__ = ["FunFlow6DNet", "NetInputs"]


@dataclass(kw_only=True)
class NetInputs:
    """What the network reads of ``[Q ; T]`` besides the flow state and the noise.

    Attributes:
        geometric: frozen geometric descriptors ``(B, 2N, Dg)``.
        semantic: (reduced) semantic descriptors ``(B, 2N, Ds)``.
        points: normalised coordinates ``(B, 2N, 3)``: ``Q`` canonical, ``T`` observed.
        normals: unit normals ``(B, 2N, 3)``.
        mask: ``(B, 2N)`` bool, True at valid points (None: all valid).
    """

    geometric: torch.Tensor
    semantic: torch.Tensor
    points: torch.Tensor
    normals: torch.Tensor
    mask: torch.Tensor | None = None

    @classmethod
    def field_names(cls) -> tuple[str, ...]:
        """The names of :class:`NetInputs`' own fields (also for a subclass).

        Example:
            >>> NetInputs.field_names()
            ('geometric', 'semantic', 'points', 'normals', 'mask')
        """
        return tuple(f.name for f in dataclasses.fields(NetInputs))

    @classmethod
    def from_kwargs(cls, tensors: Mapping[str, torch.Tensor]) -> NetInputs:
        """Build from keyword tensors named as the fields (e.g. a collated training batch).

        Raises:
            ValueRangeError: a name that is not a field, or a missing field.
        """
        names = cls.field_names()
        unknown = sorted(set(tensors) - set(names))
        required = [
            f.name for f in dataclasses.fields(NetInputs) if f.default is dataclasses.MISSING
        ]
        missing = [n for n in required if n not in tensors]
        if unknown or missing:
            raise ValueRangeError(
                f"the network takes {', '.join(names)}; got unknown {unknown}, missing {missing}"
            )
        return NetInputs(**tensors)

    def repeat_interleave(self, repeats: int) -> Self:
        """Every tensor field (a subclass's too) ``repeats`` times in a row: ``B → B·repeats``."""
        changes = {
            f.name: value.repeat_interleave(repeats, dim=0)
            for f in dataclasses.fields(self)
            if isinstance(value := getattr(self, f.name), torch.Tensor)
        }
        return dataclasses.replace(self, **changes)

    def net_kwargs(self) -> dict[str, torch.Tensor]:
        """The fields of :class:`NetInputs` as keyword tensors (inverse of :meth:`from_kwargs`)."""
        return {
            n: value for n in NetInputs.field_names() if (value := getattr(self, n)) is not None
        }


class FunFlow6DNet(nn.Module):
    """Velocity network ``Ψ(t, X(t) | C)`` with ``C = [F | P]`` built from frozen descriptors.

    Args:
        config: sizes and the fusion variant.

    Example:
        >>> net = FunFlow6DNet(NetConfig(geometric_dim=6, semantic_dim=5, feature_dim=8,
        ...                              fusion_heads=2, posenc_dim=8, dit_preset="tiny"))
        >>> B, N = 2, 4
        >>> inputs = NetInputs(geometric=torch.randn(B, 2 * N, 6),
        ...                    semantic=torch.randn(B, 2 * N, 5),
        ...                    points=torch.randn(B, 2 * N, 3), normals=torch.randn(B, 2 * N, 3))
        >>> x, x_0 = torch.randn(B, 2 * N, 3), torch.randn(B, 2 * N, 3)
        >>> net(x=x, t=torch.rand(B), inputs=inputs, x_0=x_0).shape
        torch.Size([2, 8, 3])
    """

    def __init__(self, config: NetConfig | None = None) -> None:
        super().__init__()
        self.config = cfg = NetConfig() if config is None else config
        d = cfg.feature_dim
        self.geometric_in = (
            nn.Identity() if cfg.geometric_dim == d else nn.Linear(cfg.geometric_dim, d)
        )
        self.semantic_in = (
            nn.Identity() if cfg.semantic_dim == d else nn.Linear(cfg.semantic_dim, d)
        )
        kwargs: dict[str, Any] = {"dim": d}
        if cfg.fusion in ("gated", "cross"):
            kwargs.update(num_heads=cfg.fusion_heads, dropout=cfg.dropout)
        self.fusion = build_fusion(cfg.fusion, **kwargs)
        self.posenc = PointPositionalEncoder(cfg.posenc_dim, num_frequencies=cfg.posenc_frequencies)
        self.dit = PointDiT(cfg.dit_config())

    def condition(self, inputs: NetInputs, *, x_0: torch.Tensor) -> torch.Tensor:
        """The conditioning signal ``C = [F | P]`` of ``[Q ; T]``.

        Args:
            inputs: the frozen descriptors, coordinates, normals and mask of ``[Q ; T]``.
            x_0: the noise sample ``X(0)`` ``(B, 2N, 3)`` (read as zeros by the positional
                encoder without ``config.noise_conditioning``).

        Returns:
            ``(B, 2N, D + d_P)``.
        """
        sizes = check_tensor(inputs.points, "points", ("B", "L", 3))
        if sizes["L"] % 2:
            raise ShapeError(f"[Q ; T] needs an even number of points, got {sizes['L']}")
        cfg = self.config
        check_tensor(inputs.geometric, "geometric", ("B", "L", cfg.geometric_dim), sizes=sizes)
        check_tensor(inputs.semantic, "semantic", ("B", "L", cfg.semantic_dim), sizes=sizes)
        mask = inputs.mask
        if mask is not None:
            check_mask(mask, "mask", ("B", "L"), sizes)
        B, L = sizes["B"], sizes["L"]
        n = L // 2
        g = self.geometric_in(inputs.geometric).reshape(2 * B, n, -1)
        s = self.semantic_in(inputs.semantic).reshape(2 * B, n, -1)
        # Under autocast an Identity adapter keeps float32 while a Linear one gives bfloat16.
        common = torch.promote_types(g.dtype, s.dtype)
        g, s = g.to(common), s.to(common)
        fused = self.fusion(g, s, None if mask is None else mask.reshape(2 * B, n))
        fused = fused.reshape(B, L, -1)
        is_target = torch.arange(L, device=inputs.points.device).expand(B, L) >= n
        if not cfg.noise_conditioning:
            x_0 = torch.zeros_like(x_0)
        pos = self.posenc(inputs.points, inputs.normals, x_0, is_target)
        return torch.cat([fused, pos], dim=-1)

    @torch.no_grad()
    def sample(
        self,
        inputs: NetInputs,
        sampler: ODESampler,
        *,
        frozen_mask: torch.Tensor,
        x_frozen: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
        num_samples: int = 1,
        precision: str = "fp32",
    ) -> torch.Tensor:
        """Integrate the flow from fresh noise ``X(0)`` to ``X(1)``, the condition computed once.

        Without ``config.noise_conditioning`` the condition does not depend on the noise, so
        it is computed once per instance for all its samples. The stages are reported to the
        active timer: ``fusion`` (the condition), ``integration`` (the sampler) and
        ``flow_net`` (each DiT call).

        Args:
            inputs: as in :meth:`condition`, of ``B`` instances.
            sampler: the ODE solver.
            frozen_mask: ``(B, 2N)`` bool, True at the anchor's points (velocity zero).
            x_frozen: where the anchor sits when it is pinned ``(B, 2N, 3)``, or None.
            generator: draws ``X(0) ~ N(0, I)``, all ``B · num_samples`` rows at once.
            num_samples: samples ``S`` per instance (e.g. pose hypotheses).
            precision: what the DiT computes in (:func:`~poseflow.flows.autocast_dtype`:
                ``"fp32"``, ``"bf16"``, ``"fp16"`` or ``"auto"``); the condition and the
                integrated state stay in the inputs' dtype.

        Returns:
            ``X(1)`` ``(B·S, 2N, 3)``, the samples of an instance in consecutive rows.
        """
        if num_samples < 1:
            raise ValueRangeError(f"num_samples must be positive, got {num_samples}")
        points = inputs.points
        shape = (len(points) * num_samples, *points.shape[1:])
        x_0 = initial_noise(shape, generator=generator, device=points.device, dtype=points.dtype)
        with stage("fusion"):
            if self.config.noise_conditioning:
                cond = self.condition(inputs.repeat_interleave(num_samples), x_0=x_0)
            else:
                cond = self.condition(inputs, x_0=x_0[::num_samples])
                cond = cond.repeat_interleave(num_samples, dim=0)
        repeat = functools.partial(torch.repeat_interleave, repeats=num_samples, dim=0)
        n = points.shape[1] // 2
        shortcuts = {}
        if isinstance(self.dit, PointDiT):
            # A frozen query needs no velocity; pinned (and not noise-conditioned) it is the
            # same for all samples of an instance, which the DiT then runs once per instance.
            frozen = bool(frozen_mask[:, :n].all()) and not bool(frozen_mask[:, n:].any())
            shared = frozen and x_frozen is not None and not self.config.noise_conditioning
            shortcuts = {"frozen_query": frozen, "query_repeats": num_samples if shared else 1}
        with stage("integration"), precision_autocast(precision, points.device):
            return sampler.sample(
                timed("flow_net", self.dit),
                x_0,
                frozen_mask=repeat(frozen_mask),
                x_frozen=None if x_frozen is None else repeat(x_frozen),
                condition=cond,
                mask=None if inputs.mask is None else repeat(inputs.mask),
                num_query=n,
                **shortcuts,
            )

    def forward(
        self, *, x: torch.Tensor, t: torch.Tensor, inputs: NetInputs, x_0: torch.Tensor
    ) -> torch.Tensor:
        """Velocity of every point of ``[Q ; T]``, ``(B, 2N, 3)``; see :meth:`condition`.

        Args:
            x: the flow state ``X(t)`` ``(B, 2N, 3)``.
            t: times ``(B,)``.
            inputs: as in :meth:`condition`.
            x_0: as in :meth:`condition`.
        """
        c = self.condition(inputs, x_0=x_0)
        return self.dit(x, t, condition=c, mask=inputs.mask, num_query=x.shape[1] // 2)
