"""The pygame window under SDL's dummy driver, and the headless PNG presenter."""

from __future__ import annotations

import csv
import io
import os

import numpy as np
import pytest
from PIL import Image

from device_runtime.display import (
    FRAMES_CSV_COLUMNS,
    HeadlessPresenter,
    Quit,
    Screenshot,
    ToggleOverlay,
    ViewDelta,
    Window,
    Zoom,
    encode_png,
    frame_kind,
)

pygame = pytest.importorskip("pygame")


@pytest.fixture
def window(tmp_path):
    assert os.environ.get("SDL_VIDEODRIVER") == "dummy"  # tests/conftest.py
    win = Window((30, 40), screenshot_dir=tmp_path, zoom=1.0)
    yield win
    win.close()


def _post(kind, **attrs):
    pygame.event.post(pygame.event.Event(kind, **attrs))


def _key(key, mod=0, text=""):
    _post(pygame.KEYDOWN, key=key, mod=mod, unicode=text)


def _frame(seed=0, shape=(30, 40)):
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, size=(*shape, 3), dtype=np.uint8)


def test_png_encoder_round_trips_through_a_standard_decoder():
    for shape in [(1, 1), (2, 3), (30, 40), (17, 5)]:
        image = _frame(1, shape)
        decoded = np.asarray(Image.open(io.BytesIO(encode_png(image))))
        np.testing.assert_array_equal(decoded, image)
    with pytest.raises(ValueError, match="uint8"):
        encode_png(np.zeros((4, 4, 3), np.float32))


def test_drag_arrows_and_keys_become_actions(window):
    pygame.event.get()  # drop start-up events
    _post(pygame.MOUSEMOTION, rel=(8, 0), buttons=(0, 0, 0), pos=(5, 5))  # no button: ignored
    _post(pygame.MOUSEBUTTONDOWN, button=1, pos=(5, 5))
    _post(pygame.MOUSEMOTION, rel=(10, -4), buttons=(1, 0, 0), pos=(15, 1))
    _post(pygame.MOUSEBUTTONUP, button=1, pos=(15, 1))
    _post(pygame.MOUSEMOTION, rel=(3, 3), buttons=(0, 0, 0), pos=(18, 4))  # released: ignored
    _key(pygame.K_LEFT)
    _key(pygame.K_RIGHT, pygame.KMOD_SHIFT)
    _key(pygame.K_UP)
    _key(pygame.K_DOWN)
    _key(pygame.K_PLUS, text="+")
    _key(pygame.K_MINUS, text="-")
    _key(pygame.K_h, text="h")
    _key(pygame.K_s, text="s")
    _key(pygame.K_a, text="a")  # not bound
    _key(pygame.K_ESCAPE)
    _post(pygame.QUIT)
    actions = window.poll()
    assert actions == [
        ViewDelta(-5.0, -2.0),  # 0.5 degree per pixel: drag right turns phi back, up lowers
        ViewDelta(5.0, 0.0), ViewDelta(-1.0, 0.0), ViewDelta(0.0, 5.0), ViewDelta(0.0, -5.0),
        Zoom(1.25), Zoom(0.8), ToggleOverlay(), Screenshot(), Quit(), Quit(),
    ]


def test_screenshot_is_the_frame_and_the_overlay_and_zoom_change_the_window(window, tmp_path):
    window.set_image_shape((120, 160))  # room for the overlay's box in a corner
    frame = _frame(2, (120, 160))
    window.present(frame, overlay_lines=["12.0 fps", "view 1 2"])
    path = window.screenshot()
    np.testing.assert_array_equal(np.asarray(Image.open(path)), frame)  # overlay off
    window.overlay = True
    window.present(frame, overlay_lines=["12.0 fps", "view 1 2"])
    with_overlay = window.window_pixels()
    assert not np.array_equal(with_overlay, frame)
    assert np.array_equal(with_overlay[-5:, -5:], frame[-5:, -5:])  # only a corner box
    second = window.screenshot()
    assert second != path and second.name == "screenshot-0002.png"
    window.overlay = False
    window.set_zoom(2.0)
    assert window.window_size == (320, 240)
    big = window.window_pixels()
    assert big.shape == (240, 320, 3)
    np.testing.assert_array_equal(big[::2, ::2], frame)  # nearest-neighbour doubling
    window.set_image_shape((20, 10))
    assert window.window_size == (20, 40)


def test_window_input_drives_the_runtime_view(tmp_path, window):
    from device_runtime.device import DeviceConfig
    from device_runtime.runtime import RuntimeDevice

    device = RuntimeDevice(DeviceConfig(flash_dir=tmp_path / "flash"), presenter=window,
                           view=(10.0, 0.0), log=lambda line: None)

    class Link:
        closed = False

        def __init__(self):
            self.sent = []

        def send(self, msg, **kwargs):
            self.sent.append(msg)

    device.link = Link()
    device.session.device_nonce = bytes(16)
    for action in [ViewDelta(-5.0, -2.0), ToggleOverlay(), Zoom(1.25)]:
        device.apply(action)
    assert device.view == (5.0, -2.0) and window.overlay and window.zoom == 1.25
    device.apply(Quit())
    assert device.stop_event.is_set()
    device.close()


def test_headless_presenter_writes_every_nth_frame_and_a_log(tmp_path):
    presenter = HeadlessPresenter(tmp_path / "out", every=3)
    frames = [_frame(i) for i in range(7)]
    for i, frame in enumerate(frames):
        own = i == 3  # the device's own frame (a prediction): no packet, no host frame
        presenter.present(frame, {"frame": 0 if own else 100 + i, "phi_deg": 1.5 * i,
                                  "theta_deg": -2.0, "key": i == 0,
                                  "packet_bytes": 0 if own else 90 + i, "sequence": i,
                                  "corrected": i == 6, "predicted": own})
    presenter.close()
    with open(tmp_path / "out" / "frames.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert tuple(rows[0]) == FRAMES_CSV_COLUMNS
    assert [r["file"] for r in rows] == ["frame-000000.png", "frame-000003.png",
                                         "frame-000006.png"]
    assert [r["shown"] for r in rows] == ["0", "3", "6"]  # the display's frame counter
    assert [r["host_frame"] for r in rows] == ["100", "", "106"]
    assert rows[1]["phi_deg"] == "4.5" and rows[0]["key"] == "1"
    assert [r["kind"] for r in rows] == ["key", "blend", "corrected"]
    assert frame_kind({"phi_deg": 1.0, "theta_deg": 2.0, "predicted": True,
                       "synthesized": True}) == "warp"
    for row in rows:
        index = int(row["shown"])
        got = np.asarray(Image.open(tmp_path / "out" / row["file"]))
        np.testing.assert_array_equal(got, frames[index])
    shot = presenter.screenshot()
    np.testing.assert_array_equal(np.asarray(Image.open(shot)), frames[-1])
    with pytest.raises(ValueError, match="every"):
        HeadlessPresenter(tmp_path, every=0)


def test_headless_presenter_keeps_the_last_frames(tmp_path):
    """keep=N: only the newest N PNGs stay on disk; frames.csv still lists every one."""
    presenter = HeadlessPresenter(tmp_path / "out", keep=3)
    frames = [_frame(i) for i in range(8)]
    for i, frame in enumerate(frames):
        presenter.present(frame, {"phi_deg": float(i), "theta_deg": 0.0})
    presenter.close()
    assert sorted(p.name for p in (tmp_path / "out").glob("*.png")) == [
        "frame-000005.png", "frame-000006.png", "frame-000007.png"]
    with open(tmp_path / "out" / "frames.csv") as handle:
        assert len(list(csv.DictReader(handle))) == 8
    np.testing.assert_array_equal(
        np.asarray(Image.open(tmp_path / "out" / "frame-000007.png")), frames[7])
    with pytest.raises(ValueError, match="keep"):
        HeadlessPresenter(tmp_path, keep=0)
