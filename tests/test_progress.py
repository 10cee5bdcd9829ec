"""``poseflow._progress``: status lines when the output is not a terminal."""

from __future__ import annotations

import logging

from poseflow._progress import progress, status_line


def test_progress_logs_a_plain_line_at_the_end_and_every_interval(caplog, monkeypatch):
    monkeypatch.setattr("sys.stderr.isatty", lambda: False, raising=False)
    with caplog.at_level(logging.INFO, logger="poseflow"):
        assert list(progress(range(5), total=5, desc="steps", interval=0.0)) == [0, 1, 2, 3, 4]
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 5 and lines[-1].startswith("steps: 5/5 (100%)")
    assert all("\x1b" not in line for line in lines)  # no escape codes in a log


def test_status_line_without_progress_has_no_eta():
    assert status_line("x", 0, 10, 3.0) == "x: 0/10 (0%), elapsed 0:03, ETA ?"
