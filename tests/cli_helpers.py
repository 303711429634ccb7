"""Running ``eigencast`` as a user does: a subprocess of ``python -m host.cli``, and a render
caught halfway (the resume tests)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

__all__ = ["CLI", "kill_render_halfway", "png_count", "render_tooth", "run_cli", "snapshot",
           "wait_for_views"]

CLI = [sys.executable, "-m", "host.cli"]


def run_cli(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    """``eigencast ARGS`` in a subprocess, its output captured as text."""
    return subprocess.run([*CLI, *args], capture_output=True, text=True, check=check)


def render_tooth(db: Path, views: str, size: int, samples: int) -> Path:
    """``eigencast render builtin:tooth`` into ``db`` (views, image size, samples per ray)."""
    run_cli("render", "builtin:tooth", "-o", str(db), "--views", views, "--size", str(size),
            "--samples", str(samples))
    return db


def png_count(db: Path) -> int:
    """How many view images the database ``db`` holds so far."""
    return sum(1 for _ in (db / "images").glob("view_*.png"))


def snapshot(db: Path) -> dict[str, bytes]:
    """Every file of ``db`` by its path in it (to compare two databases byte for byte)."""
    return {p.relative_to(db).as_posix(): p.read_bytes() for p in db.rglob("*") if p.is_file()}


def wait_for_views(proc: subprocess.Popen, db: Path, at_least: int) -> None:
    """Wait until the render ``proc`` has written ``at_least`` views into ``db`` (it must
    still be running; two minutes at most)."""
    deadline = time.monotonic() + 120
    while not (db / "images").exists() or png_count(db) < at_least:
        assert proc.poll() is None, "render finished before it could be interrupted"
        assert time.monotonic() < deadline, "render made no progress"
        time.sleep(0.005)  # polling a condition, not waiting out a race


def kill_render_halfway(args: list[str], db: Path, at_least: int) -> int:
    """Start ``eigencast ARGS`` (a render into ``db``), kill it once it has written
    ``at_least`` views (stopped first, so that none is written after the count); the views
    written."""
    proc = subprocess.Popen([*CLI, *args], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wait_for_views(proc, db, at_least)
    proc.send_signal(signal.SIGSTOP)
    written = png_count(db)
    proc.kill()
    proc.wait()
    return written
