"""PointDiT: a Diffusion Transformer over point tokens, the velocity net ``Ψ(t, X(t) | C)``.

Shape letters used in this file:

==========  ==================================================================================
``B``       batch (object instances)
``L``       tokens, one per point; for FunFlow6D ``L = 2N``, the query ``Q`` then the target ``T``
``C``       condition channels per point (FunFlow6D: ``D + d_P``, fused descriptor | posenc)
``E``       model width (``hidden_dim``)
``H``       attention heads, ``E = H · E_h``
``F``       channels of the sinusoidal time features (``time_frequency_dim``)
==========  ==================================================================================

The einops patterns below use the same letters in lower case (``e_h`` for ``E_h``).

One token per point: ``token = W_x x_t + W_c C``; a sinusoidal embedding of ``t`` followed by an
MLP gives ``c ∈ R^E``, which drives adaLN-Zero modulation (shift, scale and gate of both the
attention and the MLP) in every block. The modulation layers are zero-initialised, so every block
is the identity at initialisation and so is the final layer's output (zero velocity). Attention is
:func:`torch.nn.functional.scaled_dot_product_attention` over all points with a key-padding mask
(PyTorch picks its flash or memory-efficient kernel where the platform has one; there is no
flash-attn dependency).

Within-cloud attention. With ``attention="alternating"`` even blocks (0, 2, ...) attend only
within a point's own cloud and odd blocks attend over all points, as Rectified Point Flow
alternates part-wise and global attention. The model then has to know which token belongs to
which cloud; pass either

- ``num_query=N``: tokens ``[0, N)`` are the query cloud and ``[N, L)`` the target (the
  ``[Q ; T]`` layout of FunFlow6D). Each cloud then runs its own SDPA call, which keeps the
  fused kernels usable and costs half the FLOPs of a masked ``L × L`` attention; or
- ``cloud_ids`` ``(B, L)`` integers: tokens attend within equal ids (any number of clouds, in any
  order), through a dense ``(B, 1, L, L)`` boolean mask.

Both are ignored by global-only models (``attention="global"``).

Why this module lives in ``poseflow.flows`` and not a separate ``poseflow.nets``: DESIGN.md puts
the velocity networks with the probability path, loss and samplers, and the DiT knows nothing of
poses or features beyond an opaque ``(B, L, C)`` condition, exactly like the rest of ``flows``.
A user who wants flow matching on point clouds imports one torch-only package and gets the path,
the solver and a velocity net that fits them; a ``nets`` package would add a node to the import
graph without removing a dependency. The positional encoder ``Ξ``
(:mod:`poseflow.flows.positional`) lives beside it for the same reason.

The model satisfies the flows velocity-model protocol, ``model(x=x_t, t=t, **cond)`` with
``cond = {"condition": C, "mask": mask, "num_query": N}``. A sampler that keeps the query cloud
fixed may add ``frozen_query=True`` (its velocity is not computed) and ``query_repeats=S`` (the
samples of one instance share their query tokens, run once per instance in the leading
within-cloud blocks): about a quarter less work per call for FunFlow6D's hypotheses, the same
velocities where they are used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Literal

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn

from poseflow._checks import check_mask, check_same, check_tensor
from poseflow._masks import key_padding_mask
from poseflow.errors import ShapeError, ValueRangeError

__all__ = [
    "PRESETS",
    "DiTBlock",
    "PointDiT",
    "PointDiTConfig",
    "TanhGELU",
    "sinusoidal_time_embedding",
]

AttentionMode = Literal["global", "alternating"]


@dataclass(frozen=True, kw_only=True)
class PointDiTConfig:
    """Hyper-parameters of :class:`PointDiT` (the defaults are the ``"paper"`` preset).

    The paper gives only the total trainable size (43.1 M parameters for fusion and flow model);
    width 512, 9 blocks and an MLP ratio of 4 are DiT's usual proportions at that size.

    Attributes:
        cond_dim: condition channels ``C`` per point (paper: ``D + d_P = 64 + 64``).
        hidden_dim: model width ``E``.
        depth: number of DiT blocks.
        num_heads: attention heads ``H``; must divide ``hidden_dim``.
        mlp_ratio: width of each block's MLP relative to ``E``.
        attention: ``"global"`` (every block attends over all points) or ``"alternating"``
            (within-cloud and global blocks alternate, starting with within-cloud).
        time_frequency_dim: channels ``F`` of the sinusoidal time features.
        time_scale: ``t ∈ [0, 1]`` is multiplied by this before the sinusoids, so that the
            frequencies of the classic ``10000``-period embedding resolve small steps.
    """

    cond_dim: int = 128
    hidden_dim: int = 512
    depth: int = 9
    num_heads: int = 8
    mlp_ratio: float = 4.0
    attention: AttentionMode = "alternating"
    time_frequency_dim: int = 256
    time_scale: float = 1000.0

    def __post_init__(self) -> None:
        for name in ("cond_dim", "hidden_dim", "depth", "num_heads", "time_frequency_dim"):
            if getattr(self, name) <= 0:
                raise ValueRangeError(f"{name} must be positive, got {getattr(self, name)}")
        if self.hidden_dim % self.num_heads:
            raise ValueRangeError(
                f"hidden_dim ({self.hidden_dim}) must be a multiple of num_heads ({self.num_heads})"
            )
        if self.mlp_ratio <= 0 or self.time_scale <= 0:
            raise ValueRangeError("mlp_ratio and time_scale must be positive")
        if self.attention not in ("global", "alternating"):
            raise ValueRangeError(
                f"attention must be 'global' or 'alternating', got {self.attention!r}"
            )


#: Named configurations: ``"paper"`` (fusion + DiT ≈ 43.1 M trainable parameters, the paper's
#: size), ``"small"`` (about 1.2 M, trains on a CPU in minutes on a few hundred points per cloud)
#: and ``"tiny"`` (a few thousand parameters, for tests).
PRESETS: dict[str, PointDiTConfig] = {
    "paper": PointDiTConfig(),
    "small": PointDiTConfig(hidden_dim=128, depth=4, num_heads=4, time_frequency_dim=128),
    "tiny": PointDiTConfig(
        cond_dim=16, hidden_dim=32, depth=2, num_heads=2, mlp_ratio=2.0, time_frequency_dim=16
    ),
}


def sinusoidal_time_embedding(
    t: torch.Tensor, dim: int, *, scale: float = 1000.0, max_period: float = 10000.0
) -> torch.Tensor:
    """Sinusoidal features of flow times, ``[cos(s·t·ω_k), sin(s·t·ω_k)]``.

    The frequencies ``ω_k = max_period^(-k / (dim // 2))`` and the products are computed in
    ``t``'s dtype promoted to at least float32 (float64 stays float64; half precision is lifted
    so that ``s·t`` keeps its resolution); cast the result to the network's dtype.

    Args:
        t: times, shape ``(B,)``.
        dim: output channels ``F`` (an odd ``dim`` gets a trailing zero channel).
        scale: factor ``s`` applied to ``t``.
        max_period: the slowest period.

    Returns:
        ``(B, F)``, on ``t``'s device.

    Example:
        >>> e = sinusoidal_time_embedding(torch.tensor([0.0, 0.5], dtype=torch.float64), 8)
        >>> e.shape, e.dtype, e[0, :4].tolist()
        (torch.Size([2, 8]), torch.float64, [1.0, 1.0, 1.0, 1.0])
    """
    compute = torch.promote_types(t.dtype, torch.float32)
    half = dim // 2
    k = torch.arange(half, dtype=compute, device=t.device)
    freqs = torch.exp(-math.log(max_period) * k / max(half, 1))
    args = (t.to(compute) * scale)[:, None] * freqs[None, :]
    emb = torch.cat([torch.cos(args), torch.sin(args)], dim=-1)
    if dim % 2:
        emb = F.pad(emb, (0, 1))
    return emb


class _TimeEmbedding(nn.Module):
    """Sinusoidal features of ``t`` → Linear → SiLU → Linear, giving ``(B, E)``."""

    def __init__(self, hidden_dim: int, frequency_dim: int, scale: float) -> None:
        super().__init__()
        self.frequency_dim = frequency_dim
        self.scale = scale
        self.mlp = nn.Sequential(
            nn.Linear(frequency_dim, hidden_dim), nn.SiLU(), nn.Linear(hidden_dim, hidden_dim)
        )

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        feats = sinusoidal_time_embedding(t, self.frequency_dim, scale=self.scale)
        return self.mlp(feats.to(self.mlp[0].weight.dtype))


class TanhGELU(nn.Module):
    """GELU with the tanh approximation, ``nn.GELU(approximate="tanh")``, faster in CPU inference.

    Since ``(1 + tanh z) / 2 = σ(2z)``, the function is ``x σ(2z)`` with
    ``z = √(2/π) (x + 0.044715 x³)``. Without gradients on the CPU it is evaluated in that form
    (PyTorch's CPU tanh is several times slower than its sigmoid); the values agree with
    :func:`torch.nn.functional.gelu` to float rounding. Elsewhere, and whenever gradients are
    recorded, it is :func:`~torch.nn.functional.gelu` itself. No parameters: checkpoints of
    ``nn.GELU(approximate="tanh")`` load unchanged.

    Example:
        >>> x = torch.linspace(-4, 4, 9)
        >>> with torch.no_grad():
        ...     bool(torch.allclose(TanhGELU()(x), F.gelu(x, approximate="tanh"), atol=1e-6))
        True
    """

    _SLOPE = 2 * math.sqrt(2 / math.pi)  # 2 √(2/π)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``GELU_tanh(x)``, the shape and dtype of ``x``."""
        if x.device.type != "cpu" or (torch.is_grad_enabled() and x.requires_grad):
            return F.gelu(x, approximate="tanh")
        # 2z = x (2√(2/π) + 2√(2/π) 0.044715 x²), built in place from one new tensor
        two_z = torch.addcmul(x.new_tensor(self._SLOPE), x, x, value=self._SLOPE * 0.044715).mul_(x)
        return two_z.sigmoid_().mul_(x)


def _key_mask(mask: torch.Tensor | None) -> torch.Tensor | None:
    """The SDPA key-padding mask of a validity mask ``(B, S)``, or None where none is needed.

    On the CPU an all-valid mask is dropped: the same attention, and PyTorch's kernels run
    faster without one (a host check that a GPU is spared).
    """
    if mask is None or (mask.device.type == "cpu" and bool(mask.all())):
        return None
    return key_padding_mask(mask)


#: Bytes of hidden MLP activations computed at once in CPU inference: a chunk of tokens whose
#: hidden layer fits stays in the cache between the two products and the GELU.
_MLP_CHUNK_BYTES = 1 << 20


def _modulate(x: torch.Tensor, shift: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    return x * (1 + scale[:, None]) + shift[:, None]


class DiTBlock(nn.Module):
    """A DiT block with adaLN-Zero conditioning and masked multi-head self-attention.

    ``h ← h + g₁ ⊙ Attn(LN(h)·(1 + s₁) + b₁)``, then ``h ← h + g₂ ⊙ MLP(LN(h)·(1 + s₂) + b₂)``,
    where ``(b₁, s₁, g₁, b₂, s₂, g₂) = W_ada SiLU(c)`` with ``W_ada`` (weight and bias)
    zero-initialised: the block is exactly the identity at initialisation.

    Args:
        hidden_dim: width ``E``.
        num_heads: heads ``H``.
        mlp_ratio: MLP width relative to ``E``.
        within_cloud: attend only within a point's cloud (see the module docstring).

    Example:
        >>> block = DiTBlock(16, num_heads=2)
        >>> h = torch.randn(2, 5, 16)
        >>> torch.equal(block(h, torch.randn(2, 16)), h)
        True
    """

    def __init__(
        self, hidden_dim: int, *, num_heads: int, mlp_ratio: float = 4.0, within_cloud: bool = False
    ) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.within_cloud = within_cloud
        self.norm1 = nn.LayerNorm(hidden_dim, elementwise_affine=False, eps=1e-6)
        self.qkv = nn.Linear(hidden_dim, 3 * hidden_dim)
        self.proj = nn.Linear(hidden_dim, hidden_dim)
        self.norm2 = nn.LayerNorm(hidden_dim, elementwise_affine=False, eps=1e-6)
        mlp_dim = round(hidden_dim * mlp_ratio)
        self.mlp = nn.Sequential(
            nn.Linear(hidden_dim, mlp_dim),
            TanhGELU(),
            nn.Linear(mlp_dim, hidden_dim),
        )
        self.ada = nn.Sequential(nn.SiLU(), nn.Linear(hidden_dim, 6 * hidden_dim))
        nn.init.zeros_(self.ada[1].weight)
        nn.init.zeros_(self.ada[1].bias)

    def _attend(
        self,
        x: torch.Tensor,
        attn_mask: torch.Tensor | None,
        split: int | None,
        split_masks: tuple[torch.Tensor | None, torch.Tensor | None],
        first_query: int,
    ) -> torch.Tensor:
        q, k, v = rearrange(
            self.qkv(x), "b l (qkv h e_h) -> qkv b h l e_h", qkv=3, h=self.num_heads
        )
        q = q[:, :, first_query:]
        if split is None:
            out = F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask)
        else:
            head = F.scaled_dot_product_attention(
                q[:, :, :split], k[:, :, :split], v[:, :, :split], attn_mask=split_masks[0]
            )
            tail = F.scaled_dot_product_attention(
                q[:, :, split:], k[:, :, split:], v[:, :, split:], attn_mask=split_masks[1]
            )
            out = torch.cat([head, tail], dim=2)
        return self.proj(rearrange(out, "b h l e_h -> b l (h e_h)"))

    def forward(
        self,
        h: torch.Tensor,
        c: torch.Tensor,
        attn_mask: torch.Tensor | None = None,
        split: int | None = None,
        split_masks: tuple[torch.Tensor | None, torch.Tensor | None] = (None, None),
        first_query: int = 0,
    ) -> torch.Tensor:
        """Update the tokens.

        Args:
            h: tokens, shape ``(B, L, E)``.
            c: conditioning vector, shape ``(B, E)``.
            attn_mask: boolean SDPA mask broadcastable to ``(B, H, L, L)`` (True: may attend),
                used when ``split`` is None.
            split: attend separately within tokens ``[0, split)`` and ``[split, L)``.
            split_masks: the boolean SDPA masks of those two groups.
            first_query: update only tokens ``[first_query, L)``, which still attend to all
                (with ``split`` None; a dense ``attn_mask`` must then have ``L - first_query``
                query rows or broadcast over them).

        Returns:
            The updated tokens ``(B, L - first_query, E)``.
        """
        shift1, scale1, gate1, shift2, scale2, gate2 = self.ada(c).chunk(6, dim=-1)
        x = _modulate(self.norm1(h), shift1, scale1)
        a = self._attend(x, attn_mask, split, split_masks, first_query)
        h = h[:, first_query:] + gate1[:, None] * a
        m = self._mlp(_modulate(self.norm2(h), shift2, scale2))
        return h + gate2[:, None] * m

    def _mlp(self, y: torch.Tensor) -> torch.Tensor:
        """The MLP of tokens ``(B, L, E)``; in CPU inference a few rows at a time.

        Each chunk's hidden activations, :data:`_MLP_CHUNK_BYTES` in the dtype the products
        give (autocast's or ``y``'s), stay in the cache (the same values: every row is computed
        alone anyway).
        """
        if y.device.type != "cpu" or torch.is_grad_enabled():
            return self.mlp(y)
        autocast = torch.is_autocast_enabled("cpu")
        dtype = torch.get_autocast_dtype("cpu") if autocast else y.dtype
        tokens = _MLP_CHUNK_BYTES // (self.mlp[0].out_features * dtype.itemsize)
        rows = max(1, tokens // max(1, y.shape[1]))
        if y.shape[0] <= rows:
            return self.mlp(y)
        return torch.cat([self.mlp(part) for part in y.split(rows)])


class _FinalLayer(nn.Module):
    """adaLN-Zero modulated LayerNorm and a zero-initialised linear map to 3-D velocities."""

    def __init__(self, hidden_dim: int) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(hidden_dim, elementwise_affine=False, eps=1e-6)
        self.ada = nn.Sequential(nn.SiLU(), nn.Linear(hidden_dim, 2 * hidden_dim))
        self.out = nn.Linear(hidden_dim, 3)
        for layer in (self.ada[1], self.out):
            nn.init.zeros_(layer.weight)
            nn.init.zeros_(layer.bias)

    def forward(self, h: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        shift, scale = self.ada(c).chunk(2, dim=-1)
        return self.out(_modulate(self.norm(h), shift, scale))


class PointDiT(nn.Module):
    """Diffusion Transformer velocity net over point tokens.

    Args:
        config: hyper-parameters; default the ``"paper"`` preset. See :meth:`from_preset`.

    Example:
        >>> model = PointDiT.from_preset("tiny")
        >>> x, c = torch.randn(2, 10, 3), torch.randn(2, 10, 16)
        >>> v = model(x, torch.rand(2), condition=c, num_query=5)
        >>> v.shape, bool((v == 0).all())  # adaLN-Zero: zero velocity at initialisation
        (torch.Size([2, 10, 3]), True)
    """

    def __init__(self, config: PointDiTConfig | None = None) -> None:
        super().__init__()
        self.config = PointDiTConfig() if config is None else config
        cfg = self.config
        e = cfg.hidden_dim
        self.x_embed = nn.Linear(3, e)
        self.cond_embed = nn.Linear(cfg.cond_dim, e)
        self.time_embed = _TimeEmbedding(e, cfg.time_frequency_dim, cfg.time_scale)
        self.blocks = nn.ModuleList(
            DiTBlock(
                e,
                num_heads=cfg.num_heads,
                mlp_ratio=cfg.mlp_ratio,
                within_cloud=cfg.attention == "alternating" and i % 2 == 0,
            )
            for i in range(cfg.depth)
        )
        self.final = _FinalLayer(e)

    @classmethod
    def from_preset(cls, name: str, **overrides: Any) -> PointDiT:
        """Build a model from a named configuration, optionally overriding some fields.

        Args:
            name: ``"paper"``, ``"small"`` or ``"tiny"`` (see :data:`PRESETS`).
            **overrides: :class:`PointDiTConfig` fields to change, e.g. ``cond_dim=96``.

        Returns:
            A freshly initialised model.

        Raises:
            ValueRangeError: an unknown preset name or field value.

        Example:
            >>> PointDiT.from_preset("tiny", attention="global").config.attention
            'global'
        """
        try:
            base = PRESETS[name]
        except KeyError:
            raise ValueRangeError(
                f"unknown preset {name!r}; choose one of {', '.join(sorted(PRESETS))}"
            ) from None
        return cls(replace(base, **overrides))

    def forward(
        self,
        x: torch.Tensor,
        t: torch.Tensor,
        *,
        condition: torch.Tensor,
        mask: torch.Tensor | None = None,
        cloud_ids: torch.Tensor | None = None,
        num_query: int | None = None,
        frozen_query: bool = False,
        query_repeats: int = 1,
    ) -> torch.Tensor:
        """Predict the velocity of every point.

        Two inference shortcuts for a sampler that keeps the query cloud ``[0, num_query)``
        fixed (FunFlow6D's anchor) change no velocity it uses:

        - ``frozen_query``: the query's velocities are not wanted. They are returned as zeros,
          and from the last global block on only the target's tokens are updated (the query's
          are still attended to there).
        - ``query_repeats = S``: the rows come in consecutive groups of ``S`` (one instance's
          samples) with equal ``t`` and equal query tokens (``x``, ``condition`` and ``mask``).
          The within-cloud blocks before the first global block then run the query cloud once
          per group.

        Args:
            x: the flow state ``X(t)``, shape ``(B, L, 3)``.
            t: flow times in ``[0, 1]``, shape ``(B,)`` (a 0-dim tensor is broadcast).
            condition: per-point condition ``C``, shape ``(B, L, C)``, same dtype as ``x``.
            mask: ``(B, L)`` bool, True for valid points; padded points neither send nor
                receive attention and get zero velocity. None means all valid.
            cloud_ids: ``(B, L)`` integer cloud index of every token, for within-cloud blocks.
            num_query: tokens ``[0, num_query)`` form one cloud and the rest another, for
                within-cloud blocks (takes precedence over ``cloud_ids``).
            frozen_query: return zero velocity for the query cloud without computing it
                (needs ``num_query``).
            query_repeats: the size ``S`` of the row groups that share their query tokens
                (needs ``num_query``; ``B`` must be a multiple of it).

        Returns:
            Velocities ``(B, L, 3)`` in ``x``'s dtype, zero at padded points.

        Raises:
            ShapeError: shapes, dtypes or devices that do not match.
            ValueRangeError: within-cloud blocks without ``num_query`` or ``cloud_ids``,
                ``num_query`` outside ``[1, L)``, or the shortcuts without ``num_query``, with
                ``B`` not a multiple of ``query_repeats`` or with unequal rows in a group.
        """
        cfg = self.config
        sizes = check_tensor(x, "x", ("B", "L", 3))
        check_tensor(condition, "condition", ("B", "L", cfg.cond_dim), sizes=sizes)
        check_same(("x", x), ("condition", condition))
        if t.dim() == 0:
            t = t.expand(sizes["B"])
        check_tensor(t, "t", ("B",), sizes=sizes)
        check_same(("x", x), ("t", t), dtype=False)
        if mask is not None:
            check_mask(mask, "mask", ("B", "L"), sizes)
            check_same(("x", x), ("mask", mask), dtype=False)
        if isinstance(query_repeats, bool) or not isinstance(query_repeats, int):
            raise ValueRangeError(f"query_repeats must be an integer, got {query_repeats!r}")
        if query_repeats < 1 or sizes["B"] % query_repeats:
            raise ValueRangeError(
                f"query_repeats must be a positive divisor of the batch ({sizes['B']}), "
                f"got {query_repeats}"
            )
        c = self.time_embed(t)
        if frozen_query or query_repeats > 1:
            if num_query is None or not 0 < num_query < sizes["L"]:
                raise ValueRangeError(
                    f"frozen_query and query_repeats need num_query in [1, {sizes['L']}), "
                    f"got {num_query}"
                )
            v = self._forward_fixed_query(
                x, c, t, condition, mask, num_query, frozen_query, query_repeats
            )
        else:
            global_mask = _key_mask(mask)
            local_mask, split, split_masks = self._local_layout(mask, cloud_ids, num_query, sizes)
            h = self.x_embed(x) + self.cond_embed(condition)
            for block in self.blocks:
                if block.within_cloud:
                    h = block(h, c, local_mask, split, split_masks)
                else:
                    h = block(h, c, global_mask)
            v = self.final(h, c)
        if mask is not None:
            v = v * mask[..., None].to(v.dtype)
        return v

    def _forward_fixed_query(
        self,
        x: torch.Tensor,
        c: torch.Tensor,
        t: torch.Tensor,
        condition: torch.Tensor,
        mask: torch.Tensor | None,
        n: int,
        frozen_query: bool,
        repeats: int,
    ) -> torch.Tensor:
        """:meth:`forward` with its shortcuts; ``c`` ``(B, E)``, returns ``(B, L, 3)``."""
        query, target = slice(None, n), slice(n, None)
        first = slice(None, None, repeats)  # one row per group
        if repeats > 1:
            shared = [x[:, query], condition[:, query], t]
            if mask is not None:
                shared.append(mask[:, query])
            for value in shared:
                groups = value.unflatten(0, (-1, repeats))
                if not torch.equal(groups, groups[:, :1].expand_as(groups)):
                    raise ValueRangeError(
                        f"query_repeats={repeats}: the rows of a group differ in t or in their "
                        "query tokens"
                    )

        def padding(rows: slice, tokens: slice) -> torch.Tensor | None:
            return _key_mask(None if mask is None else mask[rows, tokens])

        blocks = list(self.blocks)
        leading = next((i for i, b in enumerate(blocks) if not b.within_cloud), len(blocks))
        h_query = self.x_embed(x[first, query]) + self.cond_embed(condition[first, query])
        h_target = self.x_embed(x[:, target]) + self.cond_embed(condition[:, target])
        for block in blocks[:leading]:
            h_query = block(h_query, c[first], padding(first, query))
            h_target = block(h_target, c, padding(slice(None), target))
        if leading < len(blocks):
            last = max(i for i, b in enumerate(blocks) if not b.within_cloud)
            stop = last if frozen_query else len(blocks)
            h = torch.cat([h_query.repeat_interleave(repeats, dim=0), h_target], dim=1)
            global_mask = padding(slice(None), slice(None))
            split_masks = (padding(slice(None), query), padding(slice(None), target))
            for block in blocks[leading:stop]:
                if block.within_cloud:
                    h = block(h, c, None, n, split_masks)
                else:
                    h = block(h, c, global_mask)
            if not frozen_query:
                return self.final(h, c)
            # the last global block updates the target only; after it the clouds never meet
            h_target = blocks[last](h, c, global_mask, first_query=n)
            for block in blocks[last + 1 :]:
                h_target = block(h_target, c, padding(slice(None), target))
        v_target = self.final(h_target, c)
        if frozen_query:
            v_query = v_target.new_zeros(v_target.shape[0], n, 3)
        else:  # no global block: the query never met the targets of its group
            v_query = self.final(h_query, c[first]).repeat_interleave(repeats, dim=0)
        return torch.cat([v_query, v_target], dim=1)

    def _local_layout(
        self,
        mask: torch.Tensor | None,
        cloud_ids: torch.Tensor | None,
        num_query: int | None,
        sizes: dict[str, int],
    ) -> tuple[torch.Tensor | None, int | None, tuple[torch.Tensor | None, torch.Tensor | None]]:
        """SDPA masks of the within-cloud blocks: ``(dense_mask, split, split_masks)``."""
        if self.config.attention == "global":
            return None, None, (None, None)
        length = sizes["L"]
        if num_query is not None:
            if not 0 < num_query < length:
                raise ValueRangeError(f"num_query must lie in [1, {length}), got {num_query}")
            if mask is None:
                return None, num_query, (None, None)
            head, tail = mask[:, :num_query], mask[:, num_query:]
            return None, num_query, (_key_mask(head), _key_mask(tail))
        if cloud_ids is None:
            raise ValueRangeError(
                "within-cloud attention needs num_query or cloud_ids; pass one, or build the "
                "model with attention='global'"
            )
        check_tensor(cloud_ids, "cloud_ids", ("B", "L"), floating=False, sizes=sizes)
        if cloud_ids.is_floating_point() or cloud_ids.dtype == torch.bool:
            raise ShapeError(f"cloud_ids must be an integer tensor, got {cloud_ids.dtype}")
        allowed = cloud_ids[:, :, None] == cloud_ids[:, None, :]
        if mask is not None:
            allowed = allowed & mask[:, None, :]
        allowed = allowed | ~allowed.any(dim=-1, keepdim=True)
        return allowed[:, None], None, (None, None)
