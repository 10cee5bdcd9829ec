"""Render-and-compare scores of pose hypotheses, and the rule that picks one.

Shape letters: B instances, H hypotheses per instance, C colour channels, S the crop side,
G the blocks of a crop.

Every term compares a hypothesis's rendering (:func:`~poseflow.verify.render.render_points`)
with the observation on the same crop (:func:`~poseflow.verify.render.crop_observation`), pixel
by pixel, and is a mean over a set of pixels, as in the VSD error of the BOP benchmark:

- the rendering's *visible* pixels are those not hidden by something nearer in the observed
  depth (rendered depth at most the observed depth plus ``visibility_tolerance``, or no observed
  depth there);
- depth agreement (:func:`depth_agreement`): the fraction of pixels where the visible rendering
  and the instance mask disagree or the depths differ by ``depth_tolerance`` or more, subtracted
  from 1, over the visible rendering and the masked pixels that have a depth;
- silhouette agreement (:func:`silhouette_agreement`): IoU of the visible rendering and the mask;
- appearance agreement (:func:`appearance_agreement`): on the pixels both cover, the local
  zero-mean normalised cross-correlation of rendered albedo and observed colour (white-balanced
  over the mask, :func:`balance_colors`), per channel, in small windows, weighted by how
  textured the rendering is in the window, averaged over the same pixels as the silhouette.
  Each window's correlation ignores a gain and an offset of each observed channel, so shading,
  white balance and exposure do not change it; where the model has no texture the weight is 0
  and the term stays at 0 for every hypothesis alike.

The total is the weighted mean of the three terms. Because each term is a sum over pixels, the
total splits exactly into the contributions of ``G`` blocks of pixels, kept as
:attr:`VerifierScore.evidence`. :func:`select_significant` uses them to decide whether a candidate
really beats the estimate: a one-sided paired test on the per-block differences, so the margin a
candidate must clear is the spread of the score itself on that instance, not a constant.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch

from poseflow._checks import check_mask, check_tensor
from poseflow.errors import ValueRangeError
from poseflow.verify.render import (
    ObservedCrops,
    PointRendering,
    box_sum,
    numpy_scalar,
    runs_compiled,
)

__all__ = [
    "VerifierScore",
    "appearance_agreement",
    "balance_colors",
    "depth_agreement",
    "score_renderings",
    "select_significant",
    "silhouette_agreement",
    "visible_rendering",
]

#: Relative contrast below which a window counts as flat noise in the correlation's
#: denominator (keeps the correlation of two flat windows near 0 instead of undefined).
_CONTRAST_FLOOR = 0.02
#: The smallest mean colour the relative contrast of a window divides by.
_LEAST_MEAN = 1e-3


@dataclass
class VerifierScore:
    """Scores of ``B x H`` pose hypotheses; every field is finite.

    Attributes:
        depth: depth agreement ``(B, H)`` in ``[0, 1]``.
        silhouette: IoU of visible rendering and mask ``(B, H)`` in ``[0, 1]``.
        appearance: texture-weighted local correlation ``(B, H)`` in ``[-1, 1]`` (0 for a
            texture-less model or without a colour image).
        total: weighted mean of the three ``(B, H)``.
        valid: ``(B, H)`` bool; False where the mask is empty, the masked depth has no valid
            pixel, the hypothesis shows nothing visible or was padding. Invalid entries hold 0.
        evidence: ``(B, H, G)`` contribution of each block of pixels to ``total`` (they sum to
            it).
        support: ``(B, H, G)`` bool, the blocks holding any pixel the terms are taken over.
    """

    depth: torch.Tensor
    silhouette: torch.Tensor
    appearance: torch.Tensor
    total: torch.Tensor
    valid: torch.Tensor
    evidence: torch.Tensor
    support: torch.Tensor

    def __len__(self) -> int:
        return int(self.total.shape[0])

    @classmethod
    def zeros(cls, B: int, H: int, G: int, *, like: torch.Tensor) -> VerifierScore:
        """The score of ``B x H`` unscored hypotheses on ``G`` blocks: zeros, all invalid.

        Every field is a tensor of its own (in ``like``'s dtype and device), so that it can be
        written into.

        Example:
            >>> VerifierScore.zeros(2, 3, 4, like=torch.zeros(1)).evidence.shape
            torch.Size([2, 3, 4])
        """
        zeros = [like.new_zeros(B, H) for _ in range(4)]
        flags = torch.zeros(B, H, dtype=torch.bool, device=like.device)
        support = torch.zeros(B, H, G, dtype=torch.bool, device=like.device)
        return cls(*zeros, flags, like.new_zeros(B, H, G), support)


def visible_rendering(
    rendered_depth: torch.Tensor,
    rendered_mask: torch.Tensor,
    observed_depth: torch.Tensor,
    visibility_tolerance: torch.Tensor,
) -> torch.Tensor:
    """The rendered pixels not hidden by a nearer observed surface (VSD's visibility).

    Args:
        rendered_depth: ``(B, H, S, S)`` metres.
        rendered_mask: ``(B, H, S, S)`` bool.
        observed_depth: ``(B, S, S)`` metres, 0 where missing.
        visibility_tolerance: ``(B,)`` metres.

    Returns:
        ``(B, H, S, S)`` bool: rendered, and either no observed depth or rendered depth at most
        the observed depth plus the tolerance.

    Example:
        >>> r = torch.tensor([1.0, 1.0, 2.0]).reshape(1, 1, 1, 3)
        >>> o = torch.tensor([0.0, 1.05, 1.5]).reshape(1, 1, 3)
        >>> visible_rendering(r, r > 0, o, torch.tensor([0.1]))
        tensor([[[[ True,  True, False]]]])
    """
    o = observed_depth[:, None]
    tol = visibility_tolerance[:, None, None, None]
    return rendered_mask & ((o <= 0) | (rendered_depth <= o + tol))


def depth_agreement(
    rendered_depth: torch.Tensor,
    visible: torch.Tensor,
    observed_depth: torch.Tensor,
    observed_mask: torch.Tensor,
    depth_tolerance: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel depth agreement, as in VSD.

    A pixel counts when the visible rendering covers it outside the mask (an error), or the mask
    covers it and the observed depth is there (masked pixels with no depth cannot be checked);
    it agrees when both cover it and the depths differ by less than the tolerance.

    Args:
        rendered_depth: ``(B, H, S, S)`` metres.
        visible: ``(B, H, S, S)`` bool, from :func:`visible_rendering`.
        observed_depth: ``(B, S, S)`` metres, 0 where missing.
        observed_mask: ``(B, S, S)`` bool.
        depth_tolerance: ``(B,)`` metres.

    Returns:
        ``(agree, support)``, both ``(B, H, S, S)`` bool; the term is
        ``agree.sum() / support.sum()`` per hypothesis.

    Example:
        >>> r = torch.tensor([1.0, 1.0, 1.0, 0.0]).reshape(1, 1, 1, 4)
        >>> o = torch.tensor([1.001, 1.2, 0.0, 1.0]).reshape(1, 1, 4)
        >>> m = torch.tensor([True, True, False, True]).reshape(1, 1, 4)
        >>> agree, support = depth_agreement(r, r > 0, o, m, torch.tensor([0.01]))
        >>> agree.flatten().tolist(), support.flatten().tolist()
        ([True, False, False, False], [True, True, True, True])
    """
    o = observed_depth[:, None]
    m = observed_mask[:, None]
    has = o > 0
    support = (visible & ~m) | (m & has)
    close = (rendered_depth - o).abs() < depth_tolerance[:, None, None, None]
    return visible & m & has & close, support


def silhouette_agreement(
    visible: torch.Tensor, observed_mask: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel silhouette agreement: the IoU of visible rendering and mask is a ratio of sums.

    Args:
        visible: ``(B, H, S, S)`` bool.
        observed_mask: ``(B, S, S)`` bool.

    Returns:
        ``(intersection, union)``, both ``(B, H, S, S)`` bool.

    Example:
        >>> v = torch.tensor([True, True, False]).reshape(1, 1, 1, 3)
        >>> m = torch.tensor([False, True, True]).reshape(1, 1, 3)
        >>> [x.sum().item() for x in silhouette_agreement(v, m)]
        [1, 3]
    """
    m = observed_mask[:, None]
    return visible & m, visible | m


def balance_colors(color: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Grey-world white balance over the masked pixels: each channel divided by its mean there.

    A gain per channel of the whole image (exposure, white balance, the light's colour) then
    changes nothing.

    Args:
        color: images ``(B, C, S, S)``.
        mask: ``(B, S, S)`` bool, the pixels the balance is measured on.

    Returns:
        ``(B, C, S, S)``, each channel of mean 1 over a non-empty mask (0 where it is empty).

    Example:
        >>> c = torch.rand(2, 3, 8, 8) + 0.1
        >>> m = torch.ones(2, 8, 8, dtype=torch.bool)
        >>> tint = torch.tensor([0.5, 1.0, 2.0]).reshape(1, 3, 1, 1)
        >>> torch.allclose(balance_colors(c, m), balance_colors(c * tint, m))
        True
    """
    w = mask[:, None].to(color.dtype)
    mean = ((color * w).sum((-2, -1)) / w.sum((-2, -1)).clamp_min(1))[..., None, None]
    tiny = torch.finfo(color.dtype).tiny
    return torch.where(mean > 0, color / mean.clamp_min(tiny), 0)


def appearance_agreement(
    rendered: torch.Tensor,
    observed: torch.Tensor,
    both: torch.Tensor,
    *,
    window: int,
    contrast_reference: float,
) -> torch.Tensor:
    """Per-pixel, texture-weighted local normalised cross-correlation of two colour images.

    In the ``window x window`` neighbourhood of each pixel, over the pixels ``both`` covers, each
    channel's rendered and observed values are correlated after removing their means and dividing
    by their deviations: a gain and an offset of an observed channel (shading, exposure, white
    balance) change nothing. Each channel's correlation is weighted by the rendered channel's
    relative contrast in the window (standard deviation over mean) divided by
    ``contrast_reference``, capped at 1, so flat parts of the model, where the correlation is
    only noise, carry no weight; the channels are averaged. Windows with fewer than half their
    pixels covered count 0.

    Args:
        rendered: rendered colour ``(B, H, C, S, S)``.
        observed: observed colour ``(B, C, S, S)``.
        both: ``(B, H, S, S)`` bool, the pixels both images cover.
        window: odd window side in pixels.
        contrast_reference: relative contrast that gets full weight.

    Returns:
        ``(B, H, S, S)`` values in ``[-1, 1]``, 0 outside ``both``.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> x = torch.rand(1, 1, 3, 16, 16, generator=g) + 0.5
        >>> both = torch.ones(1, 1, 16, 16, dtype=torch.bool)
        >>> same = appearance_agreement(x, 0.3 * x[:, 0] + 0.1, both, window=5,
        ...                             contrast_reference=0.1)
        >>> round(same[0, 0, 8, 8].item(), 2)
        0.99
    """
    if runs_compiled(rendered):
        return _appearance_compiled(rendered, observed, both, window, contrast_reference)
    return _appearance_tensors(rendered, observed, both, window, contrast_reference)


def _appearance_compiled(
    rendered: torch.Tensor,
    observed: torch.Tensor,
    both: torch.Tensor,
    window: int,
    contrast_reference: float,
) -> torch.Tensor:
    """:func:`appearance_agreement` by the compiled CPU kernel (float32 or float64), to rounding."""
    from poseflow.verify._score_cpu import appearance_kernel

    B, H, _, S, _ = rendered.shape
    out = torch.zeros(B, H, S, S, dtype=rendered.dtype)
    scalar = functools.partial(numpy_scalar, dtype=rendered.dtype)
    appearance_kernel(
        rendered.contiguous().numpy(), observed.to(rendered.dtype).contiguous().numpy(),
        both.contiguous().numpy(), window, scalar(_CONTRAST_FLOOR), scalar(contrast_reference),
        scalar(_LEAST_MEAN), scalar(torch.finfo(rendered.dtype).tiny), out.numpy(),
    )  # fmt: skip
    return out


def _appearance_tensors(
    rendered: torch.Tensor,
    observed: torch.Tensor,
    both: torch.Tensor,
    window: int,
    contrast_reference: float,
) -> torch.Tensor:
    """:func:`appearance_agreement` as tensor operations (any device)."""
    B, H, C, S, _ = rendered.shape
    w = both[:, :, None].to(rendered.dtype)  # (B, H, 1, S, S)
    x = rendered * w
    y = observed[:, None] * w
    stack = torch.stack((x, y, x * x, y * y, x * y), dim=2)  # (B, H, 5, C, S, S)
    sums = box_sum(torch.cat((w, stack.flatten(2, 3)), dim=2).reshape(-1, S, S), window)
    sums = sums.reshape(B, H, 1 + 5 * C, S, S)
    n = sums[:, :, :1]
    sx, sy, sxx, syy, sxy = sums[:, :, 1:].reshape(B, H, 5, C, S, S).unbind(2)
    n_safe = n.clamp_min(1)
    mx, my = sx / n_safe, sy / n_safe
    vx = (sxx / n_safe - mx * mx).clamp_min(0)
    vy = (syy / n_safe - my * my).clamp_min(0)
    cov = sxy / n_safe - mx * my
    floor_x = (_CONTRAST_FLOOR * mx).square()
    floor_y = (_CONTRAST_FLOOR * my).square()
    denom = ((vx + floor_x) * (vy + floor_y)).sqrt()
    tiny = torch.finfo(rendered.dtype).tiny
    ncc = torch.where(denom > 0, cov / denom.clamp_min(tiny), 0.0).clamp(-1.0, 1.0)
    contrast = vx.sqrt() / mx.abs().clamp_min(_LEAST_MEAN)
    weight = (contrast / contrast_reference).clamp(max=1.0)
    enough = both & (n[:, :, 0] >= (window * window + 1) // 2)
    return torch.where(enough, (weight * ncc).mean(2), 0.0)


def score_renderings(
    rendering: PointRendering,
    observed: ObservedCrops,
    *,
    depth_tolerance: torch.Tensor,
    visibility_tolerance: torch.Tensor,
    appearance_window: int,
    contrast_reference: float,
    weights: tuple[float, float, float],
    block_size: int,
    hypothesis_mask: torch.Tensor | None = None,
) -> VerifierScore:
    """Score renderings of ``B x H`` hypotheses against the observed crops.

    Args:
        rendering: renderings ``(B, H, ...)`` on ``S x S`` crops, their colour balanced as
            :func:`balance_colors` balances the observation's (or over the whole model).
        observed: the observation on the same crops ``(B, ...)``.
        depth_tolerance: ``(B,)`` metres.
        visibility_tolerance: ``(B,)`` metres.
        appearance_window: odd window side of the correlation.
        contrast_reference: see :func:`appearance_agreement`.
        weights: weights of depth, silhouette and appearance in the total.
        block_size: side of the evidence blocks, dividing ``S``.
        hypothesis_mask: ``(B, H)`` bool, False for padding hypotheses (scored invalid).

    Returns:
        A :class:`VerifierScore`.

    Raises:
        ShapeError: inconsistent shapes.
        ValueRangeError: ``block_size`` does not divide ``S`` or the weights are all 0.
    """
    sizes = check_tensor(rendering.depth, "rendering.depth", ("B", "H", "S", "S"))
    check_tensor(observed.depth, "observed.depth", ("B", "S", "S"), sizes=sizes)
    check_mask(observed.mask, "observed.mask", ("B", "S", "S"), sizes)
    S = sizes["S"]
    if hypothesis_mask is not None:
        check_mask(hypothesis_mask, "hypothesis_mask", ("B", "H"), sizes)
    if S % block_size:
        raise ValueRangeError(f"block_size {block_size} does not divide the crop side {S}")
    wd, ws, wa = (float(w) for w in weights)
    if not wd + ws + wa > 0:
        raise ValueRangeError("the weights must not all be 0")
    dtype = rendering.depth.dtype
    o_depth, o_mask = observed.depth.to(dtype), observed.mask
    visible = visible_rendering(
        rendering.depth, rendering.mask, o_depth, visibility_tolerance.to(dtype)
    )
    agree, support_d = depth_agreement(
        rendering.depth, visible, o_depth, o_mask, depth_tolerance.to(dtype)
    )
    inter, union = silhouette_agreement(visible, o_mask)
    if observed.color is not None and wa > 0:
        app = appearance_agreement(
            rendering.color,
            balance_colors(observed.color.to(dtype), o_mask),
            inter,
            window=appearance_window,
            contrast_reference=contrast_reference,
        )
    else:
        app = torch.zeros_like(rendering.depth)

    valid = (
        o_mask.any(-1).any(-1)[:, None]
        & (o_mask & (o_depth > 0)).any(-1).any(-1)[:, None]
        & visible.any(-1).any(-1)
    )
    if hypothesis_mask is not None:
        valid &= hypothesis_mask
    return _block_terms(agree, support_d, inter, union, app, valid, (wd, ws, wa), block_size)


def _block_terms(
    agree: torch.Tensor,
    support_d: torch.Tensor,
    inter: torch.Tensor,
    union: torch.Tensor,
    app: torch.Tensor,
    valid: torch.Tensor,
    weights: tuple[float, float, float],
    block_size: int,
) -> VerifierScore:
    """The score of per-pixel terms ``(B, H, S, S)``: their means and the blocks' evidence."""
    (B, H, S, _), dtype = app.shape, app.dtype
    wd, ws, wa = weights
    n_d = support_d.sum((-2, -1)).to(dtype)
    n_s = union.sum((-2, -1)).to(dtype)
    total_w = wd + ws + wa
    per_pixel = (
        wd * agree.to(dtype) / n_d.clamp_min(1)[..., None, None]
        + ws * inter.to(dtype) / n_s.clamp_min(1)[..., None, None]
        + wa * app / n_s.clamp_min(1)[..., None, None]
    ) / total_w
    per_pixel = torch.where(valid[..., None, None], per_pixel, 0.0)
    g = S // block_size
    evidence = per_pixel.reshape(B, H, g, block_size, g, block_size).sum((3, 5))
    covered = (support_d | union).reshape(B, H, g, block_size, g, block_size).any(5).any(3)
    zero = torch.zeros((), dtype=dtype, device=per_pixel.device)
    depth_term = torch.where(valid, agree.sum((-2, -1)).to(dtype) / n_d.clamp_min(1), zero)
    sil_term = torch.where(valid, inter.sum((-2, -1)).to(dtype) / n_s.clamp_min(1), zero)
    app_term = torch.where(valid, app.sum((-2, -1)) / n_s.clamp_min(1), zero)
    return VerifierScore(
        depth=depth_term,
        silhouette=sil_term,
        appearance=app_term,
        total=evidence.sum((-2, -1)),
        valid=valid,
        evidence=evidence.reshape(B, H, g * g),
        support=covered.reshape(B, H, g * g) & valid[..., None],
    )


def select_significant(
    score: VerifierScore, *, significance: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pick, per instance, hypothesis 0 (the estimate) unless a candidate clearly beats it.

    For each candidate ``h``, the per-block differences ``d_g = evidence[h, g] - evidence[0, g]``
    over the blocks either covers sum to the difference of the totals. Treating them as
    independent draws (blocks are larger than the sensor's noise correlation), the statistic
    ``t = mean(d) / (std(d) / sqrt(G))`` is a one-sided paired t-test of "the candidate explains
    the image better". A candidate can replace the estimate when ``t`` exceeds the normal
    quantile of ``1 - significance / m`` (Bonferroni over the ``m`` valid candidates, since the
    best of many noisy candidates looks better than it is); among those, the highest total wins.
    An invalid estimate gives way to the best valid candidate.

    Args:
        score: scores of ``(B, H)`` hypotheses, the estimate first.
        significance: the test's level, in ``(0, 1)``.

    Returns:
        ``(index (B,), statistic (B, H))``: the chosen hypothesis per instance (0 where the
        estimate stays, also where nothing is valid) and each candidate's ``t`` (0 for the
        estimate and for invalid candidates).

    Raises:
        ValueRangeError: ``significance`` outside ``(0, 1)``.

    Example:
        >>> ev = torch.tensor([[[0.1, 0.1, 0.1, 0.1], [0.2, 0.21, 0.19, 0.2]]])
        >>> s = VerifierScore(*[torch.zeros(1, 2)] * 3, ev.sum(-1),
        ...                   torch.ones(1, 2, dtype=torch.bool), ev, ev > 0)
        >>> index, t = select_significant(s, significance=0.01)
        >>> index.tolist(), round(t[0, 1].item(), 1)
        ([1], 24.5)
    """
    if not 0 < significance < 1:
        raise ValueRangeError(f"significance must lie in (0, 1), got {significance}")
    total, valid = score.total, score.valid
    B, H = total.shape
    dtype, device = total.dtype, total.device
    stat = torch.zeros(B, H, dtype=dtype, device=device)
    index = torch.zeros(B, dtype=torch.long, device=device)
    if H == 1:
        return index, stat
    diff = score.evidence[:, 1:] - score.evidence[:, :1]  # (B, H-1, G)
    blocks = score.support[:, 1:] | score.support[:, :1]
    count = blocks.sum(-1).to(dtype)
    mean = torch.where(blocks, diff, 0.0).sum(-1) / count.clamp_min(1)
    dev = torch.where(blocks, diff - mean[..., None], 0.0)
    var = dev.square().sum(-1) / (count - 1).clamp_min(1)
    se = (var / count.clamp_min(1)).sqrt()
    t = torch.where(
        se > 0, mean / se.clamp_min(torch.finfo(dtype).tiny), torch.sign(mean) * math.inf
    )
    usable = valid[:, 1:] & valid[:, :1] & (count >= 2)
    t = torch.where(usable, t, 0.0)
    stat[:, 1:] = torch.nan_to_num(t, posinf=torch.finfo(dtype).max)
    m = valid[:, 1:].sum(-1).clamp_min(1).to(torch.float64)
    z = torch.special.ndtri(1 - significance / m).to(dtype)  # (B,)
    passes = usable & (t > z[:, None]) & (mean > 0)
    cand_total = torch.where(passes, total[:, 1:], -math.inf)
    best_val, best = cand_total.max(-1)
    replace = torch.isfinite(best_val)
    index = torch.where(replace, best + 1, index)
    # the estimate shows nothing valid: the best valid candidate, if any
    fallback_val, fallback = torch.where(valid[:, 1:], total[:, 1:], -math.inf).max(-1)
    lost = ~valid[:, 0] & torch.isfinite(fallback_val)
    index = torch.where(lost, fallback + 1, index)
    return index, stat
