"""Rate-distortion optimal score quantization: which coefficients a packet sends, and how.

`HostModel.quantize` rounds every score to one step and zeroes the components whose
eigenvalue is below the rounding noise (reverse water-filling): the same choice for every
frame, whatever the frame holds. `rd_quantize` instead decides per frame, by one Lagrangian
``lam`` over the whole frame, minimising ``D + lam * R``:

* ``D``: squared error in score space (the device's basis is orthonormal up to its int8
  rounding, so this is the frame's squared pixel error, summed over RGB);
* ``R``: an estimate of the coded bits: each integer as an Exp-Golomb code of its zigzag
  value (1 bit for 0, 3 for +-1, 5 for +-2..+-3 ...), plus each cell's end-of-block count.

Per coefficient it chooses among ``rint(y / step)``, the value one closer to 0, and 0
(rate-distortion optimised quantization, as video encoders do); per cell it then chooses
how many leading coefficients to send (the end-of-block count of `protocol.scores`'
CODING 1) by the same cost, so a cell whose content is the mean (the empty background)
gets nothing. The result is still integers times the one scalar step, so the packet format
and the device are unchanged: `protocol.scores.encode_scores` at ``step`` codes exactly
these integers.

Wiring (for ``serve``): ``FrameEncoder.encode(view, scores=rd_delta(model, y, prev))``,
``prev`` the values of the encoder's base (``base.q * step``, None for a key frame), already
sends the result unchanged when ``step`` is the model's score step, because
`HostModel.quantize` of values on the step grid is the identity (`rd_quantize` applies the
same water-fill mask, so the two agree exactly). A coarser RD step needs ``FrameEncoder`` to
pass that step to `protocol.scores.encode_scores` and to send a key frame when the step
changes (a delta needs its base's step).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = [
    "DEFAULT_CORRECTION_KAPPA",
    "DEFAULT_CORRECTION_STEP_FACTOR",
    "DEFAULT_RD_KAPPA",
    "eg_bits",
    "encode_correction",
    "quantize_correction",
    "rd_delta",
    "rd_lambda",
    "rd_quantize",
    "ssim_cell_weights",
]

#: ``lam = kappa * step**2`` (squared score units per bit): the Lagrangian that matches a
#: uniform quantizer of that step (chosen from a sweep of 0.05-0.5 on the tooth at 256;
#: docs/design-notes.md, "Rate-distortion quantization").
DEFAULT_RD_KAPPA = 0.15
#: A moving view's correction step in model score steps (bench_link: step x2 with kappa 0.15
#: gave the best object SSIM over its drag and orbit traces at 115200 baud, issue 14).
DEFAULT_CORRECTION_STEP_FACTOR = 2.0
#: The RD factor of a moving view's correction.
DEFAULT_CORRECTION_KAPPA = DEFAULT_RD_KAPPA


def eg_bits(q: np.ndarray) -> np.ndarray:
    """Estimated bits of integers ``q``: Exp-Golomb length of the zigzag value (float64)."""
    q = np.asarray(q, dtype=np.int64)
    z = np.where(q >= 0, 2 * q, -2 * q - 1)
    return 2.0 * np.floor(np.log2(z + 1.0)) + 1.0


def rd_lambda(step: float, kappa: float = DEFAULT_RD_KAPPA) -> float:
    """The Lagrangian (squared score per bit) for a scalar ``step``: ``kappa * step**2``."""
    return float(kappa) * float(step) ** 2


def rd_quantize(
    model: Any,
    scores: np.ndarray,
    *,
    step: float | None = None,
    lam: float | None = None,
    kappa: float = DEFAULT_RD_KAPPA,
    weights: np.ndarray | None = None,
) -> np.ndarray:
    """Rate-distortion optimal quantized scores (K,) float32 of one frame.

    Parameters
    ----------
    model : host.fit.model.HostModel
        Gives the per-cell component counts (and the water-fill mask at ``step``).
    scores : ndarray of shape (K,), float
        The frame's float scores (e.g. `HostModel.project` of a fresh ray-cast).
    step : float, optional
        Quantization step (default: the model's score step, which ``serve`` sends).
    lam : float, optional
        Lagrangian, squared score units per bit (default `rd_lambda` ``(step, kappa)``).
        0 gives plain rounding with no truncation.
    kappa : float
        Used when ``lam`` is not given.
    weights : ndarray of shape (n_cells,), float, optional
        Per-cell weight of the squared error (e.g. `ssim_cell_weights`); default 1.

    Returns
    -------
    ndarray of shape (K,), float32
        ``q * step`` with integer ``q``: what a packet at ``step`` carries.
    """
    y = np.asarray(scores, dtype=np.float64)
    counts = np.asarray(model.image.n_components, dtype=np.int64)
    if y.shape != (int(counts.sum()),):
        raise ValueError(f"rd_quantize: scores of shape {y.shape}, the model has "
                         f"K={int(counts.sum())}")
    s = float(model.score_step if step is None else step)
    if not s > 0:
        raise ValueError(f"rd_quantize: step={s} must be positive")
    lam_ = rd_lambda(s, kappa) if lam is None else float(lam)
    if lam_ < 0:
        raise ValueError(f"rd_quantize: lam={lam_} must be >= 0")
    q0 = np.rint(y / s)
    mask = model.waterfill_mask(s) if hasattr(model, "waterfill_mask") else None
    if mask is not None:
        q0[mask] = 0.0
    # candidates: rounded, one toward zero, zero
    q1 = q0 - np.sign(q0)
    cands = np.stack([q0, q1, np.zeros_like(q0)])
    if weights is None:
        w = np.ones_like(y)
    else:
        wc = np.asarray(weights, dtype=np.float64)
        if wc.shape != counts.shape or not np.all(np.isfinite(wc)) or np.any(wc < 0):
            raise ValueError(f"rd_quantize: weights must be (n_cells={counts.size},) finite "
                             ">= 0")
        w = np.repeat(wc, counts)
    cost = w * (y[None] - cands * s) ** 2 + lam_ * eg_bits(cands)
    pick = np.argmin(cost, axis=0)
    q = np.take_along_axis(cands, pick[None], axis=0)[0]
    keep_cost = np.take_along_axis(cost, pick[None], axis=0)[0]
    # per cell: send the first m coefficients (end-of-block), drop the rest (cost y**2)
    gain = keep_cost - w * y * y  # cost of sending coefficient j instead of dropping it
    ends = np.cumsum(counts)
    out = np.zeros_like(q)
    for c in range(counts.size):
        n = int(counts[c])
        if n == 0:
            continue
        lo = int(ends[c]) - n
        seg = np.concatenate([[0.0], np.cumsum(gain[lo:lo + n])])
        seg += lam_ * eg_bits(np.arange(n + 1))  # the end-of-block count itself
        m = int(np.argmin(seg))
        out[lo:lo + m] = q[lo:lo + m]
    return (out * s).astype(np.float32)


def quantize_correction(
    model: Any,
    delta: np.ndarray,
    *,
    fine: bool = False,
    step: float | None = None,
    kappa: float = DEFAULT_CORRECTION_KAPPA,
    weights: np.ndarray | None = None,
) -> tuple[np.ndarray, float]:
    """A correction of the device's own frame as a version-3 packet carries it.

    ``fine`` (a resting view's complete correction): the model's own step, plain rounding
    (``lam = 0``). Otherwise (a moving view's): ``step`` (default
    `DEFAULT_CORRECTION_STEP_FACTOR` x the model's score step), RD-quantized with ``kappa``
    and the cell ``weights``. Returns ``(q * step`` (K,) float32, ``step)``; what
    ``host.link.correction.CorrectionEncoder`` sends and evaluate's ``pca_predict`` /
    ``pca_motion`` measure.
    """
    if fine:
        s = float(model.score_step)
        return rd_quantize(model, delta, step=s, lam=0.0), s
    s = float(model.score_step * DEFAULT_CORRECTION_STEP_FACTOR if step is None else step)
    return rd_quantize(model, delta, step=s, kappa=kappa, weights=weights), s


def encode_correction(
    model: Any,
    delta: np.ndarray,
    view: tuple[float, float],
    *,
    frame: int,
    always: bool = False,
    level: int | None = None,
    **quantize: Any,
) -> Any:
    """The version-3 packet (SYNTHESIZED) of the correction ``delta`` of the device's own
    frame of ``view`` (canonical), quantized by `quantize_correction` (``fine``, ``step``,
    ``kappa``, ``weights``); None when every quantized coefficient is zero and not
    ``always`` (nothing worth sending: the device keeps its own frame). ``level``: the
    packet's zstd level (default `protocol.scores.DEFAULT_LEVEL`). Returns its
    `~protocol.scores.EncodedScores`; what ``serve`` sends (`CorrectionEncoder`) and
    evaluate measures.
    """
    from protocol.scores import DEFAULT_LEVEL, encode_scores

    q, step = quantize_correction(model, delta, **quantize)
    if not (always or np.any(q)):
        return None
    return encode_scores(q, step=step, frame=frame, view=view, image_digest=model.digest,
                         synthesized=True, n_components=model.image.n_components,
                         level=DEFAULT_LEVEL if level is None else level)


def rd_delta(
    model: Any,
    scores: np.ndarray,
    base: np.ndarray | None,
    **kwargs: Any,
) -> np.ndarray:
    """RD-quantized scores (K,) float32 of a frame coded against ``base`` (a delta packet).

    A delta packet codes ``q - q_base``: the rate is that of the difference, and a
    coefficient not sent keeps the base's value. So the difference ``scores - base`` is what
    `rd_quantize` decides on, and the frame is ``base + rd_quantize(scores - base)``: on the
    step grid when ``base`` is (the previous frame at the same step), and with ``base`` the
    device's own prediction, the correction of "the device predicts, the host corrects".

    Parameters
    ----------
    model : host.fit.model.HostModel
    scores : ndarray of shape (K,), float
        The frame's float scores (e.g. the projection of a fresh ray-cast).
    base : ndarray of shape (K,), float, or None
        The values the decoder already holds (the previous frame's quantized scores);
        None: a key frame.
    **kwargs
        ``step``, ``lam``, ``kappa``, ``weights`` of `rd_quantize`.
    """
    y = np.asarray(scores, dtype=np.float64)
    if base is None:
        return rd_quantize(model, y, **kwargs)
    b = np.asarray(base, dtype=np.float64)
    if b.shape != y.shape:
        raise ValueError(f"rd_delta: base of shape {b.shape}, scores {y.shape}")
    return (b + rd_quantize(model, y - b, **kwargs)).astype(np.float32)


#: SSIM's C2 for 8-bit data, ``(0.03 * 255) ** 2``.
_SSIM_C2 = (0.03 * 255.0) ** 2


def ssim_cell_weights(
    image: np.ndarray, cell_shape: tuple[int, int], mask: np.ndarray | None = None, *,
    floor: float = 0.25,
) -> np.ndarray:
    """Per-cell error weights that make squared error track object SSIM (n_cells,) float64.

    SSIM divides an error by the local contrast, ``2 sigma**2 + C2``: the same squared error
    costs more SSIM in a smooth cell than in a textured one. Each cell's weight is
    ``1 / (2 sigma_c**2 + C2)`` (``sigma_c**2``: the variance of the cell's pixel values in
    ``image``), times ``floor + (1 - floor) * f_c`` where ``f_c`` is the fraction of object
    pixels in the cell (``mask``; all pixels when None), normalised to mean 1 over the cells
    with object pixels. The host computes them from the true view it projects; the device
    never sees them.

    Parameters
    ----------
    image : ndarray of shape (height, width, 3), uint8
    cell_shape : (int, int)
    mask : ndarray of shape (height, width), bool, optional
    floor : float
        Weight factor of a cell without object pixels (its errors show on the background).
    """
    from host.fit.cells import split_cells

    x = np.asarray(image)
    cells = split_cells(x[None], tuple(cell_shape))[0].astype(np.float64)
    var = cells.var(axis=1)
    if mask is None:
        frac = np.ones(cells.shape[0])
    else:
        m = np.repeat(np.asarray(mask, dtype=np.uint8)[..., None], 3, axis=2)
        frac = split_cells(m[None], tuple(cell_shape))[0].astype(np.float64).mean(axis=1)
    w = (floor + (1.0 - floor) * frac) / (2.0 * var + _SSIM_C2)
    ref = w[frac > 0].mean() if np.any(frac > 0) else w.mean()
    return w / ref
