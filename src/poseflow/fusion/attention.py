"""Cross-attention between two point-feature streams, with and without a sigmoid output gate.

Shape letters: ``B`` batch, ``P`` query points, ``S`` key/value points, ``D`` channels, ``H`` heads
(``D = H * D_h``). Heads are split and merged with einops' ``rearrange``, whose patterns use
the same letters in lower case (``"b n (h d_h) -> b h n d_h"``, ``n`` for ``P`` or ``S``) and
spell out that head ``h`` owns channels ``h·D_h … (h+1)·D_h − 1``.

:class:`GatedCrossAttention` is the branch of FunFlow6D's fusion block (paper, "Feature fusion via
gated cross-attention"): queries from ``X_q``, keys and values from ``X_kv``, multi-head scaled
dot-product attention, an element-wise sigmoid gate ``σ(X_q W_g)`` on the attention output, then
``W_O``, dropout and a LayerNorm with a residual from ``X_q``. :class:`CrossAttention` is the same
layer without the gate (the ablation's "standard, ungated cross-attention").

Which attention kernel runs (:func:`attend`): PyTorch's SDPA picks the first backend of its
priority order whose constraints the call meets. Two of those rules decide the speed here:

- A mask rules out flash attention. Without padding (every cloud has all its points, the common
  case) no mask is passed at all, so float16/bfloat16 calls can use flash attention; with padding
  the boolean key mask goes to the memory-efficient kernel, which accepts it in any dtype (torch
  turns it into an additive bias of the query's dtype and aligns its last dimension itself).
- cuDNN attention is left out on CUDA. From torch 2.11 on (its bundled cuDNN is newer than 9.15)
  SDPA tries cuDNN first for float16/bfloat16 on sm90/sm100 GPUs (H100, H200, B200). cuDNN builds
  an execution plan for every new shape, tens of milliseconds at the first call of each, and the
  fusion's shape changes with the number of instances in each image; flash and the
  memory-efficient kernels are compiled ahead and need no plan. float32 never reaches cuDNN (nor
  flash), which is why only bfloat16 was slow. The backends the user has enabled otherwise are
  kept, and when cuDNN is the only one enabled it is used. (Like ``sdpa_kernel`` itself, the
  switch holds for the whole process while the call runs.)
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn
from torch.nn.attention import SDPBackend, sdpa_kernel

from poseflow._checks import check_mask, check_same, check_tensor
from poseflow._masks import key_padding_mask
from poseflow.errors import ValueRangeError

__all__ = ["CrossAttention", "GatedCrossAttention", "attend", "key_padding_mask"]

#: SDPA backends :func:`attend` uses on CUDA, in torch's order, each with the switch a user
#: may have turned off (``torch.backends.cuda.enable_*_sdp``). cuDNN is not among them.
_BACKENDS: tuple[tuple[SDPBackend, Callable[[], bool]], ...] = (
    (SDPBackend.FLASH_ATTENTION, torch.backends.cuda.flash_sdp_enabled),
    (SDPBackend.EFFICIENT_ATTENTION, torch.backends.cuda.mem_efficient_sdp_enabled),
    (SDPBackend.MATH, torch.backends.cuda.math_sdp_enabled),
)


def _backends_without_cudnn() -> list[SDPBackend]:
    """The enabled SDPA backends other than cuDNN, in torch's order (empty: only cuDNN is on)."""
    return [backend for backend, enabled in _BACKENDS if enabled()]


def attend(
    q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, kv_mask: torch.Tensor | None = None
) -> torch.Tensor:
    """Multi-head scaled dot-product attention with an optional key-padding mask.

    Same result as :func:`torch.nn.functional.scaled_dot_product_attention` with the mask of
    :func:`key_padding_mask`, on a kernel chosen for speed (see the module docstring): a mask
    without padding is dropped (one host synchronisation to find out), and on CUDA the cuDNN
    backend is left out.

    Args:
        q: queries ``(B, H, P, D_h)``.
        k: keys ``(B, H, S, D_h)``.
        v: values ``(B, H, S, D_h)``.
        kv_mask: ``(B, S)`` bool, True for valid keys; None: all valid.

    Returns:
        ``(B, H, P, D_h)``, in ``q``'s dtype.

    Example:
        >>> q, k, v = torch.randn(2, 4, 5, 8), torch.randn(2, 4, 6, 8), torch.randn(2, 4, 6, 8)
        >>> mask = torch.tensor([[True] * 6, [True] * 4 + [False] * 2])
        >>> out = attend(q, k, v, mask)
        >>> out.shape, torch.allclose(out[1], attend(q[1:], k[1:, :, :4], v[1:, :, :4])[0])
        (torch.Size([2, 4, 5, 8]), True)

    Raises:
        ShapeError: shapes, dtypes or devices that do not match.
    """
    sizes = check_tensor(q, "q", ("B", "H", "P", "D_h"))
    check_tensor(k, "k", ("B", "H", "S", "D_h"), sizes=sizes)
    check_tensor(v, "v", ("B", "H", "S", "D_h"), sizes=sizes)
    check_same(("q", q), ("k", k), ("v", v))
    if kv_mask is not None:
        check_mask(kv_mask, "kv_mask", ("B", "S"), sizes)
        check_same(("q", q), ("kv_mask", kv_mask), dtype=False)
    attn_mask = None
    if kv_mask is not None and not bool(kv_mask.all()):
        attn_mask = key_padding_mask(kv_mask)
    if q.device.type == "cuda" and torch.backends.cuda.cudnn_sdp_enabled():
        backends = _backends_without_cudnn()
        if backends:
            with sdpa_kernel(backends):
                return F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask)
    return F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask)


class CrossAttention(nn.Module):
    """Multi-head cross-attention ``X_q ← X_kv`` with output projection, dropout and post-norm.

    ``out = LN(X_q + Dropout(W_O · SDPA(X_q W_Q, X_kv W_K, X_kv W_V)))``. The projections
    ``W_Q, W_K, W_V, W_O`` are :class:`torch.nn.Linear` layers with bias and PyTorch's default
    initialisation.

    Args:
        dim: channels ``D`` of both streams.
        num_heads: attention heads ``H``; must divide ``dim``.
        dropout: dropout probability after ``W_O`` (paper: 0.1).

    Example:
        >>> layer = CrossAttention(16, num_heads=2).eval()
        >>> layer(torch.randn(2, 5, 16), torch.randn(2, 7, 16)).shape
        torch.Size([2, 5, 16])
    """

    def __init__(self, dim: int = 64, *, num_heads: int = 4, dropout: float = 0.1) -> None:
        super().__init__()
        if dim <= 0 or num_heads <= 0 or dim % num_heads:
            raise ValueRangeError(
                f"dim must be a positive multiple of num_heads, got {dim} and {num_heads}"
            )
        if not 0.0 <= dropout < 1.0:
            raise ValueRangeError(f"dropout must lie in [0, 1), got {dropout}")
        self.dim = dim
        self.num_heads = num_heads
        self.to_q = nn.Linear(dim, dim)
        self.to_k = nn.Linear(dim, dim)
        self.to_v = nn.Linear(dim, dim)
        self.out_proj = nn.Linear(dim, dim)
        self.dropout = nn.Dropout(dropout)
        self.norm = nn.LayerNorm(dim)

    def gate(self, x_q: torch.Tensor) -> torch.Tensor | None:
        """Return the ``(B, P, D)`` multiplicative gate of the attention output (None: ungated)."""
        return None

    def forward(
        self,
        x_q: torch.Tensor,
        x_kv: torch.Tensor,
        *,
        kv_mask: torch.Tensor | None = None,
        q_mask: torch.Tensor | None = None,
        return_gate: bool = False,
    ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor | None]:
        """Attend from ``x_q`` to ``x_kv``.

        Args:
            x_q: query stream, shape ``(B, P, D)``.
            x_kv: key/value stream, shape ``(B, S, D)``.
            kv_mask: ``(B, S)`` bool, True for valid keys; padded keys get no attention weight.
            q_mask: ``(B, P)`` bool, True for valid queries; rows of padded queries (and of their
                gate) are set to zero.
            return_gate: also return the gate (``None`` for an ungated layer).

        Returns:
            ``(B, P, D)``, or the pair ``(output, gate)`` with the gate ``(B, P, D)`` when
            ``return_gate`` is True.
        """
        sizes = check_tensor(x_q, "x_q", ("B", "P", self.dim))
        check_tensor(x_kv, "x_kv", ("B", "S", self.dim), sizes=sizes)
        check_same(("x_q", x_q), ("x_kv", x_kv))
        if kv_mask is not None:
            check_mask(kv_mask, "kv_mask", ("B", "S"), sizes)
        if q_mask is not None:
            check_mask(q_mask, "q_mask", ("B", "P"), sizes)
        q, k, v = (
            rearrange(y, "b n (h d_h) -> b h n d_h", h=self.num_heads)
            for y in (self.to_q(x_q), self.to_k(x_kv), self.to_v(x_kv))
        )
        att = attend(q, k, v, kv_mask)
        att = rearrange(att, "b h p d_h -> b p (h d_h)")
        gate = self.gate(x_q)
        if gate is not None:
            att = gate * att
        out = self.norm(x_q + self.dropout(self.out_proj(att)))
        if q_mask is not None:
            keep = q_mask[..., None].to(out.dtype)
            out = out * keep
            gate = None if gate is None else gate * keep
        if return_gate:
            return out, gate
        return out


class GatedCrossAttention(CrossAttention):
    """Cross-attention whose output is modulated by a head-specific element-wise sigmoid gate.

    ``out = LN(X_q + Dropout(W_O · (σ(X_q W_g + b_g) ⊙ SDPA(X_q W_Q, X_kv W_K, X_kv W_V))))``.
    The gate has one entry per channel, so each head ``h`` owns the ``D_h`` channels
    ``h·D_h … (h+1)·D_h − 1`` of it: it is head-specific and element-wise as in the paper.

    Initialisation: ``W_g`` (a ``D × D`` :class:`torch.nn.Linear`) has its weight **and** bias set
    to zero, so ``σ = 0.5`` exactly, for every input, at initialisation; the paper zero-initialises
    the bias so that both modalities start on equal footing, and a zero weight makes that hold
    for any input rather than only on average. The gradient of ``W_g``'s weight is
    ``∂L/∂σ · σ'(0) · X_q``, non-zero in general, so the gate learns from the first step.
    ``W_Q, W_K, W_V, W_O`` keep PyTorch's default :class:`torch.nn.Linear` initialisation; the
    LayerNorm starts at unit scale and zero shift.

    Args:
        dim: channels ``D`` of both streams.
        num_heads: attention heads ``H``; must divide ``dim`` (paper: 4, so ``D_h = 16``).
        dropout: dropout probability after ``W_O`` (paper: 0.1).

    Example:
        >>> layer = GatedCrossAttention(16, num_heads=2).eval()
        >>> out, gate = layer(torch.randn(2, 5, 16), torch.randn(2, 5, 16), return_gate=True)
        >>> out.shape, bool((gate == 0.5).all())
        (torch.Size([2, 5, 16]), True)
    """

    def __init__(self, dim: int = 64, *, num_heads: int = 4, dropout: float = 0.1) -> None:
        super().__init__(dim, num_heads=num_heads, dropout=dropout)
        self.to_gate = nn.Linear(dim, dim)
        nn.init.zeros_(self.to_gate.weight)
        nn.init.zeros_(self.to_gate.bias)

    def gate(self, x_q: torch.Tensor) -> torch.Tensor:
        """Return ``σ(X_q W_g + b_g)``, shape ``(B, P, D)``."""
        return torch.sigmoid(self.to_gate(x_q))
