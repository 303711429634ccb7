"""Tests of host/fit/pca.py and host/fit/cells.py: eigenspace fitting, the threshold rule,
CellStack streaming."""

from __future__ import annotations

import numpy as np
import pytest

from host.errors import EigencastError, FitError
from host.fit.cells import CellStack, merge_cells, split_cells
from host.fit.pca import CellEigenspace, InvalidParameterError, NotFittedError

SOLVERS = ["gram", "svd", "randomized"]


def hadamard(n: int) -> np.ndarray:
    """Sylvester Hadamard matrix (n a power of 2): +-1 entries, orthogonal rows."""
    h = np.ones((1, 1), dtype=np.int64)
    while h.shape[0] < n:
        h = np.block([[h, h], [h, -h]])
    return h


def prescribed_cell(amplitudes, n_views=64, side=8, base=128):
    """Cell data (n_views, side*side*3) uint8 with an exactly known spectrum.

    x_v = base + sum_j a_j h_j[v] p_j with h_j, p_j orthogonal +-1 vectors
    (Hadamard columns, zero mean over views), so the centred data is exactly
    sum_j a_j h_j p_j^T: eigenvalues a_j^2 |h_j|^2 |p_j|^2 / (n - 1) and
    components p_j / |p_j|. Every value is an integer in 0..255.
    """
    pix = side * side
    hv = hadamard(n_views)
    hp = hadamard(pix)
    x = np.full((n_views, pix * 3), base, dtype=np.int64)
    patterns = []
    for j, a in enumerate(amplitudes):
        p = np.repeat(hp[j + 1], 3)  # same pattern in the 3 channels, (row, col, ch) order
        x += a * np.outer(hv[:, j + 1], p)
        patterns.append(p / np.sqrt(p.size))
    assert x.min() >= 0 and x.max() <= 255
    eig = np.array([a * a * n_views * pix * 3 / (n_views - 1) for a in amplitudes], float)
    return x.astype(np.uint8), eig, np.array(patterns)


def cells_to_images(cells, image_shape, cell_shape):
    """(n_views, n_cells, d) -> (n_views, H, W, 3) via merge_cells."""
    return merge_cells(cells, image_shape, cell_shape)


def structured_images(n_views=120, shape=(16, 16), rank=40, seed=0, decay=0.75):
    """Random but structured images: a geometric spectrum plus uint8 rounding."""
    rng = np.random.default_rng(seed)
    d = shape[0] * shape[1] * 3
    rank = min(rank, n_views, d)
    u, _ = np.linalg.qr(rng.standard_normal((n_views, rank)))
    v, _ = np.linalg.qr(rng.standard_normal((d, rank)))
    sigma = 900.0 * decay ** np.arange(rank)
    x = 128.0 + (u * sigma) @ v.T
    return np.clip(np.rint(x), 0, 255).astype(np.uint8).reshape(n_views, *shape, 3)


def reference_pca(x: np.ndarray):
    """Eigenvalues (ddof=1) and components of one cell's data via numpy's full SVD."""
    xc = x.astype(np.float64) - x.astype(np.float64).mean(axis=0)
    _, s, vt = np.linalg.svd(xc, full_matrices=False)
    return s**2 / (x.shape[0] - 1), vt


def projector(rows: np.ndarray) -> np.ndarray:
    rows = rows.astype(np.float64)
    return rows.T @ rows


# ---------------------------------------------------------------------------
# correctness against independent references


@pytest.mark.parametrize("solver", SOLVERS)
def test_prescribed_spectrum_recovered(solver):
    amps = [40, 20, 10, 5, 3]
    x, eig, patterns = prescribed_cell(amps)
    images = x.reshape(64, 8, 8, 3)
    model = CellEigenspace("cell", cell=8, components=10, solver=solver).fit(images)
    assert model.solver_ == solver
    assert model.n_components_.tolist() == [5]  # capped at the true rank
    np.testing.assert_allclose(model.eigenvalues_[0], eig, rtol=1e-9)
    np.testing.assert_allclose(model.total_variance_[0], eig.sum(), rtol=1e-12)
    np.testing.assert_allclose(np.abs(model.components_[0] @ patterns.T), np.eye(5), atol=1e-6)


@pytest.mark.parametrize("solver", SOLVERS)
@pytest.mark.parametrize("method", ["cell", "standard"])
def test_matches_numpy_full_svd(solver, method):
    images = structured_images()
    k = 10
    model = CellEigenspace(method, cell=8, components=k, solver=solver).fit(images)
    cell_shape = (8, 8) if method == "cell" else (16, 16)
    cells = split_cells(images, cell_shape)
    assert len(model.components_) == cells.shape[1]
    for c in range(cells.shape[1]):
        ref_eig, ref_vt = reference_pca(cells[:, c, :])
        got = model.eigenvalues_[c]
        assert got.shape == (k,)
        # exact solvers to float64 round-off; randomized: Ritz values converge fast
        rtol = 1e-8 if solver != "randomized" else 1e-4
        np.testing.assert_allclose(got, ref_eig[:k], rtol=rtol)
        np.testing.assert_allclose(model.total_variance_[c], ref_eig.sum(), rtol=1e-10)
        comps = model.components_[c]
        np.testing.assert_allclose(comps @ comps.T, np.eye(k), atol=1e-5)
        err = np.linalg.norm(projector(comps) - projector(ref_vt[:k]), 2)
        assert err < (1e-5 if solver != "randomized" else 1e-3), err
        np.testing.assert_allclose(
            model.explained_variance_ratio_[c], ref_eig[:k] / ref_eig.sum(), rtol=rtol
        )


def test_randomized_solver_is_picked_by_auto_for_large_cells():
    # m = min(n_views=600, cell_size=588) = 588 > 500 and 4 * (k + 16) <= 588
    rng = np.random.default_rng(3)
    images = rng.integers(0, 256, size=(600, 14, 14, 3), dtype=np.uint8)
    model = CellEigenspace("cell", cell=14, components=20).fit(images)
    assert model.solver_ == "randomized"
    # 50 views of 4x4 cells (cell_size 48 < n_views): the covariance route
    small = CellEigenspace("cell", cell=4, components=20).fit(images[:50])
    assert small.solver_ == "svd"
    assert small.solver_params_["route"] == "svd"


def test_full_rank_reconstruction_is_exact():
    rng = np.random.default_rng(1)
    images = rng.integers(0, 256, size=(20, 37, 23, 3), dtype=np.uint8)
    for method in ("cell", "standard", "adaptive"):
        model = CellEigenspace(method, cell=8, components=500, threshold=1.0).fit(images)
        assert (model.n_components_ == 19).all()  # rank of 20 centred views
        rec = model.inverse_transform(model.scores_)
        assert rec.shape == images.shape and rec.dtype == np.float32
        np.testing.assert_allclose(rec, images, atol=2e-3)
        # float32 scores ~2000: the summation order (BLAS threads) moves the last bits
        np.testing.assert_allclose(model.transform(images), model.scores_, atol=2e-3, rtol=1e-5)


@pytest.mark.parametrize("solver", ["gram", "randomized"])
@pytest.mark.parametrize(
    ("threshold", "expected_k"),
    # amplitudes 8,4,2,1 -> eigenvalue shares 64,16,4,1 / 85:
    # cumulative 0.753, 0.941, 0.988, 1.0
    [(0.5, 1), (0.75, 1), (0.76, 2), (0.94, 2), (0.95, 3), (0.988, 3), (0.99, 4), (1.0, 4)],
)
def test_threshold_rule_picks_fewest_components(solver, threshold, expected_k):
    x, eig, _ = prescribed_cell([8, 4, 2, 1])
    cum = np.cumsum(eig) / eig.sum()
    assert int(np.argmax(cum >= threshold)) + 1 == expected_k  # the rule, independently
    images = x.reshape(64, 8, 8, 3)
    model = CellEigenspace("adaptive", cell=8, threshold=threshold, solver=solver).fit(images)
    assert model.n_components_.tolist() == [expected_k]
    assert model.explained_variance_ratio_[0].sum() >= threshold - 1e-12


@pytest.mark.parametrize("solver", ["gram", "randomized"])
def test_adaptive_randomized_grows_beyond_its_first_guess(solver):
    # 60 components with shares 9 (x10), 4 (x20), 1 (x30) / 200: the cumulative
    # ratio reaches 0.9 at k = 40 > RANDOMIZED_INITIAL_COMPONENTS (32), so the
    # randomized solver must double its sketch (m = min(128, 192) = 128 > 80)
    amps = [3] * 10 + [2] * 20 + [1] * 30
    x, eig, _ = prescribed_cell(amps, n_views=128)
    cum = np.cumsum(eig) / eig.sum()
    assert int(np.argmax(cum >= 0.9 - 1e-12)) + 1 == 40
    model = CellEigenspace("adaptive", cell=8, threshold=0.9, solver=solver)
    model.fit(x.reshape(128, 8, 8, 3))
    assert model.n_components_.tolist() == [40]
    np.testing.assert_allclose(model.eigenvalues_[0], eig[:40], rtol=1e-6)


def test_adaptive_per_cell_counts_and_cap():
    # four 8x8 cells with different spectra; one constant cell
    specs = [[40, 20, 10, 5], [30], None, [10, 10, 10, 10, 10]]
    cells = []
    for spec in specs:
        if spec is None:
            cells.append(np.full((64, 192), 77, dtype=np.uint8))
        else:
            cells.append(prescribed_cell(spec)[0])
    images = cells_to_images(np.stack(cells, axis=1), (16, 16), (8, 8))
    model = CellEigenspace("adaptive", cell=8, threshold=0.9).fit(images)
    # [40,20,10,5]: shares 1600,400,100,25 / 2125 -> 0.753, 0.941 => 2
    assert model.n_components_.tolist() == [2, 1, 0, 5]
    assert model.n_components_.dtype == np.int32
    capped = CellEigenspace("adaptive", cell=8, threshold=0.9, components=3).fit(images)
    assert capped.n_components_.tolist() == [2, 1, 0, 3]
    offsets = capped.component_offsets_
    assert offsets.tolist() == [0, 2, 3, 3, 6] and offsets.dtype == np.int64
    assert capped.scores_.shape == (64, 6)


def test_zero_variance_cell_shows_its_mean():
    rng = np.random.default_rng(2)
    images = rng.integers(0, 256, size=(10, 16, 16, 3), dtype=np.uint8)
    images[:, 8:, :8] = 77  # cell 2 is constant over all views
    model = CellEigenspace("adaptive", cell=8).fit(images)
    assert model.n_components_[2] == 0
    assert model.total_variance_[2] == 0.0
    assert model.components_[2].shape == (0, 192)
    assert model.eigenvalues_[2].shape == (0,)
    assert model.explained_variance_ratio_[2].shape == (0,)
    np.testing.assert_array_equal(model.mean_[2], np.full(192, 77.0, np.float32))
    rec = model.inverse_transform(np.zeros(model.component_offsets_[-1], np.float32))
    np.testing.assert_array_equal(rec[8:, :8], 77.0)


def test_non_divisible_sizes_round_trip():
    rng = np.random.default_rng(4)
    images = rng.integers(0, 256, size=(12, 37, 23, 3), dtype=np.uint8)
    cells = split_cells(images, (8, 8))
    assert cells.shape == (12, 5 * 3, 192)
    np.testing.assert_array_equal(merge_cells(cells, (37, 23), (8, 8)), images)
    # the padding is zero
    assert (split_cells(images, (8, 8))[:, -1].reshape(12, 8, 8, 3)[:, 5:] == 0).all()
    model = CellEigenspace("cell", cell=8, components=100).fit(images)
    assert model.grid_shape_ == (5, 3)
    assert model.image_shape_ == (37, 23)
    assert model.cell_shape_ == (8, 8)
    assert model.mean_.shape == (15, 192) and model.mean_.dtype == np.float32
    rec = model.inverse_transform(model.scores_)
    np.testing.assert_allclose(rec, images, atol=2e-3)
    # padded entries have zero mean and zero loadings
    pad = np.zeros((8, 8, 3), bool)
    pad[5:] = True
    last = model.components_[-1]
    assert np.abs(last[:, pad.ravel()]).max() == 0.0
    assert np.abs(model.mean_[-1][pad.ravel()]).max() == 0.0


def test_cell_larger_than_the_image_is_clamped():
    rng = np.random.default_rng(10)
    images = rng.integers(0, 256, size=(6, 20, 12, 3), dtype=np.uint8)
    model = CellEigenspace("cell", cell=30, components=10).fit(images)
    assert model.cell_shape_ == (20, 12) and model.grid_shape_ == (1, 1)
    np.testing.assert_allclose(model.inverse_transform(model.scores_), images, atol=2e-3)


def test_sign_convention_is_deterministic():
    images = structured_images(n_views=60, seed=5)
    a = CellEigenspace("cell", cell=8, components=6).fit(images)
    b = CellEigenspace("cell", cell=8, components=6).fit(images.copy())
    for ca, cb in zip(a.components_, b.components_):
        np.testing.assert_array_equal(ca, cb)
        idx = np.argmax(np.abs(ca), axis=1)
        assert (ca[np.arange(ca.shape[0]), idx] > 0).all()
    np.testing.assert_array_equal(a.scores_, b.scores_)
    # scores follow the flipped components: transform agrees with scores_
    np.testing.assert_allclose(a.transform(images), a.scores_, atol=1e-2)
    assert a.solver_params_["sign_convention"] == "largest-abs-loading-positive"


# ---------------------------------------------------------------------------
# streaming: CellStack files and blocked decomposition


def test_cellstack_file_gives_identical_results(tmp_path):
    images = structured_images(n_views=50, shape=(20, 13), seed=6)
    path = tmp_path / "train.cells"
    stack = CellStack.build(
        iter(list(images)),
        50,
        20,
        13,
        8,
        8,
        path,
        source="db-v1",
        progress=False,
        buffer_bytes=3 * 16 * 24 * 3,  # a few views per group: exercises the grouping
    )
    assert not stack.reused and path.is_file()
    assert path.stat().st_size == stack.size_bytes == 3 * 2 * 50 * 192
    np.testing.assert_array_equal(stack.memmap(), split_cells(images, (8, 8)).transpose(1, 0, 2))
    from_file = CellEigenspace("adaptive", cell=8, threshold=0.95).fit(stack)
    in_memory = CellEigenspace("adaptive", cell=8, threshold=0.95).fit(images)
    np.testing.assert_array_equal(from_file.n_components_, in_memory.n_components_)
    np.testing.assert_array_equal(from_file.mean_, in_memory.mean_)
    np.testing.assert_array_equal(from_file.scores_, in_memory.scores_)
    for a, b in zip(from_file.components_, in_memory.components_):
        np.testing.assert_array_equal(a, b)

    def must_not_iterate():
        raise AssertionError("a matching stack must be reused without reading images")
        yield  # pragma: no cover

    again = CellStack.build(must_not_iterate(), 50, 20, 13, 8, 8, path, source="db-v1")
    assert again.reused
    rebuilt = CellStack.build(
        iter(list(images)), 50, 20, 13, 8, 8, path, source="db-v2", progress=False
    )
    assert not rebuilt.reused
    other_cell = CellStack.build(
        iter(list(images)), 50, 20, 13, 4, 4, path, source="db-v2", progress=False
    )
    assert not other_cell.reused and other_cell.cell_shape == (4, 4)
    assert CellStack.open(path).cell_shape == (4, 4)


def test_cellstack_errors(tmp_path):
    images = np.zeros((5, 8, 8, 3), np.uint8)
    path = tmp_path / "s.cells"
    with pytest.raises(FitError, match=r"view 2 is float64 \(8, 8, 3\); expected uint8"):
        bad = [images[0], images[1], images[2].astype(float)]
        CellStack.build(iter(bad), 5, 8, 8, 4, 4, path, progress=False)
    assert not path.exists() and not list(tmp_path.iterdir())  # no partial output
    with pytest.raises(FitError, match="yielded 3 images, expected n_views=5"):
        CellStack.build(iter(images[:3]), 5, 8, 8, 4, 4, path, progress=False)
    with pytest.raises(FitError, match="more than n_views=5"):
        CellStack.build(iter(np.zeros((6, 8, 8, 3), np.uint8)), 5, 8, 8, 4, 4, path, progress=False)
    stack = CellStack.build(iter(images), 5, 8, 8, 4, 4, path, progress=False)
    with pytest.raises(FitError, match=r"has 4x4 cells but method='cell', cell=8 needs 8x8"):
        CellEigenspace("cell", cell=8).fit(stack)
    with open(path, "r+b") as f:
        f.truncate(100)
    with pytest.raises(FitError, match="file has 100 bytes, header says 960"):
        CellStack.open(path)
    with pytest.raises(FitError, match=r"header nothing\.cells\.json is missing"):
        CellStack.open(tmp_path / "nothing.cells")
    (tmp_path / "junk.cells.json").write_text("{not json")
    with pytest.raises(FitError, match="unreadable"):
        CellStack.open(tmp_path / "junk.cells")


def as_stack(images, cell_shape, where, tmp_path):
    """The images as a CellStack in memory or in a file."""
    if where == "memory":
        return CellStack.from_array(images, cell_shape)
    n, h, w, _ = images.shape
    path = tmp_path / "stack.cells"
    return CellStack.build(iter(images), n, h, w, *cell_shape, path, progress=False)


@pytest.mark.parametrize("where", ["memory", "file"])
def test_streamed_blocks_match_whole_cells(where, tmp_path):
    # standard method: one 64x64 cell of 60 views = 737 kB uint8, ~7 MB of float
    # working set > batch_bytes=1 MiB, so the cell is read in column blocks
    images = structured_images(n_views=60, shape=(64, 64), rank=30, seed=7)
    whole = CellEigenspace("standard", components=12, solver="gram").fit(images)
    blocks = CellEigenspace("standard", components=12, solver="gram", batch_bytes=2**20)
    blocks.fit(as_stack(images, (64, 64), where, tmp_path))
    assert blocks._cell_working_bytes(60, 64 * 64 * 3) > 2**20
    np.testing.assert_allclose(blocks.eigenvalues_[0], whole.eigenvalues_[0], rtol=1e-9)
    np.testing.assert_allclose(blocks.mean_, whole.mean_, atol=1e-4)
    np.testing.assert_allclose(blocks.components_[0], whole.components_[0], atol=1e-5)
    np.testing.assert_allclose(blocks.scores_, whole.scores_, rtol=1e-4, atol=1e-2)


@pytest.mark.parametrize("where", ["memory", "file"])
def test_streamed_rows_match_whole_cells_covariance_route(where, tmp_path):
    # many views of a tiny image: cell_size 48 < n_views, read in row blocks
    rng = np.random.default_rng(8)
    n = 3000
    base = rng.integers(0, 256, size=(6, 4, 4, 3)).astype(float)
    coef = rng.standard_normal((n, 6)) * [30, 20, 10, 5, 2, 1]
    images = np.clip(np.rint(128 + np.einsum("nk,khwc->nhwc", coef, base / 128 - 1)), 0, 255)
    images = images.astype(np.uint8)
    whole = CellEigenspace("standard", components=6).fit(images)
    rows = CellEigenspace("standard", components=6, batch_bytes=2**20)
    rows.fit(as_stack(images, (4, 4), where, tmp_path))
    assert rows._cell_working_bytes(n, 48) > 2**20
    assert whole.solver_ == rows.solver_ == "svd"
    np.testing.assert_allclose(rows.eigenvalues_[0], whole.eigenvalues_[0], rtol=1e-9)
    np.testing.assert_allclose(rows.components_[0], whole.components_[0], atol=1e-5)
    np.testing.assert_allclose(rows.scores_, whole.scores_, rtol=1e-4, atol=1e-2)


# ---------------------------------------------------------------------------
# errors and the estimator contract


def test_not_fitted_error_says_what_to_call():
    model = CellEigenspace()
    with pytest.raises(NotFittedError, match=r"transform: .*not fitted.*call fit\(images\)"):
        model.transform(np.zeros((1, 8, 8, 3), np.uint8))
    with pytest.raises(NotFittedError, match="inverse_transform"):
        model.inverse_transform(np.zeros((1, 3), np.float32))
    assert issubclass(NotFittedError, EigencastError)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"method": "pca"}, r"method='pca' is not allowed; use one of \['adaptive', 'cell'"),
        ({"cell": 0}, r"cell=0 must be an integer in \[1, inf\]"),
        ({"cell": 2.5}, r"cell=2.5 must be an integer"),
        ({"components": True}, r"components=True must be an integer"),
        ({"threshold": 0.0}, r"threshold=0.0 must be a number in \(0, 1\]"),
        ({"threshold": 1.5}, r"threshold=1.5 must be a number in \(0, 1\]"),
        ({"threshold": float("nan")}, r"threshold=nan must be a number"),
        ({"solver": "arpack"}, r"solver='arpack' is not allowed; use one of \['auto'"),
        ({"batch_bytes": 10}, r"batch_bytes=10 must be an integer in \[1048576, inf\]"),
        ({"random_state": -1}, r"random_state=-1 must be an integer in \[0"),
    ],
)
def test_parameter_constraints(kwargs, message):
    images = np.zeros((3, 8, 8, 3), np.uint8)
    method = kwargs.pop("method", "adaptive")
    model = CellEigenspace(method, **kwargs)  # the constructor only stores
    with pytest.raises(InvalidParameterError, match=message) as info:
        model.fit(images)
    assert isinstance(info.value, FitError) and isinstance(info.value, ValueError)


def test_bad_images_are_reported():
    with pytest.raises(FitError, match=r"must be \(n_views, height, width, 3\) uint8, got float32"):
        CellEigenspace().fit(np.zeros((3, 8, 8, 3), np.float32))
    with pytest.raises(FitError, match="got list"):
        CellEigenspace().fit([[1, 2, 3]])
    with pytest.raises(FitError, match="at least 2 views"):
        CellEigenspace(cell=4).fit(np.zeros((1, 8, 8, 3), np.uint8))
    with pytest.raises(FitError, match=r"cell 16x4 is larger than the image \(8x8\)"):
        CellStack.from_array(np.zeros((3, 8, 8, 3), np.uint8), (16, 4))
    model = CellEigenspace("cell", cell=4, components=2).fit(
        np.random.default_rng(0).integers(0, 256, (4, 8, 8, 3), dtype=np.uint8)
    )
    with pytest.raises(ValueError, match=r"images must be \(n, 8, 8, 3\), got \(2, 8, 9, 3\)"):
        model.transform(np.zeros((2, 8, 9, 3), np.uint8))
    with pytest.raises(ValueError, match=r"scores must be \(n, 8\) or \(8,\), got \(2, 7\)"):
        model.inverse_transform(np.zeros((2, 7)))


def test_fitted_attribute_types():
    images = structured_images(n_views=30, shape=(16, 8), seed=9)
    model = CellEigenspace("cell", cell=8, components=4).fit(images)
    assert model.n_views_ == 30
    assert model.scores_.dtype == np.float32 and model.scores_.shape == (30, 8)
    assert all(c.dtype == np.float32 for c in model.components_)
    assert all(e.dtype == np.float64 for e in model.eigenvalues_)
    assert model.total_variance_.dtype == np.float64
    assert model.inverse_transform(model.scores_[0]).shape == (16, 8, 3)
    assert isinstance(model.solver_, str)
    assert model.solver_params_["solver"] == model.solver_
