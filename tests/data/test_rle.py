import json

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from poseflow.data.rle import rle_area, rle_decode, rle_encode
from poseflow.errors import ShapeError, ValueRangeError


def _mask_from_runs(h: int, w: int, runs: list[int]) -> np.ndarray:
    """Reference decoder written the slow, obvious way: fill column by column."""
    flat = []
    value = False
    for r in runs:
        flat += [value] * r
        value = not value
    m = np.zeros((h, w), dtype=bool)
    for k, v in enumerate(flat):
        m[k % h, k // h] = v  # column-major
    return m


def test_uncompressed_hand_made():
    # 3x4, column-major runs: 2 zeros, 3 ones, 7 zeros
    expected = np.zeros((3, 4), dtype=bool)
    expected[2, 0] = True
    expected[0:2, 1] = True
    out = rle_decode({"size": [3, 4], "counts": [2, 3, 7]})
    assert out.dtype == torch.bool and out.shape == (3, 4)
    assert np.array_equal(out.numpy(), expected)


def test_uncompressed_starting_with_ones():
    out = rle_decode({"size": [2, 2], "counts": [0, 4]})
    assert bool(out.all())


def test_compressed_hand_made_positive_delta():
    # runs [0, 3, 2, 40, 3]: from the 4th run on deltas 40-3=37 and 3-2=1;
    # 37 = 0b00101 + 0b1 << 5 -> chars chr(48+5|0x20)='U', chr(48+1)='1'
    runs = [0, 3, 2, 40, 3]
    out = rle_decode({"size": [6, 8], "counts": "032U11"})
    assert np.array_equal(out.numpy(), _mask_from_runs(6, 8, runs))
    assert rle_encode(out)["counts"] == "032U11"


def test_compressed_hand_made_negative_delta():
    # runs [5, 10, 2, 1, 2]: deltas 1-10=-9 -> 23 with the sign bit -> 'G'; 2-2=0 -> '0'
    runs = [5, 10, 2, 1, 2]
    out = rle_decode({"size": [4, 5], "counts": "5:2G0"})
    assert np.array_equal(out.numpy(), _mask_from_runs(4, 5, runs))
    assert rle_encode(out)["counts"] == "5:2G0"
    assert rle_encode(out, compressed=False)["counts"] == runs


def test_bytes_counts():
    out = rle_decode({"size": [4, 5], "counts": b"5:2G0"})
    assert int(out.sum()) == 10 + 1


@given(
    seed=st.integers(0, 2**31 - 1),
    h=st.integers(0, 40),
    w=st.integers(0, 40),
    density=st.floats(0.0, 1.0),
    compressed=st.booleans(),
)
def test_round_trip(seed, h, w, density, compressed):
    g = torch.Generator().manual_seed(seed)
    mask = torch.rand(h, w, generator=g) < density
    rle = rle_encode(mask, compressed=compressed)
    rle = json.loads(json.dumps(rle))  # must survive JSON
    assert torch.equal(rle_decode(rle), mask)
    assert rle_area(rle) == int(mask.sum())
    if not compressed:
        assert np.array_equal(rle_decode(rle).numpy(), _mask_from_runs(h, w, rle["counts"]))


def test_large_runs_compressed():
    mask = torch.zeros(480, 640, dtype=torch.bool)
    mask[100:400, 200:500] = True
    rle = rle_encode(mask)
    assert isinstance(rle["counts"], str)
    assert torch.equal(rle_decode(rle), mask)


@pytest.mark.parametrize(
    "rle",
    [
        {"size": [2, 2], "counts": [1, 2]},  # sums to 3, not 4
        {"size": [2, 2], "counts": "U"},  # continuation bit set on the last character
        {"size": [2, 2], "counts": "4~"},  # character outside the alphabet
        {"size": [2, 2], "counts": [1, -1, 4]},
        {"counts": [4]},
        {"size": [2], "counts": [2]},
    ],
)
def test_malformed(rle):
    with pytest.raises(ValueRangeError):
        rle_decode(rle)


def test_encode_wrong_rank():
    with pytest.raises(ShapeError):
        rle_encode(torch.zeros(2, 2, 2))
