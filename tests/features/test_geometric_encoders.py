from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import torch

from poseflow.errors import DegenerateInputError, MissingWeightsError, ShapeError, ValueRangeError
from poseflow.features.geometric import (
    CallableEncoder,
    FPFHEncoder,
    GeometricEncoder,
    TorchScriptEncoder,
    open3d_normals,
)
from poseflow.geometry.se3 import random_rotation


def _sphere(n: int, seed: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    p = torch.randn(n, 3, generator=g, dtype=torch.float64)
    p = p / p.norm(dim=1, keepdim=True) * torch.tensor([0.05, 0.04, 0.03], dtype=torch.float64)
    return p.to(dtype)


def test_fpfh_matches_open3d() -> None:
    pts = _sphere(300, 0)
    normals = torch.from_numpy(open3d_normals(pts.numpy(), 0.01))
    enc = FPFHEncoder(radius_fractions=(0.3,), max_nn=50)
    out = enc.encode(pts[None], normals[None], None, 0.1)[0]
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.numpy()))
    pcd.normals = o3d.utility.Vector3dVector(normals.numpy())
    ref = o3d.pipelines.registration.compute_fpfh_feature(
        pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=0.03, max_nn=50)
    )
    ref = torch.nn.functional.normalize(torch.from_numpy(np.asarray(ref.data).T), dim=1)
    assert torch.allclose(out, ref, atol=1e-10)


def test_fpfh_batched_with_mask_equals_loop(device: torch.device, dtype: torch.dtype) -> None:
    a, b = _sphere(120, 1, dtype), _sphere(90, 2, dtype)
    pts = torch.zeros(2, 120, 3, dtype=dtype)
    pts[0], pts[1, :90] = a, b
    mask = torch.zeros(2, 120, dtype=torch.bool)
    mask[0], mask[1, :90] = True, True
    enc = FPFHEncoder()
    out = enc.encode(pts.to(device), None, mask.to(device), torch.tensor([0.1, 0.1], dtype=dtype))
    assert out.shape == (2, 120, 66) and out.dtype == dtype and out.device.type == device.type
    one = enc.encode(b[None].to(device), None, None, 0.1)
    assert torch.allclose(out[1, :90], one[0], atol=1e-5)
    assert bool((out[1, 90:] == 0).all())
    assert torch.allclose(
        out[0].norm(dim=1), torch.ones(120, dtype=dtype, device=device), atol=1e-5
    )


@pytest.mark.parametrize("backend", ["numba", "open3d", "torch"])
def test_fpfh_of_the_first_points_equals_describing_all(backend: str) -> None:
    """Masked rows among the first ones stay zero; the others equal encode's."""
    pts = _sphere(400, 3)[None].expand(2, -1, -1).clone()
    mask = torch.ones(2, 400, dtype=torch.bool)
    mask[0, 5:9] = False  # gaps among the first points
    mask[1, :40] = False  # none of the first points of this cloud is valid
    enc = FPFHEncoder(backend=backend)
    every = enc.encode(pts, None, mask, 0.12)
    first = enc.encode_first(pts, None, mask, 0.12, 30)
    assert first.shape == (2, 30, 66)
    torch.testing.assert_close(first, every[:, :30], rtol=0, atol=1e-12)
    assert bool((first[0, 5:9] == 0).all()) and bool((first[1] == 0).all())
    with pytest.raises(ValueRangeError):
        enc.encode_first(pts, None, mask, 0.12, 401)


def test_fpfh_is_rotation_invariant() -> None:
    pts = _sphere(400, 3)
    normals = torch.nn.functional.normalize(pts / torch.tensor([0.05, 0.04, 0.03]) ** 2, dim=1)
    R = random_rotation(1, generator=torch.Generator().manual_seed(0), dtype=torch.float64)[0]
    enc = FPFHEncoder()
    a = enc.encode(pts[None], normals[None], None, 0.1)
    b = enc.encode((pts @ R.T + 0.3)[None], (normals @ R.T)[None], None, 0.1)
    assert torch.allclose(a, b, atol=1e-6)


def test_fpfh_bad_input() -> None:
    enc = FPFHEncoder()
    with pytest.raises(DegenerateInputError):
        enc.encode(torch.zeros(1, 2, 3), None, None, 0.1)
    with pytest.raises(ValueRangeError):
        enc.encode(torch.rand(1, 5, 3), None, None, 0.0)
    with pytest.raises(ShapeError):
        enc.encode(torch.rand(5, 3), None, None, 0.1)
    with pytest.raises(ValueRangeError):
        FPFHEncoder(radius_fractions=(0.3, -1.0))
    assert isinstance(enc, GeometricEncoder)


def test_callable_encoder_checks_output() -> None:
    enc = CallableEncoder(lambda p, n, m, d: p * 2, 3, normalize=True)
    pts = torch.rand(2, 6, 3, dtype=torch.float64)
    mask = torch.ones(2, 6, dtype=torch.bool)
    mask[1, 4:] = False
    out = enc.encode(pts, None, mask, 1.0)
    assert torch.allclose(out[0], torch.nn.functional.normalize(pts[0], dim=1))
    assert bool((out[1, 4:] == 0).all())
    with pytest.raises(ShapeError):
        CallableEncoder(lambda p, n, m, d: p, 5).encode(pts, None, None, 1.0)
    with pytest.raises(ValueRangeError):
        CallableEncoder(lambda p, n, m, d: p / 0.0, 3).encode(pts, None, None, 1.0)


def test_torchscript_encoder(tmp_path) -> None:
    class Toy(torch.nn.Module):
        def forward(self, p, n, m, d):
            return p * d[:, None, None]

    path = tmp_path / "toy.pt"
    torch.jit.save(torch.jit.script(Toy()), str(path))
    enc = TorchScriptEncoder(path, 3, trust=True)
    pts = torch.rand(2, 4, 3)
    out = enc.encode(pts, None, None, torch.tensor([1.0, 2.0]))
    assert torch.allclose(out[1], 2 * pts[1])
    with pytest.raises(MissingWeightsError):
        TorchScriptEncoder(tmp_path / "missing.pt", 3, trust=True)


def test_torchscript_encoder_reads_nothing_without_trust(tmp_path, monkeypatch) -> None:
    class Toy(torch.nn.Module):
        def forward(self, p, n, m, d):
            return p

    path = tmp_path / "toy.pt"
    torch.jit.save(torch.jit.script(Toy()), str(path))
    loads = []
    monkeypatch.setattr(torch.jit, "load", lambda *a, **k: loads.append(a))
    for trust in (False, 1, "yes"):
        with pytest.raises(ValueRangeError, match=r"runs the code it holds.*trust=True"):
            TorchScriptEncoder(path, 3, trust=trust)
    assert loads == []  # refused before torch.jit.load is called


def _box_surface(n: int, generator: torch.Generator, dtype: torch.dtype) -> tuple:
    """``n`` points on the surface of a 6 x 4 x 2 cm box, with outward normals."""
    half = torch.tensor([0.03, 0.02, 0.01], dtype=dtype)
    face = torch.randint(0, 6, (n,), generator=generator)
    axis, sign = face // 2, (face % 2) * 2 - 1
    pts = (torch.rand(n, 3, generator=generator, dtype=dtype) * 2 - 1) * half
    pts[torch.arange(n), axis] = sign.to(dtype) * half[axis]
    normals = torch.zeros(n, 3, dtype=dtype)
    normals[torch.arange(n), axis] = sign.to(dtype)
    return pts[None], normals[None]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_descriptors_on_a_dense_support_agree_across_samplings_of_the_surface(dtype) -> None:
    """Sparse points described within two independent dense samplings of the same surface get
    nearly the same descriptors; described among themselves, two sparse samplings do not."""
    from poseflow.features.geometric import encode_on_support

    g = torch.Generator().manual_seed(0)
    encoder = FPFHEncoder(backend="torch")
    points, normals = _box_surface(48, g, dtype)
    cosines = []
    for _ in range(2):
        support, support_normals = _box_surface(3000, g, dtype)
        cosines.append(
            encode_on_support(encoder, points, normals, None, support, support_normals, None, 0.075)
        )
    agree = (cosines[0] * cosines[1]).sum(-1)
    assert cosines[0].shape == (1, 48, encoder.dim) and cosines[0].dtype == dtype
    assert float(agree.median()) > 0.97
    # The sparse cloud's own descriptors differ from those of a denser sampling of its surface.
    alone = encoder.encode(points, normals, None, 0.075)
    assert float((alone * cosines[0]).sum(-1).median()) < float(agree.median()) - 0.02
    masked = encode_on_support(
        encoder, points, normals, torch.ones(1, 48, dtype=torch.bool), support,
        support_normals, torch.zeros(1, 3000, dtype=torch.bool), 0.075,
    )  # fmt: skip
    assert torch.allclose(masked, alone)  # an all-invalid support is no support
