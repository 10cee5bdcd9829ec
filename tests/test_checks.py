import pytest
import torch

from poseflow._checks import check_mask, check_same, check_tensor
from poseflow.errors import PoseflowError, ShapeError, ValueRangeError


def test_named_sizes_must_agree_across_checks():
    sizes = check_tensor(torch.zeros(2, 5, 3), "a", ("B", "N", 3))
    check_tensor(torch.zeros(2, 5), "w", ("B", "N"), sizes=sizes)
    with pytest.raises(ShapeError, match="N=5"):
        check_tensor(torch.zeros(2, 4), "w", ("B", "N"), sizes=sizes)


@pytest.mark.parametrize(
    "x, shape",
    [
        (torch.zeros(2, 5), ("B", "N", 3)),
        (torch.zeros(2, 5, 4), ("B", "N", 3)),
        (torch.zeros(2, 5, 3, dtype=torch.int64), ("B", "N", 3)),
        ([[0.0, 0.0, 0.0]], ("N", 3)),
        (torch.zeros(2), ("*", 4, 4)),
    ],
)
def test_malformed_tensors_raise_shape_error(x, shape):
    with pytest.raises(ShapeError):
        check_tensor(x, "x", shape)


def test_leading_star_accepts_any_batch_shape():
    check_tensor(torch.zeros(4, 7, 3, 3), "R", ("*", 3, 3))


def test_non_finite_values_raise_value_range_error():
    x = torch.zeros(3, 3)
    x[1, 2] = float("nan")
    with pytest.raises(ValueRangeError, match="NaN"):
        check_tensor(x, "x", ("N", 3), finite=True)


@pytest.mark.parametrize("where", [(0, 0, 0), (2, 1, 3)])
def test_an_expanded_tensor_is_checked_through_its_one_copy(where):
    image = torch.rand(3, 4, 5)
    expanded = image.expand(6, 3, 4, 5)  # one image for six instances, stride 0
    check_tensor(expanded, "images", ("B", 3, None, None), finite=True)
    image[where] = float("inf")
    with pytest.raises(ValueRangeError, match="images contains NaN or inf"):
        check_tensor(expanded, "images", ("B", 3, None, None), finite=True)
    with pytest.raises(ValueRangeError):  # a dimension of size 1 with a stride of 0 too
        check_tensor(image[:, None].expand(3, 2, 4, 5), "x", (3, 2, 4, 5), finite=True)


def test_mask_must_be_bool():
    with pytest.raises(ShapeError, match="bool"):
        check_mask(torch.ones(2, 5), "mask", ("B", "N"), {"B": 2, "N": 5})


def test_dtype_and_device_mismatch():
    with pytest.raises(ShapeError, match="dtype"):
        check_same(("a", torch.zeros(1)), ("b", torch.zeros(1, dtype=torch.float64)))
    check_same(("a", torch.zeros(1)), ("b", torch.zeros(1, dtype=torch.float64)), dtype=False)


def test_errors_are_builtin_subclasses():
    assert issubclass(ShapeError, ValueError) and issubclass(ShapeError, PoseflowError)
