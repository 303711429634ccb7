"""`Renderer.render_with_depth`: the two representative depths against closed forms.

A sphere (signed-distance volume, opaque) gives the ray-sphere intersection distance; a
homogeneous semi-transparent box gives Beer-Lambert's half-opacity distance and weighted
mean; the RGBA equals `Renderer.render`'s bit for bit.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from host.render.camera import View, orbit_camera
from host.render.raycast import DEPTH_HALF, DEPTH_MEAN, Renderer
from host.render.transfer import TransferFunction
from host.volume import Volume


def step_tf(alpha: float) -> TransferFunction:
    """Nothing below u = 0.49, opacity ``alpha`` per unit length above u = 0.51."""
    return TransferFunction(
        name="step",
        color_points=np.array([[0.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0]]),
        opacity_points=np.array([[0.0, 0.0], [0.49, 0.0], [0.51, alpha], [1.0, alpha]]),
        window=(0.0, 1.0),
    )


def sphere_volume(n: int = 40, radius: float = 12.0, center=(19.0, 21.0, 18.5)) -> Volume:
    """u = 0.5 + (radius - r) / 2 (a signed distance, mm): u = 0.5 on the sphere."""
    z, y, x = np.mgrid[0:n, 0:n, 0:n].astype(np.float64)
    r = np.sqrt((x - center[0]) ** 2 + (y - center[1]) ** 2 + (z - center[2]) ** 2)
    return Volume((0.5 + (radius - r) / 2.0).astype(np.float32))


def ray_sphere(origins, dirs, center, radius):
    """Distance along each unit ray to its first sphere hit, NaN on a miss; and the miss
    distance (closest approach minus radius)."""
    oc = origins - np.asarray(center)
    b = np.einsum("...k,...k", oc, dirs)
    closest = np.sqrt(np.maximum(np.einsum("...k,...k", oc, oc) - b * b, 0.0))
    disc = b * b - (np.einsum("...k,...k", oc, oc) - radius**2)
    with np.errstate(invalid="ignore"):
        t = -b - np.sqrt(disc)
    t[disc < 0] = np.nan
    return t, closest - radius


@pytest.mark.parametrize("projection", ["perspective", "orthographic"])
@pytest.mark.parametrize("view", [(0.0, 0.0), (37.0, 25.0), (200.0, -60.0)])
def test_opaque_sphere_depth_is_the_ray_sphere_distance(projection, view):
    center, radius = (19.0, 21.0, 18.5), 12.0
    volume = sphere_volume(center=center, radius=radius)
    renderer = Renderer(volume, step_tf(0.999), samples=400, shading=True)
    camera = orbit_camera(View(*view), volume.center_mm, volume.radius_mm, projection=projection)
    rgba, depth = renderer.render_with_depth(camera, 48, 40)
    origins, dirs = camera.rays(48, 40)
    t, miss = ray_sphere(origins, dirs, center, radius)
    inside = miss < -1.0  # rays that hit the sphere away from its silhouette
    outside = miss > 1.0
    assert inside.sum() > 100 and outside.sum() > 100
    # past the surface the extinction is sigma per mm: the opacity reaches 0.5 ln(2)/sigma
    # behind it and the weighted mean lies 1/sigma behind it (exponential weights)
    sigma = -math.log(1.0 - 0.999)
    for channel, behind in ((DEPTH_HALF, math.log(2.0) / sigma), (DEPTH_MEAN, 1.0 / sigma)):
        err = np.abs(depth[..., channel][inside] - (t[inside] + behind))
        assert err.max() <= renderer.step_mm, (channel, err.max(), renderer.step_mm)
        assert np.all(np.isnan(depth[..., channel][outside]))  # no object: marked NaN
    # the mean lies behind the half-opacity point (opacity keeps adding behind it)
    assert np.all(depth[..., DEPTH_MEAN][inside] >= depth[..., DEPTH_HALF][inside] - 1e-4)
    assert np.all(rgba[..., 3][outside] == 0.0)


def box_renderer(alpha: float) -> Renderer:
    """A homogeneous 20 x 20 x 40 box of opacity ``alpha`` per mm, white, unshaded."""
    volume = Volume(np.full((20, 20, 40), 0.5, dtype=np.float32))
    tf = TransferFunction(
        name="constant",
        color_points=np.array([[0.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0]]),
        opacity_points=np.array([[0.0, alpha], [1.0, alpha]]),
        window=(0.0, 1.0),
    )
    return Renderer(volume, tf, step=0.25, shading=False)


def box_rays(renderer: Renderer):
    """Orthographic rays along -x through the box: the camera, each ray's distance to the
    face x = 39 mm, and the rays that cross the box (39 mm of it)."""
    volume = renderer.volume
    camera = orbit_camera(View(0.0, 0.0), volume.center_mm, volume.radius_mm,
                          projection="orthographic")
    origins, _ = camera.rays(24, 24)
    t_in = origins[..., 0] - 39.0
    hits = (np.abs(origins[..., 1] - 9.5) < 9.0) & (np.abs(origins[..., 2] - 9.5) < 9.0)
    return camera, t_in, hits


def test_semi_transparent_box_depths_follow_beer_lambert():
    alpha = 0.05  # per mm: 1 - 0.95**39 = 0.86 in total, below early termination
    renderer = box_renderer(alpha)
    camera, t_in, hits = box_rays(renderer)
    _rgba, depth = renderer.render_with_depth(camera, 24, 24)
    assert hits.sum() > 50
    sigma = -math.log(1.0 - alpha)
    length = 39.0
    half = math.log(2.0) / sigma
    e = math.exp(-sigma * length)
    mean = (1.0 / sigma - (length + 1.0 / sigma) * e) / (1.0 - e)
    np.testing.assert_allclose(depth[..., DEPTH_HALF][hits] - t_in[hits], half,
                               atol=renderer.step_mm)
    np.testing.assert_allclose(depth[..., DEPTH_MEAN][hits] - t_in[hits], mean,
                               atol=renderer.step_mm)
    assert min(half, mean) > 40 * renderer.step_mm  # deep inside, not at the entry face
    # a box too thin to reach 0.5 has a mean depth but no half-opacity depth
    thin = box_renderer(0.005)
    rgba_thin, depth_thin = thin.render_with_depth(camera, 24, 24)
    assert np.all(np.isnan(depth_thin[..., DEPTH_HALF][hits]))
    assert np.all(np.isfinite(depth_thin[..., DEPTH_MEAN][hits]))
    assert np.all(rgba_thin[..., 3][hits] > 0.1)


def test_depth_layers_cross_a_quarter_and_three_quarters_of_the_opacity():
    """`render_depth_layers`: the opacity crosses 1/4 at ln(4/3) / sigma and 3/4 at
    ln(4) / sigma into a homogeneous box (Beer-Lambert), the first two channels and the
    RGBA are `render_with_depth`'s bit for bit, and a box too faint to reach 3/4 has the
    first but not the second."""
    from host.render.raycast_depth import (
        DEPTH_QUARTER,
        DEPTH_THREE_QUARTERS,
        render_depth_layers,
    )

    alpha = 0.05
    renderer = box_renderer(alpha)
    camera, t_in, hits = box_rays(renderer)
    rgba, depth = render_depth_layers(renderer, camera, 24, 24)
    rgba2, depth2 = renderer.render_with_depth(camera, 24, 24)
    np.testing.assert_array_equal(rgba, rgba2)
    np.testing.assert_array_equal(depth[..., :2], depth2)
    sigma = -math.log(1.0 - alpha)
    for channel, level in ((DEPTH_QUARTER, 0.25), (DEPTH_THREE_QUARTERS, 0.75)):
        np.testing.assert_allclose(depth[..., channel][hits] - t_in[hits],
                                   math.log(1.0 / (1.0 - level)) / sigma,
                                   atol=renderer.step_mm)
    assert np.all(depth[..., DEPTH_QUARTER][hits] < depth[..., DEPTH_HALF][hits])
    assert np.all(depth[..., DEPTH_THREE_QUARTERS][hits] > depth[..., DEPTH_HALF][hits])
    outside = np.isnan(depth2[..., DEPTH_MEAN])
    assert np.all(np.isnan(depth[..., DEPTH_QUARTER][outside]))
    faint = box_renderer(0.02)  # 1 - 0.98**39 = 0.55: crosses 1/4 and 1/2, not 3/4
    _rgba, d = render_depth_layers(faint, camera, 24, 24)
    assert np.all(np.isfinite(d[..., DEPTH_QUARTER][hits]))
    assert np.all(np.isnan(d[..., DEPTH_THREE_QUARTERS][hits]))


def test_rgba_is_bit_identical_to_render():
    rng = np.random.default_rng(4)
    from scipy.ndimage import gaussian_filter

    data = gaussian_filter(rng.random((22, 20, 24)), 2.0)
    data = ((data - data.min()) / (data.max() - data.min())).astype(np.float32)
    volume = Volume(data, (1.0, 0.8, 1.2))
    tf = TransferFunction(
        name="ramp",
        color_points=np.array([[0.0, 0.9, 0.3, 0.1], [0.5, 0.8, 0.8, 0.2], [1.0, 0.2, 0.4, 1.0]]),
        opacity_points=np.array([[0.0, 0.0], [0.3, 0.0], [0.6, 0.25], [1.0, 0.7]]),
        window=(0.0, 1.0),
    )
    renderer = Renderer(volume, tf, samples=200)
    for view in [(30.0, 20.0), (250.0, -45.0)]:
        camera = orbit_camera(View(*view), volume.center_mm, volume.radius_mm)
        rgba, depth = renderer.render_with_depth(camera, 36, 30)
        assert np.array_equal(rgba, renderer.render(camera, 36, 30))
        assert depth.shape == (30, 36, 2) and depth.dtype == np.float32
        hit = rgba[..., 3] > 0
        assert hit.any() and np.all(np.isfinite(depth[..., DEPTH_MEAN][hit]))
        assert np.all(np.isnan(depth[..., DEPTH_MEAN][~hit]))
