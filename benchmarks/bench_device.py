"""The device loop (issue 5): frame time, latency, bytes per frame, memory, serial frame rate.

One command, five sections; every figure comes with a baseline measured in the same run,
because the development machine is shared and noisy:

a. **Frame time** at each ``--sizes`` in headless mode, per stage: *decode* (a score packet
   of an orbit, delta-coded, through ``ScoreDecoder``), *reconstruct* (``Reconstructor.update``
   with 1 thread, 2 threads and what the device picks, ``threads="auto"``) and *present*
   (the headless presenter writing nothing, writing a PNG, and a pygame window under SDL's
   dummy driver), as fps. Baselines: one read of the int8 eigenspace (the memory floor) and
   Pillow decoding a JPEG (quality 90) of the same frame. The 1-thread reconstruction is also
   timed in thread CPU time, which other processes on the machine do not inflate.
b. **Latency** from VIEW_REQUEST to frame presented over TCP loopback: ``eigencast-device
   --listen`` as a separate process steps through ``--latency-views`` views (``--views``,
   each requested once its predecessor was shown) while this process serves it
   (:func:`host.link.serving.serve`); percentiles from the device's own statistics. Baseline: the
   compute on the path (host interpolation + encoding, device decode + reconstruction)
   measured in-process in the same run.
c. **Bytes per frame** over an orbit (3 and 0.5 degrees of phi per frame at theta 15), key
   frames only vs key + delta frames, beside the smallest JPEG whose SSIM against the
   ray-cast reaches the reconstruction's (`equal_quality_jpeg`) on a few of
   the orbit's views, ray-cast with the model's own render settings.
d. **Memory**: peak RSS (``VmHWM``) of the device process while it presents
   ``--rss-frames`` frames of an orbit served over TCP, against the eigenspace size (int8
   eigenimages + mean + scales) and against a bare process that imports the device runtime;
   RSS sampled along the run shows whether it grows (bound: 1.2 x eigenspace + 64 MB).
e. **Frames per second over a paced 921600-baud line** (``mem://`` with baud pacing, 8N1 ->
   92160 B/s, host and device in this process, the device taking frames of up to 64 KiB:
   key packets at 512 px pass the serial default of 4 KiB): achieved frame rate, key + delta
   and key only, against the line's capacity divided by the wire bytes per frame.
f. **Cost of the SCORES event tag** (protocol 2, a keyed device) at each ``--sizes``: the
   device's per-frame work, SCORES body decode + score decode + reconstruction (the device's
   threads), with and without ``verify_event`` (truncated HMAC-SHA256 + replay counter),
   the two interleaved frame by frame in the same run (each with its own decoder and
   reconstructor), and the verification alone as a fraction of the untagged frame.
   Target (issue 11): under 5 % of the frame time at 512.

w. **Depth-aware view synthesis** (issue 15, only with ``--warp-image IMAGE``, a standalone
   image fitted with ``--depth``): the standalone device's frame over a drag (3 degrees of phi
   per frame at theta 15) made by `device_runtime.synthesis.ViewSynthesizer` (the
   neighbours' colour and depth reconstructed on a cache miss, warped, blended, holes
   filled) against today's blended standalone frame (`StandaloneScores` +
   ``Reconstructor.update``, threads "auto") on the same views in the same run; the ratio,
   the median and mean CPU time of both (all threads: less sensitive to the shared cores'
   load than wall time), the cache misses, the synthesized frame of a display-rate orbit (1
   degree a frame: ``--orbit turn:12`` at 30 frames a second) and the frames a second its
   mean CPU time allows, and the synthesis' declared scratch (`synthesis_memory_bytes`) and
   depth sections. Targets: < 40 ms at 512 (issue 15); within 2x the blended frame on one
   core (issue 22: run under ``OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 taskset -c 0``).
   With ``--rss-frames N`` also the peak RSS (``VmHWM``) of a real ``eigencast-device
   --standalone`` process showing N orbit frames of the image (and of ``--warp-baseline``,
   the model without depth), against the issue's bound: (d)'s plus
   the image's other sections (the standalone table) and its depth sections (the synthesis'
   working set must fit inside it); and against the bare runtime process plus what the
   image declares it needs (`required_ram_bytes`, with the synthesis scratch). With
   ``--served-rss`` also a served device on the one served path: ``serve`` as it is by
   default, driving one turn of an orbit, sends a correction of the device's own frame of
   each new view, which the device makes (the warp worker's warp for an image with depth)
   and corrects (`Reconstructor.correct`).

x. **Cost of a correction** (issue 23, only with ``--correction-images A.ecs[,B.ecs...]``,
   standalone images): ``Reconstructor.correct`` of the corrections the host really sends
   (moving at ``--correction-stride``, complete at rest) against the blend of a new view,
   interleaved on one reconstructor; `device_correction` (run it pinned to one core).

Models. Real ones where it matters: ``--volume`` (default the shared vismale_head if
present, else ``builtin:head``) rendered from ``--views`` (default ``grid:36x7``) at each of
``--real-sizes`` (default 256 and 512) into ``--work`` (default ``bench-out/device``) and
fitted adaptive (cells 30, T = 0.98), signed with ``WORK/device.key``; both steps are cached
(a model present in ``--work`` for any size is used). Sizes without a real model (1080 by
default) get a *synthetic* eigenspace of realistic size for section (a) only (speed does not
depend on the values): the one of ``bench_reconstruct.py`` (30 px cells, 30 % empty, 20..60
components).

Targets (issue 5): 512x512 >= 100 fps reconstruction and latency < 30 ms; 1080x1080 >= 30 fps;
delta frames <= 1/4 of the equal-quality JPEG; peak RSS <= 1.2 x eigenspace + 64 MB, flat.

Run: ``.venv/bin/python benchmarks/bench_device.py [--quick] [--work DIR] [--sections abcdef]
[--json]`` (``--quick``: 64 and 96 px models from ``grid:12x4``, few frames: a smoke run).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(HERE))

import numpy as np  # noqa: E402
from bench_reconstruct import floor_read_s, make_eigenspace  # noqa: E402
from PIL import Image  # noqa: E402
from provision_helpers import DeviceProcess, mem_name  # noqa: E402

from device_runtime.display import HeadlessPresenter  # noqa: E402
from device_runtime.reconstruct import Reconstructor  # noqa: E402
from protocol import auth  # noqa: E402
from protocol import messages as m  # noqa: E402
from protocol.scores import ScoreDecoder, encode_scores  # noqa: E402

MB = 1e6
MAX_FRAME = 65536
"""Device frame limit on the paced line (``eigencast-device --max-frame 65536``)."""


# --------------------------------------------------------------------------- models


def default_volume() -> str:
    from host.shared_data import shared_volume

    path = shared_volume("vismale_head")
    return str(path) if path is not None else "builtin:head"


def volume_stem(volume: str) -> str:
    if volume.startswith("builtin:"):
        return volume.split(":", 1)[1]
    name = Path(volume).name
    for suffix in (".gz", ".nhdr", ".nrrd", ".mhd", ".nii", ".raw", ".tif", ".dat"):
        name = name.removesuffix(suffix)
    return name or "volume"


def key_path(work: Path) -> Path:
    from protocol.keys import write_key

    path = work / "device.key"
    if not path.exists():
        write_key(path)
    return path


def model_path(work: Path, stem: str, size: int) -> Path:
    return work / f"{stem}-{size}.ecs"


def ensure_model(work: Path, volume: str, size: int, views: str) -> Path:
    """Render and fit the model for ``size`` unless ``WORK/STEM-SIZE.ecs`` exists."""
    from host.cli import main as eigencast

    stem = volume_stem(volume)
    out = model_path(work, stem, size)
    if out.exists():
        return out
    db = work / f"{stem}-{size}.cdb"
    t0 = time.perf_counter()
    # the blend path this benchmark measures (section w takes an image with depth itself)
    code = eigencast(["render", volume, "-o", str(db), "--views", views, "--size", str(size),
                      "--no-depth"])
    if code:
        raise SystemExit(f"rendering {volume} at {size} px failed (exit {code})")
    t1 = time.perf_counter()
    tmp = out.with_name(out.stem + ".tmp.ecs")
    code = eigencast(["fit", str(db), "-o", str(tmp), "--method", "adaptive", "--cell", "30",
                      "--threshold", "0.98", "--key", str(key_path(work)), "--no-standalone"])
    if code:
        raise SystemExit(f"fitting {db} failed (exit {code})")
    tmp.replace(out)
    print(f"  model {out.name}: render {t1 - t0:.0f} s, fit {time.perf_counter() - t1:.0f} s",
          flush=True)
    return out


def eigenspace_bytes(image: Any) -> int:
    return int(image.eigenimages.nbytes + image.mean.nbytes + image.scales.nbytes)


def rss_bound_bytes(eigenspace: int) -> float:
    """Section (d)'s device memory bound: 1.2 x eigenspace + 64 MiB."""
    return 1.2 * eigenspace + 64 * 2**20


def depth_section_bytes(image: Any) -> int:
    """Bytes of an image's depth eigenspace sections, whichever coding its table has."""
    from device_runtime.synthesis import DEPTH_DELTA_SECTION, DEPTH_SECTIONS

    names = (*DEPTH_SECTIONS, DEPTH_DELTA_SECTION)
    return sum(int(a.nbytes) for name, a in image.sections.items() if name in names)


def orbit_views(n: int, theta: float = 15.0, turns: float = 1.0) -> list[tuple[float, float]]:
    from device_runtime.orbit import parse_orbit

    spec = parse_orbit(f"steps:{n}:{theta:g}:{turns:g}")
    orbit = spec.start(now_s=0.0)
    return [orbit.next_view(0.0) for _ in range(spec.total_steps or n)]


# --------------------------------------------------------------------------- helpers


def med_ms(times: list[float]) -> float:
    return 1e3 * statistics.median(times) if times else float("nan")


def jpeg_decode_s(frame: np.ndarray, repeat: int = 9) -> tuple[float, int]:
    buf = io.BytesIO()
    Image.fromarray(frame).save(buf, format="JPEG", quality=90)
    data = buf.getvalue()
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        with Image.open(io.BytesIO(data)) as im:
            im.load()
        best = min(best, time.perf_counter() - t0)
    return best, len(data)


def bare_rss_bytes() -> int:
    """Peak RSS of a fresh interpreter that imports the device runtime (the baseline)."""
    code = ("import device_runtime.runtime, device_runtime.cli; "
            "print(device_runtime.runtime.peak_rss_bytes())")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=REPO, timeout=60)
    return int(run.stdout.strip() or 0)


def proc_cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of a process so far (None once it is gone)."""
    try:
        with open(f"/proc/{pid}/stat") as handle:
            fields = handle.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def proc_status(pid: int) -> dict[str, int]:
    """VmRSS and VmHWM of a process, bytes (empty once it is gone)."""
    out = {}
    try:
        with open(f"/proc/{pid}/status") as handle:
            for line in handle:
                if line.startswith(("VmRSS:", "VmHWM:")):
                    name, value = line.split(":", 1)
                    out[name] = int(value.split()[0]) * 1024
    except OSError:
        pass
    return out


def read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


class Case:
    """One size: a real model (HostModel) or a synthetic eigenspace."""

    def __init__(self, size: int, path: Path | None, seed: int = 0) -> None:
        self.size = size
        self.path = path
        if path is not None:
            from host.fit.model import HostModel

            self.model = HostModel.load(path)
            self.image = self.model.image
            self.kind = "real"
            self.arrays = {
                "mean": self.image.mean, "eigenimages": self.image.eigenimages,
                "scales": self.image.scales, "n_components": self.image.n_components,
                "image_shape": self.image.image_shape, "cell_shape": self.image.cell_shape,
            }
        else:
            self.model = None
            self.image = None
            self.kind = "synthetic"
            self.arrays = make_eigenspace(size, seed)

    @property
    def n_coefficients(self) -> int:
        return int(self.arrays["eigenimages"].shape[0])

    @property
    def eigenspace_bytes(self) -> int:
        a = self.arrays
        return int(a["eigenimages"].nbytes + a["mean"].nbytes + a["scales"].nbytes)

    def reconstructor(self, threads: int | str) -> Reconstructor:
        a = self.arrays
        return Reconstructor(a["mean"], a["eigenimages"], a["scales"], a["n_components"],
                             a["image_shape"], a["cell_shape"], threads=threads)

    def packets(self, n: int, degrees_per_frame: float = 3.0) -> tuple[list, list]:
        """(score vectors, delta-coded packets) of an orbit of ``n`` frames."""
        if self.model is not None:
            views = orbit_views(round(360 / degrees_per_frame))[:n]
            while len(views) < n:
                views += views[: n - len(views)]
            from host.link.serving import FrameEncoder

            encoder = FrameEncoder(self.model, first_frame=1)  # what `serve` sends
            ys = [self.model.quantized_scores(*v) for v in views]
            return ys, [encoder.encode(v).packet for v in views]
        else:
            rng = np.random.default_rng(1)
            step, digest = 1.0, bytes(32)
            ys = [np.rint(rng.standard_normal(self.n_coefficients) * 100).astype(np.float32)
                  for _ in range(n)]
            views = [(float(i), 15.0) for i in range(n)]
        packets, base = [], None
        for i, (y, view) in enumerate(zip(ys, views, strict=True)):
            base = encode_scores(y, step=step, frame=i + 1, view=view, image_digest=digest,
                                 base=base)
            packets.append(base.packet)
        return ys, packets

    def decoder(self) -> ScoreDecoder:
        digest = self.model.digest if self.model is not None else bytes(32)
        return ScoreDecoder(self.n_coefficients, digest,
                            n_components=self.arrays["n_components"])


# --------------------------------------------------------------------------- (a)


def section_frame_time(case: Case, frames: int, tmp: Path) -> dict:
    ys, packets = case.packets(frames + 1)
    decoder = case.decoder()
    decode = []
    for packet in packets:
        t0 = time.perf_counter()
        decoder.decode(packet)
        decode.append(time.perf_counter() - t0)
    out: dict[str, Any] = {"size": case.size, "model": case.kind,
                           "eigenspace_mb": case.eigenspace_bytes / MB,
                           "n_coefficients": case.n_coefficients,
                           "cells": len(case.arrays["n_components"]),
                           "packet_bytes_mean": float(np.mean([len(p) for p in packets[1:]])),
                           "decode_ms": med_ms(decode[1:])}
    frame = None
    for threads in (1, 2, "auto"):
        rec = case.reconstructor(threads)
        rec.update(ys[0])  # page in, start the helper thread
        wall, cpu, cells = [], [], []
        for y in ys[1:]:
            t0, c0 = time.perf_counter(), time.thread_time()
            rec.update(y)
            wall.append(time.perf_counter() - t0)
            cpu.append(time.thread_time() - c0)
            cells.append(rec.cells_recomputed)
        frame = rec.frame.copy()
        name = f"{threads}" if threads != "auto" else f"auto({rec.threads})"
        out[f"reconstruct_ms_{name}"] = med_ms(wall)
        if threads == 1:
            out["reconstruct_cpu_ms_1"] = med_ms(cpu)
            out["cells_recomputed_fraction"] = float(np.mean(cells)) / out["cells"]
        if threads == "auto":
            out["device_threads"] = rec.threads
            out["reconstruct_ms_device"] = med_ms(wall)
        rec.close()
    assert frame is not None
    floor, _ = floor_read_s(case.arrays["eigenimages"], 7)
    out["floor_ms"] = floor * 1e3
    jpeg, jpeg_bytes = jpeg_decode_s(frame)
    out["jpeg_decode_ms"] = jpeg * 1e3
    out["jpeg_q90_bytes"] = jpeg_bytes
    # present: nothing (headless, no folder), a PNG per frame, a pygame window (dummy driver)
    n_present = max(3, min(frames, 20))
    nothing = HeadlessPresenter(None)
    png = HeadlessPresenter(tmp / f"png-{case.size}", every=1)
    for name, presenter in (("none", nothing), ("png", png)):
        times = []
        for i in range(n_present):
            t0 = time.perf_counter()
            presenter.present(frame, {"frame": i, "phi_deg": 0.0, "theta_deg": 15.0})
            times.append(time.perf_counter() - t0)
        presenter.close()
        out[f"present_ms_{name}"] = med_ms(times)
    out["present_ms_window"] = window_present_ms(frame, n_present)
    best = min(out["reconstruct_ms_1"], out["reconstruct_ms_2"])
    out["device_frame_ms"] = out["decode_ms"] + out["reconstruct_ms_device"] + out[
        "present_ms_none"]
    out["fps_reconstruct_best"] = 1e3 / best
    out["fps_reconstruct_device"] = 1e3 / out["reconstruct_ms_device"]
    out["fps_device_frame"] = 1e3 / out["device_frame_ms"]
    out["ratio_reconstruct_floor"] = best / out["floor_ms"]
    out["ratio_reconstruct_jpeg"] = best / out["jpeg_decode_ms"]
    return out


def window_present_ms(frame: np.ndarray, n: int) -> float | None:
    """Median ``Window.present`` time under SDL's dummy video driver (a subprocess)."""
    with tempfile.TemporaryDirectory() as tmp:
        np.save(Path(tmp) / "f.npy", frame)
        code = (
            "import sys, time, statistics, numpy as np\n"
            "from device_runtime.display import Window\n"
            f"f = np.load({str(Path(tmp) / 'f.npy')!r})\n"
            "w = Window(f.shape[:2], zoom=1.0)\n"
            "t = []\n"
            f"for _ in range({n}):\n"
            "    t0 = time.perf_counter(); w.present(f); t.append(time.perf_counter() - t0)\n"
            "w.close(); print(1e3 * statistics.median(t))\n"
        )
        env = dict(os.environ, SDL_VIDEODRIVER="dummy", PYGAME_HIDE_SUPPORT_PROMPT="1")
        run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             cwd=REPO, env=env, timeout=120)
    try:
        return float(run.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        return None


def print_frame_time(r: dict) -> None:
    print(f"  {r['size']}x{r['size']} ({r['model']}): {r['cells']} cells, K={r['n_coefficients']},"
          f" eigenspace {r['eigenspace_mb']:.1f} MB; {100 * r['cells_recomputed_fraction']:.0f}%"
          f" of cells recomputed per frame")
    print(f"    decode      {r['decode_ms']:7.3f} ms  (packet {r['packet_bytes_mean']:.0f} B)")
    print(f"    reconstruct {r['reconstruct_ms_1']:7.2f} ms 1 thr ({r['reconstruct_cpu_ms_1']:.2f} "
          f"ms CPU) | {r['reconstruct_ms_2']:7.2f} ms 2 thr | device ({r['device_threads']} "
          f"thr) {r['reconstruct_ms_device']:7.2f} ms = {r['fps_reconstruct_device']:.0f} fps")
    window = r["present_ms_window"]
    print(f"    present     {r['present_ms_none']:7.3f} ms headless | {r['present_ms_png']:7.2f} "
          f"ms PNG | " + (f"{window:.2f} ms window (SDL dummy)" if window is not None
                          else "window n/a"))
    print(f"    device frame (decode + reconstruct + headless present) {r['device_frame_ms']:.2f} "
          f"ms = {r['fps_device_frame']:.0f} fps")
    print(f"    baselines: floor {r['floor_ms']:.2f} ms, JPEG q90 decode {r['jpeg_decode_ms']:.2f} "
          f"ms ({r['jpeg_q90_bytes']} B); best reconstruct / floor "
          f"{r['ratio_reconstruct_floor']:.1f}x, / JPEG decode {r['ratio_reconstruct_jpeg']:.1f}x")


# --------------------------------------------------------------------------- (f)


def section_tag_cost(case: Case, frames: int) -> dict:
    """Per-frame device work with and without the SCORES event tag, interleaved."""
    _, packets = case.packets(frames + 1)
    session_key = os.urandom(32)
    plain = [m.Scores(sequence=i, packet=p).to_body() for i, p in enumerate(packets)]
    tagged = [auth.tag_event(m.Scores(sequence=i, packet=p), session_key, i + 1).to_body()
              for i, p in enumerate(packets)]
    runs = {"plain": (case.decoder(), case.reconstructor("auto"), plain, []),
            "tagged": (case.decoder(), case.reconstructor("auto"), tagged, [])}
    verify: list[float] = []
    for i in range(len(packets)):
        for name in (("plain", "tagged") if i % 2 else ("tagged", "plain")):
            decoder, rec, bodies, times = runs[name]
            t0 = time.perf_counter()
            msg = m.Scores.from_body(bodies[i])
            if name == "tagged":
                t1 = time.perf_counter()
                auth.verify_event(msg, session_key, i)
                verify.append(time.perf_counter() - t1)
            rec.update(decoder.decode(msg.packet).y)
            times.append(time.perf_counter() - t0)
    for _, rec, _, _ in runs.values():
        rec.close()
    plain_ms, tagged_ms = med_ms(runs["plain"][3][1:]), med_ms(runs["tagged"][3][1:])
    verify_ms = med_ms(verify[1:])
    return {"size": case.size, "model": case.kind, "frames": frames,
            "packet_bytes_mean": float(np.mean([len(p) for p in packets[1:]])),
            "frame_ms_plain": plain_ms, "frame_ms_tagged": tagged_ms, "verify_ms": verify_ms,
            "ratio_tagged_plain": tagged_ms / plain_ms,
            "verify_fraction": verify_ms / plain_ms}


def print_tag_cost(r: dict) -> None:
    print(f"  {r['size']}x{r['size']} ({r['model']}, packets {r['packet_bytes_mean']:.0f} B): "
          f"frame {r['frame_ms_plain']:.3f} ms untagged, {r['frame_ms_tagged']:.3f} ms tagged "
          f"(ratio {r['ratio_tagged_plain']:.3f}); verify_event {1e3 * r['verify_ms']:.1f} us "
          f"= {100 * r['verify_fraction']:.2f} % of the frame")


# --------------------------------------------------------------------------- devices


def provisioned_flash(case: Case, work: Path) -> Path:
    """A flash folder holding ``case``'s image (provisioned over TCP once, then reused)."""
    from host.link.options import ProvisionOptions, ProvisionParts
    from host.link.provisioning import provision
    from protocol.keys import load_key

    flash = work / f"flash-{case.path.stem}"
    marker = flash / ".bench-digest"
    digest = case.model.digest.hex()
    if marker.exists() and marker.read_text() == digest:
        return flash
    shutil.rmtree(flash, ignore_errors=True)
    keyf = key_path(work)
    device = DeviceProcess(flash, "--headless", "--ram-budget", "1024", "--flash-size",
                           str(max(64, int(2 * case.path.stat().st_size / MB) + 8)),
                           key_file=keyf)
    try:
        provision(case.path, device.url, ProvisionOptions(key=load_key(keyf), show_progress=False),
                  ProvisionParts(log=lambda line: None))
    finally:
        device.stop()
    marker.write_text(digest)
    return flash


def host_compute_ms(case: Case, views: list[tuple[float, float]]) -> float:
    """Median time the host spends per answered request: interpolate, quantize, encode."""
    from host.link.serving import FrameEncoder

    encoder = FrameEncoder(case.model)
    times = []
    for view in views:
        t0 = time.perf_counter()
        encoder.encode(view)
        times.append(time.perf_counter() - t0)
    return med_ms(times[1:])


def section_latency(case: Case, work: Path, n_views: int, frame: dict | None) -> dict:
    from host.link.options import ServeOptions, ServeParts
    from host.link.serving import serve
    from protocol.keys import load_key

    flash = provisioned_flash(case, work)
    rng = np.random.default_rng(7)
    views = [(round(float(p), 1), round(float(t), 1))
             for p, t in zip(rng.uniform(0, 360, n_views), rng.uniform(-30, 60, n_views),
                             strict=True)]
    stats_path = work / f"latency-{case.size}.json"
    stats_path.unlink(missing_ok=True)
    keyf = key_path(work)
    listing = ";".join(f"{p:g},{t:g}" for p, t in views)
    device = DeviceProcess(flash, "--headless", "--ram-budget", "1024", "--views", listing,
                           "--request-rate", "1000", "--stats", str(stats_path),
                           key_file=keyf)
    t0 = time.perf_counter()
    try:
        serve(case.path, device.url,
              ServeOptions(key=load_key(keyf), fps=0, reconnect=False, stats_every_s=0),
              ServeParts(log=lambda line: None, model=case.model))
    finally:
        rc = device.stop()
    wall = time.perf_counter() - t0
    stats = read_json(stats_path)
    host_ms = host_compute_ms(case, views[: min(30, len(views))])
    out = {"size": case.size, "views": n_views, "device_rc": rc, "wall_s": wall,
           "samples": stats.get("latency_samples"),
           "p50_ms": stats.get("latency_ms_p50"), "p90_ms": stats.get("latency_ms_p90"),
           "p99_ms": stats.get("latency_ms_p99"), "max_ms": stats.get("latency_ms_max"),
           "mean_ms": stats.get("latency_ms_mean"),
           "device_decode_ms": stats.get("decode_ms"),
           "device_reconstruct_ms": stats.get("reconstruct_ms"),
           "host_encode_ms": host_ms}
    if frame is not None:
        compute = host_ms + frame["decode_ms"] + frame["reconstruct_ms_device"]
        out["compute_ms"] = compute
        if out["p50_ms"] is not None:
            out["ratio_p50_compute"] = out["p50_ms"] / compute
    return out


def print_latency(r: dict) -> None:
    if r.get("p50_ms") is None:
        print(f"  {r['size']}: no latency samples (device exit {r['device_rc']})")
        return
    print(f"  {r['size']}x{r['size']}: {r['samples']} requests: p50 {r['p50_ms']:.1f} ms, p90 "
          f"{r['p90_ms']:.1f} ms, p99 {r['p99_ms']:.1f} ms, max {r['max_ms']:.1f} ms "
          f"(mean {r['mean_ms']:.1f})")
    if "compute_ms" in r:
        print(f"    compute on the path (host encode {r['host_encode_ms']:.2f} + decode + "
              f"reconstruct) {r['compute_ms']:.2f} ms: p50 / compute {r['ratio_p50_compute']:.2f}"
              f"; in the device process: decode {r['device_decode_ms'] or 0:.2f} ms, "
              f"reconstruct {r['device_reconstruct_ms'] or 0:.2f} ms")


# --------------------------------------------------------------------------- (c)


def equal_quality_jpeg(reference: np.ndarray, test: np.ndarray) -> dict[str, float]:
    """``test``'s SSIM against ``reference`` and the smallest JPEG of ``reference`` that
    reaches it (`host.evaluate.baselines.CodecLadder`; the best quality when none does)."""
    from skimage.metrics import structural_similarity

    from host.evaluate.baselines import MAX_QUALITY, CodecLadder

    def ssim(decoded: np.ndarray, name: str) -> dict[str, float]:
        return {name: float(structural_similarity(reference, decoded, data_range=255,
                                                  channel_axis=-1))}

    target = ssim(test, "ssim")["ssim"]
    ladder = CodecLadder(reference, "jpeg", ssim)
    coded = ladder.smallest(target, "ssim") or ladder.file(MAX_QUALITY)
    return {"ssim": target, "jpeg_quality": coded.quality, "jpeg_bytes": coded.size_bytes,
            "jpeg_ssim": ladder.value(coded.quality, "ssim")}


def section_bytes(case: Case, jpeg_views: int) -> dict:
    from host.link.serving import FrameEncoder
    from host.render.settings import RenderSettings, ViewRenderer

    out: dict[str, Any] = {"size": case.size}
    for label, n in (("3deg", 120), ("0.5deg", 720)):
        views = orbit_views(n)
        for mode, interval in (("key", 1), ("delta", 0)):
            encoder = FrameEncoder(case.model, keyframe_interval=interval, first_frame=1)
            sizes = [len(encoder.encode(v).packet) for v in views]
            out[f"{mode}_{label}_bytes"] = float(np.mean(sizes))
    renderer = ViewRenderer.open(RenderSettings.from_record(case.model.render_settings,
                                                            what="bench model"),
                                 None, None, what="bench model")
    pick = orbit_views(120)[:: max(1, 120 // jpeg_views)][:jpeg_views]
    rows = []
    for phi, theta in pick:
        truth = renderer.render_rgb8(phi, theta)
        rows.append(equal_quality_jpeg(truth, case.model.view(phi, theta)))
    out["jpeg_views"] = len(rows)
    out["ssim"] = float(np.mean([r["ssim"] for r in rows]))
    out["jpeg_bytes"] = float(np.mean([r["jpeg_bytes"] for r in rows]))
    out["jpeg_quality"] = [int(r["jpeg_quality"]) for r in rows]
    out["jpeg_ssim"] = float(np.mean([r["jpeg_ssim"] for r in rows]))
    for label in ("3deg", "0.5deg"):
        for mode in ("key", "delta"):
            out[f"ratio_{mode}_{label}_jpeg"] = out[f"{mode}_{label}_bytes"] / out["jpeg_bytes"]
    return out


def print_bytes(r: dict) -> None:
    print(f"  {r['size']}x{r['size']}: reconstruction SSIM {r['ssim']:.3f} vs ray-cast; "
          f"equal-quality JPEG {r['jpeg_bytes']:.0f} B (qualities {r['jpeg_quality']}, SSIM "
          f"{r['jpeg_ssim']:.3f}, {r['jpeg_views']} views)")
    for label in ("3deg", "0.5deg"):
        print(f"    orbit {label:>6}/frame: key only {r[f'key_{label}_bytes']:7.0f} B "
              f"({r[f'ratio_key_{label}_jpeg']:.2f}x JPEG) | key+delta "
              f"{r[f'delta_{label}_bytes']:7.0f} B ({r[f'ratio_delta_{label}_jpeg']:.2f}x JPEG)")


# --------------------------------------------------------------------------- (d)


def section_rss(case: Case, work: Path, frames: int, bare: int) -> dict:
    from host.link.options import ServeOptions, ServeParts
    from host.link.serving import serve
    from protocol.keys import load_key

    flash = provisioned_flash(case, work)
    stats_path = work / f"rss-{case.size}.json"
    stats_path.unlink(missing_ok=True)
    keyf = key_path(work)
    device = DeviceProcess(flash, "--headless", "--ram-budget", "1024", "--max-frames",
                           str(frames), "--stats", str(stats_path), key_file=keyf)
    samples: list[tuple[float, int]] = []
    done = threading.Event()

    def sample() -> None:
        while not done.is_set():
            rss = proc_status(device.proc.pid).get("VmRSS")
            stats = read_json(stats_path)
            if rss:
                samples.append((stats.get("frames_presented", 0), rss))
            done.wait(0.25)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    from device_runtime.orbit import parse_orbit

    t0 = time.perf_counter()
    hwm = 0
    try:
        def watch() -> None:
            nonlocal hwm
            while device.proc.poll() is None:
                hwm = max(hwm, proc_status(device.proc.pid).get("VmHWM", 0))
                time.sleep(0.05)

        watcher = threading.Thread(target=watch, daemon=True)
        watcher.start()
        serve(case.path, device.url,
              ServeOptions(key=load_key(keyf), orbit=parse_orbit("turn:12:15"), fps=400,
                           reconnect=False, stats_every_s=0),
              ServeParts(log=lambda line: None, model=case.model))
    finally:
        rc = device.stop()
        done.set()
        sampler.join(5)
    wall = time.perf_counter() - t0
    stats = read_json(stats_path)
    presented = int(stats.get("frames_presented", 0))
    peak = max(hwm, int(stats.get("peak_rss_bytes") or 0))  # both VmHWM (not ru_maxrss)
    eig = case.eigenspace_bytes
    bound = rss_bound_bytes(eig)
    warm = [rss for f, rss in samples if f >= 0.1 * presented] or [rss for _, rss in samples]
    first, last = (warm[0], warm[-1]) if warm else (0, 0)
    return {"size": case.size, "frames": presented, "device_rc": rc, "wall_s": wall,
            "fps": presented / wall if wall else 0.0, "eigenspace_mb": eig / MB,
            "peak_rss_mb": peak / MB, "bound_mb": bound / MB, "bare_rss_mb": bare / MB,
            "ratio_peak_eigenspace": peak / eig, "ratio_peak_bound": peak / bound,
            "ratio_over_bare_eigenspace": (peak - bare) / eig,
            "rss_after_10pct_mb": first / MB, "rss_end_mb": last / MB,
            "rss_growth_mb": (last - first) / MB, "rss_samples": len(samples),
            "decode_ms": stats.get("decode_ms"), "reconstruct_ms": stats.get("reconstruct_ms"),
            "present_ms": stats.get("present_ms")}


def print_rss(r: dict) -> None:
    ok = "within" if r["ratio_peak_bound"] <= 1 else "OVER"
    print(f"  {r['size']}x{r['size']}: eigenspace {r['eigenspace_mb']:.1f} MB; device peak RSS "
          f"{r['peak_rss_mb']:.1f} MB = {r['ratio_peak_eigenspace']:.2f}x eigenspace, "
          f"{r['ratio_peak_bound']:.2f}x the bound {r['bound_mb']:.1f} MB ({ok}); bare runtime "
          f"process {r['bare_rss_mb']:.1f} MB, (peak - bare) / eigenspace "
          f"{r['ratio_over_bare_eigenspace']:.2f}")
    print(f"    {r['frames']} frames presented in {r['wall_s']:.0f} s ({r['fps']:.0f} fps, stages "
          f"decode {r['decode_ms'] or 0:.2f} / reconstruct {r['reconstruct_ms'] or 0:.2f} / "
          f"present {r['present_ms'] or 0:.3f} ms); RSS after 10% {r['rss_after_10pct_mb']:.1f}"
          f" MB, at the end {r['rss_end_mb']:.1f} MB (growth {r['rss_growth_mb']:+.2f} MB, "
          f"{r['rss_samples']} samples)")


# --------------------------------------------------------------------------- (e)


def section_serial(case: Case, work: Path, seconds: float, baud: int) -> dict:
    from runtime_helpers import RuntimeThread

    from device_runtime.device import DeviceConfig
    from device_runtime.orbit import parse_orbit
    from host.link.options import ServeOptions, ServeParts
    from host.link.serving import serve
    from protocol.keys import load_key

    src = provisioned_flash(case, work)
    key = load_key(key_path(work))
    out: dict[str, Any] = {"size": case.size, "baud": baud, "line_bytes_per_s": baud / 10}
    for mode, interval in (("delta", 0), ("key", 1)):
        with tempfile.TemporaryDirectory() as tmp:
            flash = Path(tmp) / "flash"
            shutil.copytree(src, flash)
            name = mem_name("bench-dev")
            # the serial default of 4 KiB frames is too small for key packets at 512 px
            config = DeviceConfig(flash_dir=flash, key=key, ram_budget_bytes=2**30,
                                  max_frame_bytes=MAX_FRAME)
            rt = RuntimeThread(flash, f"mem://{name}?end=b", baud=baud, config=config)
            try:
                stats = serve(case.path, f"mem://{name}?end=a",
                              ServeOptions(baud=baud, key=key, orbit=parse_orbit("turn:12:15"),
                                           fps=0, keyframe_interval=interval, duration_s=seconds,
                                           stats_every_s=0, reconnect=False),
                              ServeParts(log=lambda line: None, model=case.model))
                presented = rt.device.runtime_stats.frames_presented
            finally:
                rt.stop()
        wire = stats.wire_bytes_sent / max(stats.frames, 1)  # framing included
        out[f"{mode}_fps"] = stats.fps
        out[f"{mode}_presented"] = presented
        out[f"{mode}_bytes_per_frame"] = stats.bytes_per_frame
        out[f"{mode}_wire_bytes_per_frame"] = wire
        out[f"{mode}_capacity_fps"] = (baud / 10) / wire
        out[f"{mode}_ratio_capacity"] = stats.fps / out[f"{mode}_capacity_fps"]
        out[f"{mode}_link_bytes_per_s"] = stats.link_bytes_per_s
    return out


def print_serial(r: dict) -> None:
    print(f"  {r['size']}x{r['size']} over {r['baud']} baud ({r['line_bytes_per_s']:.0f} B/s, "
          f"device --max-frame {MAX_FRAME}):")
    for mode in ("delta", "key"):
        print(f"    {'key+delta' if mode == 'delta' else 'key only':>9}: {r[f'{mode}_fps']:6.1f} "
              f"fps ({r[f'{mode}_bytes_per_frame']:.0f} B/packet, "
              f"{r[f'{mode}_wire_bytes_per_frame']:.0f} B/frame on the wire, link "
              f"{r[f'{mode}_link_bytes_per_s'] / 1024:.1f} KiB/s); line capacity "
              f"{r[f'{mode}_capacity_fps']:.1f} fps -> {r[f'{mode}_ratio_capacity']:.2f}")


# --------------------------------------------------------------------------- main


def section_warp(path: Path, frames: int) -> dict:
    """(w): synthesized vs blended standalone frames over the same drag, and the display-rate
    orbit's synthesized frame."""
    from device_runtime.image_receiver import required_ram_bytes
    from device_runtime.standalone import StandaloneScores
    from device_runtime.synthesis import ViewSynthesizer, synthesis_memory_bytes
    from protocol.image import read_image, read_manifest

    image = read_image(path, read_annex=False)
    standalone = StandaloneScores(image)
    blend = Reconstructor.from_image(image, threads="auto")
    synth = ViewSynthesizer(image, standalone, Reconstructor.from_image(image, threads="auto"))
    # a 3 degree/frame drag: 120 steps per turn, ``frames`` of them
    views = orbit_views(120, theta=15.0, turns=frames / 120.0)
    t_blend, t_warp = [], []
    synth.frame(*views[0])  # the first view's neighbours: a cold start, timed apart below
    misses0 = synth.misses
    c_blend, c_warp = [], []  # CPU seconds (all threads): less sensitive to the load
    for view in views:
        c0, t0 = time.process_time(), time.perf_counter()
        blend.update(standalone.scores(*view))
        c1, t1 = time.process_time(), time.perf_counter()
        synth.frame(*view)
        c2, t2 = time.process_time(), time.perf_counter()
        t_blend.append(t1 - t0)
        t_warp.append(t2 - t1)
        c_blend.append(c1 - c0)
        c_warp.append(c2 - c1)
    misses = (synth.misses - misses0) / len(views)
    # a standalone device's orbit (``--orbit turn:12``: 30 degrees a second) at 30 frames a
    # second moves 1 degree a frame
    orbit = orbit_views(360, theta=15.0, turns=frames / 360.0)
    synth.frame(*orbit[0])
    misses0, c_orbit = synth.misses, []
    for view in orbit:
        c0 = time.process_time()
        synth.frame(*view)
        c_orbit.append(time.process_time() - c0)
    cold = ViewSynthesizer(image, standalone, Reconstructor.from_image(image, threads="auto"))
    t0 = time.perf_counter()
    cold.frame(*views[-1])
    cold_ms = (time.perf_counter() - t0) * 1e3
    manifest = read_manifest(path)
    depth_bytes = depth_section_bytes(image)
    return {"size": image.image_shape[0], "frames": len(views),
            "blend_ms": med_ms(t_blend), "warp_ms": med_ms(t_warp),
            "warp_p90_ms": float(np.percentile(t_warp, 90) * 1e3),
            "ratio": med_ms(t_warp) / med_ms(t_blend), "cold_ms": cold_ms,
            "blend_cpu_ms": med_ms(c_blend), "warp_cpu_ms": med_ms(c_warp),
            "cpu_ratio": med_ms(c_warp) / med_ms(c_blend),
            "blend_cpu_mean_ms": 1e3 * statistics.mean(c_blend),
            "warp_cpu_mean_ms": 1e3 * statistics.mean(c_warp),
            "misses_per_frame": misses,
            "orbit_cpu_ms": med_ms(c_orbit), "orbit_cpu_mean_ms": 1e3 * statistics.mean(c_orbit),
            "orbit_misses_per_frame": (synth.misses - misses0) / len(orbit),
            "depth_sections_bytes": depth_bytes,
            "synthesis_scratch_bytes": synthesis_memory_bytes(manifest),
            "required_ram_bytes": required_ram_bytes(manifest)}


def _unkeyed_flash_holding(path: Path, work: Path) -> Path:
    """A fresh flash folder under ``work`` holding ``path``'s image, provisioned to an
    unkeyed device over loopback (the image need not be signed: memory, not trust)."""
    from host.link.options import ProvisionOptions, ProvisionParts
    from host.link.provisioning import provision

    work.mkdir(parents=True, exist_ok=True)
    flash = work / f"flash-rss-{path.stem}"
    shutil.rmtree(flash, ignore_errors=True)
    device = DeviceProcess(flash, "--headless", "--insecure", "--ram-budget", "1024",
                           "--flash-size", str(max(64, int(2 * path.stat().st_size / MB) + 8)))
    try:
        provision(path, device.url, ProvisionOptions(insecure=True, show_progress=False),
                  ProvisionParts(log=lambda line: None))
    finally:
        device.stop()
    return flash


def section_warp_rss(path: Path, work: Path, frames: int, bare: int,
                     served: bool = False) -> dict:
    """(w, memory): peak RSS of a real ``eigencast-device --standalone`` process showing
    ``frames`` frames of an orbit from ``path``, against the device bound of (d) plus what
    the image adds: its extra sections as held in memory (the standalone score table, the
    depth eigenspace); and against the bare runtime process plus what the image declares it
    needs (`required_ram_bytes`, with the synthesis scratch). With ``served`` the device is
    served on the one served path instead: ``serve`` as it is by default drives one turn of
    an orbit (12 s) and sends a correction of the device's own frame of each view, which the
    device makes (its warp worker's warp, with its own reconstructor, for an image with
    depth; else the blend) and corrects (`Reconstructor.correct`)."""
    from device_runtime.image_receiver import required_ram_bytes
    from device_runtime.synthesis import synthesis_memory_bytes
    from protocol.image import read_image, read_manifest

    flash = _unkeyed_flash_holding(path, work)
    image = read_image(path, read_annex=False)
    manifest = read_manifest(path)
    eig = eigenspace_bytes(image)
    depth = depth_section_bytes(image)
    table = sum(int(a.nbytes) for a in image.sections.values()) - depth
    scratch = synthesis_memory_bytes(manifest) if depth else 0
    declared = required_ram_bytes(manifest)
    stats_path = work / f"rss-warp-{path.stem}.json"
    stats_path.unlink(missing_ok=True)
    # served: the host drives one turn of an orbit (12 s), however many frames: every packet
    # is a correction of the device's own frame of a new view, which the device makes (the
    # warp, on its worker) and corrects; a device-driven orbit's view moves on every display
    # refresh, so the host's corrections arrive for views already left and none is applied
    cap = max(frames, 100_000) if served else frames
    run = ["--headless", *([] if served else ["--orbit", "turn:12:15"]), "--max-frames",
           str(cap), "--stats", str(stats_path), "--ram-budget", "1024"]
    t0 = time.perf_counter()
    served_stats: list[Any] = []  # serve's statistics (served)
    if served:
        from device_runtime.orbit import parse_orbit
        from host.link.options import ServeOptions, ServeParts
        from host.link.serving import serve

        device = DeviceProcess(flash, "--insecure", *run)
        proc = device.proc
        stop = threading.Event()
        failed: list[BaseException] = []

        def host() -> None:
            try:
                served_stats.append(serve(path, device.url,
                                          ServeOptions(insecure=True, reconnect=False,
                                                       orbit=parse_orbit("turn:12:15:1"),
                                                       stats_every_s=0),
                                          ServeParts(stop=stop, log=lambda line: None)))
            except BaseException as exc:  # reported below
                failed.append(exc)

        thread = threading.Thread(target=host, daemon=True)
        thread.start()
    else:
        cmd = [sys.executable, "-m", "device_runtime.cli", "--standalone", "--flash",
               str(flash), *run]
        proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE, text=True)
    hwm, cpu = 0, 0.0
    while proc.poll() is None and (not served or thread.is_alive()):
        hwm = max(hwm, proc_status(proc.pid).get("VmHWM", 0))
        cpu = proc_cpu_s(proc.pid) or cpu  # the last reading before it exits
        time.sleep(0.05)
    if served:  # the host's orbit is over: the device stops (SIGTERM writes its stats)
        stop.set()
        thread.join(30)
        hwm = max(hwm, proc_status(proc.pid).get("VmHWM", 0))
        device.stop()
        err = "\n".join(device.lines[-3:] + [repr(e) for e in failed])
        if failed:
            print(f"    serve failed: {failed[0]!r}"[:300], flush=True)
    else:
        err = proc.stderr.read() if proc.stderr else ""
    rc = proc.returncode
    wall = time.perf_counter() - t0
    if rc != 0:
        raise RuntimeError(f"device exited {rc}: {err.strip()[-300:]}")
    stats = read_json(stats_path)
    peak = max(hwm, int(stats.get("peak_rss_bytes") or 0))
    # issue 15's criterion: (d)'s bound plus the sections the image adds (the synthesis'
    # scratch is what must fit inside it; the image declares it, compared below)
    bound = rss_bound_bytes(eig) + table + depth
    shutil.rmtree(flash, ignore_errors=True)
    return {"image": path.name, "size": image.image_shape[0], "served": served,
            "frames": int(stats.get("frames_presented", 0)), "wall_s": wall,
            "warped_frames": int(stats.get("synthesized_frames", 0)),
            "host_frames": int(stats.get("packets", 0)), "device_cpu_s": cpu,
            "corrected_frames": int(stats.get("corrected_frames", 0)),
            "host_corrections": served_stats[0].correction_frames if served_stats else 0,
            "eigenspace_mb": eig / MB, "depth_sections_mb": depth / MB, "table_mb": table / MB,
            "declared_mb": declared / MB, "ratio_peak_declared": peak / (bare + declared),
            "synthesis_scratch_mb": scratch / MB, "peak_rss_mb": peak / MB,
            "bound_mb": bound / MB, "ratio_peak_bound": peak / bound, "bare_rss_mb": bare / MB,
            "reconstruct_ms": stats.get("reconstruct_ms")}


def print_warp_rss(r: dict) -> None:
    ok = "within" if r["ratio_peak_bound"] <= 1 else "OVER"
    kind = (f"served ({r['warped_frames']} warps shown, {r['host_frames']} host packets "
            f"received, {r.get('corrected_frames', 0)} corrected frames shown)"
            if r["served"] else "standalone")
    print(f"  {r['image']}: {r['frames']} {kind} frames in {r['wall_s']:.0f} s (device CPU "
          f"{r['device_cpu_s']:.1f} s); device peak "
          f"RSS {r['peak_rss_mb']:.1f} MB, {r['ratio_peak_bound']:.2f}x the bound "
          f"{r['bound_mb']:.1f} MB ({ok}: 1.2 x eigenspace {r['eigenspace_mb']:.1f} MB + 64 MiB"
          f" + other sections {r['table_mb']:.1f} MB + depth sections "
          f"{r['depth_sections_mb']:.1f} MB); {r['ratio_peak_declared']:.2f}x the bare "
          f"runtime process {r['bare_rss_mb']:.1f} MB + the image's declared "
          f"{r['declared_mb']:.1f} MB (synthesis scratch {r['synthesis_scratch_mb']:.1f} MB "
          "of it)", flush=True)


def print_warp(r: dict) -> None:
    print(f"  {r['size']:>5} px: blended {r['blend_ms']:.1f} ms, synthesized "
          f"{r['warp_ms']:.1f} ms (p90 {r['warp_p90_ms']:.1f}, cold {r['cold_ms']:.0f}) = "
          f"{r['ratio']:.1f}x (CPU {r['blend_cpu_ms']:.1f} vs {r['warp_cpu_ms']:.1f} ms = "
          f"{r['cpu_ratio']:.2f}x; means {r['blend_cpu_mean_ms']:.1f} vs "
          f"{r['warp_cpu_mean_ms']:.1f} ms); {r['misses_per_frame']:.2f} neighbour "
          f"reconstructions per frame; a 1 degree/frame orbit: CPU {r['orbit_cpu_ms']:.1f} ms "
          f"(mean {r['orbit_cpu_mean_ms']:.1f}, {1e3 / r['orbit_cpu_mean_ms']:.0f} frames/s), "
          f"{r['orbit_misses_per_frame']:.2f} reconstructions per frame; depth sections "
          f"{r['depth_sections_bytes'] / MB:.1f} MB, synthesis scratch "
          f"{r['synthesis_scratch_bytes'] / MB:.1f} MB (image needs "
          f"{r['required_ram_bytes'] / MB:.1f} MB)", flush=True)


def _rows(items: list, measure: Callable[[Any], dict], show: Callable[[dict], None]) -> list[dict]:
    """A section's rows: ``measure`` of each item in turn, each row shown as soon as it is
    measured."""
    rows = []
    for item in items:
        rows.append(measure(item))
        show(rows[-1])
    return rows


def main_correction(args: argparse.Namespace) -> int:
    """Section x alone (`device_correction`)."""
    from device_correction import print_correction, section_correction

    if not args.correction_images:
        print("bench_device: --sections x needs --correction-images A.ecs[,B.ecs]",
              file=sys.stderr)
        return 2
    paths = [Path(p) for p in args.correction_images.split(",") if p]
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        print(f"bench_device: no such image: {', '.join(missing)}", file=sys.stderr)
        return 2
    views = args.frames or (3 if args.quick else 8)
    print(f"(x) correction vs blend, median of {views} drag views x 3, one reconstructor "
          f"thread; OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', '-')}, "
          f"CPUs {sorted(os.sched_getaffinity(0))}, load {os.getloadavg()[0]:.1f}", flush=True)
    rows = _rows(paths, lambda path: section_correction(path, views, args.correction_stride),
                 print_correction)
    if args.json:
        print(json.dumps({"correction": rows}, default=float))
    return 0


def parse_sizes(text: str) -> list[int]:
    return [int(s) for s in text.split(",") if s.strip()]


def _parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke run: tiny models, few frames")
    parser.add_argument("--work", type=Path, default=REPO / "bench-out" / "device")
    parser.add_argument("--volume", default=None)
    parser.add_argument("--views", default=None, help="training views (default grid:36x7)")
    parser.add_argument("--sizes", default=None, help="frame-time sizes (default 256,512,1080)")
    parser.add_argument("--real-sizes", default=None,
                        help="sizes to render and fit a model for (default 256,512)")
    parser.add_argument("--frames", type=int, default=None, help="frames timed per size")
    parser.add_argument("--latency-views", type=int, default=None)
    parser.add_argument("--rss-frames", type=int, default=None)
    parser.add_argument("--serial-seconds", type=float, default=None)
    parser.add_argument("--baud", type=int, default=921600)
    parser.add_argument("--jpeg-views", type=int, default=None)
    parser.add_argument("--sections", default="abcdef")
    parser.add_argument("--json", action="store_true", help="print one JSON object at the end")
    parser.add_argument("--warp-image", type=Path, default=None,
                        help="section w: a standalone image fitted with --depth")
    parser.add_argument("--served-rss", action="store_true",
                        help="section w with --rss-frames: also a served device (its own "
                             "orbit, serve's corrections of its own frames; needs the "
                             "model's volume for the host's ray-casts)")
    parser.add_argument("--warp-baseline", type=Path, default=None,
                        help="section w with --rss-frames: the same model without depth, "
                             "whose standalone process is measured beside it")
    parser.add_argument("--correction-images", default=None,
                        help="section x: comma-separated standalone images (.ecs with annex)")
    parser.add_argument("--correction-stride", type=int, default=4,
                        help="section x: the moving corrections' sample stride")
    return parser.parse_args()


def main_warp(args: argparse.Namespace) -> int:
    """Section w: the standalone frame, synthesized vs blended (and the devices' peak RSS
    with --rss-frames)."""
    frames = args.frames or 40
    print(f"(w) standalone frame: synthesized (warp by depth) vs blended, median of "
          f"{frames} drag frames; load {os.getloadavg()[0]:.1f}", flush=True)
    row = section_warp(args.warp_image, frames)
    print_warp(row)
    out: dict[str, Any] = {"warp": row}
    if args.rss_frames:
        bare = bare_rss_bytes()
        rows = []
        for served in (False, True) if args.served_rss else (False,):
            print(f"(w) device peak RSS, {'served' if served else 'standalone'} process, "
                  f"{args.rss_frames} orbit frames", flush=True)
            for path in [args.warp_image, *([args.warp_baseline] if args.warp_baseline
                                            else [])]:
                rows.append(section_warp_rss(path, args.work, args.rss_frames, bare,
                                             served=served))
                print_warp_rss(rows[-1])
        out["warp_rss"] = rows
    if args.json:
        print(json.dumps(out))
    return 0


def main() -> int:
    args = _parse_args()
    if args.sections == "x":
        return main_correction(args)
    if args.warp_image is not None and args.sections == "w":
        return main_warp(args)
    q = args.quick
    volume = args.volume or ("builtin:head" if q else default_volume())
    views = args.views or ("grid:12x4" if q else "grid:36x7")
    sizes = parse_sizes(args.sizes or ("64,96" if q else "256,512,1080"))
    real_sizes = set(parse_sizes(args.real_sizes or ("64,96" if q else "256,512")))
    frames = args.frames or (5 if q else 40)
    latency_views = args.latency_views or (10 if q else 100)
    rss_frames = args.rss_frames or (300 if q else 10_000)
    serial_s = args.serial_seconds or (1.5 if q else 6.0)
    jpeg_views = args.jpeg_views or (2 if q else 6)
    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    stem = volume_stem(volume)
    print(f"device benchmarks: volume {volume}, training views {views}, work {work}; load "
          f"average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs", flush=True)
    cases = []
    for size in sizes:
        path = model_path(work, stem, size)
        if size in real_sizes or path.exists():
            path = ensure_model(work, volume, size, views)
            cases.append(Case(size, path))
        else:
            cases.append(Case(size, None))
    results: dict[str, Any] = {"volume": volume, "views": views, "load": os.getloadavg()[0]}
    real = [c for c in cases if c.kind == "real"]
    frame_rows: dict[int, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        if "a" in args.sections:
            print("\n(a) device frame time, headless, per stage (median of "
                  f"{frames} orbit frames, 3 deg/frame)", flush=True)
            for case in cases:
                row = section_frame_time(case, frames, Path(tmp))
                frame_rows[case.size] = row
                print_frame_time(row)
            results["frame_time"] = list(frame_rows.values())
    if "b" in args.sections:
        print(f"\n(b) VIEW_REQUEST -> presented over TCP loopback ({latency_views} requests)",
              flush=True)
        results["latency"] = _rows(
            real, lambda c: section_latency(c, work, latency_views, frame_rows.get(c.size)),
            print_latency)
    if "c" in args.sections:
        print("\n(c) bytes per frame over an orbit vs the equal-quality JPEG", flush=True)
        results["bytes"] = _rows(real, lambda c: section_bytes(c, jpeg_views), print_bytes)
    if "d" in args.sections:
        bare = bare_rss_bytes()
        print(f"\n(d) device peak RSS over {rss_frames} frames (bare runtime process "
              f"{bare / MB:.1f} MB)", flush=True)
        results["rss"] = _rows(real, lambda c: section_rss(c, work, rss_frames, bare),
                               print_rss)
    if "e" in args.sections:
        print(f"\n(e) frames per second over a paced {args.baud}-baud line (mem://, "
              f"{serial_s:g} s per mode)", flush=True)
        results["serial"] = _rows(real, lambda c: section_serial(c, work, serial_s, args.baud),
                                  print_serial)
    if "f" in args.sections:
        print(f"\n(f) SCORES event tag: device frame (body + decode + reconstruct) with and "
              f"without verify_event, median of {frames} interleaved frames", flush=True)
        results["tag_cost"] = _rows(cases, lambda c: section_tag_cost(c, frames), print_tag_cost)
    if args.json:
        print(json.dumps(results, default=float))
    return 0


if __name__ == "__main__":
    with contextlib.suppress(KeyboardInterrupt):
        sys.exit(main())
