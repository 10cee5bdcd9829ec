from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from transformers import Dinov2Config, Dinov2Model

from poseflow.errors import MissingWeightsError, ShapeError, ValueRangeError
from poseflow.features.appearance import (
    AppearanceEncoder,
    DenseSIFTEncoder,
    DINOv2Encoder,
    features_at,
    sample_features,
    upsample_features,
)


@pytest.fixture(scope="module")
def tiny_dino() -> Dinov2Model:
    torch.manual_seed(0)
    cfg = Dinov2Config(
        hidden_size=24,
        num_hidden_layers=3,
        num_attention_heads=2,
        intermediate_size=48,
        image_size=56,
    )
    return Dinov2Model(cfg).eval()


def test_dinov2_shapes_layers_and_norm(tiny_dino: Dinov2Model) -> None:
    img = torch.rand(2, 3, 60, 50, generator=torch.Generator().manual_seed(0))
    enc = DINOv2Encoder(tiny_dino, input_size=56)
    out = enc.encode(img)
    assert out.shape == (2, 24, 4, 4) and enc.dim == 24
    assert isinstance(enc, AppearanceEncoder) and enc.query_pooling == "mean"
    # the map is the layer's patch tokens after the final layer norm
    x = torch.nn.functional.interpolate(img, size=(56, 56), mode="bilinear", antialias=True)
    mean = torch.tensor([0.485, 0.456, 0.406])[:, None, None]
    std = torch.tensor([0.229, 0.224, 0.225])[:, None, None]
    ref = tiny_dino(pixel_values=(x - mean) / std).last_hidden_state[:, 1:]
    assert torch.allclose(out.flatten(2).transpose(1, 2), ref, atol=1e-5)
    first = DINOv2Encoder(tiny_dino, input_size=56, layer=1, layernorm=False, l2_normalize=True)
    f1 = first.encode(img)
    assert torch.allclose(f1.norm(dim=1), torch.ones(2, 4, 4), atol=1e-5)
    assert not torch.allclose(torch.nn.functional.normalize(out, dim=1), f1, atol=1e-3)
    assert enc.encode(img.double()).dtype == torch.float64


def test_dinov2_bad_settings(tiny_dino: Dinov2Model) -> None:
    with pytest.raises(ValueRangeError):
        DINOv2Encoder(tiny_dino, input_size=50)
    with pytest.raises(ValueRangeError):
        DINOv2Encoder(tiny_dino, input_size=56, layer=7)
    with pytest.raises(ShapeError):
        DINOv2Encoder(tiny_dino, input_size=56).encode(torch.rand(2, 1, 56, 56))


def test_dinov2_missing_weights_says_how(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    with pytest.raises(MissingWeightsError, match=r"hf download facebook/dinov2-small"):
        DINOv2Encoder("vits14")
    with pytest.raises(MissingWeightsError, match=r"lacks config\.json"):
        DINOv2Encoder(tmp_path)


def test_dinov2_loads_a_local_directory(tmp_path, tiny_dino: Dinov2Model) -> None:
    tiny_dino.save_pretrained(tmp_path / "dino")
    enc = DINOv2Encoder(tmp_path / "dino", input_size=28)
    img = torch.rand(1, 3, 28, 28)
    assert torch.allclose(enc.encode(img), DINOv2Encoder(tiny_dino, input_size=28).encode(img))


@given(seed=st.integers(0, 2**31 - 1), h=st.integers(2, 6), w=st.integers(2, 6))
def test_sample_features_reads_linear_maps_exactly(seed: int, h: int, w: int) -> None:
    # a map linear in the image coordinates is reproduced exactly inside the grid's centres
    H, W = 4 * h, 3 * w
    a, b, c = torch.randn(3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    cu = (torch.arange(w, dtype=torch.float64) + 0.5) * W / w - 0.5  # cell centres, image pixels
    cv = (torch.arange(h, dtype=torch.float64) + 0.5) * H / h - 0.5
    fmap = (a * cu[None, :] + b * cv[:, None] + c)[None, None]
    g = torch.Generator().manual_seed(seed + 1)
    uv = torch.stack(
        [
            cu[0] + (cu[-1] - cu[0]) * torch.rand(20, generator=g, dtype=torch.float64),
            cv[0] + (cv[-1] - cv[0]) * torch.rand(20, generator=g, dtype=torch.float64),
        ],
        dim=-1,
    )[None]
    out = sample_features(fmap, uv, (H, W))[0, :, 0]
    assert torch.allclose(out, a * uv[0, :, 0] + b * uv[0, :, 1] + c, atol=1e-10)


def test_upsample_features_shape_and_constant() -> None:
    f = torch.full((1, 3, 4, 4), 2.0)
    up = upsample_features(f, (14, 10))
    assert up.shape == (1, 3, 14, 10) and torch.allclose(up, torch.full_like(up, 2.0))


def test_dense_sift_grid_follows_the_image(device: torch.device, dtype: torch.dtype) -> None:
    g = torch.Generator().manual_seed(0)
    img = torch.rand(1, 3, 48, 48, generator=g, dtype=dtype).to(device)
    enc = DenseSIFTEncoder(input_size=48)
    out = enc.encode(img)
    assert out.shape == (1, 128, 48, 48) and out.dtype == dtype and out.device.type == device.type
    assert torch.allclose(out.norm(dim=1), torch.ones(1, 48, 48, dtype=dtype, device=device))
    shifted = enc.encode(torch.roll(img, shifts=(3, 5), dims=(2, 3)))
    # away from the borders, descriptors move with the image
    assert torch.allclose(shifted[..., 20:30, 20:30], out[..., 17:27, 15:25], atol=1e-4)
    assert DenseSIFTEncoder(input_size=32, color="rgb").encode(img).shape == (1, 384, 32, 32)
    with pytest.raises(ValueRangeError):
        DenseSIFTEncoder(color="hsv")


@pytest.mark.parametrize("color", ["gray", "rgb"])
def test_dense_sift_equals_kornia_with_its_own_weights(color: str) -> None:
    """The pieces (kornia's histograms and pooling, RootSIFT) give kornia's descriptors."""
    import torch.nn.functional as F
    from kornia.feature import DenseSIFTDescriptor

    g = torch.Generator().manual_seed(1)
    img = torch.rand(2, 3, 40, 40, generator=g)
    enc = DenseSIFTEncoder(input_size=40, color=color)
    assert enc._sift.PoolingConv.weight.is_contiguous(memory_format=torch.channels_last)
    reference = DenseSIFTDescriptor(spatial_bin_size=4, padding=0)
    weights = torch.tensor([0.299, 0.587, 0.114])[:, None, None]
    if color == "gray":
        channels = (img * weights).sum(1, keepdim=True)
    else:
        channels = img.reshape(-1, 1, 40, 40)
    lo, hi = enc._pad
    plain = reference(F.pad(channels, (lo, hi, lo, hi), mode="reflect"))
    expected = F.normalize(plain.reshape(2, -1, 40, 40), dim=1)
    torch.testing.assert_close(enc.encode(img), expected, rtol=0, atol=1e-6)


@pytest.mark.parametrize("color", ["gray", "rgb"])
@given(seed=st.integers(0, 2**31 - 1))
@settings(max_examples=10, deadline=None)
def test_dense_sift_at_points_equals_sampling_the_dense_map(color: str, seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    enc = DenseSIFTEncoder(input_size=32, color=color)
    img = torch.rand(2, 3, 32, 32, generator=g)
    uv = torch.rand(2, 40, 2, generator=g) * 36 - 2  # some outside the image (border reads)
    uv[:, :10] = uv[:, :10].round()  # on pixel centres, where one neighbour has zero weight
    expected = sample_features(enc.encode(img), uv, (32, 32))
    torch.testing.assert_close(enc.encode_at(img, uv), expected, rtol=0, atol=1e-6)
    torch.testing.assert_close(features_at(enc, img, uv), expected, rtol=0, atol=1e-6)


def test_features_at_samples_the_map_of_an_encoder_without_encode_at() -> None:
    class Colours:
        dim, input_size, query_pooling = 3, 8, "mean"

        def encode(self, images: torch.Tensor) -> torch.Tensor:
            return images

    img = torch.rand(1, 3, 8, 8, generator=torch.Generator().manual_seed(0))
    out = features_at(Colours(), img, torch.tensor([[[2.0, 5.0], [3.5, 1.0]]]))
    torch.testing.assert_close(out[0, 0], img[0, :, 5, 2])
    torch.testing.assert_close(out[0, 1], (img[0, :, 1, 3] + img[0, :, 1, 4]) / 2)
