"""Progress bars: live on a terminal, sparse in a log file."""

from __future__ import annotations

import io
import sys

from biopsynav.progress import LIVE_INTERVAL_S, LOG_INTERVAL_S, progress_bar


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_log_file_gets_a_sparse_bar_and_a_terminal_a_live_one(monkeypatch):
    monkeypatch.setattr(sys, "stderr", io.StringIO())
    with progress_bar(total=3) as bar:
        assert bar.mininterval == LOG_INTERVAL_S
        bar.update(3)
    written = sys.stderr.getvalue()
    assert "3/3" in written and written.count("\r") <= 3  # opened, closed: no stream of updates
    monkeypatch.setattr(sys, "stderr", Terminal())
    with progress_bar(total=3) as bar:
        assert bar.mininterval == LIVE_INTERVAL_S
