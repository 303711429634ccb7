"""Helpers of the runtime, display, serve, end-to-end and window tests.

* :func:`tiny_model` renders the built-in tooth at 40 px from 16 x 5 views and fits an
  adaptive, standalone, signed model (without depth, or with it) once per test session (a
  few seconds), cached under pytest's base temporary folder.
* :class:`RuntimeThread` runs a :class:`~device_runtime.runtime.RuntimeDevice` in this
  process: its link on one thread, its display loop (headless) on another.
* :func:`read_frames` reads a headless device's ``frames.csv``; :func:`check_frames`
  compares every written frame with ``HostModel.view`` (what ``eigencast view`` writes).
"""

from __future__ import annotations

import csv
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
from PIL import Image
from provision_helpers import KEY

from device_runtime.device import DeviceConfig
from device_runtime.display import HeadlessPresenter
from device_runtime.runtime import RuntimeDevice
from host.cli import main as eigencast

TINY_SIZE = 40
TINY_VIEWS = "grid:16x5"


def tiny_model(tmp_path_factory, *, name: str = "tiny", depth: bool = False) -> Path:
    """A signed (``KEY``), standalone adaptive model of the tooth without depth (its device
    frames are blends, `check_frames`); built once per session (per ``name``). ``depth``:
    with depth (the device's own frames are warps; use another ``name``)."""
    root = tmp_path_factory.getbasetemp() / f"runtime-{name}"
    model = root / "tooth.ecs"
    if model.exists():
        return model
    root.mkdir(parents=True, exist_ok=True)
    db = root / "tooth.cdb"
    key_file = root / "device.key"
    from protocol.keys import write_key

    write_key(key_file, KEY, force=True)
    assert eigencast(["render", "builtin:tooth", "-o", str(db), "--views", TINY_VIEWS,
                      "--size", str(TINY_SIZE), "--samples", "80",
                      *(() if depth else ("--no-depth",))]) == 0
    tmp = root / "tooth.tmp.ecs"
    assert eigencast(["fit", str(db), "-o", str(tmp), "--cell", "12", "--threshold", "0.99",
                      "--standalone", "--key", str(key_file)]) == 0
    tmp.replace(model)
    return model


#: The looks of `tiny_looks_model`: (render options, name); the first two differ only in
#: lighting (same depth), the third in its transfer function (its own depth).
TINY_LOOKS = ((("--lighting", "headlight"), "plain"), (("--lighting", "cinematic"), "lamp"),
              (("--tf", "generic"), "generic"))


def tiny_looks_model(tmp_path_factory) -> Path:
    """A signed (``KEY``), standalone adaptive model with depth and three looks of the tooth
    (`TINY_LOOKS`, 32 px, 16 x 5 views), fitted by ``eigencast fit A B C``; once per
    session. Its databases lie beside it (``look0.cdb`` ...)."""
    root = tmp_path_factory.getbasetemp() / "runtime-looks"
    model = root / "looks.ecs"
    if model.exists():
        return model
    root.mkdir(parents=True, exist_ok=True)
    key_path = root / "device.key"
    from protocol.keys import write_key

    write_key(key_path, KEY, force=True)
    dbs = []
    for i, (options, _) in enumerate(TINY_LOOKS):
        db = root / f"look{i}.cdb"
        assert eigencast(["render", "builtin:tooth", "-o", str(db), "--views", TINY_VIEWS,
                          "--size", "32", "--samples", "80", *options]) == 0
        dbs.append(str(db))
    tmp = root / "looks.tmp.ecs"
    assert eigencast(["fit", *dbs, "-o", str(tmp), "--cell", "12", "--threshold", "0.99",
                      "--look-names", ",".join(name for _, name in TINY_LOOKS),
                      "--key", str(key_path)]) == 0
    tmp.replace(model)
    return model


def key_file(model: Path) -> Path:
    """The key file written beside a :func:`tiny_model`."""
    return model.parent / "device.key"


def read_frames(folder: Path) -> list[dict]:
    """Rows of ``frames.csv`` with a view (the image's first, mean frame has none)."""
    path = Path(folder) / "frames.csv"
    if not path.exists():
        return []
    rows = []
    with open(path, newline="") as handle:
        for row in csv.DictReader(handle):
            if row.get("phi_deg"):
                rows.append(row)
    return rows


def check_frames(model, folder: Path, rows: list[dict] | None = None) -> int:
    """Assert every written frame equals ``model.view`` at its view (the interpolated scores
    ``ServeOptions(scores="interpolate")`` sends); return how many."""
    rows = read_frames(folder) if rows is None else rows
    for row in rows:
        got = np.asarray(Image.open(Path(folder) / row["file"]))
        want = model.view(float(row["phi_deg"]), float(row["theta_deg"]))
        assert got.shape == want.shape
        diff = np.abs(got.astype(int) - want)
        assert diff.max() == 0, (
            f"{row['file']} (phi {row['phi_deg']}, theta {row['theta_deg']}) differs from "
            f"eigencast view by up to {diff.max()} in {np.count_nonzero(diff)} values")
    return len(rows)


def wait_until(predicate, timeout_s: float, what: str = "condition") -> None:
    """Poll ``predicate`` until it is true (fail after ``timeout_s``)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        threading.Event().wait(0.01)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


def steady_requests(worker, views, interval_s: float = 60.0) -> None:
    """Make a `WarpWorker`'s recent requests ``views`` at an even pace, the next one not due
    for ``interval_s``: steady motion whose pace is set, not raced with."""
    now = time.monotonic()
    with worker._cond:
        worker._history = [(now - 0.1 * (len(views) - i), *v) for i, v in enumerate(views)]
        worker._last_request_t, worker.interval_s = now, interval_s
        worker._cond.notify_all()


class FakeClock:
    """A clock that stands still at ``now`` until a test moves it (``clock.now += dt``)."""

    def __init__(self, now: float = 0.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


class RuntimeThread:
    """A RuntimeDevice serving ``url`` (if any) with its display loop on a thread."""

    def __init__(self, flash_dir: Path, url: str | None = None, *, frames: Path | None = None,
                 display: bool = True, presenter=None, baud: int = 115200, **kwargs) -> None:
        config = kwargs.pop("config", None) or DeviceConfig(flash_dir=flash_dir, key=KEY)
        self.lines: list[str] = []
        self.presenter = presenter or HeadlessPresenter(frames)
        self.device = RuntimeDevice(config, presenter=self.presenter, log=self.lines.append,
                                    **kwargs)
        self.stop_event = threading.Event()
        self.errors: list[BaseException] = []
        self.ready = threading.Event()
        self.threads = []
        self.has_link = url is not None
        if url is not None:
            self.threads.append(threading.Thread(target=self._run_link, args=(url, baud),
                                                 daemon=True))
        if display:
            self.threads.append(threading.Thread(target=self._run_display, daemon=True))
        for thread in self.threads:
            thread.start()
        if url is not None and not self.ready.wait(10):
            raise RuntimeError("device link did not start")

    def _run_link(self, url: str, baud: int) -> None:
        try:
            self.device.run(url, baud=baud, stop=self.stop_event,
                            on_ready=lambda t: self.ready.set())
        except BaseException as exc:
            self.errors.append(exc)
            self.ready.set()

    def _run_display(self) -> None:
        try:
            self.device.run_display(self.stop_event)
        except BaseException as exc:
            self.errors.append(exc)

    def stop(self) -> None:
        self.stop_event.set()
        for thread in self.threads:
            thread.join(timeout=10)
        self.device.close_display()
        if not self.has_link:
            self.device.close()
        if self.errors:
            raise self.errors[0]

    def __enter__(self) -> RuntimeThread:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def provisioned_device(tmp_path: Path, name: str, image_path, frames: list, *,
                       host_query: str = "", **kwargs) -> RuntimeThread:
    """A predicting `RuntimeThread` on the mem:// line ``name`` (end b), provisioned with
    ``image_path`` (signed with ``KEY``) from end a, ``host_query`` appended to that end's URL
    (``"&pace=0"``); it appends each frame it shows and its info to ``frames``. ``kwargs``
    go to `RuntimeThread`."""
    from host.link.options import ProvisionOptions, ProvisionParts
    from host.link.provisioning import provision

    device = RuntimeThread(tmp_path / "flash", f"mem://{name}?end=b", predict=True,
                           on_frame=lambda f, info: frames.append((f.copy(), dict(info or {}))),
                           **kwargs)
    provision(image_path, f"mem://{name}?end=a{host_query}",
              ProvisionOptions(key=KEY, show_progress=False),
              ProvisionParts(log=lambda line: None))
    return device


def serve_cli(*args: str) -> subprocess.CompletedProcess:
    """Run ``eigencast serve ARGS`` in a subprocess from the repository root (60 s at most)."""
    return subprocess.run([sys.executable, "-m", "host.cli", "serve", *args],
                          cwd=Path(__file__).resolve().parents[1], capture_output=True,
                          text=True, timeout=60)
