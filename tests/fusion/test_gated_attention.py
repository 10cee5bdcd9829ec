"""Tests of poseflow.fusion.attention: (gated) cross-attention between two streams."""

from __future__ import annotations

import math

import pytest
import torch

from poseflow.errors import ShapeError, ValueRangeError
from poseflow.fusion import CrossAttention, GatedCrossAttention, key_padding_mask


def randn(*shape, seed, dtype=torch.float32):
    return torch.randn(*shape, generator=torch.Generator().manual_seed(seed), dtype=dtype)


def test_shapes_with_different_query_and_key_counts(device, dtype):
    layer = GatedCrossAttention(8, num_heads=2).to(device=device, dtype=dtype).eval()
    out, gate = layer(
        randn(2, 5, 8, seed=0, dtype=dtype).to(device),
        randn(2, 9, 8, seed=1, dtype=dtype).to(device),
        return_gate=True,
    )
    assert out.shape == (2, 5, 8) and gate.shape == (2, 5, 8)
    assert out.dtype == dtype and out.device.type == device.type


def test_gate_is_zero_initialised_and_exactly_one_half():
    layer = GatedCrossAttention(16, num_heads=4)
    assert torch.equal(layer.to_gate.weight, torch.zeros(16, 16))
    assert torch.equal(layer.to_gate.bias, torch.zeros(16))
    gate = layer.gate(100.0 * randn(3, 4, 16, seed=2))
    assert torch.equal(gate, torch.full_like(gate, 0.5))


def test_matches_a_hand_written_reference(dtype, tol):
    """Gated SDPA, W_O and the residual LayerNorm, written out per head."""
    torch.manual_seed(0)
    layer = GatedCrossAttention(6, num_heads=3, dropout=0.0).to(dtype)
    with torch.no_grad():
        layer.to_gate.weight.copy_(randn(6, 6, seed=3, dtype=dtype))
        layer.to_gate.bias.copy_(randn(6, seed=4, dtype=dtype))
    xq, xkv = randn(1, 4, 6, seed=5, dtype=dtype), randn(1, 3, 6, seed=6, dtype=dtype)
    q, k, v = layer.to_q(xq)[0], layer.to_k(xkv)[0], layer.to_v(xkv)[0]
    heads = []
    for h in range(3):
        sl = slice(2 * h, 2 * h + 2)
        w = torch.softmax(q[:, sl] @ k[:, sl].T / math.sqrt(2), dim=-1)
        heads.append(w @ v[:, sl])
    att = torch.cat(heads, dim=-1) * torch.sigmoid(
        xq[0] @ layer.to_gate.weight.T + layer.to_gate.bias
    )
    expected = torch.nn.functional.layer_norm(
        xq[0] + layer.out_proj(att), (6,), layer.norm.weight, layer.norm.bias
    )
    assert torch.allclose(layer(xq, xkv)[0], expected, atol=10 * tol)


def test_ungated_layer_equals_gated_layer_with_gate_one():
    torch.manual_seed(0)
    gated = GatedCrossAttention(8, num_heads=2).eval()
    plain = CrossAttention(8, num_heads=2).eval()
    plain.load_state_dict({k: v for k, v in gated.state_dict().items() if "gate" not in k})
    with torch.no_grad():
        gated.to_gate.bias.fill_(50.0)  # sigmoid(50) == 1 in float32
    xq, xkv = randn(2, 4, 8, seed=7), randn(2, 6, 8, seed=8)
    out, gate = plain(xq, xkv, return_gate=True)
    assert gate is None
    assert torch.allclose(out, gated(xq, xkv), atol=1e-6)


def test_masked_keys_are_ignored_and_masked_queries_zeroed():
    layer = GatedCrossAttention(8, num_heads=2).eval()
    xq, xkv = randn(1, 4, 8, seed=9), randn(1, 6, 8, seed=10)
    kv_mask = torch.tensor([[True, True, True, False, False, True]])
    q_mask = torch.tensor([[True, True, False, True]])
    a = layer(xq, xkv, kv_mask=kv_mask, q_mask=q_mask)
    garbage = xkv.clone()
    garbage[0, 3:5] = 1e4
    b = layer(xq, garbage, kv_mask=kv_mask, q_mask=q_mask)
    assert torch.allclose(a, b, atol=1e-6)
    assert torch.equal(a[0, 2], torch.zeros(8))
    assert torch.allclose(a[:, [0, 1, 3]], layer(xq[:, [0, 1, 3]], xkv[:, [0, 1, 2, 5]]), atol=1e-6)


def test_key_padding_mask_never_masks_a_whole_row():
    mask = torch.tensor([[True, False, True], [False, False, False]])
    out = key_padding_mask(mask)
    assert out.shape == (2, 1, 1, 3)
    assert out[0, 0, 0].tolist() == [True, False, True]
    assert out[1].all()


def test_bad_arguments_raise():
    with pytest.raises(ValueRangeError):
        GatedCrossAttention(10, num_heads=3)
    with pytest.raises(ValueRangeError):
        CrossAttention(8, num_heads=2, dropout=1.0)
    layer = GatedCrossAttention(8, num_heads=2)
    with pytest.raises(ShapeError):
        layer(randn(2, 4, 8, seed=0), randn(3, 4, 8, seed=1))
    with pytest.raises(ShapeError):
        layer(randn(2, 4, 8, seed=0), randn(2, 4, 8, seed=1), kv_mask=torch.ones(2, 3).bool())
