"""A real window under Xvfb: input injected with xdotool, screenshots checked against
``eigencast view``, and the X server's own framebuffer checked too.

Needs Debian's ``xvfb`` and ``xdotool`` (``make xvfb`` installs them, as root); skipped with
that reason when they are absent.
"""

from __future__ import annotations

import os
import shutil
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from provision_helpers import KEY, REPO, DeviceProcess
from runtime_helpers import key_file, tiny_model, wait_until

from host.fit.model import HostModel
from host.link.options import ProvisionOptions, ProvisionParts, ServeOptions, ServeParts
from host.link.provisioning import provision
from host.link.serving import serve

pytestmark = pytest.mark.skipif(
    shutil.which("Xvfb") is None or shutil.which("xdotool") is None,
    reason="Xvfb and xdotool are not installed (make xvfb installs them; needs root)",
)


def _free_display() -> int:
    for n in range(91, 200):
        if not Path(f"/tmp/.X{n}-lock").exists() and not Path(f"/tmp/.X11-unix/X{n}").exists():
            return n
    pytest.skip("no free X display number in :91..:199")


@pytest.fixture
def xvfb(tmp_path):
    n = _free_display()
    fbdir = tmp_path / "fb"
    fbdir.mkdir()
    proc = subprocess.Popen(["Xvfb", f":{n}", "-screen", "0", "320x240x24", "-fbdir",
                             str(fbdir), "-nolisten", "tcp"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        wait_until(lambda: Path(f"/tmp/.X11-unix/X{n}").exists() or proc.poll() is not None,
                   20, "Xvfb to start")
        if proc.poll() is not None:
            pytest.skip(f"Xvfb did not start: {proc.stderr.read().decode()[-200:]}")
        yield f":{n}", fbdir / "Xvfb_screen0"
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def _xdotool(display, *args, check: bool = True) -> str:
    """Run xdotool; a command that fails fails the test (a window id gone stale must not
    send the input nowhere in silence)."""
    run = subprocess.run(["xdotool", *args], capture_output=True, text=True, timeout=20,
                         env=dict(os.environ, DISPLAY=display))
    assert run.returncode == 0 or not check, f"xdotool {' '.join(args)}: {run.stderr.strip()}"
    return run.stdout.strip()


def _image_window(display: str, title: str, shape: tuple[int, int]) -> str:
    """Id of the mapped window whose name starts with ``title`` and whose size is the
    image's ``(height, width)``, waiting for it.

    The device opens its window once, at the size of the image it booted with; the size is
    checked all the same (input sent to a window id that is gone would be lost in silence).
    (``xdotool search --name`` misses windows that no window manager has managed; a search by
    class finds every window, and its name and size are then checked.)
    """
    height, width = shape
    found: list[str] = []

    def look() -> bool:
        for wid in _xdotool(display, "search", "--onlyvisible", "--class", ".",
                            check=False).split():
            geometry = _xdotool(display, "getwindowgeometry", "--shell", wid,
                                check=False).split()
            if (f"WIDTH={width}" in geometry and f"HEIGHT={height}" in geometry
                    and _xdotool(display, "getwindowname", wid, check=False).startswith(title)):
                found.append(wid)
                return True
        return False

    wait_until(look, 30, f"a {width}x{height} window named {title!r}")
    return found[0]


def read_xwd(path: Path) -> np.ndarray:
    """The X screen as uint8 (height, width, 3) from Xvfb's -fbdir XWD file (24/32 bpp)."""
    data = path.read_bytes()
    fields = struct.unpack(">25I", data[:100])
    header_size, width, height = fields[0], fields[4], fields[5]
    byte_order, bits_per_pixel, bytes_per_line, ncolors = (fields[7], fields[11], fields[12],
                                                           fields[19])
    assert bits_per_pixel == 32, bits_per_pixel
    start = header_size + 12 * ncolors
    raw = np.frombuffer(data, np.uint8, count=height * bytes_per_line, offset=start)
    pixels = raw.reshape(height, bytes_per_line)[:, : 4 * width].reshape(height, width, 4)
    return pixels[..., [2, 1, 0]] if byte_order == 0 else pixels[..., [1, 2, 3]]


def _drag_right(display: str, wid: str) -> None:
    """Drag 20 px to the right with the left button (the device turns phi by -10)."""
    # --sync: each xdotool is a client of its own, so without it the X server may take the
    # button press before the pointer reached the start (under load: a shorter drag)
    _xdotool(display, "mousemove", "--sync", "--window", wid, "10", "20")
    _xdotool(display, "mousedown", "1")
    for x in (15, 20, 25, 30):
        _xdotool(display, "mousemove", "--sync", "--window", wid, str(x), "20")
        time.sleep(0.05)  # pointer motion spread over time, as a hand drags
    _xdotool(display, "mouseup", "1")


def test_window_drag_keys_and_screenshots_show_the_reconstruction(tmp_path, tmp_path_factory,
                                                                    xvfb):
    display, screen = xvfb
    model_path = tiny_model(tmp_path_factory)
    model = HostModel.load(model_path)
    device = DeviceProcess(tmp_path / "flash", "--headless", key_file=key_file(model_path))
    provision(model_path, device.url, ProvisionOptions(key=bytes(range(32)), show_progress=False),
              ProvisionParts(log=lambda line: None))
    device.stop()
    shots = tmp_path / "shots"
    env = dict(os.environ, DISPLAY=display, SDL_VIDEODRIVER="x11",
               SDL_VIDEO_WINDOW_POS="0,0", PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        [sys.executable, "-m", "device_runtime.cli", "--standalone", "--display", "--flash",
         str(tmp_path / "flash"), "--key", str(key_file(model_path)), "--view", "30,15",
         "--screenshots", str(shots)],
        cwd=REPO, env=env, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
    try:
        # input is only meaningful once the first frame is up (under load the model may
        # still be loading when a window appears, and a screenshot of nothing is no file);
        # the window that shows it is the one to send input to
        first = model.view(30.0, 15.0)
        fh, fw = first.shape[:2]
        wait_until(lambda: proc.poll() is not None
                   or np.array_equal(read_xwd(screen)[:fh, :fw], first), 30,
                   "the first frame on the X framebuffer")
        assert proc.poll() is None, f"the device exited: {proc.poll()}"
        wid = _image_window(display, "eigencast", (fh, fw))
        _xdotool(display, "windowfocus", "--sync", wid)

        def shot(n: int) -> np.ndarray:
            # keys go to the focused window through XTEST: events sent to a window id
            # (XSendEvent) can be lost while the server is busy
            _xdotool(display, "windowfocus", "--sync", wid)
            _xdotool(display, "key", "s")
            path = shots / f"screenshot-{n:04d}.png"
            wait_until(path.exists, 30, f"{path.name}")
            return np.asarray(Image.open(path))

        np.testing.assert_array_equal(shot(1), first)
        # the pointer rests in the window before the drag, as a user's hand does
        _xdotool(display, "mousemove", "--sync", "--window", wid, "10", "20")

        def settled(frame: np.ndarray, what: str) -> None:
            # a depth image shows its blend at once and its warp when the worker has made
            # it (under load, a few frames later): wait for the device's own frame
            wait_until(lambda: np.array_equal(read_xwd(screen)[:fh, :fw], frame), 30, what)

        _xdotool(display, "key", "Left")  # phi + 5
        settled(model.view(35.0, 15.0), "the view after the Left key")
        np.testing.assert_array_equal(shot(2), model.view(35.0, 15.0))
        _drag_right(display, wid)  # phi - 10
        want = model.view(25.0, 15.0)
        settled(want, "the view after the drag")
        np.testing.assert_array_equal(shot(3), want)
        # what the X server itself shows at the window's place
        h, w = want.shape[:2]
        wait_until(lambda: np.array_equal(read_xwd(screen)[:h, :w], want), 30,
                   "the X framebuffer to show the frame")
        _xdotool(display, "key", "Escape")
        assert proc.wait(timeout=20) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)


def test_window_drag_then_rest_shows_the_exact_ray_cast(tmp_path, tmp_path_factory, xvfb,
                                                       monkeypatch):
    """serve against a real window: a view that rests ends up on the X server's own
    framebuffer exactly as the host ray-casts it, bit for bit; after a drag, so does the view
    dragged to."""
    from host.link.true_views import open_true_view_scores

    display, screen = xvfb
    model_path = tiny_model(tmp_path_factory)
    model = HostModel.load(model_path)
    renderer = open_true_view_scores(model).renderer
    for name, value in (("DISPLAY", display), ("SDL_VIDEODRIVER", "x11"),
                        ("SDL_VIDEO_WINDOW_POS", "0,0")):
        monkeypatch.setenv(name, value)
    device = DeviceProcess(tmp_path / "flash", "--display", key_file=key_file(model_path))
    stop = threading.Event()
    sent: list = []
    result: dict = {}

    def host() -> None:
        result["stats"] = serve(model_path, device.url,
                                ServeOptions(key=KEY, provision_missing=True),
                                ServeParts(model=model, stop=stop, log=lambda line: None,
                                           on_frame=lambda encoded, view: sent.append(
                                               (encoded, view))))

    thread = threading.Thread(target=host, daemon=True)
    thread.start()
    h, w = model.image.image_shape

    def exact() -> bool:
        """The last packet is a view's exact layer, and the window shows the ray-cast."""
        if not sent or not getattr(sent[-1][0], "exact", False):
            return False
        truth = renderer.render(*sent[-1][1])[0]
        return np.array_equal(read_xwd(screen)[:h, :w], truth)

    try:
        wait_until(lambda: device.proc.poll() is not None or exact(), 60,
                   "the first view's ray-cast on the X framebuffer")
        assert device.proc.poll() is None, "the device exited:\n" + "\n".join(device.lines[-5:])
        first = sent[-1][1]
        wid = _image_window(display, "eigencast", (h, w))
        _xdotool(display, "windowfocus", "--sync", wid)
        _drag_right(display, wid)
        wait_until(lambda: sent and sent[-1][1] != first and exact(), 60,
                   "the dragged-to view's ray-cast on the X framebuffer")
        view = sent[-1][1]
        assert view[1] == first[1] and view[0] < first[0]  # dragged right: phi decreased
    finally:
        stop.set()
        thread.join(20)
        device.stop()
    assert result["stats"].exact_views >= 2
