"""Sparse ray-casting: any subset of the pixel grid equals those pixels of a full render."""

from __future__ import annotations

import numpy as np
import pytest

from host.render.camera import View, orbit_camera
from host.render.raycast import Renderer, strided_pixels
from host.render.transfer import default_transfer_function
from host.volume import builtin_volume

SIZE = (37, 29)  # width, height: odd, not a multiple of any stride


@pytest.fixture(scope="module", params=["head", "tooth"])
def scene(request):
    volume = builtin_volume(request.param)
    renderer = Renderer(volume, default_transfer_function(volume), samples=200)
    return volume, renderer


def cameras(volume):
    yield orbit_camera(View(33.0, 12.0), volume.center_mm, volume.radius_mm)
    yield orbit_camera(View(-120.0, -40.0), volume.center_mm, volume.radius_mm,
                       projection="orthographic")


@pytest.mark.parametrize("stride,offset", [(1, (0, 0)), (2, (1, 0)), (3, (2, 1)), (4, (0, 3)),
                                           (8, (5, 7))])
def test_strided_equals_full_render(scene, stride, offset):
    volume, renderer = scene
    w, h = SIZE
    for camera in cameras(volume):
        full = renderer.render(camera, w, h)
        assert full[..., 3].max() > 0.1  # the object is in view, so equality means something
        sparse = renderer.render_strided(camera, w, h, stride, offset)
        dy, dx = offset
        np.testing.assert_array_equal(sparse, full[dy::stride, dx::stride])


def test_pixel_list_equals_full_render(scene):
    volume, renderer = scene
    w, h = SIZE
    rng = np.random.default_rng(3)
    rows = rng.integers(0, h, 300)
    cols = rng.integers(0, w, 300)  # repeats and any order are allowed
    for camera in cameras(volume):
        full = renderer.render(camera, w, h)
        sparse = renderer.render_pixels(camera, w, h, rows, cols)
        assert sparse.shape == (300, 4) and sparse.dtype == np.float32
        np.testing.assert_array_equal(sparse, full[rows, cols])
        np.testing.assert_array_equal(renderer.composite(sparse),
                                      renderer.composite(full)[rows, cols])


def test_one_thread_equals_all_threads(scene):
    volume, renderer = scene
    one = Renderer(volume, renderer.tf, samples=200, workers=1)
    camera = next(cameras(volume))
    rows, cols = strided_pixels(*SIZE, 3, (1, 2))
    np.testing.assert_array_equal(one.render_pixels(camera, *SIZE, rows, cols),
                                  renderer.render_pixels(camera, *SIZE, rows, cols))


def test_empty_pixel_list(scene):
    volume, renderer = scene
    camera = next(cameras(volume))
    out = renderer.render_pixels(camera, *SIZE, np.array([], dtype=np.int64),
                                 np.array([], dtype=np.int64))
    assert out.shape == (0, 4) and out.dtype == np.float32


def test_strided_pixels_pattern():
    rows, cols = strided_pixels(7, 5, 2, (1, 0))
    assert rows.tolist() == [1, 1, 1, 1, 3, 3, 3, 3]
    assert cols.tolist() == [0, 2, 4, 6, 0, 2, 4, 6]
    # the s*s offsets of one stride tile the image exactly once
    seen = np.zeros((5, 7), dtype=int)
    for dy in range(3):
        for dx in range(3):
            r, c = strided_pixels(7, 5, 3, (dy, dx))
            seen[r, c] += 1
    assert np.all(seen == 1)


@pytest.mark.parametrize("rows,cols,message", [
    ([0, 29], [0, 0], "within"),
    ([0, -1], [0, 0], "within"),
    ([0, 1], [0], "one length"),
    ([0.5], [1.0], "integer"),
])
def test_bad_pixels_are_refused(scene, rows, cols, message):
    volume, renderer = scene
    camera = next(cameras(volume))
    with pytest.raises(ValueError, match=message):
        renderer.render_pixels(camera, *SIZE, np.array(rows), np.array(cols))


@pytest.mark.parametrize("stride,offset", [(0, (0, 0)), (2, (2, 0)), (2, (0, -1))])
def test_bad_stride_is_refused(stride, offset):
    with pytest.raises(ValueError):
        strided_pixels(8, 8, stride, offset)
