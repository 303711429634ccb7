"""Tests of device_runtime.reconstruct: exactness, changed-cells-only, scratch bound."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from device_runtime.reconstruct import (
    Reconstructor,
    reconstruct_view,
    reconstruction_memory_bytes,
)
from protocol.image import EigenspaceImage


def make_space(height, width, cell_h, cell_w, *, k_max=10, zero_fraction=0.3, seed=0):
    rng = np.random.default_rng(seed)
    ny, nx = -(-height // cell_h), -(-width // cell_w)
    n_cells = ny * nx
    values = cell_h * cell_w * 3
    counts = rng.integers(1, k_max + 1, n_cells)
    counts[rng.random(n_cells) < zero_fraction] = 0
    counts[0] = max(counts[0], 1)
    n_coeff = int(counts.sum())
    return {
        "mean": rng.integers(0, 256, (n_cells, values), dtype=np.uint8),
        "eigenimages": rng.integers(-127, 128, (n_coeff, values), dtype=np.int8),
        "scales": (rng.random(n_coeff) * 0.05 + 0.001).astype(np.float32),
        "n_components": counts.astype(np.int32),
        "image_shape": (height, width),
        "cell_shape": (cell_h, cell_w),
    }


def build(space, **kwargs):
    return Reconstructor(
        space["mean"],
        space["eigenimages"],
        space["scales"],
        space["n_components"],
        space["image_shape"],
        space["cell_shape"],
        **kwargs,
    )


def reference(space, y):
    """The formula of model.md in float64, before rounding: (H, W, 3) float64."""
    height, width = space["image_shape"]
    cell_h, cell_w = space["cell_shape"]
    ny, nx = -(-height // cell_h), -(-width // cell_w)
    offsets = np.concatenate([[0], np.cumsum(space["n_components"])])
    x = space["mean"].astype(np.float64)
    for c in range(ny * nx):
        a, b = offsets[c], offsets[c + 1]
        coeff = y[a:b].astype(np.float64) * space["scales"][a:b].astype(np.float64)
        x[c] += coeff @ space["eigenimages"][a:b].astype(np.float64)
    padded = x.reshape(ny, nx, cell_h, cell_w, 3).transpose(0, 2, 1, 3, 4)
    return padded.reshape(ny * cell_h, nx * cell_w, 3)[:height, :width]


def assert_matches_reference(frame, ref):
    expected = np.clip(np.rint(ref), 0, 255)
    # float32 accumulation may land on the other side of a .5 tie: only there may it differ
    near_tie = np.abs(np.abs(ref - np.floor(ref)) - 0.5) < 1e-3
    assert frame.dtype == np.uint8
    assert frame.shape == ref.shape
    mismatch = (frame != expected) & ~near_tie
    assert not mismatch.any(), f"{mismatch.sum()} pixels differ from the float64 reference"
    assert np.abs(frame.astype(np.int64) - expected).max() <= 1


CONFIGS = [
    # (height, width, cell_h, cell_w, scratch_bytes, threads): batches, tiles, accumulation
    (48, 64, 16, 16, 1 << 20, 1),  # divisible, one batch
    (37, 23, 8, 8, 1 << 20, 1),  # padding at bottom and right
    (37, 23, 8, 8, 4000, 1),  # tiny scratch: many batches and big-cell tiles
    (37, 23, 8, 8, 4000, 2),  # two threads
    (40, 30, 40, 30, 1 << 20, 1),  # one cell (standard), fits
    (40, 30, 40, 30, 6000, 1),  # one cell, tiles of pixel rows
    (40, 30, 40, 30, 1200, 1),  # one cell, component chunks accumulated
    (5, 7, 4, 4, 1 << 16, 1),  # cells larger than the leftover image
]


@pytest.mark.parametrize("height,width,cell_h,cell_w,scratch,threads", CONFIGS)
def test_matches_float64_reference(height, width, cell_h, cell_w, scratch, threads):
    space = make_space(height, width, cell_h, cell_w, seed=height * width)
    rec = build(space, scratch_bytes=scratch, threads=threads)
    rng = np.random.default_rng(1)
    try:
        for _ in range(3):
            y = (rng.standard_normal(rec.n_coefficients) * 400).astype(np.float32)
            assert_matches_reference(rec.update(y), reference(space, y))
    finally:
        rec.close()


def test_big_cell_paths_are_exercised():
    space = make_space(40, 30, 40, 30, k_max=6, zero_fraction=0)
    tiles = build(space, scratch_bytes=6000)._workers[0].jobs[0]
    chunks = build(space, scratch_bytes=1200)._workers[0].jobs[0]
    assert len(tiles.tiles) > 1 and tiles.chunk == space["n_components"][0]
    assert chunks.chunk < space["n_components"][0]


def test_only_changed_cells_are_recomputed():
    space = make_space(37, 23, 8, 8, zero_fraction=0.3, seed=3)
    rec = build(space, scratch_bytes=1 << 20)
    rng = np.random.default_rng(2)
    y = (rng.standard_normal(rec.n_coefficients) * 300).astype(np.float32)
    rec.update(y)
    assert rec.cells_recomputed == int((space["n_components"] > 0).sum())
    before = rec.update(y).copy()
    assert rec.cells_recomputed == 0
    offsets = np.concatenate([[0], np.cumsum(space["n_components"])])
    cell = int(np.flatnonzero(space["n_components"] >= 2)[-1])
    y2 = y.copy()
    y2[offsets[cell] + 1] += 500.0
    after = rec.update(y2)
    assert rec.cells_recomputed == 1
    assert_matches_reference(after, reference(space, y2))
    # pixels outside that cell are untouched
    nx = 3  # 23 px wide in cells of 8
    cy, cx = divmod(cell, nx)
    mask = np.ones(after.shape[:2], bool)
    mask[cy * 8 : cy * 8 + 8, cx * 8 : cx * 8 + 8] = False
    assert np.array_equal(after[mask], before[mask])
    assert not np.array_equal(after[~mask], before[~mask])
    assert rec.total_cells_recomputed == int((space["n_components"] > 0).sum()) + 1


def test_partial_change_inside_one_batch_with_threads():
    space = make_space(64, 64, 8, 8, seed=5)
    rec = build(space, scratch_bytes=50_000, threads=2)
    rng = np.random.default_rng(3)
    y = (rng.standard_normal(rec.n_coefficients) * 300).astype(np.float32)
    rec.update(y)
    offsets = np.concatenate([[0], np.cumsum(space["n_components"])])
    cells = np.flatnonzero(space["n_components"])[[0, 5, -1]]
    for c in cells:
        y[offsets[c]] -= 123.0
    frame = rec.update(y)
    assert rec.cells_recomputed == 3
    assert_matches_reference(frame, reference(space, y))
    rec.close()


def test_a_group_whose_cells_partly_changed_writes_each_to_its_own_place():
    # every other cell with components changes: each group holds changed and unchanged
    # cells, and the changed ones are written together
    space = make_space(64, 64, 8, 8, zero_fraction=0.2, seed=6)
    rec = build(space, scratch_bytes=20_000)
    rng = np.random.default_rng(4)
    y = (rng.standard_normal(rec.n_coefficients) * 300).astype(np.float32)
    before = rec.update(y).copy()
    offsets = np.concatenate([[0], np.cumsum(space["n_components"])])
    cells = np.flatnonzero(space["n_components"])[::2]
    groups = [job for job in rec._workers[0].groups
              if np.isin(cells, range(job.start, job.stop)).sum() >= 2]
    assert len(groups) > 1 and all(
        np.count_nonzero(space["n_components"][job.start:job.stop])
        > np.isin(cells, range(job.start, job.stop)).sum() for job in groups)
    for c in cells:
        y[offsets[c + 1] - 1] += 321.0
    frame = rec.update(y)
    assert rec.cells_recomputed == cells.size
    assert_matches_reference(frame, reference(space, y))
    moved = np.any(frame != before, axis=2)
    rows, cols = np.nonzero(moved)
    assert set((rows // 8 * 8 + cols // 8).tolist()) <= set(cells.tolist())


def blend_bits(space, y):
    """The blend's arithmetic, one cell at a time: ``w_c @ float32(E_c)`` with ``w = y *
    scales`` (float32, one BLAS product per cell), plus the mean, rounded and clipped."""
    offsets = np.concatenate([[0], np.cumsum(space["n_components"])])
    w = y * space["scales"]
    out = space["mean"].astype(np.float32)
    for c in range(len(space["n_components"])):
        a, b = offsets[c], offsets[c + 1]
        if b > a:
            out[c] = np.matmul(w[a:b], space["eigenimages"][a:b].astype(np.float32)) + out[c]
    height, width = space["image_shape"]
    cell_h, cell_w = space["cell_shape"]
    ny, nx = -(-height // cell_h), -(-width // cell_w)
    pixels = np.clip(np.rint(out), 0, 255).astype(np.uint8)
    padded = pixels.reshape(ny, nx, cell_h, cell_w, 3).transpose(0, 2, 1, 3, 4)
    return padded.reshape(ny * cell_h, nx * cell_w, 3)[:height, :width]


@pytest.mark.parametrize("scratch,threads", [(1 << 20, 1), (20_000, 1), (20_000, 2)])
def test_the_blend_is_its_per_cell_products_bit_for_bit(scratch, threads, monkeypatch):
    """Every way `update` runs a cell that fits the scratch (one group or several, a cell of
    one component, two threads, cells changing in part) computes one float32 BLAS product
    per cell over all its rows, zero scores included, bit for bit (checked on the sums
    themselves: another order of the same terms rounds them otherwise; on the frames
    that is seen only where a value lies on a .5 tie), and its frames are those products'."""
    space = make_space(45, 61, 8, 8, k_max=12, zero_fraction=0.2, seed=21)
    counts = space["n_components"]
    assert (counts == 1).any()
    offsets = np.concatenate([[0], np.cumsum(counts)])
    sums: list[tuple[np.ndarray, np.ndarray]] = []
    write = Reconstructor._write_cells

    def spy(self, out, cells, where):
        sums.append((np.arange(self.n_cells)[cells], out.copy()))  # before the mean is added
        write(self, out, cells, where)

    monkeypatch.setattr(Reconstructor, "_write_cells", spy)
    rec = build(space, scratch_bytes=scratch, threads=threads)
    rng = np.random.default_rng(8)
    y = (rng.standard_normal(rec.n_coefficients) * 300).astype(np.float32)
    try:
        for _ in range(6):
            y[rng.random(y.size) < 0.4] = 0.0  # zero scores, as a quantized table has
            sums.clear()
            np.testing.assert_array_equal(rec.update(y), blend_bits(space, y))
            w = y * space["scales"]
            seen = 0
            for cells, out in sums:
                for c, row in zip(cells, out):
                    a, b = offsets[c], offsets[c + 1]
                    want = np.matmul(w[a:b], space["eigenimages"][a:b].astype(np.float32))
                    np.testing.assert_array_equal(row, want)
                    seen += 1
            assert seen == rec.cells_recomputed > 0
            cells = rng.choice(np.flatnonzero(counts), 5, replace=False)
            for c in cells:  # some cells change, in part
                y[offsets[c]:offsets[c + 1]] += rng.normal(0, 200, counts[c]).astype(np.float32)
    finally:
        rec.close()


@pytest.mark.parametrize("share", [0.2, 0.6, 0.95])
@pytest.mark.parametrize("cost", [1.25, 3.0, 1e9])
def test_a_correction_is_its_cells_residual_fit_whichever_way_a_batch_runs(share, cost,
                                                                           monkeypatch):
    """A correction's coefficients are sparse; a batch gathers its non-zero rows or casts
    all its rows (`GATHER_ROW_COST` decides): either way the cells it leaves alone keep the
    synthesized frame's bits, the others are ``synth + V d`` (to a level of the float64
    formula), and only corrected cells count."""
    from device_runtime import reconstruct

    monkeypatch.setattr(reconstruct, "GATHER_ROW_COST", cost)
    space = make_space(40, 56, 8, 8, zero_fraction=0.2, seed=11)
    rng = np.random.default_rng(5)
    synth = rng.integers(0, 256, (40, 56, 3), dtype=np.uint8)
    counts = space["n_components"]
    offsets = np.concatenate([[0], np.cumsum(counts)])
    cells = np.flatnonzero((counts > 0) & (rng.random(35) < share))
    d = np.zeros(int(offsets[-1]), np.float32)
    for c in cells:
        n = int(rng.integers(1, counts[c] + 1))  # its coefficients end after n
        d[offsets[c]:offsets[c] + n] = rng.normal(0, 400, n) * (rng.random(n) < 0.5)
        d[offsets[c] + n - 1] = 300.0  # the last one sent is not zero
    rec = build(space, scratch_bytes=60_000)
    rec.seam_strength = 0.0  # the cells as computed (the border smoothing: below)
    frame = rec.correct(d, synth).copy()
    assert rec.cells_recomputed == len(cells)
    as_cells = frame.reshape(5, 8, 7, 8, 3).transpose(0, 2, 1, 3, 4).reshape(35, -1)
    synth_cells = synth.reshape(5, 8, 7, 8, 3).transpose(0, 2, 1, 3, 4).reshape(35, -1)
    untouched = np.setdiff1d(np.arange(35), cells)
    np.testing.assert_array_equal(as_cells[untouched], synth_cells[untouched])
    want = synth_cells.astype(np.float64)
    for c in cells:
        a, b = offsets[c], offsets[c + 1]
        want[c] += (d[a:b].astype(np.float64) * space["scales"][a:b]) @ space[
            "eigenimages"][a:b].astype(np.float64)
    want = np.clip(np.rint(want), 0, 255)
    assert np.abs(as_cells[cells].astype(np.float64) - want[cells]).max() <= 1.0
    assert not np.array_equal(as_cells[cells], synth_cells[cells])


def test_zero_component_cells_show_their_mean():
    space = make_space(24, 24, 8, 8, zero_fraction=0.5, seed=7)
    counts = space["n_components"]
    assert (counts == 0).any()
    rec = build(space)
    rng = np.random.default_rng(4)
    for _ in range(2):
        frame = rec.update((rng.standard_normal(rec.n_coefficients) * 500).astype(np.float32))
    cells = frame.reshape(3, 8, 3, 8, 3).transpose(0, 2, 1, 3, 4).reshape(9, -1)
    for c in np.flatnonzero(counts == 0):
        assert np.array_equal(cells[c], space["mean"][c])


def test_all_zero_components_and_initial_frame_is_the_mean():
    space = make_space(10, 10, 4, 4, zero_fraction=1.0)
    space["n_components"][:] = 0
    space["eigenimages"] = np.zeros((0, 48), np.int8)
    space["scales"] = np.zeros(0, np.float32)
    rec = build(space)
    frame = rec.update(np.zeros(0, np.float32))
    padded = space["mean"].reshape(3, 3, 4, 4, 3).transpose(0, 2, 1, 3, 4).reshape(12, 12, 3)
    assert np.array_equal(frame, padded[:10, :10])


def test_padding_is_cropped_and_buffer_reused():
    space = make_space(37, 23, 8, 8)
    rec = build(space)
    y = np.zeros(rec.n_coefficients, np.float32)
    first = rec.update(y)
    assert first.shape == (37, 23, 3) and first.flags.c_contiguous
    second = rec.update(y + 1)
    assert second is first


def test_scratch_bound_respected_for_large_k():
    # K * cell_values * 4 bytes of float32 would be ~9.8 MB; scratch is 64 KiB
    rng = np.random.default_rng(0)
    n_cells, values = 16, 16 * 16 * 3
    counts = np.full(n_cells, 200, np.int32)
    n_coeff = int(counts.sum())
    mean = rng.integers(0, 256, (n_cells, values), dtype=np.uint8)
    eig = rng.integers(-127, 128, (n_coeff, values), dtype=np.int8)
    scales = np.full(n_coeff, 0.01, np.float32)
    y = rng.standard_normal(n_coeff).astype(np.float32)
    scratch = 64 << 10
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        rec = Reconstructor(mean, eig, scales, counts, (64, 64), (16, 16), scratch_bytes=scratch)
        rec.update(y)
        rec.update(y * 2)
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    frame_bytes = 64 * 64 * 3
    allowance = scratch + frame_bytes + 64 * n_coeff + 128 * 1024
    assert peak < allowance, f"peak {peak} B over {allowance} B"
    assert peak < n_coeff * values * 4 / 8


def test_from_image_and_reconstruct_view():
    space = make_space(20, 20, 8, 8, seed=9)
    image = EigenspaceImage(
        space["image_shape"],
        space["cell_shape"],
        space["mean"],
        space["eigenimages"],
        space["scales"],
        space["n_components"],
    )
    y = np.random.default_rng(0).standard_normal(image.n_coefficients).astype(np.float32) * 99
    assert_matches_reference(reconstruct_view(image, y), reference(space, y))
    assert np.array_equal(Reconstructor.from_image(image).update(y), reconstruct_view(image, y))


def test_memory_estimate_covers_the_arrays():
    space = make_space(37, 23, 8, 8)
    estimate = reconstruction_memory_bytes((37, 23), (8, 8), len(space["scales"]))
    arrays = sum(space[k].nbytes for k in ("mean", "eigenimages", "scales"))
    assert estimate > arrays + 37 * 23 * 3


@pytest.mark.parametrize(
    "change,match",
    [
        ({"mean": np.zeros((2, 2), np.uint8)}, "mean must be uint8"),
        ({"eigenimages": "x"}, "eigenimages must be int8"),
        ({"scales": None}, "scales must be float32"),
        ({"n_components": np.array([1.5])}, "n_components must be ints"),
        ({"image_shape": (0, 5)}, "must be positive"),
    ],
)
def test_bad_arrays_are_refused(change, match):
    space = {**make_space(8, 8, 4, 4), **change}
    if "scales" in change and change["scales"] is None:
        space["scales"] = np.zeros(3, np.float64)
    with pytest.raises(ValueError, match=match):
        build(space)


def test_bad_arguments_are_refused():
    space = make_space(8, 8, 4, 4)
    with pytest.raises(ValueError, match="threads"):
        build(space, threads=3)
    with pytest.raises(ValueError, match="scratch_bytes=10 is below the minimum"):
        build(space, scratch_bytes=10)
    rec = build(space)
    with pytest.raises(ValueError, match=r"y must have shape"):
        rec.update(np.zeros(rec.n_coefficients + 1, np.float32))
    y = np.zeros(rec.n_coefficients, np.float32)
    y[0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        rec.update(y)


def test_auto_threads_follow_the_cpus_the_process_may_use(monkeypatch):
    """A big eigenspace gets 2 threads only where the process may run on 2 CPUs: pinned to
    one (``taskset -c 0``, a one-core board's measurements) it gets 1, whatever the
    machine's count."""
    import os

    from device_runtime import reconstruct

    n_cells, values, k = 16, 16 * 16 * 3, 700  # 8.6 MB of int8 eigenimages
    args = (np.zeros((n_cells, values), np.uint8), np.zeros((n_cells * k, values), np.int8),
            np.ones(n_cells * k, np.float32), np.full(n_cells, k), (64, 64), (16, 16))
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0}, raising=False)
    assert reconstruct.usable_cpus() == 1
    assert Reconstructor(*args, threads="auto").threads == 1
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    r = Reconstructor(*args, threads="auto")
    assert r.threads == 2
    r.close()


def test_the_border_smoothing_follows_its_integer_rule_and_refuses_a_strength_it_cannot_hold():
    """``correct`` smooths the correction's jump at cell borders: ``J = (q - p) - (synth_q -
    synth_p)``, ``j = (J * W + 128) >> 8`` with ``W = round(256 * strength / 3)``, ``p += j``,
    ``q -= j`` (vertical borders first), checked against that rule written out in int64 for
    a new frame and for a second correction of the held one; past 0.75 it refuses."""
    space = make_space(40, 56, 8, 8, zero_fraction=0.0, seed=3)
    rng = np.random.default_rng(9)
    rec = build(space)
    n = int(np.sum(space["n_components"]))
    base = rng.integers(0, 256, (40, 56, 3), dtype=np.uint8)
    for synth in (base, None):  # a new frame, then the held one
        d = rng.normal(0, 300, n).astype(np.float32)
        rec.seam_strength = 0.0
        sharp = rec.correct(d, synth).astype(np.int64)
        rec.seam_strength = 0.5
        got = rec.correct(d).astype(np.int64)
        want, w = sharp.copy(), round(256 * 0.5 / 3)
        for axis, size in ((1, 8), (0, 8)):
            b = np.arange(size, want.shape[axis], size)
            p, q = np.take(want, b - 1, axis=axis), np.take(want, b, axis=axis)
            own = base.astype(np.int64)
            jump = (q - p) - (np.take(own, b, axis=axis) - np.take(own, b - 1, axis=axis))
            j = (jump * w + 128) >> 8
            index: list = [slice(None)] * 3
            index[axis] = b - 1
            want[tuple(index)] = np.clip(p + j, 0, 255)
            index[axis] = b
            want[tuple(index)] = np.clip(q - j, 0, 255)
        np.testing.assert_array_equal(got, want)
        assert not np.array_equal(got, sharp)
    rec.seam_strength = 1.0
    with pytest.raises(ValueError, match="seam_strength"):
        rec.correct(d)
    rec.close()


def _seams_whole_frame(frame, own, cell, strength):
    """The seam rule of `Reconstructor.correct` applied to every border of the frame
    (vertical borders, then horizontal): at ``p | q`` with ``J = (q - p) - (own_q - own_p)``,
    ``j = (J * W + 128) >> 8``, ``W = round(256 * strength / 3)``; ``p += j``, ``q -= j``."""
    out = frame.astype(np.int32)
    weight = round(256 * strength / 3)
    for axis, size in ((1, cell[1]), (0, cell[0])):
        b = np.arange(size, out.shape[axis], size)
        p, q = np.take(out, b - 1, axis=axis), np.take(out, b, axis=axis)
        jump = (q - p) - (np.take(own, b, axis=axis).astype(np.int32)
                          - np.take(own, b - 1, axis=axis))
        j = (jump * weight + 128) >> 8
        index: list = [slice(None)] * 3
        for at, value in ((b - 1, p + j), (b, q - j)):
            index[axis] = at
            out[tuple(index)] = np.clip(value, 0, 255)
    return out.astype(np.uint8)


@pytest.mark.parametrize("cells", [[(2, 3), (3, 4)], [(0, 0)], [(5, 7), (0, 7)], [(3, 1)]])
def test_seam_smoothing_of_the_changed_cells_box_is_the_whole_frames(cells):
    """The device smooths only the borders in the box of corrected cells (and the cells next
    to it that the vertical pass touches): the frame is the rule applied to every border,
    bit for bit, whichever cells (diagonal neighbours, corners, edges of a cropped frame)."""
    space = make_space(44, 61, 8, 8, k_max=6, zero_fraction=0.0, seed=3)
    rng = np.random.default_rng(8)
    synth = rng.integers(0, 256, (44, 61, 3), dtype=np.uint8)
    offsets = np.concatenate([[0], np.cumsum(space["n_components"])])
    d = np.zeros(int(offsets[-1]), np.float32)
    for r, c in cells:
        cell = r * 8 + c
        d[offsets[cell]:offsets[cell + 1]] = rng.normal(0, 3000, offsets[cell + 1] - offsets[cell])
    rec = build(space)
    rec.seam_strength = 0.0
    sharp = rec.correct(d, synth).copy()
    rec.seam_strength = 0.5
    smooth = rec.correct(d, synth).copy()
    assert not np.array_equal(sharp, smooth)
    np.testing.assert_array_equal(smooth, _seams_whole_frame(sharp, synth, (8, 8), 0.5))
    # again on the frame held (a later correction of the same frame)
    np.testing.assert_array_equal(rec.correct(d), smooth)
