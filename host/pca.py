"""Cell eigenspaces: standard, cell and adaptive-cell PCA of training images.

The data model (authoritative, shared with ``host/quantize.py``,
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

import hashlib
import json
import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from numbers import Integral, Real
from pathlib import Path
from typing import Any

import numpy as np
import scipy.linalg

from host.errors import EigencastError, FitError
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
    "CellStack",
    "InvalidParameterError",
    "NotFittedError",
    "cell_grid",
    "merge_cells",
    "split_cells",
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

_STACK_FORMAT = "eigencast-cellstack"
_STACK_VERSION = 1
_STACK_BUFFER_BYTES = 64 * 2**20
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
# cell layout helpers


def cell_grid(image_shape: tuple[int, int], cell_shape: tuple[int, int]) -> tuple[int, int]:
    """Return ``(n_cells_y, n_cells_x)`` for an image cut into cells (with zero padding).

    Parameters
    ----------
    image_shape : (int, int)
        ``(height, width)`` in pixels.
    cell_shape : (int, int)
        ``(cell_h, cell_w)`` in pixels.
    """
    return (-(-image_shape[0] // cell_shape[0]), -(-image_shape[1] // cell_shape[1]))


def split_cells(images: np.ndarray, cell_shape: tuple[int, int]) -> np.ndarray:
    """Cut images into cell vectors (zero padding at the bottom/right).

    Parameters
    ----------
    images : ndarray of shape (n_views, height, width, 3)
        Any dtype; the output keeps it.
    cell_shape : (int, int)
        ``(cell_h, cell_w)`` in pixels.

    Returns
    -------
    cells : ndarray of shape (n_views, n_cells, cell_h * cell_w * 3)
        Cells in row-major order; within a cell (row, col, channel) order.
    """
    n, h, w, ch = images.shape
    ch_, cw = cell_shape
    ny, nx = cell_grid((h, w), cell_shape)
    hp, wp = ny * ch_, nx * cw
    if (hp, wp) != (h, w):
        padded = np.zeros((n, hp, wp, ch), dtype=images.dtype)
        padded[:, :h, :w] = images
        images = padded
    cells = images.reshape(n, ny, ch_, nx, cw, ch).transpose(0, 1, 3, 2, 4, 5)
    return cells.reshape(n, ny * nx, ch_ * cw * ch)


def merge_cells(
    cells: np.ndarray, image_shape: tuple[int, int], cell_shape: tuple[int, int]
) -> np.ndarray:
    """Inverse of `split_cells`: assemble cell vectors into cropped images.

    Parameters
    ----------
    cells : ndarray of shape (n_views, n_cells, cell_h * cell_w * 3)
    image_shape : (int, int)
        ``(height, width)`` of the output (the padding is cropped).
    cell_shape : (int, int)
        ``(cell_h, cell_w)``.

    Returns
    -------
    images : ndarray of shape (n_views, height, width, 3), same dtype as ``cells``
    """
    n = cells.shape[0]
    ch_, cw = cell_shape
    ny, nx = cell_grid(image_shape, cell_shape)
    img = cells.reshape(n, ny, nx, ch_, cw, 3).transpose(0, 1, 3, 2, 4, 5)
    img = img.reshape(n, ny * ch_, nx * cw, 3)
    return np.ascontiguousarray(img[:, : image_shape[0], : image_shape[1]])


# --------------------------------------------------------------------------
# CellStack: the cell-major training data


class CellStack:
    """Training images laid out cell-major: ``(n_cells, n_views, cell_size)`` uint8.

    Every cell's training data is one contiguous block, so fitting reads one
    cell (or a batch of cells) at a time. Build it once from an image iterator
    with `CellStack.build` (a flat file plus a JSON sidecar ``PATH.json`` that
    records shape, layout and the caller's source fingerprint), reopen it with
    `CellStack.open`, or wrap in-memory images with `CellStack.from_array`
    (small data, tests).

    Attributes
    ----------
    n_views : int
    image_shape : (int, int)
        ``(height, width)`` of the (unpadded) images.
    cell_shape : (int, int)
    grid_shape : (int, int)
        ``(n_cells_y, n_cells_x)``.
    n_cells : int
    cell_size : int
        ``cell_h * cell_w * 3``, the length of one cell vector.
    path : Path or None
        The data file, or None for an in-memory stack.
    reused : bool
        True when `build` found a matching file and did not rebuild it.
    """

    def __init__(
        self,
        n_views: int,
        image_shape: tuple[int, int],
        cell_shape: tuple[int, int],
        *,
        path: Path | None = None,
        array: np.ndarray | None = None,
        reused: bool = False,
    ):
        self.n_views = int(n_views)
        self.image_shape = (int(image_shape[0]), int(image_shape[1]))
        self.cell_shape = (int(cell_shape[0]), int(cell_shape[1]))
        self.grid_shape = cell_grid(self.image_shape, self.cell_shape)
        self.n_cells = self.grid_shape[0] * self.grid_shape[1]
        self.cell_size = self.cell_shape[0] * self.cell_shape[1] * 3
        self.path = None if path is None else Path(path)
        self._array = array
        self.reused = reused

    def __repr__(self) -> str:
        where = str(self.path) if self.path is not None else "in memory"
        return (
            f"CellStack(n_views={self.n_views}, image_shape={self.image_shape}, "
            f"cell_shape={self.cell_shape}, {where})"
        )

    @property
    def size_bytes(self) -> int:
        """Size of the whole cell-major array in bytes."""
        return self.n_cells * self.n_views * self.cell_size

    # ---------------------------------------------------------------- creation

    @classmethod
    def from_array(cls, images: np.ndarray, cell_shape: tuple[int, int]) -> CellStack:
        """Wrap in-memory images (copied into the cell-major layout).

        Parameters
        ----------
        images : ndarray of shape (n_views, height, width, 3), uint8
        cell_shape : (int, int)
            ``(cell_h, cell_w)``.
        """
        _check_images(images, "images")
        _check_cell_shape(cell_shape, images.shape[1:3])
        cells = split_cells(images, cell_shape)  # (n, n_cells, d)
        array = np.ascontiguousarray(cells.transpose(1, 0, 2))
        return cls(images.shape[0], images.shape[1:3], cell_shape, array=array)

    @classmethod
    def build(
        cls,
        images: Iterable[np.ndarray],
        n_views: int,
        height: int,
        width: int,
        cell_h: int,
        cell_w: int,
        path: str | os.PathLike,
        *,
        source: str | None = None,
        progress: bool = True,
        buffer_bytes: int = _STACK_BUFFER_BYTES,
    ) -> CellStack:
        """Write images cell-major to ``path`` (or reuse a matching file there).

        Parameters
        ----------
        images : iterable of ndarray of shape (height, width, 3), uint8
            The training views in order; consumed only when a (re)build is
            needed, so pass a lazy generator.
        n_views, height, width : int
            Expected count and size of the images.
        cell_h, cell_w : int
            Cell size in pixels (``height, width`` for the standard method).
        path : path-like
            The data file; its sidecar header is ``PATH.json``.
        source : str, optional
            Fingerprint of the image source (e.g. from `fingerprint_files`).
            An existing file is reused only when its header records the same
            shape, layout and fingerprint; without a fingerprint the file is
            always rebuilt.
        progress : bool
            Report progress (views written / total) on stderr.
        buffer_bytes : int
            Bound of the image buffer: views are gathered in groups so that
            each cell receives one contiguous write per group.

        Returns
        -------
        CellStack
            Backed by the file; ``reused`` says whether it was rebuilt.

        Raises
        ------
        FitError
            An image has the wrong shape or dtype, the iterator yields a
            different number of images than ``n_views``, or the file cannot be
            written.
        """
        for name, value in (
            ("n_views", n_views),
            ("height", height),
            ("width", width),
            ("cell_h", cell_h),
            ("cell_w", cell_w),
        ):
            if not isinstance(value, Integral) or isinstance(value, bool) or value < 1:
                raise FitError(f"CellStack.build: {name}={value!r} must be a positive integer")
        _check_cell_shape((cell_h, cell_w), (height, width))
        path = Path(path)
        header = cls._header(n_views, (height, width), (cell_h, cell_w), source)
        sidecar = _sidecar(path)
        if source is not None:
            try:
                existing = cls.open(path)
            except FitError:
                existing = None
            if existing is not None and _read_json(sidecar) == header:
                existing.reused = True
                return existing
        stack = cls(n_views, (height, width), (cell_h, cell_w), path=path)
        stack._write(images, header, progress=progress, buffer_bytes=buffer_bytes)
        return stack

    @classmethod
    def open(cls, path: str | os.PathLike) -> CellStack:
        """Open an existing cell stack, checking its header against the file.

        Raises
        ------
        FitError
            The file or its ``PATH.json`` header is missing, malformed, or the
            file size does not match the header.
        """
        path = Path(path)
        sidecar = _sidecar(path)
        if not sidecar.is_file():
            raise FitError(f"cell stack {path}: header {sidecar.name} is missing (not built?)")
        header = _read_json(sidecar)
        if not isinstance(header, dict) or header.get("format") != _STACK_FORMAT:
            raise FitError(f"cell stack {path}: {sidecar.name} is not a cell stack header")
        if header.get("version") != _STACK_VERSION:
            raise FitError(
                f"cell stack {path}: header version {header.get('version')!r} is not "
                f"supported (supported: {_STACK_VERSION}); rebuild it"
            )
        try:
            n_views = int(header["n_views"])
            image_shape = (int(header["height"]), int(header["width"]))
            cell_shape = (int(header["cell_h"]), int(header["cell_w"]))
            size_bytes = int(header["size_bytes"])
        except (KeyError, TypeError, ValueError) as exc:
            raise FitError(f"cell stack {path}: header field missing or bad: {exc}") from None
        if min(n_views, *image_shape, *cell_shape) < 1:
            raise FitError(f"cell stack {path}: header has non-positive sizes")
        stack = cls(n_views, image_shape, cell_shape, path=path)
        if stack.size_bytes != size_bytes:
            raise FitError(
                f"cell stack {path}: header size {size_bytes} bytes does not match its "
                f"shape ({stack.size_bytes} bytes)"
            )
        try:
            actual = path.stat().st_size
        except OSError as exc:
            raise FitError(f"cell stack {path}: {exc.strerror or exc}") from None
        if actual != size_bytes:
            raise FitError(
                f"cell stack {path}: file has {actual} bytes, header says {size_bytes}; rebuild it"
            )
        return stack

    @staticmethod
    def fingerprint_files(paths: Sequence[str | os.PathLike], extra: str = "") -> str:
        """A cheap fingerprint of source files: names, sizes and modification times.

        Use it as ``source=`` of `build` so an edited or re-rendered database
        triggers a rebuild.
        """
        h = hashlib.sha256(extra.encode())
        for p in paths:
            st = os.stat(p)
            h.update(f"{os.fspath(p)}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
        return h.hexdigest()

    @staticmethod
    def _header(
        n_views: int,
        image_shape: tuple[int, int],
        cell_shape: tuple[int, int],
        source: str | None,
    ) -> dict:
        ny, nx = cell_grid(image_shape, cell_shape)
        d = cell_shape[0] * cell_shape[1] * 3
        return {
            "format": _STACK_FORMAT,
            "version": _STACK_VERSION,
            "layout": "cell-major (n_cells, n_views, cell_size), row-major cells",
            "dtype": "uint8",
            "n_views": int(n_views),
            "height": int(image_shape[0]),
            "width": int(image_shape[1]),
            "cell_h": int(cell_shape[0]),
            "cell_w": int(cell_shape[1]),
            "n_cells_y": ny,
            "n_cells_x": nx,
            "cell_size": d,
            "size_bytes": ny * nx * int(n_views) * d,
            "source": source,
        }

    def _write(
        self, images: Iterable[np.ndarray], header: dict, *, progress: bool, buffer_bytes: int
    ) -> None:
        path = self.path
        assert path is not None
        sidecar = _sidecar(path)
        tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
        n, (h, w) = self.n_views, self.image_shape
        ny, nx = self.grid_shape
        hp, wp = ny * self.cell_shape[0], nx * self.cell_shape[1]
        group = max(1, min(n, buffer_bytes // max(1, 2 * hp * wp * 3)))
        buf = np.zeros((group, hp, wp, 3), dtype=np.uint8)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            sidecar.unlink(missing_ok=True)  # an interrupted rebuild leaves no valid header
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        except OSError as exc:
            raise FitError(f"cell stack {path}: cannot write: {exc.strerror or exc}") from None
        ok = False
        try:
            os.ftruncate(fd, self.size_bytes)
            count = 0
            filled = 0
            with _progress("building cell stack", n, unit=" views", quiet=not progress) as p:
                for image in images:
                    if count >= n:
                        raise FitError(
                            f"cell stack {path}: the image source yields more than "
                            f"n_views={n} images"
                        )
                    if (
                        not isinstance(image, np.ndarray)
                        or image.dtype != np.uint8
                        or image.shape != (h, w, 3)
                    ):
                        got = (
                            f"{image.dtype} {image.shape}"
                            if isinstance(image, np.ndarray)
                            else type(image).__name__
                        )
                        raise FitError(
                            f"cell stack {path}: view {count} is {got}; expected uint8 "
                            f"({h}, {w}, 3)"
                        )
                    buf[filled, :h, :w] = image
                    filled += 1
                    count += 1
                    if filled == group:
                        self._flush(fd, buf, count - filled, filled)
                        filled = 0
                    p.advance()
                if filled:
                    self._flush(fd, buf, count - filled, filled)
            if count != n:
                raise FitError(
                    f"cell stack {path}: the image source yielded {count} images, "
                    f"expected n_views={n}"
                )
            os.fsync(fd)
            ok = True
        except OSError as exc:
            raise FitError(f"cell stack {path}: write failed: {exc.strerror or exc}") from None
        finally:
            os.close(fd)
            if not ok:
                tmp.unlink(missing_ok=True)
        try:
            os.replace(tmp, path)
            side_tmp = sidecar.with_name(f"{sidecar.name}.tmp-{os.getpid()}")
            side_tmp.write_text(json.dumps(header, indent=1) + "\n")
            os.replace(side_tmp, sidecar)
        except OSError as exc:
            raise FitError(f"cell stack {path}: cannot finish: {exc.strerror or exc}") from None

    def _flush(self, fd: int, buf: np.ndarray, first_view: int, count: int) -> None:
        cells = split_cells(buf[:count], self.cell_shape)  # view (count, n_cells, d)
        d = self.cell_size
        for c in range(self.n_cells):
            block = np.ascontiguousarray(cells[:, c, :])
            offset = (c * self.n_views + first_view) * d
            _pwrite_all(fd, block, offset)

    # ---------------------------------------------------------------- reading

    def read_cells(self, start: int, stop: int) -> np.ndarray:
        """Read whole cells ``start..stop-1``.

        Returns
        -------
        ndarray of shape (stop - start, n_views, cell_size), uint8
        """
        if self._array is not None:
            return self._array[start:stop]
        d, n = self.cell_size, self.n_views
        out = np.empty((stop - start, n, d), dtype=np.uint8)
        with self._fd() as fd:
            _pread_into(fd, out.reshape(-1), start * n * d, self.path)
        return out

    def read_block(self, cell: int, rows: slice, cols: slice) -> np.ndarray:
        """Read part of one cell's data.

        Parameters
        ----------
        cell : int
        rows : slice
            Views (contiguous, step 1).
        cols : slice
            Entries of the cell vector (contiguous, step 1).

        Returns
        -------
        ndarray of shape (n_rows, n_cols), uint8
        """
        r0, r1, _ = rows.indices(self.n_views)
        c0, c1, _ = cols.indices(self.cell_size)
        if self._array is not None:
            return self._array[cell, r0:r1, c0:c1]
        d, n = self.cell_size, self.n_views
        out = np.empty((r1 - r0, c1 - c0), dtype=np.uint8)
        base = cell * n * d
        with self._fd() as fd:
            if c0 == 0 and c1 == d:
                _pread_into(fd, out.reshape(-1), base + r0 * d, self.path)
            else:
                for i, r in enumerate(range(r0, r1)):
                    _pread_into(fd, out[i], base + r * d + c0, self.path)
        return out

    def memmap(self) -> np.ndarray:
        """The whole stack as a read-only array ``(n_cells, n_views, cell_size)`` uint8."""
        if self._array is not None:
            return self._array
        return np.memmap(
            self.path, dtype=np.uint8, mode="r", shape=(self.n_cells, self.n_views, self.cell_size)
        )

    def _fd(self) -> _Fd:
        return _Fd(self.path)


class _Fd:
    def __init__(self, path: Path | None):
        self.path = path

    def __enter__(self) -> int:
        try:
            self.fd = os.open(self.path, os.O_RDONLY)
        except OSError as exc:
            raise FitError(f"cell stack {self.path}: cannot read: {exc.strerror or exc}") from None
        return self.fd

    def __exit__(self, *exc: object) -> None:
        os.close(self.fd)


def _sidecar(path: Path) -> Path:
    return path.with_name(path.name + ".json")


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise FitError(f"cell stack header {path}: unreadable: {exc}") from None


def _pwrite_all(fd: int, block: np.ndarray, offset: int) -> None:
    view = memoryview(block).cast("B")
    while len(view):
        written = os.pwrite(fd, view, offset)
        view = view[written:]
        offset += written


def _pread_into(fd: int, out: np.ndarray, offset: int, path: Path | None) -> None:
    view = memoryview(out).cast("B")
    while len(view):
        got = os.preadv(fd, [view], offset)
        if got == 0:
            raise FitError(f"cell stack {path}: file is truncated at byte {offset}; rebuild it")
        view = view[got:]
        offset += got


def _check_images(images: Any, what: str) -> None:
    if not isinstance(images, np.ndarray):
        raise FitError(
            f"{what} must be a CellStack or an ndarray (n_views, height, width, 3) uint8, "
            f"got {type(images).__name__}"
        )
    if images.ndim != 4 or images.shape[-1] != 3 or images.dtype != np.uint8:
        raise FitError(
            f"{what} must be (n_views, height, width, 3) uint8, got {images.dtype} {images.shape}"
        )
    if min(images.shape) < 1:
        raise FitError(f"{what} is empty: shape {images.shape}")


def _check_cell_shape(cell_shape: tuple[int, int], image_shape: tuple[int, int]) -> None:
    if cell_shape[0] > image_shape[0] or cell_shape[1] > image_shape[1]:
        raise FitError(
            f"cell {cell_shape[0]}x{cell_shape[1]} is larger than the image "
            f"({image_shape[0]}x{image_shape[1]}); use at most the image size"
        )


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
