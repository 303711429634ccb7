"""Progress reporting for long host work.

On a terminal: a rich progress bar with rate and ETA on stderr. Elsewhere
(CI logs, pipes): one plain line about every 10 %, and at least every
`PLAIN_EVERY_S` seconds while the work advances, so logs stay short and a long
step still shows it is alive.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["PLAIN_EVERY_S", "Progress", "progress"]

#: Off a terminal, the longest wait between two progress lines while work advances, seconds.
PLAIN_EVERY_S = 5.0


class Progress:
    """A counter with a total that reports itself; use through `progress()`."""

    def __init__(self, description: str, total: float, *, unit: str = "", quiet: bool = False):
        self.description = description
        self.total = float(total)
        self.unit = unit
        self.quiet = quiet
        self.completed = 0.0
        self._start = time.perf_counter()
        self._next_report = 0.1
        self._last_line = self._start
        self._rich = None
        self._task = None

    def advance(self, amount: float = 1.0) -> None:
        self.update(self.completed + amount)

    def update(self, completed: float) -> None:
        self.completed = float(completed)
        if self.quiet:
            return
        if self._rich is not None:
            self._rich.update(self._task, completed=self.completed)
            return
        frac = self.completed / self.total if self.total else 1.0
        now = time.perf_counter()
        if frac >= self._next_report or frac >= 1.0 or now - self._last_line >= PLAIN_EVERY_S:
            while self._next_report <= frac:
                self._next_report += 0.1
            self._last_line = now
            elapsed = now - self._start
            eta = elapsed / frac - elapsed if frac > 0 else float("nan")
            print(
                f"{self.description}: {self.completed:.0f}/{self.total:.0f}{self.unit} "
                f"({100 * frac:.0f}%, {elapsed:.1f}s elapsed, ETA {eta:.1f}s)",
                file=sys.stderr,
                flush=True,
            )

    @property
    def elapsed_s(self) -> float:
        return time.perf_counter() - self._start


@contextmanager
def progress(
    description: str, total: float, *, unit: str = "", quiet: bool = False
) -> Iterator[Progress]:
    """Report progress of ``total`` units of work; yields a `Progress`."""
    p = Progress(description, total, unit=unit, quiet=quiet)
    if quiet or not sys.stderr.isatty():
        yield p
        return
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        TaskProgressColumn,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )
    from rich.progress import Progress as RichProgress

    with RichProgress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TaskProgressColumn(),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        transient=False,
    ) as rp:
        p._rich = rp
        p._task = rp.add_task(description, total=total)
        yield p
