"""The forward warp of the issue 15 measurement (scripts/warp_views.py) on a synthetic scene.

Warping a view to its own camera gives it back; a sphere rendered from one view and warped by
its depth into a view 12 degrees away matches that view's own ray-cast far better than the
unwarped image; holes inside the surface are filled.
"""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from host.render.camera import View, orbit_camera
from host.render.raycast import Renderer
from host.render.transfer import TransferFunction
from host.volume import Volume

_SCRIPT = Path(__file__).resolve().parent.parent / "scripts" / "warp_views.py"


@pytest.fixture(scope="module")
def warp_views():
    spec = importlib.util.spec_from_file_location("warp_views", _SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules["warp_views"] = module  # dataclasses look their module up
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop("warp_views", None)


@pytest.fixture(scope="module")
def scene():
    """A shaded sphere with a stripe texture (so a wrong warp shows), and its framing."""
    n = 48
    z, y, x = np.mgrid[0:n, 0:n, 0:n].astype(np.float64)
    c = (n - 1) / 2.0
    r = np.sqrt((x - c) ** 2 + (y - c) ** 2 + (z - c) ** 2)
    stripes = 0.5 + 0.5 * np.sin(x / 3.0)
    inside = np.clip(20.0 - r + 0.5, 0.0, 1.0)  # 0 -> 1 over one voxel at r = 20
    data = inside * (0.55 + 0.4 * stripes) + (1.0 - inside) * 0.3
    volume = Volume(data.astype(np.float32))
    tf = TransferFunction(
        name="stripes",
        color_points=np.array([[0.0, 0.9, 0.2, 0.1], [0.55, 0.9, 0.2, 0.1], [0.95, 0.1, 0.5, 0.9],
                               [1.0, 0.1, 0.5, 0.9]]),
        opacity_points=np.array([[0.0, 0.0], [0.49, 0.0], [0.51, 0.9], [1.0, 0.9]]),
        window=(0.0, 1.0),
    )
    renderer = Renderer(volume, tf, samples=1000, shading=False)
    center, radius = volume.center_mm, volume.radius_mm
    settings = SimpleNamespace(
        projection="perspective", fov_deg=30.0, radius_mm=radius,
        camera=lambda phi, theta: orbit_camera(View(phi, theta), center, radius),
    )
    return renderer, settings


def _render(renderer, settings, phi, theta, size=64):
    rgba, depth = renderer.render_with_depth(settings.camera(phi, theta), size, size)
    return renderer.composite(rgba), rgba[..., 3], depth[..., 0]


def test_warp_to_its_own_camera_is_the_identity(warp_views, scene):
    renderer, settings = scene
    rgb, alpha, depth = _render(renderer, settings, 30.0, 10.0)
    warper = warp_views.Warper(settings, 64, 64)
    cam = warper.camera(30.0, 10.0)
    out = warper.warp([rgb], [depth], [alpha > 0.5], [cam], np.array([1.0]), cam)
    inner = alpha > 0.5
    assert inner.sum() > 500
    assert np.abs(out[inner].astype(int) - rgb[inner]).max() <= 1


@pytest.mark.parametrize("target", [(30.0, 22.0), (42.0, 10.0)])
def test_warp_by_depth_reproduces_a_view_twelve_degrees_away(warp_views, scene, target):
    renderer, settings = scene
    src_rgb, src_alpha, src_depth = _render(renderer, settings, 30.0, 10.0)
    dst_rgb, dst_alpha, _ = _render(renderer, settings, *target)
    warper = warp_views.Warper(settings, 64, 64)
    out = warper.warp([src_rgb], [src_depth], [src_alpha > 0.5],
                      [warper.camera(30.0, 10.0)], np.array([1.0]), warper.camera(*target))
    # compare away from the silhouette (the sphere's rim is seen only by the target view)
    inner = dst_alpha > 0.5
    for _ in range(2):
        inner[1:-1, 1:-1] &= inner[:-2, 1:-1] & inner[2:, 1:-1] & inner[1:-1, :-2] & inner[1:-1, 2:]
    assert inner.sum() > 400
    err_warp = np.abs(out[inner].astype(float) - dst_rgb[inner]).mean()
    err_plain = np.abs(src_rgb[inner].astype(float) - dst_rgb[inner]).mean()
    assert err_warp < 0.5 * err_plain, (err_warp, err_plain)
    assert np.all(out[inner].max(axis=1) > 0)  # no hole left inside the surface


def test_fill_holes_closes_cracks_not_the_silhouette(warp_views):
    frame = np.zeros((9, 9, 3), np.float32)
    covered = np.zeros((9, 9), bool)
    covered[2:7, 2:7] = True
    frame[covered] = 100.0
    covered[4, 4] = False  # a crack
    frame[4, 4] = 0.0
    out = warp_views.fill_holes(frame.copy(), covered.copy())
    assert math.isclose(float(out[4, 4, 0]), 100.0)
    assert np.all(out[~np.pad(np.ones((5, 5), bool), 2)] == 0.0)  # the outside stays empty
