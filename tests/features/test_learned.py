from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import poseflow.features.learned as learned_mod
from poseflow.errors import CheckpointError, MissingWeightsError, ValueRangeError
from poseflow.features.appearance import AppearanceEncoder
from poseflow.features.descriptor_training import (
    DescriptorTrainingConfig,
    descriptor_loss,
    train_descriptor,
)
from poseflow.features.learned import (
    DescriptorNet,
    LearnedAppearanceEncoder,
    load_descriptor,
    save_descriptor,
)
from poseflow.features.procedural import random_mesh, random_texture, texture_images
from poseflow.features.view_pairs import PairGenerator, render_pair
from poseflow.models.components import build_appearance_encoder
from poseflow.models.config import FunFlow6DConfig

TINY = {"widths": (8, 16, 16), "dim": 12, "out_stride": 4}


def _net(seed: int = 0) -> DescriptorNet:
    torch.manual_seed(seed)
    return DescriptorNet(**TINY)


@pytest.fixture
def folder(tmp_path):
    return save_descriptor(_net(), tmp_path / "desc", input_size=32, query_pooling="mean")


def test_shapes_dtype_device(device, dtype) -> None:
    enc = LearnedAppearanceEncoder(_net(), input_size=32, device=device)
    img = torch.rand(3, 3, 40, 48, generator=torch.Generator().manual_seed(0))
    out = enc.encode(img.to(device=device, dtype=dtype))
    assert isinstance(enc, AppearanceEncoder)
    assert out.shape == (3, 12, 8, 8) and out.dtype == dtype and out.device == img.to(device).device
    torch.testing.assert_close(out.norm(dim=1), torch.ones(3, 8, 8, dtype=dtype, device=device))
    assert enc.dim == 12 and enc.input_size == 32 and enc.query_pooling == "mean"


@pytest.mark.parametrize("out_stride, side", [(2, 16), (4, 8)])
def test_network_strides_and_odd_sizes(out_stride: int, side: int) -> None:
    net = DescriptorNet(widths=(8, 16, 16), dim=6, out_stride=out_stride).eval()
    assert net(torch.rand(1, 3, 32, 32)).shape == (1, 6, side, side)
    assert net(torch.rand(1, 3, 30, 27)).shape[-2:] == (-(-30 // out_stride), -(-27 // out_stride))


def test_encoder_is_deterministic() -> None:
    enc = LearnedAppearanceEncoder(_net(), input_size=32)
    img = torch.rand(2, 3, 32, 32, generator=torch.Generator().manual_seed(1))
    assert torch.equal(enc.encode(img), enc.encode(img))
    # the same image alone or in a batch: equal up to the convolutions' summation order
    torch.testing.assert_close(enc.encode(img[:1]), enc.encode(img)[:1], atol=1e-5, rtol=1e-5)


def test_save_load_round_trip(folder) -> None:
    net, cfg = load_descriptor(folder)
    assert cfg["format"] == "poseflow-descriptor" and cfg["input_size"] == 32
    assert (cfg["widths"], cfg["dim"], cfg["out_stride"]) == ([8, 16, 16], 12, 4)
    for k, v in _net().state_dict().items():
        assert torch.equal(net.state_dict()[k], v)
    enc = LearnedAppearanceEncoder(folder)
    img = torch.rand(2, 3, 32, 32, generator=torch.Generator().manual_seed(2))
    ref = LearnedAppearanceEncoder(_net(), input_size=32)
    assert torch.equal(enc.encode(img), ref.encode(img))
    assert enc.input_size == 32 and enc.query_pooling == "mean"
    assert LearnedAppearanceEncoder(folder, query_pooling="select").query_pooling == "select"
    assert sorted(p.name for p in folder.iterdir()) == ["config.json", "model.safetensors"]


def test_registered_name(folder) -> None:
    enc = build_appearance_encoder(f"learned:{folder}", crop_size=48)
    assert isinstance(enc, LearnedAppearanceEncoder) and enc.input_size == 48
    assert FunFlow6DConfig(appearance_encoder=f"learned:{folder}").appearance_encoder.startswith(
        "learned"
    )


def test_bad_weights_folder_is_a_clear_error(tmp_path, folder, monkeypatch) -> None:
    with pytest.raises(MissingWeightsError, match="descriptor_training"):
        LearnedAppearanceEncoder(tmp_path / "nowhere")
    monkeypatch.setattr(learned_mod, "SHIPPED_DESCRIPTOR_DIR", tmp_path / "not_shipped")
    with pytest.raises(MissingWeightsError, match="ships no learned descriptor"):
        build_appearance_encoder("learned", crop_size=32)
    (folder / "model.safetensors").unlink()
    with pytest.raises(MissingWeightsError, match=r"lacks model\.safetensors"):
        load_descriptor(folder)
    other = save_descriptor(_net(), tmp_path / "other")
    (other / "model.safetensors").write_bytes(b"not a safetensors file")
    with pytest.raises(CheckpointError, match="cannot be read"):
        load_descriptor(other)
    save_descriptor(DescriptorNet(widths=(8, 16, 16), dim=5), other)
    cfg = json.loads((other / "config.json").read_text())
    (other / "config.json").write_text(json.dumps({**cfg, "dim": 7}))
    with pytest.raises(CheckpointError, match="does not fit"):
        load_descriptor(other)
    (other / "config.json").write_text(json.dumps({**cfg, "format": "something-else"}))
    with pytest.raises(CheckpointError, match="not a learned descriptor"):
        load_descriptor(other)
    (other / "config.json").write_text("{truncated")
    with pytest.raises(CheckpointError, match="not valid JSON"):
        load_descriptor(other)


@pytest.mark.skipif(
    not (learned_mod.SHIPPED_DESCRIPTOR_DIR / "model.safetensors").is_file(),
    reason="this checkout ships no descriptor weights",
)
def test_shipped_weights_load() -> None:
    enc = build_appearance_encoder("learned", crop_size=96)
    assert isinstance(enc, LearnedAppearanceEncoder) and enc.query_pooling in ("mean", "select")
    out = enc.encode(torch.rand(1, 3, 96, 96, generator=torch.Generator().manual_seed(0)))
    assert out.shape == (1, enc.dim, 24, 24) and bool(torch.isfinite(out).all())


def test_bad_arguments() -> None:
    with pytest.raises(ValueRangeError):
        DescriptorNet(widths=(8,))
    with pytest.raises(ValueRangeError):
        DescriptorNet(widths=(8, 16), out_stride=4)
    with pytest.raises(ValueRangeError):
        LearnedAppearanceEncoder(_net(), input_size=32, query_pooling="max")
    with pytest.raises(ValueRangeError):
        DescriptorTrainingConfig(fresh_pairs=9, batch_size=8)


def test_procedural_mesh_and_texture() -> None:
    rng = np.random.default_rng(5)
    for _ in range(5):
        mesh = random_mesh(rng, diameter=0.2)
        assert abs(np.linalg.norm(mesh.extent()) - 0.2) < 1e-9
        assert mesh.vertex_normals is not None
    images = texture_images(rng, count=2, photos=True)
    assert all(im.dtype == np.uint8 and im.shape[2] == 3 for im in images)
    pts = rng.uniform(-0.5, 0.5, size=(200, 3))
    nrm = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    for _ in range(20):
        albedo = random_texture(rng, images, patchwork=0.5)(pts, nrm)
        assert albedo.shape == (200, 3) and albedo.min() >= 0 and albedo.max() <= 1


def test_generator_correspondences_are_right() -> None:
    rng = np.random.default_rng(11)
    images = texture_images(rng, count=2, photos=False)
    checked = 0
    while checked < 4:
        mesh = random_mesh(rng)
        pair = render_pair(rng, mesh, random_texture(rng, images), images, input_size=48)
        if pair is None:
            continue
        checked += 1
        assert pair.images.shape == (2, 3, 48, 48) and len(pair.uv_a) == len(pair.uv_b) >= 32
        for view, uv in ((0, pair.uv_a), (1, pair.uv_b)):
            pix = uv.round().long().clamp(0, 47)
            assert bool(pair.mask[view][pix[:, 1], pix[:, 0]].float().mean() > 0.95)
            back = pair.coords[view][pix[:, 1], pix[:, 0]]
            # both pixels back-project to the same model point, within a pixel's footprint
            err = (back - pair.points).norm(dim=1)
            assert float(err.median()) < 0.03 and float(err.quantile(0.9)) < 0.08


@pytest.mark.parametrize("sigma", [0.0, 0.06])
def test_loss_decreases_on_a_tiny_config(sigma: float) -> None:
    torch.manual_seed(0)
    gen = PairGenerator(0, input_size=32, anchors=32, texture_count=2, photos=False)
    batch = gen.batch(4)
    net = DescriptorNet(widths=(16, 24, 32), dim=16, out_stride=2)
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    losses = []
    for _ in range(25):
        fa, fb = net(torch.cat([batch.images_a, batch.images_b])).chunk(2)
        loss, acc = descriptor_loss(fa, fb, batch, temperature=0.1, exclusion=0.1, sigma=sigma)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
        assert 0 <= float(acc) <= 1
    assert np.mean(losses[-5:]) < 0.8 * np.mean(losses[:3])


def test_train_descriptor_writes_a_loadable_folder(tmp_path) -> None:
    out = train_descriptor(
        tmp_path / "run",
        steps=2,
        batch_size=2,
        fresh_pairs=1,
        pool_size=2,
        input_size=32,
        anchors=8,
        progress=False,
        **TINY,
    )
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["training"]["steps_done"] == 2 and cfg["training"]["final"]
    enc = LearnedAppearanceEncoder(out)
    assert enc.encode(torch.rand(1, 3, 32, 32)).shape == (1, 12, 8, 8)
