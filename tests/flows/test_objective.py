"""CFMObjective, FlowBatch and StepRandom."""

from __future__ import annotations

import pytest
import torch

from poseflow.errors import ShapeError, ValueRangeError
from poseflow.flows.objective import CFMObjective, FlowBatch, StepRandom


class Recorder(torch.nn.Module):
    """Returns a fixed velocity and remembers what it was called with."""

    def __init__(self, velocity: torch.Tensor) -> None:
        super().__init__()
        self.velocity = velocity
        self.calls: list[dict] = []

    def forward(self, **kwargs):
        self.calls.append(kwargs)
        return self.velocity


def _rng(seed: int = 0, **kw) -> StepRandom:
    return StepRandom(torch.Generator().manual_seed(seed), **kw)


def test_loss_is_the_cfm_loss_of_the_drawn_path() -> None:
    x_1 = torch.randn(4, 6, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    model = Recorder(torch.zeros(4, 6, 3, dtype=torch.float64))
    loss = CFMObjective()(model, x_1, _rng(2))
    call = model.calls[0]
    # reproduce the draws: noise first, then times, from the same generator
    g = torch.Generator().manual_seed(2)
    x_0 = torch.randn(4, 6, 3, generator=g, dtype=torch.float64)
    t = torch.rand(4, generator=g, dtype=torch.float64)
    assert torch.equal(call["t"], t)
    assert torch.allclose(call["x"], x_0 + t[:, None, None] * (x_1 - x_0))
    assert torch.allclose(loss, ((x_1 - x_0) ** 2).mean())


def test_masks_anchor_pinning_and_noise_keyword() -> None:
    x_1 = torch.randn(2, 5, 3, generator=torch.Generator().manual_seed(3))
    frozen = torch.tensor([[True, True, False, False, False]] * 2)
    mask = torch.tensor([[True] * 5, [True, True, True, False, False]])
    batch = {"x_1": x_1, "frozen_mask": frozen, "mask": mask, "condition": torch.ones(2, 5, 2)}
    model = Recorder(torch.zeros(2, 5, 3))
    CFMObjective(pin_frozen=True, noise_kwarg="x_noise")(model, batch, _rng())
    call = model.calls[0]
    assert torch.equal(call["x"][frozen], x_1[frozen])  # anchors sit at their data
    assert set(call) == {"x", "t", "condition", "mask", "x_noise"}
    assert call["mask"] is mask
    assert not torch.equal(call["x_noise"][frozen], x_1[frozen])
    # with pinned anchors and include_frozen, a zero velocity is right on the anchors
    pinned = CFMObjective(pin_frozen=True, include_frozen=True)
    exclude = CFMObjective(pin_frozen=True)
    l_in = pinned(Recorder(torch.zeros(2, 5, 3)), batch, _rng())
    l_out = exclude(Recorder(torch.zeros(2, 5, 3)), batch, _rng())
    n_in, n_out = int(mask.sum()), int((mask & ~frozen).sum())
    assert torch.allclose(l_in * n_in, l_out * n_out)


def test_model_output_is_compared_in_full_precision() -> None:
    x_1 = torch.randn(2, 4, 3)
    loss = CFMObjective()(Recorder(torch.zeros(2, 4, 3, dtype=torch.bfloat16)), x_1, _rng())
    assert loss.dtype == torch.float32


def test_step_random_shards_the_global_draw() -> None:
    x = torch.zeros(3, 4, 3)
    full = _rng(9)
    noise, times = full.randn_like(torch.zeros(6, 4, 3)), full.time(6, "uniform")
    for rank in range(2):
        part = _rng(9, rank=rank, world_size=2)
        assert torch.equal(part.randn_like(x), noise[rank::2])
        assert torch.equal(part.time(3, "uniform"), times[rank::2])


def test_flow_batch_forms() -> None:
    x = torch.zeros(2, 3, 3)
    fb = FlowBatch(x_1=x)
    assert FlowBatch.from_any(fb) is fb
    assert FlowBatch.from_any(x).x_1 is x and FlowBatch.from_any(x).cond == {}
    with pytest.raises(ShapeError):
        FlowBatch.from_any({"points": x})
    with pytest.raises(ShapeError):
        FlowBatch.from_any([x])


def test_bad_input_raises() -> None:
    with pytest.raises(ValueRangeError):
        CFMObjective(time_sampler="cosine")
    with pytest.raises(ShapeError):
        CFMObjective()(Recorder(torch.zeros(2, 3)), torch.zeros(2, 3), _rng())
    with pytest.raises(ShapeError):
        CFMObjective()(lambda **kw: None, torch.zeros(2, 3, 3), _rng())


class Spin(torch.nn.Module):
    """A teacher whose velocity depends on the state: rotation about z, plus the condition."""

    def forward(self, *, x, t, condition=None, **kwargs):
        v = torch.stack([-x[..., 1], x[..., 0], torch.zeros_like(x[..., 2])], -1)
        return v if condition is None else v + condition


def test_distillation_regresses_the_teachers_endpoint_from_the_same_noise() -> None:
    from poseflow.flows.objective import DistillationObjective
    from poseflow.flows.samplers import get_sampler

    x_1 = torch.randn(3, 5, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    cond = torch.full((3, 5, 3), 0.25, dtype=torch.float64)
    batch = {"x_1": x_1, "condition": cond}
    sampler = get_sampler("midpoint", steps=1)
    student = Recorder(torch.zeros(3, 5, 3, dtype=torch.float64))
    loss = DistillationObjective(Spin(), sampler, noise_kwarg="x_noise")(student, batch, _rng(5))
    x_0 = torch.randn(3, 5, 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    call = student.calls[0]
    assert torch.equal(call["x"], x_0) and bool((call["t"] == 0).all())
    assert torch.equal(call["x_noise"], x_0) and call["condition"] is cond
    end = sampler.sample(Spin(), x_0, condition=cond)  # the teacher's own sample
    assert torch.allclose(loss, ((end - x_0) ** 2).mean())
    # a student that already takes the teacher's step in one Euler step has zero loss
    exact = Recorder(end - x_0)
    zero = DistillationObjective(Spin(), sampler)(exact, batch, _rng(5))
    assert float(zero) < 1e-24


def test_distillation_pins_anchors_and_ignores_them() -> None:
    from poseflow.flows.objective import DistillationObjective
    from poseflow.flows.samplers import get_sampler

    x_1 = torch.randn(2, 5, 3, generator=torch.Generator().manual_seed(6))
    frozen = torch.tensor([[True, True, False, False, False]] * 2)
    mask = torch.tensor([[True] * 5, [True, True, True, True, False]])
    batch = {"x_1": x_1, "frozen_mask": frozen, "mask": mask}
    teacher = Recorder(torch.ones(2, 5, 3))
    wrong = torch.zeros(2, 5, 3)
    wrong[1, 4] = 7.0  # at the padded point only: must not count
    wrong[:, :2] = 5.0  # at the anchors only: must not count
    student = Recorder(wrong)
    objective = DistillationObjective(teacher, get_sampler("heun", steps=2), pin_frozen=True)
    loss = objective(student, batch, _rng())
    assert len(teacher.calls) == 4  # Heun: two calls per step
    assert torch.equal(teacher.calls[0]["x"][frozen], x_1[frozen])
    assert torch.equal(student.calls[0]["x"][frozen], x_1[frozen])
    # the teacher moves every free point by 1 per unit time (its anchors stay): the target
    # is 1 on the valid free points; the loss is their mean squared error against 0
    assert torch.allclose(loss, torch.tensor(1.0))
