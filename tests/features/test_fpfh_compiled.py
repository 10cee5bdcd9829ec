"""The compiled FPFH kernel (FPFHEncoder(backend="numba")) against the torch backend and Open3D.

The torch backend equals Open3D to float64 rounding (``test_fpfh_torch.py``); the kernel must
equal both wherever the neighbourhoods do not hang on exact ties of distance (random floats have
none), including pairs whose two normals make the same angle with the line between them, whose
feature depends on the pair's order.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from poseflow.errors import ValueRangeError
from poseflow.features._fpfh_cpu import fpfh_first_kernel
from poseflow.features.fpfh import compute_fpfh
from poseflow.features.geometric import FPFH_BACKENDS, FPFHEncoder

F64 = torch.float64


def _random_cloud(seed: int, B: int, P: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Points uniform in a 0.1 m cube and random unit normals, ``(B, P, 3)`` float64."""
    g = torch.Generator().manual_seed(seed)
    points = torch.rand(B, P, 3, generator=g, dtype=F64) * 0.1
    normals = torch.nn.functional.normalize(torch.randn(B, P, 3, generator=g, dtype=F64), dim=-1)
    return points, normals


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    P=st.integers(1, 150),
    max_nn=st.integers(2, 60),
    radii=st.lists(st.floats(0.005, 0.2), min_size=1, max_size=3),
    data=st.data(),
)
def test_kernel_equals_compute_fpfh(seed, P, max_nn, radii, data) -> None:
    """Raw histograms of the first ``count`` points, every scale, equal the torch ones."""
    count = data.draw(st.integers(0, P))
    points, normals = _random_cloud(seed, 1, P)
    table = torch.tensor([radii], dtype=F64)
    ref = compute_fpfh(points, normals, radius=table, max_nn=max_nn)[0, :count]
    bounds = np.array([r * r for r in radii])
    out = fpfh_first_kernel(points[0].numpy(), normals[0].numpy(), count, bounds, max_nn)
    assert out.shape == (count, 33 * len(radii))
    torch.testing.assert_close(torch.from_numpy(out), ref, rtol=0, atol=1e-10)


def test_two_scales_equal_open3d() -> None:
    pytest.importorskip("open3d")
    points, normals = _random_cloud(4, 2, 200)
    kwargs = {"radius_fractions": (0.15, 0.3), "max_nn": 40}
    ours = FPFHEncoder(backend="numba", **kwargs).encode(points, normals, None, 0.17)
    ref = FPFHEncoder(backend="open3d", **kwargs).encode(points, normals, None, 0.17)
    assert (ours - ref).abs().max() < 1e-12


def test_pairs_whose_normals_tie_keep_their_order() -> None:
    """On a plane with one normal every pair ties; each order keeps its own source point."""
    g = torch.Generator().manual_seed(3)
    points = torch.zeros(1, 120, 3, dtype=F64)
    points[..., :2] = torch.rand(1, 120, 2, generator=g, dtype=F64) * 0.1
    normals = torch.zeros(1, 120, 3, dtype=F64)
    normals[..., :2] = 0.6
    normals[..., 2] = 0.28**0.5
    ref = FPFHEncoder(backend="torch").encode(points, normals, None, 0.14)
    ours = FPFHEncoder(backend="numba").encode(points, normals, None, 0.14)
    assert (ours - ref).abs().max() < 1e-12


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_encoder_batched_with_padding_and_support(dtype) -> None:
    """Masked rows and clouds, the first points of a support cloud: as the torch backend."""
    points, normals = _random_cloud(11, 3, 160)
    mask = torch.ones(3, 160, dtype=torch.bool)
    mask[0, 10:20] = False  # gaps among the described points
    mask[1, :32] = False  # nothing to describe in this cloud
    mask[2, 100:] = False  # padding in the support
    diameter = torch.tensor([0.17, 0.15, 0.2], dtype=dtype)
    args = (points.to(dtype), normals.to(dtype), mask, diameter, 32)
    ours = FPFHEncoder(backend="numba").encode_first(*args)
    ref = FPFHEncoder(backend="torch").encode_first(*args)
    assert ours.dtype == dtype and ours.shape == (3, 32, 66)
    tol = 1e-12 if dtype == F64 else 1e-6
    assert (ours - ref).abs().max() < tol
    assert bool((ours[0, 10:20] == 0).all()) and bool((ours[1] == 0).all())


def test_estimated_normals_equal_the_torch_backend() -> None:
    """Without normals both estimate them the same way (estimate_outward_normals)."""
    g = torch.Generator().manual_seed(2)
    sphere = torch.nn.functional.normalize(torch.randn(1, 400, 3, generator=g, dtype=F64), dim=-1)
    kwargs = {"normal_radius_fraction": 0.15}
    ours = FPFHEncoder(backend="numba", **kwargs).encode(sphere * 0.05, None, None, 0.1)
    ref = FPFHEncoder(backend="torch", **kwargs).encode(sphere * 0.05, None, None, 0.1)
    assert (ours - ref).abs().max() < 1e-12


def test_backend_names() -> None:
    assert set(FPFH_BACKENDS) == {"auto", "numba", "torch", "open3d"}
    with pytest.raises(ValueRangeError, match="numba"):
        FPFHEncoder(backend="compiled")


def test_a_cosine_past_one_by_rounding_swaps_as_open3d() -> None:
    """A float32 unit normal along the line between two points: |cos| exceeds 1 in float64.

    acos is NaN there, so the reference (and Open3D) swaps in neither order; so must the kernel.
    """
    g = torch.Generator().manual_seed(0)
    n1 = torch.nn.functional.normalize(torch.randn(3, generator=g), dim=0).double()
    assert n1.norm() > 1  # float32 rounding left it a hair long
    n2 = torch.nn.functional.normalize(torch.randn(3, generator=g, dtype=F64), dim=0)
    points = torch.stack([torch.zeros(3, dtype=F64), 0.01 * n1])
    normals = torch.stack([n1, n2])
    ref = compute_fpfh(points[None], normals[None], radius=0.05, max_nn=10)[0]
    out = fpfh_first_kernel(points.numpy(), normals.numpy(), 2, np.array([0.05**2]), 10)
    torch.testing.assert_close(torch.from_numpy(out), ref, rtol=0, atol=1e-10)
