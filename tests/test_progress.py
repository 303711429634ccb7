"""Progress off a terminal: a line every 10 %, and at least every few seconds while the work
advances (a long step in a log must show it is alive)."""

from __future__ import annotations

import host.progress as progress_module
from host.progress import PLAIN_EVERY_S, progress


def test_plain_progress_reports_every_tenth_and_every_few_seconds(monkeypatch, capsys):
    now = [100.0]
    monkeypatch.setattr(progress_module.time, "perf_counter", lambda: now[0])
    with progress("render", 1000, unit=" views") as bar:  # stderr is not a terminal here
        for _ in range(5):  # 0.5 %: no tenth reached, but time passes
            now[0] += PLAIN_EVERY_S / 2
            bar.advance()
        slow = capsys.readouterr().err.splitlines()
        for _ in range(200):  # 20 % quickly: two tenths
            bar.advance()
        fast = capsys.readouterr().err.splitlines()
    assert len(slow) == 2 and "render: 2/1000 views" in slow[0]  # every PLAIN_EVERY_S
    assert len(fast) == 2 and "(10%" in fast[0] and "(20%" in fast[1]
