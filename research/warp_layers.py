"""Where the depth warp loses against the projection, and whether a second depth layer pays.

docs/design-notes.md, "One depth layer" (issue 22). For a standalone depth image (``fit
--standalone --depth``), its training database (``render --depth``) and a held-out database
of the same volume and settings (``render --depth --views random:N:SEED``, whose stored
images are the truth; object pixels: a channel above `OBJECT_LEVEL`), every held-out view is
made by the product's warp (`device_runtime.synthesis.forward_warp`) of the neighbours and
weights the device uses (`ViewSynthesizer.neighbours`), from:

``product``
    What the device holds: colour reconstructed from the eigenspace (the training view's
    standalone scores), depth from the depth eigenspace (`pca_warp`, bit for bit).
``rec_colour_true_depth`` / ``true_colour_eig_depth`` / ``true_colour_true_depth``
    The colour or the depth (or both) replaced by the truth: the database's image, and its
    stored half-resolution depth (the 2 x 2 mean of the half-opacity depth, the map the
    depth eigenspace is fitted to, background filled with the nearest object depth as the
    fit fills it). Separates the colour's error from the depth's.
``true_colour_mean_depth``
    True colour, the opacity-weighted mean depth instead of the half-opacity one.
``true_colour_two_layers`` / ``rec_colour_two_layers``
    A second depth layer: each pixel splats twice, at the depths where the accumulated
    opacity crosses 1/4 and 3/4 (`host.render.raycast_depth.render_depth_layers`, 2 x 2
    means at half resolution like the stored map; the half-opacity depth where a crossing
    is missing), each with half the view's weight; the z-test as for one layer.
``blend``, ``projection``
    Today's score blend, and the projection of the true view (what ``serve`` shows at rest;
    `host.evaluate.DevicePath.projection_frame`).

The layer depths are ray-cast for the neighbours the held-out views use only (true depth
needs the volume: the database's recorded source). Object SSIM over the truth's object
pixels, the mean over the views, and the share of views where a variant beats the product.

Usage::

    .venv/bin/python research/warp_layers.py MODEL.ecs TRAIN.cdb TEST.cdb [--views 40] \\
        [--no-layers] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from device_runtime.reconstruct import Reconstructor
from device_runtime.standalone import StandaloneScores
from device_runtime.synthesis import OBJECT_LEVEL, ViewSynthesizer, forward_warp
from host.evaluate.masks import object_mask
from host.evaluate.metrics import compare_images
from host.fit.depth import fill_nearest
from host.render.cinema import CinemaDB

__all__ = ["half_resolution", "main"]


def half_resolution(depth: np.ndarray) -> np.ndarray:
    """2 x 2 means of the finite values (NaN where none), as the database stores depth."""
    h, w = depth.shape
    blocks = depth.astype(np.float64).reshape(h // 2, 2, w // 2, 2).swapaxes(1, 2)
    blocks = blocks.reshape(h // 2, w // 2, 4)
    ok = np.isfinite(blocks)
    count = ok.sum(axis=2)
    total = np.where(ok, blocks, 0.0).sum(axis=2)
    out = np.full((h // 2, w // 2), np.nan)
    np.divide(total, count, out=out, where=count > 0)
    return out.astype(np.float32)


class Layers:
    """The true depth layers of training views, ray-cast on demand (cached)."""

    def __init__(self, train: CinemaDB) -> None:
        from host.render.settings import RenderSettings, ViewRenderer

        settings = RenderSettings.from_record(train.settings, what=str(train.path))
        self.view = ViewRenderer.open(settings, what=str(train.path))
        self.train = train
        self._cache: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def __call__(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Half-resolution (mean, quarter, three-quarter) depth maps of view ``i``, filled."""
        from host.render.raycast import DEPTH_HALF, DEPTH_MEAN
        from host.render.raycast_depth import (
            DEPTH_QUARTER,
            DEPTH_THREE_QUARTERS,
            render_depth_layers,
        )

        if i not in self._cache:
            s = self.view.settings
            camera = s.camera(float(self.train.phi_deg[i]), float(self.train.theta_deg[i]))
            _rgba, d = render_depth_layers(self.view.renderer, camera, s.width, s.height)
            half = np.where(np.isfinite(d[..., DEPTH_HALF]), d[..., DEPTH_HALF],
                            d[..., DEPTH_MEAN])
            front = np.where(np.isfinite(d[..., DEPTH_QUARTER]), d[..., DEPTH_QUARTER], half)
            back = np.where(np.isfinite(d[..., DEPTH_THREE_QUARTERS]),
                            d[..., DEPTH_THREE_QUARTERS], half)
            self._cache[i] = tuple(fill_nearest(half_resolution(x))
                                   for x in (d[..., DEPTH_MEAN], front, back))
        return self._cache[i]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", type=Path)
    ap.add_argument("train", type=Path)
    ap.add_argument("test", type=Path)
    ap.add_argument("--views", type=int, default=40)
    ap.add_argument("--no-layers", action="store_true",
                    help="skip the variants that ray-cast depth layers (no volume needed)")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    from host.evaluate.device_path import DevicePath
    from host.fit.model import HostModel
    from protocol.image import read_image

    t0 = time.perf_counter()
    image = read_image(a.model, read_annex=False)
    st = StandaloneScores(image)
    synth = ViewSynthesizer(image, st, Reconstructor.from_image(image, threads=1))
    rec = Reconstructor.from_image(image, threads=1)
    warper = synth.warper
    train, test = CinemaDB.open(a.train), CinemaDB.open(a.test)
    layers = None if a.no_layers else Layers(train)
    oracle = DevicePath(HostModel.load(a.model))
    n = min(a.views, test.n_views)
    sources: dict[int, tuple] = {}

    def source(i: int) -> tuple:
        if i not in sources:
            sources[i] = (rec.update(st.training_scores(i)).copy(), train.read_image(i),
                          synth.depth.reconstruct(i), fill_nearest(train.read_depth(i)))
        return sources[i]

    def cloud(colour: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        top = np.maximum(np.maximum(colour[..., 0], colour[..., 1]), colour[..., 2])
        return warper.cloud_at(colour, half, np.flatnonzero(top > OBJECT_LEVEL).astype(np.int32))

    names = ["product", "rec_colour_true_depth", "true_colour_eig_depth",
             "true_colour_true_depth", "blend", "projection"]
    if layers is not None:
        names[4:4] = ["true_colour_mean_depth", "true_colour_two_layers",
                      "rec_colour_two_layers"]
    scores: dict[str, list[float]] = {k: [] for k in names}
    for v in range(n):
        phi, theta = float(test.phi_deg[v]), float(test.theta_deg[v])
        truth = test.read_image(v)
        mask = object_mask(truth)

        def score(frame: np.ndarray, truth: np.ndarray = truth, mask: np.ndarray = mask
                  ) -> float:
            return float(compare_images(truth, frame, mask=mask, metrics=("ssim",)).ssim_object)

        idx, wts = synth.neighbours(phi, theta)
        poses = [warper.pose(float(synth.phi[i]), float(synth.theta[i])) for i in idx]
        target = warper.pose(phi, theta)
        srcs = [source(int(i)) for i in idx]
        for name, c, d in (("product", 0, 2), ("rec_colour_true_depth", 0, 3),
                           ("true_colour_eig_depth", 1, 2), ("true_colour_true_depth", 1, 3)):
            frame = forward_warp(warper, [cloud(s[c], s[d]) for s in srcs], poses, wts, target)
            scores[name].append(score(frame))
        if layers is not None:
            lay = [layers(int(i)) for i in idx]
            frame = forward_warp(warper, [cloud(s[1], q[0]) for s, q in zip(srcs, lay)],
                                 poses, wts, target)
            scores["true_colour_mean_depth"].append(score(frame))
            for name, c in (("true_colour_two_layers", 1), ("rec_colour_two_layers", 0)):
                clouds, two_poses = [], []
                for s, q, pose in zip(srcs, lay, poses):
                    clouds += [cloud(s[c], q[1]), cloud(s[c], q[2])]
                    two_poses += [pose, pose]
                frame = forward_warp(warper, clouds, two_poses, np.repeat(wts / 2, 2), target)
                scores[name].append(score(frame))
        scores["blend"].append(score(rec.update(st.scores(phi, theta))))
        scores["projection"].append(score(oracle.projection_frame(truth)[0]))
        if len(sources) > 64:
            sources.clear()
    product = np.array(scores["product"])
    rows = {k: {"object_ssim": float(np.mean(x)),
                "beats_product": float(np.mean(np.array(x) > product))}
            for k, x in scores.items()}
    print(f"{a.model.name}: {n} held-out views of {a.test.name}, "
          f"{time.perf_counter() - t0:.0f} s; object SSIM (share of views above the product)")
    for k, r in rows.items():
        print(f"  {k:24s} {r['object_ssim']:.4f}  ({r['beats_product']:.2f})")
    if a.json is not None:
        a.json.write_text(json.dumps({"model": str(a.model), "views": n, "rows": rows,
                                      "per_view": scores}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
