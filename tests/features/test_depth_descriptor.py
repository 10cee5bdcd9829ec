"""The depth-aware learned descriptor: its depth layers, network, training pairs and lifting."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from poseflow.errors import ShapeError, ValueRangeError
from poseflow.features.learned import (
    DEPTH_CHANNELS,
    DescriptorNet,
    LearnedAppearanceEncoder,
    depth_layers,
    load_descriptor,
    save_descriptor,
)
from poseflow.features.lifting import lift_query_features, lift_target_features
from poseflow.features.procedural import random_mesh
from poseflow.features.view_pairs import PairGenerator

DEPTH_TINY = {"widths": (8, 16, 16), "dim": 12, "out_stride": 4, "in_channels": 5}


def _encoder(seed: int = 0) -> LearnedAppearanceEncoder:
    torch.manual_seed(seed)
    return LearnedAppearanceEncoder(DescriptorNet(**DEPTH_TINY), input_size=32)


@given(
    shift=st.floats(-0.5, 2.0),
    scale=st.floats(0.2, 5.0),
    seed=st.integers(0, 2**16),
    dtype=st.sampled_from([torch.float32, torch.float64]),
)
def test_depth_layers_ignore_distance_and_size(shift, scale, seed, dtype) -> None:
    g = torch.Generator().manual_seed(seed)
    depth = (1.0 + 0.05 * torch.rand(2, 12, 10, generator=g)).to(dtype)
    mask = torch.rand(2, 12, 10, generator=g) > 0.3
    depth[0, :3] = 0.0  # missing measurements
    diameter = torch.tensor([0.1, 0.25], dtype=dtype)
    ref = depth_layers(depth, mask, diameter)
    moved = depth_layers(torch.where(depth > 0, depth + shift + 0.5, depth), mask, diameter)
    scaled = depth_layers(depth * scale, mask, diameter * scale)
    tol = 1e-4 if dtype == torch.float32 else 1e-9
    torch.testing.assert_close(moved, ref, atol=tol, rtol=0)
    torch.testing.assert_close(scaled, ref, atol=tol, rtol=0)
    valid = mask & (depth > 0)
    assert ref.shape == (2, DEPTH_CHANNELS, 12, 10) and ref.dtype == dtype
    assert torch.equal(ref[:, 1] > 0, valid) and bool((ref[:, 0][~valid] == 0).all())
    assert float(ref[:, 0].abs().max()) <= 4.0
    # the relief is centred on the object's valid pixels
    means = (ref[:, 0] * valid).sum(dim=(1, 2)) / valid.sum(dim=(1, 2))
    torch.testing.assert_close(means, torch.zeros(2, dtype=dtype), atol=tol, rtol=0)


def test_network_with_depth_input_round_trips(tmp_path) -> None:
    torch.manual_seed(0)
    net = DescriptorNet(**DEPTH_TINY).eval()
    x = torch.rand(2, 5, 32, 32, generator=torch.Generator().manual_seed(1))
    out = net(x)
    assert out.shape == (2, 12, 8, 8)
    # the depth channels are read: changing them changes the descriptors
    assert not torch.allclose(out, net(torch.cat([x[:, :3], x[:, 3:] + 1.0], dim=1)))
    folder = save_descriptor(net, tmp_path / "d", input_size=32)
    loaded, cfg = load_descriptor(folder)
    assert cfg["in_channels"] == 5 and loaded.in_channels == 5
    assert torch.equal(loaded(x), out)
    enc = LearnedAppearanceEncoder(folder)
    assert enc.in_channels == 5 and enc.encode(x).shape == (2, 12, 8, 8)
    with pytest.raises(ShapeError):
        enc.encode(x[:, :3])
    # an RGB network keeps the configuration it always had
    assert "in_channels" not in DescriptorNet(widths=(8, 16), dim=4, out_stride=2).config()
    with pytest.raises(ValueRangeError):
        DescriptorNet(widths=(8, 16), in_channels=4)


def test_training_pairs_carry_depth_layers() -> None:
    gen = PairGenerator(3, input_size=32, anchors=16, texture_count=2, photos=False, depth=True)
    batch = gen.batch(3, fresh=3)
    assert batch.images_a.shape == (3, 5, 32, 32) and batch.images_b.shape == (3, 5, 32, 32)
    for images, uv in ((batch.images_a, batch.uv_a), (batch.images_b, batch.uv_b)):
        pix = uv.round().long().clamp(0, 31)
        valid = torch.stack([images[b, 4][pix[b, :, 1], pix[b, :, 0]] for b in range(3)])
        # the matched object pixels have depth (bilinear crops soften the mask's edge)
        assert float(valid.mean()) > 0.8
        assert float(images[:, 3].abs().max()) <= 4.0


def test_lifting_with_a_depth_aware_encoder() -> None:
    enc = _encoder()
    mesh = random_mesh(np.random.default_rng(0), diameter=0.2)
    points = torch.from_numpy(np.asarray(mesh.vertices)[::7]).float()
    bank = lift_query_features(enc, mesh, points, 0.2, num_views=4, rolls=1)
    seen = bank.visible.any(dim=1)
    assert bank.features.shape[-1] == 12 and bool(seen.any())
    assert bool((bank.features[seen].abs().sum(-1) > 0).any())
    K = torch.tensor([[60.0, 0, 31.5], [0, 60.0, 31.5], [0, 0, 1]])
    pts = torch.rand(1, 30, 3, generator=torch.Generator().manual_seed(0)) * 0.1
    pts[..., 2] += 0.8
    rgb = torch.rand(1, 3, 64, 64)
    depth = torch.full((1, 64, 64), 0.85)
    layers = depth_layers(depth, torch.ones(1, 64, 64, dtype=torch.bool), torch.tensor([0.2]))
    feats = lift_target_features(enc, torch.cat([rgb, layers], dim=1), pts, K)
    assert feats.shape == (1, 30, 12) and bool(torch.isfinite(feats).all())
    with pytest.raises(ShapeError):
        lift_target_features(enc, rgb, pts, K)


def test_retrained_weights_change_the_encoder_key(tmp_path) -> None:
    torch.manual_seed(0)
    folder = save_descriptor(DescriptorNet(**DEPTH_TINY), tmp_path / "d", input_size=32)
    before = repr(LearnedAppearanceEncoder(folder))
    assert repr(LearnedAppearanceEncoder(folder)) == before
    torch.manual_seed(1)
    save_descriptor(DescriptorNet(**DEPTH_TINY), folder, input_size=32)
    assert repr(LearnedAppearanceEncoder(folder)) != before
