"""``poseflow._progress``: status lines when the output is not a terminal."""

from __future__ import annotations

import logging

import pytest

from poseflow._progress import ProgressBar, progress, status_line


@pytest.fixture
def log_file(caplog, monkeypatch):
    """stderr is not a terminal; the ``poseflow`` lines are captured."""
    monkeypatch.setattr("sys.stderr.isatty", lambda: False, raising=False)
    with caplog.at_level(logging.INFO, logger="poseflow"):
        yield caplog


def _lines(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records]


def test_progress_logs_a_plain_line_at_the_end_and_every_interval(log_file):
    assert list(progress(range(5), total=5, desc="steps", interval=0.0)) == [0, 1, 2, 3, 4]
    lines = _lines(log_file)
    assert len(lines) == 5 and lines[-1].startswith("steps: 5/5 (100%)")
    assert all("\x1b" not in line for line in lines)  # no escape codes in a log


def test_progress_bar_line_shows_the_postfix_and_counts_from_initial(log_file):
    with ProgressBar(2000, desc="cfm", initial=100, interval=0.0) as bar:
        bar.update(20)
        bar.set_postfix(loss="0.4123", samples_s="512")
    lines = _lines(log_file)
    assert len(lines) == 2  # the update, then the close with the new postfix
    assert lines[0].startswith("cfm: 120/2000 (6%), elapsed 0:00, ETA ")
    assert lines[1].endswith(", loss 0.4123, samples_s 512")
    assert all("\x1b" not in line for line in lines)


def test_progress_bar_logs_at_most_once_per_interval_plus_the_last(log_file):
    with ProgressBar(100, desc="steps", interval=3600.0) as bar:
        for _ in range(100):
            bar.update()
    assert _lines(log_file) == [status_line("steps", 100, 100, 0.0)]  # well under a second


def test_progress_bar_logs_where_a_loop_stopped_early(log_file):
    for step in progress(range(10), total=10, desc="steps", interval=3600.0):
        if step == 3:
            break
    assert [line.split(",")[0] for line in _lines(log_file)] == ["steps: 3/10 (30%)"]


def test_disabled_progress_bar_logs_nothing(log_file):
    with ProgressBar(3, desc="steps", enabled=False, interval=0.0) as bar:
        bar.update(3)
        bar.set_postfix(loss="1.0")
    assert bar.done == 3 and _lines(log_file) == []


def test_status_line_without_progress_has_no_eta():
    assert status_line("x", 0, 10, 3.0) == "x: 0/10 (0%), elapsed 0:03, ETA ?"


def test_status_line_eta_uses_the_steps_taken_since_initial():
    assert status_line("x", 60, 100, 10.0, initial=50) == "x: 60/100 (60%), elapsed 0:10, ETA 0:40"
