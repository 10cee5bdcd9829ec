import pytest
import torch

from poseflow.errors import ValueRangeError
from poseflow.flows import PRECISIONS, autocast_dtype, native_bfloat16, precision_autocast

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("name", sorted(PRECISIONS))
def test_named_precisions_mean_their_dtype(name, device):
    assert autocast_dtype(name, device) is PRECISIONS[name]


@pytest.mark.parametrize("device", DEVICES)
def test_auto_is_bfloat16_exactly_where_the_device_has_it(device):
    expected = torch.bfloat16 if native_bfloat16(device) else None
    assert autocast_dtype("auto", device) is expected


@pytest.mark.parametrize("native", [False, True])
def test_auto_follows_the_cpu_instructions(monkeypatch, native):
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: native, raising=False)
    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: False, raising=False)
    assert native_bfloat16("cpu") is native
    assert autocast_dtype("auto", "cpu") is (torch.bfloat16 if native else None)


def test_an_unknown_precision_is_named_in_the_error():
    with pytest.raises(ValueRangeError, match=r"'tf32'"):
        autocast_dtype("tf32", "cpu")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_products_run_in_the_precision_and_fp32_leaves_them_alone(dtype):
    a = torch.randn(8, 8, dtype=torch.float32)
    with precision_autocast("bf16", "cpu"):
        assert (a @ a).dtype == torch.bfloat16
    b = torch.randn(8, 8, dtype=dtype)
    with precision_autocast("fp32", "cpu"):
        assert not torch.is_autocast_enabled("cpu") and (b @ b).dtype == dtype
