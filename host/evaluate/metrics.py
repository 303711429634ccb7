"""Image metrics: PSNR, SSIM and FLIP, over every pixel or over the object's pixels.

Each metric takes the reference first and an explicit range, like ``skimage.metrics``:
``(image_true, image_test, *, data_range=255, mask=None)``; images are ``(height, width, 3)``
(or ``(height, width)``) in ``0..data_range``. ``mask`` (``(height, width)`` bool) restricts
the average to some pixels -- the *object pixels* of a ray-cast (alpha >= `OBJECT_ALPHA_MIN`),
so a view that is mostly black background is not flattered by it.

* `peak_signal_noise_ratio`: ``10 log10(data_range**2 / MSE)`` over every channel (scikit-image's
  ``peak_signal_noise_ratio`` without a mask; ``inf`` for identical images).
* `structural_similarity`: scikit-image's SSIM with its defaults (7x7 uniform window,
  ``data_range=255, channel_axis=-1``); with a mask, the full SSIM map (border of 3 pixels
  cropped, as scikit-image does for its mean) is averaged over the masked pixels.
* `flip_error`: NVIDIA's FLIP (``flip_evaluator``, LDR, sRGB inputs scaled to [0, 1], the
  default 67 pixels per degree); the mean of the error map, over the mask when given.
  0 is identical, 1 is the largest error.
* `blockiness`: how much more a frame changes across the borders of the eigenspace's cells
  than inside them (no reference: the ray-cast's own figure is the floor to compare with).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = [
    "HIGHER_IS_BETTER",
    "METRICS",
    "ImageComparison",
    "blockiness",
    "compare_images",
    "flip_error",
    "flip_error_map",
    "peak_signal_noise_ratio",
    "structural_similarity",
]

METRICS = ("psnr", "ssim", "flip")
#: Whether a larger value is better, per metric.
HIGHER_IS_BETTER = {"psnr": True, "ssim": True, "flip": False}
_SSIM_WIN = 7  # scikit-image's default window; its mean crops (win - 1) // 2 pixels


def _check_pair(
    image_true: Any, image_test: Any, data_range: float, mask: Any, where: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    a = np.asarray(image_true)
    b = np.asarray(image_test)
    if a.shape != b.shape:
        raise ValueError(f"{where}: image shapes differ: {a.shape} (true) vs {b.shape} (test)")
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (1, 3)):
        raise ValueError(
            f"{where}: images must be (height, width) or (height, width, 3), got {a.shape}"
        )
    if not (isinstance(data_range, (int, float)) and math.isfinite(data_range) and data_range > 0):
        raise ValueError(f"{where}: data_range={data_range!r} must be a positive number")
    for name, arr in (("image_true", a), ("image_test", b)):
        if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
            raise ValueError(f"{where}: {name} has dtype {arr.dtype}; expected real numbers")
        if arr.size and (arr.min() < 0 or arr.max() > data_range):
            raise ValueError(
                f"{where}: {name} values span [{arr.min():g}, {arr.max():g}], outside "
                f"[0, data_range={data_range:g}]"
            )
    m = None
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != a.shape[:2] or m.dtype != bool:
            raise ValueError(
                f"{where}: mask must be bool of shape {a.shape[:2]}, got {m.dtype} {m.shape}"
            )
        if not m.any():
            raise ValueError(f"{where}: mask selects no pixels")
    return a, b, m


def _psnr_from_mse(mse: float, data_range: float) -> float:
    if mse == 0.0:
        return math.inf
    return float(10.0 * math.log10(data_range**2 / mse))


def peak_signal_noise_ratio(
    image_true: Any, image_test: Any, *, data_range: float = 255, mask: Any = None
) -> float:
    """Peak signal-to-noise ratio (PSNR) in dB.

    Parameters
    ----------
    image_true, image_test : ndarray of shape (height, width[, 3])
        Reference and test image, values in ``0..data_range``.
    data_range : float
        Peak value (255 for 8-bit images).
    mask : ndarray of shape (height, width), bool, optional
        Average the squared error over these pixels (all channels) only.

    Returns
    -------
    float
        ``inf`` for identical images.
    """
    a, b, m = _check_pair(image_true, image_test, data_range, mask, "peak_signal_noise_ratio")
    if m is None:
        from skimage.metrics import peak_signal_noise_ratio as sk_psnr

        if np.array_equal(a, b):
            return math.inf
        return float(sk_psnr(a, b, data_range=data_range))
    diff = a.astype(np.float64) - b.astype(np.float64)
    sq = diff * diff
    if sq.ndim == 3:
        sq = sq.sum(axis=2) / sq.shape[2]
    return _psnr_from_mse(float(sq[m].mean(dtype=np.float64)), data_range)


def _ssim_map(a: np.ndarray, b: np.ndarray, data_range: float) -> np.ndarray:
    """scikit-image's full SSIM map, averaged over channels: float64 (height, width)."""
    from skimage.metrics import structural_similarity as sk_ssim

    if min(a.shape[:2]) < _SSIM_WIN:
        raise ValueError(
            f"structural_similarity: images of {a.shape[1]}x{a.shape[0]} are smaller than the "
            f"{_SSIM_WIN}x{_SSIM_WIN} SSIM window"
        )
    channel_axis = -1 if a.ndim == 3 else None
    _, full = sk_ssim(
        a.astype(np.float64), b.astype(np.float64), data_range=data_range,
        channel_axis=channel_axis, full=True,
    )
    return full.mean(axis=2) if full.ndim == 3 else full


def _masked_ssim(ssim_map: np.ndarray, mask: np.ndarray | None) -> float:
    pad = (_SSIM_WIN - 1) // 2
    inner = ssim_map[pad:-pad, pad:-pad]
    if mask is None:
        return float(inner.mean(dtype=np.float64))
    m = mask[pad:-pad, pad:-pad]
    if not m.any():  # the object lies in the cropped border only
        return float(ssim_map[mask].mean(dtype=np.float64))
    return float(inner[m].mean(dtype=np.float64))


def structural_similarity(
    image_true: Any, image_test: Any, *, data_range: float = 255, mask: Any = None
) -> float:
    """Mean structural similarity (SSIM), scikit-image's definition.

    Parameters
    ----------
    image_true, image_test : ndarray of shape (height, width[, 3])
        Values in ``0..data_range``; both sides at least 7 pixels.
    data_range : float
    mask : ndarray of shape (height, width), bool, optional
        Average the SSIM map over these pixels only.

    Returns
    -------
    float
        1.0 for identical images.
    """
    a, b, m = _check_pair(image_true, image_test, data_range, mask, "structural_similarity")
    return _masked_ssim(_ssim_map(a, b, data_range), m)


def flip_error_map(image_true: Any, image_test: Any, *, data_range: float = 255) -> np.ndarray:
    """Per-pixel FLIP error (LDR), float32 (height, width) in [0, 1].

    Parameters
    ----------
    image_true, image_test : ndarray of shape (height, width, 3)
        sRGB-coded colour images with values in ``0..data_range``.
    """
    a, b, _ = _check_pair(image_true, image_test, data_range, None, "flip_error")
    return _flip_map(a, b, data_range)


def _flip_map(a: np.ndarray, b: np.ndarray, data_range: float) -> np.ndarray:
    import flip_evaluator

    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"flip_error: FLIP needs (height, width, 3) colour images, got {a.shape}")
    scale = np.float32(1.0 / data_range)
    ref = np.ascontiguousarray(a, dtype=np.float32) * scale
    test = np.ascontiguousarray(b, dtype=np.float32) * scale
    error, _mean, _params = flip_evaluator.evaluate(
        ref, test, "LDR", inputsRGB=True, applyMagma=False, computeMeanError=False
    )
    return np.asarray(error, dtype=np.float32).reshape(a.shape[:2])


def flip_error(
    image_true: Any, image_test: Any, *, data_range: float = 255, mask: Any = None
) -> float:
    """Mean FLIP error (NVIDIA's perceptual difference, LDR); 0 means identical.

    Parameters
    ----------
    image_true, image_test : ndarray of shape (height, width, 3)
        sRGB-coded colour images with values in ``0..data_range``.
    data_range : float
    mask : ndarray of shape (height, width), bool, optional
        Average the error map over these pixels only.
    """
    a, b, m = _check_pair(image_true, image_test, data_range, mask, "flip_error")
    err = _flip_map(a, b, data_range)
    return float(err[m].mean(dtype=np.float64) if m is not None else err.mean(dtype=np.float64))


@dataclass(frozen=True)
class ImageComparison:
    """Metrics of one test image against one reference, whole image and object pixels.

    Attributes
    ----------
    psnr, ssim, flip : float
        Over the whole image (NaN when not computed).
    psnr_object, ssim_object, flip_object : float
        Over the mask's pixels (NaN without a mask or when it is empty).
    flip_map : ndarray of shape (height, width), float32, or None
        The FLIP error map (kept when asked for, for reports).
    """

    psnr: float = math.nan
    ssim: float = math.nan
    flip: float = math.nan
    psnr_object: float = math.nan
    ssim_object: float = math.nan
    flip_object: float = math.nan
    flip_map: np.ndarray | None = field(default=None, repr=False)

    def values(self) -> dict[str, float]:
        """``{"psnr", "ssim", "flip", "psnr_object", "ssim_object", "flip_object"}``."""
        return {
            "psnr": self.psnr,
            "ssim": self.ssim,
            "flip": self.flip,
            "psnr_object": self.psnr_object,
            "ssim_object": self.ssim_object,
            "flip_object": self.flip_object,
        }


def compare_images(
    image_true: Any,
    image_test: Any,
    *,
    data_range: float = 255,
    mask: Any = None,
    metrics: Sequence[str] = METRICS,
    keep_flip_map: bool = False,
) -> ImageComparison:
    """Compute several metrics at once, each map once, over the image and over ``mask``.

    Parameters
    ----------
    image_true, image_test : ndarray of shape (height, width, 3)
    data_range : float
    mask : ndarray of shape (height, width), bool, optional
        Object pixels; an empty mask gives NaN object metrics (not an error).
    metrics : sequence of {"psnr", "ssim", "flip"}
    keep_flip_map : bool
        Return the FLIP map too.
    """
    unknown = sorted(set(metrics) - set(METRICS))
    if unknown:
        raise ValueError(f"compare_images: unknown metrics {unknown}; known: {list(METRICS)}")
    m = None if mask is None or not np.asarray(mask).any() else mask
    a, b, m = _check_pair(image_true, image_test, data_range, m, "compare_images")
    out: dict[str, Any] = {}
    if "psnr" in metrics:
        diff = a.astype(np.float64) - b.astype(np.float64)
        sq = diff * diff
        if sq.ndim == 3:
            sq = sq.sum(axis=2) / sq.shape[2]
        out["psnr"] = _psnr_from_mse(float(sq.mean(dtype=np.float64)), data_range)
        if m is not None:
            out["psnr_object"] = _psnr_from_mse(float(sq[m].mean(dtype=np.float64)), data_range)
    if "ssim" in metrics:
        smap = _ssim_map(a, b, data_range)
        out["ssim"] = _masked_ssim(smap, None)
        if m is not None:
            out["ssim_object"] = _masked_ssim(smap, m)
    if "flip" in metrics:
        fmap = _flip_map(a, b, data_range)
        out["flip"] = float(fmap.mean(dtype=np.float64))
        if m is not None:
            out["flip_object"] = float(fmap[m].mean(dtype=np.float64))
        if keep_flip_map:
            out["flip_map"] = fmap
    return ImageComparison(**out)


def blockiness(image: np.ndarray, cell_shape: tuple[int, int],
               mask: np.ndarray | None = None) -> float:
    """The cell-border figure of a frame: the mean absolute difference (over RGB) of the
    pairs of neighbouring pixels that straddle a cell border, divided by that of the pairs
    inside cells; over pairs whose two pixels are both in ``mask`` when given.

    1 means borders are like anywhere else; a frame made cell by cell with visible tile
    borders is above the ray-cast of the same view (whose figure is 1 up to the content).
    NaN when there are no pairs of one kind or the inside pairs do not change at all.

    Parameters
    ----------
    image : ndarray of shape (height, width, 3) or (height, width)
    cell_shape : (int, int)
        ``(cell_h, cell_w)``; cells start at pixel (0, 0).
    mask : ndarray of shape (height, width), bool, optional
    """
    a = np.asarray(image, dtype=np.float32)
    if a.ndim == 2:
        a = a[..., None]
    ch, cw = (int(v) for v in cell_shape)
    if min(ch, cw) < 1:
        raise ValueError(f"blockiness: cell_shape={cell_shape} must be positive")
    m = np.ones(a.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    if m.shape != a.shape[:2]:
        raise ValueError(f"blockiness: mask of shape {m.shape} for an image of {a.shape[:2]}")
    sums = np.zeros(4)  # border sum, border pairs, inside sum, inside pairs
    for axis, size in ((1, cw), (0, ch)):
        diff = np.abs(np.diff(a, axis=axis)).mean(axis=2)
        n = diff.shape[axis]
        border = (np.arange(n) + 1) % size == 0
        border = border[None, :] if axis == 1 else border[:, None]
        both = (m[:, 1:] & m[:, :-1]) if axis == 1 else (m[1:] & m[:-1])
        b, i = both & border, both & ~border
        sums += [diff[b].sum(), b.sum(), diff[i].sum(), i.sum()]
    if sums[1] == 0 or sums[3] == 0 or sums[2] == 0:
        return math.nan
    return float((sums[0] / sums[1]) / (sums[2] / sums[3]))
