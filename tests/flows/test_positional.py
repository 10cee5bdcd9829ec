"""Tests of poseflow.flows.positional: the positional encoder Ξ."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from poseflow.errors import ShapeError, ValueRangeError
from poseflow.flows.positional import PointPositionalEncoder, nerf_embedding


def point_inputs(b, n, *, seed, dtype=torch.float32, device="cpu"):
    gen = torch.Generator().manual_seed(seed)
    p = torch.randn(b, n, 3, generator=gen, dtype=dtype).to(device)
    normals = torch.nn.functional.normalize(
        torch.randn(b, n, 3, generator=gen, dtype=dtype), dim=-1
    )
    x0 = torch.randn(b, n, 3, generator=gen, dtype=dtype).to(device)
    flag = (torch.arange(n) >= n // 2).expand(b, -1).to(device)
    return p, normals.to(device), x0, flag


def test_nerf_embedding_closed_form(dtype, tol):
    a = torch.tensor([[0.1, -0.7]], dtype=dtype)
    out = nerf_embedding(a, 3)
    expected = [0.1, -0.7]
    for k in range(3):
        w = math.pi * 2**k
        expected += [math.sin(w * 0.1), math.sin(-w * 0.7), math.cos(w * 0.1), math.cos(-w * 0.7)]
    assert out.dtype == dtype
    assert torch.allclose(out, torch.tensor([expected], dtype=dtype), atol=tol)
    assert torch.equal(nerf_embedding(a, 0), a)


def test_shape_dtype_device(device, dtype):
    enc = PointPositionalEncoder(32, num_frequencies=4).to(device=device, dtype=dtype)
    out = enc(*point_inputs(2, 7, seed=0, dtype=dtype, device=device))
    assert out.shape == (2, 7, 32) and out.dtype == dtype and out.device.type == device.type
    assert enc.proj.in_features == 9 * (1 + 2 * 4) + 64


@settings(max_examples=10)
@given(seed=st.integers(0, 2**16), n=st.integers(1, 12))
def test_point_wise_and_permutation_equivariant(seed, n):
    torch.manual_seed(seed % 5)
    enc = PointPositionalEncoder(16, num_frequencies=3).double()
    p, normals, x0, flag = point_inputs(1, n, seed=seed, dtype=torch.float64)
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(seed))
    out = enc(p, normals, x0, flag)
    assert torch.allclose(
        enc(p[:, perm], normals[:, perm], x0[:, perm], flag[:, perm]), out[:, perm]
    )
    i = int(perm[0])
    one = enc(p[:, i : i + 1], normals[:, i : i + 1], x0[:, i : i + 1], flag[:, i : i + 1])
    assert torch.allclose(one[0, 0], out[0, i], atol=1e-12)


def test_every_attribute_and_the_flag_change_the_code():
    torch.manual_seed(0)
    enc = PointPositionalEncoder(16)
    p, normals, x0, flag = point_inputs(1, 4, seed=1)
    base = enc(p, normals, x0, flag)
    for changed in (
        enc(p + 0.01, normals, x0, flag),
        enc(p, -normals, x0, flag),
        enc(p, normals, x0 + 0.01, flag),
        enc(p, normals, x0, ~flag),
    ):
        assert (changed - base).abs().amax(dim=-1).min() > 1e-6


def test_gradients_reach_every_parameter():
    torch.manual_seed(0)
    enc = PointPositionalEncoder(8, num_frequencies=2, feature_dim=4)
    out = enc(*point_inputs(2, 5, seed=2))
    (out**2).sum().backward()
    for name, param in enc.named_parameters():
        assert param.grad is not None and param.grad.abs().sum() > 0, name


def test_gradcheck_float64():
    torch.manual_seed(0)
    enc = PointPositionalEncoder(4, num_frequencies=2, feature_dim=3).double()
    p, normals, x0, flag = point_inputs(1, 3, seed=3, dtype=torch.float64)
    for a in (p, normals, x0):
        a.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b, c: enc(a, b, c, flag), (p, normals, x0))


def test_bad_inputs_raise():
    with pytest.raises(ValueRangeError):
        PointPositionalEncoder(0)
    with pytest.raises(ValueRangeError):
        PointPositionalEncoder(8, num_frequencies=-1)
    enc = PointPositionalEncoder(8)
    p, normals, x0, flag = point_inputs(2, 5, seed=4)
    with pytest.raises(ShapeError):
        enc(p, normals[:, :4], x0, flag)
    with pytest.raises(ShapeError):
        enc(p, normals, x0, flag.float())
    with pytest.raises(ShapeError):
        enc(p, normals.double(), x0, flag)
    with pytest.raises(ShapeError):
        enc(p[..., :2], normals, x0, flag)
