"""The cell layout of training images and `CellStack`, their streamed cell-major store.

Images ``(n_views, height, width, 3)`` uint8 are cut into cells of ``cell_shape`` pixels
after zero padding at the bottom/right (`cell_grid`, `split_cells`, `merge_cells`; the data
model is in `host.fit.pca`). `CellStack` writes them cell-major to disk,
``(n_cells, n_views, cell_size)`` uint8, so `host.fit.pca.CellEigenspace` reads every cell's
training data as one contiguous block and memory does not grow with the image size.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable, Sequence
from numbers import Integral
from pathlib import Path
from typing import Any

import numpy as np

from host.errors import FitError
from host.progress import progress as _progress

__all__ = ["CellStack", "cell_grid", "merge_cells", "split_cells"]

_STACK_FORMAT = "eigencast-cellstack"
_STACK_VERSION = 1
_STACK_BUFFER_BYTES = 64 * 2**20


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

