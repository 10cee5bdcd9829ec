"""Tests of poseflow.fusion.blocks: the four fusion blocks behind one call signature."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from poseflow.errors import ShapeError, ValueRangeError
from poseflow.fusion import (
    FUSIONS,
    ConcatMLPFusion,
    CrossAttentionFusion,
    Fusion,
    FusionGates,
    GatedCrossAttentionFusion,
    SumFusion,
    build_fusion,
)

NAMES = sorted(FUSIONS)


def make(name: str, dim: int = 8, *, seed: int = 0, dtype=torch.float32, device="cpu"):
    torch.manual_seed(seed)
    kwargs = {"dim": dim}
    if name in ("gated", "cross"):
        kwargs["num_heads"] = 2
    block = build_fusion(name, **kwargs).to(device=device, dtype=dtype).eval()
    gen = torch.Generator().manual_seed(seed + 1)
    with torch.no_grad():  # move the gates off their constant start so they depend on the input
        for p in block.parameters():
            if (p == 0).all():
                p.copy_(0.3 * torch.randn(p.shape, generator=gen, dtype=dtype))
    return block


def streams(b, p, d, *, seed, dtype=torch.float32, device="cpu"):
    gen = torch.Generator().manual_seed(seed)
    g = torch.randn(b, p, d, generator=gen, dtype=dtype).to(device)
    s = torch.randn(b, p, d, generator=gen, dtype=dtype).to(device)
    return g, s


@pytest.mark.parametrize("name", NAMES)
def test_shape_dtype_device_and_unit_norm(name, device, dtype, tol):
    block = make(name, dtype=dtype, device=device)
    g, s = streams(3, 7, 8, seed=1, dtype=dtype, device=device)
    mask = torch.ones(3, 7, dtype=torch.bool, device=device)
    mask[1, 4:] = False
    out = block(g, s, mask)
    assert out.shape == (3, 7, 8)
    assert out.dtype == dtype and out.device == g.device
    norms = out.norm(dim=-1)
    assert torch.allclose(norms[mask], torch.ones_like(norms[mask]), atol=tol)
    assert torch.equal(out[~mask], torch.zeros_like(out[~mask]))


@settings(max_examples=10)
@given(seed=st.integers(0, 2**16), p=st.integers(2, 9), name=st.sampled_from(NAMES))
def test_permutation_equivariance(seed, p, name):
    block = make(name, seed=seed, dtype=torch.float64)
    g, s = streams(2, p, 8, seed=seed, dtype=torch.float64)
    perm = torch.randperm(p, generator=torch.Generator().manual_seed(seed))
    out = block(g, s)
    out_perm = block(g[:, perm], s[:, perm])
    assert torch.allclose(out_perm, out[:, perm], atol=1e-10)


@settings(max_examples=10)
@given(
    seed=st.integers(0, 2**16),
    sizes=st.lists(st.integers(1, 6), min_size=1, max_size=3),
    extra=st.integers(1, 4),
    name=st.sampled_from(NAMES),
)
def test_padding_does_not_change_valid_points(seed, sizes, extra, name):
    """The batched, padded result equals the per-instance result on the valid points."""
    block = make(name, seed=seed, dtype=torch.float64)
    p = max(sizes) + extra
    g, s = streams(len(sizes), p, 8, seed=seed, dtype=torch.float64)  # padding: random values
    mask = torch.arange(p)[None] < torch.tensor(sizes)[:, None]
    out = block(g, s, mask)
    for i, n in enumerate(sizes):
        alone = block(g[i : i + 1, :n], s[i : i + 1, :n])
        assert torch.allclose(out[i, :n], alone[0], atol=1e-10)
        assert torch.equal(out[i, n:], torch.zeros_like(out[i, n:]))


def test_batch_item_with_no_valid_point_gives_zeros_not_nan():
    block = make("gated")
    g, s = streams(2, 4, 8, seed=3)
    mask = torch.tensor([[True, True, False, False], [False] * 4])
    out = block(g, s, mask)
    assert torch.isfinite(out).all()
    assert torch.equal(out[1], torch.zeros_like(out[1]))


def test_gates_start_at_one_half_exactly():
    torch.manual_seed(0)
    block = GatedCrossAttentionFusion(16, num_heads=4).eval()
    g, s = streams(2, 6, 16, seed=4)
    mask = torch.tensor([[True] * 6, [True] * 4 + [False] * 2])
    _, gates = block(g, s, mask, return_gates=True)
    assert isinstance(gates, FusionGates)
    for gate in gates:
        assert gate.shape == (2, 6, 16)
        assert torch.equal(gate[mask], torch.full_like(gate[mask], 0.5))
        assert torch.equal(gate[~mask], torch.zeros_like(gate[~mask]))


@pytest.mark.parametrize("name", ["cross", "concat_mlp", "sum"])
def test_ungated_blocks_return_no_gates(name):
    g, s = streams(1, 3, 8, seed=0)
    out, gates = make(name)(g, s, return_gates=True)
    assert gates is None and out.shape == (1, 3, 8)


def test_learned_gates_depend_on_the_input():
    block = make("gated")
    g, s = streams(1, 5, 8, seed=2)
    _, gates = block(g, s, return_gates=True)
    assert gates.geometric.std() > 1e-3
    assert not torch.allclose(gates.geometric, gates.semantic)


def test_sum_fusion_closed_form(dtype, tol):
    g = torch.tensor([[[3.0, 0.0], [0.0, -2.0]]], dtype=dtype)
    s = torch.tensor([[[0.0, 5.0], [0.0, 1.0]]], dtype=dtype)
    out = SumFusion(2)(g, s)
    r = 2**-0.5
    # Point 1: normalised inputs cancel exactly, and the zero vector stays zero.
    expected = torch.tensor([[[r, r], [0.0, 0.0]]], dtype=dtype)
    assert torch.allclose(out, expected, atol=tol)


def test_inputs_are_normalised_inside():
    block = make("concat_mlp")
    g, s = streams(2, 4, 8, seed=5)
    assert torch.allclose(block(g, s), block(7.0 * g, 0.1 * s), atol=1e-5)


@pytest.mark.parametrize("name", ["gated", "cross", "concat_mlp"])
def test_gradients_reach_every_parameter_at_initialisation(name):
    torch.manual_seed(0)
    block = build_fusion(name, dim=8, **({"num_heads": 2} if name != "concat_mlp" else {}))
    g, s = streams(2, 5, 8, seed=6)
    target = torch.randn(2, 5, 8, generator=torch.Generator().manual_seed(7))
    mask = torch.tensor([[True] * 5, [True] * 3 + [False] * 2])
    loss = ((block(g, s, mask) - target) ** 2).sum()
    loss.backward()
    for pname, p in block.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, pname


def test_gradcheck_gated_fusion_float64():
    block = make("gated", dim=4, dtype=torch.float64)
    g, s = streams(2, 3, 4, seed=8, dtype=torch.float64)
    g.requires_grad_(True)
    s.requires_grad_(True)
    mask = torch.tensor([[True, True, True], [True, True, False]])
    assert torch.autograd.gradcheck(lambda a, b: block(a, b, mask), (g, s))


def test_gradcheck_gated_fusion_parameters_float64():
    block = make("gated", dim=4, dtype=torch.float64)
    g, s = streams(1, 3, 4, seed=9, dtype=torch.float64)
    names, params = zip(*block.named_parameters())
    params = tuple(p.detach().clone().requires_grad_(True) for p in params)

    def run(*ps):
        return torch.func.functional_call(block, dict(zip(names, ps)), (g, s))

    assert torch.autograd.gradcheck(run, params)


def test_dropout_acts_only_in_training():
    torch.manual_seed(0)
    block = GatedCrossAttentionFusion(8, num_heads=2, dropout=0.5)
    g, s = streams(2, 6, 8, seed=10)
    torch.manual_seed(1)
    a = block(g, s)
    torch.manual_seed(2)
    b = block(g, s)
    assert not torch.allclose(a, b)
    block.eval()
    assert torch.equal(block(g, s), block(g, s))


def test_build_fusion_names_and_errors():
    assert isinstance(build_fusion("gated"), GatedCrossAttentionFusion)
    assert isinstance(build_fusion("cross", dim=32, num_heads=4), CrossAttentionFusion)
    assert isinstance(build_fusion("concat_mlp", dim=16, hidden_dim=8), ConcatMLPFusion)
    assert isinstance(build_fusion("sum"), SumFusion)
    assert build_fusion("gated").dim == 64
    with pytest.raises(ValueRangeError, match="unknown fusion"):
        build_fusion("film")
    with pytest.raises(ValueRangeError):
        build_fusion("gated", dim=10, num_heads=4)


def test_fusion_base_is_abstract_and_every_block_derives_from_it():
    with pytest.raises(TypeError, match="abstract"):
        Fusion(8)  # type: ignore[abstract]
    for name in NAMES:
        assert issubclass(FUSIONS[name], Fusion)
        assert isinstance(build_fusion(name, dim=8), Fusion)

    class Geometric(Fusion):
        def _fuse(self, g, s, mask):
            return 2 * g, None

    g, s = streams(1, 3, 4, seed=0)
    mask = torch.tensor([[True, True, False]])
    out = Geometric(4)(g, s, mask)
    assert torch.allclose(out[0, :2], torch.nn.functional.normalize(g[0, :2], dim=-1))
    assert bool((out[0, 2] == 0).all())


def test_bad_inputs_raise():
    block = make("gated")
    g, s = streams(2, 4, 8, seed=0)
    with pytest.raises(ShapeError):
        block(g, s[:, :3])
    with pytest.raises(ShapeError):
        block(g[..., :6], s[..., :6])
    with pytest.raises(ShapeError):
        block(g, s.double())
    with pytest.raises(ShapeError):
        block(g, s, torch.ones(2, 4))
    with pytest.raises(ShapeError):
        block(g, s, torch.ones(2, 5, dtype=torch.bool))
