"""The forward warp of issue 15 (device_runtime/synthesis.py; research/warp_views.py, the
go/no-go measurement, imports it) on synthetic scenes.

Warping a view to its own camera gives it back; a sphere rendered from one view and warped by
its depth into a view 12 degrees away matches that view's own ray-cast far better than the
unwarped image; holes inside the surface are filled; a textured plane of known depth warps
to its analytic image in another camera within a stated tolerance.
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

_SCRIPT = Path(__file__).resolve().parent.parent / "research" / "warp_views.py"


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


def _warper(settings, size=64):
    from device_runtime.synthesis import Z_TOLERANCE, Warper

    distance = settings.radius_mm / math.sin(math.radians(settings.fov_deg) / 2.0)
    return Warper(settings.fov_deg, distance, size, size, Z_TOLERANCE * 2 * settings.radius_mm)


def _render(renderer, settings, phi, theta, size=64):
    rgba, depth = renderer.render_with_depth(settings.camera(phi, theta), size, size)
    return renderer.composite(rgba), rgba[..., 3], depth[..., 0]


def test_the_script_uses_the_product_warp(warp_views):
    from device_runtime import synthesis

    assert warp_views.forward_warp is synthesis.forward_warp
    assert warp_views.fill_holes is synthesis.fill_holes
    assert issubclass(warp_views.Warper, synthesis.Warper)

def _plane_scene(size, radius=10.0, fov=30.0):
    """A plane through an orbit centre off the origin (the device places it at the origin:
    must not matter), textured by a smooth function of the world point, every pixel's depth
    known exactly: ``image(phi, theta) -> rgb, depth, ok`` and the orbit distance."""
    center = np.array([1.0, -2.0, 3.0])
    normal = np.array([1.0, 0.3, 0.2])
    normal /= np.linalg.norm(normal)

    def image(phi, theta):
        cam = orbit_camera(View(phi, theta), center, radius, fov_deg=fov)
        o, d = cam.rays(size, size)
        t = ((center - o) @ normal) / (d @ normal)
        x = o + t[..., None] * d - center
        ok = np.linalg.norm(x, axis=-1) < 0.8 * radius
        tex = np.stack([np.sin(x[..., 0] / 2.0), np.cos(x[..., 1] / 2.5),
                        np.sin((x[..., 2] + x[..., 0]) / 3.0)], axis=-1)
        rgb = np.where(ok[..., None], np.rint(128 + 100 * tex), 0).astype(np.uint8)
        return rgb, np.where(ok, t, np.nan).astype(np.float32), ok

    return image, radius / math.sin(math.radians(fov) / 2.0)



def test_a_plane_of_known_depth_warps_to_its_analytic_image():
    """A plane through the orbit centre, textured by a smooth function of the world point,
    seen by two orbit cameras 12 degrees apart: every pixel's depth is known exactly, so the
    warp of the source image must give the target's analytic image up to the nearest-pixel
    splatting's resampling (mean error under 1.5 levels, 99th percentile under 6)."""
    from device_runtime.synthesis import Warper

    size, radius, fov = 64, 10.0, 30.0
    image, distance = _plane_scene(size, radius, fov)
    warper = Warper(fov, distance, size, size, 0.02 * 2 * radius)
    src, depth, ok = image(20.0, 5.0)
    dst, _, dst_ok = image(32.0, 5.0)
    out = warper.warp([src], [depth], [ok], [warper.pose(20.0, 5.0)], np.array([1.0]),
                      warper.pose(32.0, 5.0))
    inner = dst_ok.copy()
    inner[1:-1, 1:-1] &= inner[:-2, 1:-1] & inner[2:, 1:-1] & inner[1:-1, :-2] & inner[1:-1, 2:]
    assert inner.sum() > 1000
    err = np.abs(out[inner].astype(float) - dst[inner])
    assert err.mean() < 1.5 and np.percentile(err, 99) < 6, (err.mean(), err.max())
    unwarped = np.abs(src[inner].astype(float) - dst[inner]).mean()
    # Nearest-pixel splatting lands each sample up to half a pixel from where it projects
    # (a quarter on average): on this texture (~7 levels per pixel) that is ~1.3 levels,
    # against 2.7 for not warping (this smooth texture barely changes over 12 degrees).
    # Bilinear splatting gave 0.2; the margin asked is therefore 1.8x, not 10x.
    assert unwarped > 1.8 * err.mean()


def test_warp_to_its_own_camera_is_the_identity(warp_views, scene):
    renderer, settings = scene
    rgb, alpha, depth = _render(renderer, settings, 30.0, 10.0)
    warper = _warper(settings)
    cam = warper.pose(30.0, 10.0)
    out = warper.warp([rgb], [depth], [alpha > 0.5], [cam], np.array([1.0]), cam)
    inner = alpha > 0.5
    assert inner.sum() > 500
    # every pixel lands on itself; the splat filter (SPLAT_TENT: [1/8, 3/4, 1/8] in x and y,
    # normalised over the covered pixels) is then the only change, computed here apart
    expected = _tent_normalised(rgb.astype(float), inner)
    assert np.abs(out[inner].astype(int) - np.rint(expected[inner])).max() <= 1


def _tent_normalised(img, covered):
    k = np.array([0.125, 0.75, 0.125])
    num = np.pad(img * covered[..., None], ((1, 1), (1, 1), (0, 0)))
    den = np.pad(covered.astype(float), 1)
    h, w = covered.shape

    def filt(a):
        t = sum(k[i] * a[i:i + h] for i in range(3))
        return sum(k[j] * t[:, j:j + w] for j in range(3))

    return filt(num) / np.maximum(filt(den), 1e-12)[..., None]


@pytest.mark.parametrize("target", [(30.0, 22.0), (42.0, 10.0)])
def test_warp_by_depth_reproduces_a_view_twelve_degrees_away(warp_views, scene, target):
    renderer, settings = scene
    src_rgb, src_alpha, src_depth = _render(renderer, settings, 30.0, 10.0)
    dst_rgb, dst_alpha, _ = _render(renderer, settings, *target)
    warper = _warper(settings)
    out = warper.warp([src_rgb], [src_depth], [src_alpha > 0.5],
                      [warper.pose(30.0, 10.0)], np.array([1.0]), warper.pose(*target))
    # compare away from the silhouette (the sphere's rim is seen only by the target view)
    inner = dst_alpha > 0.5
    for _ in range(2):
        inner[1:-1, 1:-1] &= inner[:-2, 1:-1] & inner[2:, 1:-1] & inner[1:-1, :-2] & inner[1:-1, 2:]
    assert inner.sum() > 400
    err_warp = np.abs(out[inner].astype(float) - dst_rgb[inner]).mean()
    err_plain = np.abs(src_rgb[inner].astype(float) - dst_rgb[inner]).mean()
    assert err_warp < 0.5 * err_plain, (err_warp, err_plain)
    assert np.all(out[inner].max(axis=1) > 0)  # no hole left inside the surface


def test_fill_holes_closes_cracks_not_the_silhouette():
    from device_runtime.synthesis import fill_holes

    frame = np.zeros((9, 9, 3), np.float32)
    covered = np.zeros((9, 9), bool)
    covered[2:7, 2:7] = True
    frame[covered] = 100.0
    covered[4, 4] = False  # a crack
    frame[4, 4] = 0.0
    out = fill_holes(frame.copy(), covered.copy())
    assert math.isclose(float(out[4, 4, 0]), 100.0)
    assert np.all(out[~np.pad(np.ones((5, 5), bool), 2)] == 0.0)  # the outside stays empty


def test_packed_points_are_the_float_points_to_half_a_step_and_warp_alike():
    """The view cache's int16 points (`unproject_at(packed=True)`): within half a
    `point_step` of the float32 points, and the same frame but for a few splats that
    crossed a pixel edge."""
    from device_runtime.synthesis import Warper, forward_warp

    size = 96
    image, distance = _plane_scene(size)
    warper = Warper(30.0, distance, size, size, 0.4)
    src, depth, ok = image(20.0, 5.0)
    at = np.flatnonzero(ok)
    pts, rgb = warper.unproject_at(src, depth.reshape(-1)[at], at)
    q, qrgb = warper.unproject_at(src, depth.reshape(-1)[at], at, packed=True)
    assert q.dtype == np.int16 and np.array_equal(rgb, qrgb)
    back = q.astype(float) * warper.point_step
    back[2] += distance
    # half a step, and float32's rounding of the points themselves
    assert np.abs(back - pts).max() <= 0.5 * warper.point_step + 1e-6 * distance
    assert warper.point_step < 1e-4 * distance  # far below a pixel (~distance / size)
    args = ([warper.pose(20.0, 5.0)], np.array([1.0]), warper.pose(32.0, 5.0))
    a = forward_warp(warper, [(pts, rgb)], *args)
    b = forward_warp(warper, [(q, qrgb)], *args)
    assert (a != b).any(axis=2).mean() < 0.02
    assert np.abs(a.astype(int) - b).mean() < 0.1


def test_a_frames_memory_is_the_warpers_grid_and_one_views_temporaries():
    """What a frame holds beyond its input: the warper's grid (z-buffer, 3 float32
    accumulators, coverage: 17 bytes per padded pixel) and 4 bytes per splat, kept between
    frames; while it runs, one view's projection temporaries and two filter planes (under
    24 bytes per pixel), never a full-frame float64 copy or every view's splats at once."""
    import tracemalloc

    from device_runtime.synthesis import Warper, forward_warp

    size = 192
    image, distance = _plane_scene(size)
    warper = Warper(30.0, distance, size, size, 0.4)
    views = [(20.0, 5.0), (32.0, 5.0), (20.0, 17.0), (32.0, 17.0)]
    clouds = []
    for v in views:
        rgb, depth, ok = image(*v)
        clouds.append(warper.unproject(rgb, depth, ok))
    splats = sum(c[0].shape[1] for c in clouds)
    assert splats > 1.5 * size * size  # nearly half of every view is object
    args = ([warper.pose(*v) for v in views], np.full(4, 0.25), warper.pose(26.0, 11.0))
    padded = (size + 2) ** 2
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        forward_warp(warper, clouds, *args)  # the warper's buffers are made here
        kept = tracemalloc.get_traced_memory()[0] - before
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        forward_warp(warper, clouds, *args)
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    assert kept <= 17 * padded + 5 * splats + 65536, (kept, padded, splats)
    assert peak <= 24 * size * size + 65536, (peak / size**2)
