"""Quantize a fitted eigenspace to the device's int8 model and measure what that costs.

The quantized model (``/work/briefs/model.md``):

* ``mean = rint(clip(mean_, 0, 255))`` as uint8, (n_cells, cell_values);
* per component j (row of ``components_[c]``, cell-major): ``scales[j] = max|v_j| / 127``
  (float32) and ``eigenimages[j] = rint(v_j / scales[j])`` as int8 in -127..127, so that
  ``|v_j - scales[j] * eigenimages[j]| <= scales[j] / 2`` entry-wise (symmetric: -128 is never
  used);
* ``n_components`` int32 (n_cells,).

Bit allocation (`allocate_bits`, ``quantize_eigenspace(bit_budget=...)``): a component whose
scores vary little contributes little error when its levels are coarse, so it may keep fewer
than 8 bits' worth of levels (``scales[j] = max|v_j| / (2**(b_j-1) - 1)``); the entries stay
int8, the device is unchanged, and zstd stores the smaller alphabets in fewer bytes.

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
    "DEFAULT_BIT_BUDGET",
    "MAX_BITS",
    "MIN_BITS",
    "QuantizationLoss",
    "QuantizedEigenspace",
    "allocate_bits",
    "int8_loss_db",
    "quantize_components",
    "quantize_eigenspace",
    "quantize_mean",
    "residual_mse",
]

_INT8_LIMIT = 127
#: Default bit allocation of ``fit``: the eigenimages' quantization may add this fraction of
#: the model's own approximation error (`residual_mse`), i.e. at most 10 log10(1.03) = 0.13 dB
#: on the training views; measured on tooth and head at 256 and 512 it cuts the
#: eigenimages' compressed bytes by 50-73 % for at most 0.0016 object SSIM on novel views
#: (docs/rate-distortion-packets.md).
DEFAULT_BIT_BUDGET = 0.03
#: Range of per-component bits (`allocate_bits`, `quantize_components`).
MIN_BITS, MAX_BITS = 2, 8


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
    bits : ndarray of shape (n_coefficients,), int8, or None
        Bits of levels each component uses (`allocate_bits`; None: 8 for all).
    """

    mean: np.ndarray
    eigenimages: np.ndarray
    scales: np.ndarray
    n_components: np.ndarray
    image_shape: tuple[int, int]
    cell_shape: tuple[int, int]
    bits: np.ndarray | None = None

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


def quantize_components(
    components: np.ndarray, *, bits: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Symmetric per-row quantization to int8 storage, optionally with fewer levels per row.

    Parameters
    ----------
    components : ndarray of shape (n_components, cell_values), float
        One component per row.
    bits : ndarray of shape (n_components,), int in 2..8, optional
        Bits of each row (`allocate_bits`): row ``j`` uses the levels
        ``-(2**(b-1) - 1) .. 2**(b-1) - 1``. Default 8 for every row.

    Returns
    -------
    eigenimages : ndarray of shape (n_components, cell_values), int8
        ``rint(v / scale)`` within each row's levels (-127..127 at 8 bits).
    scales : ndarray of shape (n_components,), float32
        ``max|v| / (2**(b-1) - 1)`` per row (0 for an all-zero row, whose int8 row is then 0).
    """
    v = np.asarray(components, dtype=np.float64)
    if v.ndim != 2:
        raise ValueError(f"quantize_components: components must be 2-D, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError("quantize_components: components have NaN or infinite entries")
    if bits is None:
        limit = np.full(v.shape[0], float(_INT8_LIMIT))
    else:
        b = np.asarray(bits)
        if b.shape != (v.shape[0],) or not np.issubdtype(b.dtype, np.integer) or (
            b.size and (b.min() < MIN_BITS or b.max() > MAX_BITS)
        ):
            raise ValueError(
                f"quantize_components: bits must be ({v.shape[0]},) ints within "
                f"{MIN_BITS}..{MAX_BITS}"
            )
        limit = (2.0 ** (b.astype(np.int64) - 1) - 1.0).astype(np.float64)
    peak = np.abs(v).max(axis=1) if v.shape[1] else np.zeros(v.shape[0])
    scales = (peak / limit).astype(np.float32)
    divisor = np.where(scales > 0, scales.astype(np.float64), 1.0)[:, None]
    q = np.clip(np.rint(v / divisor), -limit[:, None], limit[:, None]).astype(np.int8)
    return q, scales


def allocate_bits(
    eigenvalues: np.ndarray,
    peaks: np.ndarray,
    *,
    n_cells: int,
    mse_budget: float,
    min_bits: int = MIN_BITS,
) -> np.ndarray:
    """Bits per component (reverse water-filling over the eigenimages' quantization noise).

    Row ``j`` quantized with step ``s_j = peaks[j] / (2**(b-1) - 1)`` adds ``s_j**2 / 12`` of
    noise to each of its entries; a view's score on it has variance ``eigenvalues[j]``, so the
    reconstruction's squared error grows by ``eigenvalues[j] * s_j**2 / 12`` summed over its
    cell, i.e. ``eigenvalues[j] * s_j**2 / (12 * n_cells)`` per pixel value of the image. The
    allocation minimises the total bits subject to the MSE added over 8 bits staying within
    ``mse_budget`` (0..255 pixel units), by bisection on the Lagrange multiplier: each row
    takes the ``b`` minimising ``b + mu * added_j(b)``.

    Parameters
    ----------
    eigenvalues : ndarray of shape (K,), float
        Variance of each component's scores.
    peaks : ndarray of shape (K,), float
        ``max |v_j|`` of each (orthonormal) component.
    n_cells : int
        Cells of the image (the MSE is per pixel value of the whole image).
    mse_budget : float
        Added MSE allowed (0: every row keeps 8 bits).
    min_bits : int
        Fewest bits a row may get (2..8).

    Returns
    -------
    ndarray of shape (K,), int8
        Bits per component in ``min_bits..8``.
    """
    lam = np.maximum(np.asarray(eigenvalues, dtype=np.float64), 0.0)
    peak = np.asarray(peaks, dtype=np.float64)
    if lam.ndim != 1 or peak.shape != lam.shape:
        raise ValueError(f"allocate_bits: eigenvalues {lam.shape} and peaks {peak.shape} differ")
    if not (np.all(np.isfinite(lam)) and np.all(np.isfinite(peak))):
        raise ValueError("allocate_bits: eigenvalues and peaks must be finite")
    if not MIN_BITS <= int(min_bits) <= MAX_BITS:
        raise ValueError(f"allocate_bits: min_bits={min_bits} must be within {MIN_BITS}..8")
    if not (math.isfinite(mse_budget) and mse_budget >= 0) or n_cells < 1:
        raise ValueError(f"allocate_bits: mse_budget={mse_budget} must be >= 0, n_cells >= 1")
    levels = np.arange(int(min_bits), MAX_BITS + 1)
    limit = 2.0 ** (levels - 1) - 1.0  # (L,)
    noise = lam[None, :] * (peak[None, :] / limit[:, None]) ** 2 / (12.0 * n_cells)  # (L, K)
    added = noise - noise[-1]
    if lam.size == 0 or mse_budget <= 0:
        return np.full(lam.size, MAX_BITS, dtype=np.int8)

    def choose(mu: float) -> np.ndarray:
        return np.argmin(levels[:, None] + mu * added, axis=0)

    cols = np.arange(lam.size)
    if added[choose(0.0), cols].sum() <= mse_budget:
        return np.full(lam.size, levels[0], dtype=np.int8)
    lo, hi = 0.0, 1.0
    while added[choose(hi), cols].sum() > mse_budget:
        hi *= 4.0
        if hi > 1e300:
            return np.full(lam.size, MAX_BITS, dtype=np.int8)
    for _ in range(100):  # lo breaks the budget, hi keeps it
        mid = math.sqrt(lo * hi) if lo > 0 else hi / 1e6
        if added[choose(mid), cols].sum() <= mse_budget:
            hi = mid
        else:
            lo = mid
        if lo > 0 and hi / lo < 1 + 1e-9:
            break
    return levels[choose(hi)].astype(np.int8)


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


def residual_mse(model: Any) -> float:
    """Mean squared error per pixel value the fitted components leave on the training views.

    ``sum over cells of (trace - kept eigenvalues) / (n_cells * cell_values)``: the float
    model's own approximation error, the yardstick of `DEFAULT_BIT_BUDGET`. Needs the fitted
    ``eigenvalues_`` and ``total_variance_`` (0.0 when the model lacks them).
    """
    eig = getattr(model, "eigenvalues_", None)
    total = getattr(model, "total_variance_", None)
    if eig is None or total is None:
        return 0.0
    kept = np.array([float(np.sum(e)) for e in eig], dtype=np.float64)
    total = np.asarray(total, dtype=np.float64)
    values = int(np.asarray(model.mean_).shape[1])
    if total.shape != kept.shape or total.size == 0 or values == 0:
        return 0.0
    return float(max(0.0, np.sum(total - kept)) / (total.size * values))


def quantize_eigenspace(model: Any, *, bit_budget: float = 0.0) -> QuantizedEigenspace:
    """Quantize a fitted eigenspace (a `host.fit.pca.CellEigenspace` or any object with its
    fitted attributes ``mean_``, ``components_``, ``n_components_``, ``image_shape_`` and
    ``cell_shape_``) to the int8 device model.

    Parameters
    ----------
    model : CellEigenspace
    bit_budget : float
        Bit allocation (`allocate_bits`): the MSE the eigenimages' quantization may add over
        int8, as a fraction of the model's `residual_mse` (0: every component at 8 bits; the
        model also needs ``eigenvalues_``). Components then keep 2..8 bits' worth of levels,
        still one int8 per entry, so the device format and reconstruction are unchanged and
        the image's zstd sections shrink (docs/rate-distortion-packets.md).

    Returns
    -------
    QuantizedEigenspace
        ``bits`` holds the bits of each component.
    """
    mean, components, counts, image_shape, cell_shape = _model_arrays(model)
    values = mean.shape[1]
    if components:
        stacked = np.concatenate(components, axis=0) if counts.sum() else np.zeros((0, values))
    else:
        stacked = np.zeros((0, values))
    if not (math.isfinite(bit_budget) and bit_budget >= 0):
        raise ValueError(f"quantize_eigenspace: bit_budget={bit_budget} must be >= 0")
    bits = np.full(stacked.shape[0], MAX_BITS, dtype=np.int8)
    eig = getattr(model, "eigenvalues_", None)
    if bit_budget > 0 and eig is not None and stacked.shape[0]:
        lam = np.concatenate([np.asarray(e, dtype=np.float64) for e in eig])
        peaks = np.abs(stacked).max(axis=1) if values else np.zeros(stacked.shape[0])
        budget = bit_budget * residual_mse(model)
        if lam.shape == peaks.shape and budget > 0:
            bits = allocate_bits(lam, peaks, n_cells=mean.shape[0], mse_budget=budget)
    eigenimages, scales = quantize_components(stacked, bits=bits)
    return QuantizedEigenspace(
        mean=quantize_mean(mean),
        eigenimages=eigenimages,
        scales=scales,
        n_components=counts.astype(np.int32),
        image_shape=image_shape,
        cell_shape=cell_shape,
        bits=bits,
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
