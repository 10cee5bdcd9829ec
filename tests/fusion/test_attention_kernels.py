"""Which SDPA kernel the fusion's attention runs on, and that choosing it changes no result.

PyTorch names the kernel it ran in the profiler: ``aten::_scaled_dot_product_flash_attention``,
``..._efficient_attention``, ``..._cudnn_attention`` and ``..._attention_math`` on CUDA,
``..._flash_attention_for_cpu`` (the CPU's fused kernel) and ``..._attention_math`` on the CPU.
The CPU has no memory-efficient or cuDNN kernel (``sdpa_kernel([EFFICIENT_ATTENTION])`` finds no
viable backend there), so the CUDA choices are checked only where a GPU is present; on the CPU the
tests check that float32 and bfloat16, with and without padding, all stay on the fused kernel.
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from torch.nn.attention import SDPBackend, sdpa_kernel
from torch.profiler import ProfilerActivity, profile

from poseflow.errors import ShapeError
from poseflow.fusion import GatedCrossAttentionFusion, attend, key_padding_mask
from poseflow.fusion.attention import _backends_without_cudnn

CPU_FUSED = "aten::_scaled_dot_product_flash_attention_for_cpu"
FLASH = "aten::_scaled_dot_product_flash_attention"
EFFICIENT = "aten::_scaled_dot_product_efficient_attention"
CUDNN = "aten::_scaled_dot_product_cudnn_attention"
MATH = "aten::_scaled_dot_product_attention_math"

needs_sm80 = pytest.mark.skipif(
    not torch.cuda.is_available() or torch.cuda.get_device_capability() < (8, 0),
    reason="flash and memory-efficient bfloat16 attention need a CUDA GPU of sm80 or newer",
)


def sdpa_kernels(fn) -> set[str]:
    """The SDPA kernels (aten op names) that ``fn()`` ran."""
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        fn()
    return {e.name for e in prof.events() if e.name.startswith("aten::_scaled_dot_product")}


def qkv(batch=4, heads=4, p=24, s=32, dim=16, *, dtype=torch.float32, device="cpu", seed=0):
    g = torch.Generator().manual_seed(seed)
    shapes = ((batch, heads, p, dim), (batch, heads, s, dim), (batch, heads, s, dim))
    return [torch.randn(*sh, generator=g).to(device=device, dtype=dtype) for sh in shapes]


def masks(batch=4, s=32, device="cpu"):
    """No mask, an all-valid mask, padding, and padding with one item entirely padded."""
    padded = torch.ones(batch, s, dtype=torch.bool)
    padded[1, 20:] = False
    padded[3, 5:] = False
    empty = padded.clone()
    empty[2] = False
    all_valid = torch.ones(batch, s, dtype=torch.bool)
    return {
        "none": None,
        "all_valid": all_valid.to(device),
        "padded": padded.to(device),
        "empty_item": empty.to(device),
    }


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.bfloat16])
@pytest.mark.parametrize("which", ["none", "all_valid", "padded", "empty_item"])
def test_attend_equals_sdpa_with_the_boolean_key_mask_bit_for_bit(dtype, which):
    """The former call, SDPA with the boolean mask of key_padding_mask, gives the same bits."""
    q, k, v = qkv(dtype=dtype)
    mask = masks()[which]
    expected = F.scaled_dot_product_attention(
        q, k, v, attn_mask=None if mask is None else key_padding_mask(mask)
    )
    out = attend(q, k, v, mask)
    assert out.dtype == dtype
    assert torch.equal(out, expected)


def test_gated_fusion_output_is_unchanged_by_dropping_an_all_valid_mask():
    torch.manual_seed(0)
    block = GatedCrossAttentionFusion(32, num_heads=4).eval()
    g = torch.Generator().manual_seed(1)
    geo, sem = torch.randn(2, 3, 40, 32, generator=g)
    with torch.no_grad():
        a = block(geo, sem)
        b = block(geo, sem, torch.ones(3, 40, dtype=torch.bool))
    assert torch.equal(a, b)


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
@pytest.mark.parametrize("which", ["none", "all_valid", "padded"])
def test_cpu_runs_the_fused_kernel_not_the_math_fallback(dtype, which):
    q, k, v = qkv(dtype=dtype)
    mask = masks()[which]
    assert sdpa_kernels(lambda: attend(q, k, v, mask)) == {CPU_FUSED}


@pytest.mark.parametrize("padded", [False, True])
def test_gated_fusion_under_bf16_autocast_stays_on_the_fused_cpu_kernel(padded):
    torch.manual_seed(0)
    block = GatedCrossAttentionFusion(64, num_heads=4).eval()
    g = torch.Generator().manual_seed(2)
    geo, sem = torch.randn(2, 4, 48, 64, generator=g)
    mask = torch.ones(4, 48, dtype=torch.bool)
    if padded:
        mask[1, 30:] = False

    def run():
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
            return block(geo, sem, mask)

    assert sdpa_kernels(run) == {CPU_FUSED}
    assert run().isfinite().all()


def test_the_backends_left_follow_the_users_switches():
    every = [
        SDPBackend.CUDNN_ATTENTION,
        SDPBackend.FLASH_ATTENTION,
        SDPBackend.EFFICIENT_ATTENTION,
        SDPBackend.MATH,
    ]
    with sdpa_kernel(every):
        assert _backends_without_cudnn() == [
            SDPBackend.FLASH_ATTENTION,
            SDPBackend.EFFICIENT_ATTENTION,
            SDPBackend.MATH,
        ]
    with sdpa_kernel([SDPBackend.MATH, SDPBackend.CUDNN_ATTENTION]):
        assert _backends_without_cudnn() == [SDPBackend.MATH]
    with sdpa_kernel([SDPBackend.CUDNN_ATTENTION]):
        assert _backends_without_cudnn() == []


def test_bad_inputs_raise():
    q, k, v = qkv()
    with pytest.raises(ShapeError):
        attend(q, k[:, :, :5], v)
    with pytest.raises(ShapeError):
        attend(q, k, v, torch.ones(4, 31, dtype=torch.bool))
    with pytest.raises(ShapeError):
        attend(q, k.double(), v)


@needs_sm80
@pytest.mark.parametrize(
    ("dtype", "which", "kernel"),
    [
        (torch.bfloat16, "none", FLASH),
        (torch.bfloat16, "all_valid", FLASH),
        (torch.bfloat16, "padded", EFFICIENT),
        (torch.float32, "none", EFFICIENT),
        (torch.float32, "padded", EFFICIENT),
    ],
)
def test_cuda_picks_flash_or_efficient_even_where_cudnn_comes_first(dtype, which, kernel):
    """cuDNN first in the priority order is torch 2.11's default on H100/H200/B200."""
    q, k, v = qkv(dtype=dtype, device="cuda")
    mask = masks(device="cuda")[which]
    order = [
        SDPBackend.CUDNN_ATTENTION,
        SDPBackend.FLASH_ATTENTION,
        SDPBackend.EFFICIENT_ATTENTION,
        SDPBackend.MATH,
    ]
    with sdpa_kernel(order, set_priority=True):
        ran = sdpa_kernels(lambda: attend(q, k, v, mask))
        out = attend(q, k, v, mask)
    assert ran == {kernel}
    expected = F.scaled_dot_product_attention(
        *(t.float() for t in (q, k, v)),
        attn_mask=None if mask is None else key_padding_mask(mask),
    )
    tol = 2e-2 if dtype == torch.bfloat16 else 1e-5
    assert torch.allclose(out.float(), expected, atol=tol, rtol=tol)
