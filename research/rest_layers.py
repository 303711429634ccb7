"""The true picture at rest: what refinement layers from the rested frame to the ray-cast cost.

A served device at rest shows ``F``: its own frame of the view (depth warp or blend) plus the
host's complete eigenspace correction (`host.evaluate.device_path.ServedFrames.at_rest`, the
product's code, with the correction packet's bytes ``c``). This study measures, per novel
view, what it costs to take the device from ``F`` to the exact ray-cast ``R``, layer by layer,
and compares every plan with the smallest JPEG / WebP / AVIF of ``R`` of the same object SSIM
(`host.evaluate.metrics.structural_similarity` over `host.evaluate.masks.alpha_object_mask`,
as ``eigencast evaluate`` scores).

Per view (``--views``, `host.render.camera.parse_view_set`, ray-cast with the database's
recorded render settings at the canonical view the served path uses) and per target object
SSIM (0.90, 0.95, 0.97, 0.99), each lossy candidate's bytes are those of the lowest setting
(quality 1..100, or a ladder for the numpy coder) whose frame reaches the target, found by
bisection like `host.evaluate.baselines.encode_within_budget` (quality for bytes there,
bytes for quality here; the codecs' files from `host.evaluate.baselines.encode_image`: WebP
method 6, AVIF speed 4, JPEG optimized 4:2:0). Candidates (``c +``: the correction's bytes
are included):

* ``webp``, ``avif``, ``jpeg``: the ray-cast alone (the baselines; ``webp`` is also the
  "skip the correction" first layer);
* ``res1``/``res2``: c + WebP lossy of ``(R - F) / k + 128`` (k 1, 2), the device adding
  ``k (decoded - 128)`` to its frame and clipping; ``res1_cw``/``res1_sharp``: the same
  through ``cwebp`` (libwebp's tool, when installed) without/with ``-sharp_yuv``;
* ``res1_obj``: c + the residual zeroed outside the object mask the device knows from its
  own frame (``F`` non-black, dilated), the layer applied only inside it; ``res1_crop``: the
  same cropped to the mask's bounding box (a smaller picture);
* ``res1_jpeg``: c + JPEG 4:4:4 of the residual; ``resq_zstd``: c + the residual quantized
  (uniform step) and zstd-19'd (pure numpy on the device);
* ``res_own``: no correction: WebP of ``R - S + 128`` (``S`` the device's own frame);
* ``best``: per view and target the smallest of what a pygame device can decode
  (``res1``, ``res2``, ``res1_obj``, ``res_own``, ``webp``): the host's choice.

Exact (``R`` bit for bit): WebP lossless and optimized PNG of ``R``; zstd-19 of ``R``; WebP
lossless and zstd of ``(R - F) mod 256`` (depend on the device's float frame: reference only);
``(R - D) mod 256`` with ``D`` a WebP lossy decode of ``R`` (depends only on bytes), WebP
lossless and zstd-19 with and without a dictionary trained on the other views' residuals
(leave one out), cumulative with ``D``'s bytes. Layer plans: cumulative bytes of correction ->
lossy layers -> exact layer. Tiles: a layer as 2x2 and 4x4 independent WebP files.

Also: whether a WebP lossy file decodes to the same bytes through Pillow (libwebp of
Pillow), pygame (SDL_image's libwebp) and ``dwebp`` with and without its SIMD code
(``-noasm``); and (``--timing``, run pinned to one core) the device's cost of a layer,
``pygame.image.load`` + the numpy add/clip, against the blend (``Reconstructor.update`` of
a new view's predicted scores, as ``benchmarks/device_correction.py`` times it), at 256 and
512.

Run (one command; databases from ``/work/cache`` by default, models fitted into ``--work``)::

    nice -n 10 .venv/bin/python research/rest_layers.py --volumes tooth-256,head-256

It writes ``WORK/NAME-SIZE.json`` per volume (reused unless ``--redo``) and the tables to
``--out`` (default ``research/rest_layers.md``).
"""

from __future__ import annotations

import argparse
import io
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")

#: Object SSIM targets of the lossy layers.
TARGETS = (0.90, 0.95, 0.97, 0.99)
#: Quantization steps of the numpy coder, coarse to fine (a ladder like quality 1..100).
ZSTD_STEPS = (96, 64, 48, 32, 24, 16, 12, 10, 8, 6, 5, 4, 3, 2, 1)
#: Dilation of the device-known object mask, pixels.
MASK_DILATE = 4
#: Level above which a pixel of F counts as object for the device's mask.
MASK_LEVEL = 0
DEFAULT_VOLUMES = ("tooth-256", "head-256", "vismale_head-256", "engine-256", "headsq-256",
                   "brainsmall-256", "mni152-256", "tooth-512", "head-512", "vismale_head-512")
#: The line below which ``--out`` is rewritten (the findings above it are kept).
MARKER = "<!-- rest_layers.py writes everything below this line -->"
#: Candidates a pygame device decodes that `best` chooses from.
BEST_FROM = ("res1", "res2", "res1_obj", "res_own", "webp")
LOSSY_ORDER = ("webp", "avif", "jpeg", "res1", "res2", "res1_cw", "res1_sharp", "res1_obj",
               "res1_crop", "res1_jpeg", "resq_zstd", "res_own", "best")


# --------------------------------------------------------------------------- coders


def webp(image: np.ndarray, q: int, *, lossless: bool = False) -> bytes:
    """WebP of ``image`` (uint8 (h, w, 3)): lossy at quality ``q``, method 6, as
    `host.evaluate.baselines.encode_image`; lossless at effort ``q`` (100: the smallest)."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(image, "RGB").save(buf, format="WEBP", quality=int(q), method=6,
                                       lossless=lossless)
    return buf.getvalue()


def png(image: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(image, "RGB").save(buf, format="PNG", optimize=True)
    return buf.getvalue()


def jpeg444(image: np.ndarray, q: int) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(image, "RGB").save(buf, format="JPEG", quality=int(q), optimize=True,
                                       subsampling=0)
    return buf.getvalue()


def decode(data: bytes) -> np.ndarray:
    from host.evaluate.baselines import decode_image

    return decode_image(data)


def cwebp(image: np.ndarray, q: int, *, sharp: bool) -> bytes | None:
    """libwebp's ``cwebp -m 6 -q q [-sharp_yuv]`` (None: not installed)."""
    exe = shutil.which("cwebp")
    if exe is None:
        return None
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "in.png", Path(tmp) / "out.webp"
        from PIL import Image

        Image.fromarray(image, "RGB").save(src, compress_level=1)
        cmd = [exe, "-quiet", "-m", "6", "-q", str(int(q)), str(src), "-o", str(dst)]
        if sharp:
            cmd.insert(1, "-sharp_yuv")
        subprocess.run(cmd, check=True)
        return dst.read_bytes()


def zstd(data: bytes, *, dictionary: Any = None, level: int = 19) -> bytes:
    import zstandard

    if dictionary is None:
        return zstandard.ZstdCompressor(level=level).compress(data)
    return zstandard.ZstdCompressor(level=level, dict_data=dictionary).compress(data)


def offset_residual(target: np.ndarray, base: np.ndarray, k: int) -> np.ndarray:
    """``(target - base) / k + 128`` rounded and clipped to uint8 (the lossy residual image)."""
    d = target.astype(np.int16) - base.astype(np.int16)
    if k == 1:
        return np.clip(d + 128, 0, 255).astype(np.uint8)
    return np.clip(np.floor(d / k + 0.5) + 128, 0, 255).astype(np.uint8)


def add_residual(base: np.ndarray, decoded: np.ndarray, k: int,
                 mask: np.ndarray | None = None) -> np.ndarray:
    """The device's frame after a residual layer: ``clip(base + k (decoded - 128))``
    (only inside ``mask`` when given)."""
    d = decoded.astype(np.int16) - 128
    if k != 1:
        d *= k
    if mask is not None:
        d *= mask[..., None]
    return np.clip(base.astype(np.int16) + d, 0, 255).astype(np.uint8)


def device_mask(frame: np.ndarray) -> np.ndarray:
    """The object mask a device derives from its own frame: non-black pixels, dilated."""
    from scipy.ndimage import binary_dilation

    m = frame.max(axis=2) > MASK_LEVEL
    return binary_dilation(m, iterations=MASK_DILATE)


def bbox(mask: np.ndarray) -> tuple[slice, slice]:
    ys, xs = np.nonzero(mask)
    if ys.size == 0:
        return slice(0, 1), slice(0, 1)
    return slice(int(ys.min()), int(ys.max()) + 1), slice(int(xs.min()), int(xs.max()) + 1)


# --------------------------------------------------------------------------- search


class Quality:
    """Object SSIM against one ray-cast (memoized per candidate and setting)."""

    def __init__(self, truth: np.ndarray, mask: np.ndarray) -> None:
        self.truth = truth
        self.mask = mask

    def __call__(self, frame: np.ndarray) -> float:
        from host.evaluate.metrics import structural_similarity

        if np.array_equal(frame, self.truth):
            return 1.0
        return structural_similarity(self.truth, frame, mask=self.mask)


class Ladder:
    """One candidate on one view: ``code(setting) -> (bytes, frame)`` over ``settings``
    (worst to best); `reach` finds the cheapest setting whose frame reaches a target."""

    def __init__(self, code: Callable[[Any], tuple[int, np.ndarray]], settings: Sequence[Any],
                 quality: Quality, fixed_bytes: int = 0) -> None:
        self.code = code
        self.settings = list(settings)
        self.quality = quality
        self.fixed = int(fixed_bytes)
        self.memo: dict[int, tuple[int, float, np.ndarray]] = {}

    def at(self, i: int) -> tuple[int, float, np.ndarray]:
        if i not in self.memo:
            size, frame = self.code(self.settings[i])
            self.memo[i] = (size + self.fixed, self.quality(frame), frame)
        return self.memo[i]

    def reach(self, target: float) -> dict | None:
        """The lowest setting whose quality reaches ``target`` (quality monotone-ish in the
        setting; bisection keeping "lo misses, hi reaches"), or None when the best misses."""
        lo, hi = -1, len(self.settings) - 1
        if self.at(hi)[1] < target:
            return None
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if self.at(mid)[1] >= target:
                hi = mid
            else:
                lo = mid
        size, q, _ = self.at(hi)
        return {"bytes": size, "ssim": q, "setting": self.settings[hi]}


# --------------------------------------------------------------------------- per view


def measure_view(R: np.ndarray, mask: np.ndarray, F: np.ndarray, S: np.ndarray, c: int,
                 have_cwebp: bool, plain_cwebp: bool = False) -> tuple[dict, dict]:
    """Every candidate on one view. Returns (record, layers): the JSON record and the layer
    files the timing and tile sections reuse."""
    from host.evaluate.baselines import encode_image

    quality = Quality(R, mask)
    rec: dict[str, Any] = {"correction_bytes": c, "ssim_own": quality(S), "ssim_F": quality(F),
                           "object_fraction": float(mask.mean())}
    Mdev = device_mask(F)
    rec["mask_fraction"] = float(Mdev.mean())
    rec["mask_misses_object"] = float((mask & ~Mdev).sum() / max(1, mask.sum()))
    qs = list(range(1, 101))

    def codec(name: str) -> Callable[[int], tuple[int, np.ndarray]]:
        def code(q: int) -> tuple[int, np.ndarray]:
            coded = encode_image(R, name, q)
            return coded.size_bytes, coded.decode()
        return code

    def residual(base: np.ndarray, k: int, enc: Callable[[np.ndarray, int], bytes],
                 obj: np.ndarray | None = None, crop: bool = False
                 ) -> Callable[[int], tuple[int, np.ndarray]]:
        res = offset_residual(R, base, k)
        if obj is not None:
            res = res.copy()
            res[~obj] = 128
        box = bbox(obj) if crop and obj is not None else (slice(None), slice(None))
        part = np.ascontiguousarray(res[box])

        def code(q: int) -> tuple[int, np.ndarray]:
            data = enc(part, q)
            dec = np.full_like(res, 128)
            dec[box] = decode(data)
            return len(data), add_residual(base, dec, k, obj)
        return code

    def resq(q_step: int) -> tuple[int, np.ndarray]:
        d = R.astype(np.int16) - F.astype(np.int16)
        qd = np.floor(d / q_step + 0.5).astype(np.int16)
        data = zstd(np.clip(qd, -128, 127).astype(np.int8).tobytes())
        return len(data), np.clip(F.astype(np.int16) + qd * q_step, 0, 255).astype(np.uint8)

    ladders: dict[str, Ladder] = {
        "webp": Ladder(codec("webp"), qs, quality),
        "avif": Ladder(codec("avif"), qs, quality),
        "jpeg": Ladder(codec("jpeg"), qs, quality),
        "res1": Ladder(residual(F, 1, webp), qs, quality, c),
        "res2": Ladder(residual(F, 2, webp), qs, quality, c),
        "res1_obj": Ladder(residual(F, 1, webp, Mdev), qs, quality, c),
        "res1_crop": Ladder(residual(F, 1, webp, Mdev, crop=True), qs, quality, c),
        "res1_jpeg": Ladder(residual(F, 1, jpeg444), qs, quality, c),
        "resq_zstd": Ladder(resq, ZSTD_STEPS, quality, c),
        "res_own": Ladder(residual(S, 1, webp), qs, quality, 0),
    }
    if have_cwebp and plain_cwebp:  # cwebp's own bytes without -sharp_yuv (a few views)
        ladders["res1_cw"] = Ladder(
            residual(F, 1, lambda im, q: cwebp(im, q, sharp=False)), qs, quality, c)
    if have_cwebp:
        ladders["res1_sharp"] = Ladder(
            residual(F, 1, lambda im, q: cwebp(im, q, sharp=True)), qs, quality, c)
    lossy: dict[str, dict] = {}
    for name, ladder in ladders.items():
        lossy[name] = {}
        for t in TARGETS:
            if name.startswith(("res", "resq")) and name != "res_own" and rec["ssim_F"] >= t:
                lossy[name][str(t)] = {"bytes": c, "ssim": rec["ssim_F"], "setting": "F"}
            elif name == "res_own" and rec["ssim_own"] >= t:
                lossy[name][str(t)] = {"bytes": 0, "ssim": rec["ssim_own"], "setting": "S"}
            else:
                lossy[name][str(t)] = ladder.reach(t)
    lossy["best"] = {}
    for t in TARGETS:
        options = [(lossy[n][str(t)]["bytes"], n) for n in BEST_FROM if lossy[n][str(t)]]
        if options:
            b, n = min(options)
            lossy["best"][str(t)] = {"bytes": b, "ssim": lossy[n][str(t)]["ssim"], "from": n}
        else:
            lossy["best"][str(t)] = None
    rec["lossy"] = lossy
    layers: dict[str, Any] = {}
    # the layer files the timing section decodes (at the settings that reach 0.95 / 0.99)
    for t in (0.95, 0.99):
        hit = lossy["res1"][str(t)]
        if hit and hit["setting"] != "F":
            layers[f"res1@{t}"] = webp(offset_residual(R, F, 1), hit["setting"])
        hit = lossy["webp"][str(t)]
        if hit:
            layers[f"webp@{t}"] = encode_image(R, "webp", hit["setting"]).data
        hit = lossy["res1_jpeg"][str(t)]
        if hit and hit["setting"] != "F":
            layers[f"res1_jpeg@{t}"] = jpeg444(offset_residual(R, F, 1), hit["setting"])
    rec["exact"], exact_layers, residuals = measure_exact(R, F, lossy, ladders, c)
    layers.update(exact_layers)
    rec["plans"] = layer_plans(R, F, S, c, lossy, ladders, rec["exact"], quality)
    rec["tiles"] = measure_tiles(R, F, lossy)
    return rec, {"layers": layers, "residuals": residuals}


def measure_exact(R: np.ndarray, F: np.ndarray, lossy: dict, ladders: dict[str, Ladder],
                  c: int) -> tuple[dict, dict, dict]:
    """The exact layers (bytes), the files for timing, and the residual images the
    dictionary is trained on (per lossy base)."""
    out: dict[str, Any] = {}
    files: dict[str, bytes] = {}
    wll = webp(R, 100, lossless=True)
    files["wll_R"] = wll
    out["wll_R"] = len(wll)
    files["png_R"] = png(R)
    out["png_R"] = len(files["png_R"])
    out["zstd_R"] = len(zstd(R.tobytes()))
    eF = (R.astype(np.int16) - F.astype(np.int16)).astype(np.uint8)  # mod 256
    out["wll_resF"] = len(webp(eF, 100, lossless=True)) + c
    out["zstd_resF"] = len(zstd(eF.tobytes())) + c
    residuals: dict[str, np.ndarray] = {}
    for t in (0.95, 0.97, 0.99):
        hit = lossy["webp"][str(t)]
        if not hit:
            continue
        D = ladders["webp"].at(ladders["webp"].settings.index(hit["setting"]))[2]
        eD = (R.astype(np.int16) - D.astype(np.int16)).astype(np.uint8)
        residuals[str(t)] = eD
        data = webp(eD, 100, lossless=True)
        if t != 0.97:  # the files the timing decodes (their bases are saved at 0.95, 0.99)
            files[f"wll_resD@{t}"] = data
        out[f"wll_resD@{t}"] = {"layer": len(data), "cumulative": len(data) + hit["bytes"],
                                "base": hit["bytes"]}
        z = zstd(eD.tobytes())
        if t != 0.97:
            files[f"zstd_resD@{t}"] = z
        out[f"zstd_resD@{t}"] = {"layer": len(z), "cumulative": len(z) + hit["bytes"],
                                 "base": hit["bytes"]}
        # the residual against the corrected frame plus the lossy residual layer (depends on
        # the device's float frame: reference)
        hit1 = lossy["res1"][str(t)]
        if hit1 and hit1["setting"] != "F":
            G = ladders["res1"].at(ladders["res1"].settings.index(hit1["setting"]))[2]
            eG = (R.astype(np.int16) - G.astype(np.int16)).astype(np.uint8)
            out[f"wll_resG@{t}"] = {"layer": len(webp(eG, 100, lossless=True)),
                                    "cumulative": None, "base": hit1["bytes"]}
            out[f"wll_resG@{t}"]["cumulative"] = out[f"wll_resG@{t}"]["layer"] + hit1["bytes"]
    return out, files, residuals


def layer_plans(R: np.ndarray, F: np.ndarray, S: np.ndarray, c: int, lossy: dict,
                ladders: dict[str, Ladder], exact: dict, quality: Quality) -> dict:
    """Cumulative bytes of layer plans, the host choosing per layer.

    A plan: its first layer (``res1``: correction then the residual layer; ``res_own``: no
    correction, the residual against the own frame; ``webp``: the ray-cast; ``best``: the
    smallest of `BEST_FROM` for the view) at a target, optionally a layer to 0.99 (the
    smaller of the residual against the frame the device then shows and a WebP of ``R``),
    then the exact layer (the smaller of WebP lossless of ``R`` and, after a WebP of ``R``,
    WebP lossless of ``(R - D) mod 256``). Each step: [object SSIM, cumulative bytes, the
    smallest WebP of ``R`` reaching that SSIM (WebP lossless for the exact step), the same
    for AVIF, what the layer is]."""
    wll = exact["wll_R"]

    def ref(name: str, ssim: float) -> int | None:
        hit = ladders[name].reach(ssim)
        return hit["bytes"] if hit else None

    def step(ssim: float, size: int, kind: str) -> list:
        if ssim >= 1.0:
            return [1.0, size, wll, None, kind]
        return [ssim, size, ref("webp", ssim), ref("avif", ssim), kind]

    def frame_of(name: str, hit: dict) -> np.ndarray:
        if hit["setting"] == "F":
            return F
        if hit["setting"] == "S":
            return S
        ladder = ladders[name]
        return ladder.at(ladder.settings.index(hit["setting"]))[2]

    def exact_step(prev: int, webp_at: float | None) -> list:
        options = [(wll, "wll_R")]
        key = f"wll_resD@{webp_at}" if webp_at is not None else None
        if key and key in exact:
            options.append((exact[key]["layer"], "wll_resD"))
        size, kind = min(options)
        return step(1.0, prev + size, kind)

    ssim_F = quality(F)
    ssim_S = quality(S)
    plans: dict[str, list[list]] = {}
    for first, t1 in (("res1", 0.95), ("res_own", 0.95), ("webp", 0.95), ("best", 0.95),
                      ("best", 0.97)):
        if True:
            name = first
            if first == "best":
                best = lossy["best"][str(t1)]
                if not best:
                    continue
                name = best["from"]
            hit = lossy[name][str(t1)]
            if not hit:
                continue
            # stage 0: what the device shows before any layer
            corrected = name not in ("res_own", "webp")
            s0 = step(ssim_F, c, "correction") if corrected else step(ssim_S, 0, "own frame")
            # stage 1: the first lossy layer (none when the frame already reaches t1)
            if hit["setting"] in ("F", "S"):
                s1 = step(hit["ssim"], s0[1], "reached")
            else:
                s1 = step(hit["ssim"], hit["bytes"], name)
            webp_at = t1 if name == "webp" else None
            label = f"{first}@{t1}"
            plans[f"{label} > exact"] = [s0, s1, exact_step(s1[1], webp_at)]
            # stage 2: a layer to 0.99, the residual against the frame shown or WebP of R
            G = frame_of(name, hit)
            res = offset_residual(R, G, 1)

            def code(q: int, res: np.ndarray = res, G: np.ndarray = G
                     ) -> tuple[int, np.ndarray]:
                data = webp(res, q)
                return len(data), add_residual(G, decode(data), 1)

            second = Ladder(code, list(range(1, 101)), quality, s1[1]).reach(0.99)
            fresh = lossy["webp"]["0.99"]
            options = []
            if second:
                options.append((second["bytes"], second["ssim"], "residual", None))
            if fresh:
                options.append((s1[1] + fresh["bytes"], fresh["ssim"], "webp", 0.99))
            if not options:
                continue
            size, ssim, kind, at = min(options)
            s2 = step(ssim, size, kind)
            plans[f"{label} > 0.99 > exact"] = [s0, s1, s2, exact_step(size, at)]
    return plans


def measure_tiles(R: np.ndarray, F: np.ndarray, lossy: dict) -> dict:
    """A layer as n x n independent WebP files: total bytes against one file (residual at
    the quality reaching 0.95, and the exact WebP lossless of R)."""
    out: dict[str, Any] = {}
    hit = lossy["res1"]["0.95"]
    res = offset_residual(R, F, 1)
    h, w = R.shape[:2]
    for n in (2, 4):
        ys = np.linspace(0, h, n + 1).astype(int)
        xs = np.linspace(0, w, n + 1).astype(int)
        tiles = [(slice(ys[i], ys[i + 1]), slice(xs[j], xs[j + 1]))
                 for i in range(n) for j in range(n)]
        if hit and hit["setting"] != "F":
            q = hit["setting"]
            one = len(webp(res, q))
            many = sum(len(webp(np.ascontiguousarray(res[t]), q)) for t in tiles)
            out[f"res1@0.95 {n}x{n}"] = many / one
        one = len(webp(R, 100, lossless=True))
        many = sum(len(webp(np.ascontiguousarray(R[t]), 100, lossless=True)) for t in tiles)
        out[f"wll_R {n}x{n}"] = many / one
    return out


def dictionary_sizes(views: list[dict], residuals: list[dict], size_bytes: int = 16384) -> None:
    """zstd-19 of each view's ``(R - D) mod 256`` with a dictionary trained on the *other*
    views' residuals (leave one out); added to each view's ``exact`` record."""
    import zstandard

    chunk = 4096
    for t in ("0.95", "0.99"):
        for i, rec in enumerate(views):
            if t not in residuals[i]:
                continue
            samples = []
            for j, other in enumerate(residuals):
                if j == i or t not in other:
                    continue
                raw = other[t].tobytes()
                samples += [raw[k:k + chunk] for k in range(0, len(raw), chunk)]
            if len(samples) < 16:
                continue
            try:
                d = zstandard.train_dictionary(size_bytes, samples, level=19)
            except zstandard.ZstdError:
                continue
            z = zstd(residuals[i][t].tobytes(), dictionary=d)
            base = rec["exact"][f"zstd_resD@{t}"]["base"]
            rec["exact"][f"zstd_dict_resD@{t}"] = {"layer": len(z), "cumulative": len(z) + base,
                                                   "base": base, "dictionary": len(d.as_bytes())}


# --------------------------------------------------------------------------- determinism


def _pygame_libwebp() -> str | None:
    """The version of the libwebp pygame's SDL_image decodes with (its wheel's copy)."""
    import ctypes
    import glob

    import pygame

    libs = Path(pygame.__file__).resolve().parent.parent / "pygame.libs"
    try:
        for dep in glob.glob(str(libs / "libsharpyuv-*")):
            ctypes.CDLL(dep, mode=ctypes.RTLD_GLOBAL)
        so = glob.glob(str(libs / "libwebp-*"))
        v = ctypes.CDLL(so[0]).WebPGetDecoderVersion()
    except (OSError, IndexError, AttributeError):
        return None
    return f"{v >> 16}.{(v >> 8) & 255}.{v & 255}"


def decode_agreement(files: list[bytes]) -> dict:
    """Whether lossy WebP files decode to the same pixels through Pillow, pygame and dwebp
    (with and without SIMD): counts of files whose decodes differ from Pillow's."""
    import pygame
    from PIL import features

    out: dict[str, Any] = {"files": len(files), "pillow_libwebp": features.version("webp"),
                           "pygame": pygame.version.ver, "pygame_libwebp": _pygame_libwebp()}
    dwebp = shutil.which("dwebp")
    diffs = {"pygame": 0, "dwebp": 0, "dwebp_noasm": 0}
    maxdiff = {k: 0 for k in diffs}
    for data in files:
        ref = decode(data)
        surf = pygame.image.load(io.BytesIO(data), "x.webp")
        got = {"pygame": pygame.surfarray.array3d(surf).transpose(1, 0, 2)}
        if dwebp:
            with tempfile.TemporaryDirectory() as tmp:
                src = Path(tmp) / "a.webp"
                src.write_bytes(data)
                for name, extra in (("dwebp", []), ("dwebp_noasm", ["-noasm"])):
                    dst = Path(tmp) / f"{name}.ppm"
                    subprocess.run(["dwebp", "-quiet", *extra, str(src), "-ppm", "-o",
                                    str(dst)], check=True)
                    got[name] = decode(dst.read_bytes())
        for name, arr in got.items():
            if not np.array_equal(arr, ref):
                diffs[name] += 1
                maxdiff[name] = max(maxdiff[name], int(np.abs(arr.astype(int) - ref).max()))
    out["differs_from_pillow"] = diffs if dwebp else {"pygame": diffs["pygame"]}
    out["max_level_difference"] = maxdiff
    if dwebp:
        version = subprocess.run(["dwebp", "-version"], capture_output=True, text=True)
        out["dwebp_libwebp"] = version.stdout.strip()
    return out


# --------------------------------------------------------------------------- volumes


def ensure_model(db: Path, work: Path, name: str) -> Path:
    """``eigencast fit DB -o WORK/NAME.ecs`` (defaults; the fit cache in WORK) unless there."""
    out = work / f"{name}.ecs"
    if out.exists():
        return out
    tmp = work / f"{name}.tmp.ecs"
    cache = work / f"{name}.fitcache"
    t0 = time.perf_counter()
    exe = Path(sys.executable).with_name("eigencast")
    cmd = [str(exe), "fit", str(db), "-o", str(tmp), "--cache", str(cache)]
    code = subprocess.run(cmd, cwd=REPO).returncode
    shutil.rmtree(cache, ignore_errors=True)
    if code:
        raise SystemExit(f"fit of {db} failed (exit {code})")
    tmp.replace(out)
    print(f"  fitted {out.name} in {time.perf_counter() - t0:.0f} s", flush=True)
    return out


def run_volume(name: str, db: Path, work: Path, views_spec: str, have_cwebp: bool) -> dict:
    from device_runtime.prediction import prediction_view
    from host.evaluate.device_path import ServedFrames
    from host.evaluate.masks import alpha_object_mask
    from host.fit.model import HostModel
    from host.render.camera import parse_view_set
    from host.render.settings import RenderSettings, ViewRenderer

    model_path = ensure_model(db, work, name)
    model = HostModel.load(model_path)
    settings = RenderSettings.from_record(model.render_settings, what=str(model_path))
    scene = ViewRenderer.open(settings, None, None, what=str(model_path))
    served = ServedFrames(model, scene)
    views = parse_view_set(views_spec).views
    records: list[dict] = []
    residuals: list[dict] = []
    keep: dict[str, Any] = {}
    t_start = time.perf_counter()
    for i, v in enumerate(views):
        view = prediction_view(float(v.phi_deg), float(v.theta_deg))
        t0 = time.perf_counter()
        S = served.own_frame(*view)
        F, c = served.at_rest(*view)
        R, alpha = scene.render(*view)
        mask = alpha_object_mask(alpha)
        if not mask.any():
            continue
        t1 = time.perf_counter()
        rec, extra = measure_view(R, mask, F, S, c, have_cwebp, plain_cwebp=i < 3)
        rec.update({"phi_deg": view[0], "theta_deg": view[1], "frames_s": t1 - t0,
                    "measure_s": time.perf_counter() - t1})
        records.append(rec)
        residuals.append(extra["residuals"])
        if i < 4:  # the layers and frames the timing section decodes
            keep[f"view{i}"] = {"F": F, "R": R, "layers": extra["layers"], "view": view}
        print(f"  {name} view {i + 1}/{len(views)} ({view[0]:.1f}, {view[1]:.1f}): F "
              f"{rec['ssim_F']:.3f} (own {rec['ssim_own']:.3f}, c {c} B), webp@0.95 "
              f"{_b(rec['lossy']['webp']['0.95'])}, res1@0.95 "
              f"{_b(rec['lossy']['res1']['0.95'])}, wll {rec['exact']['wll_R']}; "
              f"{time.perf_counter() - t0:.0f} s", flush=True)
    dictionary_sizes(records, residuals)
    files = [f for k in keep.values() for n, f in k["layers"].items()
             if n.startswith(("res1@", "webp@"))]
    result = {
        "name": name, "database": str(db), "model": str(model_path), "views": views_spec,
        "size": int(model.image.image_shape[0]), "own_frame": served.kind,
        "eigenspace_bytes": model_path.stat().st_size, "per_view": records,
        "decode_agreement": decode_agreement(files), "seconds": time.perf_counter() - t_start,
    }
    np.savez_compressed(work / f"{name}.layers.npz",
                        **{f"{k}/{n}": np.frombuffer(d, np.uint8)
                           for k, rec in keep.items() for n, d in rec["layers"].items()},
                        **{f"{k}/F": rec["F"] for k, rec in keep.items()},
                        **{f"{k}/R": rec["R"] for k, rec in keep.items()},
                        **{f"{k}/view": np.array(rec["view"]) for k, rec in keep.items()})
    return result


def _b(hit: dict | None) -> str:
    return "-" if hit is None else f"{hit['bytes']}"


# --------------------------------------------------------------------------- timing


class _Device:
    """What a device does with a layer file: decode it through pygame into its frame buffer
    (a residual added and clipped, a ray-cast copied, a mod-256 residual added), or zstd
    into a preallocated buffer."""

    def __init__(self, shape: tuple[int, int]) -> None:
        import zstandard

        self.frame = np.empty((*shape, 3), np.uint8)
        self.scratch = np.empty((*shape, 3), np.int16)
        self.zbuf = bytearray(self.frame.nbytes)
        self.dctx = zstandard.ZstdDecompressor()

    def _add(self, px: np.ndarray, base: np.ndarray) -> None:
        np.subtract(px, 128, out=self.scratch, dtype=np.int16)
        np.add(self.scratch, base, out=self.scratch)
        np.clip(self.scratch, 0, 255, out=self.scratch)
        self.frame[...] = self.scratch

    def add_pixels3d(self, data: bytes, base: np.ndarray) -> None:
        import pygame

        surf = pygame.image.load(io.BytesIO(data), "x.webp")
        self._add(pygame.surfarray.pixels3d(surf).transpose(1, 0, 2), base)  # a view

    def add_tobytes(self, data: bytes, base: np.ndarray) -> None:
        import pygame

        surf = pygame.image.load(io.BytesIO(data), "x.webp")
        px = np.frombuffer(pygame.image.tobytes(surf, "RGB"), np.uint8)
        self._add(px.reshape(self.frame.shape), base)

    def copy(self, data: bytes, hint: str) -> None:
        import pygame

        surf = pygame.image.load(io.BytesIO(data), hint)
        self.frame[...] = pygame.surfarray.pixels3d(surf).transpose(1, 0, 2)

    def add_mod(self, data: bytes, base: np.ndarray) -> None:
        import pygame

        surf = pygame.image.load(io.BytesIO(data), "x.webp")
        np.add(base, pygame.surfarray.pixels3d(surf).transpose(1, 0, 2), out=self.frame)

    def zstd_mod(self, data: bytes, base: np.ndarray) -> None:
        with self.dctx.stream_reader(io.BytesIO(data)) as reader:  # a preallocated buffer
            reader.readinto(self.zbuf)
        np.add(base, np.frombuffer(self.zbuf, np.uint8).reshape(self.frame.shape),
               out=self.frame)


def _layer_calls(dev: _Device, saved: Any, key: str) -> list[tuple[str, Callable[[], Any]]]:
    """The timed calls for one saved view's layer files."""
    F = saved[f"{key}/F"]
    calls: list[tuple[str, Callable[[], Any]]] = []
    for lname in [k.split("/", 1)[1] for k in saved.files if k.startswith(key + "/")
                  and k.split("/", 1)[1] not in ("F", "R", "view")]:
        data = saved[f"{key}/{lname}"].tobytes()
        kind, _, t = lname.partition("@")
        if kind == "res1":
            calls.append((f"res1@{t} pixels3d", lambda d=data: dev.add_pixels3d(d, F)))
            calls.append((f"res1@{t} tobytes", lambda d=data: dev.add_tobytes(d, F)))
        elif kind == "res1_jpeg":
            calls.append((f"res1_jpeg@{t}", lambda d=data: dev.add_pixels3d(d, F)))
        elif kind in ("webp", "wll_R", "png_R"):
            hint = "x.png" if kind == "png_R" else "x.webp"
            calls.append((lname, lambda d=data, h=hint: dev.copy(d, h)))
        elif kind in ("wll_resD", "zstd_resD"):
            D = decode(saved[f"{key}/webp@{t}"].tobytes())
            fn = dev.add_mod if kind == "wll_resD" else dev.zstd_mod
            calls.append((lname, lambda d=data, D=D, fn=fn: fn(d, D)))
    return calls


class _RandomScores:
    """Scores of a synthetic eigenspace: a new random vector per view (every cell changes)."""

    def __init__(self, n: int, rng: np.random.Generator) -> None:
        self.n, self.rng = n, rng

    def __call__(self, phi_deg: float, theta_deg: float) -> np.ndarray:
        return self.rng.standard_normal(self.n).astype(np.float32)


def proxy_layers(work: Path, name: str, size: int) -> str | None:
    """Layer files at ``size`` px for the timing when no database of that size was measured:
    ``R`` ray-cast at ``size`` with the volume's settings, ``F`` the measured view's rested
    frame upsampled (bilinear) -- a rougher F than a real one, so residual layers somewhat
    larger; the blend then is the synthetic eigenspace of ``benchmarks/bench_reconstruct.py``
    at that size (as ``bench_device.py`` times sizes without a model)."""
    import dataclasses

    from PIL import Image

    from host.evaluate.masks import alpha_object_mask
    from host.fit.model import HostModel
    from host.render.settings import RenderSettings, ViewRenderer

    npz = work / f"{name}.layers.npz"
    if not npz.exists():
        return None
    proxy = f"{name.split('-')[0]}-{size}proxy"
    out = work / f"{proxy}.layers.npz"
    if out.exists():
        return proxy
    model = HostModel.load(work / f"{name}.ecs")
    settings = dataclasses.replace(
        RenderSettings.from_record(model.render_settings, what=name), width=size, height=size)
    scene = ViewRenderer.open(settings, None, None, what=name)
    saved = np.load(npz)
    arrays: dict[str, np.ndarray] = {}
    for key in sorted({k.split("/")[0] for k in saved.files if k.startswith("view")}):
        view = tuple(float(x) for x in saved[f"{key}/view"])
        R, alpha = scene.render(*view)
        mask = alpha_object_mask(alpha)
        F = np.asarray(Image.fromarray(saved[f"{key}/F"]).resize((size, size),
                                                                   Image.Resampling.BILINEAR))
        quality = Quality(R, mask)
        files: dict[str, bytes] = {"wll_R": webp(R, 100, lossless=True), "png_R": png(R)}
        res = offset_residual(R, F, 1)

        def code(q: int, res: np.ndarray = res, F: np.ndarray = F) -> tuple[int, np.ndarray]:
            data = webp(res, q)
            return len(data), add_residual(F, decode(data), 1)

        def plain(q: int, R: np.ndarray = R) -> tuple[int, np.ndarray]:
            data = webp(R, q)
            return len(data), decode(data)

        lres = Ladder(code, list(range(1, 101)), quality)
        lweb = Ladder(plain, list(range(1, 101)), quality)
        for t in (0.95, 0.99):
            hit = lres.reach(t)
            if hit:
                files[f"res1@{t}"] = webp(res, hit["setting"])
                files[f"res1_jpeg@{t}"] = jpeg444(res, hit["setting"])
            hit = lweb.reach(t)
            if hit:
                files[f"webp@{t}"] = webp(R, hit["setting"])
                D = decode(files[f"webp@{t}"])
                eD = (R.astype(np.int16) - D.astype(np.int16)).astype(np.uint8)
                files[f"wll_resD@{t}"] = webp(eD, 100, lossless=True)
                files[f"zstd_resD@{t}"] = zstd(eD.tobytes())
        arrays.update({f"{key}/{n}": np.frombuffer(d, np.uint8) for n, d in files.items()})
        arrays[f"{key}/F"] = F
        arrays[f"{key}/view"] = np.array(view)
        print(f"  {proxy} {key}: layers {', '.join(f'{n} {len(d)}' for n, d in files.items())}",
              flush=True)
    np.savez_compressed(out, **arrays)
    return proxy


def timing(work: Path, names: Sequence[str], views: int = 6, repeat: int = 5) -> dict:
    """One core: a layer's decode + add against the blend of a new view, interleaved.

    For each volume with a model and saved layers: the blend (``Reconstructor.update`` of a
    new view's predicted scores after another view's, one thread, as
    ``benchmarks/device_correction.py``) and, per saved layer file, ``pygame.image.load``
    then the numpy add/clip into the frame (residual layers) or the copy into it (``R``
    layers); thread CPU time, medians."""
    from device_runtime.prediction import Predictor, prediction_view
    from device_runtime.reconstruct import Reconstructor
    from protocol.image import read_image

    out: dict[str, Any] = {"affinity": sorted(os.sched_getaffinity(0)),
                           "openblas": os.environ.get("OPENBLAS_NUM_THREADS"),
                           "load": os.getloadavg()[0], "volumes": {}}
    for name in names:
        ecs, npz = work / f"{name}.ecs", work / f"{name}.layers.npz"
        if not npz.exists():
            continue
        if ecs.exists():
            image = read_image(ecs)
            predictor = Predictor(image)
            rec = Reconstructor.from_image(image, threads=1)
            shape = tuple(image.image_shape)
        else:  # a proxy: the synthetic eigenspace bench_device.py times sizes without a model
            sys.path.insert(0, str(REPO / "benchmarks"))
            from bench_reconstruct import make_eigenspace

            size = int(name.split("-")[1].removesuffix("proxy"))
            rec = Reconstructor(**make_eigenspace(size), threads=1)
            rng = np.random.default_rng(0)
            predictor = _RandomScores(rec.n_coefficients, rng)
            shape = (size, size)
        saved = np.load(npz)
        keys = sorted({k.split("/")[0] for k in saved.files if k.startswith("view")})
        dev = _Device(shape)
        calls = {key: _layer_calls(dev, saved, key) for key in keys}
        drag = [prediction_view(17.0 + 3.0 * i, 15.0) for i in range(views)]
        other = predictor(*prediction_view(200.0, 15.0))
        times: dict[str, list[float]] = {"blend": []}
        for _ in range(repeat):
            for i, view in enumerate(drag):
                rec.update(other)
                y = predictor(*view)
                c0 = time.thread_time()
                rec.update(y)
                times["blend"].append(time.thread_time() - c0)
                for label, fn in calls[keys[i % len(keys)]]:
                    c0 = time.thread_time()
                    fn()
                    times.setdefault(label, []).append(time.thread_time() - c0)
        rec.close()
        blend = statistics.median(times["blend"])
        out["volumes"][name] = {
            "size": int(shape[0]), "blend_ms": 1e3 * blend, "synthetic": not ecs.exists(),
            **{k: {"ms": 1e3 * statistics.median(v), "ratio": statistics.median(v) / blend}
               for k, v in sorted(times.items()) if k != "blend"}}
    return out


# --------------------------------------------------------------------------- report


def _stats(values: list[float]) -> str:
    v = [x for x in values if x is not None and math.isfinite(x)]
    if not v:
        return "-"
    return f"{statistics.median(v):.2f} ({max(v):.2f})"


def summarize(result: dict) -> dict:
    """Per candidate and target: the median and worst (max) ratio to WebP and to AVIF over
    the views both reach, how many views each reaches, and the median bytes."""
    views = result["per_view"]
    out: dict[str, Any] = {}
    for name in LOSSY_ORDER:
        if not any(name in v["lossy"] for v in views):
            continue
        row = {}
        for t in TARGETS:
            key = str(t)
            rw, ra, b = [], [], []
            for v in views:
                if name not in v["lossy"]:
                    continue
                hit, w, a = (v["lossy"][name][key], v["lossy"]["webp"][key],
                             v["lossy"]["avif"][key])
                if hit is None:
                    continue
                b.append(hit["bytes"])
                if w:
                    rw.append(hit["bytes"] / w["bytes"])
                if a:
                    ra.append(hit["bytes"] / a["bytes"])
            row[key] = {"webp": rw, "avif": ra, "bytes": b, "reached": len(b)}
        out[name] = row
    return out


def _stages(name: str, steps: list[list], view: dict) -> list[list]:
    """A plan's steps as its stages (before any layer, the first lossy layer[, the layer to
    0.99], exact), layer kinds without their targets. Results of an earlier version of this
    script listed only the steps that sent something; their stages are rebuilt here."""
    def kind(x: list, k: str | None = None) -> list:
        return [*x[:4], k if k is not None else str(x[4]).split("@")[0]]

    rest = list(steps)
    if rest[0][4] in ("correction", "own frame"):
        s0 = kind(rest.pop(0))
    else:
        s0 = [view["ssim_own"], 0, None, None, "own frame"]
    layer = [x for x in rest if "@" in str(x[4]) and str(x[4]).split("@")[1] in ("0.95", "0.97")
             and not str(x[4]).startswith("wll")]
    new = [x for x in rest if x[4] in BEST_FROM or x[4] == "reached"]
    s1 = kind(layer[0]) if layer else (kind(new[0]) if new else kind(s0, "reached"))
    second = [x for x in rest if x[4] in ("residual@0.99", "webp@0.99")
              or (x[4] in ("residual", "webp") and x is not (new[0] if new else None))]
    out = [s0, s1]
    if "0.99" in name and second:
        out.append(kind(second[-1]))
    out.append(kind(rest[-1]))
    return out


def _worst(values: list[float]) -> str:
    v = [x for x in values if x is not None and math.isfinite(x)]
    return f"{statistics.median(v):.2f} / {max(v):.2f}" if v else "-"


def overview(results: list[dict], timing_result: dict | None) -> list[str]:
    """The bars, per volume: the host's choice per view (`best`: the smallest of the
    residual after the correction, the residual against the own frame with no correction,
    and WebP of R) against WebP and AVIF of R; the plan one lossy layer then WebP lossless
    of R against WebP lossless of R; how often the correction is skipped."""
    lines = ["## The bars, per volume", "",
             "`best` = per view the smallest of " + ", ".join(BEST_FROM) + " reaching the "
             "target (cumulative, the correction included where sent). Ratios median / worst "
             "over the views. `exact` = `best@0.95 > exact` (one lossy layer, then WebP "
             "lossless of R) / WebP lossless of R; `+0.99` = with a second lossy layer to "
             "0.99 in between. `skip` = views whose cheapest first layer (at 0.95) needs no "
             "correction.", "",
             "| volume | own / F SSIM | c B | " + " | ".join(
                 f"{t} /WebP | {t} /AVIF" for t in TARGETS) + " | exact | +0.99 | skip |",
             "|---|---|---|" + "---|---|" * len(TARGETS) + "---|---|---|"]
    for r in results:
        views = r["per_view"]
        cells = [f"{statistics.median(v['ssim_own'] for v in views):.3f} / "
                 f"{statistics.median(v['ssim_F'] for v in views):.3f}",
                 f"{statistics.median(v['correction_bytes'] for v in views):.0f}"]
        for t in TARGETS:
            rw, ra = [], []
            for v in views:
                hit, w, a = (v["lossy"]["best"][str(t)], v["lossy"]["webp"][str(t)],
                             v["lossy"]["avif"][str(t)])
                if hit and w:
                    rw.append(hit["bytes"] / w["bytes"])
                if hit and a:
                    ra.append(hit["bytes"] / a["bytes"])
            cells += [_worst(rw), _worst(ra)]
        for plan in ("best@0.95 > exact", "best@0.95 > 0.99 > exact"):
            cells.append(_worst([v["plans"][plan][-1][1] / v["exact"]["wll_R"]
                                 for v in views if plan in v["plans"]]))
        skip = sum(1 for v in views if v["lossy"]["best"]["0.95"]
                   and v["lossy"]["best"]["0.95"]["from"] in ("res_own", "webp"))
        cells.append(f"{skip}/{len(views)}")
        lines.append(f"| {r['name']} | " + " | ".join(cells) + " |")
    lines.append("")
    return lines


def _md_candidates(r: dict, views: list[dict]) -> list[str]:
    """A volume's lossy candidates: bytes to each target against WebP and AVIF."""
    lines = []
    s = summarize(r)
    head = "| candidate | " + " | ".join(
        f"{t} bytes | /WebP | /AVIF | n" for t in TARGETS) + " |"
    lines += [head, "|" + "---|" * (1 + 4 * len(TARGETS))]
    for name, row in s.items():
        cells = []
        for t in TARGETS:
            e = row[str(t)]
            med = f"{statistics.median(e['bytes']):.0f}" if e["bytes"] else "-"
            cells.append(f"{med} | {_stats(e['webp'])} | {_stats(e['avif'])} | "
                         f"{e['reached']}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    # how often best picks what
    picks: dict[str, dict[str, int]] = {}
    for t in TARGETS:
        for v in views:
            hit = v["lossy"]["best"][str(t)]
            if hit:
                picks.setdefault(str(t), {}).setdefault(hit["from"], 0)
                picks[str(t)][hit["from"]] += 1
    lines += ["", "`best` picks: " + "; ".join(
        f"{t}: " + ", ".join(f"{k} {n}" for k, n in sorted(p.items()))
        for t, p in picks.items()), ""]
    return lines


def _md_exact(views: list[dict]) -> list[str]:
    """A volume's exact layers: bytes against WebP lossless of the ray-cast."""
    wll = [v["exact"]["wll_R"] for v in views]
    lines = ["Exact (bytes, median (worst) ratio to WebP lossless of R; `cumulative` "
             "includes the lossy base):", "", "| coding | median bytes | /WLL(R) |",
             "|---|---|---|"]
    keys = [k for k in views[0]["exact"]]
    for v in views[1:]:
        keys += [k for k in v["exact"] if k not in keys]
    for k in keys:
        vals, ratios = [], []
        for v, w in zip(views, wll):
            e = v["exact"].get(k)
            if e is None:
                continue
            b = e if isinstance(e, int) else e["cumulative"]
            vals.append(b)
            ratios.append(b / w)
        if not vals:
            continue
        label = k if k in ("wll_R", "png_R", "zstd_R", "wll_resF", "zstd_resF") else \
            f"{k} (cumulative)"
        lines.append(f"| {label} | {statistics.median(vals):.0f} | {_stats(ratios)} |")
        if not isinstance(views[0]["exact"].get(k, 0), int):
            layer = [v["exact"][k]["layer"] / w for v, w in zip(views, wll)
                     if k in v["exact"]]
            lines.append(f"| {k} (layer alone) | - | {_stats(layer)} |")
    return lines


def _md_plans(views: list[dict]) -> list[str]:
    """A volume's layer plans, stage by stage."""
    lines = ["", "Layer plans (per step: median object SSIM @ median cumulative bytes, "
             "then the cumulative bytes as median (worst) ratio to the smallest WebP of R "
             "reaching that step's SSIM on that view / to the smallest AVIF; the exact "
             "step to WebP lossless of R). Stages: before any layer (the correction, or "
             "the own frame when none is sent) -> the first lossy layer (`reached`: the "
             "frame already reaches the target, nothing sent) [-> a layer to 0.99: the "
             "residual against the frame shown or WebP of R, the smaller] -> exact (WebP "
             "lossless of R, or of (R - D) mod 256 after a WebP of R, the smaller). What "
             "each stage was, per view, in brackets:", ""]
    plan_names = []
    for v in views:
        plan_names += [p for p in v["plans"] if p not in plan_names]
    for p in plan_names:
        rows = [v for v in views if p in v["plans"]]
        staged = [_stages(p, v["plans"][p], v) for v in rows]
        n_steps = min(len(x) for x in staged)  # stages: before, layer 1[, 0.99], exact
        parts = []
        for k in range(n_steps):
            st = [x[k] for x in staged]
            rw = [x[1] / x[2] for x in st if x[2]]
            ra = [x[1] / x[3] for x in st if x[3]]
            kinds: dict[str, int] = {}
            for x in st:
                kinds[x[4]] = kinds.get(x[4], 0) + 1
            what = ", ".join(f"{kk} {n}" for kk, n in sorted(kinds.items()))
            tail = f" / {_stats(ra)}" if ra else ""
            parts.append(f"{statistics.median(x[0] for x in st):.3f} @ "
                         f"{statistics.median(x[1] for x in st):.0f} B = {_stats(rw)}"
                         f"{tail} [{what}]")
        lines.append(f"* `{p}` ({len(rows)} views): " + " -> ".join(parts))
    return lines


def _md_volume(r: dict) -> list[str]:
    """One volume's section: correction, lossy candidates, exact layers, plans, tiles and
    the decode agreement."""
    views = r["per_view"]
    lines = [f"## {r['name']} ({r['size']} px, {len(views)} views `{r['views']}`, own frame "
             f"{r['own_frame']})", ""]
    c = [v["correction_bytes"] for v in views]
    lines.append(
        f"Correction: median {statistics.median(c):.0f} B (max {max(c)}); object SSIM of "
        f"own frame median {statistics.median(v['ssim_own'] for v in views):.3f}, of F "
        f"{statistics.median(v['ssim_F'] for v in views):.3f} (min "
        f"{min(v['ssim_F'] for v in views):.3f}). Device mask (F non-black, dilated "
        f"{MASK_DILATE} px) misses median "
        f"{100 * statistics.median(v['mask_misses_object'] for v in views):.2f} % of the "
        "object's pixels.")
    lines.append("")
    lines += _md_candidates(r, views)
    lines += _md_exact(views)
    lines += _md_plans(views)
    tiles: dict[str, list[float]] = {}
    for v in views:
        for k, x in v["tiles"].items():
            tiles.setdefault(k, []).append(x)
    lines += ["", "Tiles (bytes of n x n independent files / one file, median (worst)): "
              + "; ".join(f"{k} {_stats(x)}" for k, x in tiles.items()), ""]
    da = r["decode_agreement"]
    lines += [f"Lossy WebP decode agreement ({da['files']} files, Pillow libwebp "
              f"{da['pillow_libwebp']}, pygame {da['pygame']} libwebp "
              f"{da.get('pygame_libwebp') or 'not recorded'}): files whose decode "
              "differs from Pillow's "
              f"{da['differs_from_pillow']}, largest difference "
              f"{da['max_level_difference']}"
              + (f"; dwebp: {da['dwebp_libwebp']}" if "dwebp_libwebp" in da else ""), ""]
    return lines


def _md_timing(timing_result: dict) -> list[str]:
    """The device cost of a layer against the blend, one core."""
    lines = ["## Device cost of a layer (one core)", "",
             f"CPUs {timing_result['affinity']}, OPENBLAS_NUM_THREADS="
             f"{timing_result['openblas']}, load {timing_result['load']:.1f}. Thread CPU "
             "time, median; ratio to the blend (`Reconstructor.update` of a new view's "
             "predicted scores) interleaved in the same run. Layer files per view: "
             "`res1@t` the residual against F (`pixels3d`: added from a view of the "
             "surface; `tobytes`: from a copy), `res1_jpeg@t` the same as JPEG 4:4:4, "
             "`webp@t` / `wll_R` / `png_R` the ray-cast copied into the frame, "
             "`wll_resD@t` / `zstd_resD@t` the mod-256 exact residual added to the "
             "`webp@t` frame. `NAME-512proxy`: no 512 database was measured, so R is "
             "ray-cast at 512 with the volume's settings, F is the 256 F upsampled "
             "(bilinear; a rougher F, so larger residual layers) and the blend is "
             "`benchmarks/bench_reconstruct.py`'s synthetic 512 eigenspace (as "
             "`bench_device.py` times sizes without a model).", "",
             "| volume | px | blend ms | layer: ms (x blend) |", "|---|---|---|---|"]
    for name, v in timing_result["volumes"].items():
        parts = [f"{k} {x['ms']:.2f} ({x['ratio']:.2f}x)" for k, x in v.items()
                 if isinstance(x, dict)]
        lines.append(f"| {name} | {v['size']} | {v['blend_ms']:.2f} | "
                     + "; ".join(parts) + " |")
    lines.append("")
    return lines


def write_markdown(results: list[dict], timing_result: dict | None, path: Path,
                   command: str) -> None:
    lines = [
        "# The true picture at rest: refinement layers, measured",
        "",
        f"Reproduce: `{command}` (`research/rest_layers.py`; {time.strftime('%Y-%m-%d')}, "
        f"load {os.getloadavg()[0]:.1f} on a shared 2-core machine).",
        "",
        "Per view: `F` = the device's own frame + the complete correction at rest "
        "(`ServedFrames.at_rest`, `c` its packet bytes), `S` = the own frame, `R` = the "
        "ray-cast. Bytes to reach each object SSIM as **median (worst)** ratio over the views to "
        "the smallest WebP (method 6) / AVIF (speed 4) file of `R` of that object SSIM on the "
        "same view. Candidates starting `res` include `c` (`res_own`: no correction); where `F` "
        "already reaches the target they cost `c`. `best` = the smallest of "
        f"{', '.join(BEST_FROM)} per view (what a pygame device can decode). `n` = views that "
        "reach the target (of the views measured).",
        "",
    ]
    lines += overview(results, timing_result)
    for r in results:
        lines += _md_volume(r)
    if timing_result:
        lines += _md_timing(timing_result)
    head = ""
    if path.exists() and MARKER in path.read_text():  # the hand-written findings above it
        head = path.read_text().split(MARKER)[0]
        lines = lines[2:]  # the title is the findings'
    path.write_text(head + MARKER + "\n\n" + "\n".join(lines) + "\n")


# --------------------------------------------------------------------------- main


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--volumes", default=",".join(DEFAULT_VOLUMES),
                   help="NAME-SIZE databases (CACHE/NAME-SIZE.cdb, used once NAME-SIZE.done "
                        "exists); default: all shared ones")
    p.add_argument("--cache", default="/work/cache", help="where the databases are")
    p.add_argument("--work", default=str(REPO / "bench-out" / "rest_layers"),
                   help="models, per-volume results and layer files")
    p.add_argument("--views", default="random:12:7", help="novel views (default random:12:7)")
    p.add_argument("--out", default=str(REPO / "research" / "rest_layers.md"))
    p.add_argument("--redo", action="store_true", help="measure volumes already measured")
    p.add_argument("--no-timing", action="store_true", help="skip the one-core timing")
    p.add_argument("--report-only", action="store_true",
                   help="only rewrite --out from the volumes already measured (no timing)")
    p.add_argument("--timing-only", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    names = [n.strip() for n in args.volumes.split(",") if n.strip()]
    if args.timing_only:  # the child pinned to one core
        print(json.dumps(timing(work, names)))
        return 0
    have_cwebp = shutil.which("cwebp") is not None
    results = []
    for name in names:
        db = Path(args.cache) / f"{name}.cdb"
        done = Path(args.cache) / f"{name}.done"
        out = work / f"{name}.json"
        if out.exists() and not args.redo:
            results.append(json.loads(out.read_text()))
            print(f"{name}: measured before ({out})", flush=True)
            continue
        if args.report_only:
            continue
        if not done.exists():
            print(f"{name}: not ready ({done} missing), skipped", flush=True)
            continue
        print(f"{name}: measuring", flush=True)
        result = run_volume(name, db, work, args.views, have_cwebp)
        out.write_text(json.dumps(result))
        results.append(result)
    timing_result = None
    if args.report_only:
        args.no_timing = True
    if args.no_timing and (work / "timing.json").exists():  # the last timing run's
        timing_result = json.loads((work / "timing.json").read_text())
    timed = [r["name"] for r in results]
    if not args.no_timing and results and not any(r["size"] >= 512 for r in results):
        proxy = proxy_layers(work, results[0]["name"], 512)
        if proxy:
            timed.append(proxy)
    if not args.no_timing and results:
        env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1",
               "NUMBA_NUM_THREADS": "1"}
        cmd = ["taskset", "-c", "0", sys.executable, __file__, "--timing-only", "--work",
               str(work), "--volumes", ",".join(timed)]
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
        if proc.returncode == 0:
            timing_result = json.loads(proc.stdout.strip().splitlines()[-1])
            (work / "timing.json").write_text(json.dumps(timing_result))
        else:
            print(f"timing failed: {proc.stderr.strip().splitlines()[-1:]}", flush=True)
    write_markdown(results, timing_result, Path(args.out),
                   "nice -n 10 .venv/bin/python research/rest_layers.py "
                   + " ".join(a for a in (argv if argv is not None else sys.argv[1:])
                              if a != "--report-only"))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
