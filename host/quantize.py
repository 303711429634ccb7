"""Quantize a fitted eigenspace to the device's int8 model and measure what that costs.

The quantized model (``/work/briefs/model.md``):

* ``mean = rint(clip(mean_, 0, 255))`` as uint8, (n_cells, cell_values);
* per component j (row of ``components_[c]``, cell-major): ``scales[j] = max|v_j| / 127``
  (float32) and ``eigenimages[j] = rint(v_j / scales[j])`` as int8 in -127..127, so that
  ``|v_j - scales[j] * eigenimages[j]| <= scales[j] / 2`` entry-wise (symmetric: -128 is never
  used);
* ``n_components`` int32 (n_cells,).

The loss is measured, not assumed: `int8_loss_db` reconstructs the same score vectors with the
float model (rounded to 8 bits like any displayed image) and with the int8 model through the
device's own `device_runtime.reconstruct.Reconstructor`, and compares both with the originals.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from device_runtime.reconstruct import Reconstructor
from protocol.image import EigenspaceImage

__all__ = [
    "QuantizationLoss",
    "QuantizedEigenspace",
    "int8_loss_db",
    "quantize_components",
    "quantize_eigenspace",
    "quantize_mean",
]

_INT8_LIMIT = 127


@dataclass(eq=False)
class QuantizedEigenspace:
    """The arrays of the device model.

    Attributes
    ----------
    mean : ndarray of shape (n_cells, cell_values), uint8
    eigenimages : ndarray of shape (n_coefficients, cell_values), int8
    scales : ndarray of shape (n_coefficients,), float32
    n_components : ndarray of shape (n_cells,), int32
    image_shape : (int, int)
        ``(height, width)``.
    cell_shape : (int, int)
        ``(cell_h, cell_w)``.
    """

    mean: np.ndarray
    eigenimages: np.ndarray
    scales: np.ndarray
    n_components: np.ndarray
    image_shape: tuple[int, int]
    cell_shape: tuple[int, int]

    @property
    def n_coefficients(self) -> int:
        """K, the total number of components."""
        return int(self.eigenimages.shape[0])

    def to_image(self, **fields: Any) -> EigenspaceImage:
        """Wrap the arrays in an `EigenspaceImage`; ``fields`` fill its manifest entries."""
        return EigenspaceImage(
            image_shape=tuple(self.image_shape),
            cell_shape=tuple(self.cell_shape),
            mean=self.mean,
            eigenimages=self.eigenimages,
            scales=self.scales,
            n_components=self.n_components,
            **fields,
        )

    def reconstructor(self, **kwargs: Any) -> Reconstructor:
        """A `Reconstructor` over these arrays (keyword arguments pass through)."""
        return Reconstructor(
            self.mean,
            self.eigenimages,
            self.scales,
            self.n_components,
            self.image_shape,
            self.cell_shape,
            **kwargs,
        )


def quantize_mean(mean: np.ndarray) -> np.ndarray:
    """``rint(clip(mean, 0, 255))`` as uint8 (same shape)."""
    return np.rint(np.clip(np.asarray(mean, dtype=np.float64), 0, 255)).astype(np.uint8)


def quantize_components(components: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Symmetric per-row int8 quantization.

    Parameters
    ----------
    components : ndarray of shape (n_components, cell_values), float
        One component per row.

    Returns
    -------
    eigenimages : ndarray of shape (n_components, cell_values), int8
        ``rint(v / scale)`` in -127..127.
    scales : ndarray of shape (n_components,), float32
        ``max|v| / 127`` per row (0 for an all-zero row, whose int8 row is then 0).
    """
    v = np.asarray(components, dtype=np.float64)
    if v.ndim != 2:
        raise ValueError(f"quantize_components: components must be 2-D, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError("quantize_components: components have NaN or infinite entries")
    peak = np.abs(v).max(axis=1) if v.shape[1] else np.zeros(v.shape[0])
    scales = (peak / _INT8_LIMIT).astype(np.float32)
    divisor = np.where(scales > 0, scales.astype(np.float64), 1.0)[:, None]
    q = np.clip(np.rint(v / divisor), -_INT8_LIMIT, _INT8_LIMIT).astype(np.int8)
    return q, scales


def _model_arrays(model: Any) -> tuple[np.ndarray, list, np.ndarray, tuple, tuple]:
    missing = [
        name
        for name in ("mean_", "components_", "n_components_", "image_shape_", "cell_shape_")
        if not hasattr(model, name)
    ]
    if missing:
        raise ValueError(
            f"quantize: {type(model).__name__} lacks fitted attributes {missing}; pass a fitted "
            "CellEigenspace (call fit first)"
        )
    mean = np.asarray(model.mean_)
    components = list(model.components_)
    counts = np.asarray(model.n_components_)
    image_shape = tuple(int(v) for v in model.image_shape_)
    cell_shape = tuple(int(v) for v in model.cell_shape_)
    n_cells = mean.shape[0]
    if len(components) != n_cells or counts.shape != (n_cells,):
        raise ValueError(
            f"quantize: mean_ has {n_cells} cells but components_ has {len(components)} and "
            f"n_components_ has shape {counts.shape}"
        )
    for c, comps in enumerate(components):
        if comps.shape != (int(counts[c]), mean.shape[1]):
            raise ValueError(
                f"quantize: components_[{c}] has shape {comps.shape}, expected "
                f"({int(counts[c])}, {mean.shape[1]})"
            )
    return mean, components, counts, image_shape, cell_shape


def quantize_eigenspace(model: Any) -> QuantizedEigenspace:
    """Quantize a fitted eigenspace (a `host.pca.CellEigenspace` or any object with its
    fitted attributes ``mean_``, ``components_``, ``n_components_``, ``image_shape_`` and
    ``cell_shape_``) to the int8 device model.

    Returns
    -------
    QuantizedEigenspace
    """
    mean, components, counts, image_shape, cell_shape = _model_arrays(model)
    values = mean.shape[1]
    if components:
        stacked = np.concatenate(components, axis=0) if counts.sum() else np.zeros((0, values))
    else:
        stacked = np.zeros((0, values))
    eigenimages, scales = quantize_components(stacked)
    return QuantizedEigenspace(
        mean=quantize_mean(mean),
        eigenimages=eigenimages,
        scales=scales,
        n_components=counts.astype(np.int32),
        image_shape=image_shape,
        cell_shape=cell_shape,
    )


@dataclass(frozen=True)
class QuantizationLoss:
    """Quality of the float and int8 models on the same scores (PSNR over all pixels).

    Attributes
    ----------
    psnr_float_db : float
        Originals vs the float model's reconstruction rounded to uint8.
    psnr_int8_db : float
        Originals vs the int8 model's reconstruction (the device's output).
    loss_db : float
        ``psnr_float_db - psnr_int8_db``: what quantization costs.
    psnr_float_vs_int8_db : float
        The two reconstructions against each other.
    n_views : int
    """

    psnr_float_db: float
    psnr_int8_db: float
    loss_db: float
    psnr_float_vs_int8_db: float
    n_views: int


def _psnr_db(sse: float, count: int) -> float:
    if sse == 0:
        return math.inf
    return 10.0 * math.log10(255.0**2 * count / sse)


def int8_loss_db(
    model: Any,
    images: np.ndarray,
    *,
    scores: np.ndarray | None = None,
    quantized: QuantizedEigenspace | None = None,
) -> QuantizationLoss:
    """Measure the quality lost to int8 quantization.

    Parameters
    ----------
    model : CellEigenspace
        The fitted float model (``transform`` and ``inverse_transform`` are used).
    images : ndarray of shape (n_views, height, width, 3), uint8
        The reference images (training or held-out views).
    scores : ndarray of shape (n_views, n_coefficients), float, optional
        The scores to reconstruct; default ``model.transform(images)``.
    quantized : QuantizedEigenspace, optional
        Default ``quantize_eigenspace(model)``.

    Returns
    -------
    QuantizationLoss
    """
    images = np.asarray(images)
    if images.ndim != 4 or images.shape[-1] != 3 or images.dtype != np.uint8:
        raise ValueError(
            f"int8_loss_db: images must be uint8 (n_views, height, width, 3), got "
            f"{images.dtype} {images.shape}"
        )
    if quantized is None:
        quantized = quantize_eigenspace(model)
    if tuple(images.shape[1:3]) != tuple(quantized.image_shape):
        raise ValueError(
            f"int8_loss_db: images are {images.shape[1]}x{images.shape[2]}, the model is "
            f"{quantized.image_shape[0]}x{quantized.image_shape[1]}"
        )
    if scores is None:
        scores = model.transform(images)
    scores = np.asarray(scores, dtype=np.float32)
    if scores.shape != (images.shape[0], quantized.n_coefficients):
        raise ValueError(
            f"int8_loss_db: scores must have shape ({images.shape[0]}, "
            f"{quantized.n_coefficients}), got {scores.shape}"
        )
    rec = quantized.reconstructor()
    sse_float = sse_int8 = sse_between = 0.0
    try:
        for i in range(images.shape[0]):
            reference = images[i].astype(np.float64)
            float_image = np.clip(np.rint(model.inverse_transform(scores[i])), 0, 255)
            int8_image = rec.update(scores[i]).astype(np.float64)
            sse_float += float(np.square(float_image - reference).sum())
            sse_int8 += float(np.square(int8_image - reference).sum())
            sse_between += float(np.square(float_image - int8_image).sum())
    finally:
        rec.close()
    count = images[0].size * images.shape[0] if images.shape[0] else 1
    psnr_float = _psnr_db(sse_float, count)
    psnr_int8 = _psnr_db(sse_int8, count)
    return QuantizationLoss(
        psnr_float_db=psnr_float,
        psnr_int8_db=psnr_int8,
        loss_db=psnr_float - psnr_int8 if math.isfinite(psnr_float) else math.inf,
        psnr_float_vs_int8_db=_psnr_db(sse_between, count),
        n_views=int(images.shape[0]),
    )
