"""``eigencast demo``: render, fit, start a device process, provision it, serve it.

One command on a fresh clone (``make demo``), every step cached in a work folder
(``./demo-out`` by default) so a second run starts showing frames in seconds:

1. **render** the volume (default the built-in head) from ``grid:72x9`` at 192 px with
   300 samples per ray, with each view's depth, into ``WORK/NAME.cdb`` (an interrupted or
   finished render resumes or skips: the Cinema writer keeps valid images);
2. **fit** an adaptive eigenspace (cells of 16 px, T = 0.98) with the depth eigenspace and
   the standalone table (``fit``'s defaults: the device can make its own frame of any view),
   signed with ``WORK/device.key``, into ``WORK/NAME.ecs``, skipped when
   ``WORK/NAME.fit-stamp`` shows it was fitted from this database (index and image sizes),
   key and settings;
3. start **eigencast-device** as a separate process listening on TCP loopback
   (``tcp-listen://127.0.0.1:PORT``, printed) with its flash in ``WORK/flash``: a window
   when a display exists, headless otherwise;
4. **provision** it with a progress bar (skipped when it already holds the image);
5. **serve** the one served path: the device shows its own frame of every view (the depth
   warp of its neighbouring training views) and the host sends the correction of that frame
   from a ray-cast of the view (sparse within the frame deadline while the view moves, the
   whole view once it rests). With a window, the device's drags and key presses drive the
   view until the window is closed; headless, the host drives an orbit (``steps:120:15``,
   at most 60 frames per second, the rate of a display), the device writes every 10th frame
   to ``WORK/frames`` and a summary follows (with progress while it is computed): frames,
   the device's frame rate, bytes per frame, and the object SSIM of the device's own frames,
   of the streamed (corrected) frames it saved and of the same views at rest (the complete
   correction), each beside the smallest JPEG, WebP and AVIF of those views with the same
   object SSIM, and the link rate.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from host.errors import EigencastError

__all__ = [
    "DemoSettings",
    "codec_curves",
    "display_available",
    "equal_object_quality",
    "run_demo",
]

_LISTEN = re.compile(r"listening on tcp-listen://([^:\s]+):(\d+)")


@dataclass(frozen=True)
class DemoSettings:
    """What the demo renders and fits (the defaults finish in a few minutes on 2 cores)."""

    volume: str = "builtin:head"
    views: str = "grid:72x9"
    size: int = 192
    samples: int = 300
    cell: int = 16
    threshold: float = 0.98
    orbit: str = "steps:120:15"
    every: int = 10
    compare_views: int = 4


def display_available() -> bool:
    """True when a window can be opened here (DISPLAY/WAYLAND set and pygame opens it)."""
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return False
    if os.environ.get("SDL_VIDEODRIVER", "") in ("dummy", "offscreen"):
        return False
    code = "import pygame; pygame.display.init(); pygame.display.set_mode((8, 8)); print('ok')"
    try:
        run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             timeout=30, env=dict(os.environ, PYGAME_HIDE_SUPPORT_PROMPT="1"))
    except (OSError, subprocess.TimeoutExpired):
        return False
    return run.returncode == 0 and "ok" in run.stdout


def codec_curves(reference: np.ndarray, mask: np.ndarray,
                 codecs: tuple[str, ...] = ("jpeg", "webp", "avif")
                 ) -> dict[str, list[tuple[int, int, float]]]:
    """Per codec, ``(bytes, quality, object SSIM)`` of ``reference`` coded at every quality
    1..100 (object SSIM: `host.evaluate.structural_similarity` over ``mask``). Computed once
    per view and shared by every frame compared with it (AVIF's encoder is most of the cost:
    about 0.1 s a quality at 192 px)."""
    from host.evaluate import encode_image, structural_similarity

    curves: dict[str, list[tuple[int, int, float]]] = {}
    for codec in codecs:
        curves[codec] = []
        for quality in range(1, 101):
            coded = encode_image(reference, codec, quality)
            curves[codec].append((coded.size_bytes, quality,
                                  structural_similarity(reference, coded.decode(), mask=mask)))
    return curves


def equal_object_quality(reference: np.ndarray, frame: np.ndarray, mask: np.ndarray,
                         codecs: tuple[str, ...] = ("jpeg", "webp", "avif"), *,
                         curves: dict[str, list[tuple[int, int, float]]] | None = None
                         ) -> dict[str, float]:
    """The smallest file of each codec whose object SSIM against ``reference`` reaches
    ``frame``'s.

    Object SSIM is `host.evaluate.structural_similarity` over ``mask`` (the object's
    pixels). Every quality 1..100 is tried (`codec_curves`; pass ``curves`` to share them
    between frames of one view): at low qualities a codec's SSIM is far from monotone in the
    quality (on the dark, noisy background of a ray-cast JPEG quality 10 can beat quality 15
    by 0.1), so a bisection would miss the smallest file.

    Returns
    -------
    dict
        ``object_ssim`` of ``frame``; per codec ``{codec}_bytes``, ``{codec}_quality`` and
        ``{codec}_object_ssim`` of the smallest file reaching it (the best one if none does).
    """
    from host.evaluate import structural_similarity

    if curves is None:
        curves = codec_curves(reference, mask, codecs)
    target = structural_similarity(reference, frame, mask=mask)
    out = {"object_ssim": target}
    for codec in codecs:
        curve = curves[codec]
        reaching = [c for c in curve if c[2] >= target]
        chosen = (min(reaching, key=lambda c: (c[0], c[1])) if reaching
                  else max(curve, key=lambda c: (c[2], -c[0])))
        out.update({f"{codec}_bytes": chosen[0], f"{codec}_quality": chosen[1],
                    f"{codec}_object_ssim": chosen[2]})
    return out


class _DeviceProcess:
    """``eigencast-device --listen 127.0.0.1:0`` as a child; its log goes to a file."""

    def __init__(self, args: list[str], log_path: Path) -> None:
        cmd = [sys.executable, "-m", "device_runtime.cli", "--listen", "127.0.0.1:0", *args]
        env = dict(os.environ, PYTHONUNBUFFERED="1", PYGAME_HIDE_SUPPORT_PROMPT="1")
        self.proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL,
                                     text=True, env=env)
        self.log = open(log_path, "a", encoding="utf-8")  # noqa: SIM115 (closed in stop())
        self.port: int | None = None
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.log.write(line)
            found = _LISTEN.search(line)
            if found:
                self.port = int(found.group(2))
                break
        self.log.flush()
        if self.port is None:
            self.proc.wait(timeout=10)
            raise EigencastError(f"the device process did not start (see {log_path})")
        self._drain = threading.Thread(target=self._copy, daemon=True)
        self._drain.start()

    def _copy(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.log.write(line)
            self.log.flush()

    @property
    def url(self) -> str:
        return f"socket://127.0.0.1:{self.port}"

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        self._drain.join(timeout=5)
        self.log.close()
        return int(self.proc.returncode or 0)


def _fit_stamp(db: Path, key_path: Path, settings: DemoSettings) -> str:
    """What the model depends on: the database's index and images, the key, the fit settings.

    (Not modification times: a resumed render rewrites ``data.csv`` even when it renders
    nothing, which would refit the model on every run.)
    """
    digest = hashlib.sha256()
    digest.update((db / "data.csv").read_bytes())
    for path in sorted(db.rglob("*")):
        if path.is_file() and path.name != "data.csv" and ".eigencast-cache" not in path.parts:
            stat = path.stat()
            digest.update(f"{path.relative_to(db)}:{stat.st_size}\n".encode())
    digest.update(hashlib.sha256(key_path.read_bytes()).digest())
    digest.update(f"adaptive cell={settings.cell} threshold={settings.threshold!r} "
                  "depth standalone".encode())
    return digest.hexdigest()


def _step(n: int, text: str) -> None:
    print(f"[{n}/5] {text}", file=sys.stderr, flush=True)


def run_demo(
    work: str | os.PathLike = "demo-out",
    *,
    settings: DemoSettings = DemoSettings(),
    headless: bool | None = None,
) -> dict[str, Any]:
    """Run the demo; return its summary (see the module docstring).

    Parameters
    ----------
    work : path-like
        Work folder (created; kept between runs as the cache).
    settings : DemoSettings
    headless : bool, optional
        Force headless (True) or a window (False); default: a window when one can be opened.

    Returns
    -------
    dict
        ``model``, ``device_url``, ``provision`` outcome, serving statistics and, headless,
        the device's statistics and the quality comparison (``quality``).
    """
    from host.fit.model import HostModel
    from host.link.options import ProvisionOptions
    from host.link.provisioning import provision

    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    name = settings.volume.split(":", 1)[-1] if settings.volume.startswith("builtin:") else (
        Path(settings.volume).stem or "volume")
    name = re.sub(r"[^A-Za-z0-9_.-]", "_", name)
    if headless is None:
        headless = not display_available()
    model_path, key_path, key = _render_and_fit(work, name, settings)

    frames = work / "frames"
    if headless and frames.is_dir():  # this run's frames only (frames.csv is appended to)
        shutil.rmtree(frames)
    stats_path = work / "device-stats.json"
    device_args = ["--flash", str(work / "flash"), "--key", str(key_path), "--stats",
                   str(stats_path)]
    if headless:
        device_args += ["--headless", "--frames", str(frames), "--every", str(settings.every)]
    else:
        device_args += ["--display", "--screenshots", str(work)]
    device = _DeviceProcess(device_args, work / "device.log")
    summary: dict[str, Any] = {"model": str(model_path), "device_url": device.url,
                               "headless": headless}
    try:
        _step(3, f"device runtime started as a separate process (pid {device.proc.pid}), "
                 f"listening on tcp-listen://127.0.0.1:{device.port}; the host connects to "
                 f"{device.url} (log: {work / 'device.log'})")
        _step(4, f"provision {model_path.name} on the device")
        result = provision(model_path, device.url, ProvisionOptions(key=key, show_progress=True))
        summary["provision"] = result.outcome
        print(f"      {result.outcome}: {result.size_bytes} bytes in slot {result.slot}",
              file=sys.stderr)
        model = HostModel.load(model_path, key=key)
        stats = _serve_the_device(device, model_path, key, model, settings, headless, frames)
        summary["serve"] = stats.as_dict()
    finally:
        device.stop()
    if stats_path.exists():
        summary["device"] = json.loads(stats_path.read_text())
    if headless:
        summary["quality"] = _quality(settings, model, frames)
        _print_summary(summary, frames)
    return summary


def _render_and_fit(work: Path, name: str, settings: DemoSettings
                    ) -> tuple[Path, Path, bytes]:
    """Steps 1 and 2: render the database (resumes) and fit the model (kept when this
    database and these settings made it); (model path, key path, key)."""
    from host.cli import main as eigencast
    from protocol.keys import load_key, write_key

    db = work / f"{name}.cdb"
    model_path = work / f"{name}.ecs"
    key_path = work / "device.key"
    _step(1, f"render {settings.volume} from {settings.views} at {settings.size} px, with "
             f"depth, into {db} (resumes; skipped when complete)")
    code = eigencast(["render", settings.volume, "-o", str(db), "--views", settings.views,
                      "--size", str(settings.size), "--samples", str(settings.samples)])
    if code != 0:
        raise EigencastError(f"rendering {settings.volume} failed (exit {code})")

    if not key_path.exists():
        write_key(key_path)
    key = load_key(key_path)
    stamp_path = work / f"{name}.fit-stamp"
    stamp = _fit_stamp(db, key_path, settings)
    fresh = model_path.exists() and stamp_path.exists() and stamp_path.read_text() == stamp
    if fresh:
        _step(2, f"fit: {model_path} was fitted from this database with these settings; kept")
    else:
        stamp_path.unlink(missing_ok=True)
        _step(2, f"fit an adaptive eigenspace (cells {settings.cell} px, T={settings.threshold})"
                 f", its depth and the training views' scores into {model_path}")
        code = eigencast(["fit", str(db), "-o", str(model_path), "--method", "adaptive",
                          "--cell", str(settings.cell), "--threshold", str(settings.threshold),
                          "--key", str(key_path)])
        if code != 0:
            raise EigencastError(f"fitting {db} failed (exit {code})")
        stamp_path.write_text(stamp)
    return model_path, key_path, key


def _serve_the_device(device: _DeviceProcess, model_path: Path, key: bytes, model: Any,
                      settings: DemoSettings, headless: bool, frames: Path) -> Any:
    """Step 5: serve an orbit (headless) or the window's views until it closes; the
    serving statistics."""
    from host.link.options import ServeOptions, ServeParts
    from host.link.serving import serve

    if headless:
        from device_runtime.runtime import parse_orbit

        orbit = parse_orbit(settings.orbit)
        _step(5, f"serve an orbit ({settings.orbit}, 60 frames/s at most): the device "
                 "warps its own frame of each view, the host corrects it from a sparse "
                 "ray-cast within the frame deadline; the device writes every "
                 f"{settings.every}th frame to {frames}")
        stats = serve(model_path, device.url,
                      ServeOptions(key=key, orbit=orbit, fps=60, stats_every_s=0),
                      ServeParts(model=model, log=lambda line: None))
        time.sleep(1.2)  # the device's statistics file is refreshed every second
        return stats
    _step(5, "serve: drag the window or use the arrow keys; +/- zoom, h overlay, "
             "s screenshot, Esc quits; the device shows its own frame of each view at "
             "once, the host corrects it, and a view you stop on sharpens to the "
             "ray-cast's best")
    stop = threading.Event()

    def watch() -> None:
        device.proc.wait()
        stop.set()

    threading.Thread(target=watch, daemon=True).start()
    return serve(model_path, device.url,
                 ServeOptions(key=key, stats_every_s=10.0, max_reconnects=3),
                 ServeParts(model=model, stop=stop))


#: What the demo's summary compares, in the order it prints them.
_KINDS = ("own", "streamed", "rest")


def _quality(settings: DemoSettings, model: Any, frames: Path) -> dict[str, Any]:
    """Object SSIM of a few orbit views as the device's own frame, as streamed (the frame it
    saved) and at rest (the complete correction), each with the smallest JPEG, WebP and AVIF
    of the view that reach it; averaged over the views (progress on stderr)."""
    import csv

    from PIL import Image

    from host.evaluate import ServedFrames
    from host.progress import progress
    from host.render.settings import OBJECT_ALPHA_MIN, RenderSettings, ViewRenderer

    index = frames / "frames.csv"
    if not index.exists():
        return {}
    with open(index, newline="") as handle:
        rows = [r for r in csv.DictReader(handle) if r.get("kind") == "corrected"]
    if not rows:
        return {}
    pick = rows[:: max(1, len(rows) // settings.compare_views)][: settings.compare_views]
    renderer = ViewRenderer.open(RenderSettings.from_record(model.render_settings,
                                                            what="demo model"),
                                 what="demo model")
    served = ServedFrames(model, renderer)  # the device's frames, as evaluate measures them
    per_view: list[dict[str, Any]] = []
    with progress("comparing with JPEG, WebP and AVIF", len(pick), unit=" views") as bar:
        for row in pick:
            view = (float(row["phi_deg"]), float(row["theta_deg"]))
            truth, alpha = renderer.render(*view)
            mask = alpha >= OBJECT_ALPHA_MIN
            synth = served.own_frame(*view)
            with Image.open(frames / row["file"]) as im:
                streamed = np.asarray(im.convert("RGB"))
            rest, rest_bytes = served.at_rest(*view)
            out: dict[str, Any] = {"rest_bytes": rest_bytes,
                                   "streamed_bytes": int(row["packet_bytes"] or 0)}
            curves = codec_curves(truth, mask)  # one view's codec files, for all three
            for kind, frame in zip(_KINDS, (synth, streamed, rest)):
                for k, v in equal_object_quality(truth, frame, mask, curves=curves).items():
                    out[f"{kind}_{k}"] = v
            bar.advance()
            per_view.append(out)
    return {k: float(np.mean([v[k] for v in per_view])) for k in per_view[0]} | {
        "views": len(per_view)}


def _print_summary(summary: dict, frames: Path) -> None:
    serve_stats = summary["serve"]
    device = summary.get("device") or {}
    quality = summary.get("quality") or {}
    strides = ", ".join(f"{n} at stride {s}" if s != "0" else f"{n} with no time for a ray"
                        for s, n in sorted(serve_stats.get("stride_frames", {}).items(),
                                           key=lambda kv: int(kv[0])))
    lines = [
        "",
        "demo summary",
        f"  frames sent      {serve_stats['frames']} corrections of the device's own frames "
        f"({strides or 'no ray-cast'}) at {serve_stats.get('fps', 0) or 0:.0f} frames/s; "
        f"the device presented {device.get('frames_presented', '?')} frames",
        f"  bytes per frame  {serve_stats['bytes_per_frame']:.0f}; link "
        f"{serve_stats['link_bytes_per_s'] / 1024:.1f} KiB/s while streaming",
    ]
    if quality:
        lines.append(f"  object SSIM of {quality['views']} views, and the smallest JPEG / WebP / "
                     "AVIF of each view with the same object SSIM:")
        names = {"own": "the device's own frame (0 B)", "streamed": "streamed (moving)",
                 "rest": "at rest"}
        for kind in _KINDS:
            size = "" if kind == "own" else f" at {quality[f'{kind}_bytes']:.0f} B"
            lines.append(
                f"    {names[kind]:<29} {quality[f'{kind}_object_ssim']:.3f}{size}; JPEG "
                f"{quality[f'{kind}_jpeg_bytes']:.0f} B, WebP {quality[f'{kind}_webp_bytes']:.0f}"
                f" B, AVIF {quality[f'{kind}_avif_bytes']:.0f} B")
        lines.append("  what it depends on: at rest and the own frame, only the model; "
                     "streamed, the host's speed (the frame deadline picks how many pixels "
                     "are ray-cast, so a busy machine streams less and shows its own frame "
                     "more) and the link")
    lines.append(f"  frames           {frames}")
    print("\n".join(lines))
