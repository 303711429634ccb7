"""Evaluation: how good are the frames a device shows, and what would an image codec do instead?

Metrics
-------
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

Equal-bytes codecs
------------------
`encode_within_budget` finds, by bisection over Pillow's quality 1..100, the highest quality whose
file is not larger than a byte budget (JPEG: ``optimize=True``, 4:2:0; WebP: ``method=6``). It
keeps the invariant "quality lo fits, quality hi does not", so the answer's ``quality + 1``
always exceeds the budget; if even quality 1 does not fit it says so (``within_budget`` False)
and returns that file.

The device path
---------------
`DevicePath` is what a device shows: interpolated scores -> a real key score packet
(`protocol.scores.encode_scores` at the model's step; its length is the bytes per view) ->
`protocol.scores.ScoreDecoder` -> the device's `Reconstructor` (through `host.model.HostModel`).

The evaluation engine
---------------------
`evaluate_model` ray-casts novel views with the model's own render settings
(`host.render_settings.ViewRenderer`) and compares, per view, the device frame (from
interpolated scores, and from the ray-cast's own scores as ``serve --scores render`` sends
them), the equal-bytes JPEG and WebP, the angularly nearest training view and the *WebP
image database* (`WebPDatabase`: every training view stored as WebP on the device, the novel
view blended from the decoded training images with the model's own interpolation weights;
zero bytes per frame) with the ray-cast; then a rate-distortion sweep over a subset of the
views (the model truncated to lower thresholds / fewer components through the annexed
eigenvalues, coarser score steps, the *projection* of the true views onto the eigenspace --
what the eigenspace can do without view interpolation -- and JPEG/WebP at several
qualities). `Evaluation.summary` is the JSON of
``eigencast evaluate --json``; `host.report.write_report` turns an `Evaluation` into HTML.
"""

from __future__ import annotations

import io
import math
import tempfile
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from host.errors import EigencastError
from host.progress import progress as _progress
from host.render_settings import OBJECT_ALPHA_MIN

__all__ = [
    "CODECS",
    "DEFAULT_QUALITIES",
    "DEFAULT_STEP_FACTORS",
    "DEFAULT_THRESHOLDS",
    "DEFAULT_WEBP_DB_QUALITY",
    "METHODS",
    "METRICS",
    "CodedImage",
    "DevicePath",
    "Evaluation",
    "ImageComparison",
    "WebPDatabase",
    "compare_images",
    "decode_image",
    "default_metric_workers",
    "encode_image",
    "encode_within_budget",
    "evaluate_model",
    "flip_error",
    "flip_error_map",
    "nearest_training_view",
    "peak_signal_noise_ratio",
    "structural_similarity",
]

METRICS = ("psnr", "ssim", "flip")
#: Whether a larger value is better, per metric.
HIGHER_IS_BETTER = {"psnr": True, "ssim": True, "flip": False}
CODECS = ("jpeg", "webp")
#: Methods an evaluation reports: the device frame from interpolated scores (``pca``), the
#: device frame from the ray-cast's own scores (``pca_render``: what ``serve --scores
#: render`` sends, and ``refine`` once a view rests), equal-bytes codecs, the nearest
#: training view and the on-device WebP image database.
METHODS = ("pca", "pca_render", "jpeg", "webp", "nearest", "webp_db")
MAX_QUALITY = 100
#: Thresholds tried by the rate-distortion sweep of an adaptive model (those below its own T).
DEFAULT_THRESHOLDS = (0.8, 0.9, 0.95, 0.97, 0.98, 0.99, 0.995, 0.998, 0.999)
#: Score-step multiples tried by the rate-distortion sweep at the model's own components.
DEFAULT_STEP_FACTORS = (2.0, 4.0, 8.0, 16.0)
#: Codec qualities of the rate-distortion sweep.
DEFAULT_QUALITIES = (2, 5, 10, 20, 35, 50, 70, 90)
#: WebP quality of the on-device image database baseline (``webp_db``).
DEFAULT_WEBP_DB_QUALITY = 80
_NOT_AVERAGED = {"index"}  # per-view entries whose mean means nothing
_SSIM_WIN = 7  # scikit-image's default window; its mean crops (win - 1) // 2 pixels
_PIL_FORMAT = {"jpeg": "JPEG", "webp": "WEBP"}


# =========================================================================== metrics


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


# =========================================================================== codecs


@dataclass(frozen=True, eq=False)
class CodedImage:
    """An image encoded by a codec at one quality.

    Attributes
    ----------
    codec : {"jpeg", "webp"}
    quality : int
        Pillow's quality, 1..100.
    data : bytes
        The whole file.
    budget_bytes : int or None
        The budget it was searched for (None: a fixed quality).
    """

    codec: str
    quality: int
    data: bytes
    budget_bytes: int | None = None

    @property
    def size_bytes(self) -> int:
        return len(self.data)

    @property
    def within_budget(self) -> bool:
        """True when no budget was set or the file fits it."""
        return self.budget_bytes is None or self.size_bytes <= self.budget_bytes

    def decode(self) -> np.ndarray:
        """The decoded image, uint8 (height, width, 3)."""
        return decode_image(self.data)


def _check_codec(codec: str) -> None:
    if codec not in CODECS:
        raise ValueError(f"codec={codec!r} is unknown; use one of {list(CODECS)}")


def encode_image(image: np.ndarray, codec: str, quality: int) -> CodedImage:
    """Encode ``image`` (uint8 (height, width, 3)) with Pillow at ``quality`` (1..100)."""
    from PIL import Image

    _check_codec(codec)
    if isinstance(quality, bool) or not isinstance(quality, (int, np.integer)) or not (
        1 <= quality <= MAX_QUALITY
    ):
        raise ValueError(f"quality={quality!r} must be an integer within 1..{MAX_QUALITY}")
    arr = np.asarray(image)
    if arr.dtype != np.uint8 or arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(
            f"encode_image: image must be uint8 (h, w, 3), got {arr.dtype} {arr.shape}"
        )
    buf = io.BytesIO()
    pil = Image.fromarray(arr, mode="RGB")
    if codec == "jpeg":
        pil.save(buf, format="JPEG", quality=int(quality), optimize=True)
    else:
        pil.save(buf, format="WEBP", quality=int(quality), method=6)
    return CodedImage(codec, int(quality), buf.getvalue())


def decode_image(data: bytes) -> np.ndarray:
    """Decode a JPEG/WebP/PNG file's bytes to uint8 (height, width, 3)."""
    from PIL import Image

    with Image.open(io.BytesIO(data)) as im:
        im.load()
        return np.asarray(im.convert("RGB"), dtype=np.uint8)


def encode_within_budget(
    image: np.ndarray, budget_bytes: int, *, codec: str, hint: int | None = None
) -> CodedImage:
    """The highest-quality file not larger than ``budget_bytes`` (search over quality 1..100).

    Parameters
    ----------
    image : ndarray of shape (height, width, 3), uint8
    budget_bytes : int
        Largest file size allowed, in bytes (> 0).
    codec : {"jpeg", "webp"}
    hint : int, optional
        A quality to start from (e.g. the previous view's answer): the search gallops out from
        it before bisecting, which takes 2-4 encodes instead of ~8 when the hint is close.

    Returns
    -------
    CodedImage
        With ``budget_bytes`` set. If quality 1 already exceeds the budget, the quality-1 file
        (``within_budget`` False). Otherwise a quality ``q`` that fits while ``q + 1`` does not
        (or ``q`` = 100); with file size non-decreasing in quality this is the highest fitting
        quality.
    """
    _check_codec(codec)
    if isinstance(budget_bytes, bool) or not isinstance(budget_bytes, (int, np.integer)) or (
        budget_bytes <= 0
    ):
        raise ValueError(f"budget_bytes={budget_bytes!r} must be a positive integer")
    budget = int(budget_bytes)
    tried: dict[int, CodedImage] = {}

    def at(q: int) -> CodedImage:
        if q not in tried:
            coded = encode_image(image, codec, q)
            tried[q] = CodedImage(codec, q, coded.data, budget)
        return tried[q]

    def fits(q: int) -> bool:
        return at(q).size_bytes <= budget

    # invariant: quality lo fits (0: none does) and quality hi does not (MAX + 1: all do)
    lo, hi = 0, MAX_QUALITY + 1
    if hint is not None:
        q = min(MAX_QUALITY, max(1, int(hint)))
        step = 1
        if fits(q):
            lo = q
            while lo + step <= MAX_QUALITY and fits(lo + step):
                lo, step = lo + step, step * 2
            hi = min(hi, lo + step)
        else:
            hi = q
            while hi - step >= 1 and not fits(hi - step):
                hi, step = hi - step, step * 2
            lo = max(lo, hi - step)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if fits(mid):
            lo = mid
        else:
            hi = mid
    return at(max(lo, 1))


# =========================================================================== device path


class DevicePath:
    """Frames exactly as a device shows them, with the bytes each one costs on the link.

    Interpolated float scores -> `protocol.scores.encode_scores` (key packet, the model's
    step) -> `protocol.scores.ScoreDecoder` -> the device's reconstruction.

    Parameters
    ----------
    model : host.model.HostModel
    """

    def __init__(self, model: Any) -> None:
        from protocol.scores import ScoreDecoder

        self.model = model
        self.digest = model.digest
        self.decoder = ScoreDecoder(
            model.image.n_coefficients, self.digest, n_components=model.image.n_components
        )
        self._frame = 0

    def packet(self, phi_deg: float, theta_deg: float) -> bytes:
        """The key score packet of a view."""
        from protocol.scores import encode_scores

        self._frame = (self._frame + 1) & 0xFFFFFFFF
        y = self.model.quantized_scores(phi_deg, theta_deg)  # as serve sends (water-filled)
        return encode_scores(
            y, step=self.model.score_step, frame=self._frame, view=(phi_deg, theta_deg),
            image_digest=self.digest, n_components=self.model.image.n_components,
        ).packet

    def frame(self, phi_deg: float, theta_deg: float) -> tuple[np.ndarray, int]:
        """The frame (uint8 (height, width, 3)) and its packet size in bytes."""
        packet = self.packet(phi_deg, theta_deg)
        decoded = self.decoder.decode(packet)
        return self.model.reconstruct(decoded.y), len(packet)

    def projection_frame(self, image: np.ndarray) -> tuple[np.ndarray, int]:
        """The frame from the *true* view's own scores (an oracle: no interpolation).

        ``image`` (uint8 (height, width, 3)) is fitted onto the device's eigenimages
        (`host.model.HostModel.project`, least squares per cell), then sent through the same
        packet (water-filled, the model's step), decoder and reconstruction. It separates
        what the eigenspace can represent from what view interpolation loses, and it is the
        frame ``eigencast serve --scores render`` streams.
        """
        from protocol.scores import encode_scores

        y = self.model.quantize(self.model.project(image))
        self._frame = (self._frame + 1) & 0xFFFFFFFF
        packet = encode_scores(y, step=self.model.score_step, frame=self._frame, view=(0.0, 0.0),
                               image_digest=self.digest,
                               n_components=self.model.image.n_components).packet
        return self.model.reconstruct(self.decoder.decode(packet).y), len(packet)


# =========================================================================== nearest view


def nearest_training_view(
    phi_deg: float, theta_deg: float, train_phi_deg: Any, train_theta_deg: Any
) -> tuple[int, float]:
    """Index of the training view with the smallest great-circle angle, and that angle.

    Parameters
    ----------
    phi_deg, theta_deg : float
        The query view (azimuth, elevation) in degrees.
    train_phi_deg, train_theta_deg : array-like of shape (n_views,)

    Returns
    -------
    (int, float)
        Index into the training views and the angle in degrees (first index on ties).
    """
    tp = np.radians(np.asarray(train_phi_deg, dtype=np.float64))
    tt = np.radians(np.asarray(train_theta_deg, dtype=np.float64))
    if tp.ndim != 1 or tp.shape != tt.shape or tp.size == 0:
        raise ValueError("nearest_training_view: training angles must be 1-D, equal, non-empty")
    p, t = math.radians(phi_deg), math.radians(theta_deg)
    q = np.array([math.cos(t) * math.cos(p), math.cos(t) * math.sin(p), math.sin(t)])
    dirs = np.stack([np.cos(tt) * np.cos(tp), np.cos(tt) * np.sin(tp), np.sin(tt)], axis=1)
    cos = np.clip(dirs @ q, -1.0, 1.0)
    i = int(np.argmax(cos))
    # atan2 of |cross| and dot is accurate for tiny angles too
    angle = math.degrees(math.atan2(float(np.linalg.norm(np.cross(dirs[i], q))), float(cos[i])))
    return i, angle


class _TrainingImages:
    """Training view ``i``: from the training database when it is intact, else re-rendered."""

    def __init__(self, model: Any, scene: Any) -> None:
        self.scene = scene
        views = model.image.views or {}
        self.phi = np.asarray(views.get("phi_deg", []), dtype=np.float64)
        self.theta = np.asarray(views.get("theta_deg", []), dtype=np.float64)
        self.db = self._open_db(model)
        self.source = "database" if self.db is not None else "re-rendered"
        self._cache: dict[int, tuple[np.ndarray, int]] = {}

    def _open_db(self, model: Any) -> Any:
        from host.cinema import CinemaDB

        path = model.image.provenance.get("source_database")
        if not path or not Path(path).is_dir():
            return None
        try:
            db = CinemaDB.open(path)
        except EigencastError:
            return None
        same = (
            db.settings == model.render_settings
            and db.n_views == self.phi.size
            and np.allclose(db.phi_deg, self.phi)
            and np.allclose(db.theta_deg, self.theta)
            and tuple(db.image_shape) == tuple(model.image.image_shape)
        )
        return db if same else None

    def get(self, index: int) -> tuple[np.ndarray, int]:
        """(image uint8 (h, w, 3), PNG size in bytes)."""
        if index not in self._cache:
            if self.db is not None:
                path = self.db.path / self.db.files[index]
                image, size = self.db.read_image(index), path.stat().st_size
            else:
                from host.cinema import encode_png

                image = self.scene.render_rgb8(self.phi[index], self.theta[index])
                size = len(encode_png(image))
            if len(self._cache) > 64:
                self._cache.clear()
            self._cache[index] = (image, size)
        return self._cache[index]


class WebPDatabase:
    """The on-device image database baseline: training views as WebP files, blended locally.

    Every training view is stored as a WebP file at ``quality`` (what a device would hold
    instead of the eigenspace image); a novel view is the blend of the decoded training images
    with the *same interpolation weights* the model uses for its scores
    (``model.interpolator.weights``), rounded to uint8. Nothing is sent per frame.

    Parameters
    ----------
    model : host.model.HostModel
    training : _TrainingImages
        Where the training images come from.
    quality : int
        WebP quality 1..100 (`encode_image`, ``method=6``).
    encode_all : bool, optional
        Encode every training view now, so `storage_bytes` is the exact sum of the files
        (default: when the images come from the training database; re-rendering all of
        them would cost a full database render, so then only the views used are encoded and
        the storage is estimated from their mean size, ``storage_estimated`` True).
    progress : bool
        Progress on stderr while encoding.
    """

    def __init__(self, model: Any, training: _TrainingImages, quality: int, *,
                 encode_all: bool | None = None, progress: bool = False) -> None:
        encode_image(np.zeros((8, 8, 3), np.uint8), "webp", quality)  # checks the quality
        self.model = model
        self.training = training
        self.quality = int(quality)
        self.n_views = int(training.phi.size)
        self._files: dict[int, int] = {}  # index -> file size
        self._decoded: dict[int, np.ndarray] = {}
        if encode_all is None:
            encode_all = training.db is not None
        self.storage_estimated = not encode_all
        if encode_all:
            with _progress("webp database", self.n_views, unit=" views",
                           quiet=not progress) as bar:
                for i in range(self.n_views):
                    self._encode(i, keep=False)
                    bar.advance()

    def _encode(self, index: int, *, keep: bool) -> np.ndarray | None:
        if index in self._decoded:
            return self._decoded[index]
        if self.training.db is not None:
            image = self.training.db.read_image(index)
        else:
            image = self.training.get(index)[0]
        coded = encode_image(image, "webp", self.quality)
        self._files[index] = coded.size_bytes
        if not keep:
            return None
        if len(self._decoded) > 64:
            self._decoded.clear()
        self._decoded[index] = coded.decode()
        return self._decoded[index]

    @property
    def storage_bytes(self) -> int:
        """Sum of the WebP files of every training view (estimated: see the class notes)."""
        if not self._files:
            return 0
        if self.storage_estimated:
            return round(float(np.mean(list(self._files.values()))) * self.n_views)
        return int(sum(self._files.values()))

    def frame(self, phi_deg: float, theta_deg: float) -> np.ndarray:
        """The blended novel view, uint8 (height, width, 3)."""
        idx, w = self.model.interpolator.weights(phi_deg, theta_deg)
        acc: np.ndarray | None = None
        for i, wi in zip(np.asarray(idx).ravel().tolist(), np.asarray(w).ravel().tolist()):
            if wi == 0.0:
                continue
            image = self._encode(int(i), keep=True).astype(np.float32)
            acc = image * np.float32(wi) if acc is None else acc + image * np.float32(wi)
        if acc is None:  # cannot happen: weights sum to 1
            raise EigencastError("webp database: interpolation gave no training view")
        return np.clip(np.rint(acc), 0, 255).astype(np.uint8)


# =========================================================================== engine


@dataclass
class Evaluation:
    """Everything ``eigencast evaluate`` measured.

    Attributes
    ----------
    info : dict
        Model facts: ``method``, ``threshold``, ``components_per_cell``, ``n_coefficients``,
        ``eigenspace_bytes``, ``score_step``, ``image_shape``, ``cell_shape``, ``int8``,
        ``volume`` ...
    views : list of dict
        One record per novel view: ``phi_deg``, ``theta_deg``, ``object_fraction`` and, per
        method (``pca``, ``jpeg``, ``webp``, ``nearest``), a dict of ``bytes_per_view`` and
        the metrics (plus ``quality``/``within_budget`` for codecs, ``index``/``angle_deg``
        for the nearest view).
    rd : list of dict
        Rate-distortion points: ``kind`` (pca/projection/jpeg/webp), ``label``, ``setting``,
        ``bytes_per_view``, ``psnr``, ``ssim``, ``flip``, ``components_per_cell``.
    samples : list of dict
        A few views with their images (``raycast``, ``pca``, ``jpeg``, ``webp``,
        ``flip_pca``, ``flip_jpeg``) for the report.
    timing_s : dict
        Seconds spent per phase.
    """

    info: dict
    views: list[dict]
    rd: list[dict] = field(default_factory=list)
    samples: list[dict] = field(default_factory=list)
    timing_s: dict = field(default_factory=dict)

    def means(self, method: str) -> dict[str, float]:
        """Means over the views of every numeric entry of ``method``'s records."""
        keys: list[str] = []
        for rec in self.views:
            for k, v in rec[method].items():
                if k not in keys and k not in _NOT_AVERAGED and isinstance(v, (int, float)) \
                        and not isinstance(v, bool):
                    keys.append(k)
        out: dict[str, float] = {}
        for k in keys:
            vals = np.array([float(rec[method].get(k, math.nan)) for rec in self.views])
            finite = vals[~np.isnan(vals)]
            out[k] = float(finite.mean()) if finite.size else math.nan
        if method in CODECS:
            out["over_budget_views"] = int(
                sum(not rec[method]["within_budget"] for rec in self.views)
            )
        return out

    def summary(self) -> dict:
        """The ``--json`` object of ``eigencast evaluate``.

        Model facts, the per-method means over the views (`METHODS`: ``pca``,
        ``pca_render``, ``jpeg``, ``webp``, ``nearest``, ``webp_db``), the rate-distortion
        points, the time per phase and the per-view records;
        non-finite floats are ``None``.
        """
        info = self.info
        out = {
            "method": info["method"],
            "threshold": info["threshold"],
            "components_per_cell": info["components_per_cell"],
            "eigenspace_bytes": info["eigenspace_bytes"],
            "views": len(self.views),
            "view_spec": info.get("view_spec"),
            "image_size": [info["image_shape"][1], info["image_shape"][0]],
            "n_coefficients": info["n_coefficients"],
            "score_step": info["score_step"],
            "int8": info.get("int8"),
        }
        for method in METHODS:
            if self.views and method in self.views[0]:
                out[method] = self.means(method)
        if "webp_db" in out:
            out["webp_db"]["storage_bytes"] = info.get("webp_db_storage_bytes")
            out["webp_db"]["storage_estimated"] = info.get("webp_db_storage_estimated")
        out["rate_distortion"] = [
            {k: v for k, v in p.items() if k != "model"} for p in self.rd
        ]
        out["timing_s"] = dict(self.timing_s)
        out["per_view"] = self.views
        return _json_safe(out)


def _json_safe(value: Any) -> Any:
    """Non-finite floats become None (strict JSON); numpy scalars become Python ones."""
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def eigenspace_bytes(model: Any) -> int:
    """Size of the device image (what provisioning sends and a device stores), in bytes."""
    from protocol.image import HEADER_SIZE, image_size, write_image

    if model.path is not None and Path(model.path).is_file():
        with open(model.path, "rb") as f:
            return image_size(f.read(HEADER_SIZE))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "m.ecs"
        write_image(path, model.image, annex=None)
        with open(path, "rb") as f:
            return image_size(f.read(HEADER_SIZE))


def model_info(model: Any) -> dict:
    """Facts about a model for reports: method, T, components per cell, sizes ..."""
    image = model.image
    fit = image.provenance.get("fit") or {}
    render = model.render_settings
    return {
        "path": str(model.path) if model.path else None,
        "method": image.method,
        "threshold": model.threshold,
        "components": fit.get("components"),
        "components_per_cell": float(np.mean(image.n_components)),
        "n_cells": int(image.n_cells),
        "n_coefficients": int(image.n_coefficients),
        "image_shape": [int(v) for v in image.image_shape],
        "cell_shape": [int(v) for v in image.cell_shape],
        "score_step": model.score_step,
        "eigenspace_bytes": eigenspace_bytes(model),
        "training_views": len((image.views or {}).get("phi_deg", [])),
        "training_view_spec": (image.views or {}).get("spec"),
        "interpolation": (image.interpolation or {}).get("method"),
        "int8": image.provenance.get("int8"),
        "target": image.provenance.get("target"),
        "volume": (render.get("volume") or {}),
        "transfer_function": (render.get("transfer_function") or {}).get("name"),
    }


def _pca_settings(
    model: Any, thresholds: Sequence[float], step_factors: Sequence[float]
) -> list[dict]:
    """Truncations / score steps of ``model`` for the rate-distortion sweep."""
    from host.model import score_step_for

    counts = np.asarray(model.image.n_components)
    d = model.image.cell_values
    auto = score_step_for(counts, d)
    factor = model.score_step / auto  # keep the model's step relative to the auto rule
    out: list[dict] = []
    seen: set[bytes] = set()
    levels: list[tuple[str, dict, np.ndarray]] = []
    own_t = model.threshold
    if model.image.method == "adaptive" and own_t is not None and model.eigenvalues is not None:
        for t in sorted({*[t for t in thresholds if t < own_t - 1e-9], own_t}):
            levels.append((f"T={t:g}", {"threshold": t}, model.components_for(threshold=t)))
    else:
        k_max = int(counts.max()) if counts.size else 0
        ks = sorted({max(1, k_max // 8), max(1, k_max // 4), max(1, k_max // 2), k_max})
        for k in ks:
            levels.append((f"k={k}", {"components": k}, model.components_for(components=k)))
    for label, setting, new in levels:
        key = new.tobytes()
        if key in seen or (int(new.sum()) == 0 and counts.sum() > 0):
            continue
        seen.add(key)
        own = np.array_equal(new, counts)
        step = model.score_step if own else score_step_for(new, d) * factor
        out.append({"label": label, "setting": {**setting, "step_factor": 1.0},
                    "counts": new, "step": step, "own": own})
    for f in step_factors:
        out.append({"label": f"step x{f:g}",
                    "setting": {"threshold": own_t, "step_factor": float(f)},
                    "counts": counts, "step": model.score_step * f, "own": False})
    return out


class _Metrics:
    """Run `compare_images` jobs in worker processes (or inline), returning futures.

    The metrics (FLIP above all) are single-threaded and dominate an evaluation, while the
    ray-caster already uses every core only while it renders; a few worker processes keep
    the cores busy in between. ``workers=0`` computes inline.
    """

    def __init__(self, workers: int) -> None:
        self.pool = None
        if workers > 0:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            # spawn, not fork: the parent holds numba's threading layer
            self.pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context(
                "spawn"))

    def submit(self, *args: Any, **kwargs: Any) -> Future:
        if self.pool is not None:
            return self.pool.submit(_compare_job, *args, **kwargs)
        done: Future = Future()
        done.set_result(_compare_job(*args, **kwargs))
        return done

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(cancel_futures=True)


def _compare_job(truth: np.ndarray, test: np.ndarray, mask: np.ndarray | None,
                 keep: bool) -> ImageComparison:
    return compare_images(truth, test, mask=mask, keep_flip_map=keep)


def default_metric_workers() -> int:
    """Metric worker processes by default: the CPU count, at most 2 (0 on one CPU)."""
    import os

    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (
        os.cpu_count() or 1)
    return 0 if cpus < 2 else min(2, cpus)


def evaluate_model(
    model: Any,
    scene: Any,
    views: Any,
    *,
    nearest: bool = True,
    rd_views: int = 8,
    sample_views: int = 4,
    thresholds: Sequence[float] = DEFAULT_THRESHOLDS,
    step_factors: Sequence[float] = DEFAULT_STEP_FACTORS,
    qualities: Sequence[int] = DEFAULT_QUALITIES,
    webp_db_quality: int | None = DEFAULT_WEBP_DB_QUALITY,
    metric_workers: int | None = None,
    progress: bool = True,
    info: dict | None = None,
    on_view: Callable[[int, dict], None] | None = None,
) -> Evaluation:
    """Evaluate ``model`` on novel views ray-cast by ``scene``.

    Parameters
    ----------
    model : host.model.HostModel
    scene : host.render_settings.ViewRenderer
        Ray-casts with the model's own render settings; its image size must be the model's.
    views : host.camera.ViewSet or sequence of (phi_deg, theta_deg)
    nearest : bool
        Also score the angularly nearest training view.
    rd_views : int
        Views (the first ones) used by the rate-distortion sweep; 0 skips it.
    sample_views : int
        Views whose images are kept for side-by-side figures.
    thresholds, step_factors, qualities
        The rate-distortion sweep's settings (see `DEFAULT_THRESHOLDS` ...).
    webp_db_quality : int or None
        WebP quality of the on-device image database baseline (`WebPDatabase`, method
        ``webp_db``); None skips it.
    metric_workers : int, optional
        Processes computing the metrics (default `default_metric_workers`; 0: inline).
    progress : bool
        Progress on stderr.
    info : dict, optional
        Extra facts merged into `Evaluation.info` (e.g. ``view_spec``).
    on_view : callable, optional
        Called as ``on_view(i, record)`` after each view, in order.

    Returns
    -------
    Evaluation
    """
    pairs = [(float(v.phi_deg), float(v.theta_deg)) if hasattr(v, "phi_deg") else
             (float(v[0]), float(v[1])) for v in views]
    if not pairs:
        raise EigencastError("evaluate: no views to evaluate")
    if tuple(scene.image_shape) != tuple(model.image.image_shape):
        raise EigencastError(
            f"evaluate: the renderer makes {scene.image_shape[1]}x{scene.image_shape[0]} images, "
            f"the model is {model.image.image_shape[1]}x{model.image.image_shape[0]}"
        )
    workers = default_metric_workers() if metric_workers is None else int(metric_workers)
    timing = {"raycast": 0.0, "nearest": 0.0, "device": 0.0, "codecs": 0.0, "webp_db": 0.0,
              "metrics_wait": 0.0, "rate_distortion": 0.0}
    evaluation = Evaluation(info={**model_info(model), **(info or {})}, views=[])
    evaluation.info["metric_workers"] = workers
    device = DevicePath(model)
    training = _TrainingImages(model, scene) if nearest or webp_db_quality is not None else None
    if training is not None:
        evaluation.info["nearest_source"] = training.source
    webp_db = None
    if webp_db_quality is not None:
        t0 = time.perf_counter()
        webp_db = WebPDatabase(model, training, webp_db_quality, progress=progress)
        timing["webp_db"] += time.perf_counter() - t0
        evaluation.info["webp_db_quality"] = webp_db.quality
    rd_refs: list[tuple[np.ndarray, np.ndarray, float, float]] = []
    metrics = _Metrics(workers)
    hints: dict[str, int | None] = {c: None for c in CODECS}
    in_flight: list[tuple[int, dict, dict[str, Future], dict | None]] = []

    def finish(bar: Any) -> None:
        i, record, futures, sample = in_flight.pop(0)
        t0 = time.perf_counter()
        results = {name: f.result() for name, f in futures.items()}
        timing["metrics_wait"] += time.perf_counter() - t0
        for name, c in results.items():
            record[name].update(c.values())
        if sample is not None:
            sample.update({f"flip_{name}": results[name].flip_map
                           for name in ("pca", "jpeg", "webp", "webp_db") if name in results})
            evaluation.samples.append(sample)
        evaluation.views.append(record)
        if on_view is not None:
            on_view(i, record)
        bar.advance()

    try:
        with _progress("evaluate", len(pairs), unit=" views", quiet=not progress) as bar:
            for i, (phi, theta) in enumerate(pairs):
                t0 = time.perf_counter()
                truth, alpha = scene.render(phi, theta)
                mask = alpha >= OBJECT_ALPHA_MIN
                t1 = time.perf_counter()
                timing["raycast"] += t1 - t0
                frame, packet_bytes = device.frame(phi, theta)
                # what `serve --scores render|refine` sends: the ray-cast's own scores
                render_frame, render_bytes = device.projection_frame(truth)
                t2 = time.perf_counter()
                timing["device"] += t2 - t1
                coded = {c: encode_within_budget(truth, packet_bytes, codec=c, hint=hints[c])
                         for c in CODECS}
                hints = {c: coded[c].quality for c in CODECS}
                decoded = {c: coded[c].decode() for c in CODECS}
                t3 = time.perf_counter()
                timing["codecs"] += t3 - t2
                keep = i < sample_views
                record: dict[str, Any] = {"phi_deg": phi, "theta_deg": theta,
                                          "object_fraction": float(mask.mean()),
                                          "pca": {"bytes_per_view": packet_bytes}}
                futures = {"pca": metrics.submit(truth, frame, mask, keep)}
                record["pca_render"] = {"bytes_per_view": render_bytes}
                futures["pca_render"] = metrics.submit(truth, render_frame, mask, False)
                for c in CODECS:
                    record[c] = {"bytes_per_view": coded[c].size_bytes,
                                 "quality": coded[c].quality,
                                 "within_budget": coded[c].within_budget}
                    futures[c] = metrics.submit(truth, decoded[c], mask, keep)
                if webp_db is not None:
                    t4 = time.perf_counter()
                    blended = webp_db.frame(phi, theta)
                    timing["webp_db"] += time.perf_counter() - t4
                    record["webp_db"] = {"bytes_per_view": 0, "quality": webp_db.quality}
                    futures["webp_db"] = metrics.submit(truth, blended, mask, keep)
                t3 = time.perf_counter()
                if nearest and training is not None:
                    index, angle = nearest_training_view(phi, theta, training.phi,
                                                         training.theta)
                    near, png_bytes = training.get(index)
                    timing["nearest"] += time.perf_counter() - t3
                    record["nearest"] = {"bytes_per_view": png_bytes, "index": index,
                                         "angle_deg": angle}
                    futures["nearest"] = metrics.submit(truth, near, mask, False)
                sample = None
                if keep:
                    sample = {"phi_deg": phi, "theta_deg": theta, "raycast": truth,
                              "pca": frame, "pca_render": render_frame,
                              "jpeg": decoded["jpeg"], "webp": decoded["webp"],
                              "record": record}
                    if webp_db is not None:
                        sample["webp_db"] = blended
                if i < rd_views:
                    rd_refs.append((truth, mask, phi, theta))
                in_flight.append((i, record, futures, sample))
                while len(in_flight) > max(1, workers):
                    finish(bar)
            while in_flight:
                finish(bar)
        if rd_refs:
            t0 = time.perf_counter()
            evaluation.rd = _rate_distortion(model, rd_refs, thresholds, step_factors,
                                             qualities, metrics, progress=progress)
            timing["rate_distortion"] = time.perf_counter() - t0
            evaluation.info["rd_views"] = len(rd_refs)
    finally:
        metrics.close()
    if webp_db is not None:
        evaluation.info["webp_db_storage_bytes"] = webp_db.storage_bytes
        evaluation.info["webp_db_storage_estimated"] = webp_db.storage_estimated
    evaluation.timing_s = {k: round(v, 3) for k, v in timing.items()}
    return evaluation


def _mean_point(rows: list[dict]) -> dict:
    out = {}
    for k in ("bytes_per_view", "psnr", "ssim", "flip", "psnr_object", "ssim_object",
              "flip_object"):
        vals = np.array([r[k] for r in rows], dtype=np.float64)
        vals = vals[np.isfinite(vals)]
        out[k] = float(vals.mean()) if vals.size else math.nan
    return out


def _rate_distortion(
    model: Any,
    refs: list[tuple[np.ndarray, np.ndarray, float, float]],
    thresholds: Sequence[float],
    step_factors: Sequence[float],
    qualities: Sequence[int],
    metrics: _Metrics,
    *,
    progress: bool,
) -> list[dict]:
    settings = _pca_settings(model, thresholds, step_factors)
    jobs: list[tuple[dict, list[tuple[int, Future]]]] = []
    total = len(settings) + len(CODECS) * len(qualities)
    with _progress("rate-distortion", total, unit=" settings", quiet=not progress) as bar:
        for s in settings:
            m = model if s["own"] else model.truncated(s["counts"], score_step=s["step"])
            path = DevicePath(m)
            point = {"kind": "pca", "label": s["label"], "setting": s["setting"],
                     "own": s["own"], "score_step": s["step"],
                     "components_per_cell": float(np.mean(s["counts"]))}
            rows = []
            for truth, mask, phi, theta in refs:
                frame, size = path.frame(phi, theta)
                rows.append((size, metrics.submit(truth, frame, mask, False)))
            jobs.append((point, rows))
            if s["own"]:  # the oracle: this eigenspace fed the true views' own scores
                rows = []
                for truth, mask, _phi, _theta in refs:
                    frame, size = path.projection_frame(truth)
                    rows.append((size, metrics.submit(truth, frame, mask, False)))
                jobs.append(({**point, "kind": "projection", "label": "projection",
                              "own": False}, rows))
            bar.advance()
        for codec in CODECS:
            for q in qualities:
                rows = []
                for truth, mask, _phi, _theta in refs:
                    coded = encode_image(truth, codec, int(q))
                    rows.append((coded.size_bytes,
                                 metrics.submit(truth, coded.decode(), mask, False)))
                jobs.append(({"kind": codec, "label": f"q={q}", "setting": {"quality": int(q)},
                              "own": False}, rows))
                bar.advance()
    points = []
    for point, rows in jobs:
        values = []
        for size, future in rows:
            c = future.result()
            values.append({"bytes_per_view": size, **c.values()})
        points.append({**point, **_mean_point(values)})
    return points
