"""Presenting frames: a pygame window with mouse/keyboard input, or PNG files (headless).

This is the only module of the device runtime that imports pygame, and only lazily (inside
:class:`Window`), so a headless board needs no pygame at all.

Two presenters share one small interface (``present``, ``poll``, ``screenshot``, ``close``
and the ``overlay`` / ``zoom`` state) that :mod:`device_runtime.runtime` drives:

:class:`Window`
    A window at the image size (scaled down to fit the screen). Input becomes
    :class:`Action` values: mouse drag and the arrow keys change the view
    (:class:`ViewDelta`), ``+``/``-`` zoom the displayed image (:class:`Zoom`), ``h``
    toggles a small overlay (fps, bytes per frame, link rate, view, look), ``s`` saves a
    screenshot of the window, ``l`` shows the image's next look (:class:`CycleLook`, an
    image with several), ``Esc`` or closing the window quits (:class:`Quit`).
:class:`HeadlessPresenter`
    Writes every ``every``-th presented frame as a PNG into a folder (keeping the last
    ``keep``), plus one line per written frame in ``frames.csv`` so the output can be
    checked against ``eigencast view``. Its columns (:data:`FRAMES_CSV_COLUMNS`): ``shown``
    (the display's frame counter: the n-th frame presented, from 0), ``file``, ``host_frame``
    (the score packet's frame number as the host counts it, from a random start; empty for
    the device's own frames), ``phi_deg``, ``theta_deg``, ``key`` (1: a key frame or a
    frame of the device's own), ``packet_bytes`` (0: the device's own frame),
    ``sequence`` (the view request the frame answers, 0: none) and ``kind`` (the device's
    own frame of the view: ``warp``, the depth warp of its neighbours, or ``blend``, the
    blend of its own scores, shown while the warp is made or when the image has no depth;
    ``corrected``: the own frame corrected by the host; ``layer``: a resting view's frame
    refined by a layer, ``exact``: refined until it is the host's ray-cast bit for bit;
    ``key`` / ``delta``: a host frame of absolute scores; ``mean``: the image's first
    frame). Without a folder it presents nothing.

PNGs are written by :func:`encode_png` (zlib + struct: no imaging library on the device),
atomically (temporary file, then rename), so a reader never sees half a file.
"""

from __future__ import annotations

import collections
import contextlib
import os
import struct
import sys
import tempfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "DRAG_DEG_PER_PIXEL",
    "FRAMES_CSV_COLUMNS",
    "KEY_STEP_DEG",
    "ZOOM_FACTOR",
    "Action",
    "CycleLook",
    "HeadlessPresenter",
    "Quit",
    "Screenshot",
    "ToggleOverlay",
    "ViewDelta",
    "Window",
    "WindowUnavailable",
    "Zoom",
    "encode_png",
    "write_png",
]

DRAG_DEG_PER_PIXEL = 0.5
"""View change per pixel of mouse drag, degrees (drag right: phi decreases, the object turns
with the mouse; drag up: theta increases)."""
KEY_STEP_DEG = 5.0
"""View change per arrow-key press, degrees (1 degree with Shift)."""
ZOOM_FACTOR = 1.25
"""Zoom change per ``+`` / ``-`` press."""
ZOOM_RANGE = (0.125, 8.0)
_FRAMES_CSV = "frames.csv"
FRAMES_CSV_COLUMNS = ("shown", "file", "host_frame", "phi_deg", "theta_deg", "key",
                      "packet_bytes", "sequence", "kind")
"""``frames.csv``'s header (see the module docstring for what each column holds)."""
_CSV_HEADER = ",".join(FRAMES_CSV_COLUMNS) + "\n"


def frame_kind(info: dict) -> str:
    """What a presented frame is (``frames.csv``'s ``kind``) from its info."""
    if info.get("layer") is not None:
        return "exact" if info.get("exact") else "layer"
    if info.get("corrected"):
        return "corrected"
    if info.get("synthesized"):
        return "warp"
    if info.get("predicted") or (
            info.get("phi_deg") is not None and not info.get("packet_bytes")):
        return "blend"
    if info.get("phi_deg") is None:
        return "mean"
    return "key" if info.get("key") else "delta"


class WindowUnavailable(RuntimeError):
    """No window can be opened (no pygame, no display): run headless instead."""


# --------------------------------------------------------------------------- actions


@dataclass(frozen=True)
class ViewDelta:
    """Change the view by ``dphi_deg`` / ``dtheta_deg`` (theta is clamped to [-90, 90])."""

    dphi_deg: float
    dtheta_deg: float


@dataclass(frozen=True)
class Zoom:
    """Multiply the displayed image's zoom by ``factor``."""

    factor: float


@dataclass(frozen=True)
class ToggleOverlay:
    """Show or hide the overlay."""


@dataclass(frozen=True)
class Screenshot:
    """Save the window's contents as a PNG."""


@dataclass(frozen=True)
class Quit:
    """Leave the runtime (Esc or the window closed)."""


@dataclass(frozen=True)
class CycleLook:
    """Show the image's next look (the first after the last; nothing with one look)."""


Action = ViewDelta | Zoom | ToggleOverlay | Screenshot | Quit | CycleLook


# --------------------------------------------------------------------------- PNG


def encode_png(image: np.ndarray, *, level: int = 3) -> bytes:
    """Encode an RGB image as PNG (8-bit, no interlace, "Up" filter on every row).

    Parameters
    ----------
    image : ndarray of shape (height, width, 3), uint8
    level : int
        zlib level, 0..9.

    Returns
    -------
    bytes
        A complete PNG file.
    """
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 3 or (
        image.shape[2] != 3
    ):
        raise ValueError(
            f"encode_png: image must be uint8 of shape (height, width, 3), got "
            f"{getattr(image, 'dtype', type(image))} {getattr(image, 'shape', '')}"
        )
    height, width = image.shape[:2]
    rows = np.ascontiguousarray(image).reshape(height, width * 3)
    filtered = np.empty((height, width * 3 + 1), dtype=np.uint8)
    filtered[:, 0] = 2  # Up: each byte minus the byte above it (mod 256)
    filtered[0, 1:] = rows[0]
    if height > 1:
        np.subtract(rows[1:], rows[:-1], out=filtered[1:, 1:])  # uint8 arithmetic wraps

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(
            ">I", zlib.crc32(kind + data) & 0xFFFFFFFF
        )

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(filtered.tobytes(), level))
        + chunk(b"IEND", b"")
    )


def write_png(path: str | os.PathLike, image: np.ndarray, *, level: int = 3) -> Path:
    """Write ``image`` to ``path`` as PNG atomically (temporary file in the folder, rename)."""
    path = Path(path)
    data = encode_png(image, level=level)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return path


def _next_free(folder: Path, stem: str) -> Path:
    for n in range(1, 1_000_000):
        path = folder / f"{stem}-{n:04d}.png"
        if not path.exists():
            return path
    raise OSError(f"{folder}: no free screenshot name")


# --------------------------------------------------------------------------- headless


class HeadlessPresenter:
    """Present frames without a screen: every ``every``-th frame becomes a PNG in ``folder``.

    Parameters
    ----------
    folder : path-like or None
        Where ``frame-NNNNNN.png`` and ``frames.csv`` go (created); None: write nothing.
    every : int
        Write one frame in ``every`` (>= 1); the first presented frame is always written.
    keep : int or None
        Keep only the last ``keep`` PNGs this presenter wrote (older ones are deleted as new
        ones come; ``frames.csv`` keeps every row); None keeps them all.
    screenshot_dir : path-like, optional
        Where :meth:`screenshot` saves (default: ``folder`` or the current folder).

    Attributes
    ----------
    frames_written : int
    overlay : bool
        Ignored headless (kept for the runtime's bookkeeping).
    zoom : float
    """

    headless = True

    def __init__(
        self,
        folder: str | os.PathLike | None = None,
        *,
        every: int = 1,
        keep: int | None = None,
        screenshot_dir: str | os.PathLike | None = None,
    ) -> None:
        if not isinstance(every, int) or every < 1:
            raise ValueError(f"HeadlessPresenter: every={every!r} must be an int >= 1")
        if keep is not None and (not isinstance(keep, int) or keep < 1):
            raise ValueError(f"HeadlessPresenter: keep={keep!r} must be None or an int >= 1")
        self.folder = None if folder is None else Path(folder)
        self.every = every
        self.keep = keep
        self._written: collections.deque[Path] = collections.deque()
        self.frames_written = 0
        self.overlay = False
        self.zoom = 1.0
        self._count = 0
        self._last: np.ndarray | None = None
        self._csv: Any = None
        if self.folder is not None:
            self.folder.mkdir(parents=True, exist_ok=True)
            csv_path = self.folder / _FRAMES_CSV
            fresh = not csv_path.exists() or csv_path.stat().st_size == 0
            self._csv = open(csv_path, "a", encoding="ascii")  # noqa: SIM115 (closed in close())
            if fresh:
                self._csv.write(_CSV_HEADER)
                self._csv.flush()
        self.screenshot_dir = Path(screenshot_dir) if screenshot_dir else (self.folder or Path("."))

    def poll(self) -> list[Action]:
        """No input without a screen."""
        return []

    def present(self, frame: np.ndarray, info: dict | None = None, *,
                overlay_lines: list[str] | None = None) -> bool:
        """Take a frame; write it when it is the first or an ``every``-th one.

        Parameters
        ----------
        frame : ndarray of shape (height, width, 3), uint8
            Not kept beyond this call unless written (the runtime reuses its buffer).
        info : dict, optional
            ``frame``, ``phi_deg``, ``theta_deg``, ``key``, ``packet_bytes``, ``sequence``
            for ``frames.csv``.

        Returns
        -------
        bool
            Whether the frame was written.
        """
        index = self._count
        self._count += 1
        self._last = frame
        if self.folder is None or index % self.every:
            return False
        name = f"frame-{index:06d}.png"
        self._written.append(write_png(self.folder / name, frame))
        if self.keep is not None and len(self._written) > self.keep:
            with contextlib.suppress(OSError):
                self._written.popleft().unlink()
        info = info or {}

        def num(field: str) -> str:
            value = info.get(field)
            return "" if value is None else repr(float(value))

        packet_bytes = info.get("packet_bytes", 0) or 0
        host_frame = info.get("frame", "") if packet_bytes else ""  # own frames: none
        self._csv.write(
            f"{index},{name},{host_frame},{num('phi_deg')},{num('theta_deg')},"
            f"{int(bool(info.get('key', False)))},{packet_bytes},"
            f"{info.get('sequence', 0)},{frame_kind(info)}\n"
        )
        self._csv.flush()
        self.frames_written += 1
        return True

    def screenshot(self) -> Path | None:
        """Save the last presented frame as ``screenshot-NNNN.png``; None before any frame."""
        if self._last is None:
            return None
        self.screenshot_dir.mkdir(parents=True, exist_ok=True)
        return write_png(_next_free(self.screenshot_dir, "screenshot"), self._last)

    def close(self) -> None:
        """Close ``frames.csv``."""
        if self._csv is not None:
            self._csv.close()
            self._csv = None


# --------------------------------------------------------------------------- window


@contextlib.contextmanager
def _c_stderr_captured() -> Any:
    """Capture what C code (SDL) writes to file descriptor 2 meanwhile: yields a list that
    gets the text, if any, once the block ends (Python's own stderr is flushed first)."""
    said: list[str] = []
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no fd 2 to redirect: let SDL print
        yield said
        return
    try:
        with tempfile.TemporaryFile() as tmp:
            os.dup2(tmp.fileno(), 2)
            try:
                yield said
            finally:
                os.dup2(saved, 2)
                tmp.seek(0)
                text = tmp.read().decode("utf-8", "replace")
                if text.strip():
                    said.append(text)
    finally:
        os.close(saved)


def _no_screen() -> str:
    """Why there is no screen, in the device's words."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY")
                                                 or os.environ.get("WAYLAND_DISPLAY")):
        return "no display (neither DISPLAY nor WAYLAND_DISPLAY is set)"
    return "no display (SDL found no screen to open a window on)"



class Window:
    """A pygame window showing frames, with view control by mouse and keyboard.

    Parameters
    ----------
    image_shape : (int, int)
        ``(height, width)`` of the frames.
    title : str
    screenshot_dir : path-like
        Where ``s`` saves ``screenshot-NNNN.png``.
    zoom : float, optional
        Initial zoom; default: 1, or less so that the window fits the screen.

    Raises
    ------
    WindowUnavailable
        pygame is not installed or no display can be opened.

    Notes
    -----
    Call every method from the thread that created the window (pygame's rule; the
    runtime keeps the display loop on the main thread).
    """

    headless = False

    def __init__(
        self,
        image_shape: tuple[int, int],
        *,
        title: str = "eigencast",
        screenshot_dir: str | os.PathLike = ".",
        zoom: float | None = None,
    ) -> None:
        os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")  # no banner on stdout
        try:
            import pygame
        except ImportError as exc:
            raise WindowUnavailable(f"pygame is not installed ({exc})") from None
        self._pg = pygame
        try:
            with _c_stderr_captured() as sdl_said:  # SDL's probes print to fd 2 themselves
                pygame.display.init()
        except pygame.error as exc:
            raise WindowUnavailable(f"no display: {exc}") from None
        if not os.environ.get("SDL_VIDEODRIVER") and pygame.display.get_driver() in (
                "offscreen", "dummy"):  # SDL's last resort: a window no one would see
            pygame.display.quit()
            raise WindowUnavailable(_no_screen())
        if sdl_said:  # a window opened: what SDL said on the way may matter
            print(sdl_said[0], end="", file=sys.stderr, flush=True)
        height, width = (int(v) for v in image_shape)
        info = pygame.display.Info()
        self._screen_size = (info.current_w, info.current_h)
        self._auto_zoom = zoom is None
        if zoom is None:
            zoom = self._fit_zoom((height, width))
        self.image_shape = (height, width)
        self.title = title
        self.screenshot_dir = Path(screenshot_dir)
        self.zoom = float(zoom)
        self.overlay = False
        self._dragging = False
        self._font: Any = None
        self._surface: Any = None
        self._screen: Any = None
        try:
            self._set_mode()
        except pygame.error as exc:
            pygame.display.quit()
            raise WindowUnavailable(f"cannot open a window: {exc}") from None
        pygame.display.set_caption(title)
        self._last_frame: np.ndarray | None = None
        self._last_overlay: list[str] | None = None

    # ------------------------------------------------------------------ state
    @property
    def window_size(self) -> tuple[int, int]:
        """``(width, height)`` of the window in pixels."""
        height, width = self.image_shape
        return max(1, round(width * self.zoom)), max(1, round(height * self.zoom))

    def _set_mode(self) -> None:
        self._screen = self._pg.display.set_mode(self.window_size)

    def _fit_zoom(self, image_shape: tuple[int, int]) -> float:
        """1, or less when the image would not fit the screen."""
        screen_w, screen_h = self._screen_size
        if screen_w <= 0 or screen_h <= 0:
            return 1.0
        return min(1.0, 0.95 * screen_w / image_shape[1], 0.9 * screen_h / image_shape[0])

    def set_image_shape(self, image_shape: tuple[int, int]) -> None:
        """Frames of another size from now on (a new image): resize the window (and, unless a
        zoom was given, fit it to the screen again)."""
        shape = (int(image_shape[0]), int(image_shape[1]))
        if shape != self.image_shape:
            self.image_shape = shape
            self._last_frame = None
            if self._auto_zoom:
                self.zoom = self._fit_zoom(shape)
            self._set_mode()

    def set_zoom(self, zoom: float) -> None:
        """Resize the window to ``zoom`` times the image size (clamped to 1/8..8)."""
        zoom = min(max(float(zoom), ZOOM_RANGE[0]), ZOOM_RANGE[1])
        if zoom != self.zoom:
            self.zoom = zoom
            self._set_mode()
            if self._last_frame is not None:
                self.present(self._last_frame, overlay_lines=self._last_overlay)

    # ------------------------------------------------------------------ input
    def poll(self) -> list[Action]:
        """Translate pending pygame events into actions (never blocks)."""
        actions: list[Action] = []
        for event in self._pg.event.get():
            action = self.action_for(event)
            if action is not None:
                actions.append(action)
        return actions

    def action_for(self, event: Any) -> Action | None:
        """The action one pygame event stands for (None: ignored).

        Drag: left button down, motion with the button held, button up; ``dx`` pixels turn
        the view by ``-dx * DRAG_DEG_PER_PIXEL / zoom`` degrees of phi, ``dy`` by
        ``dy * DRAG_DEG_PER_PIXEL / zoom`` of theta (drag up looks from higher up).
        """
        pg = self._pg
        if event.type == pg.QUIT:
            return Quit()
        if event.type == pg.MOUSEBUTTONDOWN and event.button == 1:
            self._dragging = True
            return None
        if event.type == pg.MOUSEBUTTONUP and event.button == 1:
            self._dragging = False
            return None
        if event.type == pg.MOUSEMOTION and self._dragging and event.buttons[0]:
            dx, dy = event.rel
            scale = DRAG_DEG_PER_PIXEL / max(self.zoom, 1e-6)
            if dx or dy:
                return ViewDelta(-dx * scale, dy * scale)
            return None
        if event.type != pg.KEYDOWN:
            return None
        key = event.key
        step = 1.0 if event.mod & pg.KMOD_SHIFT and key in (
            pg.K_LEFT, pg.K_RIGHT, pg.K_UP, pg.K_DOWN) else KEY_STEP_DEG
        if key == pg.K_ESCAPE:
            return Quit()
        if key == pg.K_LEFT:
            return ViewDelta(step, 0.0)
        if key == pg.K_RIGHT:
            return ViewDelta(-step, 0.0)
        if key == pg.K_UP:
            return ViewDelta(0.0, step)
        if key == pg.K_DOWN:
            return ViewDelta(0.0, -step)
        text = getattr(event, "unicode", "") or ""
        if key in (pg.K_PLUS, pg.K_EQUALS, pg.K_KP_PLUS) or text == "+":
            return Zoom(ZOOM_FACTOR)
        if key in (pg.K_MINUS, pg.K_KP_MINUS) or text == "-":
            return Zoom(1.0 / ZOOM_FACTOR)
        if key == pg.K_h:
            return ToggleOverlay()
        if key == pg.K_s:
            return Screenshot()
        if key == pg.K_l:
            return CycleLook()
        return None

    # ------------------------------------------------------------------ output
    def present(self, frame: np.ndarray, info: dict | None = None, *,
                overlay_lines: list[str] | None = None) -> bool:
        """Show ``frame`` (uint8 (height, width, 3)) scaled by the zoom, plus the overlay."""
        pg = self._pg
        height, width = self.image_shape
        if frame.shape != (height, width, 3):
            raise ValueError(f"Window.present: frame shape {frame.shape} is not "
                             f"({height}, {width}, 3)")
        self._last_frame = frame
        self._last_overlay = overlay_lines
        surface = pg.image.frombuffer(np.ascontiguousarray(frame).tobytes(), (width, height),
                                      "RGB")
        size = self.window_size
        if size != (width, height):
            surface = pg.transform.scale(surface, size)
        self._screen.blit(surface, (0, 0))
        if self.overlay and overlay_lines:
            self._draw_overlay(overlay_lines)
        pg.display.flip()
        return True

    def _draw_overlay(self, lines: list[str]) -> None:
        pg = self._pg
        if self._font is None:
            pg.font.init()
            self._font = pg.font.Font(None, 18)
        rendered = [self._font.render(line, True, (255, 255, 255)) for line in lines]
        width = max(r.get_width() for r in rendered) + 8
        height = sum(r.get_height() for r in rendered) + 6
        box = pg.Surface((width, height), pg.SRCALPHA)
        box.fill((0, 0, 0, 160))
        self._screen.blit(box, (2, 2))
        y = 5
        for r in rendered:
            self._screen.blit(r, (6, y))
            y += r.get_height()

    def window_pixels(self) -> np.ndarray:
        """What the window shows now: uint8 (window height, window width, 3)."""
        pg = self._pg
        data = pg.image.tostring(self._screen, "RGB")
        width, height = self._screen.get_size()
        return np.frombuffer(data, dtype=np.uint8).reshape(height, width, 3).copy()

    def screenshot(self) -> Path:
        """Save the window's contents (overlay included) as ``screenshot-NNNN.png``."""
        self.screenshot_dir.mkdir(parents=True, exist_ok=True)
        return write_png(_next_free(self.screenshot_dir, "screenshot"), self.window_pixels())

    def close(self) -> None:
        """Close the window."""
        with contextlib.suppress(Exception):
            self._pg.display.quit()
