"""The warp's splat filter for each image (``eigencast fit --depth``), chosen on its training
views.

The device's depth warp spreads its splats by [1, c, 1] / (c + 2) in x and y
(`device_runtime.warping.SPLAT_TENTS`). Which c suits an image depends on the volume and the
size (docs/design-notes.md, "A splat filter for each image"), so the fit measures the
device's own warp, with each filter, on training views warped from their row neighbours, and
names the clearly better one in the image. It scores frames with this stage's metrics, so it
lives here, like ``fit --target``'s search (`host.evaluate.target`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from device_runtime.synthesis import (
    DEPTH_DELTA_SECTION,
    NOISE_FLOOR_SECTION,
    SPLAT_TENTS,
    SYNTHESIS_METHOD,
    SYNTHESIS_METHOD_FLOOR,
    SYNTHESIS_METHOD_TENT,
)

__all__ = ["TENT_MARGIN", "TENT_TIE", "TENT_VIEWS", "choose_splat_tent", "pick_splat_tent"]

#: Training views `choose_splat_tent` warps from their two row neighbours (at most).
TENT_VIEWS = 40
#: Object SSIM by which another splat filter must beat the default on those views to be
#: chosen: where the default was best on held-out views, the others came within +0.0005 of
#: it on the training views (docs/design-notes.md).
TENT_MARGIN = 0.002
#: Filters within this object SSIM of the best on those views count as tied, and the one
#: that spreads the splats most among them is taken: a view warped from its row neighbours
#: moves a whole grid step, farther than a novel view from its nearest neighbour, which
#: favours the weaker filters (held-out views preferred the stronger of tied ones).
TENT_TIE = 0.001


def choose_splat_tent(image: Any, db: Any, *, views: int = TENT_VIEWS,
                      margin: float = TENT_MARGIN, quiet: bool = False) -> dict:
    """Choose the warp's splat filter for ``image`` (with depth) on its own training views.

    Up to ``views`` training views, spread over the database, are each warped from their
    two neighbours on the same theta row (the view itself left out, each neighbour weighted
    by its nearness in phi) with every filter of `SPLAT_TENTS`, exactly as a device warps
    (`device_runtime.synthesis.ViewSynthesizer` on the image), and scored by object SSIM
    against the rendered view. Of the filters within `TENT_TIE` of the best mean, the one
    that spreads the splats most is taken; it is written into the image (method
    `SYNTHESIS_METHOD_TENT`, ``synthesis.splat_tent``) only when it beats the default by
    more than ``margin``, else the image keeps `SYNTHESIS_METHOD`. An image with the noise
    floor (`NOISE_FLOOR_SECTION`, `host.fit.floor.add_noise_floor`) is warped with it and
    named `SYNTHESIS_METHOD_FLOOR` with the filter taken (the default included). The image's
    sections are left as they were.

    Returns
    -------
    dict
        ``tent`` (chosen), ``ssim`` ({tent: mean object SSIM}), ``views`` (warped; 0 when no
        theta row has three views: the default is kept).
    """
    from dataclasses import replace

    from device_runtime.reconstruct import Reconstructor
    from device_runtime.standalone import STANDALONE_DELTA_SECTION, StandaloneScores
    from device_runtime.synthesis import ViewSynthesizer
    from device_runtime.warping import forward_warp
    from host.evaluate.masks import object_mask
    from host.evaluate.metrics import compare_images
    from host.progress import progress

    default = SPLAT_TENTS[0]
    floored = NOISE_FLOOR_SECTION in image.sections
    record = {k: v for k, v in image.synthesis.items() if k != "splat_tent"}
    record["method"] = SYNTHESIS_METHOD
    if floored:
        record.update(method=SYNTHESIS_METHOD_FLOOR, splat_tent=default)
    image.synthesis = record
    cases = _row_triples(np.asarray(image.views["phi_deg"], dtype=np.float64),
                         np.asarray(image.views["theta_deg"], dtype=np.float64), views)
    if not cases:
        return {"tent": default, "ssim": {}, "views": 0}
    # the device's loaders decode delta-coded tables in place, in their own arrays: they get
    # copies of those (the image is written as it is)
    coded = (DEPTH_DELTA_SECTION, STANDALONE_DELTA_SECTION)
    work = replace(image, sections={k: v.copy() if k in coded else v
                                    for k, v in image.sections.items()})
    reconstructor = Reconstructor.from_image(work)
    synth = ViewSynthesizer(work, StandaloneScores(work), reconstructor)
    warper = synth.warper
    poses = {v: warper.pose(float(synth.phi[v]), float(synth.theta[v]))
             for view, pair, _ in cases for v in (view, *pair)}
    scores: dict[int, list[float]] = {t: [] for t in SPLAT_TENTS}
    try:
        with progress("choosing the splat filter", len(cases), unit=" views",
                      quiet=quiet) as bar:
            for view, (left, right), weights in cases:
                truth = db.read_image(view)
                mask = object_mask(truth)
                clouds = [synth.view_cloud(left), synth.view_cloud(right)]
                for tent in SPLAT_TENTS:
                    warper.tent = tent
                    frame = forward_warp(warper, clouds, [poses[left], poses[right]], weights,
                                         poses[view])
                    scores[tent].append(compare_images(truth, frame, mask=mask,
                                                       metrics=("ssim",)).ssim_object)
                bar.advance()
    finally:
        reconstructor.close()
    # views without object pixels score NaN; none with any: the default
    means = {t: float(np.mean([x for x in v if np.isfinite(x)] or [np.nan]))
             for t, v in scores.items()}
    if not all(np.isfinite(m) for m in means.values()):
        return {"tent": default, "ssim": means, "views": len(cases)}
    best = pick_splat_tent(means, margin)
    if floored:
        image.synthesis = {**record, "splat_tent": int(best)}
    elif best != default:
        image.synthesis = {**record, "method": SYNTHESIS_METHOD_TENT, "splat_tent": int(best)}
    return {"tent": best, "ssim": means, "views": len(cases)}


def pick_splat_tent(means: dict[int, float], margin: float = TENT_MARGIN,
                    tie: float = TENT_TIE) -> int:
    """The filter `choose_splat_tent` takes given each filter's mean object SSIM: the
    smallest centre weight (the most spread) within ``tie`` of the best, if it beats the
    default (`SPLAT_TENTS`' first) by more than ``margin``, else the default."""
    default = SPLAT_TENTS[0]
    top = max(means.values())
    best = min(t for t in SPLAT_TENTS if means[t] >= top - tie)
    return best if means[best] > means[default] + margin else default


def _row_triples(phi: np.ndarray, theta: np.ndarray, views: int
                 ) -> list[tuple[int, tuple[int, int], np.ndarray]]:
    """Up to ``views`` training views, evenly spread over those whose theta row holds at
    least three views, each with its row's previous and next view in phi (around the
    circle) and their weights (the nearer, the heavier; float64, summing to 1)."""
    eligible = []
    for t in np.unique(theta):
        row = np.flatnonzero(theta == t)
        if row.size < 3:
            continue
        row = row[np.argsort(phi[row], kind="stable")]
        for k, v in enumerate(row):
            eligible.append((int(v), int(row[k - 1]), int(row[(k + 1) % row.size])))
    if not eligible:
        return []
    eligible.sort()
    pick = np.unique(np.linspace(0, len(eligible) - 1, min(views, len(eligible))).round()
                     .astype(int))
    out = []
    for v, left, right in (eligible[i] for i in pick):
        d = np.abs((phi[[left, right]] - phi[v] + 180.0) % 360.0 - 180.0)
        w = d[::-1] / d.sum() if d.sum() > 0 else np.array([0.5, 0.5])
        out.append((v, (left, right), w))
    return out
