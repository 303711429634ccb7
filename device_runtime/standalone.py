"""Standalone scores: a device that interpolates its own scores from a table in the image.

With ``standalone=True`` (:class:`~device_runtime.runtime.RuntimeDevice`), the image
carries a quantized table of the training views' scores (section
:data:`STANDALONE_SECTION`, or the smaller :data:`STANDALONE_DELTA_SECTION`, written by
``eigencast fit --standalone``) and the interpolation manifest. :func:`standalone_table`
restores the table when the image is loaded; :class:`StandaloneScores` then interpolates
the scores of any view locally, exactly as the host's ``eigencast view`` does for that
image, so the device needs no host at all.
"""

from __future__ import annotations

import math

import numpy as np

from device_runtime.interpolation import interpolate, interpolator_from_manifest
from protocol.errors import ImageFormatError
from protocol.image import EigenspaceImage

__all__ = [
    "STANDALONE_DELTA_SECTION",
    "STANDALONE_SECTION",
    "StandaloneScores",
    "delta_decode",
    "delta_encode",
    "standalone_order",
    "standalone_table",
]

STANDALONE_SECTION = "standalone_scores"
#: The same table stored smaller (``fit --standalone`` since issue 6): uint8 of shape
#: (K, 2, n_views). Per component, the views are taken in `standalone_order` (theta rings,
#: phi ascending: neighbours on the paper's grid are 3.6 degrees apart), each value minus the
#: previous one as int16 (wrapping), zigzag-mapped to uint16 and split into a plane of low
#: bytes and a plane of high bytes (zstd packs the planes far better than interleaved int16).
#: `standalone_table` restores the int16 table in place when the image is loaded.
STANDALONE_DELTA_SECTION = "standalone_scores_delta"
_DELTA_BLOCK_ROWS = 256
"""Name of the image section holding the quantized training-score table (n_views, K)."""


def standalone_table(image: EigenspaceImage) -> tuple[np.ndarray, float] | None:
    """The image's quantized training-score table and its step, or None when it has none.

    Returns
    -------
    (table, step) : ndarray of shape (n_views, K), int16 or int32, and float
        Training view ``i``'s scores are ``table[i] * step`` (orthonormal coordinates).

    Raises
    ------
    ImageFormatError
        The section or its step is inconsistent with the image (shape, dtype, step, views).

    Notes
    -----
    An image written with the delta-coded table (:data:`STANDALONE_DELTA_SECTION`) is decoded
    here once, in place, a block of components at a time (no second table is allocated), and
    the section is replaced in ``image.sections`` by the int16 table itself under
    :data:`STANDALONE_SECTION` (a transposed view of the same memory).
    """
    coded = image.sections.get(STANDALONE_DELTA_SECTION)
    if coded is not None:
        _decode_delta_table(image, coded)
    table = image.sections.get(STANDALONE_SECTION)
    if table is None:
        return None
    quant = image.score_quantization or {}
    step = quant.get("table_step")
    n_views = (image.interpolation or {}).get("n_views")
    if table.dtype not in (np.int16, np.int32) or table.ndim != 2 or (
        table.shape[1] != image.n_coefficients
    ):
        raise ImageFormatError(
            f"image section {STANDALONE_SECTION!r}: expected int16/int32 of shape (n_views, "
            f"K={image.n_coefficients}), got {table.dtype} {table.shape}"
        )
    if not isinstance(step, (int, float)) or isinstance(step, bool) or not (
        math.isfinite(step) and step > 0
    ):
        raise ImageFormatError(
            f"image manifest: score_quantization.table_step={step!r} must be a number > 0"
        )
    if n_views != table.shape[0]:
        raise ImageFormatError(
            f"image section {STANDALONE_SECTION!r} has {table.shape[0]} views, the "
            f"interpolation manifest {n_views!r}"
        )
    return table, float(step)


def standalone_order(image: EigenspaceImage, n_views: int) -> np.ndarray:
    """The order in which a delta-coded table runs through the training views.

    ``np.lexsort((phi mod 360, theta))`` of the manifest's ``views``: theta rings from the
    bottom up, phi ascending within each (the writer and the device compute it alike).

    Raises
    ------
    ImageFormatError
        The manifest lacks the views' angles or has another number of them.
    """
    views = image.views or {}
    try:
        phi = np.mod(np.asarray(views["phi_deg"], dtype=np.float64), 360.0)
        theta = np.asarray(views["theta_deg"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        raise ImageFormatError(
            "image manifest: a delta-coded standalone table needs views.phi_deg and "
            "views.theta_deg"
        ) from None
    if phi.shape != (n_views,) or theta.shape != (n_views,):
        raise ImageFormatError(
            f"image manifest: views has {phi.size} / {theta.size} angles, the standalone "
            f"table {n_views} views"
        )
    return np.lexsort((phi, theta))


def _decode_delta_table(image: EigenspaceImage, coded: np.ndarray) -> None:
    """Undo :data:`STANDALONE_DELTA_SECTION` in place (see `standalone_table`)."""
    if STANDALONE_SECTION in image.sections:
        raise ImageFormatError(
            f"image sections {STANDALONE_SECTION!r} and {STANDALONE_DELTA_SECTION!r} are "
            "both present; an image holds one standalone table"
        )
    n_views = (image.interpolation or {}).get("n_views")
    k = image.n_coefficients
    if coded.dtype != np.uint8 or coded.shape != (k, 2, n_views):
        raise ImageFormatError(
            f"image section {STANDALONE_DELTA_SECTION!r}: expected uint8 of shape "
            f"(K={k}, 2, n_views={n_views}), got {coded.dtype} {coded.shape}"
        )
    table = delta_decode(coded, standalone_order(image, int(n_views)))
    del image.sections[STANDALONE_DELTA_SECTION]
    image.sections[STANDALONE_SECTION] = table


def delta_encode(table: np.ndarray, order: np.ndarray) -> np.ndarray:
    """An int16 table (n_views, K) delta-coded for zstd: uint8 (K, 2, n_views).

    Per column, the rows in ``order`` (`standalone_order`), each minus the previous one as
    int16 (wrapping), zigzag-mapped to uint16 and split into a plane of low bytes and a
    plane of high bytes. `delta_decode` undoes it. The standalone table
    (:data:`STANDALONE_DELTA_SECTION`) and the depth table of ``fit --depth``
    (``depth_scores_delta``) are stored this way.
    """
    if table.dtype != np.int16 or table.ndim != 2:
        raise ValueError(f"delta_encode: expected an int16 (n_views, K) table, got "
                         f"{table.dtype} {table.shape}")
    diffs = np.ascontiguousarray(table[order].T)  # (K, n_views) in coding order
    diffs[:, 1:] = diffs[:, 1:] - diffs[:, :-1]  # wraps in int16, like the decoder
    wide = diffs.astype(np.int32)
    z = ((wide << 1) ^ (wide >> 15)).astype(np.uint16)
    return np.stack([(z & 0xFF).astype(np.uint8), (z >> 8).astype(np.uint8)], axis=1)


def delta_decode(coded: np.ndarray, order: np.ndarray) -> np.ndarray:
    """Undo `delta_encode`: the int16 table (n_views, K), a transposed view of ``coded``'s
    memory (decoded in place, a block of columns at a time: no second table is allocated;
    a read-only or non-contiguous ``coded`` is copied first).

    ``coded`` is uint8 (K, 2, n_views) and ``order`` a permutation of the n_views rows (the
    caller checks both against its image)."""
    k, _, n_views = coded.shape
    if not coded.flags.writeable or not coded.flags.c_contiguous:
        coded = np.ascontiguousarray(coded).copy()
    table = coded.reshape(k, 2 * int(n_views)).view("<i2")  # (K, n_views), same memory
    for start in range(0, k, _DELTA_BLOCK_ROWS):
        block = coded[start:start + _DELTA_BLOCK_ROWS]
        z = block[:, 0, :].astype(np.uint16) | (block[:, 1, :].astype(np.uint16) << 8)
        d = (z >> 1).astype(np.int16) ^ -(z & 1).astype(np.int16)
        np.cumsum(d, axis=1, dtype=np.int16, out=d)
        rows = table[start:start + _DELTA_BLOCK_ROWS]
        rows[:, order] = d
    return table.T


class StandaloneScores:
    """Local score interpolation from the image's quantized table (a device with no host).

    The computation is the host's for the same image (``HostModel.quantized_scores``):
    interpolate the dequantized table (``float32(q) * float32(table_step)``) with the
    manifest's interpolator, then round to the packet step. Only the ``m`` rows a query
    needs are dequantized, so the table stays int16 in RAM.

    Parameters
    ----------
    image : EigenspaceImage
        With a standalone table and interpolation manifest.

    Raises
    ------
    ImageFormatError
        No table, or a malformed one / malformed interpolation manifest.
    """

    def __init__(self, image: EigenspaceImage) -> None:
        found = standalone_table(image)
        if found is None:
            raise ImageFormatError(
                "the image has no standalone score table (refit with eigencast fit --standalone)"
            )
        if image.interpolation is None:
            raise ImageFormatError("the image has no interpolation manifest")
        self.table, self.table_step = found
        try:
            self.interpolator = interpolator_from_manifest(image.interpolation)
        except ValueError as exc:
            raise ImageFormatError(f"image interpolation manifest: {exc}") from None
        self.step = float((image.score_quantization or {}).get("step", 1.0))
        self._step32 = np.float32(self.table_step)

    def scores(self, phi_deg: float, theta_deg: float) -> np.ndarray:
        """Quantized scores (K,) float32 of a view, as the host would send them."""
        idx, w = self.interpolator.weights(phi_deg, theta_deg)
        rows = self.table[idx].astype(np.float32) * self._step32  # (m, K)
        return self._to_packet_step(interpolate(rows, np.arange(rows.shape[0]), w))

    def training_scores(self, view: int) -> np.ndarray:
        """Training view ``view``'s own scores (K,) float32: its dequantized table row,
        rounded to the packet step as `scores` rounds (no interpolation)."""
        return self._to_packet_step(self.table[view].astype(np.float32) * self._step32)

    def _to_packet_step(self, y: np.ndarray) -> np.ndarray:
        step = self.step
        return (np.rint(y / step) * step).astype(np.float32)
