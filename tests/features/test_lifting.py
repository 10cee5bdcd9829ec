from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from poseflow.errors import DegenerateInputError, ValueRangeError
from poseflow.features.cache import FeatureCache, cached_query_features
from poseflow.features.lifting import (
    QueryFeatureBank,
    lift_query_features,
    lift_target_features,
    viewpoint_poses,
)
from poseflow.geometry.pointcloud import project_points
from poseflow.render.mesh import TexturedMesh


class ColourEncoder:
    """The image itself as a 3-channel feature map: lifting must return each point's colour."""

    dim = 3
    input_size = 64
    query_pooling = "mean"

    def encode(self, images: torch.Tensor) -> torch.Tensor:
        return images

    def __repr__(self) -> str:
        return "ColourEncoder()"


def _cube(size: float = 0.1) -> tuple[TexturedMesh, torch.Tensor]:
    """A cube whose vertex colours are a smooth function of position, and points on its faces."""
    h = size / 2
    v = np.array([[x, y, z] for x in (-h, h) for y in (-h, h) for z in (-h, h)])
    f = np.array(
        [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    )  # fmt: skip
    colours = (v / size + 0.5) * 0.8 + 0.1
    g = torch.Generator().manual_seed(0)
    uv = torch.rand(300, 2, generator=g, dtype=torch.float64) * 0.8 * size - 0.4 * size
    axis = torch.arange(300) % 6
    pts = torch.zeros(300, 3, dtype=torch.float64)
    for a in range(3):
        for s, k in ((h, 2 * a), (-h, 2 * a + 1)):
            sel = axis == k
            others = [i for i in range(3) if i != a]
            pts[sel, a] = s
            pts[sel, others[0]] = uv[sel, 0]
            pts[sel, others[1]] = uv[sel, 1]
    return TexturedMesh(v, f, vertex_colors=colours), pts


def test_viewpoint_poses_look_at_the_centre() -> None:
    centre = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    T = viewpoint_poses(10, rolls=3, distance=2.0, centre=centre)
    R = T[:, :3, :3]
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(30, 3, 3))
    assert torch.allclose(torch.linalg.det(R), torch.ones(30, dtype=torch.float64))
    c_cam = (R @ centre + T[:, :3, 3]).double()
    assert torch.allclose(c_cam, torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64).expand(30, 3))
    # the rolls of one viewpoint share the optical axis and differ by in-plane rotations
    assert torch.allclose(R[0, 2], R[1, 2]) and not torch.allclose(R[0, 0], R[1, 0])


def test_lift_target_features_reads_point_colours() -> None:
    K = torch.tensor([[300.0, 0.0, 80.0], [0.0, 300.0, 60.0], [0.0, 0.0, 1.0]])
    H, W = 120, 160
    u = torch.arange(W, dtype=torch.float32)
    v = torch.arange(H, dtype=torch.float32)
    image = torch.stack(
        [u[None].expand(H, W) / W, v[:, None].expand(H, W) / H, torch.full((H, W), 0.5)]
    )[None]
    pix = torch.stack(
        torch.meshgrid(torch.arange(60, 100), torch.arange(40, 70), indexing="xy"), -1
    )
    pix = pix.reshape(1, -1, 2)
    z = torch.full(pix.shape[:2], 1.0)
    pts = torch.cat([(pix - K[:2, 2]) / 300.0 * z[..., None], z[..., None]], dim=-1)
    feats = lift_target_features(ColourEncoder(), image, pts, K)
    want = torch.stack([pix[0, :, 0] / W, pix[0, :, 1] / H], dim=-1)
    # a linear image resampled bilinearly stays linear: exact up to the crop's resampling
    assert torch.allclose(feats[0, :, :2], want, atol=2e-3)
    with_pixels = lift_target_features(ColourEncoder(), image, pts, K, pixels=pix)
    assert torch.allclose(with_pixels, feats, atol=1e-5)
    # NaN outside the instance's crop (pixels 60-100 x 40-70 plus margin) is never read ...
    far = image.clone()
    far[0, :, :, :10] = float("nan")
    torch.testing.assert_close(lift_target_features(ColourEncoder(), far, pts, K), feats)
    # ... inside it is a clear error
    near = image.clone()
    near[0, 1, 55, 80] = float("nan")
    with pytest.raises(ValueRangeError, match="where an instance is cropped"):
        lift_target_features(ColourEncoder(), near, pts, K)


def test_lift_query_features_recovers_the_albedo() -> None:
    mesh, pts = _cube()
    bank = lift_query_features(ColourEncoder(), mesh, pts.float(), 0.17, num_views=12)
    assert bank.features.shape == (300, 12, 3) and bank.rolls == 1
    assert bool(bank.visible.any(dim=1).all())
    albedo = torch.from_numpy((pts.numpy() / 0.1 + 0.5) * 0.8 + 0.1).float()
    pooled = bank.pooled()
    # shading darkens the albedo: compare chromaticity (colour direction), robust to it
    cos = torch.nn.functional.cosine_similarity(pooled, albedo, dim=1)
    assert float(cos.median()) > 0.97
    sel = bank.select(bank.features[None, :, 0])
    assert sel.shape == (1, 300, 3)
    assert torch.allclose(sel[0][bank.visible[:, 0]], bank.features[bank.visible[:, 0], 0])


def test_select_and_pooled_fill_unseen_points() -> None:
    pts = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [1.1, 0, 0]])
    feats = torch.tensor([[[1.0], [3.0]], [[5.0], [0.0]], [[0.0], [0.0]]])
    vis = torch.tensor([[True, True], [True, False], [False, False]])
    bank = QueryFeatureBank(pts, feats, vis, torch.eye(4).expand(2, 4, 4))
    assert bank.pooled().flatten().tolist() == [2.0, 5.0, 5.0]
    none = QueryFeatureBank(pts, feats, torch.zeros_like(vis), torch.eye(4).expand(2, 4, 4))
    with pytest.raises(DegenerateInputError):
        none.pooled()


def test_project_consistency_of_views() -> None:
    mesh, pts = _cube()
    bank = lift_query_features(ColourEncoder(), mesh, pts.float(), 0.17, num_views=4, rolls=2)
    assert bank.poses.shape == (8, 4, 4)
    cam = pts.float() @ bank.poses[0, :3, :3].T + bank.poses[0, :3, 3]
    assert bool((cam[:, 2] > 0).all())
    assert project_points(cam[None], torch.eye(3)).shape == (1, 300, 2)


def test_cache_roundtrip_and_keys(tmp_path) -> None:
    mesh, pts = _cube()
    calls = []
    enc = ColourEncoder()
    original = enc.encode

    def counting(images):
        calls.append(len(images))
        return original(images)

    enc.encode = counting
    a = cached_query_features(tmp_path, "cube", enc, mesh, pts.float(), 0.17, num_views=4)
    n_calls = len(calls)
    b = cached_query_features(tmp_path, "cube", enc, mesh, pts.float(), 0.17, num_views=4)
    assert len(calls) == n_calls  # loaded, not recomputed
    assert torch.equal(a.features, b.features)  # stored as computed: bit for bit
    assert torch.equal(a.visible, b.visible)
    cached_query_features(tmp_path, "cube", enc, mesh, pts.float(), 0.17, num_views=5)
    assert len(calls) > n_calls  # other settings, other entry
    cache = FeatureCache(tmp_path)
    assert len(list((tmp_path / "cube").glob("*.safetensors"))) == 2
    with pytest.raises(ValueError):
        cache.key("../evil", pts, enc, {})


def _select_one_by_one(bank, feats, mask, max_t):
    """The selection rule written plainly, instance by instance (the reference)."""
    q = F.normalize(bank.features, dim=-1)  # (N, K, G); every query point is used here
    out = []
    for b in range(len(feats)):
        t = feats[b][mask[b]]
        t = t[torch.linspace(0, len(t) - 1, min(len(t), max_t)).round().long()]
        sim = torch.einsum("mg,nkg->mnk", F.normalize(t, dim=-1), q)
        score = sim.masked_fill(~bank.visible[None], -2.0).amax(dim=1).mean(dim=0)  # (K,)
        score = torch.where(bank.visible.any(dim=0), score, torch.full_like(score, -3.0))
        per_point = torch.where(bank.visible, score[None], torch.full_like(score[None], -4.0))
        out.append(bank.features[torch.arange(len(q)), per_point.argmax(dim=1)])
    return torch.stack(out)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), max_t=st.sampled_from([3, 7, 64]))
def test_batched_select_equals_the_rule_applied_instance_by_instance(seed, max_t):
    g = torch.Generator().manual_seed(seed)
    N, K, G, B, M = 20, 6, 8, 4, 15
    visible = torch.rand(N, K, generator=g) < 0.6
    visible[:, 0] = True  # every point seen by some view: no filling involved
    bank = QueryFeatureBank(
        torch.rand(N, 3, generator=g), torch.randn(N, K, G, generator=g), visible,
        torch.eye(4).expand(K, 4, 4),
    )  # fmt: skip
    feats = torch.randn(B, M, G, generator=g, dtype=torch.float64).float()
    mask = torch.rand(B, M, generator=g) < 0.7
    mask[:, 0] = True
    out = bank.select(feats, mask, max_target_points=max_t)
    assert torch.equal(out, _select_one_by_one(bank, feats, mask, max_t))
