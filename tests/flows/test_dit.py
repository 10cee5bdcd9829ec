"""Tests of poseflow.flows.dit: the PointDiT velocity net."""

from __future__ import annotations

import shutil
from dataclasses import replace

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from poseflow.errors import ShapeError, ValueRangeError
from poseflow.flows.dit import (
    PRESETS,
    DiTBlock,
    PointDiT,
    PointDiTConfig,
    TanhGELU,
    sinusoidal_time_embedding,
)
from poseflow.flows.positional import PointPositionalEncoder
from poseflow.fusion import GatedCrossAttentionFusion

COND = PRESETS["tiny"].cond_dim


def model(*, attention="alternating", seed=0, dtype=torch.float32, device="cpu", trained=True):
    """A tiny model; ``trained`` moves the zero-initialised tensors off zero."""
    torch.manual_seed(seed)
    m = PointDiT.from_preset("tiny", attention=attention).to(device=device, dtype=dtype)
    if trained:
        gen = torch.Generator().manual_seed(seed + 1)
        with torch.no_grad():
            for p in m.parameters():
                if (p == 0).all():
                    p.copy_(0.2 * torch.randn(p.shape, generator=gen, dtype=dtype))
    return m.eval()


def inputs(b, n, *, seed, dtype=torch.float32, device="cpu"):
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(b, n, 3, generator=gen, dtype=dtype).to(device)
    t = torch.rand(b, generator=gen, dtype=dtype).to(device)
    c = torch.randn(b, n, COND, generator=gen, dtype=dtype).to(device)
    return x, t, c


def test_shape_dtype_device(device, dtype):
    m = model(dtype=dtype, device=device)
    x, t, c = inputs(2, 10, seed=0, dtype=dtype, device=device)
    v = m(x=x, t=t, condition=c, num_query=4)
    assert v.shape == (2, 10, 3) and v.dtype == dtype and v.device == x.device
    assert torch.isfinite(v).all()


def test_zero_velocity_and_identity_blocks_at_initialisation():
    m = model(trained=False)
    x, t, c = inputs(2, 8, seed=1)
    assert torch.equal(m(x, t, condition=c, num_query=4), torch.zeros(2, 8, 3))
    h = torch.randn(2, 8, m.config.hidden_dim, generator=torch.Generator().manual_seed(2))
    emb = m.time_embed(t)
    for block in m.blocks:
        assert torch.equal(block(h, emb), h)
        assert torch.equal(block(h, emb, split=3), h)


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_every_block_of_every_preset_starts_as_identity(preset):
    with torch.device("meta"):
        m = PointDiT.from_preset(preset)
    for block in m.blocks:
        assert block.ada[1].weight.is_meta  # counted, never materialised
    cfg = PRESETS[preset]
    block = DiTBlock(cfg.hidden_dim, num_heads=cfg.num_heads, mlp_ratio=cfg.mlp_ratio)
    h = torch.randn(1, 4, cfg.hidden_dim)
    assert torch.equal(block(h, torch.randn(1, cfg.hidden_dim)), h)


@settings(max_examples=8)
@given(seed=st.integers(0, 2**16), nq=st.integers(2, 6), nt=st.integers(2, 6))
def test_permutation_equivariance_within_each_cloud(seed, nq, nt):
    m = model(seed=seed % 7, dtype=torch.float64)
    x, t, c = inputs(2, nq + nt, seed=seed, dtype=torch.float64)
    gen = torch.Generator().manual_seed(seed)
    perm = torch.cat([torch.randperm(nq, generator=gen), nq + torch.randperm(nt, generator=gen)])
    v = m(x, t, condition=c, num_query=nq)
    v_perm = m(x[:, perm], t, condition=c[:, perm], num_query=nq)
    assert torch.allclose(v_perm, v[:, perm], atol=1e-10)


@settings(max_examples=8)
@given(seed=st.integers(0, 2**16), n=st.integers(2, 10))
def test_permutation_equivariance_over_all_points(seed, n):
    x, t, c = inputs(2, n, seed=seed, dtype=torch.float64)
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(seed))
    ids = torch.randint(0, 3, (2, n), generator=torch.Generator().manual_seed(seed + 1))
    glob = model(attention="global", dtype=torch.float64)
    assert torch.allclose(
        glob(x[:, perm], t, condition=c[:, perm]), glob(x, t, condition=c)[:, perm], atol=1e-10
    )
    alt = model(dtype=torch.float64)
    v = alt(x, t, condition=c, cloud_ids=ids)
    v_perm = alt(x[:, perm], t, condition=c[:, perm], cloud_ids=ids[:, perm])
    assert torch.allclose(v_perm, v[:, perm], atol=1e-10)


@settings(max_examples=8)
@given(
    seed=st.integers(0, 2**16),
    clouds=st.lists(st.tuples(st.integers(1, 5), st.integers(1, 5)), min_size=1, max_size=3),
    pad=st.integers(0, 3),
    layout=st.sampled_from(["num_query", "cloud_ids", "global"]),
)
def test_padding_does_not_change_valid_points(seed, clouds, pad, layout):
    """A padded batch of [Q ; T] instances equals each instance run alone, unpadded."""
    m = model(attention="global" if layout == "global" else "alternating", dtype=torch.float64)
    nq = max(q for q, _ in clouds) + pad
    nt = max(t for _, t in clouds) + pad
    x, t, c = inputs(len(clouds), nq + nt, seed=seed, dtype=torch.float64)
    idx = torch.arange(nq + nt)[None]
    q_len = torch.tensor([q for q, _ in clouds])[:, None]
    t_len = torch.tensor([n for _, n in clouds])[:, None]
    mask = (idx < q_len) | ((idx >= nq) & (idx < nq + t_len))
    extra = {"num_query": nq} if layout == "num_query" else {}
    if layout == "cloud_ids":
        extra = {"cloud_ids": (idx >= nq).long().expand(len(clouds), -1)}
    v = m(x, t, condition=c, mask=mask, **extra)
    assert torch.equal(v[~mask], torch.zeros_like(v[~mask]))
    for i, (q, _) in enumerate(clouds):
        keep = mask[i]
        one = {"num_query": q} if layout == "num_query" else {}
        if layout == "cloud_ids":
            one = {"cloud_ids": extra["cloud_ids"][i : i + 1, keep]}
        alone = m(x[i : i + 1, keep], t[i : i + 1], condition=c[i : i + 1, keep], **one)
        assert torch.allclose(v[i, keep], alone[0], atol=1e-10)


def _model_of_depth(depth, attention, seed):
    """A trained-looking tiny model with ``depth`` blocks."""
    torch.manual_seed(seed)
    m = PointDiT(replace(PRESETS["tiny"], depth=depth, attention=attention)).double()
    gen = torch.Generator().manual_seed(seed + 1)
    with torch.no_grad():
        for p in m.parameters():
            p.add_(0.2 * torch.randn(p.shape, generator=gen, dtype=p.dtype))
    return m.eval()


@settings(max_examples=12, deadline=None)
@given(
    seed=st.integers(0, 2**16),
    depth=st.integers(1, 4),
    attention=st.sampled_from(["alternating", "global"]),
    groups=st.integers(1, 3),
    repeats=st.integers(1, 4),
    nq=st.integers(1, 5),
    nt=st.integers(1, 5),
    padded=st.booleans(),
)
def test_fixed_query_shortcuts_change_no_velocity_that_is_used(
    seed, depth, attention, groups, repeats, nq, nt, padded
):
    """frozen_query / query_repeats: the target's velocities of the plain forward pass."""
    m = _model_of_depth(depth, attention, seed)
    gen = torch.Generator().manual_seed(seed)
    B, L = groups * repeats, nq + nt
    x, t, c = inputs(B, L, seed=seed, dtype=torch.float64)
    t = torch.rand(groups, generator=gen, dtype=torch.float64).repeat_interleave(repeats)
    mask = torch.rand(B, L, generator=gen) > 0.3 if padded else torch.ones(B, L, dtype=torch.bool)
    for value in (x, c, mask):  # one query per group, its own targets per row
        value[:, :nq] = value[::repeats, :nq].repeat_interleave(repeats, dim=0)
    plain = m(x, t, condition=c, mask=mask, num_query=nq)
    shared = m(x, t, condition=c, mask=mask, num_query=nq, query_repeats=repeats)
    frozen = m(x, t, condition=c, mask=mask, num_query=nq, frozen_query=True)
    both = m(x, t, condition=c, mask=mask, num_query=nq, frozen_query=True, query_repeats=repeats)
    assert torch.allclose(shared, plain, atol=1e-12)
    for v in (frozen, both):
        assert torch.allclose(v[:, nq:], plain[:, nq:], atol=1e-12)
        assert torch.equal(v[:, :nq], torch.zeros(B, nq, 3, dtype=v.dtype))


def test_fixed_query_shortcuts_refuse_what_they_cannot_do():
    m = model(dtype=torch.float64)
    x, t, c = inputs(4, 6, seed=7, dtype=torch.float64)
    t = t[:1].expand(4)
    for value in (x, c):
        value[:, :3] = value[:1, :3]
    with pytest.raises(ValueRangeError, match="num_query"):
        m(x, t, condition=c, frozen_query=True)
    with pytest.raises(ValueRangeError, match="divisor"):
        m(x, t, condition=c, num_query=3, query_repeats=3)
    with pytest.raises(ValueRangeError, match="integer"):
        m(x, t, condition=c, num_query=3, query_repeats=True)
    m(x, t, condition=c, num_query=3, query_repeats=4)  # one group of equal rows
    other = x.clone()
    other[2, 1] += 1.0
    with pytest.raises(ValueRangeError, match="differ"):
        m(other, t, condition=c, num_query=3, query_repeats=2)
    with pytest.raises(ValueRangeError, match="differ"):
        m(x, torch.arange(4.0, dtype=torch.float64) / 4, condition=c, num_query=3, query_repeats=2)


def test_num_query_and_cloud_ids_agree(dtype, tol):
    m = model(dtype=dtype)
    x, t, c = inputs(2, 9, seed=3, dtype=dtype)
    mask = torch.ones(2, 9, dtype=torch.bool)
    mask[1, 3] = mask[1, 8] = False
    ids = (torch.arange(9) >= 4).long().expand(2, -1)
    a = m(x, t, condition=c, mask=mask, num_query=4)
    b = m(x, t, condition=c, mask=mask, cloud_ids=ids)
    assert torch.allclose(a, b, atol=10 * tol)


def test_within_cloud_blocks_keep_clouds_apart():
    """In the first (within-cloud) block, moving a target point does not move query tokens."""
    m = model()
    x, t, c = inputs(1, 8, seed=4)
    emb = m.time_embed(t)
    h = m.x_embed(x) + m.cond_embed(c)
    h2 = h.clone()
    h2[0, 6] += torch.randn(h.shape[-1], generator=torch.Generator().manual_seed(5))
    block = m.blocks[0]
    assert block.within_cloud and not m.blocks[1].within_cloud
    assert torch.allclose(block(h, emb, split=4)[0, :4], block(h2, emb, split=4)[0, :4])
    assert not torch.allclose(m.blocks[1](h, emb)[0, :4], m.blocks[1](h2, emb)[0, :4])


def test_an_empty_cloud_gives_finite_zeros():
    m = model()
    x, t, c = inputs(2, 6, seed=5)
    mask = torch.ones(2, 6, dtype=torch.bool)
    mask[1, 3:] = False  # the second instance has no target point
    v = m(x, t, condition=c, mask=mask, num_query=3)
    assert torch.isfinite(v).all() and torch.equal(v[1, 3:], torch.zeros(3, 3))


def test_gradients_reach_every_parameter():
    m = model().train()
    x, t, c = inputs(2, 8, seed=6)
    mask = torch.ones(2, 8, dtype=torch.bool)
    mask[0, 7] = False
    target = torch.randn(2, 8, 3, generator=torch.Generator().manual_seed(7))
    ((m(x, t, condition=c, mask=mask, num_query=4) - target) ** 2).mean().backward()
    for name, p in m.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name


def test_at_initialisation_the_output_layer_learns_first():
    m = model(trained=False).train()
    x, t, c = inputs(2, 8, seed=8)
    target = torch.randn(2, 8, 3, generator=torch.Generator().manual_seed(9))
    ((m(x, t, condition=c, num_query=4) - target) ** 2).mean().backward()
    assert m.final.out.weight.grad.abs().sum() > 0
    opt = torch.optim.SGD(m.parameters(), lr=0.5)
    opt.step()
    assert m(x, t, condition=c, num_query=4).abs().sum() > 0


def test_gradcheck_float64():
    torch.manual_seed(0)
    cfg = PointDiTConfig(cond_dim=2, hidden_dim=4, depth=2, num_heads=2, time_frequency_dim=4)
    m = PointDiT(cfg).double()
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for p in m.parameters():
            if (p == 0).all():
                p.copy_(0.5 * torch.randn(p.shape, generator=gen, dtype=torch.float64))
    x = torch.randn(1, 4, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    c = torch.randn(1, 4, 2, generator=gen, dtype=torch.float64, requires_grad=True)
    t = torch.tensor([0.3], dtype=torch.float64, requires_grad=True)
    mask = torch.tensor([[True, True, True, False]])
    assert torch.autograd.gradcheck(
        lambda a, b, s: m(a, s, condition=b, mask=mask, num_query=2), (x, c, t)
    )


def test_time_may_be_a_scalar_and_of_another_dtype():
    m = model()
    x, _, c = inputs(3, 6, seed=10)
    a = m(x, torch.tensor(0.25), condition=c, num_query=3)
    b = m(x, torch.full((3,), 0.25, dtype=torch.float64), condition=c, num_query=3)
    assert torch.allclose(a, b, atol=1e-4)  # float64 times give slightly finer sinusoids
    assert not torch.allclose(a, m(x, torch.tensor(0.75), condition=c, num_query=3))


def test_time_embedding_keeps_float64_resolution_and_lifts_half():
    t = torch.tensor([0.5, 0.5 + 1e-10], dtype=torch.float64)
    e = sinusoidal_time_embedding(t, 64)
    assert e.dtype == torch.float64 and not torch.equal(e[0], e[1])
    h = sinusoidal_time_embedding(torch.tensor([0.5], dtype=torch.float16), 9)
    assert h.dtype == torch.float32 and h.shape == (1, 9) and h[0, -1] == 0
    e0 = sinusoidal_time_embedding(torch.zeros(1), 8)
    assert torch.equal(e0, torch.tensor([[1.0, 1, 1, 1, 0, 0, 0, 0]]))


def test_paper_preset_parameter_count_within_two_percent_of_43_1m():
    """Fusion + positional encoder + DiT: the trainable networks of the paper's table."""
    with torch.device("meta"):
        parts = (
            GatedCrossAttentionFusion(),
            PointPositionalEncoder(64),
            PointDiT.from_preset("paper"),
        )
    total = sum(p.numel() for part in parts for p in part.parameters() if p.requires_grad)
    assert PRESETS["paper"].cond_dim == 64 + 64
    assert abs(total - 43.1e6) / 43.1e6 < 0.02, total


def test_presets_are_ordered_by_size():
    with torch.device("meta"):
        sizes = [
            sum(p.numel() for p in PointDiT.from_preset(n).parameters())
            for n in ("tiny", "small", "paper")
        ]
    assert sizes == sorted(sizes) and sizes[0] < 1e5 and sizes[1] < 3e6


def test_bad_configuration_and_inputs_raise():
    with pytest.raises(ValueRangeError, match="unknown preset"):
        PointDiT.from_preset("huge")
    with pytest.raises(ValueRangeError):
        PointDiTConfig(hidden_dim=30, num_heads=4)
    with pytest.raises(ValueRangeError):
        PointDiTConfig(attention="local")  # type: ignore[arg-type]
    with pytest.raises(TypeError):
        PointDiTConfig(64)  # type: ignore[misc]
    m = model()
    x, t, c = inputs(2, 6, seed=11)
    with pytest.raises(ValueRangeError, match="num_query or cloud_ids"):
        m(x, t, condition=c)
    with pytest.raises(ValueRangeError):
        m(x, t, condition=c, num_query=6)
    with pytest.raises(ShapeError):
        m(x, t, condition=c[..., :5], num_query=3)
    with pytest.raises(ShapeError):
        m(x, t[:1], condition=c, num_query=3)
    with pytest.raises(ShapeError):
        m(x, t, condition=c.double(), num_query=3)
    with pytest.raises(ShapeError):
        m(x, t, condition=c, mask=torch.ones(2, 6), num_query=3)
    with pytest.raises(ShapeError):
        m(x, t, condition=c, cloud_ids=torch.zeros(2, 6))
    with pytest.raises(TypeError):
        m(x, t, c)  # the condition is keyword-only


@pytest.mark.slow
@pytest.mark.skipif(
    shutil.which("cc") is None and shutil.which("gcc") is None, reason="no C compiler"
)
def test_torch_compile_matches_eager_on_cpu():
    m = model()
    x, t, c = inputs(2, 10, seed=12)
    mask = torch.ones(2, 10, dtype=torch.bool)
    mask[1, 3:5] = mask[1, 8:] = False
    compiled = torch.compile(m)
    with torch.no_grad():
        for kwargs in ({"num_query": 5}, {"num_query": 5, "mask": mask}):
            expected = m(x, t, condition=c, **kwargs)
            assert torch.allclose(compiled(x, t, condition=c, **kwargs), expected, atol=1e-5)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@settings(max_examples=30, deadline=None)
@given(scale=st.floats(0.01, 30.0), seed=st.integers(0, 2**31 - 1))
def test_tanh_gelu_is_pytorchs_tanh_gelu(dtype, scale, seed):
    """The sigmoid form equals F.gelu(approximate="tanh") to rounding; F.gelu with gradients."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(3, 5, 64, generator=g, dtype=dtype) * scale
    expected = torch.nn.functional.gelu(x, approximate="tanh")
    with torch.no_grad():
        fast = TanhGELU()(x)
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    assert fast.dtype == dtype and torch.allclose(fast, expected, rtol=tol, atol=tol)
    leaf = x.clone().requires_grad_(True)
    out = TanhGELU()(leaf)
    assert torch.equal(out, torch.nn.functional.gelu(leaf, approximate="tanh"))
    out.sum().backward()
    assert leaf.grad is not None and torch.isfinite(leaf.grad).all()


def test_dit_blocks_load_weights_saved_with_nn_gelu():
    """Replacing nn.GELU(approximate="tanh") left the state dict's keys as they were."""
    block = DiTBlock(16, num_heads=2)
    assert isinstance(block.mlp[1], TanhGELU)
    assert sorted(k for k in block.state_dict() if k.startswith("mlp.")) == [
        "mlp.0.bias",
        "mlp.0.weight",
        "mlp.2.bias",
        "mlp.2.weight",
    ]


@pytest.mark.parametrize("bf16", [False, True])
def test_cpu_inference_runs_the_mlp_in_chunks_with_the_same_values(monkeypatch, bf16):
    import poseflow.flows.dit as dit_module

    m = model()
    x, t, c = inputs(300, 10, seed=11)  # 300 rows of 10 tokens
    calls = []
    mlp_forward = m.blocks[0].mlp.forward

    def counted(y):
        calls.append(y.shape[0])
        return mlp_forward(y)

    # 2,048 tokens of the tiny preset's 64 hidden float32 values (half as many bytes in bfloat16)
    monkeypatch.setattr(dit_module, "_MLP_CHUNK_BYTES", 2048 * 64 * 4)
    monkeypatch.setattr(m.blocks[0].mlp, "forward", counted)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
        chunked = m(x, t, condition=c, num_query=4)
        monkeypatch.setattr(dit_module, "_MLP_CHUNK_BYTES", 10**12)
        whole = m(x, t, condition=c, num_query=4)
    assert calls[:-1] == ([300] if bf16 else [204, 96]) and calls[-1] == 300
    assert torch.equal(chunked, whole)


def test_an_all_valid_mask_is_the_same_as_none():
    from poseflow.flows.dit import _key_mask

    m = model()
    x, t, c = inputs(3, 8, seed=12)
    every = torch.ones(3, 8, dtype=torch.bool)
    assert _key_mask(every) is None and _key_mask(None) is None
    some = every.clone()
    some[1, 2] = False
    assert _key_mask(some).shape == (3, 1, 1, 8)
    with torch.no_grad():
        for kw in ({"num_query": 4}, {"num_query": 4, "frozen_query": True}):
            assert torch.equal(m(x, t, condition=c, mask=every, **kw), m(x, t, condition=c, **kw))
