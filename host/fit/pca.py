"""Cell eigenspaces: standard, cell and adaptive-cell PCA of training images.

The data model (authoritative, shared with ``host/fit/quantize.py``,
``protocol/image.py`` and ``device_runtime/reconstruct.py``):

* Images are ``(n_views, height, width, 3)`` uint8. They are cut into cells of
  ``cell_shape = (cell_h, cell_w)`` pixels (the whole image for ``standard``),
  after padding the bottom/right with zeros to a whole number of cells. Cells
  are numbered in row-major order; a cell's vector has
  ``cell_size = cell_h * cell_w * 3`` entries in (row, col, channel) order, in
  0..255 units.
* Each cell has its own mean and its own orthonormal components; the scores of
  all cells are concatenated cell-major into one row of ``K`` coefficients.

Fitting streams: `CellStack` lays the training images out cell-major on disk,
``(n_cells, n_views, cell_size)`` uint8, so every cell's training data is one
contiguous block; `CellEigenspace.fit` reads cells in batches bounded by
``batch_bytes`` (cells too big for one batch are read in column or row blocks),
so memory does not grow with the image size.

Examples
--------
>>> import numpy as np
>>> rng = np.random.default_rng(0)
>>> images = rng.integers(0, 256, size=(12, 20, 20, 3), dtype=np.uint8)
>>> model = CellEigenspace("cell", cell=10, components=5).fit(images)
>>> model.n_components_.tolist()
[5, 5, 5, 5]
>>> model.scores_.shape
(12, 20)
>>> model.inverse_transform(model.scores_).shape
(12, 20, 20, 3)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from numbers import Integral, Real
from typing import Any

import numpy as np
import scipy.linalg

from host.errors import EigencastError, FitError
from host.fit.cells import CellStack, _check_images, merge_cells, split_cells
from host.progress import progress as _progress

__all__ = [
    "DEFAULT_BATCH_BYTES",
    "PARAMETER_CONSTRAINTS",
    "RANDOMIZED_INITIAL_COMPONENTS",
    "RANDOMIZED_MIN_SIZE",
    "RANDOMIZED_OVERSAMPLES",
    "RANDOMIZED_POWER_ITERATIONS",
    "SIGN_CONVENTION",
    "CellEigenspace",
    "InvalidParameterError",
    "NotFittedError",
]

#: Default bound of the float working set of one batch of cells, in bytes.
DEFAULT_BATCH_BYTES = 512 * 2**20
#: Randomized solver: extra columns of the sketch beyond the components trusted.
RANDOMIZED_OVERSAMPLES = 16
#: Randomized solver: subspace (power) iterations on the Gram/covariance matrix.
#: One iteration on ``X X^T`` equals two on ``X``, so 4 here is sklearn's 8.
RANDOMIZED_POWER_ITERATIONS = 4
#: Randomized solver, adaptive method: components tried first (then doubled).
RANDOMIZED_INITIAL_COMPONENTS = 32
#: ``auto`` picks ``randomized`` only for matrices with a smaller side above this.
RANDOMIZED_MIN_SIZE = 500
#: The sign convention of every component (recorded in provenance).
SIGN_CONVENTION = "largest-abs-loading-positive"

# Slack on the explained-variance ratio of the adaptive rule, so that
# threshold=1.0 is reachable although the eigenvalue sum and the trace differ
# in the last bits.
_THRESHOLD_SLACK = 1e-12


# --------------------------------------------------------------------------
# errors


class NotFittedError(EigencastError):
    """A fitted attribute or method was used before ``fit``."""


class InvalidParameterError(FitError, ValueError):
    """A `CellEigenspace` parameter is outside its allowed values."""


# --------------------------------------------------------------------------
# the parameter constraints table


@dataclass(frozen=True)
class _Options:
    options: frozenset[str]

    def check(self, name: str, value: Any) -> None:
        if not isinstance(value, str) or value not in self.options:
            raise InvalidParameterError(
                f"CellEigenspace: {name}={value!r} is not allowed; "
                f"use one of {sorted(self.options)}"
            )

    def __str__(self) -> str:
        return f"one of {sorted(self.options)}"


@dataclass(frozen=True)
class _Interval:
    kind: type  # Integral or Real
    low: float | None
    high: float | None
    closed: str = "both"  # "both", "left", "right", "neither"

    def check(self, name: str, value: Any) -> None:
        ok_type = isinstance(value, self.kind) and not isinstance(value, bool)
        ok = ok_type and math.isfinite(float(value))
        if ok and self.low is not None:
            ok = value >= self.low if self.closed in ("both", "left") else value > self.low
        if ok and self.high is not None:
            ok = value <= self.high if self.closed in ("both", "right") else value < self.high
        if not ok:
            raise InvalidParameterError(f"CellEigenspace: {name}={value!r} must be {self}")

    def __str__(self) -> str:
        kind = "an integer" if self.kind is Integral else "a number"
        lo_b = "[" if self.closed in ("both", "left") else "("
        hi_b = "]" if self.closed in ("both", "right") else ")"
        fmt = "{:d}" if self.kind is Integral else "{:g}"
        lo = "-inf" if self.low is None else fmt.format(self.low)
        hi = "inf" if self.high is None else fmt.format(self.high)
        return f"{kind} in {lo_b}{lo}, {hi}{hi_b}"


#: Every parameter of `CellEigenspace` and what it may be (checked by ``fit``).
PARAMETER_CONSTRAINTS: dict[str, _Options | _Interval] = {
    "method": _Options(frozenset({"standard", "cell", "adaptive"})),
    "cell": _Interval(Integral, 1, None),
    "components": _Interval(Integral, 1, None),
    "threshold": _Interval(Real, 0.0, 1.0, closed="right"),
    "solver": _Options(frozenset({"auto", "gram", "svd", "randomized"})),
    "batch_bytes": _Interval(Integral, 2**20, None),
    "random_state": _Interval(Integral, 0, 2**63 - 1),
}


# --------------------------------------------------------------------------
# the estimator


@dataclass
class _CellFit:
    mean: np.ndarray  # float32 (d,)
    components: np.ndarray  # float32 (k, d)
    eigenvalues: np.ndarray  # float64 (k,)
    total_variance: float
    scores: np.ndarray  # float32 (n, k)


class CellEigenspace:
    """PCA eigenspaces of training images: one whole-image space or one per cell.

    Parameters
    ----------
    method : {"adaptive", "cell", "standard"}
        ``standard``: one eigenspace over the whole image with
        ``min(components, rank)`` components. ``cell``: square cells of
        ``cell`` pixels, each with ``min(components, rank)`` components.
        ``adaptive``: square cells, each with the fewest ``k`` such that
        ``sum(lambda_1..k) / sum(lambda) >= threshold``, capped at
        ``components``; a cell with zero variance keeps 0 components and
        shows its mean. (``threshold=1.0`` keeps the full numerical rank,
        still capped by ``components``.)
    cell : int
        Cell side in pixels (``cell`` and ``adaptive``; ignored by ``standard``).
        Images are zero-padded at the bottom/right to whole cells. A cell
        larger than the image is clamped to the image's height/width.
    components : int
        Components per cell (``cell``/``standard``), or the cap of ``adaptive``.
    threshold : float in (0, 1]
        Explained-variance threshold T of ``adaptive``.
    solver : {"auto", "gram", "svd", "randomized"}
        How each cell's data X, (n_views, cell_size) centred, is decomposed.
        ``gram``: ``eigh`` of ``X X^T`` (n_views x n_views), components
        ``X^T u / sqrt(mu)``. ``svd``: the covariance route, ``eigh`` of
        ``X^T X`` (cell_size x cell_size). ``randomized``: the smaller of those
        two matrices (m x m) is formed and only its top eigenpairs are found by
        randomized subspace iteration (Gaussian sketch seeded by
        ``random_state`` and the cell index, ``RANDOMIZED_OVERSAMPLES`` extra
        columns, ``RANDOMIZED_POWER_ITERATIONS`` LU-normalised iterations,
        then QR and Rayleigh-Ritz). For ``adaptive`` it needs no eigenvalue tail:
        ``sum(lambda)`` is the trace of that matrix, known exactly, so it tries
        ``RANDOMIZED_INITIAL_COMPONENTS`` components and doubles (up to
        ``components``) until the trusted Ritz values reach the threshold.
        Ritz sums never exceed the true top-k sums (Ky Fan), so the k it picks
        is never smaller than the exact rule's (at worst slightly larger).
        ``auto`` follows this rule (recorded in ``solver_``): with
        ``m = min(n_views, cell_size)`` and ``k`` the most components any cell
        may keep, ``randomized`` if ``m > RANDOMIZED_MIN_SIZE`` and
        ``4 * (k + RANDOMIZED_OVERSAMPLES) <= m``; otherwise ``gram`` if
        ``n_views <= cell_size``, else ``svd``. Accumulation is in float64.
    batch_bytes : int
        Bound of the float working set of one batch of cells (bytes). Cells
        whose data alone exceeds it are read in column blocks (``gram`` and
        ``randomized`` on ``X X^T``) or row blocks (``svd`` route).
    random_state : int
        Seed of the randomized solver (per cell: ``[random_state, cell]``), so
        results do not depend on batching.
    progress : bool
        Report fitting progress (cells done / total) on stderr.

    Attributes
    ----------
    mean_ : ndarray of shape (n_cells, cell_size), float32
    components_ : list of n_cells ndarrays of shape (n_components_c, cell_size), float32
        Orthonormal rows sorted by eigenvalue, descending. Sign convention:
        the entry with the largest absolute value of each row is positive.
    eigenvalues_ : list of n_cells ndarrays of shape (n_components_c,), float64
        Variance along each kept component (ddof=1).
    explained_variance_ratio_ : list of n_cells ndarrays of shape (n_components_c,), float64
        ``eigenvalues_[c] / total_variance_[c]`` (empty for zero-variance cells).
    total_variance_ : ndarray of shape (n_cells,), float64
        Sum of all eigenvalues of each cell (the trace).
    n_components_ : ndarray of shape (n_cells,), int32
    component_offsets_ : ndarray of shape (n_cells + 1,), int64
        ``[0, cumsum(n_components_)]``; ``K = component_offsets_[-1]``.
    scores_ : ndarray of shape (n_views, K), float32
        Training scores; cell c's columns are ``offsets[c]:offsets[c+1]``,
        ``score_j = dot(x_c - mean_c, v_j)``.
    n_views_ : int
    image_shape_ : (int, int)
        ``(height, width)``.
    cell_shape_ : (int, int)
        ``(cell_h, cell_w)``; the whole image for ``standard``.
    grid_shape_ : (int, int)
        ``(n_cells_y, n_cells_x)``.
    solver_ : str
        The solver used (what ``auto`` picked); the same for every cell.
    solver_params_ : dict
        Everything needed to reproduce the fit bit for bit (solver, its
        settings, accumulation dtype, sign convention, seed).

    See Also
    --------
    CellStack : the streamed, cell-major training data.
    split_cells, merge_cells : the cell layout.

    Notes
    -----
    Each cell is centred with its float64 mean (stored as float32 ``mean_``)
    and the Gram or covariance matrix is accumulated in float64 (a float32
    Gram product measured ~1.7x faster for 1500 x 2700 cells, but its
    round-off, ~1e-6 of the largest eigenvalue, swamps the trailing
    eigenvalues of a ``cell`` fit with 100 components). Eigenvalues at or below
    ``lambda_max * m * eps`` are numerically zero: that is the rank that caps
    ``k``. Cells whose training data are identical in every view are found by
    a cheap equality test and skipped (0 components). Memory: one batch of
    cells (``batch_bytes``) plus the fitted model; the training data stay on
    disk in the `CellStack`.

    References
    ----------
    The adaptive-cell method: "Volume Visualization Using Principal Component
    Analysis", section 5 (``/work/shared/seed-paper.txt``).
    """

    def __init__(
        self,
        method: str = "adaptive",
        *,
        cell: int = 30,
        components: int = 100,
        threshold: float = 0.98,
        solver: str = "auto",
        batch_bytes: int = DEFAULT_BATCH_BYTES,
        random_state: int = 0,
        progress: bool = False,
    ):
        self.method = method
        self.cell = cell
        self.components = components
        self.threshold = threshold
        self.solver = solver
        self.batch_bytes = batch_bytes
        self.random_state = random_state
        self.progress = progress

    def __repr__(self) -> str:
        return (
            f"CellEigenspace({self.method!r}, cell={self.cell}, components={self.components}, "
            f"threshold={self.threshold}, solver={self.solver!r})"
        )

    # ------------------------------------------------------------------ checks

    def _validate_params(self) -> None:
        for name, constraint in PARAMETER_CONSTRAINTS.items():
            constraint.check(name, getattr(self, name))

    def _check_fitted(self, what: str) -> None:
        if not hasattr(self, "scores_"):
            raise NotFittedError(
                f"CellEigenspace.{what}: this model is not fitted yet; call fit(images) first"
            )

    # --------------------------------------------------------------------- fit

    def fit(self, images: CellStack | np.ndarray) -> CellEigenspace:
        """Fit the eigenspace(s) of the training images.

        Parameters
        ----------
        images : CellStack or ndarray of shape (n_views, height, width, 3), uint8
            A `CellStack` whose cell shape matches the method (the whole image
            for ``standard``, ``cell x cell`` otherwise), or in-memory images.

        Returns
        -------
        self : CellEigenspace

        Raises
        ------
        InvalidParameterError
            A parameter is outside `PARAMETER_CONSTRAINTS`.
        FitError
            Bad images (dtype, shape, fewer than 2 views), or a stack whose
            cell shape does not match.
        """
        self._validate_params()
        if isinstance(images, CellStack):
            stack = images
            image_shape = stack.image_shape
        else:
            _check_images(images, "images")
            image_shape = images.shape[1:3]
            stack = None
        cell_shape = self._cell_shape_for(image_shape)
        if stack is None:
            stack = CellStack.from_array(images, cell_shape)
        elif stack.cell_shape != cell_shape:
            raise FitError(
                f"{stack!r} has {stack.cell_shape[0]}x{stack.cell_shape[1]} cells but "
                f"method={self.method!r}, cell={self.cell} needs {cell_shape[0]}x"
                f"{cell_shape[1]}; rebuild the stack with that cell size"
            )
        n = stack.n_views
        if n < 2:
            raise FitError(f"fit needs at least 2 views to estimate variance, got n_views={n}")
        self._prepare_solver(n, stack.cell_size)
        with _progress(
            "fitting eigenspace", stack.n_cells, unit=" cells", quiet=not self.progress
        ) as p:
            fits = self._fit_cells(stack, 0, stack.n_cells, p)

        self._store(fits, stack)
        return self

    def _prepare_solver(self, n: int, d: int) -> None:
        """Choose the solver and route for ``n`` views of cells of ``d`` entries."""
        self._n, self._d = n, d
        self._k_cap = min(int(self.components), n - 1, d)
        self.solver_ = self._choose_solver(n, d)
        gram = self.solver_ == "gram" or (self.solver_ == "randomized" and n <= d)
        self._route = "gram" if gram else "svd"

    def _fit_cells(self, stack: CellStack, start: int, stop: int, p: Any) -> list[_CellFit]:
        """Decompose cells ``start..stop-1`` of ``stack`` in batches (after `_prepare_solver`).

        A cell's fit does not depend on the batch it is in, so `host.cluster` fits
        blocks of cells on workers with this same loop and gets the same bytes.
        """
        fits: list[_CellFit] = []
        per_cell = self._cell_working_bytes(self._n, self._d)
        if per_cell <= self.batch_bytes:
            per_batch = max(1, min(256, self.batch_bytes // per_cell))
            for first in range(start, stop, per_batch):
                last = min(stop, first + per_batch)
                fits.extend(self._fit_batch(stack.read_cells(first, last), first))
                p.advance(last - first)
        else:
            for c in range(start, stop):
                fits.append(self._fit_streamed(stack, c, p))
        return fits

    def _cell_shape_for(self, image_shape: tuple[int, int]) -> tuple[int, int]:
        if self.method == "standard":
            return (int(image_shape[0]), int(image_shape[1]))
        cell = int(self.cell)
        return (min(cell, int(image_shape[0])), min(cell, int(image_shape[1])))

    def _choose_solver(self, n: int, d: int) -> str:
        if self.solver != "auto":
            return self.solver
        m = min(n, d)
        if m > RANDOMIZED_MIN_SIZE and 4 * (self._k_cap + RANDOMIZED_OVERSAMPLES) <= m:
            return "randomized"
        return "gram" if n <= d else "svd"

    def _cell_working_bytes(self, n: int, d: int) -> int:
        m = min(n, d)
        k = self._k_cap
        # uint8 data + float64 centred copy + Gram/cov matrix and eigenvectors
        # (+ eigh workspace) + components and scores in float64
        return n * d * 9 + 24 * m * m + 16 * k * (n + d)

    def _store(self, fits: list[_CellFit], stack: CellStack) -> None:
        n_comp = np.array([f.components.shape[0] for f in fits], dtype=np.int32)
        offsets = np.zeros(len(fits) + 1, dtype=np.int64)
        np.cumsum(n_comp, out=offsets[1:])
        scores = np.zeros((stack.n_views, int(offsets[-1])), dtype=np.float32)
        for c, f in enumerate(fits):
            scores[:, offsets[c] : offsets[c + 1]] = f.scores
        total = np.array([f.total_variance for f in fits], dtype=np.float64)
        self.n_views_ = stack.n_views
        self.image_shape_ = stack.image_shape
        self.cell_shape_ = stack.cell_shape
        self.grid_shape_ = stack.grid_shape
        self.mean_ = np.stack([f.mean for f in fits]).astype(np.float32)
        self.components_ = [f.components for f in fits]
        self.eigenvalues_ = [f.eigenvalues for f in fits]
        self.total_variance_ = total
        with np.errstate(invalid="ignore", divide="ignore"):
            self.explained_variance_ratio_ = [
                f.eigenvalues / t if t > 0 else np.zeros(0) for f, t in zip(fits, total)
            ]
        self.n_components_ = n_comp
        self.component_offsets_ = offsets
        self.solver_params_ = {
            "method": self.method,
            "cell": list(self.cell_shape_),
            "components": int(self.components),
            "threshold": float(self.threshold),
            "solver": self.solver_,
            "route": self._route,
            "accumulation": "float64",
            "sign_convention": SIGN_CONVENTION,
            "random_state": int(self.random_state),
            "oversamples": RANDOMIZED_OVERSAMPLES,
            "power_iterations": RANDOMIZED_POWER_ITERATIONS,
            "initial_components": RANDOMIZED_INITIAL_COMPONENTS,
        }
        self.scores_ = scores

    # ----------------------------------------------------------- decomposition

    def _fit_batch(self, data: np.ndarray, first_cell: int) -> list[_CellFit]:
        """Decompose a batch of whole cells, data (b, n, d) uint8."""
        b, n, _ = data.shape
        constant = (data == data[:, :1, :]).all(axis=(1, 2))
        fits: list[_CellFit | None] = [None] * b
        for i in np.flatnonzero(constant):
            fits[i] = _empty_fit(data[i, 0].astype(np.float32), n)
        live = np.flatnonzero(~constant)
        if live.size:
            x = data[live].astype(np.float64)
            mean = x.mean(axis=1)  # (bl, d)
            x -= mean[:, None, :]
            if self._route == "gram":
                mat = x @ x.transpose(0, 2, 1)
            else:
                mat = x.transpose(0, 2, 1) @ x
            traces = np.einsum("bii->b", mat)
            tops = self._eigen_top(mat, traces, first_cell + live)
            del mat
            for j, i in enumerate(live):
                w, u = tops[j]
                comps = self._components_from(u, w, x[j])
                scores = x[j] @ comps.T
                comps, scores = _flip_signs(comps, scores)
                fits[i] = _CellFit(
                    mean=mean[j].astype(np.float32),
                    components=comps.astype(np.float32),
                    eigenvalues=w / (n - 1),
                    total_variance=float(traces[j]) / (n - 1),
                    scores=scores.astype(np.float32),
                )
        return fits  # type: ignore[return-value]

    def _components_from(self, u: np.ndarray, w: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Components (k, d) float64 from eigenvectors u (m, k) of the route's matrix."""
        if u.shape[1] == 0:
            return np.zeros((0, self._d))
        if self._route == "svd":
            return np.ascontiguousarray(u.T)
        return (x.T @ u / np.sqrt(w)).T

    def _fit_streamed(self, stack: CellStack, cell: int, progress: Any) -> _CellFit:
        """Decompose one cell too large for a batch, reading it in blocks.

        Advances ``progress`` by 1 in fractions, one per block read.
        """
        n, d = stack.n_views, stack.cell_size
        done = progress.completed + 1.0
        budget = max(1, self.batch_bytes - 24 * min(n, d) ** 2)
        if self._route == "gram":
            width = max(1, budget // (n * 17))
            blocks = [slice(c0, min(d, c0 + width)) for c0 in range(0, d, width)]
            mat = np.zeros((n, n))
            mean = np.empty(d)
            step = 0.5 / len(blocks)
            for cols in blocks:
                x = stack.read_block(cell, slice(None), cols).astype(np.float64)
                mean[cols] = x.mean(axis=0)
                x -= mean[cols]
                mat += x @ x.T
                progress.advance(step)
            trace = float(np.trace(mat))
            if trace == 0.0:
                progress.update(done)
                return _empty_fit(mean.astype(np.float32), n)
            w, u = self._eigen_top(mat[None], np.array([trace]), np.array([cell]))[0]
            k = u.shape[1]
            comps = np.empty((k, d))
            scores = np.zeros((n, k))
            if k:
                inv = 1.0 / np.sqrt(w)
                for cols in blocks:
                    x = stack.read_block(cell, slice(None), cols).astype(np.float64)
                    x -= mean[cols]
                    part = (x.T @ u) * inv  # (w, k)
                    comps[:, cols] = part.T
                    scores += x @ part
                    progress.advance(step)
        else:
            height = max(1, budget // (d * 17))
            blocks = [slice(r0, min(n, r0 + height)) for r0 in range(0, n, height)]
            step = 1.0 / (3 * len(blocks))
            total = np.zeros(d)
            for rows in blocks:
                total += stack.read_block(cell, rows, slice(None)).sum(axis=0, dtype=np.float64)
                progress.advance(step)
            mean = total / n
            mat = np.zeros((d, d))
            for rows in blocks:
                x = stack.read_block(cell, rows, slice(None)).astype(np.float64) - mean
                mat += x.T @ x
                progress.advance(step)
            trace = float(np.trace(mat))
            if trace == 0.0:
                progress.update(done)
                return _empty_fit(mean.astype(np.float32), n)
            w, u = self._eigen_top(mat[None], np.array([trace]), np.array([cell]))[0]
            comps = np.ascontiguousarray(u.T)
            scores = np.empty((n, comps.shape[0]))
            for rows in blocks:
                x = stack.read_block(cell, rows, slice(None)).astype(np.float64) - mean
                scores[rows] = x @ u
                progress.advance(step)
        progress.update(done)
        comps, scores = _flip_signs(comps, scores)
        return _CellFit(
            mean=mean.astype(np.float32),
            components=comps.astype(np.float32),
            eigenvalues=w / (n - 1),
            total_variance=trace / (n - 1),
            scores=scores.astype(np.float32),
        )

    def _eigen_top(
        self, mat: np.ndarray, traces: np.ndarray, cells: np.ndarray
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """Top eigenpairs kept per cell of symmetric PSD matrices mat (b, m, m).

        Returns, per cell, ``(w, u)``: eigenvalues of ``mat`` (k,) descending
        (not yet divided by n - 1) and eigenvectors (m, k).
        """
        m = mat.shape[1]
        out: list[tuple[np.ndarray, np.ndarray] | None] = [None] * mat.shape[0]
        if self.solver_ in ("gram", "svd"):
            w_all, u_all = np.linalg.eigh(mat)
            for i in range(mat.shape[0]):
                w, u = w_all[i, ::-1], u_all[i, :, ::-1]
                k, _ = self._choose_k(w, float(traces[i]), trusted=m, m=m)
                out[i] = (w[:k].copy(), np.ascontiguousarray(u[:, :k]))
            return out  # type: ignore[return-value]

        if self.method == "adaptive":
            k_try = min(self._k_cap, RANDOMIZED_INITIAL_COMPONENTS)
        else:
            k_try = self._k_cap
        pending = np.arange(mat.shape[0])
        while pending.size:
            width = min(m, k_try + RANDOMIZED_OVERSAMPLES)
            trusted = m if width == m else k_try
            w_all, u_all = _subspace_iteration(
                mat[pending], width, [(int(self.random_state), int(cells[i])) for i in pending]
            )
            still = []
            for j, i in enumerate(pending):
                k, done = self._choose_k(w_all[j], float(traces[i]), trusted=trusted, m=m)
                if done or k_try >= self._k_cap or trusted == m:
                    out[i] = (w_all[j, :k].copy(), np.ascontiguousarray(u_all[j, :, :k]))
                else:
                    still.append(i)
            pending = np.array(still, dtype=np.int64)
            k_try = min(self._k_cap, 2 * k_try)
        return out  # type: ignore[return-value]

    def _choose_k(self, w: np.ndarray, trace: float, *, trusted: int, m: int) -> tuple[int, bool]:
        """Components to keep from descending eigenvalues w of the route's matrix.

        Returns ``(k, complete)``; ``complete`` is False when the adaptive rule
        was not met within the ``trusted`` leading values and more could be.
        """
        if trace <= 0.0 or w.size == 0 or w[0] <= 0.0:
            return 0, True
        w = w[:trusted]
        tol = w[0] * m * np.finfo(np.float64).eps
        rank = int(np.count_nonzero(w > tol))
        cap = min(self._k_cap, rank)
        if self.method != "adaptive":
            return cap, True
        cum = np.cumsum(w[:cap]) / trace
        reached = np.flatnonzero(cum >= float(self.threshold) - _THRESHOLD_SLACK)
        if reached.size:
            return int(reached[0]) + 1, True
        return cap, rank < trusted

    # ------------------------------------------------------- transform/inverse

    def transform(self, images: np.ndarray) -> np.ndarray:
        """Project images onto the eigenspace: the scores in orthonormal coordinates.

        Parameters
        ----------
        images : ndarray of shape (n, height, width, 3)
            uint8 or float, 0..255 units, same size as the training images.

        Returns
        -------
        scores : ndarray of shape (n, K), float32
        """
        self._check_fitted("transform")
        images = np.asarray(images)
        h, w = self.image_shape_
        if images.ndim != 4 or images.shape[1:] != (h, w, 3):
            raise ValueError(
                f"CellEigenspace.transform: images must be (n, {h}, {w}, 3), got {images.shape}"
            )
        offsets = self.component_offsets_
        out = np.empty((images.shape[0], int(offsets[-1])), dtype=np.float32)
        chunk = max(1, self.batch_bytes // max(1, 8 * h * w * 3))
        for s in range(0, images.shape[0], chunk):
            cells = split_cells(images[s : s + chunk], self.cell_shape_)
            for c, comps in enumerate(self.components_):
                if comps.shape[0]:
                    xc = cells[:, c, :].astype(np.float32) - self.mean_[c]
                    out[s : s + chunk, offsets[c] : offsets[c + 1]] = xc @ comps.T
        return out

    def inverse_transform(self, scores: np.ndarray) -> np.ndarray:
        """Reconstruct images from scores (float model: no rounding or clipping).

        Parameters
        ----------
        scores : ndarray of shape (n, K) or (K,)
            Coefficients in orthonormal coordinates.

        Returns
        -------
        images : ndarray of shape (n, height, width, 3) or (height, width, 3), float32
            Padding cropped; values in 0..255 units (not clipped).
        """
        self._check_fitted("inverse_transform")
        scores = np.asarray(scores, dtype=np.float32)
        single = scores.ndim == 1
        if single:
            scores = scores[None]
        offsets = self.component_offsets_
        k_total = int(offsets[-1])
        if scores.ndim != 2 or scores.shape[1] != k_total:
            raise ValueError(
                f"CellEigenspace.inverse_transform: scores must be (n, {k_total}) or "
                f"({k_total},), got {scores.shape}"
            )
        n = scores.shape[0]
        cells = np.empty((n, len(self.components_), self.mean_.shape[1]), dtype=np.float32)
        cells[:] = self.mean_
        for c, comps in enumerate(self.components_):
            if comps.shape[0]:
                cells[:, c, :] += scores[:, offsets[c] : offsets[c + 1]] @ comps
        images = merge_cells(cells, self.image_shape_, self.cell_shape_)
        return images[0] if single else images


# --------------------------------------------------------------------------
# numerical kernels


def _empty_fit(mean: np.ndarray, n: int) -> _CellFit:
    d = mean.shape[0]
    return _CellFit(
        mean=mean,
        components=np.zeros((0, d), dtype=np.float32),
        eigenvalues=np.zeros(0),
        total_variance=0.0,
        scores=np.zeros((n, 0), dtype=np.float32),
    )


def _flip_signs(comps: np.ndarray, scores: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Make the largest-|.| entry of each component row positive (like svd_flip)."""
    if comps.shape[0] == 0:
        return comps, scores
    idx = np.argmax(np.abs(comps), axis=1)
    signs = np.sign(comps[np.arange(comps.shape[0]), idx])
    signs[signs == 0] = 1.0
    return comps * signs[:, None], scores * signs[None, :]


def _subspace_iteration(
    mat: np.ndarray, width: int, seeds: list[tuple[int, int]]
) -> tuple[np.ndarray, np.ndarray]:
    """Randomized top eigenpairs of symmetric PSD matrices.

    Parameters
    ----------
    mat : ndarray of shape (b, m, m), float64
    width : int
        Columns of the sketch (components wanted + oversamples), <= m.
    seeds : list of b (random_state, cell) pairs
        One Gaussian sketch per matrix, independent of the batching.

    Returns
    -------
    w : ndarray of shape (b, width), float64
        Ritz values, descending.
    u : ndarray of shape (b, m, width), float64
        Ritz vectors (orthonormal columns).
    """
    b, m, _ = mat.shape
    omega = np.empty((b, m, width))
    for i, seed in enumerate(seeds):
        omega[i] = np.random.default_rng(list(seed)).standard_normal((m, width))
    y = mat @ omega
    for _ in range(RANDOMIZED_POWER_ITERATIONS):
        # LU (permuted L) keeps the sketch well conditioned at a fraction of
        # QR's cost; one QR at the end gives the orthonormal basis.
        y = mat @ scipy.linalg.lu(y, permute_l=True, check_finite=False)[0]
    q, _ = np.linalg.qr(y)
    t = q.transpose(0, 2, 1) @ (mat @ q)
    t = 0.5 * (t + t.transpose(0, 2, 1))
    w, v = np.linalg.eigh(t)
    w, v = w[:, ::-1], v[:, :, ::-1]
    return np.ascontiguousarray(w), q @ v
