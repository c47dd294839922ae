"""The default progress callback: a bar on a terminal outside CI, log lines otherwise, and the
stage's count and time logged either way."""

from __future__ import annotations

import io
import logging

from railtraj.pipeline import _log_progress


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_log_lines_when_ci_is_set(monkeypatch, caplog):
    monkeypatch.setattr("sys.stderr", _Terminal())
    monkeypatch.setenv("CI", "true")
    report = _log_progress("matched", "tile pairs")
    with caplog.at_level(logging.INFO, logger="railtraj.pipeline"):
        for done in range(1, 4):
            report(done, 3)
    assert "matched 3/3 tile pairs in" in caplog.text
    assert "%|" not in caplog.text


def test_bar_with_count_rate_and_eta_on_a_terminal(monkeypatch, caplog):
    terminal = _Terminal()
    monkeypatch.setattr("sys.stderr", terminal)
    monkeypatch.delenv("CI", raising=False)
    report = _log_progress("detected keypoints in", "tiles")
    with caplog.at_level(logging.INFO, logger="railtraj.pipeline"):
        for done in range(1, 5):
            report(done, 4)
    bar = terminal.getvalue()
    assert "detected keypoints in" in bar and "4/4" in bar and "tiles/s" in bar and "<" in bar
    assert "detected keypoints in 4/4 tiles in" in caplog.text   # the log keeps the stage time
