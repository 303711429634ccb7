"""The numba ray-caster against closed forms, symmetry, its numpy reference and itself."""

from __future__ import annotations

import json
import math

import numba
import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from host.errors import TransferFunctionError
from host.render.camera import View, orbit_camera
from host.render.raycast import (
    AMBIENT,
    DIFFUSE,
    EARLY_TERMINATION_ALPHA,
    SPECULAR,
    Renderer,
    warmup,
)
from host.render.raycast_reference import render_reference
from host.render.transfer import TransferFunction
from host.volume import Volume


def constant_tf(alpha: float, rgb=(1.0, 1.0, 1.0)) -> TransferFunction:
    return TransferFunction(
        name="constant",
        color_points=np.array([[0.0, *rgb], [1.0, *rgb]]),
        opacity_points=np.array([[0.0, alpha], [1.0, alpha]]),
        window=(0.0, 1.0),
    )


def ramp_tf() -> TransferFunction:
    """Zero opacity below t=0.3, then a ramp; colour varies with t."""
    return TransferFunction(
        name="ramp",
        color_points=np.array([[0.0, 0.9, 0.3, 0.1], [0.5, 0.8, 0.8, 0.2], [1.0, 0.2, 0.4, 1.0]]),
        opacity_points=np.array([[0.0, 0.0], [0.3, 0.0], [0.6, 0.25], [1.0, 0.7]]),
        window=(0.0, 1.0),
    )


def smooth_volume(shape=(24, 24, 24), spacing=(1.0, 0.8, 1.2), seed=0) -> Volume:
    """Smooth random blobs in [0, 1], (nz, ny, nx)."""
    rng = np.random.default_rng(seed)
    d = gaussian_filter(rng.random(shape), 2.0)
    d = (d - d.min()) / (d.max() - d.min())
    return Volume(d.astype(np.float32), spacing)


def blob_volume(n=40, center=(0.5, 0.5, 0.5), sigma_frac=0.12) -> Volume:
    """A Gaussian blob at fractional position ``center`` (x, y, z) in an n^3 box."""
    z, y, x = np.mgrid[0:n, 0:n, 0:n] / (n - 1.0)
    r2 = (x - center[0]) ** 2 + (y - center[1]) ** 2 + (z - center[2]) ** 2
    return Volume(np.exp(-r2 / (2 * sigma_frac**2)).astype(np.float32))


def cam(volume: Volume, phi: float, theta: float, projection="perspective"):
    return orbit_camera(View(phi, theta), volume.center_mm, volume.radius_mm, projection=projection)


def path_lengths_mm(volume: Volume, camera, width: int, height: int) -> np.ndarray:
    """Length of each pixel ray inside the box [0, extent] (test oracle, slab method)."""
    origins, dirs = camera.rays(width, height)
    hi = volume.extent_mm
    t0 = np.zeros((height, width))
    t1 = np.full((height, width), np.inf)
    for a in range(3):
        with np.errstate(divide="ignore"):
            ta = (0.0 - origins[..., a]) / dirs[..., a]
            tb = (hi[a] - origins[..., a]) / dirs[..., a]
        t0 = np.maximum(t0, np.minimum(ta, tb))
        t1 = np.minimum(t1, np.maximum(ta, tb))
    return np.maximum(t1 - t0, 0.0)


@pytest.fixture(scope="module", autouse=True)
def compiled():
    warmup()  # compile (or load from the disk cache) once for the module


# --------------------------------------------------------------------------- closed form
@pytest.mark.parametrize("step_units", [0.5, 0.1])
@pytest.mark.parametrize("view", [(0.0, 0.0, "orthographic"), (30.0, 20.0, "perspective")])
def test_homogeneous_box_matches_beer_lambert(step_units, view):
    # anisotropic spacing: the opacity unit is min(spacing) = 0.8 mm
    volume = Volume(np.full((12, 16, 20), 0.5, dtype=np.float32), spacing=(1.0, 1.5, 0.8))
    alpha = 0.02
    renderer = Renderer(volume, constant_tf(alpha), step=step_units, shading=False)
    camera = cam(volume, *view)
    image = renderer.render(camera, 48, 40)
    length = path_lengths_mm(volume, camera, 48, 40)
    expected = 1.0 - (1.0 - alpha) ** (length / 0.8)
    # Midpoint sampling takes round(L/step) samples: the effective path is within
    # step/2 of L, so |dA| <= -ln(1 - alpha) * (step/2) / unit.
    bound = -math.log(1.0 - alpha) * step_units / 2.0 + 1e-6
    assert np.abs(image[..., 3] - expected).max() <= bound
    assert np.all(image[length == 0.0] == 0.0)  # outside the box: nothing
    assert (length > 0).mean() > 0.1 and expected.max() > 0.3
    np.testing.assert_allclose(image[..., 0], image[..., 3], atol=1e-6)  # white: C = A
    if view[2] == "orthographic":  # every hit crosses the full 19 mm in x
        hits = length > 0
        np.testing.assert_allclose(length[hits], 19.0, atol=1e-9)


# --------------------------------------------------------------------------- symmetry
def test_mirror_symmetric_volume_gives_mirrored_images():
    base = smooth_volume(shape=(20, 18, 22), spacing=(1.0, 1.3, 0.9), seed=3)
    symmetric = Volume((base.data + base.data[:, :, ::-1]) / 2, base.spacing)  # x -> -x
    renderer = Renderer(symmetric, ramp_tf(), samples=150)
    for phi, theta in [(30.0, 20.0), (75.0, -40.0), (0.0, 60.0)]:
        a = renderer.render(cam(symmetric, phi, theta), 40, 32)
        b = renderer.render(cam(symmetric, 180.0 - phi, theta), 40, 32)
        assert a[..., 3].max() > 0.3
        np.testing.assert_allclose(b, a[:, ::-1], atol=2e-5)
    # the check can fail: the unsymmetrised volume does not mirror
    plain = Renderer(base, ramp_tf(), samples=150)
    a = plain.render(cam(base, 30.0, 20.0), 40, 32)
    b = plain.render(cam(base, 150.0, 20.0), 40, 32)
    assert np.abs(b - a[:, ::-1]).max() > 0.05


def test_image_orientation_up_is_top_and_right_is_right():
    # blob near +z (top) and +y; camera at +x looking -x: up = +z, right = +y
    volume = blob_volume(n=24, center=(0.5, 0.8, 0.8), sigma_frac=0.08)
    renderer = Renderer(volume, ramp_tf(), samples=100, shading=False)
    alpha = renderer.render(cam(volume, 0.0, 0.0), 32, 32)[..., 3]
    rows, cols = np.nonzero(alpha > 0.05)
    assert rows.max() < 16 and cols.min() >= 16
    # from +y (phi=90) looking -y, right = -x: a blob at +x shows on the left
    volume = blob_volume(n=24, center=(0.8, 0.5, 0.5), sigma_frac=0.08)
    renderer = Renderer(volume, ramp_tf(), samples=100, shading=False)
    alpha = renderer.render(cam(volume, 90.0, 0.0), 32, 32)[..., 3]
    _, cols = np.nonzero(alpha > 0.05)
    assert cols.max() < 16


# --------------------------------------------------------------------------- step invariance
def test_opacity_correction_makes_step_size_matter_little():
    volume = smooth_volume(seed=5)
    camera = cam(volume, 40.0, 25.0)
    images = {}
    for corrected in (True, False):
        for samples in (200, 400):  # step 0.25 and 0.125 voxels
            r = Renderer(
                volume, ramp_tf(), samples=samples, shading=False, opacity_correction=corrected
            )
            images[corrected, samples] = r.render(camera, 32, 32)
    diff = np.abs(images[True, 200] - images[True, 400])
    raw = np.abs(images[False, 200] - images[False, 400])
    # With correction only the sampling (Riemann-sum) error of the ray integral
    # remains, first order in the step: measured 0.001 mean / 0.03 max alpha
    # here, halving again with each halving of the step. Without correction the
    # optical depth doubles with the sample count: 0.013 mean / 0.3 max.
    assert diff[..., 3].mean() < 0.003 and diff.max() < 0.06
    assert raw[..., 3].mean() > 2 * 0.003 and raw.max() > 0.15
    assert images[True, 200][..., 3].mean() > 0.1


# --------------------------------------------------------------------------- numpy reference
@pytest.mark.parametrize(
    "phi, theta, projection",
    [
        (30.0, 20.0, "perspective"),
        (200.0, -50.0, "orthographic"),
        (0.0, 90.0, "perspective"),
        (90.0, 0.0, "orthographic"),
    ],
)
def test_agrees_with_numpy_reference(phi, theta, projection):
    volume = smooth_volume(seed=1)
    renderer = Renderer(volume, ramp_tf(), samples=120, shading=True)
    camera = cam(volume, phi, theta, projection)
    fast = renderer.render(camera, 32, 32)
    slow = render_reference(
        volume, ramp_tf(), camera, 32, 32, step_mm=renderer.step_mm, window=(0.0, 1.0), shading=True
    )
    # Same model; differences come from float32 vs float64 volume values, LUT
    # opacity correction order (~1e-6) and rays crossing the early-termination
    # threshold one sample apart (<= 1/255): far below one 8-bit level on average.
    diff = np.abs(fast - slow)
    assert diff.max() < 1e-3, diff.max()
    assert diff.mean() < 1e-5, diff.mean()
    assert slow[..., 3].mean() > 0.05  # a non-trivial image


def test_reference_comparison_is_sensitive():
    volume = smooth_volume(seed=1)
    camera = cam(volume, 30.0, 20.0)
    slow = render_reference(volume, ramp_tf(), camera, 32, 32, step_mm=0.3, window=(0.0, 1.0))
    shifted = Renderer(volume, ramp_tf(), step=0.3 / 0.8 * 1.5).render(camera, 32, 32)
    unshaded = Renderer(volume, ramp_tf(), step=0.3 / 0.8, shading=False).render(camera, 32, 32)
    assert np.abs(shifted - slow).max() > 1e-2
    assert np.abs(unshaded - slow).max() > 1e-2


# --------------------------------------------------------------------------- shading
def test_headlight_shading_closed_form_on_a_sphere():
    n = 33  # centre voxel 16 sits on the central pixel ray
    z, y, x = np.mgrid[0:n, 0:n, 0:n] - 16.0
    field = np.clip(1.0 - np.sqrt(x**2 + y**2 + z**2) / 14.0, 0.0, 1.0).astype(np.float32)
    volume = Volume(field)
    tf = TransferFunction(
        name="shell",
        color_points=np.array([[0.0, 0.5, 0.5, 0.5], [1.0, 0.5, 0.5, 0.5]]),
        opacity_points=np.array([[0.0, 0.0], [0.3, 0.0], [0.35, 0.9], [1.0, 0.9]]),
        window=(0.0, 1.0),
    )
    camera = cam(volume, 0.0, 0.0)
    shaded = Renderer(volume, tf, samples=300).render(camera, 33, 33)
    flat = Renderer(volume, tf, samples=300, shading=False).render(camera, 33, 33)
    np.testing.assert_array_equal(shaded[..., 3], flat[..., 3])  # shading never changes alpha
    centre_shaded = shaded[16, 16, :3] / shaded[16, 16, 3]
    centre_flat = flat[16, 16, :3] / flat[16, 16, 3]
    # the normal faces the headlight: c * (ambient + diffuse) + specular
    np.testing.assert_allclose(centre_flat, 0.5, atol=1e-6)
    np.testing.assert_allclose(centre_shaded, 0.5 * (AMBIENT + DIFFUSE) + SPECULAR, atol=1e-5)
    # near the silhouette the normal turns away: darker than the centre
    row = shaded[16]
    rim = next(c for c in range(33) if row[c, 3] > 0.5)
    assert row[rim, 0] / row[rim, 3] < 0.5 * (AMBIENT + DIFFUSE) + 0.5 * SPECULAR


# --------------------------------------------------------------------------- determinism, skipping
def test_deterministic_across_runs_and_thread_counts():
    volume = smooth_volume(seed=2)
    camera = cam(volume, 123.0, -33.0)
    full = Renderer(volume, ramp_tf(), samples=150)
    first = full.render(camera, 37, 29)
    np.testing.assert_array_equal(first, full.render(camera, 37, 29))
    one = Renderer(volume, ramp_tf(), samples=150, workers=1).render(camera, 37, 29)
    np.testing.assert_array_equal(first, one)
    max_threads = numba.config.NUMBA_NUM_THREADS
    if max_threads > 1:
        two = Renderer(volume, ramp_tf(), samples=150, workers=2).render(camera, 37, 29)
        np.testing.assert_array_equal(first, two)
    assert numba.get_num_threads() == max_threads  # restored after the render


def slabbed_volume(n=40) -> Volume:
    """Dense noise in [0.5, 1] cut by zero slabs. Voxels 0..8 in x and 24..32 in z are
    exactly one empty block (its 9 voxel planes) thick, so the first sample past them is
    already visible; the slabs x 24..31, y 16..23 and z 8..15 miss one plane of their
    block, so those blocks are NOT empty (a block must include its far face)."""
    rng = np.random.default_rng(4)
    d = 0.5 + 0.5 * gaussian_filter(rng.random((n, n, n)), 1.0)
    d[:, :, 0:9] = 0.0
    d[24:33, :, :] = 0.0
    d[:, :, 24:32] = 0.0
    d[:, 16:24, :] = 0.0
    d[8:16, :, :] = 0.0
    return Volume(d.astype(np.float32), spacing=(1.0, 0.9, 1.1))


def thin_tf() -> TransferFunction:
    """Visible for any t > 0, faint: rays go deep and see every block."""
    return TransferFunction(
        name="thin",
        color_points=np.array([[0.0, 1.0, 0.5, 0.2], [1.0, 0.2, 0.6, 1.0]]),
        opacity_points=np.array([[0.0, 0.0], [0.01, 0.02], [1.0, 0.05]]),
        window=(0.0, 1.0),
    )


@pytest.mark.parametrize("scene", ["blob", "slabs"])
@pytest.mark.parametrize(
    "phi, theta, projection",
    [
        (0.0, 0.0, "orthographic"),
        (37.0, 11.0, "perspective"),
        (0.0, 90.0, "orthographic"),
        (250.0, -70.0, "perspective"),
    ],
)
def test_empty_space_skipping_does_not_change_the_image(scene, phi, theta, projection):
    if scene == "blob":
        volume, tf = blob_volume(n=40, center=(0.45, 0.55, 0.5), sigma_frac=0.1), ramp_tf()
    else:
        volume, tf = slabbed_volume(), thin_tf()
    with_skip = Renderer(volume, tf, samples=200)
    without = Renderer(volume, tf, samples=200, empty_space_skipping=False)
    assert with_skip.empty_block_fraction > (0.5 if scene == "blob" else 0.3)
    camera = cam(volume, phi, theta, projection)
    a = with_skip.render(camera, 40, 40)
    b = without.render(camera, 40, 40)
    assert a[..., 3].max() > 0.5
    np.testing.assert_allclose(a, b, atol=1e-6, rtol=0)


def test_early_termination_threshold():
    volume = Volume(np.ones((10, 10, 10), dtype=np.float32))
    camera = cam(volume, 10.0, 10.0)
    stop = Renderer(volume, constant_tf(0.9), samples=200, shading=False).render(camera, 16, 16)
    full = Renderer(
        volume, constant_tf(0.9), samples=200, shading=False, early_termination=False
    ).render(camera, 16, 16)
    opaque = full[..., 3] > 0.9999
    assert opaque.sum() > 20
    assert np.all(stop[opaque, 3] > EARLY_TERMINATION_ALPHA)
    assert np.all(full[..., 3] - stop[..., 3] <= 1.0 - EARLY_TERMINATION_ALPHA + 1e-7)
    assert np.all(stop[..., 3] <= 1.0)


# --------------------------------------------------------------------------- output and settings
def test_rgb8_composites_over_background():
    volume = blob_volume(n=20)
    renderer = Renderer(volume, ramp_tf(), samples=100, background=(0.2, 0.4, 0.6))
    camera = cam(volume, 0.0, 0.0)
    rgba = renderer.render(camera, 24, 24)
    rgb8 = renderer.render_rgb8(camera, 24, 24)
    assert rgb8.shape == (24, 24, 3) and rgb8.dtype == np.uint8
    assert rgba.shape == (24, 24, 4) and rgba.dtype == np.float32
    assert tuple(rgb8[0, 0]) == (51, 102, 153)  # an empty corner shows the background
    expected = rgba[..., :3] + (1 - rgba[..., 3:]) * np.array([0.2, 0.4, 0.6])
    assert np.abs(rgb8 - expected * 255).max() <= 0.5 + 1e-3


def test_settings_record_what_was_used():
    volume = smooth_volume(spacing=(2.0, 0.5, 1.0))
    by_samples = Renderer(volume, ramp_tf(), samples=500).settings()
    json.dumps(by_samples)
    assert by_samples["samples"] == 500
    assert by_samples["step_mm"] == pytest.approx(2 * volume.radius_mm / 500)
    assert by_samples["tf_window"] == [0.0, 1.0]
    assert by_samples["early_termination_alpha"] == pytest.approx(1 - 1 / 255)
    for key in ("renderer", "shading", "background", "opacity_unit_mm", "lut_size"):
        assert key in by_samples
    by_step = Renderer(volume, ramp_tf(), step=0.5, shading=False).settings()
    assert by_step["samples"] is None and by_step["step_mm"] == pytest.approx(0.25)
    assert by_step["shading"] is False
    assert Renderer(volume, ramp_tf()).settings()["samples"] == 1000  # documented default


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"samples": 100, "step": 1.0}, "not both"),
        ({"samples": 1}, "samples=1"),
        ({"samples": 10**7}, "samples=10000000"),
        ({"samples": 2.5}, "integer"),
        ({"step": 0.0}, "step=0.0"),
        ({"step": float("nan")}, "step=nan"),
        ({"step": 1e-6}, "at most"),
        ({"background": (0.0, 2.0, 0.0)}, "background"),
        ({"background": (0.0, 0.0)}, "background"),
        ({"workers": 0}, "workers=0"),
        ({"workers": 10**6}, "workers=1000000"),
    ],
)
def test_bad_renderer_options_raise_value_error(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Renderer(blob_volume(n=8), ramp_tf(), **kwargs)


@pytest.mark.parametrize("size", [(0, 10), (10, 0), (8193, 10), (10.5, 10), (True, 10)])
def test_bad_image_size_raises_value_error(size):
    volume = blob_volume(n=8)
    with pytest.raises(ValueError, match=r"width|height"):
        Renderer(volume, ramp_tf()).render(cam(volume, 0.0, 0.0), *size)


def test_degenerate_window_and_non_finite_voxels():
    with pytest.raises((TransferFunctionError, ValueError), match="window"):
        tf = TransferFunction(
            name="flat",
            color_points=np.array([[0, 1, 1, 1], [1, 1, 1, 1.0]]),
            opacity_points=np.array([[0, 0.5], [1, 0.5]]),
            window=(1.0, 1.0),
        )
        Renderer(blob_volume(n=8), tf)
    data = blob_volume(n=12).data.copy()
    data[3:6, 3:6, 3:6] = np.nan
    data[7, 7, 7] = np.inf
    volume = Volume(data)
    auto = TransferFunction(
        name="auto",
        color_points=np.array([[0, 1, 1, 1], [1, 1, 1, 1.0]]),
        opacity_points=np.array([[0, 0.0], [1, 0.5]]),
    )
    image = Renderer(volume, auto, samples=50).render(cam(volume, 10.0, 10.0), 16, 16)
    assert np.all(np.isfinite(image)) and image[..., 3].max() > 0.1
    constant = Volume(np.full((6, 6, 6), 3.0, dtype=np.float32))
    image = Renderer(constant, auto, samples=20).render(cam(constant, 0.0, 0.0), 8, 8)
    assert np.all(np.isfinite(image))


def test_visible_sphere_frames_the_visible_object_not_the_box():
    """A small opaque ball off-centre in a big empty box: the sphere hugs the ball."""
    from host.render.raycast import Renderer

    n = 48
    z, y, x = np.mgrid[0:n, 0:n, 0:n].astype(np.float32)
    centre_vox = np.array([30.0, 14.0, 20.0])  # x, y, z
    ball = np.sqrt((x - centre_vox[0]) ** 2 + (y - centre_vox[1]) ** 2
                   + (z - centre_vox[2]) ** 2) <= 6.0
    spacing = (1.0, 2.0, 0.5)
    vol = Volume(ball.astype(np.float32), spacing)
    tf = TransferFunction("step", np.array([[0, 1, 1, 1], [1, 1, 1, 1]], float),
                          np.array([[0, 0], [0.4, 0], [0.6, 1], [1, 1]], float), window=(0, 1))
    centre, radius = Renderer(vol, tf, samples=64).visible_sphere()
    want = centre_vox * np.array(spacing)
    np.testing.assert_allclose(centre, want, atol=max(spacing))
    # the ball's farthest voxel is 6 voxels away along y (2 mm spacing) = 12 mm
    assert 12.0 <= radius <= 12.0 + 2 * max(spacing)
    assert radius < vol.radius_mm / 3

    empty = Volume(np.zeros((8, 8, 8), np.float32))
    c2, r2 = Renderer(empty, tf, samples=16).visible_sphere()
    np.testing.assert_allclose(c2, empty.center_mm)
    assert r2 == empty.radius_mm
