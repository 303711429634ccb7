"""The steps of `device_runtime.warping.forward_warp` on their own (the whole warp is
`test_warping.py` and the golden frames): the working rectangle, the emptied grid border and
the copy of the compact grid into the frame."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from device_runtime.warping import _copy_into_frame, _empty_grid_border, _rectangle


def test_the_rectangle_is_where_splats_landed_with_three_pixels_to_spare_inside_the_grid():
    w = SimpleNamespace(height=20, width=30)  # padded grid 22 x 32
    assert _rectangle(w, (10.0, 12.5, 5.0, 7.9)) == (2, 11, 7, 16)
    assert _rectangle(w, (0.0, 31.0, 0.0, 21.0)) == (0, 22, 0, 32)  # clamped to the grid


def test_the_grid_border_is_emptied_only_where_the_rectangle_meets_it():
    plane = np.ones(4 * 5, dtype=np.float32)
    _empty_grid_border((plane,), (0, 4, 3, 8), grid_h=10, grid_w=8)  # top and right edges
    p2 = plane.reshape(4, 5)
    assert not p2[0].any() and not p2[:, -1].any()
    assert p2[1:, :-1].all()  # the bottom row and left column are inside the grid


def test_the_compact_grid_lands_on_the_frame_one_pixel_up_and_left():
    frame = np.zeros((4, 6, 3), dtype=np.uint8)
    rect = (0, 3, 2, 5)  # padded rows 0..2, columns 2..4
    pb = np.arange(3 * 9, dtype=np.float32).reshape(3, 9) + 0.5
    _copy_into_frame(frame, pb, rect)
    # padded row 0 is the border: frame rows 0..1 get padded rows 1..2, columns 1..3
    assert frame[0, 1:4, 0].tolist() == [3, 4, 5] and frame[1, 1:4, 2].tolist() == [24, 25, 26]
    assert frame[2:].sum() == 0 and frame[:, 0].sum() == 0 and frame[:, 4:].sum() == 0
