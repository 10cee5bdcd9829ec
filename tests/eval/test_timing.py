from __future__ import annotations

import json

import pytest
from PIL import Image

from poseflow.errors import ValueRangeError
from poseflow.eval.timing import STAGES, StageTimer, active_timer, stage, timed


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def _timed(clock: FakeClock) -> StageTimer:
    timer = StageTimer(clock=clock, synchronize=False)
    for _ in range(2):
        with timer.image():
            clock.now += 0.001  # uncovered: other
            with timer.stage("segmentation"):
                clock.now += 0.080
            with timer.stage("integration"):
                clock.now += 0.010
                with timer.stage("flow_net"):
                    clock.now += 0.005
                clock.now += 0.010
            with timer.stage("ransac"):
                clock.now += 0.004
    return timer


def test_nested_stages_are_exclusive():
    timer = _timed(FakeClock())
    b = timer.breakdown()
    assert b["num_images"] == 2
    assert b["stages_ms"]["integration"] == pytest.approx(20.0)
    assert b["stages_ms"]["flow_net"] == pytest.approx(5.0)
    assert b["stages_ms"]["ransac"] == pytest.approx(4.0)
    assert b["stages_ms"]["other"] == pytest.approx(1.0)
    # Segmentation is reported but not in the total.
    assert b["excluded_ms"] == {"segmentation": pytest.approx(80.0)}
    assert b["total_ms"] == pytest.approx(30.0)
    assert sum(b["percent"].values()) == pytest.approx(100.0)
    assert list(b["stages_ms"]) == [s for s in STAGES if s in b["stages_ms"]]


def test_decorator_and_counts():
    clock = FakeClock()
    timer = StageTimer(clock=clock, synchronize=False)

    @timer.wrap("icp")
    def step(x: int) -> int:
        clock.now += 0.002
        return x * 2

    assert step.__name__ == "step"
    assert [step(i) for i in range(3)] == [0, 2, 4]
    assert timer.counts["icp"] == 3
    assert timer.breakdown()["stages_ms"]["icp"] == pytest.approx(6.0)


def test_exception_closes_the_stage():
    clock = FakeClock()
    timer = StageTimer(clock=clock, synchronize=False)
    with pytest.raises(RuntimeError):
        with timer.stage("reducer"):
            clock.now += 0.003
            raise RuntimeError("boom")
    with timer.stage("fusion"):
        clock.now += 0.001
    b = timer.breakdown()["stages_ms"]
    assert b["reducer"] == pytest.approx(3.0) and b["fusion"] == pytest.approx(1.0)


def test_json_and_plots(tmp_path):
    pytest.importorskip("matplotlib")
    timer = _timed(FakeClock())
    data = timer.to_json(tmp_path / "t.json")
    assert json.loads((tmp_path / "t.json").read_text()) == data
    for kind in ("pie", "bar"):
        out = tmp_path / f"t_{kind}.png"
        timer.plot(out, kind=kind)
        with Image.open(out) as im:
            assert im.size == (700, 450)
    with pytest.raises(ValueRangeError):
        timer.plot(tmp_path / "x.png", kind="donut")
    with pytest.raises(ValueRangeError):
        StageTimer().plot(tmp_path / "y.png")


def test_bar_chart_names_every_stage_sorted_with_ms_and_share(tmp_path):
    pytest.importorskip("matplotlib")
    timer = _timed(FakeClock())
    fig = timer.figure(title="FunFlow6D")
    ax = fig.axes[0]
    names = [t.get_text() for t in ax.get_yticklabels()]
    # longest first (integration 20 ms, flow_net 5, ransac 4, other 1), the excluded one last
    assert names == [
        "integration",
        "flow net",
        "ransac",
        "other (not in any stage)",
        "segmentation (not in total)",
    ]
    texts = [t.get_text().strip() for t in ax.texts]
    assert texts == ["20.0 ms  66.7%", "5.0 ms  16.7%", "4.0 ms  13.3%", "1.0 ms  3.3%", "80.0 ms"]
    widths = [bar.get_width() for bar in ax.patches]
    assert widths == pytest.approx([20.0, 5.0, 4.0, 1.0, 80.0])
    assert ax.get_title() == "FunFlow6D: 30.0 ms per image (2 images)"
    pie = timer.figure(kind="pie").axes[0]
    labels = [t.get_text() for t in pie.get_legend().get_texts()]
    assert labels[0] == "integration: 20.0 ms (66.7%)" and len(labels) == 4
    timer.plot(tmp_path / "t.png", title="FunFlow6D")
    assert (tmp_path / "t.png").stat().st_size > 0


def test_reset_and_real_clock():
    timer = StageTimer()
    with timer.image(), timer.stage("ransac"):
        sum(range(1000))
    assert timer.breakdown()["total_ms"] >= 0.0
    timer.reset()
    assert timer.breakdown()["stages_ms"] == {} and timer.num_images == 0
    with pytest.raises(ValueRangeError):
        with timer.stage(""):
            pass


def test_stages_reach_the_active_timer_only():
    clock = FakeClock()
    timer = StageTimer(clock=clock, synchronize=False)
    net = timed("flow_net", lambda x: x + 1)
    with stage("ransac"):  # no timer active: nothing recorded anywhere
        clock.now += 0.001
    assert net(1) == 2 and active_timer() is None
    with timer.active() as active:
        assert active is timer and active_timer() is timer
        with stage("ransac"):
            clock.now += 0.002
        assert net(2) == 3
    assert active_timer() is None
    assert net(3) == 4 and timer.counts == {"ransac": 1, "flow_net": 1}
    assert timer.breakdown()["stages_ms"]["ransac"] == pytest.approx(2.0)


def test_active_timers_nest_and_restore():
    outer, inner = StageTimer(synchronize=False), StageTimer(synchronize=False)
    with outer.active():
        with inner.active():
            with stage("icp"):
                pass
        with stage("fusion"):
            pass
    assert inner.counts == {"icp": 1} and outer.counts == {"fusion": 1}
    with pytest.raises(RuntimeError), outer.active():
        raise RuntimeError("boom")
    assert active_timer() is None


def test_timed_keeps_the_name_but_not_a_modules_state():
    import torch

    layer = torch.nn.Linear(2, 2)
    wrapped = timed("flow_net", layer)
    assert not hasattr(wrapped, "_parameters")
    x = torch.ones(1, 2)
    assert torch.equal(wrapped(x), layer(x))
