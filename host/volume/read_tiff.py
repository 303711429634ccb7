"""TIFF stacks through tifffile: one multi-page file or a folder of single-page files."""

from __future__ import annotations

import contextlib
import logging
import re
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from host.volume.core import (
    _fail,
    _Loaded,
    _one_line,
)

_LENGTH_UNITS_MM = {
    "nm": 1e-6,
    "nanometer": 1e-6,
    "micron": 1e-3,
    "um": 1e-3,
    "\u00b5m": 1e-3,
    "\\u00b5m": 1e-3,
    "micrometer": 1e-3,
    "mm": 1.0,
    "millimeter": 1.0,
    "cm": 10.0,
    "centimeter": 10.0,
    "m": 1000.0,
    "meter": 1000.0,
}


def _tiff_pixel_size_mm(page: object, imagej: dict | None) -> tuple[float, float] | None:
    """(sx, sy) in mm from resolution tags, when they mean a physical size."""
    tags = page.tags  # type: ignore[attr-defined]

    def res(tag: str) -> float | None:
        if tag not in tags:
            return None
        value = tags[tag].value
        num, den = value if isinstance(value, tuple) else (value, 1)
        return float(num) / float(den) if den else None

    xres, yres = res("XResolution"), res("YResolution")
    if not xres or not yres:
        return None
    unit_tag = int(tags["ResolutionUnit"].value) if "ResolutionUnit" in tags else 2
    if imagej and str(imagej.get("unit", "")).lower() in _LENGTH_UNITS_MM:
        factor = _LENGTH_UNITS_MM[str(imagej["unit"]).lower()]
        return factor / xres, factor / yres
    if unit_tag == 3:  # centimetre
        return 10.0 / xres, 10.0 / yres
    return None  # NONE, or INCH: print DPI (72/96/300), not a voxel size


@contextlib.contextmanager
def _tifffile_messages() -> Iterator[list[str]]:
    """Collect what tifffile logs or warns while reading, instead of stray stderr lines.

    Yields the list that receives the text of every ERROR-level log record (a broken page
    chain, as in a truncated file: the one thing worth folding into the error); warnings
    are dropped.
    """
    logger = logging.getLogger("tifffile")
    errors: list[str] = []

    class _Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if record.levelno >= logging.ERROR:
                errors.append(re.sub(r"^<[^>]*>\s*", "", record.getMessage()))

    handler = _Keep(logging.DEBUG)
    propagate = logger.propagate
    logger.addHandler(handler)
    logger.propagate = False
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield errors
    finally:
        logger.removeHandler(handler)
        logger.propagate = propagate


def _tiff_problem(exc: BaseException | None, errors: list[str]) -> str:
    parts = ([_one_line(exc)] if exc is not None else []) + errors[:1]
    return "; ".join(dict.fromkeys(parts)) + ("" if exc is not None else " (truncated or damaged)")


def _load_tiff(path: Path) -> _Loaded:
    import tifffile

    with _tifffile_messages() as errors:
        try:
            with tifffile.TiffFile(path) as tif:
                series = tif.series[0]
                axes = series.axes
                data = series.asarray()
                imagej = tif.imagej_metadata
                pixel_mm = _tiff_pixel_size_mm(tif.pages[0], imagej)
        except (tifffile.TiffFileError, ValueError, KeyError, IndexError, EOFError) as exc:
            raise _fail(path, f"cannot read TIFF: {_tiff_problem(exc, errors)}") from None
        except OSError as exc:
            raise _fail(path, f"cannot read TIFF: {exc.strerror or _one_line(exc)}") from None
    if errors:  # read, but tifffile found the page chain broken: pages may be missing
        raise _fail(path, f"cannot read TIFF: {_tiff_problem(None, errors)}")
    for ax in ("S", "C"):
        if ax in axes and data.shape[axes.index(ax)] > 1:
            raise _fail(path, f"TIFF has {data.shape[axes.index(ax)]} channels: only greyscale")
    squeeze = tuple(i for i, n in enumerate(data.shape) if n == 1)
    data = np.squeeze(data, axis=squeeze) if squeeze and data.ndim > 3 else data
    if data.ndim != 3:
        raise _fail(
            path,
            f"TIFF holds an array of shape {data.shape} (axes {axes}); "
            "a volume needs a multi-page stack (pages = z)",
        )
    return _tiff_result(data, pixel_mm, imagej, "tiff", {"tiff_axes": axes})


def _tiff_result(
    data: np.ndarray,
    pixel_mm: tuple[float, float] | None,
    imagej: dict | None,
    fmt: str,
    extra: dict,
) -> _Loaded:
    sp: tuple[float, ...] = (1.0, 1.0, 1.0)
    if pixel_mm is not None:
        factor = _LENGTH_UNITS_MM.get(str((imagej or {}).get("unit", "")).lower())
        if imagej and "spacing" in imagej and factor:
            sz = float(imagej["spacing"]) * factor
        else:
            sz = float(np.mean(pixel_mm))
            extra["z_spacing"] = "assumed equal to the pixel size"
        sp = (pixel_mm[0], pixel_mm[1], sz)
    return _Loaded(data, sp, fmt, extra=extra)


def _natural_key(path: Path) -> list[object]:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", path.name)]


def _load_tiff_folder(path: Path) -> _Loaded:
    import tifffile

    files = sorted(
        (p for p in path.iterdir() if p.suffix.lower() in (".tif", ".tiff")), key=_natural_key
    )
    slices = []
    pixel_mm = None
    for i, p in enumerate(files):
        with _tifffile_messages() as errors:
            try:
                with tifffile.TiffFile(p) as tif:
                    page = tif.series[0].asarray()
                    if i == 0:
                        pixel_mm = _tiff_pixel_size_mm(tif.pages[0], tif.imagej_metadata)
            except (tifffile.TiffFileError, ValueError, KeyError, IndexError, EOFError) as exc:
                raise _fail(p, f"cannot read TIFF slice: {_tiff_problem(exc, errors)}") from None
            except OSError as exc:
                raise _fail(
                    p, f"cannot read TIFF slice: {exc.strerror or _one_line(exc)}"
                ) from None
        if errors:
            raise _fail(p, f"cannot read TIFF slice: {_tiff_problem(None, errors)}")
        page = np.squeeze(page)
        if page.ndim != 2:
            raise _fail(p, f"TIFF slice has shape {page.shape}: expected one greyscale page")
        if slices and page.shape != slices[0].shape:
            raise _fail(
                p, f"slice is {page.shape}, the first slice {files[0].name} is {slices[0].shape}"
            )
        slices.append(page)
    if len(slices) < 2:
        raise _fail(path, f"folder holds {len(slices)} TIFF slice(s); a volume needs 2 or more")
    extra = {"slices": len(slices)}
    return _tiff_result(np.stack(slices), pixel_mm, None, "tiff-folder", extra)
