"""Tests of the render-and-compare terms and of the selection rule."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from poseflow.errors import ValueRangeError
from poseflow.verify import (
    ObservedCrops,
    PointRendering,
    VerifierScore,
    appearance_agreement,
    balance_colors,
    depth_agreement,
    score_renderings,
    select_significant,
    silhouette_agreement,
    visible_rendering,
)

S = 16


def textured(
    seed: int, B: int = 1, H: int = 1, C: int = 3, dtype: torch.dtype = torch.float64
) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return 0.2 + torch.rand(B, H, C, S, S, generator=g, dtype=dtype)


@given(
    seed=st.integers(0, 2**31 - 1),
    gain=st.floats(0.05, 20.0),
    offset=st.floats(-0.5, 0.5),
    double=st.booleans(),
)
def test_appearance_ignores_gain_and_offset(
    seed: int, gain: float, offset: float, double: bool
) -> None:
    dtype = torch.float64 if double else torch.float32
    x = textured(seed, dtype=dtype)
    g = torch.Generator().manual_seed(seed + 1)
    y = (x[:, 0] + 0.05 * torch.rand(1, 3, S, S, generator=g, dtype=dtype)).clamp_min(0)
    both = torch.ones(1, 1, S, S, dtype=torch.bool)
    kw = {"window": 5, "contrast_reference": 0.1}
    ref = appearance_agreement(x, y, both, **kw)
    # the contrast floor is relative to the local mean, so an offset moves it a little
    moved = appearance_agreement(x, gain * y + offset * y.mean(), both, **kw)
    # a different gain and offset per channel (a colour cast) changes nothing either
    cast = torch.tensor([gain, 1.0, 0.5], dtype=dtype).reshape(1, 3, 1, 1)
    tinted = appearance_agreement(x, cast * y + offset * y.mean(), both, **kw)
    torch.testing.assert_close(tinted, ref, atol=0.02, rtol=0)
    assert ref.dtype == dtype
    assert (ref[both] > 0.5).float().mean() > 0.9
    torch.testing.assert_close(moved, ref, atol=0.02, rtol=0)
    only_gain = appearance_agreement(x, gain * y, both, **kw)
    torch.testing.assert_close(only_gain, ref, atol=1e-4 if not double else 1e-9, rtol=0)


@given(seed=st.integers(0, 2**31 - 1), double=st.booleans())
def test_balance_colors_ignores_colour_gains(seed: int, double: bool) -> None:
    dtype = torch.float64 if double else torch.float32
    g = torch.Generator().manual_seed(seed)
    color = torch.rand(2, 3, S, S, generator=g, dtype=dtype) + 0.01
    mask = torch.rand(2, S, S, generator=g) > 0.3
    gains = 0.1 + 3 * torch.rand(1, 3, 1, 1, generator=g, dtype=dtype)
    balanced = balance_colors(color, mask)
    torch.testing.assert_close(balance_colors(color * gains, mask), balanced)
    w = mask[:, None].to(dtype)
    means = (balanced * w).sum((-2, -1)) / w.sum((-2, -1))
    torch.testing.assert_close(means, torch.ones(2, 3, dtype=dtype))


def test_appearance_of_flat_model_is_zero_and_of_mismatch_is_low() -> None:
    both = torch.ones(1, 1, S, S, dtype=torch.bool)
    kw = {"window": 5, "contrast_reference": 0.1}
    y = textured(0)[:, 0]
    flat_model = torch.full((1, 1, 3, S, S), 0.5, dtype=torch.float64)
    flat = appearance_agreement(flat_model, y, both, **kw)
    assert flat.abs().max() < 1e-6
    other = appearance_agreement(textured(5), y, both, **kw)
    same = appearance_agreement(textured(0), y, both, **kw)
    assert same.mean() > 0.9 and other.mean().abs() < 0.2
    none = appearance_agreement(textured(0), y, torch.zeros_like(both), **kw)
    assert (none == 0).all()


def test_depth_and_silhouette_closed_form() -> None:
    r = torch.zeros(1, 1, 1, 6, dtype=torch.float64)
    r[..., :4] = 1.0
    o = torch.tensor([[[1.001, 1.2, 0.0, 0.8, 1.0, 0.0]]], dtype=torch.float64)
    m = torch.tensor([[[True, True, True, True, True, False]]])
    vis = visible_rendering(r, r > 0, o, torch.tensor([0.1], dtype=torch.float64))
    # pixel 3: rendered 1.0 behind observed 0.8 by more than 0.1: hidden
    assert vis.flatten().tolist() == [True, True, True, False, False, False]
    agree, support = depth_agreement(r, vis, o, m, torch.tensor([0.01], dtype=torch.float64))
    assert agree.flatten().tolist() == [True, False, False, False, False, False]
    # pixel 2 is masked but has no depth: not counted; pixel 3 and 4 are masked misses
    assert support.flatten().tolist() == [True, True, False, True, True, False]
    inter, union = silhouette_agreement(vis, m)
    assert int(inter.sum()) == 3 and int(union.sum()) == 5


def crops_and_renders(H: int, B: int = 1) -> tuple[PointRendering, ObservedCrops]:
    depth = torch.ones(B, S, S, dtype=torch.float64)
    mask = torch.zeros(B, S, S, dtype=torch.bool)
    mask[:, 4:12, 4:12] = True
    tint = torch.tensor([0.9, 0.6, 0.3], dtype=torch.float64).reshape(1, 3, 1, 1)
    albedo = textured(7, B, 1)[:, 0]
    color = albedo * tint
    r_depth = depth[:, None].repeat(1, H, 1, 1)
    r_mask = mask[:, None].repeat(1, H, 1, 1)
    r_color = albedo[:, None].repeat(1, H, 1, 1, 1)
    return PointRendering(r_depth, r_mask, r_color), ObservedCrops(depth, mask, color)


def score(render: PointRendering, obs: ObservedCrops, **kw: object) -> VerifierScore:
    B = obs.depth.shape[0]
    args = {
        "depth_tolerance": torch.full((B,), 0.01, dtype=torch.float64),
        "visibility_tolerance": torch.full((B,), 0.05, dtype=torch.float64),
        "appearance_window": 5,
        "contrast_reference": 0.1,
        "weights": (1.0, 1.0, 1.0),
        "block_size": 4,
    }
    args.update(kw)
    return score_renderings(render, obs, **args)  # type: ignore[arg-type]


def test_perfect_rendering_scores_one_and_evidence_sums_to_total() -> None:
    render, obs = crops_and_renders(2)
    render.depth[0, 1, 4:12, 4:8] += 0.05  # half of hypothesis 1 is 5 cm too far
    out = score(render, obs)
    assert out.valid.all()
    torch.testing.assert_close(out.depth[0, 0], torch.tensor(1.0, dtype=torch.float64))
    torch.testing.assert_close(out.silhouette[0, 0], torch.tensor(1.0, dtype=torch.float64))
    assert out.appearance[0, 0] > 0.6
    assert out.depth[0, 1] < 0.6 and out.total[0, 1] < out.total[0, 0]
    torch.testing.assert_close(out.evidence.sum(-1), out.total)
    expected = (out.depth + out.silhouette + out.appearance) / 3
    torch.testing.assert_close(out.total, expected)


def test_empty_mask_or_no_depth_is_flagged_and_finite() -> None:
    render, obs = crops_and_renders(3, B=3)
    obs.mask[0] = False  # no mask
    obs.depth[1] = 0.0  # no depth
    render.mask[2, 2] = False  # hypothesis shows nothing
    pad = torch.ones(3, 3, dtype=torch.bool)
    pad[2, 1] = False  # padding
    out = score(render, obs, hypothesis_mask=pad)
    assert out.valid.tolist() == [[False] * 3, [False] * 3, [True, False, False]]
    for field in ("depth", "silhouette", "appearance", "total", "evidence"):
        value = getattr(out, field)
        assert torch.isfinite(value).all()
        assert (value[~out.valid] == 0).all()
    index, stat = select_significant(out, significance=0.01)
    assert index.tolist() == [0, 0, 0] and torch.isfinite(stat).all()


def test_batched_scores_equal_per_instance() -> None:
    render, obs = crops_and_renders(2, B=3)
    g = torch.Generator().manual_seed(0)
    render.depth += 0.02 * torch.rand(render.depth.shape, generator=g, dtype=torch.float64)
    out = score(render, obs)
    for b in range(3):
        one = score(
            PointRendering(
                render.depth[b : b + 1], render.mask[b : b + 1], render.color[b : b + 1]
            ),
            ObservedCrops(obs.depth[b : b + 1], obs.mask[b : b + 1], obs.color[b : b + 1]),
        )
        torch.testing.assert_close(one.total[0], out.total[b])
        torch.testing.assert_close(one.evidence[0], out.evidence[b])


def make_score(evidence: torch.Tensor, valid: torch.Tensor | None = None) -> VerifierScore:
    B, H, _ = evidence.shape
    z = torch.zeros(B, H, dtype=evidence.dtype)
    valid = torch.ones(B, H, dtype=torch.bool) if valid is None else valid
    return VerifierScore(z, z, z, evidence.sum(-1), valid, evidence, evidence != 0)


@given(seed=st.integers(0, 2**31 - 1), G=st.integers(20, 80))
def test_selection_keeps_estimate_against_noise(seed: int, G: int) -> None:
    """Candidates that differ from the estimate only by noise replace it rarely."""
    g = torch.Generator().manual_seed(seed)
    base = 0.5 + torch.rand(200, 1, G, generator=g, dtype=torch.float64)
    noise = 0.05 * torch.randn(200, 3, G, generator=g, dtype=torch.float64)
    ev = torch.cat((base, base + noise), dim=1)  # (200, 4, G)
    index, _ = select_significant(make_score(ev), significance=0.01)
    # level 1 % over the instances (plus the t vs normal quantile slack at small G)
    assert (index != 0).float().mean() < 0.05


def test_selection_takes_a_clear_winner_and_the_best_of_several() -> None:
    g = torch.Generator().manual_seed(0)
    base = 0.5 + torch.rand(1, 1, 40, generator=g, dtype=torch.float64)
    noise = 0.01 * torch.randn(1, 3, 40, generator=g, dtype=torch.float64)
    ev = torch.cat((base, base + noise + torch.tensor([0.0, 0.05, 0.1]).reshape(1, 3, 1)), 1)
    index, stat = select_significant(make_score(ev), significance=0.01)
    assert index.tolist() == [3]
    assert stat[0, 0] == 0 and stat[0, 2] > 5 and stat[0, 3] > stat[0, 2]


def test_selection_replaces_an_invalid_estimate_and_ignores_invalid_candidates() -> None:
    ev = torch.rand(2, 3, 10, dtype=torch.float64)
    valid = torch.tensor([[False, True, True], [True, False, False]])
    ev[0, 2] += 1.0
    ev[1, 1] += 5.0  # invalid candidate: never chosen
    index, stat = select_significant(make_score(ev, valid), significance=0.01)
    assert index.tolist() == [2, 0]
    assert stat[1, 1] == 0


def test_bonferroni_makes_many_candidates_harder() -> None:
    g = torch.Generator().manual_seed(1)
    base = 1 + torch.rand(1, 1, 30, generator=g, dtype=torch.float64)
    e = torch.randn(30, generator=g, dtype=torch.float64)
    e = (e - e.mean()) / e.std()
    lift = base + 0.03 * (2.2 / 30**0.5 + e)  # per-block gains with t = 2.2 exactly
    _, stat = select_significant(make_score(torch.cat((base, lift), 1)), significance=0.05)
    assert float(stat[0, 1]) == pytest.approx(2.2)
    one = torch.special.ndtri(torch.tensor(1 - 0.05)).item()
    many = torch.special.ndtri(torch.tensor(1 - 0.05 / 20)).item()
    assert one < 2.2 < many  # passes alone, fails among 20 candidates
    ev_one = torch.cat((base, lift), 1)
    ev_many = torch.cat((base, lift, base.expand(1, 19, 30) - 1.0), 1)
    assert select_significant(make_score(ev_one), significance=0.05)[0].item() == 1
    assert select_significant(make_score(ev_many), significance=0.05)[0].item() == 0


def test_bad_arguments_raise() -> None:
    render, obs = crops_and_renders(1)
    with pytest.raises(ValueRangeError):
        score(render, obs, block_size=5)
    with pytest.raises(ValueRangeError):
        score(render, obs, weights=(0.0, 0.0, 0.0))
    with pytest.raises(ValueRangeError):
        select_significant(make_score(torch.ones(1, 2, 4)), significance=1.5)
    assert math.isfinite(float(score(render, obs).total))


@given(
    seed=st.integers(0, 2**31 - 1),
    B=st.integers(1, 2),
    H=st.integers(1, 3),
    C=st.integers(1, 3),
    half=st.integers(1, 3),
    double=st.booleans(),
)
def test_compiled_appearance_equals_the_tensor_one_to_rounding(
    seed: int, B: int, H: int, C: int, half: int, double: bool
) -> None:
    from poseflow.verify.score import _appearance_compiled, _appearance_tensors

    dtype = torch.float64 if double else torch.float32
    g = torch.Generator().manual_seed(seed)
    S = 12
    rendered = torch.rand(B, H, C, S, S, generator=g).to(dtype)
    rendered[..., :4, :] = 0.5  # flat windows: the contrast floor and a zero weight
    observed = (torch.rand(B, C, S, S, generator=g) * 2).to(dtype)
    both = torch.rand(B, H, S, S, generator=g) > 0.3
    args = (rendered, observed, both, 2 * half + 1, 0.1)
    compiled, tensors = _appearance_compiled(*args), _appearance_tensors(*args)
    assert compiled.dtype == dtype and (tensors != 0).any()
    assert torch.equal(compiled != 0, tensors != 0)  # the same windows count
    eps = torch.finfo(dtype).eps
    torch.testing.assert_close(compiled, tensors, rtol=0, atol=16 * eps)
