from __future__ import annotations

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from poseflow.errors import MissingWeightsError
from poseflow.features.gedi import (
    GeDiEncoder,
    GeDiNet,
    ball_query,
    local_reference_frame,
)
from poseflow.geometry.pointcloud import farthest_point_sample
from poseflow.geometry.se3 import quaternion_to_rotation, random_rotation


def _cloud(n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    p = torch.randn(n, 3, generator=g, dtype=torch.float64)
    p = p / p.norm(dim=1, keepdim=True) * torch.tensor([0.06, 0.04, 0.03], dtype=torch.float64)
    return p + 0.002 * torch.randn(n, 3, generator=g, dtype=torch.float64)


@given(seed=st.integers(0, 2**31 - 1))
def test_quaternion_to_rotation_is_a_rotation(seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    q = torch.nn.functional.normalize(torch.randn(8, 4, generator=g, dtype=torch.float64), dim=1)
    R = quaternion_to_rotation(q)
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(8, 3, 3))
    assert torch.allclose(torch.linalg.det(R), torch.ones(8, dtype=torch.float64))
    assert torch.allclose(quaternion_to_rotation(-q), R)


@given(seed=st.integers(0, 2**31 - 1))
def test_lrf_is_rotation_equivariant(seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    nb = torch.randn(3, 60, 3, generator=g, dtype=torch.float64) * torch.tensor(
        [1.0, 0.6, 0.2], dtype=torch.float64
    )
    centres = torch.zeros(3, 3, dtype=torch.float64)
    mask = torch.ones(3, 60, dtype=torch.bool)
    R = random_rotation(1, generator=g, dtype=torch.float64)[0]
    a = local_reference_frame(centres, nb, mask, 4.0)
    b = local_reference_frame(centres + 1.0, nb @ R.T + 1.0, mask, 4.0)
    assert torch.allclose(b, R @ a, atol=1e-8)
    # the frame is orthonormal with columns x, x × z, z (GeDi's convention)
    assert torch.allclose(a.transpose(1, 2) @ a, torch.eye(3, dtype=torch.float64).expand(3, 3, 3))
    assert torch.allclose(a[..., 1], torch.linalg.cross(a[..., 0], a[..., 2], dim=-1))


def test_lrf_planar_patch_is_finite() -> None:
    g = torch.Generator().manual_seed(0)
    nb = torch.randn(2, 30, 3, generator=g, dtype=torch.float64)
    nb[..., 2] = 0.0
    lrf = local_reference_frame(torch.zeros(2, 3, dtype=torch.float64), nb, nb[..., 0] > -9, 5.0)
    assert bool(torch.isfinite(lrf).all())
    assert torch.allclose(
        lrf.transpose(1, 2) @ lrf, torch.eye(3, dtype=torch.float64).expand(2, 3, 3)
    )


def test_fps_and_ball_query_against_brute_force() -> None:
    pts = torch.rand(2, 50, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    idx, _ = farthest_point_sample(pts, 10)
    for k in range(2):  # sequential reference
        chosen = [0]
        for _ in range(9):
            d = torch.cdist(pts[k], pts[k][chosen]).min(dim=1).values
            chosen.append(int(d.argmax()))
        assert idx[k].tolist() == chosen
    centres = pts[:, :4]
    group = ball_query(pts, centres, 0.3, 8)
    for k in range(2):
        for s in range(4):
            inside = torch.nonzero((pts[k] - centres[k, s]).norm(dim=1) < 0.3).flatten().tolist()
            want = inside[:8] + [inside[0]] * max(0, 8 - len(inside))
            assert group[k, s].tolist() == want


def test_state_dict_names_match_the_public_checkpoint() -> None:
    keys = set(GeDiNet().state_dict())
    for name in (
        "qnet.conv1.0.weight",
        "qnet.conv3.1.running_var",
        "qnet.fc3.bias",
        "samodule1.mlps.0.0.weight",
        "samodule1.mlps.0.7.running_mean",
        "samodule3.mlps.0.6.weight",
        "fc_layer.4.weight",
        "fc_layer.7.weight",
    ):
        assert name in keys
    assert GeDiNet().samodule3.mlps[0][6].weight.shape == (1024, 512, 1, 1)
    assert GeDiNet().samodule2.mlps[0][0].weight.shape == (256, 131, 1, 1)


@pytest.fixture(scope="module")
def small_encoder() -> GeDiEncoder:
    torch.manual_seed(0)
    net = GeDiNet(width=1 / 16).double()
    return GeDiEncoder(net, samples_per_patch=128, patch_batch=64)


def test_gedi_encoder_is_rigid_invariant(small_encoder: GeDiEncoder) -> None:
    pts = _cloud(60, 0)
    R = random_rotation(1, generator=torch.Generator().manual_seed(5), dtype=torch.float64)[0]
    a = small_encoder.encode(pts[None], None, None, 0.12)
    b = small_encoder.encode((pts @ R.T + 0.5)[None], None, None, 0.12)
    assert a.shape == (1, 60, 64)
    # an LRF is ambiguous where its sign test is near zero: allow a few such points
    same = (a - b).abs().amax(dim=-1) < 1e-8
    assert float(same.double().mean()) >= 0.95
    assert torch.allclose(a.norm(dim=-1), torch.ones(1, 60, dtype=torch.float64))
    assert not torch.allclose(a[0, 0], a[0, 1])


def test_gedi_encoder_mask_and_dtype(small_encoder: GeDiEncoder) -> None:
    pts = torch.zeros(2, 40, 3, dtype=torch.float32)
    pts[0], pts[1, :30] = _cloud(40, 1).float(), _cloud(30, 2).float()
    mask = torch.ones(2, 40, dtype=torch.bool)
    mask[1, 30:] = False
    out = small_encoder.encode(pts, None, mask, torch.tensor([0.12, 0.12]))
    assert out.dtype == torch.float32 and out.shape == (2, 40, 64)
    assert bool((out[1, 30:] == 0).all())
    one = small_encoder.encode(pts[1:2, :30], None, None, 0.12)
    assert torch.allclose(out[1, :30], one[0], atol=1e-5)


def test_from_checkpoint_roundtrip(tmp_path, small_encoder: GeDiEncoder) -> None:
    from safetensors.torch import save_file

    torch.manual_seed(1)
    net = GeDiNet()
    state = net.state_dict()
    torch.save({"pnet_model_state_dict": state, "epoch": 3}, tmp_path / "chkpt.tar")
    save_file({k: v.contiguous() for k, v in state.items()}, str(tmp_path / "gedi.safetensors"))
    for name in ("chkpt.tar", "gedi.safetensors"):
        enc = GeDiEncoder.from_checkpoint(tmp_path / name, samples_per_patch=128)
        for k, v in enc.net.state_dict().items():
            assert torch.equal(v, state[k])
        assert not enc.net.training and enc.dim == 64
    with pytest.raises(MissingWeightsError, match="fabiopoiesi/gedi"):
        GeDiEncoder.from_checkpoint(tmp_path / "nope.tar")
