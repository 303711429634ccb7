"""What the eigenspace is compared with: equal-bytes JPEG/WebP, the nearest training view
and the on-device WebP image database.

Equal-bytes codecs
------------------
`encode_within_budget` finds, by bisection over Pillow's quality 1..100, the highest quality whose
file is not larger than a byte budget (JPEG: ``optimize=True``, 4:2:0; WebP: ``method=6``). It
keeps the invariant "quality lo fits, quality hi does not", so the answer's ``quality + 1``
always exceeds the budget; if even quality 1 does not fit it says so (``within_budget`` False)
and returns that file.

Equal-quality codecs
--------------------
`CodecLadder` codes one image at any quality on demand (each file once) and finds the
smallest file whose decoded image reaches a quality (`CodecLadder.smallest`; a measure of
the caller's: object SSIM, SSIM, FLIP ...): a bisection over the quality setting keeping
"lo misses, hi reaches", starting from a hint (the last view's answer) when given. A
codec's quality is not strictly monotone in its setting, so the answer is the smallest file
among the settings tried that reaches the target.
"""

from __future__ import annotations

import io
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from host.errors import EigencastError
from host.progress import progress as _progress

__all__ = [
    "CODECS",
    "MAX_QUALITY",
    "CodecLadder",
    "CodedImage",
    "TrainingImages",
    "WebPDatabase",
    "decode_image",
    "encode_image",
    "encode_within_budget",
    "nearest_training_view",
    "webp_database_frames",
]

CODECS = ("jpeg", "webp", "avif")
"""The codecs `encode_image` speaks (AVIF through Pillow's plugin): the equal-bytes baselines
`eigencast evaluate` reports."""
MAX_QUALITY = 100


@dataclass(frozen=True, eq=False)
class CodedImage:
    """An image encoded by a codec at one quality.

    Attributes
    ----------
    codec : {"jpeg", "webp", "avif"}
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
    elif codec == "avif":  # speed 4: near libavif's best size for a few ms more per frame
        pil.save(buf, format="AVIF", quality=int(quality), speed=4)
    else:
        pil.save(buf, format="WEBP", quality=int(quality), method=6)
    return CodedImage(codec, int(quality), buf.getvalue())


def decode_image(data: bytes) -> np.ndarray:
    """Decode a JPEG/WebP/AVIF/PNG file's bytes to uint8 (height, width, 3)."""
    from PIL import Image

    with Image.open(io.BytesIO(data)) as im:
        im.load()
        return np.asarray(im.convert("RGB"), dtype=np.uint8)


def _bisect(lo: int, hi: int, below: Callable[[int], bool]) -> tuple[int, int]:
    """Narrow ``lo < hi`` to neighbouring qualities by bisection, keeping ``below(lo)`` true
    and ``below(hi)`` false (the search never asks ``below`` of ``lo`` or ``hi`` itself)."""
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if below(mid):
            lo = mid
        else:
            hi = mid
    return lo, hi


def encode_within_budget(
    image: np.ndarray, budget_bytes: int, *, codec: str, hint: int | None = None
) -> CodedImage:
    """The highest-quality file not larger than ``budget_bytes`` (search over quality 1..100).

    Parameters
    ----------
    image : ndarray of shape (height, width, 3), uint8
    budget_bytes : int
        Largest file size allowed, in bytes (> 0).
    codec : {"jpeg", "webp", "avif"}
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
    lo, hi = _bisect(lo, hi, fits)
    return at(max(lo, 1))

class CodecLadder:
    """One image coded by one codec at any quality on demand, and the smallest file whose
    decoded image reaches a quality (module docstring).

    Parameters
    ----------
    image : ndarray of shape (height, width, 3), uint8
    codec : {"jpeg", "webp", "avif"}
    measure : callable
        ``measure(decoded, name) -> dict``: the value called ``name`` of a decoded file
        (and any others computed on the way, e.g. whole-frame and object SSIM from one SSIM
        map); each is kept per quality setting.
    """

    def __init__(self, image: np.ndarray, codec: str,
                 measure: Any) -> None:
        _check_codec(codec)
        self.image = image
        self.codec = codec
        self.measure = measure
        self._files: dict[int, CodedImage] = {}
        self._decoded: dict[int, np.ndarray] = {}
        self._values: dict[int, dict[str, float]] = {}

    def file(self, quality: int) -> CodedImage:
        """The file at ``quality`` (1..100), coded once."""
        if quality not in self._files:
            self._files[quality] = encode_image(self.image, self.codec, quality)
        return self._files[quality]

    def decoded(self, quality: int) -> np.ndarray:
        """The file at ``quality`` decoded (Pillow), uint8 (height, width, 3)."""
        if quality not in self._decoded:
            self._decoded[quality] = self.file(quality).decode()
        return self._decoded[quality]

    def value(self, quality: int, name: str) -> float:
        """``measure``'s ``name`` of the file at ``quality``."""
        values = self._values.setdefault(quality, {})
        if name not in values:
            values.update(self.measure(self.decoded(quality), name))
        return float(values[name])

    def values(self, quality: int) -> dict[str, float]:
        """Every value measured so far of the file at ``quality``."""
        return dict(self._values.get(quality, {}))

    def smallest(self, target: float, name: str, *, higher_is_better: bool = True,
                 hint: int | None = None) -> CodedImage | None:
        """The smallest file whose ``name`` reaches ``target`` (at least it, or at most it
        where lower is better), or None when even quality 100 does not.

        A bisection over the quality keeping "lo misses, hi reaches" (from ``hint`` and
        ``hint - 8`` first when given), then the smallest of the files tried that reach it.
        """
        def reaches(q: int) -> bool:
            v = self.value(q, name)
            return v >= target if higher_is_better else v <= target

        if not reaches(MAX_QUALITY):
            return None
        lo, hi = 0, MAX_QUALITY  # quality lo misses (0: none tried), hi reaches
        if hint is not None and 1 <= hint < MAX_QUALITY:
            if reaches(hint):
                hi = hint
                below = max(1, hint - 8)
                if below < hint:
                    if reaches(below):
                        hi = below
                    else:
                        lo = below
            else:
                lo = hint
        lo, hi = _bisect(lo, hi, lambda q: not reaches(q))
        tried = [q for q in self._values if name in self._values[q] and reaches(q)]
        return min((self._files[q] for q in tried), key=lambda c: (c.size_bytes, c.quality))


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


class TrainingImages:
    """Training view ``i``: from the training database when it is intact, else re-rendered.

    Parameters
    ----------
    model : host.fit.HostModel
        Its provenance names the training database; its views are the training views.
    scene : host.render.ViewRenderer or None
        Re-renders a view when the database is gone or differs from the model's settings
        (None: the database must be intact).
    """

    def __init__(self, model: Any, scene: Any) -> None:
        self.scene = scene
        views = model.image.views or {}
        self.phi = np.asarray(views.get("phi_deg", []), dtype=np.float64)
        self.theta = np.asarray(views.get("theta_deg", []), dtype=np.float64)
        self.db = self._open_db(model)
        self.source = "database" if self.db is not None else "re-rendered"
        self._cache: dict[int, tuple[np.ndarray, int]] = {}

    def _open_db(self, model: Any) -> Any:
        from host.render.cinema import CinemaDB

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
                from host.render.cinema import encode_png

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
    model : host.fit.model.HostModel
    training : TrainingImages
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

    def __init__(self, model: Any, training: TrainingImages, quality: int, *,
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


def webp_database_frames(
    db: Any, weights: Sequence[tuple[Any, Any]], quality: int
) -> tuple[int, list[np.ndarray]]:
    """The on-device WebP image database of a whole Cinema database, at one quality.

    Every view of ``db`` is stored as WebP at ``quality`` (the storage the device would hold
    instead of the eigenspace image) and each novel view is the blend of the decoded training
    views with its interpolation weights, rounded to uint8 -- `WebPDatabase` for views that
    do not come from a model (the rate-distortion scripts).

    Parameters
    ----------
    db : host.render.cinema.CinemaDB
        The training views.
    weights : sequence of (indices, weights)
        Per novel view, what ``ScoreInterpolator.weights(phi, theta)`` returns.
    quality : int
        WebP quality 1..100 (`encode_image`).

    Returns
    -------
    (int, list of ndarray)
        Total bytes of the WebP files and the blended frames, uint8 (height, width, 3).
    """
    needed = {int(i) for idx, _ in weights for i in np.asarray(idx).ravel()}
    total = 0
    decoded: dict[int, np.ndarray] = {}
    for i in range(db.n_views):
        coded = encode_image(db.read_image(i), "webp", quality)
        total += coded.size_bytes
        if i in needed:
            decoded[i] = decode_image(coded.data).astype(np.float32)
    frames = []
    for idx, w in weights:
        img = sum(float(wi) * decoded[int(ii)] for ii, wi in zip(np.asarray(idx).ravel(),
                                                                 np.asarray(w).ravel()))
        frames.append(np.clip(np.rint(img), 0, 255).astype(np.uint8))
    return total, frames
