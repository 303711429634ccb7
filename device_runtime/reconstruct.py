"""Reconstruct views from score vectors with the quantized eigenspace (pure numpy).

For each cell c (row-major grid, zero-padded at the bottom/right)::

    x_c = mean_c + sum_{j in cell c} y_j * scales[j] * eigenimages[j]
    pixel = clip(rint(x), 0, 255) as uint8, then crop the padding

How it is computed (the host evaluates with this same code, so what is measured is what is
shown):

* ``w = y * scales`` is formed once per frame (the scales fold into the coefficients).
* Only cells whose slice of ``y`` changed since the last call (exact equality) are recomputed;
  cells with 0 components show their mean, written once at construction.
* The work is cut at construction into jobs that respect ``scratch_bytes``. `update` runs
  *groups*: runs of consecutive cells whose largest cell's rows, cast to float32, plus one
  float32 output row per cell fit the scratch budget (at the default budget, the whole frame
  of a 256 or 512 px image in one or two groups). Per changed cell of a group: its int8 rows
  are cast into the first rows of the group's cast area, which stays in the CPU's cache for
  the one BLAS ``sgemv`` (``w_c @ E_c``) that reads them back into the cell's output row;
  then the group's changed cells get their means added and are rounded, clipped and written
  together straight into the frame buffer through a ``(n_cells_y, cell_h, n_cells_x, cell_w,
  3)`` view. Each product runs over all of a cell's rows, its zero scores included: the
  frame is the same bit for bit however the cells are grouped (a product over the non-zero
  rows only sums the same terms in another order, so a value on a .5 tie may round
  otherwise; gathering those rows costs about what casting them does, and at the 20-35 %
  zeros of a changed cell's scores it was no faster). A cell too large for the scratch (e.g.
  the single cell of a ``standard`` eigenspace) is cut into tiles of whole pixel rows of the
  cell, accumulating over row chunks when even one tile of all its components does not fit.
  No per-pixel Python work, no float32 copy of the eigenspace: memory beyond the arrays
  themselves is the scratch buffer, the frame buffer and O(K) vectors.
* With ``threads=2`` the jobs are split in two halves of equal row count, each with its own
  half of the scratch budget; numpy releases the GIL in the casts and in BLAS.
* `Reconstructor.correct` runs *batches* (runs of cells whose rows all fit the scratch at
  once) with a given frame in place of the mean:
  ``clip(rint(synth_c + sum_j d_j * scales[j] * E[j]))`` for the cells whose ``d`` is not
  all zero, the device's own synthesized frame corrected by the host (a version-3 score
  packet, `protocol.scores`). It keeps that frame's cells (one frame of memory), so later
  corrections of the same frame need not pass it again. A correction's coefficients are
  sparse (the RD quantizer zeroes most of the later, smaller ones), so a batch gathers the
  int8 rows of its non-zero coefficients only (`numpy.take` into the scratch, then one cast)
  and multiplies each corrected cell's gathered rows; a batch with so many non-zero rows that
  gathering them (`GATHER_ROW_COST` each) costs at least a contiguous cast of all its rows
  blends its corrected cells' rows whole instead, as `update` does (``w`` is zero elsewhere:
  the same sums, to float rounding; host and device choose alike). Either way a batch adds,
  rounds and writes only its corrected cells, all at once.
  So a correction costs about what its non-zero rows cost: a complete one at rest 0.3-0.4 of its
  cells' rows, one while moving a few rows in a fraction of the cells (BENCHMARKS.md,
  "Correcting the own frame").
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = [
    "DEFAULT_SCRATCH_BYTES",
    "Reconstructor",
    "reconstruct_view",
    "reconstruction_memory_bytes",
    "usable_cpus",
]

#: Default scratch budget (float32 cast buffer + output rows), in bytes.
DEFAULT_SCRATCH_BYTES = 4 << 20
#: `Reconstructor.correct` gathers the rows of a batch's non-zero coefficients unless they,
#: times this, are at least the batch's rows (then it casts the batch whole): a gathered row
#: costs about this much more than one of a contiguous cast (module docstring; measured on
#: the shared volumes' real corrections at 256 and 512). At least 1.25 (scratch room).
GATHER_ROW_COST = 1.5
#: `Reconstructor.correct`: the share of a correction's jump across a cell border that is
#: smoothed away (the pixel either side moves by a third of it towards the other). A
#: correction is fitted cell by cell, so it steps at cell borders where the device's own
#: frame does not; at 0.5 the frames' blockiness at borders is back to the uncorrected
#: frame's, for at most 0.001 of object SSIM (docs/design-notes.md, "Cell seams"). At most
#: 0.75 (the smoothing's int16 arithmetic).
SEAM_STRENGTH = 0.5
_FLOAT_BYTES = 4


@dataclass
class _Cells:
    """Consecutive cells [start, stop) blended one at a time into consecutive output rows
    (`Reconstructor._blend_cells`): each cell's int8 rows cast into the first rows of one
    small cast area, then one BLAS product."""

    start: int
    stop: int
    out: np.ndarray  # float32 (stop - start, d) view of the scratch
    outs: list[np.ndarray]  # its rows
    # per cell of [start, stop): (k, its int8 rows, its weights (views of ``_w``), the first
    # k rows of the cast area)
    calls: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]]


@dataclass
class _Batch(_Cells):
    """`Reconstructor.correct`: consecutive cells whose rows all fit the scratch at once
    (a correction gathers a batch's non-zero rows into its first rows)."""

    row_start: int
    row_stop: int
    cast_dst: np.ndarray  # float32 (rows, d) view of the scratch


@dataclass
class _Tile:
    """Pixel rows [y0, y1) of one big cell; its components in chunks of `chunk` rows."""

    col_start: int
    col_stop: int
    y0: int
    y1: int


@dataclass
class _BigCell:
    cell: int
    row_start: int
    row_stop: int
    chunk: int
    tiles: list[_Tile]
    scratch: np.ndarray  # flat float32
    tile_values: int


@dataclass
class _Sparse:
    """A correction's non-zero coefficients, laid out once per `Reconstructor.correct` so
    that each batch finds its own by slicing."""

    nz: np.ndarray  # the non-zero coefficients' indices (ascending)
    w: np.ndarray  # their weights
    changed: np.ndarray  # bool (n_cells,): cells with a non-zero coefficient
    cum_nz: list[int]  # non-zero coefficients before each cell (n_cells + 1)
    cum_cells: list[int]  # changed cells before each cell (n_cells + 1)
    counts: list[int]  # per changed cell, its non-zero coefficients
    cell_y: np.ndarray  # per changed cell, its grid row
    cell_x: np.ndarray  # and column

    @classmethod
    def of(cls, w: np.ndarray, offsets: np.ndarray, nx: int, cum: np.ndarray) -> _Sparse:
        """``cum``: scratch of ``w.size + 1`` int64 whose first value is 0."""
        mask = w != 0
        np.cumsum(mask, out=cum[1:])
        cum_nz = cum[offsets]  # non-zero coefficients before each cell
        per_cell = np.diff(cum_nz)
        changed = per_cell > 0
        cells = np.flatnonzero(changed)
        cum_cells = np.zeros(offsets.size, np.int64)
        np.cumsum(changed, out=cum_cells[1:])
        nz = np.flatnonzero(mask)
        return cls(nz, w[nz], changed, cum_nz.tolist(), cum_cells.tolist(),
                   per_cell[cells].tolist(), cells // nx, cells % nx)


@dataclass
class _Worker:
    jobs: list[Any] = field(default_factory=list)  # `correct`: batches and big cells
    groups: list[Any] = field(default_factory=list)  # `update`: groups and big cells
    rows: int = 0


class Reconstructor:
    """Blend int8 eigenimages into a uint8 frame, recomputing only changed cells.

    Parameters
    ----------
    mean : ndarray of shape (n_cells, cell_values), uint8
        Per-cell means (``cell_values = cell_h * cell_w * 3``).
    eigenimages : ndarray of shape (n_coefficients, cell_values), int8
        Quantized components, cell-major.
    scales : ndarray of shape (n_coefficients,), float32
        Per-component scales (``component_j ~= scales[j] * eigenimages[j]``).
    n_components : ndarray of shape (n_cells,), int
        Components per cell (0: the cell shows its mean).
    image_shape : (int, int)
        ``(height, width)`` of the output.
    cell_shape : (int, int)
        ``(cell_h, cell_w)``.
    scratch_bytes : int
        Budget for the float32 scratch buffers (split between threads).
    threads : int or "auto"
        1 or 2 worker threads; ``"auto"`` picks 2 when the process may run on at least 2
        CPUs (`usable_cpus`) and the eigenspace is larger than 8 MB.
    scratch_of : Reconstructor, optional
        Use this reconstructor's scratch buffers when they have the same size and threads
        (another look of the same image, `device_runtime.loaded.LoadedModel.for_look`): the
        first frame then finds their pages mapped. That reconstructor must not `update` or
        `correct` again (its frames would race this one's).

    Attributes
    ----------
    frame : ndarray of shape (height, width, 3), uint8
        The frame buffer `update` returns (reused: copy it to keep a frame).
    cells_recomputed : int
        Cells recomputed by the last `update`.
    total_cells_recomputed : int
        Sum over all updates.
    threads : int
        Threads actually used.
    """

    def __init__(
        self,
        mean: np.ndarray,
        eigenimages: np.ndarray,
        scales: np.ndarray,
        n_components: np.ndarray,
        image_shape: tuple[int, int],
        cell_shape: tuple[int, int],
        *,
        scratch_bytes: int = DEFAULT_SCRATCH_BYTES,
        threads: int | str = 1,
        scratch_of: Reconstructor | None = None,
    ) -> None:
        height, width = (int(v) for v in image_shape)
        cell_h, cell_w = (int(v) for v in cell_shape)
        if min(height, width, cell_h, cell_w) < 1:
            raise ValueError(
                f"Reconstructor: image_shape={image_shape} and cell_shape={cell_shape} must be "
                "positive"
            )
        ny, nx = -(-height // cell_h), -(-width // cell_w)
        n_cells = ny * nx
        values = cell_h * cell_w * 3
        counts = np.asarray(n_components)
        if (
            counts.shape != (n_cells,)
            or counts.dtype.kind not in "iu"
            or (counts.size and counts.min() < 0)
        ):
            raise ValueError(
                f"Reconstructor: n_components must be ints >= 0 of shape ({n_cells},) for image "
                f"{height}x{width} with cells {cell_h}x{cell_w}, got {counts.dtype} {counts.shape}"
            )
        n_coeff = int(counts.sum())
        for name, arr, dtype, shape in (
            ("mean", mean, np.uint8, (n_cells, values)),
            ("eigenimages", eigenimages, np.int8, (n_coeff, values)),
            ("scales", scales, np.float32, (n_coeff,)),
        ):
            if not isinstance(arr, np.ndarray) or arr.dtype != dtype or arr.shape != shape:
                got = f"{arr.dtype} {arr.shape}" if isinstance(arr, np.ndarray) else type(arr)
                raise ValueError(
                    f"Reconstructor: {name} must be {np.dtype(dtype).name} of shape {shape}, "
                    f"got {got}"
                )
        if threads == "auto":
            big = eigenimages.nbytes > 8_000_000
            threads = 2 if big and usable_cpus() >= 2 else 1
        if threads not in (1, 2):
            raise ValueError(f"Reconstructor: threads={threads!r} must be 1, 2 or 'auto'")
        min_scratch = self.min_scratch_bytes(cell_shape) * threads
        if scratch_bytes < min_scratch:
            raise ValueError(
                f"Reconstructor: scratch_bytes={scratch_bytes} is below the minimum "
                f"{min_scratch} for cells of width {cell_w} with {threads} thread(s)"
            )
        self.image_shape = (height, width)
        self.cell_shape = (cell_h, cell_w)
        self.grid_shape = (ny, nx)
        self.n_cells = n_cells
        self.cell_values = values
        self.n_coefficients = n_coeff
        self.scratch_bytes = int(scratch_bytes)
        self.threads = int(threads)
        self.mean = np.ascontiguousarray(mean)
        self.eigenimages = np.ascontiguousarray(eigenimages)
        self.scales = np.ascontiguousarray(scales)
        self.n_components = counts.astype(np.int64)
        self.offsets = np.zeros(n_cells + 1, dtype=np.int64)
        np.cumsum(self.n_components, out=self.offsets[1:])
        self._padded = np.empty((ny * cell_h, nx * cell_w, 3), dtype=np.uint8)
        self._cells_view = self._padded.reshape(ny, cell_h, nx, cell_w, 3)
        self._cells_view[...] = self.mean.reshape(ny, nx, cell_h, cell_w, 3).transpose(
            0, 2, 1, 3, 4
        )
        needs_crop = (ny * cell_h, nx * cell_w) != (height, width)
        self.frame = self._padded[:height, :width].copy() if needs_crop else self._padded
        self._needs_crop = needs_crop
        self._w = np.zeros(n_coeff, dtype=np.float32)
        self._last_y = np.full(n_coeff, np.nan, dtype=np.float32)
        self._cum = np.zeros(n_coeff + 1, dtype=np.int64)
        self._diff = np.zeros(n_coeff, dtype=bool)
        self._changed = np.zeros(n_cells, dtype=bool)  # cells without components: never
        self._filled = np.flatnonzero(self.n_components)
        self._starts = self.offsets[self._filled]  # strictly increasing: reduceat's segments
        self._cell_y = np.arange(n_cells) // nx
        self._cell_x = np.arange(n_cells) % nx
        self.cells_recomputed = 0
        self.total_cells_recomputed = 0
        self._scratch_of = scratch_of
        self._workers = self._plan(self.scratch_bytes // self.threads)
        self._scratch_of = None
        self._pool = ThreadPoolExecutor(1) if self.threads == 2 else None
        self._held: np.ndarray | None = None  # `correct`: the frame to correct (as _padded)
        self._zero_cells = np.flatnonzero(self.n_components == 0)
        self._corrected = False  # the buffer holds a corrected frame (0-component cells too)
        self._nz: _Sparse | None = None  # `correct`: its non-zero coefficients (else None)
        self.seam_strength = SEAM_STRENGTH  # `correct`: 0 leaves the borders as computed
        self._seams: list[_SeamStrips] | None = None  # `correct`: scratch, base jumps held

    # ------------------------------------------------------------------ construction

    @staticmethod
    def min_scratch_bytes(cell_shape: tuple[int, int]) -> int:
        """Smallest scratch (per thread) that holds three pixel rows of one cell, in bytes."""
        return 3 * int(cell_shape[1]) * 3 * _FLOAT_BYTES

    @classmethod
    def from_image(cls, image: Any, **kwargs: Any) -> Reconstructor:
        """Build from an `protocol.image.EigenspaceImage` (keyword arguments pass through)."""
        return cls(
            image.mean,
            image.eigenimages,
            image.scales,
            image.n_components,
            image.image_shape,
            image.cell_shape,
            **kwargs,
        )

    def _plan(self, budget_bytes: int) -> list[_Worker]:
        """Cut the cells into jobs under the per-thread budget and split them among threads:
        `correct`'s batches (all of a batch's rows fit the scratch at once) and `update`'s
        groups (a cell's rows at a time: a group's output rows fit beside its largest cell's
        rows); a cell whose rows do not fit is a big cell in both."""
        budget = budget_bytes // _FLOAT_BYTES
        values = self.cell_values
        shared = self._scratch_of
        if (shared is not None and shared.threads == self.threads
                and all(a.size == budget for a in shared._scratches)):
            scratches = shared._scratches  # its pages are there already (a look switch)
        else:
            scratches = [np.zeros(budget, dtype=np.float32) for _ in range(self.threads)]
        self._scratches = scratches
        # first pass: job boundaries (cells) and their row counts
        spans: list[tuple[str, int, int]] = []
        c = 0
        counts = self.n_components
        while c < self.n_cells:
            k = int(counts[c])
            if (k + 1) * values > budget:
                spans.append(("big", c, c + 1))
                c += 1
                continue
            start = c
            rows = 0
            while c < self.n_cells:
                k = int(counts[c])
                if (rows + k + (c - start + 1)) * values > budget:
                    break
                rows += k
                c += 1
            spans.append(("batch", start, c))
        total_rows = max(1, self.n_coefficients)
        workers = [_Worker() for _ in range(self.threads)]
        done_rows = 0
        for kind, start, stop in spans:
            rows = int(self.offsets[stop] - self.offsets[start])
            index = 0 if self.threads == 1 or done_rows < total_rows / 2 else 1
            done_rows += rows
            scratch = scratches[index]
            job = (
                self._make_big(start, scratch)
                if kind == "big"
                else self._make_batch(start, stop, scratch)
            )
            workers[index].jobs.append(job)
            workers[index].rows += rows
        for worker, scratch in zip(workers, scratches):
            worker.groups = self._make_groups(worker.jobs, scratch)
        return workers

    def _calls(self, start: int, stop: int, cast: np.ndarray) -> list[tuple[int, np.ndarray,
                                                                           np.ndarray, np.ndarray]]:
        """Per cell of [start, stop): its component count, int8 rows, weights and the first
        rows of the cast area ``cast`` (`_Cells.calls`)."""
        calls = []
        for c in range(start, stop):
            a, b = int(self.offsets[c]), int(self.offsets[c + 1])
            calls.append((b - a, self.eigenimages[a:b], self._w[a:b], cast[: b - a]))
        return calls

    def _make_batch(self, start: int, stop: int, scratch: np.ndarray) -> _Batch:
        values = self.cell_values
        r0, r1 = int(self.offsets[start]), int(self.offsets[stop])
        rows = r1 - r0
        cast_dst = scratch[: rows * values].reshape(rows, values)
        out = scratch[rows * values : (rows + stop - start) * values].reshape(stop - start, values)
        return _Batch(start, stop, out, list(out), self._calls(start, stop, cast_dst), r0, r1,
                      cast_dst)

    def _make_groups(self, jobs: list[Any], scratch: np.ndarray) -> list[Any]:
        """`update`'s jobs for the cells of ``jobs`` (a worker's): runs of consecutive cells
        whose largest cell's rows plus one output row per cell fit ``scratch``, and the big
        cells as they are."""
        values = self.cell_values
        budget = scratch.size // values  # rows of the scratch
        counts = self.n_components
        groups: list[Any] = []

        def close(start: int, stop: int, k_max: int) -> None:
            cast = scratch[: k_max * values].reshape(k_max, values)
            out = scratch[k_max * values : (k_max + stop - start) * values].reshape(
                stop - start, values)
            groups.append(_Cells(start, stop, out, list(out), self._calls(start, stop, cast)))

        start = k_max = -1
        for job in jobs:
            if isinstance(job, _BigCell):
                if start >= 0:
                    close(start, job.cell, k_max)
                    start = -1
                groups.append(job)
                continue
            for c in range(job.start, job.stop):
                k = int(counts[c])
                if start >= 0 and max(k_max, k) + c + 1 - start > budget:
                    close(start, c, k_max)
                    start = -1
                if start < 0:
                    start, k_max = c, 0
                k_max = max(k_max, k)
        if start >= 0:  # the last job is a batch (a big cell closes the run)
            close(start, jobs[-1].stop, k_max)
        return groups

    def _make_big(self, c: int, scratch: np.ndarray) -> _BigCell:
        cell_h, cell_w = self.cell_shape
        row_len = cell_w * 3
        k = int(self.n_components[c])
        budget = scratch.size
        # rows of pixels per tile when all k components are cast at once (+ out + accumulator)
        pix_rows = budget // ((k + 2) * row_len)
        if pix_rows >= 1:
            chunk = max(1, k)
            pix_rows = min(pix_rows, cell_h)
        else:
            pix_rows = 1
            chunk = max(1, budget // row_len - 2)
        tiles = []
        for y0 in range(0, cell_h, pix_rows):
            y1 = min(cell_h, y0 + pix_rows)
            tiles.append(_Tile(y0 * row_len, y1 * row_len, y0, y1))
        return _BigCell(
            c,
            int(self.offsets[c]),
            int(self.offsets[c + 1]),
            chunk,
            tiles,
            scratch,
            pix_rows * row_len,
        )

    # ------------------------------------------------------------------ per frame

    def update(self, y: np.ndarray) -> np.ndarray:
        """Reconstruct the frame for score vector ``y``.

        Parameters
        ----------
        y : ndarray of shape (n_coefficients,), float32
            Scores in orthonormal coordinates (other float dtypes are converted).

        Returns
        -------
        ndarray of shape (height, width, 3), uint8
            The frame buffer (the same array every call).
        """
        y = np.asarray(y, dtype=np.float32)
        if y.shape != (self.n_coefficients,):
            raise ValueError(
                f"Reconstructor.update: y must have shape ({self.n_coefficients},), got {y.shape}"
            )
        if not np.all(np.isfinite(y)):
            raise ValueError("Reconstructor.update: y has NaN or infinite entries")
        changed = self._changed
        if self._starts.size:  # per cell with components: did any of its scores change
            np.not_equal(y, self._last_y, out=self._diff)
            changed[self._filled] = np.logical_or.reduceat(self._diff, self._starts)
        n_changed = int(np.count_nonzero(changed))
        if n_changed == 0:
            self.cells_recomputed = 0
            return self.frame
        self._last_y[...] = y
        if self._corrected:  # cells without components show their mean again
            self._corrected = False
            z = self._zero_cells
            self._cells_view[self._cell_y[z], :, self._cell_x[z]] = self.mean[z].reshape(
                -1, self.cell_shape[0], self.cell_shape[1], 3)
        np.multiply(y, self.scales, out=self._w)
        if self._pool is not None and n_changed > 1:
            future = self._pool.submit(self._run, self._workers[1], changed)
            done = self._run(self._workers[0], changed) + future.result()
        else:
            done = sum(self._run(worker, changed) for worker in self._workers)
        # counted where the work is done, so the instrumentation cannot drift from it
        self.cells_recomputed = done
        self.total_cells_recomputed += done
        if self._needs_crop:
            height, width = self.image_shape
            self.frame[...] = self._padded[:height, :width]
        return self.frame

    def correct(self, delta: np.ndarray, synth: np.ndarray | None = None) -> np.ndarray:
        """The frame ``synth`` corrected by ``delta``: per cell ``c`` whose slice of
        ``delta`` is not all zero, ``clip(rint(synth_c + sum_j delta_j * scales[j] *
        E[j]))``; the other cells show ``synth`` unchanged. Then the correction's jump
        across each cell border is smoothed (`seam_strength`): with ``D = frame - synth``,
        the pixels ``p | q`` either side of a border move by ``j ~ seam_strength / 3 * (D_q -
        D_p)`` towards each other (vertical borders, then horizontal; `_SeamStrips` has the
        exact integer rule), so a frame whose correction is zero is ``synth`` bit for bit.

        Parameters
        ----------
        delta : ndarray of shape (n_coefficients,), float32
            The correction's scores (a version-3 packet's ``q * step``).
        synth : ndarray of shape (height, width, 3), uint8, optional
            The frame to correct (the device's own synthesis of the view). Its cells are
            kept, so the next correction of the same frame may pass None.

        Returns
        -------
        ndarray of shape (height, width, 3), uint8
            The frame buffer (as `update`; the next `update` recomputes every cell).

        Raises
        ------
        ValueError
            Wrong shapes, non-finite ``delta``, or None before any ``synth``.
        """
        d = np.asarray(delta, dtype=np.float32)
        if d.shape != (self.n_coefficients,):
            raise ValueError(f"Reconstructor.correct: delta must have shape "
                             f"({self.n_coefficients},), got {d.shape}")
        if not np.all(np.isfinite(d)):
            raise ValueError("Reconstructor.correct: delta has NaN or infinite entries")
        height, width = self.image_shape
        if synth is not None:
            s = np.asarray(synth)
            if s.shape != (height, width, 3) or s.dtype != np.uint8:
                raise ValueError(f"Reconstructor.correct: synth must be uint8 of shape "
                                 f"{(height, width, 3)}, got {s.dtype} {s.shape}")
            if self._held is None:
                self._held = np.empty_like(self._padded)
            self._padded[:height, :width] = s
            np.copyto(self._held, self._padded)
            if self._seams is not None:
                for strips in self._seams:
                    strips.held = False  # a new frame: its jumps at the borders change
        elif self._held is None:
            raise ValueError("Reconstructor.correct: no synthesized frame to correct yet")
        else:
            np.copyto(self._padded, self._held)
        self._last_y[...] = np.nan  # the buffer holds no reconstruction of any scores now
        self._corrected = True
        np.multiply(d, self.scales, out=self._w)
        self._nz = sparse = _Sparse.of(self._w, self.offsets, self.grid_shape[1], self._cum)
        changed = sparse.changed  # the other cells: w = 0, base + 0 = base
        try:
            if self._pool is not None and np.count_nonzero(changed) > 1:
                future = self._pool.submit(self._run, self._workers[1], changed)
                done = self._run(self._workers[0], changed) + future.result()
            else:
                done = sum(self._run(worker, changed) for worker in self._workers)
        finally:
            self._nz = None
        self.cells_recomputed = done
        self.total_cells_recomputed += done
        if self.seam_strength and done:
            self._smooth_seams(changed)
        if self._needs_crop:
            self.frame[...] = self._padded[:height, :width]
        return self.frame

    def _smooth_seams(self, changed: np.ndarray) -> None:
        """Reduce the correction's jump at every cell border (`correct`); reads and writes
        only the two pixel strips at each border, and only within the box of cells the
        correction changed (plus the neighbours the first direction touched): elsewhere the
        jump is the frame's own and nothing moves."""
        if not 0.0 <= self.seam_strength <= 0.75:
            raise ValueError(f"Reconstructor: seam_strength={self.seam_strength!r} must be "
                             "between 0 and 0.75")
        ny, nx = self.grid_shape
        frame = self._cells_view  # (ny, cell_h, nx, cell_w, 3)
        base = self._held.reshape(frame.shape)
        grid = changed.reshape(ny, nx)
        rows, cols = np.flatnonzero(grid.any(axis=1)), np.flatnonzero(grid.any(axis=0))
        r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
        sides = []
        if nx > 1:  # vertical borders: a cell's last column | the next cell's first
            sides.append(((slice(None), slice(None), slice(None, -1), -1),
                          (slice(None), slice(None), slice(1, None), 0),
                          (slice(r0, r1), slice(None), slice(max(c0 - 1, 0), min(c1, nx - 1)))))
        if ny > 1:  # horizontal borders: a cell's last row | the next cell's first
            sides.append(((slice(None, -1), -1), (slice(1, None), 0),
                          (slice(max(r0 - 1, 0), min(r1, ny - 1)),
                           slice(max(c0 - 1, 0), min(c1 + 1, nx)))))
        if self._seams is None:
            self._seams = [_SeamStrips(frame[p].shape) for p, _q, _box in sides]
        weight = round(256 * self.seam_strength / 3)
        for strips, (p, q, box) in zip(self._seams, sides):
            if not strips.held:
                np.subtract(base[q], base[p], out=strips.base_jump, dtype=np.int16)
                strips.held = True
            strips.soften(frame[p][box], frame[q][box], strips.base_jump[box], weight)

    def _run(self, worker: _Worker, changed: np.ndarray) -> int:
        """Run a worker's jobs for the changed cells (`update`: its groups; `correct`: its
        batches); return how many cells it computed."""
        done = 0
        correcting = self._nz is not None
        for job in worker.jobs if correcting else worker.groups:
            if isinstance(job, _BigCell):
                if changed[job.cell]:
                    self._run_big(job)
                    done += 1
            elif correcting:
                done += self._correct_batch(job, changed[job.start : job.stop])
            else:
                done += self._run_cells(job, changed[job.start : job.stop])
        return done

    def _run_cells(self, job: _Cells, flags: np.ndarray) -> int:
        """The cells of ``job`` whose ``flags`` are set: each one blended on its own
        (`_blend_cells`) into consecutive output rows, then all written at once."""
        cells = np.flatnonzero(flags)
        n = cells.size
        if n == 0:
            return 0
        self._blend_cells(job, cells.tolist())
        cells += job.start
        self._write_cells(job.out[:n], cells, (self._cell_y[cells], self._cell_x[cells]))
        return n

    @staticmethod
    def _blend_cells(job: _Cells, positions: list[int]) -> None:
        """Output row ``i`` of ``job``: ``w_c @ E_c`` of the cell ``job.start +
        positions[i]``, its int8 rows cast into the first rows of the cast area (small
        enough to stay in the CPU's cache for the product that reads them back) and one BLAS
        product (`numpy.dot`: less overhead than `numpy.matmul`, the same call); a cell of
        one component is the product ``w_0 * E_0`` that BLAS would compute."""
        outs, calls = job.outs, job.calls
        for i, p in enumerate(positions):
            k, rows, w, cast = calls[p]
            if k == 1:  # float32 math whatever numpy's promotion of an int8 row and a scalar
                np.multiply(rows[0], w[0], out=outs[i], dtype=np.float32)
            else:
                np.copyto(cast, rows, casting="unsafe")
                np.dot(w, cast, out=outs[i])

    def _correct_batch(self, job: _Batch, flags: np.ndarray) -> int:
        """`correct` on one batch: the cells whose ``delta`` is not all zero get ``base +
        sum_j w_j E_j`` over their non-zero coefficients only. Those rows are gathered
        (`GATHER_ROW_COST` each) unless blending the corrected cells' rows whole costs less
        (`_run_cells`)."""
        sp = self._nz
        lo, hi = sp.cum_nz[job.start], sp.cum_nz[job.stop]
        n = hi - lo
        if n == 0:
            return 0
        if n * GATHER_ROW_COST >= job.row_stop - job.row_start:
            # the changed cells' rows whole (w is 0 elsewhere); the others keep their pixels
            return self._run_cells(job, flags)
        values = self.cell_values
        flat = job.cast_dst.reshape(-1)
        rows = flat[: n * values].reshape(n, values)
        # the int8 rows land just past the float32 ones (n <= rows / GATHER_ROW_COST: room)
        raw = flat[n * values : n * values + -(-n * values // _FLOAT_BYTES)].view(np.int8)
        raw = raw[: n * values].reshape(n, values)
        # mode="clip": the indices are valid, and "raise" buffers ``out`` (twice the time)
        np.take(self.eigenimages, sp.nz[lo:hi], axis=0, out=raw, mode="clip")
        np.copyto(rows, raw, casting="unsafe")
        w = sp.w[lo:hi]
        a, b = sp.cum_cells[job.start], sp.cum_cells[job.stop]
        out = job.out[: b - a]
        pos = 0
        for i, k in enumerate(sp.counts[a:b]):
            if k == 1:
                np.multiply(rows[pos], w[pos], out=out[i])
            else:
                np.dot(w[pos : pos + k], rows[pos : pos + k], out=out[i])
            pos += k
        self._write_cells(out, None, (sp.cell_y[a:b], sp.cell_x[a:b]))
        return b - a

    def _write_cells(self, out: np.ndarray, cells: Any,
                     where: tuple[np.ndarray, np.ndarray]) -> None:
        """``out`` (one row per cell) plus those cells' means (`correct`: the pixels they
        hold, the frame to correct), rounded and clipped, into the frame buffer at grid
        positions ``where``."""
        if self._nz is None:
            np.add(out, self.mean[cells], out=out)
        else:
            base = self._cells_view[where[0], :, where[1]]
            np.add(out, base.reshape(out.shape), out=out)
        self._finish(out)
        self._cells_view[where[0], :, where[1]] = out.reshape(
            -1, self.cell_shape[0], self.cell_shape[1], 3)

    def _run_big(self, job: _BigCell) -> None:
        c = job.cell
        cell = self._cells_view[self._cell_y[c], :, self._cell_x[c]]  # (cell_h, cell_w, 3)
        scratch = job.scratch
        for tile in job.tiles:
            width = tile.col_stop - tile.col_start
            out = scratch[:width]
            acc = scratch[width : 2 * width]
            first = True
            for r0 in range(job.row_start, job.row_stop, job.chunk):
                r1 = min(job.row_stop, r0 + job.chunk)
                dst = scratch[2 * width : 2 * width + (r1 - r0) * width].reshape(r1 - r0, width)
                np.copyto(
                    dst, self.eigenimages[r0:r1, tile.col_start : tile.col_stop], casting="unsafe"
                )
                if first:
                    np.matmul(self._w[r0:r1], dst, out=out)
                    first = False
                else:
                    np.matmul(self._w[r0:r1], dst, out=acc)
                    out += acc
            if self._nz is None:
                np.add(out, self.mean[c, tile.col_start : tile.col_stop], out=out)
            else:  # `correct`: the pixels the cell holds
                np.add(out, cell[tile.y0 : tile.y1].reshape(-1), out=out)
            self._finish(out)
            cell[tile.y0 : tile.y1] = out.reshape(tile.y1 - tile.y0, self.cell_shape[1], 3)

    @staticmethod
    def _finish(x: np.ndarray) -> None:
        np.rint(x, out=x)
        np.clip(x, 0.0, 255.0, out=x)

    def close(self) -> None:
        """Stop the helper thread (if any)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def __del__(self) -> None:  # pragma: no cover - best effort
        pool = getattr(self, "_pool", None)
        if pool is not None:
            pool.shutdown(wait=False)


def usable_cpus() -> int:
    """The CPUs this process may run on (its affinity, e.g. ``taskset -c 0``: 1), else the
    machine's count."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        return os.cpu_count() or 1


def reconstruction_memory_bytes(
    image_shape: tuple[int, int],
    cell_shape: tuple[int, int],
    n_coefficients: int,
    *,
    scratch_bytes: int = DEFAULT_SCRATCH_BYTES,
) -> int:
    """Estimate the RAM a `Reconstructor` needs (arrays + frame buffers + scratch), in bytes.

    The eigenspace arrays (int8 eigenimages, uint8 mean, float32 scales) dominate; the device
    compares this figure with its declared RAM budget.
    """
    height, width = image_shape
    cell_h, cell_w = cell_shape
    ny, nx = -(-height // cell_h), -(-width // cell_w)
    values = cell_h * cell_w * 3
    padded = ny * cell_h * nx * cell_w * 3
    crop = height * width * 3 if padded != height * width * 3 else 0
    arrays = n_coefficients * values + ny * nx * values + 4 * n_coefficients
    vectors = (4 + 4 + 4 + 8) * n_coefficients + 8 * 4 * (ny * nx + 1)
    return int(arrays + padded + crop + vectors + scratch_bytes)


def reconstruct_view(image: Any, y: np.ndarray) -> np.ndarray:
    """One-shot reconstruction of ``y`` with an `EigenspaceImage` (returns a new array)."""
    return Reconstructor.from_image(image).update(y).copy()



class _SeamStrips:
    """Scratch for one direction of `Reconstructor._smooth_seams`: the pixel strips either
    side of its borders (int16, contiguous) and the base frame's jump across them (held
    until the next frame to correct)."""

    def __init__(self, shape: tuple[int, ...]) -> None:
        size = int(np.prod(shape))
        self.p = np.empty(size, dtype=np.int16)
        self.q = np.empty(size, dtype=np.int16)
        self.jump = np.empty(size, dtype=np.int16)
        self.base_jump = np.empty(shape, dtype=np.int16)
        self.held = False

    def soften(self, p: np.ndarray, q: np.ndarray, base_jump: np.ndarray, weight: int) -> None:
        """In place on the uint8 strips ``p | q`` (a box of them): with the correction's
        jump ``J = (q - p) - base_jump`` and ``j = (J * weight + 128) >> 8`` (``weight / 256``
        of it, rounded), ``p += j`` and ``q -= j``, clipped to 0..255. ``|J| * weight`` fits
        int16 for ``weight <= 64``."""
        size = p.size
        sp, sq, j = (a[:size].reshape(p.shape) for a in (self.p, self.q, self.jump))
        np.copyto(sp, p)
        np.copyto(sq, q)
        np.subtract(sq, sp, out=j)
        j -= base_jump
        j *= weight
        j += 128
        j >>= 8
        sp += j
        sq -= j
        for a in (sp, sq):  # clipped to 0..255 (np.clip's checks cost 3x the arithmetic)
            np.maximum(a, 0, out=a)
            np.minimum(a, 255, out=a)
        np.copyto(p, sp, casting="unsafe")
        np.copyto(q, sq, casting="unsafe")
