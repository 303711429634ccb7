"""Scores of a view from a sparse ray-cast: regularised per-cell least squares (issue 13).

A device frame is, per cell ``c``, ``x_c = mean_c + sum_j a_j * scales[j] * E[j]`` over the
cell's int8 eigenimages ``E`` (`device_runtime.reconstruct`). Write ``B_c`` for the cell's
rows ``scales[j] * E[j]`` (K_c x cell values): the device's own basis, slightly
non-orthogonal after quantization. Given the RGB values ``x_S`` of only some pixels ``S``
of the true view (a sparse ray-cast, `host.render.raycast.Renderer.render_pixels`) and a prior
score vector ``a0`` (interpolated scores, or the previous frame's), `SparseRecovery` solves,
per cell::

    a_c = a0_c + (B_S B_Sᵀ + λ Σ⁻¹)⁻¹ B_S (x_S - mean_S - B_Sᵀ a0_c)

where ``B_S`` keeps the columns of ``B_c`` at the sampled values and ``Σ`` is the diagonal
of the components' variances over the training views (the annexed eigenvalues). This is the
MAP estimate for ``x = mean + a B + noise`` with noise variance ``λ`` (squared 0..255
units per value) and the Gaussian prior ``a ~ N(a0, Σ)``: with every pixel sampled and
``λ -> 0`` it is `HostModel.project`'s least-squares projection; with few samples the prior
keeps the components the samples cannot tell apart. λ is `DEFAULT_LAMBDA`
(docs/design-notes.md, "Sparse ray-casts while moving").

Cost. Per sample pattern (`SamplePattern`: a stride with an offset, or a list of pixels),
each cell's factor ``M = (B_S B_Sᵀ + λ Σ⁻¹)⁻¹ B_S``, ``G = I - M B_Sᵀ`` and ``m = M mean_S``
is computed once and cached, so one recovery is ``a_c = G a0_c + M x_S - m``: two small
matrix-vector products per cell. Cells with 0 components have nothing to solve; cells with
no sampled pixel keep the prior; components whose scale is 0 (they show nothing) get 0,
as in `HostModel.project`.

`ProgressiveRecovery` accumulates successive strided offsets of one resting view (item 3 of
the issue): the information form ``(λ Σ⁻¹ + Σ_i B_Si B_Siᵀ) a = λ Σ⁻¹ a0 + Σ_i B_Si (x_Si -
mean_Si)`` over the offsets seen so far, whose per-offset Gram matrices are cached, so after
all ``stride**2`` offsets the frame is the full projection (up to λ).

Residuals (issue 23): `SparseRecovery.recover_residual` recovers a *correction* of a frame
the device already shows (its own synthesis ``S``) from the residual ``r_S = x_S - S_S`` at
the sampled pixels, with prior zero: ``d_c = (B_S B_Sᵀ + λ Σ⁻¹)⁻¹ B_S r_S`` (no sample, no
change). Σ and λ are then the statistics of the residual, not of the views: a
`SparseRecovery` built with ``variance=`` (the residual scores' variance per component) and
``lam=`` (the residual's power outside the eigenspace), as `host.fit.motion.ResidualPrior`
measured them.

Pixels in the padding of the bottom/right cells do not exist in the view and are never
sampled (`HostModel.project` fits them as zeros; on models whose image size is a multiple
of the cell size the two agree).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = [
    "DEFAULT_LAMBDA",
    "ProgressiveRecovery",
    "SamplePattern",
    "SparseRecovery",
    "offset_order",
    "sparse_samples",
]

#: Default λ: the noise variance (squared 0..255 units per sampled value) the prior is
#: weighed against. Tuned on the tooth and the head at 192 (docs/design-notes.md).
DEFAULT_LAMBDA = 100.0

#: Variance floor for components whose training scores never vary (avoids 1/0).
_MIN_VARIANCE = 1e-6


@dataclass(frozen=True, eq=False)
class SamplePattern:
    """Which pixels of a ``width`` x ``height`` view were ray-cast.

    Build it with `strided` or `pixels`; ``key`` identifies it for the factor cache.

    Attributes
    ----------
    width, height : int
    rows, cols : ndarray of shape (n,), int64
        The pixels, in the order their samples come in.
    key : tuple
        ``("stride", s, dy, dx)`` or ``("pixels", digest)``, plus the size.
    """

    width: int
    height: int
    rows: np.ndarray
    cols: np.ndarray
    key: tuple

    @classmethod
    def strided(
        cls, width: int, height: int, stride: int, offset: tuple[int, int] = (0, 0)
    ) -> SamplePattern:
        """Every ``stride``-th row and column from ``offset = (dy, dx)``, row-major
        (`host.render.raycast.strided_pixels`; samples come as
        ``render_strided(...).reshape(-1, 4)``)."""
        from host.render.raycast import strided_pixels

        rows, cols = strided_pixels(width, height, stride, offset)
        dy, dx = (int(v) for v in offset)
        return cls(int(width), int(height), rows, cols,
                   ("stride", int(width), int(height), int(stride), dy, dx))

    @classmethod
    def pixels(cls, width: int, height: int, rows: Any, cols: Any) -> SamplePattern:
        """An explicit list of distinct pixels ``(rows[i], cols[i])`` inside the view.

        Raises
        ------
        ValueError
            Mismatched or non-1-D indices, pixels outside the view, or a repeated pixel.
        """
        rows = np.asarray(rows, dtype=np.int64).ravel()
        cols = np.asarray(cols, dtype=np.int64).ravel()
        if rows.shape != cols.shape:
            raise ValueError(f"SamplePattern: {rows.size} rows but {cols.size} cols")
        if rows.size and (rows.min() < 0 or rows.max() >= height or cols.min() < 0
                          or cols.max() >= width):
            raise ValueError(f"SamplePattern: pixels must lie within {height} x {width}")
        flat = rows * int(width) + cols
        if np.unique(flat).size != flat.size:
            raise ValueError("SamplePattern: a pixel is listed twice")
        import hashlib

        digest = hashlib.sha1(flat.tobytes()).hexdigest()
        return cls(int(width), int(height), rows, cols,
                   ("pixels", int(width), int(height), digest))

    @property
    def n_pixels(self) -> int:
        return int(self.rows.size)


def offset_order(stride: int) -> list[tuple[int, int]]:
    """The ``stride**2`` offsets of a stride in a dispersed order (the Bayer dither matrix):
    each prefix spreads its pixels evenly ((0, 0), then the diagonal (1, 1), ...; the first
    quarter of stride 4 is stride 2's grid), so partial accumulations look uniform.

    The first offset is ``(0, 0)``; every offset appears once.
    """
    if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
        raise ValueError(f"stride={stride!r} must be a positive integer")
    s = int(stride)
    bits = max(1, (s - 1).bit_length())
    # the Bayer ordered-dither index: interleave the bits of (dy ^ dx) and dy, low bits first
    keys = []
    for dy in range(s):
        for dx in range(s):
            code = 0
            for b in range(bits):
                shift = 2 * (bits - 1 - b)
                code |= (((dy ^ dx) >> b) & 1) << (shift + 1) | ((dy >> b) & 1) << shift
            keys.append((code, dy, dx))
    return [(dy, dx) for _, dy, dx in sorted(keys)]


def sparse_samples(view_renderer: Any, phi_deg: float, theta_deg: float,
                   pattern: SamplePattern) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast only ``pattern``'s pixels of a view, as `ViewRenderer.render` would show them.

    Parameters
    ----------
    view_renderer : host.render.settings.ViewRenderer
        The model's recorded render settings and volume.
    phi_deg, theta_deg : float
    pattern : SamplePattern
        Of the renderer's image size.

    Returns
    -------
    rgb8 : ndarray of shape (n, 3), uint8
        Equal to ``view_renderer.render(phi, theta)[0][pattern.rows, pattern.cols]``.
    alpha : ndarray of shape (n,), float32
    """
    settings = view_renderer.settings
    if (pattern.height, pattern.width) != (settings.height, settings.width):
        raise ValueError(f"sample pattern of a {pattern.width} x {pattern.height} view; the "
                         f"renderer's is {settings.width} x {settings.height}")
    camera = settings.camera(phi_deg, theta_deg)
    rgba = view_renderer.renderer.render_pixels(camera, settings.width, settings.height,
                                                pattern.rows, pattern.cols)
    return view_renderer.renderer.composite(rgba), np.ascontiguousarray(rgba[:, 3])


@dataclass
class _CellFactor:
    cell: int
    lo: int
    hi: int
    start: int  # slice of the pattern's cell-sorted flat samples
    stop: int
    m: np.ndarray  # float32 (K, n): M
    g: np.ndarray  # float32 (K, K): I - M B_Sᵀ
    mean_term: np.ndarray  # float32 (K,): M mean_S


@dataclass
class _Factor:
    order: np.ndarray  # int64: flat sample index (pixel * 3 + channel) sorted by cell
    cells: list[_CellFactor] = field(default_factory=list)
    zero: np.ndarray | None = None  # components forced to 0 (scale 0) in sampled cells
    nbytes: int = 0


@dataclass
class _CellGram:
    cell: int
    lo: int
    hi: int
    start: int
    stop: int
    basis: np.ndarray  # float64 (K, n): B_S
    mean: np.ndarray  # float64 (n,): mean_S
    gram: np.ndarray  # float64 (K, K): B_S B_Sᵀ


class SparseRecovery:
    """Recover a view's scores from samples at some of its pixels (see the module docstring).

    Parameters
    ----------
    model : HostModel
        Its int8 eigenimages, scales and means are what the device reconstructs with; its
        annexed eigenvalues (else the training scores' variance) are Σ.
    lam : float
        λ >= 0, the noise variance in squared 0..255 units (default `DEFAULT_LAMBDA`).
        0 is plain least squares (underdetermined cells then use the pseudo-inverse).
    max_patterns : int
        Factors kept in the cache (least recently used dropped first).
    variance : ndarray of shape (K,), optional
        Σ's diagonal (default: the annexed eigenvalues, else the training scores' variance).

    Attributes
    ----------
    variance : ndarray of shape (K,), float64
        Σ's diagonal.
    """

    def __init__(self, model: Any, *, lam: float = DEFAULT_LAMBDA, max_patterns: int = 64,
                 variance: Any = None) -> None:
        lam = float(lam)
        if not (np.isfinite(lam) and lam >= 0.0):
            raise ValueError(f"lam={lam} must be a finite number >= 0")
        if int(max_patterns) < 1:
            raise ValueError(f"max_patterns={max_patterns} must be >= 1")
        self.model = model
        self.lam = lam
        self.max_patterns = int(max_patterns)
        img = model.image
        self.image_shape = tuple(int(v) for v in img.image_shape)
        self.cell_shape = tuple(int(v) for v in img.cell_shape)
        self.grid = tuple(int(v) for v in img.grid_shape)
        self.n_coefficients = int(img.n_coefficients)
        counts = np.asarray(img.n_components, dtype=np.int64)
        self._offsets = np.concatenate([[0], np.cumsum(counts)])
        if variance is not None:
            var = np.asarray(variance, dtype=np.float64)
        elif model.eigenvalues is not None:
            var = np.asarray(model.eigenvalues, dtype=np.float64)
        else:
            var = np.asarray(model.training_scores, dtype=np.float64).var(axis=0, ddof=1)
        if var.shape != (self.n_coefficients,):
            raise ValueError(f"variance of shape {var.shape}, the model has "
                             f"K={self.n_coefficients}")
        self.variance = np.maximum(var, _MIN_VARIANCE)
        self._scales = np.asarray(img.scales, dtype=np.float64)
        self._factors: OrderedDict[tuple, _Factor] = OrderedDict()
        self._grams: OrderedDict[tuple, tuple[np.ndarray, list[_CellGram]]] = OrderedDict()

    # ------------------------------------------------------------------ patterns
    def _check_pattern(self, pattern: SamplePattern) -> None:
        h, w = self.image_shape
        if (pattern.height, pattern.width) != (h, w):
            raise ValueError(
                f"sample pattern of a {pattern.width} x {pattern.height} view; the model's "
                f"views are {w} x {h}"
            )

    def _layout(self, pattern: SamplePattern):
        """Flat sample indices sorted by cell, each one's cell and value index in the cell."""
        ch, cw = self.cell_shape
        nx = self.grid[1]
        cell_of_pixel = (pattern.rows // ch) * nx + pattern.cols // cw
        value_of_pixel = ((pattern.rows % ch) * cw + pattern.cols % cw) * 3
        flat = np.arange(pattern.n_pixels * 3, dtype=np.int64)
        pixel = flat // 3
        cell = cell_of_pixel[pixel]
        value = value_of_pixel[pixel] + flat % 3
        order = np.argsort(cell, kind="stable")
        cell_sorted = cell[order]
        bounds = np.searchsorted(cell_sorted, np.arange(self.grid[0] * nx + 1))
        return order, value[order], bounds

    def _cell_basis(self, c: int, values: np.ndarray) -> tuple[int, int, np.ndarray, np.ndarray]:
        img = self.model.image
        lo, hi = int(self._offsets[c]), int(self._offsets[c + 1])
        basis = img.eigenimages[lo:hi][:, values].astype(np.float64)
        basis *= self._scales[lo:hi, None]
        mean = img.mean[c][values].astype(np.float64)
        return lo, hi, basis, mean

    def factor(self, pattern: SamplePattern) -> _Factor:
        """The per-cell factors of ``pattern`` (computed once, then cached)."""
        self._check_pattern(pattern)
        cached = self._factors.get(pattern.key)
        if cached is not None:
            self._factors.move_to_end(pattern.key)
            return cached
        order, values, bounds = self._layout(pattern)
        out = _Factor(order=order)
        zero = []
        for c in range(len(bounds) - 1):
            start, stop = int(bounds[c]), int(bounds[c + 1])
            lo, hi = int(self._offsets[c]), int(self._offsets[c + 1])
            if hi == lo or stop == start:
                continue
            lo, hi, basis, mean = self._cell_basis(c, values[start:stop])
            gram = basis @ basis.T
            if self.lam > 0.0:
                gram[np.diag_indices_from(gram)] += self.lam / self.variance[lo:hi]
                m = np.linalg.solve(gram, basis)
            else:
                m = np.linalg.pinv(gram) @ basis
            g = np.eye(hi - lo) - m @ basis.T
            dead = self._scales[lo:hi] == 0.0
            if np.any(dead):
                g[dead] = 0.0
                m[dead] = 0.0
                zero.append(np.flatnonzero(dead) + lo)
            out.cells.append(_CellFactor(
                c, lo, hi, start, stop, m.astype(np.float32), g.astype(np.float32),
                (m @ mean).astype(np.float32),
            ))
            out.nbytes += 4 * (m.size + g.size + hi - lo)
        out.zero = np.concatenate(zero) if zero else None
        self._factors[pattern.key] = out
        while len(self._factors) > self.max_patterns:
            self._factors.popitem(last=False)
        return out

    # ------------------------------------------------------------------ recovery
    @staticmethod
    def _flat_samples(pattern: SamplePattern, samples: Any) -> np.ndarray:
        x = np.asarray(samples)
        if x.ndim == 3:
            x = x.reshape(-1, x.shape[-1])
        if x.shape != (pattern.n_pixels, 3):
            raise ValueError(
                f"recover: samples of shape {np.shape(samples)}; the pattern has "
                f"{pattern.n_pixels} pixels of 3 values"
            )
        return x.reshape(-1)

    def recover(self, pattern: SamplePattern, samples: Any, prior: Any) -> np.ndarray:
        """The scores (K,) float32 of the view whose pixels ``pattern`` shows as ``samples``.

        Parameters
        ----------
        pattern : SamplePattern
        samples : array-like of shape (n, 3) (or (ny, nx, 3) for a strided pattern)
            RGB in 0..255 as the device shows them, e.g. ``renderer.composite(render_pixels(
            ...))``, in the pattern's pixel order.
        prior : array-like of shape (K,)
            The prior scores ``a0`` (interpolated, or the previous frame's).

        Returns
        -------
        ndarray of shape (K,), float32
        """
        a0 = np.asarray(prior, dtype=np.float32)
        if a0.shape != (self.n_coefficients,):
            raise ValueError(f"recover: prior of shape {a0.shape}, the model has "
                             f"K={self.n_coefficients}")
        x = self._flat_samples(pattern, samples)
        fac = self.factor(pattern)
        xs = x[fac.order].astype(np.float32)
        out = a0.copy()
        for cf in fac.cells:
            out[cf.lo:cf.hi] = (cf.g @ a0[cf.lo:cf.hi] + cf.m @ xs[cf.start:cf.stop]
                                - cf.mean_term)
        if fac.zero is not None:
            out[fac.zero] = 0.0
        return out

    def recover_residual(self, pattern: SamplePattern, residual: Any) -> np.ndarray:
        """The correction (K,) float32 of a frame from its residual at ``pattern``'s pixels.

        ``residual`` (n, 3) float: the true view minus the frame being corrected, at the
        sampled pixels, in the pattern's order. The prior is zero: cells with no sample get
        no correction, and no samples give none at all.
        """
        r = self._flat_samples(pattern, residual)
        fac = self.factor(pattern)
        rs = r[fac.order].astype(np.float32)
        out = np.zeros(self.n_coefficients, dtype=np.float32)
        for cf in fac.cells:
            out[cf.lo:cf.hi] = cf.m @ rs[cf.start:cf.stop]
        if fac.zero is not None:
            out[fac.zero] = 0.0
        return out

    # ------------------------------------------------------------------ accumulation
    def grams(self, pattern: SamplePattern) -> tuple[np.ndarray, list[_CellGram]]:
        """The cell-sorted sample order and, per sampled cell, ``B_S``, ``mean_S`` and
        ``B_S B_Sᵀ`` of ``pattern`` (cached): the terms `ProgressiveRecovery` adds up."""
        self._check_pattern(pattern)
        cached = self._grams.get(pattern.key)
        if cached is not None:
            self._grams.move_to_end(pattern.key)
            return cached
        order, values, bounds = self._layout(pattern)
        out = []
        for c in range(len(bounds) - 1):
            start, stop = int(bounds[c]), int(bounds[c + 1])
            if self._offsets[c + 1] == self._offsets[c] or stop == start:
                continue
            lo, hi, basis, mean = self._cell_basis(c, values[start:stop])
            out.append(_CellGram(c, lo, hi, start, stop, basis, mean, basis @ basis.T))
        self._grams[pattern.key] = (order, out)
        while len(self._grams) > self.max_patterns:
            self._grams.popitem(last=False)
        return self._grams[pattern.key]


class ProgressiveRecovery:
    """Accumulate strided sparse ray-casts of one resting view over successive frames.

    Each `add` brings the samples at one more offset of ``stride`` (`next_offset` says which,
    in `offset_order`); the scores solve the MAP problem over every sample added since the
    last `reset`, so after ``stride**2`` frames they are the full projection (up to λ).

    Parameters
    ----------
    recovery : SparseRecovery
    stride : int
    """

    def __init__(self, recovery: SparseRecovery, stride: int) -> None:
        self.recovery = recovery
        self.stride = int(stride)
        self.order = offset_order(self.stride)
        h, w = recovery.image_shape
        self._patterns = {o: SamplePattern.strided(w, h, self.stride, o) for o in self.order}
        k = recovery.n_coefficients
        n_cells = recovery.grid[0] * recovery.grid[1]
        self._prior = np.zeros(k, dtype=np.float64)
        self._rhs = np.zeros(k, dtype=np.float64)
        self._gram: list[np.ndarray | None] = [None] * n_cells
        self._seen: list[tuple[int, int]] = []

    @property
    def offsets_seen(self) -> list[tuple[int, int]]:
        """The offsets accumulated since the last `reset`, in order."""
        return list(self._seen)

    @property
    def complete(self) -> bool:
        """Every pixel of the view has been sampled."""
        return len(self._seen) == len(self.order)

    def next_offset(self) -> tuple[int, int] | None:
        """The next offset to ray-cast, or None when complete."""
        for o in self.order:
            if o not in self._seen:
                return o
        return None

    def pattern(self, offset: tuple[int, int]) -> SamplePattern:
        """The strided pattern of ``offset``."""
        return self._patterns[tuple(int(v) for v in offset)]

    def reset(self, prior: Any) -> None:
        """Forget every sample (the view moved); ``prior`` is the new ``a0``."""
        a0 = np.asarray(prior, dtype=np.float64)
        if a0.shape != self._prior.shape:
            raise ValueError(f"reset: prior of shape {a0.shape}, expected {self._prior.shape}")
        self._prior = a0.copy()
        self._rhs = (self.recovery.lam / self.recovery.variance) * a0
        self._gram = [None] * len(self._gram)
        self._seen = []

    def add(self, offset: tuple[int, int], samples: Any) -> np.ndarray:
        """Add the samples (ny, nx, 3) or (n, 3) of ``offset``; return the scores (K,) float32.

        Raises
        ------
        ValueError
            An offset already added since the last `reset`, or samples of the wrong shape.
        """
        offset = tuple(int(v) for v in offset)
        if offset not in self._patterns:
            raise ValueError(f"offset {offset} is not within stride {self.stride}")
        if offset in self._seen:
            raise ValueError(f"offset {offset} was already added since the last reset")
        rec = self.recovery
        pattern = self._patterns[offset]
        x = SparseRecovery._flat_samples(pattern, samples)
        order, cells = rec.grams(pattern)
        xs = x[order].astype(np.float64)
        reg = rec.lam / rec.variance
        for cg in cells:
            self._rhs[cg.lo:cg.hi] += cg.basis @ (xs[cg.start:cg.stop] - cg.mean)
            g = self._gram[cg.cell]
            if g is None:
                g = np.diag(reg[cg.lo:cg.hi]).astype(np.float64)
                self._gram[cg.cell] = g
            g += cg.gram
        self._seen.append(offset)
        return self.scores()

    def scores(self) -> np.ndarray:
        """The current MAP scores (K,) float32 (the prior where nothing was sampled)."""
        rec = self.recovery
        out = self._prior.copy()
        scales = rec._scales
        for c, g in enumerate(self._gram):
            if g is None:
                continue
            lo, hi = int(rec._offsets[c]), int(rec._offsets[c + 1])
            if rec.lam > 0.0:
                out[lo:hi] = np.linalg.solve(g, self._rhs[lo:hi])
            else:
                out[lo:hi] = np.linalg.pinv(g) @ self._rhs[lo:hi]
            out[lo:hi][scales[lo:hi] == 0.0] = 0.0
        return out.astype(np.float32)
