import pytest
import torch

from poseflow._api import Hyperparameters
from poseflow.errors import ValueRangeError
from poseflow.features.gedi import GeDiEncoder, GeDiNet
from poseflow.features.geometric import FPFHEncoder
from poseflow.registration import (
    ICP,
    MultiScaleICP,
    Procrustes,
    RANSACProcrustes,
    icp,
    multi_scale_icp,
    procrustes,
    ransac_procrustes,
)

SOLVERS = [
    Procrustes(with_scaling=True),
    ICP(max_correspondence_distance=0.25, max_iterations=7, relative_rmse=0.0),
    MultiScaleICP(max_correspondence_distances=[0.3, 0.1], max_iterations=[5, 9]),
    RANSACProcrustes(max_correspondence_distance=0.05, max_iterations=50, confidence=1.0),
    FPFHEncoder(radius_fractions=(0.2,), backend="torch"),
]
NAMES = {type(s).__name__: type(s) for s in SOLVERS}


@pytest.mark.parametrize("solver", SOLVERS, ids=lambda s: type(s).__name__)
def test_repr_rebuilds_an_equal_solver(solver):
    again = eval(repr(solver), NAMES)  # the repr is the call that builds it
    assert type(again) is type(solver)
    assert again.hyperparameters() == solver.hyperparameters()


def test_hyperparameters_are_the_keyword_arguments_in_order():
    solver = ICP(max_correspondence_distance=1, relative_fitness=0)
    assert solver.hyperparameters() == {
        "max_correspondence_distance": 1.0,
        "max_iterations": 30,
        "relative_fitness": 0.0,
        "relative_rmse": 1e-6,
    }
    assert repr(solver) == (
        "ICP(max_correspondence_distance=1.0, max_iterations=30, relative_fitness=0.0, "
        "relative_rmse=1e-06)"
    )


def test_positional_arguments_are_not_hyperparameters():
    encoder = GeDiEncoder(GeDiNet(width=1 / 16), samples_per_patch=128, seed=3)
    assert encoder.hyperparameters() == {
        "radius_fractions": (0.3, 0.4),
        "samples_per_patch": 128,
        "patch_batch": 128,
        "seed": 3,
    }
    assert repr(encoder).startswith(
        "GeDiEncoder(radius_fractions=(0.3, 0.4), samples_per_patch=128"
    )


def test_a_subclass_must_store_what_it_takes():
    class Forgetful(Hyperparameters):
        def __init__(self, *, size: int = 1) -> None:
            self.width = size

    with pytest.raises(AttributeError):
        repr(Forgetful())


def test_class_and_function_give_the_same_result():
    g = torch.Generator().manual_seed(0)
    src = torch.rand(2, 200, 3, generator=g, dtype=torch.float64)
    dst = src + torch.tensor([0.02, -0.01, 0.03], dtype=torch.float64)
    p = Procrustes(with_scaling=True)(src, dst)
    q = procrustes(src, dst, with_scaling=True)
    assert torch.equal(p.transformation, q.transformation)
    assert torch.equal(p.valid, q.valid)
    a = ICP(max_correspondence_distance=0.1, max_iterations=5)(src, dst)
    b = icp(src, dst, max_correspondence_distance=0.1, max_iterations=5)
    assert torch.equal(a.transformation, b.transformation)
    assert torch.equal(a.num_iterations, b.num_iterations)
    a = MultiScaleICP(max_correspondence_distances=[0.2, 0.05])(src, dst)
    b = multi_scale_icp(src, dst, max_correspondence_distances=[0.2, 0.05])
    assert torch.equal(a.transformation, b.transformation)
    assert torch.equal(a.num_iterations, b.num_iterations)
    solver = RANSACProcrustes(max_correspondence_distance=0.01, max_iterations=20)
    a = solver(src, dst, generator=torch.Generator().manual_seed(1))
    b = ransac_procrustes(
        src,
        dst,
        max_correspondence_distance=0.01,
        max_iterations=20,
        generator=torch.Generator().manual_seed(1),
    )
    assert torch.equal(a.transformation, b.transformation) and torch.equal(a.inliers, b.inliers)


@pytest.mark.parametrize(
    "build",
    [
        lambda: ICP(max_correspondence_distance=0.0),
        lambda: MultiScaleICP(max_correspondence_distances=[0.1, 0.2]),
        lambda: RANSACProcrustes(max_correspondence_distance=0.1, confidence=0.0),
    ],
)
def test_bad_hyperparameters_fail_when_the_solver_is_built(build):
    with pytest.raises(ValueRangeError):
        build()


def test_the_call_takes_data_not_hyperparameters():
    x = torch.rand(1, 20, 3, generator=torch.Generator().manual_seed(0))
    with pytest.raises(TypeError):
        ICP(max_correspondence_distance=0.1)(x, x, max_iterations=3)
