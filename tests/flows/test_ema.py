"""EMA of weights: closed form, warm-up, tied weights, integer buffers."""

from __future__ import annotations

import pytest
import torch

from poseflow.errors import ValueRangeError
from poseflow.flows.ema import EMA


def test_closed_form_over_several_updates() -> None:
    net = torch.nn.Linear(3, 2).double()
    ema = EMA(net, decay=0.9, warmup=False)
    expected = net.weight.detach().clone()
    for k in range(5):
        with torch.no_grad():
            net.weight.add_(k + 1.0)
        ema.update(net)
        expected = 0.9 * expected + 0.1 * net.weight.detach()
    assert torch.allclose(ema.module.weight, expected)
    assert ema.num_updates == 5
    assert not ema.module.weight.requires_grad and not ema.module.training


def test_warmup_decay() -> None:
    ema = EMA(torch.nn.Linear(1, 1), decay=0.999)
    assert ema.decay_at(0) == pytest.approx(0.1)
    assert ema.decay_at(90) == pytest.approx(91 / 100)
    assert ema.decay_at(10**6) == 0.999


def test_tied_weights_are_averaged_once_and_int_buffers_copied() -> None:
    class Tied(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.a = torch.nn.Linear(2, 2, bias=False)
            self.b = torch.nn.Linear(2, 2, bias=False)
            self.b.weight = self.a.weight
            self.register_buffer("count", torch.zeros((), dtype=torch.long))

    net = Tied()
    ema = EMA(net, decay=0.5, warmup=False)
    start = net.a.weight.detach().clone()
    with torch.no_grad():
        net.a.weight.add_(2.0)
        net.count += 3
    ema.update(net)
    assert torch.allclose(ema.module.a.weight, start + 1.0)
    assert ema.module.b.weight is ema.module.a.weight
    assert int(ema.module.count) == 3


def test_state_round_trip_and_bad_decay() -> None:
    net = torch.nn.Linear(2, 2)
    ema = EMA(net, decay=0.9)
    other = EMA(torch.nn.Linear(2, 2), decay=0.9)
    other.load_state_dict(ema.state_dict(), num_updates=7)
    assert torch.equal(other.module.weight, ema.module.weight) and other.num_updates == 7
    with pytest.raises(ValueRangeError):
        EMA(net, decay=1.2)
