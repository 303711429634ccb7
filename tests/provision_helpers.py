"""Helpers shared by the link, provisioning, device-CLI and fuzz tests (and the benchmark).

* :func:`make_image` writes a valid, signed ``.ecs`` of about the size asked for
  with protocol.image's own writer (random int8 eigenimages: incompressible, or
  small values: compressible).
* :class:`DeviceThread` runs a :class:`~device_runtime.device.Device` on a URL in a
  background thread of this process (the ``mem://`` line needs both ends in one process).
* :class:`DeviceProcess` runs ``eigencast-device`` as a separate process on TCP and
  learns its port from the "listening on" line it logs.
* :func:`reseal` recomputes an image's header CRC, digest and tag after a test edited it.
"""

from __future__ import annotations

import hashlib
import hmac
import itertools
import os
import re
import signal
import struct
import subprocess
import sys
import threading
import time
import zlib
from pathlib import Path

import numpy as np

from device_runtime.device import Device, DeviceConfig
from protocol.image import EigenspaceImage, write_image

REPO = Path(__file__).resolve().parents[1]
KEY = bytes(range(32))
OTHER_KEY = bytes(range(100, 132))
_names = itertools.count()


def mem_name(prefix: str = "t") -> str:
    """A line name no other test uses."""
    return f"{prefix}{os.getpid()}-{next(_names)}"


def make_image(
    path: Path,
    *,
    size_bytes: int = 200_000,
    key: bytes | None = KEY,
    generation: int = 1,
    compressible: bool = False,
    seed: int = 0,
) -> bytes:
    """Write a signed ``.ecs`` of roughly ``size_bytes`` (device image) to ``path``.

    Returns the device image's bytes (what provisioning sends).
    """
    cell = (8, 8)
    image_shape = (64, 64)
    n_cells = (image_shape[0] // cell[0]) * (image_shape[1] // cell[1])
    values = cell[0] * cell[1] * 3
    per_cell = max(1, size_bytes // (n_cells * values))
    k_total = per_cell * n_cells
    rng = np.random.default_rng(seed)
    if compressible:
        eig = rng.integers(-3, 4, size=(k_total, values), dtype=np.int8)
    else:
        eig = rng.integers(-128, 128, size=(k_total, values), dtype=np.int8)
    image = EigenspaceImage(
        image_shape=image_shape,
        cell_shape=cell,
        mean=rng.integers(0, 256, size=(n_cells, values), dtype=np.uint8),
        eigenimages=eig,
        scales=np.full(k_total, 1 / 128, dtype=np.float32),
        n_components=np.full(n_cells, per_cell, dtype=np.int32),
        method="cell",
        image_generation=generation,
        provenance={"test": "provision_helpers", "seed": seed},
    )
    write_image(path, image, key=key, level=3)
    data = Path(path).read_bytes()
    size = struct.unpack_from("<Q", data, 20)[0]
    return data[:size]


def reseal(data: bytes, key: bytes | None = KEY) -> bytes:
    """Fix the header CRC, digest and tag of an edited device image (bytes)."""
    buf = bytearray(data)
    struct.pack_into("<Q", buf, 20, len(buf))
    struct.pack_into("<I", buf, 28, zlib.crc32(bytes(buf[:28])))
    digest = hashlib.sha256(bytes(buf[:-64])).digest()
    buf[-64:-32] = digest
    if key is not None:
        buf[-32:] = hmac.new(key, digest, hashlib.sha256).digest()
    return bytes(buf)


def wait_for_line(device, text: str, timeout_s: float) -> bool:
    """Wait until a log line of ``device`` (DeviceThread or DeviceProcess) contains ``text``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if any(text in line for line in list(device.lines)):
            return True
        threading.Event().wait(0.01)
    return False


class DeviceThread:
    """A Device serving ``url`` on a background thread; ``stop()`` ends it."""

    def __init__(self, url: str, flash_dir: Path, *, baud: int = 115200, **config) -> None:
        config.setdefault("key", KEY)
        self.lines: list[str] = []
        self.config = DeviceConfig(flash_dir=flash_dir, **config)
        self.device = Device(self.config, log=self.lines.append)
        self.stop_event = threading.Event()
        self.ready = threading.Event()
        self.error: BaseException | None = None
        self.transport = None

        def target() -> None:
            try:
                self.device.run(url, baud=baud, stop=self.stop_event, on_ready=self._ready)
            except BaseException as exc:  # surfaced by stop()
                self.error = exc
                self.ready.set()

        self.thread = threading.Thread(target=target, name="device", daemon=True)
        self.thread.start()
        if not self.ready.wait(10):
            raise RuntimeError("device did not start")
        if self.error is not None:
            raise self.error

    def _ready(self, transport) -> None:
        self.transport = transport
        self.ready.set()

    def stop(self) -> None:
        self.stop_event.set()
        self.thread.join(timeout=10)
        if self.thread.is_alive():
            raise RuntimeError("device thread did not stop")
        if self.error is not None:
            raise self.error

    def __enter__(self) -> DeviceThread:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


_LISTEN = re.compile(r"listening on tcp-listen://([^:]+):(\d+)")


class DeviceProcess:
    """``eigencast-device --listen HOST:PORT`` as a child process (stderr captured)."""

    def __init__(self, flash_dir: Path, *args: str, port: int = 0, key_file: Path | None = None):
        cmd = [sys.executable, "-m", "device_runtime.cli", "--listen", f"127.0.0.1:{port}",
               "--flash", str(flash_dir), *args]
        if key_file is not None:
            cmd += ["--key", str(key_file)]
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.proc = subprocess.Popen(
            cmd, cwd=REPO, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, env=env
        )
        self.lines: list[str] = []
        self.port = None
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.lines.append(line.rstrip("\n"))
            found = _LISTEN.search(line)
            if found:
                self.port = int(found.group(2))
                break
        if self.port is None:
            self.proc.wait(timeout=10)
            raise RuntimeError("device process did not start:\n" + "\n".join(self.lines))
        self._reader = threading.Thread(target=self._drain, daemon=True)
        self._reader.start()

    def _drain(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.lines.append(line.rstrip("\n"))

    @property
    def url(self) -> str:
        return f"socket://127.0.0.1:{self.port}"

    def kill(self) -> None:
        """SIGKILL (a power cut for the process)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=10)
        self._reader.join(timeout=5)

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        self._reader.join(timeout=5)
        return self.proc.returncode
