"""Go / no-go for issue 15: depth-aware view synthesis from the training views' depth.

For the shared tooth and VisMale head at 256 and 512 on the paper's grid (``grid:100x15``,
the cached databases and models ``/work/cache/{tooth,vismale_head}-{256,512}.{cdb,ecs}``) and
N held-out random views (``random:N:SEED``, ray-cast fresh with their opacity), every novel
view is made by:

``blend``
    Today's frame: the model's bilinear interpolation of the training scores, rounded to the
    score step, reconstructed by the device code from the int8 eigenspace (`HostModel.view`;
    a standalone device blends the same four views).
``webp_db``
    The on-device WebP image database (quality 80, `host.evaluate.WebPDatabase`): the four
    training images as decoded WebP, blended with the same weights.
``oracle``
    The held-out view projected onto the eigenspace and sent through the score packet
    (`host.evaluate.DevicePath.projection_frame`): the best the eigenspace can show.
``warp_true_{half,mean}``
    (a) The four training views the bilinear interpolation uses, from their TRUE images and
    TRUE depths (ray-cast at the frame's size with `Renderer.render_with_depth`), each
    forward-warped into the novel camera (`forward_warp`), blended by the interpolation weights
    where their depths agree, holes filled. ``half``: the depth where the opacity crosses 0.5
    (the mean where it never does); ``mean``: the opacity-weighted mean depth.
``warp_true_half_d256`` (512 only)
    (a) with the depth ray-cast at 256 and upsampled: what half-resolution depth costs.
``warp_rec_{half,mean}``
    (b) The same from what a device holds: each training view's colour reconstructed from
    the model's training scores (quantized to the score step, int8 eigenspace, device code)
    and its depth from a cell PCA of the 1500 training depth maps at 256 (`DepthEigenspace`:
    cells 16, adaptive at the colour model's threshold T, int8 components, quantized score
    table; upsampled x2 for 512).
``warp_rec_half_T<t>``
    (b) with the depth eigenspace at another threshold (``--depth-thresholds``): what the
    depth's components buy.
``warp_rec_half_truedepth``
    Diagnostic: reconstructed colour, true depth (separates colour from depth error).

Quality: object SSIM / FLIP (and PSNR) over the held-out view's object pixels (ray-cast alpha
>= `OBJECT_ALPHA_MIN`), `host.evaluate.compare_images`. "Gap closed" = (warp - blend) /
(oracle - blend) of the mean object SSIM (and of FLIP). Device cost: median ms per frame in
numpy on this machine, of the warp alone (4 views' colour and depth given) and of the whole
frame (``device_frame``: 4 colour reconstructions through the device code, 4 depth
reconstructions, upsampling at 512, the warp), with today's frame (`HostModel.view`:
interpolated scores, one reconstruction) timed in the same run.

Every parameter of the warp (z tolerance, splat filter, hole filling) is fixed here
before looking at the held-out views; nothing is tuned on them.

Cost: ray-casting the 1500 training depths at 256 (~3-5 min per volume on 2 cores, cached),
the neighbours' depths at 512 (~80 views per volume, cached) and the held-out views; then
~1-3 min per case for the frames and metrics. Everything is cached under ``--cache``
(default ``/work/cache/warp``).

Usage::

    .venv/bin/python research/warp_views.py [--volumes tooth,vismale_head] [--sizes 256,512] \\
        [--views 20] [--seed 15] [--cache /work/cache/warp] [--images docs/images] \\
        [-o /work/cache/warp/results.json]

Produces: docs/design-notes.md, "The device's own frame is a depth warp" (the
tables printed at the end, and the pictures ``docs/images/warp-<volume>.jpg``).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from device_runtime.synthesis import (
    HOLE_NEIGHBOURS,
    HOLE_PASSES,
    SPLAT_TENT,
    Z_TOLERANCE,
    DepthEigenspace,
    fill_holes,
    forward_warp,
    upsample2,
)
from device_runtime.synthesis import Warper as _Warper
from host.evaluate import DevicePath, TrainingImages, WebPDatabase, compare_images
from host.evaluate.masks import OBJECT_LEVEL, alpha_object_mask
from host.fit.depth import fill_nearest, fit_depth_eigenspaces
from host.fit.model import HostModel
from host.render.camera import parse_view_set
from host.render.cinema import CinemaDB
from host.render.raycast import DEPTH_HALF, DEPTH_MEAN
from host.render.settings import RenderSettings, ViewRenderer
from host.shared_data import shared_volume

#: The warp (z tolerance, coverage, hole filling: `forward_warp`, `fill_holes`) and the depth
#: fit are the product's, `device_runtime.synthesis` and `host.fit.depth`, imported above.
__all__ = ["Warper", "fill_holes", "forward_warp", "upsample2"]
#: The depth cells' side.
DEPTH_CELL = 16
DEPTH_SIZE = 256
#: WebP image database quality (evaluate's default).
WEBP_QUALITY = 80
#: Training views whose depth reconstruction error is reported (evenly spread).
DEPTH_CHECK_VIEWS = 60
VARIANTS = {"half": DEPTH_HALF, "mean": DEPTH_MEAN}


# ----------------------------------------------------------------------------- geometry


class Warper(_Warper):
    """`device_runtime.synthesis.Warper` for a database's recorded framing."""

    def __init__(self, settings: RenderSettings, width: int, height: int) -> None:
        if settings.projection != "perspective":
            raise SystemExit("warp_views: only perspective databases are supported")
        distance = settings.radius_mm / math.sin(math.radians(settings.fov_deg) / 2.0)
        super().__init__(settings.fov_deg, distance, width, height,
                         Z_TOLERANCE * 2.0 * settings.radius_mm)

    def camera(self, phi: float, theta: float) -> tuple[np.ndarray, np.ndarray]:
        """(position (3,), rotation (3, 3) whose columns are right, up, forward)."""
        return self.pose(phi, theta)


def variant_depth(depth2: np.ndarray, variant: str) -> np.ndarray:
    """One depth variant from (h, w, 2); ``half`` falls back to the mean where the opacity
    never reaches 0.5 (faint rims)."""
    if variant == "mean":
        return depth2[..., DEPTH_MEAN]
    half = depth2[..., DEPTH_HALF]
    return np.where(np.isfinite(half), half, depth2[..., DEPTH_MEAN])


# ----------------------------------------------------------------------------- depth PCA


def zstd_bytes(pca: DepthEigenspace, order: np.ndarray) -> dict[str, int]:
    """Compressed sizes as an ``.ecs`` would hold the depth eigenspace: int8 components and
    float16 means zstd-compressed at the image's level, the score table delta-coded in the
    standalone order like the colour's (`host.fit.model.add_standalone_table`), the scales."""
    import zstandard

    from protocol.image import DEFAULT_LEVEL

    cctx = zstandard.ZstdCompressor(level=DEFAULT_LEVEL)

    def size(a: np.ndarray) -> int:
        return len(cctx.compress(np.ascontiguousarray(a).tobytes()))

    comps = pca.components
    diffs = np.ascontiguousarray(pca.table[order].T)
    diffs[:, 1:] = diffs[:, 1:] - diffs[:, :-1]
    wide = diffs.astype(np.int32)
    zz = ((wide << 1) ^ (wide >> 15)).astype(np.uint16)
    coded = np.stack([(zz & 0xFF).astype(np.uint8), (zz >> 8).astype(np.uint8)], axis=1)
    out = {"components": size(comps), "means": size(pca.mean.astype(np.float16)),
           "table": min(size(coded), size(pca.table)), "scales": 4 * pca.n_components}
    out["total"] = int(sum(out.values()))
    return out


def colour_bytes(model: HostModel) -> dict[str, int]:
    """The colour device image's size and its standalone table's (delta-coded, zstd)."""
    import dataclasses

    import zstandard

    from host.evaluate import eigenspace_bytes
    from host.fit.model import add_standalone_table
    from protocol.image import DEFAULT_LEVEL

    image = dataclasses.replace(model.image, sections=dict(model.image.sections))
    info = add_standalone_table(image, model.training_scores, eigenvalues=model.eigenvalues)
    table = np.ascontiguousarray(image.sections[info["section"]])
    packed = len(zstandard.ZstdCompressor(level=DEFAULT_LEVEL).compress(table.tobytes()))
    return {"image": int(eigenspace_bytes(model)), "standalone_table": packed,
            "components": int(model.image.n_coefficients)}


def fit_depth_pcas(depths: np.ndarray, thresholds: list[float], offset: float
                   ) -> dict[float, DepthEigenspace]:
    """`host.fit.depth.fit_depth_eigenspaces` (the product's fit) at the script's cell."""
    return fit_depth_eigenspaces(depths, thresholds, offset, DEPTH_CELL)


def depth_bytes(pca: DepthEigenspace) -> dict[str, int]:
    """Raw sizes of a depth eigenspace's parts."""
    d = pca.cell * pca.cell
    return {"components_int8": pca.n_components * d, "scales": 4 * pca.n_components,
            "means_f16": 2 * pca.mean.shape[0] * d, "table_int16": 2 * pca.table.size}


# ----------------------------------------------------------------------------- caches


class Volume:
    """One shared volume: its databases, models, renderers and depth caches."""

    def __init__(self, name: str, cache: Path, sizes: list[int]) -> None:
        self.name = name
        self.cache = cache
        self.dbs = {s: CinemaDB.open(f"/work/cache/{name}-{s}.cdb") for s in sizes}
        if DEPTH_SIZE not in self.dbs:
            self.dbs[DEPTH_SIZE] = CinemaDB.open(f"/work/cache/{name}-{DEPTH_SIZE}.cdb")
        self.models = {s: HostModel.load(f"/work/cache/{name}-{s}.ecs") for s in sizes}
        source = shared_volume(name)
        if source is None:
            raise SystemExit(f"warp_views: shared volume {name!r} not found (../shared/data)")
        self.scenes: dict[int, ViewRenderer] = {}
        self.settings: dict[int, RenderSettings] = {}
        for s, db in self.dbs.items():
            st = RenderSettings.from_record(db.settings, what=str(db.path))
            self.settings[s] = st
            self.scenes[s] = ViewRenderer.open(st, str(source), what=str(db.path))
        st = self.settings[DEPTH_SIZE]
        self.distance = st.radius_mm / math.sin(math.radians(st.fov_deg) / 2.0)

    def training_depths(self) -> np.ndarray:
        """(n_views, 256, 256, 2) float32 memmap of every training view's two depths."""
        path = self.cache / f"{self.name}-{DEPTH_SIZE}-train-depth.npy"
        done = path.with_suffix(".done")
        db = self.dbs[DEPTH_SIZE]
        if done.exists():
            return np.load(path, mmap_mode="r")
        h, w = db.image_shape
        arr = np.lib.format.open_memmap(path, mode="w+", dtype=np.float32,
                                        shape=(db.n_views, h, w, 2))
        scene = self.scenes[DEPTH_SIZE]
        t0 = time.perf_counter()
        for i in range(db.n_views):
            rgb, _alpha, depth = scene.render_with_depth(float(db.phi_deg[i]),
                                                         float(db.theta_deg[i]))
            if i % 300 == 0 and not np.array_equal(rgb, db.read_image(i)):
                raise SystemExit(f"{self.name}: view {i} differs from the database's image")
            arr[i] = depth
            if (i + 1) % 100 == 0:
                print(f"  {self.name} training depths {i + 1}/{db.n_views} "
                      f"({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
        arr.flush()
        del arr
        done.write_text("ok")
        return np.load(path, mmap_mode="r")

    def view_depth(self, size: int, index: int) -> np.ndarray:
        """Training view ``index``'s two depths at ``size`` (cached per view)."""
        if size == DEPTH_SIZE:
            return np.asarray(self.training_depths()[index])
        path = self.cache / f"{self.name}-{size}-depth-{index:04d}.npy"
        if path.exists():
            return np.load(path)
        db = self.dbs[size]
        rgb, _alpha, depth = self.scenes[size].render_with_depth(float(db.phi_deg[index]),
                                                                 float(db.theta_deg[index]))
        if not np.array_equal(rgb, db.read_image(index)):
            raise SystemExit(f"{self.name}-{size}: view {index} differs from the database's")
        np.save(path, depth)
        return depth

    def held_out(self, size: int, phi: float, theta: float, k: int) -> tuple[np.ndarray, ...]:
        """A fresh ray-cast of held-out view ``k``: (rgb8, alpha)."""
        path = self.cache / f"{self.name}-{size}-test-{k:03d}-{phi:.6f}-{theta:.6f}.npz"
        if path.exists():
            z = np.load(path)
            return z["rgb"], z["alpha"]
        rgb, alpha = self.scenes[size].render(phi, theta)
        np.savez(path, rgb=rgb, alpha=alpha)
        return rgb, alpha


# ----------------------------------------------------------------------------- the run


def depth_pcas(vol: Volume, thresholds: list[float], variants: tuple[str, ...] = tuple(VARIANTS)
               ) -> tuple[dict[str, dict[float, DepthEigenspace]], dict]:
    """Fit the depth eigenspaces of each variant at each threshold; report components, bytes
    and the depth error on object pixels of training views."""
    depths = vol.training_depths()
    out, report = {}, {}
    n = depths.shape[0]
    check = np.unique(np.linspace(0, n - 1, DEPTH_CHECK_VIEWS).round().astype(int))
    for variant in variants:
        t0 = time.perf_counter()
        filled = np.stack([fill_nearest(variant_depth(depths[i], variant)) for i in range(n)])
        pcas = fit_depth_pcas(filled, thresholds, vol.distance)
        del filled
        fit_s = time.perf_counter() - t0
        report[variant] = {}
        for t, pca in pcas.items():
            err = []
            for i in check:
                truth = variant_depth(depths[i], variant)
                ok = np.isfinite(truth)
                err.append(np.square(pca.reconstruct(int(i))[ok] - truth[ok]))
            rmse = float(np.sqrt(np.concatenate(err).mean()))
            b = depth_bytes(pca)
            order = np.lexsort((np.mod(vol.dbs[DEPTH_SIZE].phi_deg, 360.0),
                                vol.dbs[DEPTH_SIZE].theta_deg))
            report[variant][str(t)] = {
                "zstd_bytes": zstd_bytes(pca, order),
                "threshold": t,
                "components": pca.n_components,
                "components_per_cell": float(pca.counts.mean()),
                "bytes": b,
                "bytes_total": int(sum(b.values())),
                "score_step_mm": pca.step,
                "rmse_object_mm": rmse,
                "fit_s": fit_s,
            }
            print(f"  {vol.name} depth PCA {variant}: T={t} K={pca.n_components} "
                  f"({pca.counts.mean():.2f}/cell), {sum(b.values()) / 1e6:.2f} MB raw, "
                  f"{report[variant][str(t)]['zstd_bytes']['total'] / 1e6:.2f} MB zstd, "
                  f"RMSE {rmse:.3f} mm", file=sys.stderr, flush=True)
        out[variant] = pcas
    return out, report


class _Case:
    """One volume at one size for `run_case`: the model, its database, the warper and the
    colour reconstructions made so far (each training view's once)."""

    def __init__(self, vol: Volume, size: int, pcas: dict[str, dict[float, DepthEigenspace]],
                 threshold: float) -> None:
        self.vol, self.size, self.pcas, self.threshold = vol, size, pcas, threshold
        self.model = vol.models[size]
        self.db = vol.dbs[size]
        st = vol.settings[size]
        self.warper = Warper(st, st.width, st.height)
        self.device = DevicePath(self.model)
        training = TrainingImages(self.model, None)
        training.db = self.db  # the model's provenance names the database relatively
        self.webp = WebPDatabase(self.model, training, WEBP_QUALITY, encode_all=False)
        self.step_rec: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.timing: dict[str, list[float]] = {"blend": [], "warp": [], "device_frame": [],
                                               "colour_reconstructs": [],
                                               "depth_reconstructs": []}

    def rec_colour(self, i: int) -> np.ndarray:
        if i not in self.step_rec:
            y = self.model.quantize(self.model.training_scores[i])
            self.step_rec[i] = (self.model.reconstruct(y), y)
        return self.step_rec[i][0]

    def rec_depth(self, i: int, variant: str, t: float | None = None) -> np.ndarray:
        d = self.pcas[variant][self.threshold if t is None else t].reconstruct(i)
        return upsample2(d) if self.size == 2 * DEPTH_SIZE else d

    def view_frames(self, phi: float, theta: float, truth: np.ndarray) -> dict[str, np.ndarray]:
        """Every method's frame of one held-out view (and the device frame's timing)."""
        model, db, warper = self.model, self.db, self.warper
        idx, w = model.interpolator.weights(phi, theta)
        idx = np.asarray(idx).ravel().astype(int)
        w = np.asarray(w, dtype=np.float64).ravel()
        target = warper.camera(phi, theta)
        sources = [warper.camera(float(db.phi_deg[i]), float(db.theta_deg[i])) for i in idx]
        true_rgb = [db.read_image(int(i)) for i in idx]
        true_d = [self.vol.view_depth(self.size, int(i)) for i in idx]
        true_ok = [c.max(axis=2) > 0 for c in true_rgb]
        rec_rgb = [self.rec_colour(int(i)) for i in idx]
        rec_ok = [c.max(axis=2) > OBJECT_LEVEL for c in rec_rgb]
        frames: dict[str, np.ndarray] = {}
        t0 = time.perf_counter()
        frames["blend"] = model.view(phi, theta)
        self.timing["blend"].append(time.perf_counter() - t0)
        frames["webp_db"] = self.webp.frame(phi, theta)
        frames["oracle"], _ = self.device.projection_frame(truth)
        true = (true_rgb, true_ok)
        rec = (rec_rgb, rec_ok)
        for variant in self.pcas:
            self._warp_variant(frames, variant, idx, true, true_d, rec, (sources, w, target))
        self._time_device_frame(idx, sources, w, target)
        return frames

    def _warp_variant(self, frames: dict[str, np.ndarray], variant: str, idx: np.ndarray,
                      true: tuple[list, list], true_d: list[np.ndarray], rec: tuple[list, list],
                      geometry: tuple) -> None:
        """The warps of one depth variant: from true images, from reconstructions."""
        warper = self.warper
        (true_rgb, true_ok), (rec_rgb, rec_ok) = true, rec
        d = [variant_depth(x, variant) for x in true_d]
        frames[f"warp_true_{variant}"] = warper.warp(true_rgb, d, true_ok, *geometry)
        if variant == "half":
            frames["warp_rec_half_truedepth"] = warper.warp(rec_rgb, d, rec_ok, *geometry)
            if self.size == 2 * DEPTH_SIZE:
                low = [upsample2(fill_nearest(variant_depth(self.vol.view_depth(DEPTH_SIZE,
                                                                                int(i)), variant)))
                       for i in idx]
                frames["warp_true_half_d256"] = warper.warp(true_rgb, low, true_ok, *geometry)
        rd = [self.rec_depth(int(i), variant) for i in idx]
        t0 = time.perf_counter()
        frames[f"warp_rec_{variant}"] = warper.warp(rec_rgb, rd, rec_ok, *geometry)
        if variant == "half":
            self.timing["warp"].append(time.perf_counter() - t0)
            for t in self.pcas[variant]:
                if t != self.threshold:
                    rd = [self.rec_depth(int(i), variant, t) for i in idx]
                    frames[f"warp_rec_half_T{t}"] = warper.warp(rec_rgb, rd, rec_ok, *geometry)

    def _time_device_frame(self, idx: np.ndarray, sources: list, w: np.ndarray,
                           target: object) -> None:
        """The whole device frame: 4 colour + 4 depth reconstructions, upsampling, the warp."""
        t0 = time.perf_counter()
        cols = [self.model.reconstruct(self.step_rec[int(i)][1]) for i in idx]
        t1 = time.perf_counter()
        oks = [c.max(axis=2) > OBJECT_LEVEL for c in cols]
        ds = [self.rec_depth(int(i), "half") for i in idx]
        t2 = time.perf_counter()
        self.warper.warp(cols, ds, oks, sources, w, target)
        t3 = time.perf_counter()
        self.timing["device_frame"].append(t3 - t0)
        self.timing["colour_reconstructs"].append(t1 - t0)
        self.timing["depth_reconstructs"].append(t2 - t1)


def _view_record(phi: float, theta: float, truth: np.ndarray, mask: np.ndarray,
                 frames: dict[str, np.ndarray]) -> dict:
    rec = {"phi_deg": phi, "theta_deg": theta, "object_fraction": float(mask.mean())}
    for name, fr in frames.items():
        c = compare_images(truth, fr, mask=mask)
        rec[name] = {"ssim_object": c.ssim_object, "flip_object": c.flip_object,
                     "psnr_object": c.psnr_object}
    return rec


def _case_summary(case: _Case, per_view: list[dict]) -> dict:
    """Means over the views, the share of the blend-to-oracle gap closed, median times."""
    names = list(per_view[0].keys() - {"phi_deg", "theta_deg", "object_fraction"})
    means = {m: {key: float(np.mean([v[m][key] for v in per_view]))
                 for key in ("ssim_object", "flip_object", "psnr_object")} for m in names}
    blend, oracle = means["blend"], means["oracle"]
    gap = {}
    for m in names:
        gap[m] = {key: (means[m][key] - blend[key]) / (oracle[key] - blend[key])
                  if oracle[key] != blend[key] else math.nan
                  for key in ("ssim_object", "flip_object")}
    ms = {k: 1e3 * float(np.median(v)) for k, v in case.timing.items()}
    return {"volume": case.vol.name, "size": case.size, "views": len(per_view), "means": means,
            "colour_bytes": colour_bytes(case.model),
            "gap_closed": gap, "median_ms": ms,
            "ratio_to_blend": {k: ms[k] / ms["blend"] for k in ms},
            "z_tolerance_mm": case.warper.tol_mm, "per_view": per_view}


def run_case(vol: Volume, size: int, pcas: dict[str, dict[float, DepthEigenspace]],
             threshold: float, views: np.ndarray, images: Path | None) -> dict:
    case = _Case(vol, size, pcas, threshold)
    per_view = []
    picture = None
    for k, (phi, theta) in enumerate(views):
        phi, theta = float(phi), float(theta)
        truth, alpha = vol.held_out(size, phi, theta, k)
        mask = alpha_object_mask(alpha)
        frames = case.view_frames(phi, theta, truth)
        rec = _view_record(phi, theta, truth, mask, frames)
        per_view.append(rec)
        if k == 0:
            picture = (truth, frames)
        print(f"  {vol.name}-{size} view {k + 1}/{len(views)}: blend "
              f"{rec['blend']['ssim_object']:.3f} warp_rec_half "
              f"{rec['warp_rec_half']['ssim_object']:.3f} oracle "
              f"{rec['oracle']['ssim_object']:.3f}", file=sys.stderr, flush=True)
    summary = _case_summary(case, per_view)
    if images is not None and picture is not None:
        save_picture(images / f"warp-{vol.name}-{size}.jpg", *picture)
    return summary


def save_picture(path: Path, truth: np.ndarray, frames: dict[str, np.ndarray]) -> None:
    """true | blend | warp (b) | oracle, and the warp's FLIP error map, as one JPEG."""
    from PIL import Image

    from host.evaluate.metrics import flip_error_map

    err = flip_error_map(truth, frames["warp_rec_half"])
    heat = (np.clip(err, 0, 1)[..., None] * np.array([255, 200, 60])).astype(np.uint8)
    tiles = [truth, frames["blend"], frames["warp_rec_half"], frames["oracle"], heat]
    row = np.concatenate([np.pad(t, ((2, 2), (2, 2), (0, 0)), constant_values=255)
                          for t in tiles], axis=1)
    image = Image.fromarray(row)
    if image.width > 1300:
        image = image.resize((image.width // 2, image.height // 2), Image.LANCZOS)
    path.parent.mkdir(parents=True, exist_ok=True)
    image.save(path, quality=85, optimize=True)


def _print_method_table(title: str, heads: list[str], methods: list[str],
                        columns: list[dict], digits: int) -> None:
    """One Markdown table: a row per method, a column per case, object SSIM / FLIP in each
    cell to ``digits`` decimals ("–" where the case lacks the method)."""
    print(f"| {title} (SSIM obj / FLIP obj) | " + " | ".join(heads) + " |")
    print("|---" * (len(heads) + 1) + "|")
    for m in methods:
        cells = ["–" if (v := col.get(m)) is None
                 else f"{v['ssim_object']:.{digits}f} / {v['flip_object']:.{digits}f}"
                 for col in columns]
        print(f"| {m} | " + " | ".join(cells) + " |")
    print()


def study_parser(description: str) -> argparse.ArgumentParser:
    """The arguments of the warp studies (this script and research/warp_storage.py): which
    volumes at which sizes, how many held-out views from which seed."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--volumes", default="tooth,vismale_head")
    ap.add_argument("--sizes", default="256,512")
    ap.add_argument("--views", type=int, default=20)
    ap.add_argument("--seed", type=int, default=15)
    return ap


def print_tables(results: list[dict], depth: dict) -> None:
    methods = ["blend", "webp_db", "oracle", "warp_true_half", "warp_true_mean",
               "warp_true_half_d256", "warp_rec_half", "warp_rec_mean",
               "warp_rec_half_truedepth"]
    methods += sorted({m for r in results for m in r["means"] if m.startswith("warp_rec_half_T")})
    heads = [f"{r['volume']} {r['size']}" for r in results]
    _print_method_table("method", heads, methods, [r["means"] for r in results], 4)
    _print_method_table("gap closed", heads, [m for m in methods if m not in ("blend", "oracle")],
                        [r["gap_closed"] for r in results], 2)
    print("| median ms per frame | " + " | ".join(heads) + " |")
    print("|---" * (len(heads) + 1) + "|")
    for key in ("blend", "warp", "colour_reconstructs", "depth_reconstructs", "device_frame"):
        cells = [f"{r['median_ms'][key]:.1f} ({r['ratio_to_blend'][key]:.1f}x)" for r in results]
        print(f"| {key} | " + " | ".join(cells) + " |")
    print()
    for name, rep in depth.items():
        for variant, by_t in rep.items():
            for v in by_t.values():
                print(f"depth PCA {name} {variant}: T={v['threshold']} K={v['components']} "
                      f"({v['components_per_cell']:.2f}/cell) {v['bytes_total'] / 1e6:.2f} MB "
                      f"raw {v['bytes']}, zstd {v['zstd_bytes']} RMSE "
                      f"{v['rmse_object_mm']:.3f} mm")
    for r in results:
        c = r["colour_bytes"]
        print(f"colour {r['volume']} {r['size']}: image {c['image'] / 1e6:.2f} MB, standalone "
              f"table {c['standalone_table'] / 1e6:.2f} MB (K={c['components']})")


def main(argv: list[str] | None = None) -> int:
    ap = study_parser(__doc__.split("\n")[0])
    ap.add_argument("--cache", default="/work/cache/warp")
    ap.add_argument("--images", default="docs/images", help="'' for no pictures")
    ap.add_argument("-o", "--output", default="/work/cache/warp/results.json")
    ap.add_argument("--limit", type=int, default=0,
                    help="measure only the first N views of the set (quick comparisons)")
    ap.add_argument("--variants", default="half,mean",
                    help="depth variants measured (half: half-opacity, mean: weighted mean)")
    ap.add_argument("--depth-thresholds", default="0.99,0.999",
                    help="depth PCA thresholds measured besides the colour model's T")
    args = ap.parse_args(argv)
    extra = [float(t) for t in args.depth_thresholds.split(",") if t]
    variants = tuple(v for v in args.variants.split(",") if v)
    if "half" not in variants or any(v not in VARIANTS for v in variants):
        raise SystemExit(f"warp_views: --variants must include half, of {', '.join(VARIANTS)}")
    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    sizes = [int(s) for s in args.sizes.split(",") if s]
    if any(s not in (DEPTH_SIZE, 2 * DEPTH_SIZE) for s in sizes):
        raise SystemExit(f"warp_views: sizes must be {DEPTH_SIZE} or {2 * DEPTH_SIZE}")
    views = parse_view_set(f"random:{args.views}:{args.seed}").angles_deg()
    if args.limit > 0:
        views = views[:args.limit]
    images = Path(args.images) if args.images else None
    results, depth = [], {}
    for name in [v for v in args.volumes.split(",") if v]:
        vol = Volume(name, cache, sizes)
        threshold = next(iter(vol.models.values())).threshold or 0.98
        thresholds = sorted({threshold, *extra})
        pcas, depth[name] = depth_pcas(vol, thresholds, variants)
        for size in sizes:
            results.append(run_case(vol, size, pcas, threshold, views, images))
            Path(args.output).write_text(json.dumps({"partial": results}, default=float))
    out = {"views": f"random:{args.views}:{args.seed}", "z_tolerance": Z_TOLERANCE,
           "splat": "nearest, tent filter" if SPLAT_TENT else "nearest",
           "hole_passes": HOLE_PASSES,
           "hole_neighbours": HOLE_NEIGHBOURS, "depth": depth, "cases": results}
    Path(args.output).write_text(json.dumps(out, indent=1, default=float))
    print_tables(results, depth)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
