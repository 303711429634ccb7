"""Link budget: what a device shows over a slow serial line, eigencast vs WebP/AVIF streams.

Issue 14. Three parts (``--parts``, default ``key,link``):

``key``: bytes per *key* frame at rest. For ``--key-views`` random views per model, the
true view is ray-cast and projected onto the model (`HostModel.project`), then quantized
(a) as ``serve`` does today (`HostModel.quantize`: the model's score step, water-filled)
and (b) rate-distortion optimally (`host.fit.rate.rd_quantize`, SSIM-weighted cells,
``kappa`` and step factors of ``--rd``), coded as real key packets
(`protocol.scores.encode_scores`). Each packet's object SSIM is matched by the smallest
WebP and AVIF file of the same view that reaches it (qualities 1..100, Pillow); the table
gives medians of bytes, SSIM and the ratio packet / file.

``link``: a simulated paced serial line (``--bauds``; ``baud / 10`` bytes per second,
plus `FRAME_OVERHEAD` bytes and COBS's 1/254 per frame). The device asks for the view of a
trace at ``--fps`` display ticks (an orbit at constant speed; a synthesised human-like
drag: accelerate, hold, brake, rest, reverse, rest); whenever the line is free the host
sends the latest view's frame, which the device shows from the first tick after its last
byte arrives. Host compute time is not modelled (the host is assumed to keep up: a GPU
ray-cast, cached projections). Modes:

* ``interp``: interpolated scores (delta packets), what ``serve --scores interpolate`` sends;
* ``project``: the projection of a fresh ray-cast of the view (``serve --scores render``);
* ``rd``: the same, rate-distortion quantized as a delta against the previous frame;
* ``extrap`` (issue 14's temporal prediction, not in the product): the packets of ``rd``,
  but the device extrapolates every tick linearly in time from the last two frames it
  received (``y2 + a (y2 - y1)``, ``a`` the ticks since frame 2's view over the ticks
  between the two views, at most `EXTRAP_MAX`); a new frame every moving tick, no bytes;
* ``pc`` (predict + correct, host-side model): the device interpolates every tick itself
  (no bytes); the host sends an RD-quantized correction from that prediction to the
  projection of the current view; the device shows prediction + correction while the view
  is the corrected one. Measured on the host with the device's own interpolation and
  reconstruction code. Until the correction arrives the device shows its own frame of the
  view: for an image with depth (``fit --depth``) the warp of the neighbouring training
  views (`host.evaluate.warp.WarpFrames`, the device's `ViewSynthesizer`: what a served
  device that predicts shows, issue 15), otherwise the score blend ``reconstruct(pred)``;
* ``pc-blend``: ``pc`` with the score blend as the interim frame even where the image has
  depth (the device before issue 15's served warp; the baseline of the warp);
* ``webp`` / ``avif``: a stream of image files, each the highest quality that fits the
  bytes per frame ``rd`` used on this line (so equal frame rate and latency: SSIM compares
  at equal cost), decoded with Pillow.

Per tick, what the device shows is compared to a fresh ray-cast of the tick's view: object
SSIM and FLIP (mask: ray-cast alpha). ``fps`` is the number of ticks showing a new frame per
second of trace (at most ``--fps``).

``real`` (issue 23, `link_real`): the same traces through *real* sessions of the one served
path: ``eigencast serve`` as it is by default to a `RuntimeDevice` that synthesizes its own
frames (``served``: the model with depth; ``served-blend``: the same database fitted
``--no-depth``, from ``--blend-cache``), what an older device gets (``motion``), and
simulated WebP streams on the same trace and line (``webpN``: each frame at most N line
ticks), with the verdict "served at least 0.1 object SSIM above the best WebP stream at no
more frames per second". The key part's ``correction at rest (predict ...)`` rows measure
issue 14's retired correction of the score blend (version-2 packets), kept for history.

``rest`` (`link_real.rest_part`): real resting sessions at each baud: the device rests on
each of ``--rest-views`` random views until its exact frame is on show; the time from rest
to the corrected frame (or the first layer where the plan skips the correction), to object
SSIM 0.95 and 0.99 and to the exact frame, against the time the smallest WebP and AVIF of
each quality and the WebP lossless file take on the same line; medians over the views.

``cells``: cell sizes (``--cells``) at 128 and 256: ``eigencast fit DB --cell C`` into
``--work``, then the ``key`` measurement of each (plus the interpolated frame's SSIM).

Usage::

    .venv/bin/python benchmarks/bench_link.py [--cache /work/cache] [--sizes 128,256,512]
        [--volumes tooth,vismale_head] [--parts key,link,cells] [--bauds 115200,921600]
        [--traces orbit,drag] [--seconds 4] [--fps 10] [--key-views 8] [--write BENCHMARKS.md]
        [--quick]

The served path on a 115200-baud line, both shared volumes at 256 (issue 23; BENCHMARKS.md,
"Slow links")::

    .venv/bin/python benchmarks/bench_link.py --cache /work/cache/db \
        --blend-cache /work/cache/bench23/nodepth --sizes 256 --parts real --bauds 115200

Resting sessions at 115200 and 921600 baud, 20 views per volume at 256 (BENCHMARKS.md,
"Refinement layers at rest"; about 10 minutes per volume)::

    nice .venv/bin/python benchmarks/bench_link.py --cache bench-out/rest/ecs --sizes 256 \
        --volumes tooth,head,vismale_head --parts rest --bauds 115200,921600

Missing models in ``--cache`` (``VOLUME-SIZE.ecs``) are skipped with one line.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")  # (the device decodes layers)

from link_real import DEFAULT_REAL_MODES, SAMPLE_DELAY_S, real_part, rest_part  # noqa: E402

from host.evaluate.baselines import decode_image, encode_image, encode_within_budget  # noqa: E402
from host.evaluate.masks import alpha_object_mask  # noqa: E402
from host.evaluate.metrics import compare_images  # noqa: E402
from host.fit.model import HostModel  # noqa: E402
from host.fit.rate import (  # noqa: E402
    DEFAULT_RD_KAPPA,
    rd_delta,
    rd_quantize,
    ssim_cell_weights,
)
from protocol.scores import EncodedScores, encode_scores  # noqa: E402

#: Bytes a frame costs on the wire beyond its payload: frame header and CRC (14), CBOR
#: message envelope (~12), delimiter (1), event counter and tag of a keyed device (~?; not
#: counted): docs/protocol.md, "Frame overhead".
FRAME_OVERHEAD = 27
#: ``extrap``: the largest extrapolation factor (in multiples of the last two frames' gap).
EXTRAP_MAX = 1.5
CODECS = ("webp", "avif")
#: Predict + correct, the interim frame the depth warp where the image has depth, or the
#: score blend always.
PC_MODES = ("pc", "pc-blend")


def wire_bytes(payload: int) -> int:
    """Bytes on the line for one frame carrying ``payload`` bytes (COBS adds 1 per 254)."""
    return payload + FRAME_OVERHEAD + payload // 254 + 1


# --------------------------------------------------------------------------- traces


def orbit_trace(seconds: float, fps: float, *, speed: float = 36.0,
                theta: float = 20.0) -> list[tuple[float, float]]:
    """Views at each display tick of an orbit at ``speed`` deg/s in phi."""
    n = round(seconds * fps)
    return [((17.0 + speed * i / fps) % 360.0, theta) for i in range(n)]


def drag_trace(seconds: float, fps: float) -> list[tuple[float, float]]:
    """A human-like drag: accelerate, hold, brake, rest, reverse, rest (scaled to ``seconds``).

    Phi velocity (deg/s) is piecewise smooth (raised-cosine ramps); theta drifts a few
    degrees while the hand moves, as a mouse drag does.
    """
    # (duration fraction, start velocity, end velocity) of each phase
    phases = [(0.12, 0, 120), (0.18, 120, 120), (0.10, 120, 0), (0.20, 0, 0),
              (0.12, 0, -80), (0.08, -80, 0), (0.20, 0, 0)]
    n = round(seconds * fps)
    dt = 1.0 / fps
    phi, theta = 17.0, 20.0
    bounds = np.cumsum([p[0] for p in phases]) * seconds
    out = []
    for i in range(n):
        t = i * dt
        k = int(np.searchsorted(bounds, t, side="right"))
        k = min(k, len(phases) - 1)
        t0 = bounds[k - 1] if k else 0.0
        frac = (t - t0) / (phases[k][0] * seconds)
        v0, v1 = phases[k][1], phases[k][2]
        v = v0 + (v1 - v0) * 0.5 * (1 - math.cos(math.pi * min(1.0, frac)))
        out.append((phi % 360.0, theta))
        phi += v * dt
        theta += 0.04 * v * dt * math.sin(2 * math.pi * t / seconds)
    return out


TRACES = {"orbit": orbit_trace, "drag": drag_trace}


# --------------------------------------------------------------------------- helpers


@dataclass
class Case:
    """One model and its ray-caster."""

    name: str
    model: HostModel
    renderer: Any
    _renders: dict = field(default_factory=dict)
    _warp: Any = None

    def interim(self, view: tuple[float, float], pred: np.ndarray, *, warp: bool
                ) -> np.ndarray:
        """What a predicting device shows of ``view`` before the host's correction: the
        depth warp (``warp`` and an image with depth: `WarpFrames`, the device's own code)
        or the score blend ``reconstruct(pred)``."""
        if warp and self.model.image.synthesis is not None:
            if self._warp is None:
                from host.evaluate.warp import WarpFrames

                self._warp = WarpFrames(self.model)
            from device_runtime.orbit import canonical_view

            return self._warp.frame(*canonical_view(*view))  # the device's view
        return self.model.reconstruct(pred)

    def render(self, view: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
        """(rgb uint8, object mask) of a fresh ray-cast (cached)."""
        key = (round(view[0], 6), round(view[1], 6))
        if key not in self._renders:
            rgb, alpha = self.renderer.render(*key)
            self._renders[key] = (rgb, alpha_object_mask(alpha))
        return self._renders[key]

    def packet(self, y: np.ndarray, step: float, base: EncodedScores | None = None,
               frame: int = 1, predicted: bool = False) -> EncodedScores:
        m = self.model
        return encode_scores(y, step=step, frame=frame, view=(0.0, 0.0), image_digest=m.digest,
                             base=base, n_components=m.image.n_components,
                             predicted=predicted)


def open_case(path: Path) -> Case:
    from host.link.serving import open_true_view_scores

    model = HostModel.load(path)
    return Case(path.stem, model, open_true_view_scores(model, workers=1).renderer)


def ssim_obj(ref: np.ndarray, img: np.ndarray, mask: np.ndarray) -> float:
    return float(compare_images(ref, img, mask=mask, metrics=("ssim",)).ssim_object)


def quality(ref: np.ndarray, img: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    c = compare_images(ref, img, mask=mask, metrics=("ssim", "flip"))
    return float(c.ssim_object), float(c.flip_object)


def smallest_file(rgb: np.ndarray, mask: np.ndarray, target: float, codec: str,
                  ladder: dict) -> float:
    """Bytes of the smallest ``codec`` file of ``rgb`` with object SSIM >= ``target``."""
    def at(q: int) -> tuple[int, float]:
        if q not in ladder:
            c = encode_image(rgb, codec, q)
            ladder[q] = (c.size_bytes, ssim_obj(rgb, decode_image(c.data), mask))
        return ladder[q]

    lo, hi = 0, 101  # SSIM(lo) < target (0: none), SSIM(hi) >= target (101: none reaches)
    if at(100)[1] < target:
        return float("nan")
    hi = 100
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if at(mid)[1] >= target:
            hi = mid
        else:
            lo = mid
    return float(min(b for q, (b, s) in ladder.items() if s >= target))


# --------------------------------------------------------------------------- key frames


def rd_settings(text: str) -> list[tuple[float, float]]:
    """``"1:0.2,2:0.2"`` -> [(step factor, kappa), ...]."""
    out = []
    for item in text.split(","):
        f, k = item.split(":")
        out.append((float(f), float(k)))
    return out


def key_frames(case: Case, n_views: int, rd: list[tuple[float, float]], *,
               seed: int = 0, correction_rd: tuple[float, float] = (2.0, DEFAULT_RD_KAPPA)
               ) -> dict[str, dict[str, float]]:
    """Medians over random views of bytes, SSIM and the ratio to equal-SSIM WebP/AVIF."""
    m = case.model
    rng = np.random.default_rng(seed)
    rows: dict[str, list[list[float]]] = {}
    for _ in range(n_views):
        view = (float(rng.uniform(0, 360)), float(rng.uniform(-80, 80)))
        rgb, mask = case.render(view)
        y = m.project(rgb)
        w = ssim_cell_weights(rgb, m.image.cell_shape, mask)
        ladders: dict[str, dict] = {c: {} for c in CODECS}
        tries = [("project (serve today)", m.score_step, m.quantize(y))]
        pred = m.quantized_scores(*view) if "table_step" in m.image.score_quantization else None
        for f, k in rd:
            s = m.score_step * f
            tries.append((f"plain step x{f:g}", s, rd_quantize(m, y, step=s, lam=0.0))
                         if k == 0 else
                         (f"RD step x{f:g} kappa {k:g}", s,
                          rd_quantize(m, y, step=s, kappa=k, weights=w)))
        if pred is not None:  # predict + correct at rest: the correction packet alone
            f, k = correction_rd
            c = rd_quantize(m, y - pred, step=m.score_step * f, kappa=k, weights=w)
            tries.append((f"correction at rest (predict, step x{f:g} kappa {k:g})",
                          m.score_step * f, c))
            # what serve sends once the view has rested (host.link.correction.sharpen_at_rest)
            tries.append(("correction at rest, sharpened (predict, step x1, plain)",
                          m.score_step, rd_quantize(m, y - pred, step=m.score_step, lam=0.0)))
        for name, s, v in tries:
            predicted = name.startswith("correction")
            n = len(case.packet(v, s, predicted=predicted).packet)
            ss = ssim_obj(rgb, m.reconstruct(pred + v if predicted else v), mask)
            row = [n, ss] + [n / smallest_file(rgb, mask, ss, c, ladders[c]) for c in CODECS]
            rows.setdefault(name, []).append(row)
    return {name: dict(zip(["bytes", "ssim_object", "x_webp", "x_avif"],
                           np.nanmedian(np.array(r), axis=0).tolist()))
            for name, r in rows.items()}


def key_table(title: str, res: dict[str, dict[str, float]]) -> str:
    lines = [f"**{title}**", "",
             "| frame | bytes | SSIM obj | x smallest equal-SSIM WebP | x AVIF |",
             "|---|---|---|---|---|"]
    for name, r in res.items():
        lines.append(f"| {name} | {r['bytes']:.0f} | {r['ssim_object']:.4f} | "
                     f"{r['x_webp']:.2f} | {r['x_avif']:.2f} |")
    return "\n".join(lines)


# --------------------------------------------------------------------------- link


@dataclass
class Sent:
    """A frame on the line: the view it shows, its image, when its last byte arrives."""

    view: tuple[float, float]
    image: np.ndarray | None
    arrives: float
    ident: int


class _HostCoder:
    """The host's coder in `simulate`: the frame it sends for a view in one mode, and the
    state that carries from frame to frame (the delta base, the codec's quality hint)."""

    def __init__(self, case: Case, mode: str, rd: tuple[float, float], budget: int | None
                 ) -> None:
        self.case, self.mode, self.budget = case, mode, budget
        f, self.kappa = rd
        self.s_rd = case.model.score_step * f
        self.base: EncodedScores | None = None
        self.base_y: np.ndarray | None = None
        self.hint: int | None = None
        self.frame_no = 1

    def make(self, view: tuple[float, float]) -> tuple[np.ndarray | None, int, Any]:
        """(shown image or None for pc, payload bytes, extra) of the frame for ``view``."""
        case, m, mode, s_rd, kappa = self.case, self.case.model, self.mode, self.s_rd, self.kappa
        self.frame_no += 1
        frame_no = self.frame_no
        if mode in CODECS:
            rgb, _ = case.render(view)
            c = encode_within_budget(rgb, max(1, self.budget), codec=mode, hint=self.hint)
            self.hint = c.quality
            return decode_image(c.data), c.size_bytes, None
        if mode == "interp":
            y, s = m.quantized_scores(*view), m.score_step
        else:
            rgb, mask = case.render(view)
            p = m.project(rgb)
            if mode == "project":
                y, s = m.quantize(p), m.score_step
            elif mode in ("rd", "extrap"):
                w = ssim_cell_weights(rgb, m.image.cell_shape, mask)
                y, s = rd_delta(m, p, self.base_y, step=s_rd, kappa=kappa, weights=w), s_rd
            else:  # pc, pc-blend: a correction from the device's prediction, coded alone
                w = ssim_cell_weights(rgb, m.image.cell_shape, mask)
                pred = m.quantized_scores(*view)
                corr = rd_quantize(m, p - pred, step=s_rd, kappa=kappa, weights=w)
                enc = case.packet(corr, s_rd, frame=frame_no, predicted=True)
                return None, len(enc.packet), corr
        enc = case.packet(y, s, base=self.base, frame=frame_no)
        self.base, self.base_y = enc, y.astype(np.float64)
        if mode == "extrap":  # the device keeps the scores and extrapolates them per tick
            return None, len(enc.packet), y.astype(np.float64)
        return m.reconstruct(y), len(enc.packet), None


def _extrapolated(m: Any, tick_of: dict[int, int], frames: list[Sent], tick: int
                  ) -> tuple[np.ndarray, float]:
    """Scores extrapolated linearly in time from the last two frames' views (``extrap``):
    y2 + a (y2 - y1), a = ticks since frame 2's view / ticks between the two views,
    clamped to [0, EXTRAP_MAX] (no extrapolation at rest or from one frame)."""
    y2 = frames[-1].image
    if len(frames) < 2:
        return m.reconstruct(y2), 0.0
    t1, t2 = tick_of[frames[0].ident], tick_of[frames[1].ident]
    a = 0.0 if t2 <= t1 else min(EXTRAP_MAX, max(0.0, (tick - t2) / (t2 - t1)))
    if frames[0].view == frames[1].view:
        a = 0.0
    return m.reconstruct((y2 + a * (y2 - frames[0].image)).astype(np.float32)), a


def simulate(case: Case, trace: list[tuple[float, float]], fps: float, baud: int, mode: str,
             *, rd: tuple[float, float], budget: int | None = None) -> dict[str, float]:
    """Run one mode over one trace on one line; per-tick quality and frames shown."""
    m = case.model
    rate = baud / 10.0
    dt = 1.0 / fps
    coder = _HostCoder(case, mode, rd, budget)
    make = coder.make
    sent_bytes = 0
    n_sent = 0
    tick_of: dict[int, int] = {0: 0}  # extrap: frame ident -> the trace tick of its view
    held: list[Sent] = []  # extrap: the last two frames received

    n = len(trace)
    # at t = 0 the device already shows view 0 (steady state before the trace), for free
    img0, _, extra0 = make(trace[0])
    if mode == "extrap":
        held = [Sent(trace[0], extra0, 0.0, 0)]
    if mode in PC_MODES:
        pc_views = {trace[0]: extra0}
        img0 = None
    shown = Sent(trace[0], img0, 0.0, 0)
    queue: list[Sent] = []
    line_free = 0.0
    last_view = trace[0]
    ssims, flips = [], []
    new_frames = 0
    prev_ident: Any = None  # the first tick shows the frame already held
    ident = 0
    for i in range(n):
        t = i * dt
        view = trace[i]
        # the host fills the line up to time t with frames of the latest view
        while line_free <= t:
            want = trace[min(n - 1, int(line_free / dt + 1e-9))]
            if want == last_view and (mode not in PC_MODES or want in pc_views):
                # nothing new to send: idle until the next tick with a new view
                j = int(line_free / dt + 1e-9) + 1
                while j < n and trace[j] == last_view:
                    j += 1
                if j >= n:
                    line_free = float("inf")
                    break
                line_free = max(line_free, j * dt)
                continue
            img, nbytes, extra = make(want)
            line_free_start = line_free
            line_free += wire_bytes(nbytes) / rate
            sent_bytes += wire_bytes(nbytes)
            n_sent += 1
            ident += 1
            last_view = want
            if mode in PC_MODES:
                queue.append(Sent(want, None, line_free, ident))
                pc_views.setdefault(want, None)
                queue[-1].image = extra  # the correction
            elif mode == "extrap":  # remember the view's tick: the time its scores stand for
                queue.append(Sent(want, extra, line_free, ident))
                tick_of[ident] = min(n - 1, int(line_free_start / dt + 1e-9))
            else:
                queue.append(Sent(want, img, line_free, ident))
        while queue and queue[0].arrives <= t:
            if mode == "extrap":
                held = [*held, queue[0]][-2:]
            shown = queue.pop(0)
            if mode in PC_MODES:
                pc_views[shown.view] = shown.image
        rgb, mask = case.render(view)
        if mode in PC_MODES:
            corr = pc_views.get(view)
            pred = m.quantized_scores(*view)
            if corr is None:
                img, key = case.interim(view, pred, warp=mode == "pc"), ("pred", view)
            else:
                img, key = m.reconstruct(pred + corr), ("corr", view)
        elif mode == "extrap":
            img, a = _extrapolated(m, tick_of, held, i)
            key = (shown.ident, i) if a > 0 else shown.ident  # a new frame each moving tick
        else:
            img, key = shown.image, shown.ident
        if key != prev_ident and i > 0:
            new_frames += 1
            prev_ident = key
        s_, f_ = quality(rgb, img, mask)
        ssims.append(s_)
        flips.append(f_)
    seconds = n * dt
    return {"fps": new_frames / seconds, "ssim_object": float(np.mean(ssims)),
            "flip_object": float(np.mean(flips)),
            "bytes_per_frame": sent_bytes / max(1, n_sent),
            "line_use": sent_bytes / rate / seconds}


def link_case(case: Case, trace_name: str, seconds: float, fps: float, bauds: list[int],
              rd: tuple[float, float], modes: list[str]) -> dict[int, dict[str, dict]]:
    trace = TRACES[trace_name](seconds, fps)
    out: dict[int, dict[str, dict]] = {}
    for baud in bauds:
        res: dict[str, dict] = {}
        for mode in modes:
            if mode in CODECS:
                continue
            res[mode] = simulate(case, trace, fps, baud, mode, rd=rd)
        # equal bytes per frame as rd (so equal frame rate and latency on the line)
        ref = res.get("rd", {}).get("bytes_per_frame") or baud / 10.0 / fps
        budget = max(64, int(ref) - FRAME_OVERHEAD - int(ref) // 254 - 1)
        for mode in modes:
            if mode in CODECS:
                r = simulate(case, trace, fps, baud, mode, rd=rd, budget=budget)
                r["budget"] = budget
                res[mode] = r
        out[baud] = res
    return out


def link_table(title: str, res: dict[int, dict[str, dict]]) -> str:
    lines = [f"**{title}**", "",
             "| baud | mode | fps shown | SSIM obj | FLIP obj | bytes/frame | line use |",
             "|---|---|---|---|---|---|---|"]
    for baud, modes in res.items():
        for mode, r in modes.items():
            lines.append(f"| {baud} | {mode} | {r['fps']:.1f} | {r['ssim_object']:.4f} | "
                         f"{r['flip_object']:.4f} | {r['bytes_per_frame']:.0f} | "
                         f"{100 * r['line_use']:.0f} % |")
    return "\n".join(lines)


# --------------------------------------------------------------------------- real


# the real part lives in link_real.py (imported by main)


# --------------------------------------------------------------------------- cells


def cells_part(cache: Path, work: Path, volumes: list[str], sizes: list[int],
               cells: list[int], n_views: int, rd: list[tuple[float, float]]) -> list[str]:
    tables = []
    work.mkdir(parents=True, exist_ok=True)
    exe = ROOT / ".venv" / "bin" / "eigencast"
    for vol in volumes:
        threshold = 0.997 if vol == "tooth" else 0.98
        for size in sizes:
            db = cache / f"{vol}-{size}.cdb"
            if not (db / ".done").exists():
                print(f"skip cells {vol}-{size}: no finished database {db}", flush=True)
                continue
            rows = []
            for cell in cells:
                out = work / f"{vol}-{size}-c{cell}.ecs"
                shared = cache / f"{vol}-{size}.ecs"  # the shared model has cells 16
                if cell == 16 and size < 512 and shared.exists():
                    out = shared
                if not out.exists():
                    t0 = time.perf_counter()
                    subprocess.run([str(exe), "fit", str(db), "-o", str(out), "--cell",
                                    str(cell), "--threshold", str(threshold),
                                    "--no-standalone"], check=True, stdout=subprocess.DEVNULL)
                    print(f"fit {out.name}: {time.perf_counter() - t0:.0f} s", flush=True)
                case = open_case(out)
                res = key_frames(case, n_views, rd)
                rng = np.random.default_rng(0)
                interp = []
                for _ in range(n_views):
                    view = (float(rng.uniform(0, 360)), float(rng.uniform(-80, 80)))
                    rgb, mask = case.render(view)
                    interp.append(ssim_obj(rgb, case.model.view(*view), mask))
                k = case.model.image.n_coefficients
                for name, r in res.items():
                    rows.append((cell, k, name, r, float(np.median(interp))))
            lines = [f"**cells: {vol} {size}x{size}, T {threshold}**", "",
                     "| cell | K | frame | bytes | SSIM obj | x WebP | x AVIF | interp SSIM obj |",
                     "|---|---|---|---|---|---|---|---|"]
            for cell, k, name, r, si in rows:
                lines.append(f"| {cell} | {k} | {name} | {r['bytes']:.0f} | "
                             f"{r['ssim_object']:.4f} | {r['x_webp']:.2f} | {r['x_avif']:.2f} "
                             f"| {si:.4f} |")
            table = "\n".join(lines)
            print(table + "\n", flush=True)
            tables.append(table)
    return tables


# --------------------------------------------------------------------------- main


def _parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cache", type=Path, default=Path("/work/cache"))
    ap.add_argument("--work", type=Path, default=Path("/work/cache/ratelink"),
                    help="folder for the cell-size fits")
    ap.add_argument("--volumes", default="tooth,vismale_head")
    ap.add_argument("--sizes", default="128,256,512")
    ap.add_argument("--parts", default="key,link")
    ap.add_argument("--bauds", default="115200,921600")
    ap.add_argument("--traces", default="orbit,drag")
    ap.add_argument("--modes", default="interp,project,rd,pc,webp,avif")
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("--key-views", type=int, default=8)
    ap.add_argument("--rd", default="2:0,4:0,1:0.2,2:0.2,4:0.2",
                    help="key part: step factor:kappa pairs (kappa 0: plain rounding)")
    ap.add_argument("--link-rd", default=f"2:{DEFAULT_RD_KAPPA}",
                    help="link part: step factor:kappa of the rd and pc modes")
    ap.add_argument("--real-modes", default=DEFAULT_REAL_MODES,
                    help="real part: served, served-blend, motion, webpN (a WebP stream, "
                    "each frame at most N line ticks)")
    ap.add_argument("--repeats", type=int, default=1,
                    help="real part: sessions per real mode (the verdict uses their mean)")
    ap.add_argument("--cold-host", action="store_true",
                    help="real part: each session's serve makes and prepares its own frame "
                    "source (default: one prepared source per mode, a steady-state host)")
    ap.add_argument("--blend-cache", type=Path, default=None,
                    help="real part: VOLUME-SIZE.ecs fitted --no-depth (served-blend)")
    ap.add_argument("--sample-ticks", type=float, default=SAMPLE_DELAY_S * 60.0,
                    help="real part: a tick's frame is the one on show this many 60 Hz "
                    "display ticks after its view was set")
    ap.add_argument("--real-work", type=Path, default=Path("/work/cache/link-real"),
                    help="real part: the devices' flash folders")
    ap.add_argument("--rest-views", type=int, default=20,
                    help="rest part: views the device rests on, each until its exact frame")
    ap.add_argument("--cells", default="8,12,16,24")
    ap.add_argument("--cell-sizes", default="128,256")
    ap.add_argument("--write", type=Path, default=None,
                    help="append the tables (markdown) to this file")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--quick", action="store_true",
                    help="smoke run: tooth at 128, drag, 115200, 2 s at 5 ticks/s, 2 views")
    args = ap.parse_args(argv)
    if args.quick:
        args.sizes, args.volumes, args.traces, args.bauds = "128", "tooth", "drag", "115200"
        args.seconds, args.fps, args.key_views, args.rd = 2.0, 5.0, 2, "2:0,2:0.2"
        args.parts = ",".join(p for p in args.parts.split(",") if p != "cells") or "key"
    return args


def main(argv: list[str] | None = None) -> int:
    args = _parse_args(argv)
    parts = args.parts.split(",")
    volumes = args.volumes.split(",")
    rd = rd_settings(args.rd)
    link_rd = rd_settings(args.link_rd)[0]
    tables: list[str] = []
    record: dict[str, Any] = {"args": {k: str(v) for k, v in vars(args).items()}}
    t_start = time.perf_counter()
    for size in [int(s) for s in args.sizes.split(",")]:
        for vol in volumes:
            path = args.cache / f"{vol}-{size}.ecs"
            if not ({"key", "link", "real", "rest"} & set(parts)):
                break
            if not path.exists():
                print(f"skip {vol}-{size}: no model {path}", flush=True)
                continue
            case = open_case(path)
            m = case.model
            desc = (f"{vol} {size}x{size}, cells {m.image.cell_shape[0]}, K "
                    f"{m.image.n_coefficients}, step {m.score_step:.3g}")
            if "key" in parts:
                t0 = time.perf_counter()
                res = key_frames(case, args.key_views, rd, correction_rd=link_rd)
                table = key_table(f"key frames at rest: {desc} (median of "
                                  f"{args.key_views} views)", res)
                print(table + f"\n({time.perf_counter() - t0:.0f} s)\n", flush=True)
                tables.append(table)
                record[f"key/{vol}-{size}"] = res
            if "link" in parts:
                for trace in args.traces.split(","):
                    t0 = time.perf_counter()
                    res = link_case(case, trace, args.seconds, args.fps,
                                    [int(b) for b in args.bauds.split(",")], link_rd,
                                    args.modes.split(","))
                    table = link_table(
                        f"link: {desc}, {trace} {args.seconds:g} s at {args.fps:g} ticks/s, "
                        f"rd/pc step x{link_rd[0]:g} kappa {link_rd[1]:g}", res)
                    print(table + f"\n({time.perf_counter() - t0:.0f} s)\n", flush=True)
                    tables.append(table)
                    record[f"link/{vol}-{size}/{trace}"] = {str(k): v for k, v in res.items()}
            if "real" in parts:
                blend_path = (args.blend_cache / f"{vol}-{size}.ecs" if args.blend_cache
                              else None)
                blend_case = None
                if blend_path is not None and blend_path.exists():
                    blend_case = open_case(blend_path)
                    blend_case._renders = case._renders  # same database: same true views
                tabs, rec = real_part(case, blend_case, path, blend_path, desc,
                                      args.traces.split(","),
                                      [int(b) for b in args.bauds.split(",")],
                                      args.real_modes.split(","), args.seconds, args.fps,
                                      args.real_work, link_rd, args.sample_ticks,
                                      args.repeats, prepare=not args.cold_host)
                tables += tabs
                for trace_name, r in rec.items():
                    record[f"real/{vol}-{size}/{trace_name}"] = r
            if "rest" in parts:
                tabs, rec = rest_part(case, path, desc, [int(b) for b in args.bauds.split(",")],
                                      args.rest_views, args.real_work)
                tables += tabs
                record[f"rest/{vol}-{size}"] = rec
    if "cells" in parts:
        tables += cells_part(args.cache, args.work, volumes,
                             [int(s) for s in args.cell_sizes.split(",")],
                             [int(c) for c in args.cells.split(",")], args.key_views, rd)
    print(f"total {time.perf_counter() - t_start:.0f} s")
    if args.write:
        with open(args.write, "a") as fh:
            fh.write("\n" + "\n\n".join(tables) + "\n")
    if args.json:
        args.json.write_text(json.dumps(record, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
