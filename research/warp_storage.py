"""Issue 15's storage question: what depth costs, and eigencast + depth against WebP + depth.

docs/design-notes.md, "The depth eigenspace", "Storage against image databases". For the
shared tooth and VisMale head at 256 and 512 (the
cached databases and models ``/work/cache/{tooth,vismale_head}-{256,512}.{cdb,ecs}``, the
paper's grid of 1500 views) and the 20 held-out views of sections 9.1 / 9.5
(``random:20:15``, ray-cast truth cached by ``research/warp_views.py`` in ``--warp-cache``),
every novel view is made by the product's warp (`device_runtime.synthesis.forward_warp`
through `Warper.warp`: nearest splats, tent filter, z-test, hole filling) from the 4
neighbours of the model's bilinear interpolation, and scored by object SSIM / FLIP:

``eigencast``
    Colour: each neighbour's training scores quantized to the model's score step,
    reconstructed from the int8 eigenspace (`HostModel.reconstruct`), optionally at a lower
    colour threshold (`HostModel.truncated`, ``--colour-thresholds``). Depth: the product's
    depth eigenspace (`host.fit.depth.fit_depth_eigenspaces`) of the product's depth maps (half
    the image size: the 2 x 2 mean of the half-opacity depth, float16, as
    `host.render.cinema.encode_depth` stores it; at 512 the 256 ray-cast of the research
    cache stands in for the 2 x 2 mean of a 512 one), at every depth threshold
    ``--depth-thresholds`` and table noise ``--depth-mse`` (mm^2 per pixel), upsampled x2.
    Bytes: the device image (`image_size` of the cached model: no annex) + the standalone
    table as ``fit --standalone`` writes it (`add_standalone_table`) + the depth sections as
    ``fit --depth`` writes them (`host.fit.depth.depth_sections`), each zstd-compressed at
    the image's level; for the default settings the whole ``.ecs`` is written and its
    device size read back (``ecs_bytes``).
``webp_depth``
    A "WebP + depth" image database: every training view as a WebP file (quality
    ``--webp-qualities``, `host.evaluate.encode_image`, method 6) and its depth map at half
    resolution (the same maps as above, true, not an eigenspace), quantized to
    ``--db-depth-steps`` mm as uint16 (0 = no object; the background within 2 pixels of the
    object keeps its nearest object depth so the x2 upsampling is right at silhouettes), each
    view's map as the smaller of a 16-bit PNG and a zstd frame (level 19) of its row-delta
    zigzag byte planes. The decoded WebP colour and the upsampled depth go through the same
    warp (object pixels: decoded colour above `OBJECT_LEVEL` where the depth map has depth).
``webp_blend``
    Today's ghosting WebP image database (section 5 / 9.6): the decoded WebP neighbours
    blended with the interpolation weights (`host.evaluate.WebPDatabase`'s frame).

Storage of the WebP databases: every ``--storage-stride``-th training view is encoded
(stride 10: 150 of the 1500) and the mean file size times 1500 is reported (the 80 or so
neighbours the held-out views use are encoded as well, for their frames only).

Usage::

    nice -n 5 .venv/bin/python research/warp_storage.py [--volumes tooth,vismale_head] \\
        [--sizes 256,512] [--views 20] [--seed 15] [-o /work/cache/warpstore/results.json]

Everything is cached under ``--cache`` (default ``/work/cache/warpstore``): the product depth
maps per volume and size, the WebP files' sizes and decoded neighbours, and the per-case
results (a rerun skips finished cases; ``--fresh`` recomputes them).
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import itertools
import json
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import zstandard

from device_runtime.synthesis import DepthEigenspace, upsample2
from host.evaluate import compare_images, encode_image
from host.evaluate.masks import OBJECT_LEVEL, alpha_object_mask
from host.fit.depth import (
    DEPTH_CELL,
    DEPTH_SCORE_MSE,
    DEPTH_SCORE_NOISE_Z2,
    depth_sections,
    fill_nearest,
    fit_depth_eigenspaces,
    quantize_depth_table,
)
from host.fit.model import HostModel, add_standalone_table, score_step_for
from host.render.camera import parse_view_set
from host.render.cinema import CinemaDB
from protocol.image import DEFAULT_LEVEL, HEADER_SIZE, image_size, write_image
from research.warp_views import Volume, Warper, study_parser, variant_depth

#: Depth score noise of the fit used to re-quantize at every ``--depth-mse`` (mm^2 / pixel):
#: fine enough that rounding twice adds nothing measurable.
FINE_MSE = 0.002
#: Pixels (half resolution) around the object whose depth a WebP + depth view keeps.
BAND = 2
CCTX = zstandard.ZstdCompressor(level=DEFAULT_LEVEL)


def zsize(a: np.ndarray) -> int:
    """zstd size at the image's level, as one ``.ecs`` section."""
    return len(CCTX.compress(np.ascontiguousarray(a).tobytes()))


# ----------------------------------------------------------------------------- depth maps


def product_depths(vol: Volume, size: int, cache: Path) -> tuple[np.ndarray, np.ndarray]:
    """The product's depth maps of every training view for ``size`` frames.

    Returns
    -------
    raw : ndarray (n, size/2, size/2) float32
        mm along the rays, NaN off the object (`encode_depth`'s maps: float16 after the
        offset is subtracted).
    filled : same shape, `fill_nearest` of ``raw`` (what the eigenspace is fitted to).
    """
    half = size // 2
    rp = cache / f"{vol.name}-{size}-depth-raw.npy"
    fp = cache / f"{vol.name}-{size}-depth-filled.npy"
    if rp.exists() and fp.exists():
        return np.load(rp, mmap_mode="r"), np.load(fp, mmap_mode="r")
    train = vol.training_depths()  # (n, 256, 256, 2)
    n = train.shape[0]
    raw = np.lib.format.open_memmap(rp.with_suffix(".tmp.npy"), mode="w+", dtype=np.float32,
                                    shape=(n, half, half))
    filled = np.lib.format.open_memmap(fp.with_suffix(".tmp.npy"), mode="w+",
                                       dtype=np.float32, shape=(n, half, half))
    off = vol.distance
    t0 = time.perf_counter()
    for i in range(n):
        d = variant_depth(np.asarray(train[i]), "half").astype(np.float64)
        if half != d.shape[0]:  # 2x2 mean of finite values (encode_depth)
            b = d.reshape(half, 2, half, 2).swapaxes(1, 2).reshape(half, half, 4)
            ok = np.isfinite(b)
            cnt = ok.sum(axis=2)
            tot = np.where(ok, b, 0.0).sum(axis=2)
            d = np.full((half, half), np.nan)
            np.divide(tot, cnt, out=d, where=cnt > 0)
        d = (d - off).astype(np.float16).astype(np.float32) + np.float32(off)
        raw[i] = d
        filled[i] = fill_nearest(d)
        if (i + 1) % 500 == 0:
            print(f"  {vol.name}-{size} depth maps {i + 1}/{n} ({time.perf_counter() - t0:.0f} s)",
                  file=sys.stderr, flush=True)
    raw.flush()
    filled.flush()
    del raw, filled
    rp.with_suffix(".tmp.npy").rename(rp)
    fp.with_suffix(".tmp.npy").rename(fp)
    return np.load(rp, mmap_mode="r"), np.load(fp, mmap_mode="r")


# ----------------------------------------------------------------------------- eigencast


def depth_section_bytes(eig: DepthEigenspace, order: np.ndarray) -> dict:
    """zstd bytes of the depth sections as ``fit --depth`` writes them, with the plain and
    delta-coded table both measured (``table_plain``, ``table_delta``), and the int8 table
    where it fits (``table_int8``)."""
    out = {}
    for delta in (False, True):
        secs = depth_sections(eig, order if delta else None)
        sizes = {k: zsize(v) for k, v in secs.items()}
        table = sizes.pop("depth_scores_delta" if delta else "depth_scores")
        out["table_delta" if delta else "table_plain"] = table
        out["other"] = sizes
    lim = int(np.abs(eig.table).max()) if eig.table.size else 0
    out["table_int8"] = zsize(eig.table.astype(np.int8)) if lim <= 127 else None
    out["components"] = int(eig.n_components)
    out["rest"] = int(sum(out["other"].values()))
    out["total_plain"] = out["rest"] + out["table_plain"]
    out["total_delta"] = out["rest"] + out["table_delta"]
    return out


def colour_setting(model: HostModel, threshold: float) -> HostModel:
    """The cached model, or its truncation to a lower colour threshold."""
    if model.threshold is not None and threshold >= model.threshold - 1e-9:
        return model
    counts = model.components_for(threshold=threshold)
    step = score_step_for(counts, model.image.cell_values)
    return model.truncated(counts, score_step=step)


def colour_bytes(model: HostModel) -> dict:
    """Device image (no annex) and standalone table bytes (``fit --standalone``'s choice)."""
    image = dataclasses.replace(model.image, sections=dict(model.image.sections))
    info = add_standalone_table(image, model.training_scores, eigenvalues=model.eigenvalues)
    table = zsize(image.sections[info["section"]])
    if model.path is not None:
        with open(model.path, "rb") as f:
            dev = image_size(f.read(HEADER_SIZE))
    else:
        dev = ecs_bytes(model.image)
    return {"image": int(dev), "standalone_table": int(table), "K": int(model.image.n_coefficients)}


def write_ecs(model: HostModel, eig: DepthEigenspace, order: np.ndarray) -> int:
    """Device size of the ``.ecs`` that ``fit --standalone --depth`` would write for this
    colour model and depth eigenspace (the smaller table codings, as `add_depth` picks)."""
    image = dataclasses.replace(model.image, sections=dict(model.image.sections))
    add_standalone_table(image, model.training_scores, eigenvalues=model.eigenvalues)
    plain, coded = depth_sections(eig), depth_sections(eig, order)
    image.sections.update(coded if zsize(coded["depth_scores_delta"]) < zsize(
        plain["depth_scores"]) else plain)
    image.synthesis = {"method": "warp-depth-1", "fov_deg": 30.0, "distance_mm": 1.0,
                       "z_tolerance_mm": 1.0, "depth_shape": list(eig.shape),
                       "depth_cell": eig.cell, "depth_step": eig.step,
                       "depth_offset_mm": eig.offset, "depth_threshold": 0.9}
    return ecs_bytes(image)


def ecs_bytes(image: object) -> int:
    """Size of ``image`` written as a device image (no annex)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "m.ecs"
        write_image(path, image, annex=None)
        with open(path, "rb") as f:
            return image_size(f.read(HEADER_SIZE))


# ----------------------------------------------------------------------------- WebP + depth


def db_depth_code(raw: np.ndarray, step: float, lo: float) -> np.ndarray:
    """A half-resolution depth map as the WebP + depth database stores it: uint16
    ``round((d - lo) / step) + 1``, 0 where there is no object within `BAND` pixels."""
    from scipy.ndimage import binary_dilation

    ok = np.isfinite(raw)
    keep = binary_dilation(ok, iterations=BAND) if ok.any() else ok
    d = fill_nearest(raw)
    q = np.clip(np.rint((d - lo) / step) + 1, 1, 65535).astype(np.uint16)
    q[~keep] = 0
    return q


def db_depth_decode(q: np.ndarray, step: float, lo: float) -> tuple[np.ndarray, np.ndarray]:
    """(depth at twice the size, float32; has-depth mask at twice the size)."""
    d = q.astype(np.float32) * np.float32(step) + np.float32(lo - step)
    has = q > 0
    return upsample2(d), np.repeat(np.repeat(has, 2, axis=0), 2, axis=1)


def depth_file_bytes(q: np.ndarray) -> dict:
    """A coded depth map's file: 16-bit PNG, or zstd -19 of row-delta zigzag byte planes."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(q.astype(np.uint16)).save(buf, format="PNG", optimize=True)
    wide = q.astype(np.int32)
    diff = np.empty_like(wide)
    diff[:, 0] = wide[:, 0]
    diff[:, 1:] = wide[:, 1:] - wide[:, :-1]
    zz = ((diff << 1) ^ (diff >> 31)).astype(np.uint32)
    planes = np.stack([(zz & 0xFF), ((zz >> 8) & 0xFF), (zz >> 16) & 0xFF]).astype(np.uint8)
    z = len(zstandard.ZstdCompressor(level=19).compress(planes.tobytes()))
    out = {"png16": len(buf.getvalue()), "zstd": z}
    if int(q.max()) < 256:  # 8 bits are enough: lossless WebP of the grey map
        buf = io.BytesIO()
        Image.fromarray(q.astype(np.uint8)).convert("RGB").save(buf, format="WEBP",
                                                                lossless=True, quality=100,
                                                                method=6)
        out["webp_lossless8"] = len(buf.getvalue())
    return out


class WebPViews:
    """WebP files of a database's views at one quality: sizes (sampled) and decoded views."""

    def __init__(self, db: CinemaDB, quality: int, cache: Path, tag: str) -> None:
        self.db, self.q = db, int(quality)
        self.path = cache / f"{tag}-webp-q{self.q}.npz"
        self.sizes: dict[int, int] = {}
        self.decoded: dict[int, np.ndarray] = {}
        if self.path.exists():
            z = np.load(self.path)
            self.sizes = dict(zip(z["size_idx"].tolist(), z["size_val"].tolist()))
            self.decoded = {int(i): z[f"v{int(i)}"] for i in z["dec_idx"]}

    def get(self, i: int) -> np.ndarray:
        if i not in self.decoded:
            coded = encode_image(self.db.read_image(i), "webp", self.q)
            self.sizes[i] = coded.size_bytes
            self.decoded[i] = coded.decode()
        return self.decoded[i]

    def size(self, i: int) -> int:
        if i not in self.sizes:
            self.sizes[i] = encode_image(self.db.read_image(i), "webp", self.q).size_bytes
        return self.sizes[i]

    def save(self) -> None:
        arrays = {f"v{i}": v for i, v in self.decoded.items()}
        np.savez(self.path, size_idx=np.array(list(self.sizes), dtype=np.int64),
                 size_val=np.array(list(self.sizes.values()), dtype=np.int64),
                 dec_idx=np.array(list(self.decoded), dtype=np.int64), **arrays)


# ----------------------------------------------------------------------------- one case


class _StorageCase:
    """One volume at one size for `run_case`: the depth eigenspaces fitted finely once, the
    held-out views with their neighbours, and the scoring of a frame maker on them."""

    def __init__(self, vol: Volume, size: int, views: np.ndarray, args: argparse.Namespace,
                 cache: Path) -> None:
        self.vol, self.size, self.args, self.cache = vol, size, args, cache
        self.model0 = vol.models[size]
        self.db = db = vol.dbs[size]
        self.st = st = vol.settings[size]
        self.warper = Warper(st, st.width, st.height)
        self.n = db.n_views
        self.order = np.lexsort((np.mod(db.phi_deg, 360.0), db.theta_deg))
        self.raw, filled = product_depths(vol, size, cache)
        self.t_col = t_col = self.model0.threshold or 0.98
        self.d_ts = sorted({*args.depth_thresholds, t_col})
        lower = args.colour_thresholds_for(vol.name, t_col)[1:]
        # fit --depth's default noise for this framing (DEPTH_SCORE_NOISE_Z2 z-tolerances^2)
        self.default_mse = round(DEPTH_SCORE_NOISE_Z2 * self.warper.tol_mm ** 2, 4)
        self.mses = sorted({*args.depth_mse, self.default_mse})
        self.all_t = sorted({*args.all_t_mse, self.default_mse})
        t0 = time.perf_counter()
        self.fine = fit_depth_eigenspaces(filled, sorted({*self.d_ts, *lower}), vol.distance,
                                          DEPTH_CELL, score_mse=FINE_MSE)
        self.fit_s = time.perf_counter() - t0
        print(f"  {vol.name}-{size}: depth fit {self.fit_s:.0f} s", file=sys.stderr, flush=True)
        self.items = self._held_out(views)
        self.neigh = sorted({int(i) for it in self.items for i in it["idx"]})

    def _held_out(self, views: np.ndarray) -> list[dict]:
        """The held-out views, their truth and mask, and their neighbours' cameras."""
        items = []
        db, warper = self.db, self.warper
        for k, (phi, theta) in enumerate(views):
            phi, theta = float(phi), float(theta)
            truth, alpha = self.vol.held_out(self.size, phi, theta, k)
            idx, w = self.model0.interpolator.weights(phi, theta)
            idx = np.asarray(idx).ravel().astype(int)
            w = np.asarray(w, dtype=np.float64).ravel()
            items.append({"truth": truth, "mask": alpha_object_mask(alpha), "idx": idx, "w": w,
                          "target": warper.camera(phi, theta),
                          "sources": [warper.camera(float(db.phi_deg[i]),
                                                    float(db.theta_deg[i])) for i in idx]})
        return items

    def score(self, frames_for: Callable[[dict], np.ndarray]) -> dict:
        ss, ff = [], []
        for it in self.items:
            fr = frames_for(it)
            c = compare_images(it["truth"], fr, mask=it["mask"])
            ss.append(c.ssim_object)
            ff.append(c.flip_object)
        return {"ssim_object": float(np.mean(ss)), "flip_object": float(np.mean(ff)),
                "ssim_per_view": [float(s) for s in ss]}

    def settings(self) -> list[tuple[float, float, float]]:
        """(colour T, depth T, table noise) measured: every depth T at the noises --all-t-mse
        and the default, every noise at the colour's T, and the lower colour Ts (depth at the
        model's T and at theirs) at the default noise."""
        t_col, default_mse = self.t_col, self.default_mse
        settings = [(t_col, td, mse) for td in self.d_ts for mse in self.all_t]
        settings += [(t_col, t_col, mse) for mse in self.mses]
        settings += [(tc, td, default_mse)
                     for tc in self.args.colour_thresholds_for(self.vol.name, t_col)
                     for td in (t_col, tc)]
        return sorted(set(settings), key=lambda x: (-x[0], x[1], x[2]))

    def depth_bytes(self) -> list[dict]:
        """The depth sections' bytes of every (depth T, noise)."""
        out = []
        for td in self.d_ts:
            for mse in self.mses:
                eig = quantize_depth_table(self.fine[td], mse)
                out.append({"depth_threshold": td, "depth_mse": mse,
                            "components_per_cell": float(eig.counts.mean()),
                            **depth_section_bytes(eig, self.order)})
        return out

    def eigencast(self) -> list[dict]:
        """eigencast: colour thresholds x depth thresholds x table noise (`settings`)."""
        out = []
        settings = self.settings()
        for tc in self.args.colour_thresholds_for(self.vol.name, self.t_col):
            model = colour_setting(self.model0, tc)
            cb = colour_bytes(model)
            rec = {}
            for i in self.neigh:
                y = model.quantize(model.training_scores[i])
                c = model.reconstruct(y)
                rec[i] = (c, c.max(axis=2) > OBJECT_LEVEL)
            for tc2, td, mse in settings:
                if tc2 == tc:
                    out.append(self._eigencast_entry(model, cb, rec, tc, td, mse))
        return out

    def _eigencast_entry(self, model: HostModel, cb: dict, rec: dict, tc: float, td: float,
                         mse: float) -> dict:
        warper = self.warper
        eig = quantize_depth_table(self.fine[td], mse)
        db_bytes = depth_section_bytes(eig, self.order)

        def frame(it: dict, eig: DepthEigenspace = eig, rec: dict = rec) -> np.ndarray:
            cols = [rec[int(i)][0] for i in it["idx"]]
            oks = [rec[int(i)][1] for i in it["idx"]]
            ds = [upsample2(eig.reconstruct(int(i))) for i in it["idx"]]
            return warper.warp(cols, ds, oks, it["sources"], it["w"], it["target"])

        q = self.score(frame)
        entry = {"colour_threshold": tc, "depth_threshold": td, "depth_mse": mse,
                 "depth_step": eig.step, "colour": cb, "depth": db_bytes,
                 "depth_components_per_cell": float(eig.counts.mean()),
                 "total_delta": cb["image"] + cb["standalone_table"] + db_bytes[
                     "total_delta"],
                 "total_plain": cb["image"] + cb["standalone_table"] + db_bytes[
                     "total_plain"], **q}
        if td == self.t_col and mse in (DEPTH_SCORE_MSE, self.default_mse):
            entry["ecs_bytes"] = write_ecs(model, eig, self.order)
        print(f"  {self.vol.name}-{self.size} eigencast Tc={tc} Td={td} mse={mse}: depth "
              f"{db_bytes['total_delta'] / 1e6:.2f} MB (plain table "
              f"{db_bytes['total_plain'] / 1e6:.2f}), total {entry['total_delta'] / 1e6:.2f}"
              f" MB, SSIM {q['ssim_object']:.4f} FLIP {q['flip_object']:.4f}",
              file=sys.stderr, flush=True)
        return entry

    def webp(self, out: dict) -> None:
        """WebP + depth and today's WebP blend, into ``out``."""
        args, n, name = self.args, self.n, f"{self.vol.name}-{self.size}"
        sample = list(range(0, n, args.storage_stride))
        for qual in args.webp_qualities:
            webp = WebPViews(self.db, qual, self.cache, name)
            colours = {i: webp.get(i) for i in self.neigh}
            sizes = [webp.size(i) for i in sample]
            webp.save()
            colour_total = float(np.mean(sizes)) * n

            def blend(it: dict, colours: dict = colours) -> np.ndarray:
                acc = sum(colours[int(i)].astype(np.float32) * np.float32(wi)
                          for i, wi in zip(it["idx"], it["w"]) if wi > 0)
                return np.clip(np.rint(acc), 0, 255).astype(np.uint8)

            q = self.score(blend)
            out["webp_blend"].append({"quality": qual, "colour_bytes": colour_total, **q})
            print(f"  {name} webp blend q{qual}: {colour_total / 1e6:.2f} MB, SSIM "
                  f"{q['ssim_object']:.4f} FLIP {q['flip_object']:.4f}", file=sys.stderr,
                  flush=True)
            for dstep in args.db_depth_steps:
                if qual != args.chosen_quality and dstep != args.chosen_db_step:
                    continue
                out["webp_depth"].append(self._webp_depth_entry(qual, dstep, colours,
                                                                colour_total, sample))

    def _webp_depth_entry(self, qual: int, dstep: float, colours: dict, colour_total: float,
                          sample: list[int]) -> dict:
        warper, raw, n = self.warper, self.raw, self.n
        lo = self.vol.distance - 1.05 * self.st.radius_mm
        dep = {}
        for i in self.neigh:
            dep[i] = db_depth_decode(db_depth_code(np.asarray(raw[i]), dstep, lo), dstep, lo)
        files = [depth_file_bytes(db_depth_code(np.asarray(raw[i]), dstep, lo))
                 for i in sample]
        depth_total = float(np.mean([min(f.values()) for f in files])) * n

        def warp(it: dict, colours: dict = colours, dep: dict = dep) -> np.ndarray:
            cols = [colours[int(i)] for i in it["idx"]]
            ds = [dep[int(i)][0] for i in it["idx"]]
            oks = [(c.max(axis=2) > OBJECT_LEVEL) & dep[int(i)][1]
                   for c, i in zip(cols, it["idx"])]
            return warper.warp(cols, ds, oks, it["sources"], it["w"], it["target"])

        q = self.score(warp)
        entry = {"quality": qual, "depth_step_mm": dstep, "colour_bytes": colour_total,
                 "depth_bytes": depth_total,
                 **{f"depth_{k}": float(np.mean([f.get(k, np.nan) for f in files])) * n
                    for k in files[0]},
                 "total": colour_total + depth_total, **q}
        print(f"  {self.vol.name}-{self.size} webp+depth q{qual} step {dstep} mm: "
              f"{colour_total / 1e6:.2f} + {depth_total / 1e6:.2f} MB, SSIM "
              f"{q['ssim_object']:.4f} FLIP {q['flip_object']:.4f}", file=sys.stderr,
              flush=True)
        return entry


def run_case(vol: Volume, size: int, views: np.ndarray, args: argparse.Namespace,
             cache: Path) -> dict:
    case = _StorageCase(vol, size, views, args, cache)
    out: dict = {"default_mse": case.default_mse, "volume": vol.name, "size": size,
                 "views": len(case.items), "neighbours": len(case.neigh),
                 "colour_threshold": case.t_col, "depth_fit_s": case.fit_s, "eigencast": [],
                 "webp_depth": [], "webp_blend": []}
    out["depth_bytes"] = case.depth_bytes()
    out["eigencast"] = case.eigencast()
    case.webp(out)
    return out


def bytes_at_ssim(points: list[tuple[float, float]], ssim: float) -> float | None:
    """Bytes a curve of (object SSIM, bytes) points needs for ``ssim``: linear between the
    two points around it (the points sorted by SSIM); None outside the curve."""
    pts = sorted(points)
    for (s0, b0), (s1, b1) in itertools.pairwise(pts):
        if s0 <= ssim <= s1:
            return b0 if s1 == s0 else b0 + (b1 - b0) * (ssim - s0) / (s1 - s0)
    return None


def print_tables(cases: list[dict], db_step: float) -> None:
    mb = 1e6
    for c in cases:
        t_col, dm = c["colour_threshold"], c["default_mse"]
        print(f"\n### {c['volume']} {c['size']} ({c['views']} views; fit --depth's default "
              f"noise {dm} mm²)")
        base = next(e for e in c["eigencast"] if e["colour_threshold"] == t_col
                    and e["depth_threshold"] == t_col and e["depth_mse"] == DEPTH_SCORE_MSE)
        print("| depth T, noise mm² | depth sections MB: delta (plain table) | "
              "object SSIM / FLIP | ΔSSIM |")
        print("|---|---|---|---|")
        for e in c["eigencast"]:
            if e["colour_threshold"] != t_col:
                continue
            print(f"| {e['depth_threshold']}, {e['depth_mse']:g} | "
                  f"{e['depth']['total_delta'] / mb:.2f} ({e['depth']['total_plain'] / mb:.2f}) | "
                  f"{e['ssim_object']:.4f} / {e['flip_object']:.4f} | "
                  f"{e['ssim_object'] - base['ssim_object']:+.4f} |")
        curve = [(e["ssim_object"], e["total"]) for e in c["webp_depth"]
                 if e["depth_step_mm"] == db_step]
        print("\n| store | MB | object SSIM / FLIP | WebP + depth at that SSIM, MB |")
        print("|---|---|---|---|")
        for e in c["eigencast"]:
            if e["depth_mse"] != dm or e["depth_threshold"] not in (t_col, e[
                    "colour_threshold"]):
                continue
            at = bytes_at_ssim(curve, e["ssim_object"])
            ecs = f" (.ecs {e['ecs_bytes'] / mb:.2f})" if "ecs_bytes" in e else ""
            print(f"| eigencast colour T {e['colour_threshold']}, depth T "
                  f"{e['depth_threshold']} | {e['total_delta'] / mb:.2f}{ecs} | "
                  f"{e['ssim_object']:.4f} / {e['flip_object']:.4f} | "
                  f"{'–' if at is None else f'{at / mb:.2f}'} |")
        for e in c["webp_depth"]:
            print(f"| WebP q{e['quality']} + depth {e['depth_step_mm']:g} mm | "
                  f"{e['colour_bytes'] / mb:.2f} + {e['depth_bytes'] / mb:.2f} | "
                  f"{e['ssim_object']:.4f} / {e['flip_object']:.4f} | |")
        for e in c["webp_blend"]:
            print(f"| WebP q{e['quality']}, blended (today) | {e['colour_bytes'] / mb:.2f} | "
                  f"{e['ssim_object']:.4f} / {e['flip_object']:.4f} | |")


def main(argv: list[str] | None = None) -> int:
    ap = study_parser(__doc__.split("\n")[0])
    ap.add_argument("--limit", type=int, default=0, help="only the first N held-out views")
    ap.add_argument("--cache", default="/work/cache/warpstore")
    ap.add_argument("--warp-cache", default="/work/cache/warp",
                    help="research/warp_views.py's cache (training depths, held-out truth)")
    ap.add_argument("--depth-thresholds", default="0.9,0.95,0.98,0.99")
    ap.add_argument("--depth-mse", default=f"{DEPTH_SCORE_MSE},0.5,2,8,32",
                    help="depth table noise, mm^2 per pixel (fit --depth's default for the "
                         "case is added)")
    ap.add_argument("--all-t-mse", default=f"{DEPTH_SCORE_MSE}",
                    help="table noises measured at every depth threshold (and the default)")
    ap.add_argument("--colour-thresholds", default="tooth:0.995,0.99,0.98;"
                    "vismale_head:0.97,0.95,0.9",
                    help="lower colour thresholds per volume (besides the model's), each "
                         "measured with the depth at the model's T and at its own")
    ap.add_argument("--webp-qualities", default="20,40,60,80,95")
    ap.add_argument("--db-depth-steps", default="0.25,1,4,8,16", help="WebP + depth: mm")
    ap.add_argument("--chosen-quality", type=int, default=80)
    ap.add_argument("--chosen-db-step", type=float, default=4.0,
                    help="WebP + depth: the depth step measured at every quality")
    ap.add_argument("--storage-stride", type=int, default=10)
    ap.add_argument("--fresh", action="store_true")
    ap.add_argument("-o", "--output", default="/work/cache/warpstore/results.json")
    args = ap.parse_args(argv)
    args.depth_thresholds = [float(t) for t in args.depth_thresholds.split(",") if t]
    args.depth_mse = sorted({float(t) for t in args.depth_mse.split(",") if t})
    args.all_t_mse = sorted({float(t) for t in args.all_t_mse.split(",") if t})
    args.webp_qualities = [int(q) for q in args.webp_qualities.split(",") if q]
    args.db_depth_steps = [float(s) for s in args.db_depth_steps.split(",") if s]
    extra = {}
    for part in args.colour_thresholds.split(";"):
        if part:
            name, ts = part.split(":")
            extra[name] = [float(t) for t in ts.split(",") if t]
    args.colour_thresholds_for = lambda name, t: [t, *[x for x in extra.get(name, []) if x < t]]
    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    sizes = [int(s) for s in args.sizes.split(",") if s]
    views = parse_view_set(f"random:{args.views}:{args.seed}").angles_deg()
    if args.limit > 0:
        views = views[:args.limit]
    cases = []
    for name in [v for v in args.volumes.split(",") if v]:
        vol = None
        for size in sizes:
            path = cache / f"case-{name}-{size}-{len(views)}.json"
            if path.exists() and not args.fresh:
                cases.append(json.loads(path.read_text()))
                continue
            if vol is None:
                vol = Volume(name, Path(args.warp_cache), sizes)
            t0 = time.perf_counter()
            case = run_case(vol, size, views, args, cache)
            case["seconds"] = time.perf_counter() - t0
            path.write_text(json.dumps(case, indent=1, default=float))
            cases.append(case)
    Path(args.output).write_text(json.dumps({"views": f"random:{args.views}:{args.seed}",
                                             "cases": cases}, indent=1, default=float))
    print_tables(cases, args.chosen_db_step)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
