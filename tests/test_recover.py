"""Recovering a view's scores from a sparse ray-cast (host.fit.recover, issue 13)."""

from __future__ import annotations

import numpy as np
import pytest

from host.cli import main as eigencast
from host.fit.model import HostModel
from host.fit.pca import merge_cells
from host.fit.recover import (
    ProgressiveRecovery,
    SamplePattern,
    SparseRecovery,
    offset_order,
    sparse_samples,
)
from host.render.settings import RenderSettings, ViewRenderer

SIZE = 36  # a multiple of the cell: no padding, so full recovery is exactly `project`
CELL = 12
NOVEL = [(17.0, 23.0), (-101.0, -37.0), (160.0, 5.0)]


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    root = tmp_path_factory.mktemp("recover")
    db, path = root / "tooth.cdb", root / "tooth.ecs"
    assert eigencast(["render", "builtin:tooth", "-o", str(db), "--views", "grid:16x5",
                      "--size", str(SIZE), "--samples", "80"]) == 0
    assert eigencast(["fit", str(db), "-o", str(path), "--cell", str(CELL),
                      "--threshold", "0.99"]) == 0
    return HostModel.load(path)


@pytest.fixture(scope="module")
def views(model):
    settings = RenderSettings.from_record(model.render_settings, what="test model")
    return ViewRenderer.open(settings)


def _mse(a, b) -> float:
    return float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))


def test_all_pixels_without_regularisation_is_the_projection(model, views):
    rec = SparseRecovery(model, lam=0.0)
    pattern = SamplePattern.strided(SIZE, SIZE, 1)
    rng = np.random.default_rng(0)
    for phi, theta in NOVEL:
        truth = views.render_rgb8(phi, theta)
        want = model.project(truth)
        scale = float(np.abs(want).max())
        assert scale > 1.0
        # the prior cancels out when every pixel is known and lam = 0
        for prior in (model.scores(phi, theta), rng.normal(0, 50, want.size)):
            got = rec.recover(pattern, truth.reshape(-1, 3), prior)
            np.testing.assert_allclose(got, want, atol=2e-3 * scale)


def test_small_lambda_tends_to_the_projection(model, views):
    truth = views.render_rgb8(*NOVEL[0])
    want = model.project(truth)
    prior = model.scores(*NOVEL[0])
    pattern = SamplePattern.strided(SIZE, SIZE, 1)
    errors = [float(np.abs(SparseRecovery(model, lam=lam).recover(pattern, truth, prior)
                           - want).max()) for lam in (100.0, 1.0, 0.01)]
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 0.01 * float(np.abs(want).max())


def _frame_in_span(model, scores) -> np.ndarray:
    """float (H, W, 3): mean + scores x scaled int8 eigenimages, unrounded (exactly in span)."""
    img = model.image
    offsets = img.component_offsets
    cells = img.mean.astype(np.float64).copy()
    for c in range(img.n_cells):
        lo, hi = int(offsets[c]), int(offsets[c + 1])
        cells[c] += (np.asarray(scores[lo:hi], np.float64) * img.scales[lo:hi]) \
            @ img.eigenimages[lo:hi].astype(np.float64)
    return merge_cells(cells[None], img.image_shape, img.cell_shape)[0]


def _determined_cells(model, pattern) -> list[tuple[int, int]]:
    """Component ranges of the cells whose sampled int8 rows have full rank."""
    img = model.image
    offsets = img.component_offsets
    nx = img.grid_shape[1]
    cell = (pattern.rows // CELL) * nx + pattern.cols // CELL
    value = ((pattern.rows % CELL) * CELL + pattern.cols % CELL) * 3
    out = []
    for c in range(img.n_cells):
        lo, hi = int(offsets[c]), int(offsets[c + 1])
        cols = (value[cell == c][:, None] + np.arange(3)).ravel()
        rows = img.eigenimages[lo:hi][:, cols].astype(np.float64)
        if hi > lo and np.linalg.matrix_rank(rows) == hi - lo:
            out.append((lo, hi))
    return out


@pytest.mark.parametrize("stride,offset", [(2, (1, 0)), (2, (0, 1)), (3, (2, 2))])
def test_sparse_samples_of_a_frame_in_the_span_recover_its_scores(model, stride, offset):
    """In every cell the samples determine, a view the eigenspace can show exactly is
    recovered exactly from a strided subset of its pixels, whatever the prior."""
    rng = np.random.default_rng(stride)
    k = model.image.n_coefficients
    target = (model.training_scores[5] + rng.normal(0, 3, k)).astype(np.float64)
    truth = _frame_in_span(model, target)
    pattern = SamplePattern.strided(SIZE, SIZE, stride, offset)
    determined = _determined_cells(model, pattern)
    assert len(determined) >= 3
    rec = SparseRecovery(model, lam=1e-9)
    for prior in (model.scores(*NOVEL[0]), np.zeros(k)):
        got = rec.recover(pattern, truth[pattern.rows, pattern.cols], prior)
        for lo, hi in determined:
            np.testing.assert_allclose(got[lo:hi], target[lo:hi],
                                       atol=1e-3 * float(np.abs(target[lo:hi]).max()))
    # a wrong sample layout (the pattern's pixels transposed) does not
    wrong = rec.recover(pattern, truth[pattern.cols, pattern.rows], np.zeros(k))
    lo, hi = determined[0]
    assert not np.allclose(wrong[lo:hi], target[lo:hi],
                           atol=1e-3 * float(np.abs(target[lo:hi]).max()))


@pytest.mark.parametrize("stride", [2, 3])
def test_sparse_samples_come_from_the_sparse_ray_cast(model, views, stride):
    rec = SparseRecovery(model)
    phi, theta = NOVEL[1]
    truth = views.render_rgb8(phi, theta)
    pattern = SamplePattern.strided(SIZE, SIZE, stride, (stride - 1, 0))
    samples, alpha = sparse_samples(views, phi, theta, pattern)
    np.testing.assert_array_equal(samples, truth[pattern.rows, pattern.cols])
    assert alpha.shape == (pattern.n_pixels,) and alpha.max() > 0.5
    prior = model.scores(phi, theta)
    got = rec.recover(pattern, samples.reshape(-1, 3), prior)
    assert got.shape == prior.shape and np.all(np.isfinite(got))
    assert not np.array_equal(got, prior.astype(np.float32))


def test_cells_without_samples_keep_the_prior(model, views):
    rec = SparseRecovery(model)
    truth = views.render_rgb8(*NOVEL[1])
    prior = model.scores(*NOVEL[1])
    rows, cols = np.meshgrid(np.arange(CELL, 2 * CELL, 2), np.arange(CELL, 2 * CELL, 3),
                             indexing="ij")
    pattern = SamplePattern.pixels(SIZE, SIZE, rows.ravel(), cols.ravel())
    got = rec.recover(pattern, truth[pattern.rows, pattern.cols], prior)
    offsets = model.image.component_offsets
    centre = 1 * (SIZE // CELL) + 1
    lo, hi = int(offsets[centre]), int(offsets[centre + 1])
    assert hi > lo  # the sampled cell has components, so something was solved
    assert not np.array_equal(got[lo:hi], prior[lo:hi])
    others = np.ones(got.size, dtype=bool)
    others[lo:hi] = False
    np.testing.assert_array_equal(got[others], prior[others].astype(np.float32))


def test_empty_pattern_returns_the_prior(model):
    rec = SparseRecovery(model)
    prior = model.scores(*NOVEL[2])
    pattern = SamplePattern.pixels(SIZE, SIZE, [], [])
    got = rec.recover(pattern, np.zeros((0, 3), np.uint8), prior)
    np.testing.assert_array_equal(got, prior.astype(np.float32))


def test_factors_are_cached_by_pattern(model):
    rec = SparseRecovery(model, max_patterns=2)
    a = rec.factor(SamplePattern.strided(SIZE, SIZE, 2, (1, 1)))
    assert rec.factor(SamplePattern.strided(SIZE, SIZE, 2, (1, 1))) is a
    pixels = SamplePattern.pixels(SIZE, SIZE, [0, 5, 9], [3, 3, 30])
    assert rec.factor(SamplePattern.pixels(SIZE, SIZE, [0, 5, 9], [3, 3, 30])) \
        is rec.factor(pixels)
    rec.factor(SamplePattern.strided(SIZE, SIZE, 4))  # evicts the least recently used
    assert rec.factor(SamplePattern.strided(SIZE, SIZE, 2, (1, 1))) is not a


def test_progressive_accumulation_reaches_the_projection(model, views):
    rec = SparseRecovery(model, lam=1e-3)
    phi, theta = NOVEL[0]
    truth = views.render_rgb8(phi, theta)
    prior = model.scores(phi, theta)
    prog = ProgressiveRecovery(rec, 2)
    prog.reset(prior)
    first = prog.next_offset()
    assert first == (0, 0)
    pattern = prog.pattern(first)
    got = prog.add(first, truth[pattern.rows, pattern.cols])
    # one offset: the same MAP estimate as a one-shot recovery of that pattern
    once = rec.recover(pattern, truth[pattern.rows, pattern.cols], prior)
    np.testing.assert_allclose(got, once, atol=1e-3 * float(np.abs(once).max()))
    errors = [_mse(model.reconstruct(got), truth)]
    while (offset := prog.next_offset()) is not None:
        p = prog.pattern(offset)
        got = prog.add(offset, truth[p.rows, p.cols])
        errors.append(_mse(model.reconstruct(got), truth))
    assert prog.complete and len(errors) == 4
    assert errors[-1] < errors[0]
    want = model.project(truth)
    np.testing.assert_allclose(got, want, atol=2e-3 * float(np.abs(want).max()))
    with pytest.raises(ValueError, match="already"):
        prog.add((0, 0), truth[pattern.rows, pattern.cols])
    prog.reset(prior)
    assert prog.offsets_seen == [] and prog.next_offset() == (0, 0)
    np.testing.assert_array_equal(prog.scores(), prior.astype(np.float32))


def test_offset_order_is_a_dispersed_permutation():
    for s in (1, 2, 3, 4, 8):
        order = offset_order(s)
        assert sorted(order) == [(dy, dx) for dy in range(s) for dx in range(s)]
        assert order[0] == (0, 0)
    # the first quarter of stride 4 is stride 2's grid: partial sums stay uniform
    assert set(offset_order(4)[:4]) == {(0, 0), (0, 2), (2, 0), (2, 2)}
    assert offset_order(2)[1] == (1, 1)


def test_bad_input_is_refused(model):
    rec = SparseRecovery(model)
    pattern = SamplePattern.strided(SIZE, SIZE, 2)
    prior = np.zeros(model.image.n_coefficients)
    with pytest.raises(ValueError, match="prior"):
        rec.recover(pattern, np.zeros((pattern.n_pixels, 3)), prior[:-1])
    with pytest.raises(ValueError, match="samples"):
        rec.recover(pattern, np.zeros((pattern.n_pixels - 1, 3)), prior)
    with pytest.raises(ValueError, match="model's views"):
        rec.recover(SamplePattern.strided(SIZE + 1, SIZE, 2), np.zeros((342, 3)), prior)
    with pytest.raises(ValueError, match="twice"):
        SamplePattern.pixels(SIZE, SIZE, [1, 1], [2, 2])
    with pytest.raises(ValueError, match="within"):
        SamplePattern.pixels(SIZE, SIZE, [SIZE], [0])
    with pytest.raises(ValueError, match="lam"):
        SparseRecovery(model, lam=-1.0)
