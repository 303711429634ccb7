"""The depth warp at the image's borders (device_runtime/warping.py): splats that reach every
border, some of them hidden, warp without error at every size; the default `fit` with depth
and a device orbiting its image work on small images of both built-in volumes."""

from __future__ import annotations

import numpy as np
import pytest

from device_runtime.warping import Warper, forward_warp
from host.cli import main as eigencast

#: the borders a source plane reaches: rows and columns of the frame it covers
_EXTENTS = {
    "all": (slice(None), slice(None)),
    "top": (slice(0, None), slice(3, -3)),
    "bottom": (slice(None, -1), slice(3, -3)),
    "left": (slice(3, -3), slice(0, None)),
    "right": (slice(3, -3), slice(None, -1)),
}


def _plane(w: Warper, depth: float, shade: int, extent):
    valid = np.zeros((w.height, w.width), bool)
    valid[extent] = True
    colour = np.full((w.height, w.width, 3), shade, np.uint8)
    return w.unproject(colour, np.full((w.height, w.width), depth, np.float32), valid), valid


def _within(mask: np.ndarray) -> np.ndarray:
    """``mask`` less the pixels with one of their 8 neighbours outside it (the 3 x 3 splat
    filter's reach; the frame's edge counts as inside)."""
    pad = np.pad(mask, 1, mode="edge")
    h, w = mask.shape
    out = mask.copy()
    for dy in range(3):
        for dx in range(3):
            out &= pad[dy:dy + h, dx:dx + w]
    return out


@pytest.mark.parametrize("size", [(32, 32), (48, 40), (64, 64), (96, 96), (33, 71)])
@pytest.mark.parametrize("border", sorted(_EXTENTS))
def test_splats_reaching_every_border_with_some_hidden_warp_to_the_front_surface(size, border):
    """A plane in front of another, both reaching the border(s): the compact grid is the whole
    padded grid, and hidden splats still have their spare slot (it was one past the z-buffer,
    an IndexError)."""
    width, height = size
    w = Warper(30.0, 100.0, width, height, 1.0)
    pose = w.pose(20.0, 10.0)
    front, valid = _plane(w, 96.0, 200, _EXTENTS[border])
    back, _ = _plane(w, 104.0, 40, (slice(None), slice(None)))
    for weights in ([0.5, 0.5], [0.9, 0.1]):
        frame = forward_warp(w, [front, back], [pose, pose], np.array(weights), pose)
        # the front plane wins wherever it is; the hidden plane shows only where it is alone
        # (the splat filter blends the pixels along the front plane's edge)
        assert (frame[_within(valid)] == 200).all()
        assert (frame[_within(~valid)] == 40).all()
        assert frame[_within(valid)].size > 0
    # the warper's working set is clean for the next frame: a frame of the back plane alone
    alone = forward_warp(w, [back], [pose], np.array([1.0]), pose)
    assert (alone == 40).all()


@pytest.fixture(scope="module")
def small_models(tmp_path_factory):
    """The built-in head and tooth at 32, 64, 96 and 128 px on a 12 x 10 grid with depth,
    fitted with `fit`'s defaults (the splat filter's choice warps training views)."""
    root = tmp_path_factory.mktemp("small-depth")
    models = {}
    for volume in ("head", "tooth"):
        for size in (32, 64, 96, 128):
            db, ecs = root / f"{volume}{size}.cdb", root / f"{volume}{size}.ecs"
            assert eigencast(["render", f"builtin:{volume}", "-o", str(db), "--size", str(size),
                              "--views", "grid:12x10", "--samples", "120"]) == 0
            assert eigencast(["fit", str(db), "-o", str(ecs)]) == 0
            models[volume, size] = ecs
    return models


def test_default_fit_and_device_frames_work_at_every_small_size(small_models):
    """Every training view and every view between them warps (the frames a standalone device
    orbiting the image shows), on both volumes at each size."""
    from host.evaluate.warp import WarpFrames
    from host.fit import HostModel

    phi = np.arange(0.0, 360.0, 15.0)  # training views (30 degrees apart) and midpoints
    theta = np.linspace(-75.0, 75.0, 11)
    for (volume, size), ecs in small_models.items():
        model = HostModel.load(ecs)
        assert model.image.synthesis["method"].startswith("warp-depth"), (volume, size)
        frames = WarpFrames(model)
        shown = 0
        for t in theta:
            for p in phi:
                frame = frames.frame(float(p), float(t))
                assert frame.shape == (size, size, 3)
                shown += int(frame.any())
        assert shown == phi.size * theta.size, (volume, size)
