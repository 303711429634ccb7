"""The fitted model on the host: database -> eigenspace image (.ecs) -> novel views.

`fit_database` streams a Cinema database into a cell-major stack and fits a
`CellEigenspace`; `build_image` quantizes it and fills the manifest (view set,
interpolation data, score quantization, provenance including the render
settings); `save_model` writes the ``.ecs`` with the float training scores in
the host annex. `HostModel` loads it back and synthesises novel views with the
device's own code (`device_runtime.reconstruct`, `device_runtime.interpolation`),
so what the host measures is what a device shows.

The annex also keeps, per kept component, its eigenvalue and, per cell, the
total variance (the trace), so `HostModel.truncated` can cut a model to any
lower threshold T (or fewer components per cell) without refitting: the
quantization scale is per component, so at 8 bits truncating the int8 model equals
quantizing the truncated float model (with bit allocation, `host.fit.quantize.allocate_bits`,
the kept rows keep the bits chosen for the whole model).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from device_runtime.reconstruct import Reconstructor
from host import __version__
from host.errors import FitError
from host.fit.cells import CellStack
from host.fit.interpolate import ScoreInterpolator
from host.fit.pca import SIGN_CONVENTION, CellEigenspace
from host.fit.quantize import DEFAULT_BIT_BUDGET, quantize_eigenspace, residual_mse
from host.render.cinema import CinemaDB
from protocol.image import EigenspaceImage, read_image, write_image

__all__ = [
    "ANNEX_EIGENVALUES",
    "ANNEX_SCORES",
    "ANNEX_TOTAL_VARIANCE",
    "DEFAULT_SCORE_MSE",
    "INT8_CHECK_VIEWS",
    "HostModel",
    "add_standalone_table",
    "auto_score_step",
    "build_image",
    "components_for_threshold",
    "fit_database",
    "int8_report",
    "read_model_image",
    "save_model",
    "score_step_for",
    "stack_cache",
    "stack_for",
    "standalone_scores",
    "subset_database",
    "truncate_eigenspace",
]

#: Default score quantization: the step whose uniform rounding noise adds this
#: mean squared error (in 0..255 pixel units) to a cell with the mean number
#: of components. Measured (docs/rate-distortion-packets.md, tooth and head at 256 and 512,
#: object pixels of held-out views): 1.0 is the coarsest of 0.25 x 4**n whose object SSIM
#: stays within 0.005 of unquantized scores, and its packets are ~20 % smaller than at the
#: former 0.25; coarser steps keep shrinking packets (4.0: -43 %) but cost 0.006-0.01 SSIM.
DEFAULT_SCORE_MSE = 1.0

#: Views `int8_report` uses (training views for the loss, novel views for float vs int8).
INT8_CHECK_VIEWS = 16

ANNEX_SCORES = "training_scores"
#: float64 (K,): eigenvalue (variance, ddof=1) of each kept component, cell-major.
ANNEX_EIGENVALUES = "eigenvalues"
#: float64 (n_cells,): total variance (trace) of each cell.
ANNEX_TOTAL_VARIANCE = "total_variance"
# Same slack as host.fit.pca's adaptive rule, so truncating to the fitted T keeps every component.
_THRESHOLD_SLACK = 1e-12


def stack_cache(db: CinemaDB, cache_dir: str | os.PathLike | None = None) -> Path:
    """The folder `stack_for` keeps ``db``'s stack in: ``cache_dir``, else
    ``DB.cdb/.eigencast-cache``, else (a read-only database) one under the system's temporary
    folder. Not created here."""
    if cache_dir is not None:
        return Path(cache_dir)
    if os.access(db.path, os.W_OK):
        return db.path / ".eigencast-cache"
    return Path(tempfile.gettempdir()) / "eigencast-cache" / db.path.resolve().name


def _cache_dir(db: CinemaDB, cache_dir: str | os.PathLike | None) -> Path:
    path = stack_cache(db, cache_dir)
    path.mkdir(parents=True, exist_ok=True)
    return path


def stack_for(
    db: CinemaDB,
    cell_shape: tuple[int, int],
    *,
    cache_dir: str | os.PathLike | None = None,
    progress: bool = True,
) -> CellStack:
    """The cell-major uint8 stack of ``db`` for ``cell_shape``, built once and reused.

    Fitting streams its cells from this file (the images of a large database do not fit in
    memory, and a cell's views must lie together); it is kept so that the next fit of the
    database with the same cell size starts at once instead of decoding every image again
    (7 s for 1500 views at 256 px on 2 cores). It lives in `stack_cache` (``DB.cdb/.eigencast-
    cache/`` or ``cache_dir``), uncompressed (3 bytes per pixel per view, padded to whole
    cells: 330 MB for 1500 views at 256 px, 6-50 times the PNGs), and is rebuilt when any
    image file changes (names, sizes, mtimes). The folder keeps this stack only: the others
    in it are deleted, so it holds one stack at most.
    """
    height, width = db.image_shape
    cache = _cache_dir(db, cache_dir)
    name = f"stack-{height}x{width}-cell{cell_shape[0]}x{cell_shape[1]}.u8"
    for old in cache.glob("stack-*.u8*"):
        if old.name not in (name, f"{name}.json") and old.is_file():
            with contextlib.suppress(OSError):
                old.unlink()
    source = CellStack.fingerprint_files([db.path / f for f in db.files])
    return CellStack.build(
        db.iter_images(), db.n_views, height, width, cell_shape[0], cell_shape[1],
        cache / name, source=source, progress=progress,
    )


def fit_database(
    db: CinemaDB,
    *,
    method: str = "adaptive",
    cell: int = 30,
    components: int = 100,
    threshold: float = 0.98,
    cache_dir: str | os.PathLike | None = None,
    progress: bool = True,
    fit_elsewhere: Callable[..., CellEigenspace] | None = None,
) -> CellEigenspace:
    """Fit an eigenspace to every image of ``db`` (streams from a memory-mapped stack).

    ``fit_elsewhere(model, db, cell_shape, progress=...)``, when given, builds the stack and
    fits the unfitted ``model``'s cells somewhere else and returns it fitted (the CLI passes
    `host.cluster.fit_blocks` bound to a Dask cluster: same model, no ``cache_dir``). The fit
    stage itself knows nothing of clusters.
    """
    if method == "standard":
        cell_shape = db.image_shape
    else:
        if not isinstance(cell, int) or cell < 1:
            raise FitError(f"--cell {cell!r}: must be a positive integer")
        cell_shape = (min(cell, db.image_shape[0]), min(cell, db.image_shape[1]))
    model = CellEigenspace(method, cell=cell, components=components, threshold=threshold,
                           progress=progress)
    if fit_elsewhere is not None:
        return fit_elsewhere(model, db, cell_shape, progress=progress)
    stack = stack_for(db, cell_shape, cache_dir=cache_dir, progress=progress)
    return model.fit(stack)


def subset_database(db: CinemaDB, indices: Any) -> CinemaDB:
    """The same database restricted to the views ``indices`` (in that order).

    Used to fit without held-out views; `fit_database` caches its stack separately.
    """
    idx = np.asarray(indices, dtype=np.int64)
    if idx.ndim != 1 or idx.size < 2 or idx.min() < 0 or idx.max() >= db.n_views:
        raise FitError(f"subset of {db.path}: need >= 2 view indices within 0..{db.n_views - 1}")
    return dataclasses.replace(
        db,
        phi_deg=db.phi_deg[idx].copy(),
        theta_deg=db.theta_deg[idx].copy(),
        files=[db.files[i] for i in idx],
    )


def truncate_eigenspace(
    model: CellEigenspace, n_components: np.ndarray, *, threshold: float | None = None,
    components: int | None = None,
) -> CellEigenspace:
    """A shallow copy of a fitted float model keeping the first ``n_components[c]`` per cell.

    Parameters
    ----------
    model : CellEigenspace
        Fitted.
    n_components : ndarray of shape (n_cells,), int
        New counts, each at most the fitted one.
    threshold, components : optional
        Recorded as the copy's ``threshold`` / ``components`` (what the counts correspond to).
    """
    import copy

    old = np.asarray(model.n_components_, dtype=np.int64)
    new = np.asarray(n_components, dtype=np.int64)
    if new.shape != old.shape or (new.size and (new.min() < 0 or np.any(new > old))):
        raise ValueError("truncate_eigenspace: n_components must be (n_cells,) within 0..fitted")
    out = copy.copy(model)
    out.components_ = [c[:k] for c, k in zip(model.components_, new)]
    out.eigenvalues_ = [e[:k] for e, k in zip(model.eigenvalues_, new)]
    out.explained_variance_ratio_ = [r[:k] for r, k in zip(model.explained_variance_ratio_, new)]
    out.n_components_ = new.astype(np.int32)
    offsets = np.zeros(new.size + 1, dtype=np.int64)
    np.cumsum(new, out=offsets[1:])
    out.component_offsets_ = offsets
    keep = (np.arange(int(old.sum())) - np.repeat(model.component_offsets_[:-1], old)) < np.repeat(
        new, old)
    out.scores_ = np.ascontiguousarray(model.scores_[:, keep])
    if threshold is not None:
        out.threshold = float(threshold)
    if components is not None:
        out.components = int(components)
    out.solver_params_ = {**model.solver_params_, "threshold": float(out.threshold),
                          "components": int(out.components)}
    return out


def int8_report(model: CellEigenspace, db: CinemaDB, *, n_views: int = INT8_CHECK_VIEWS,
                quantized: Any = None) -> dict:
    """Measure what int8 quantization costs (recorded in provenance["int8"] by ``fit``).

    The float components exist only while fitting, so the measurement is made here:

    * ``train_*``: ``n_views`` training views (evenly spread) reconstructed from their own
      scores by the float model (rounded to 8 bits) and by the int8 model through the device
      code, each against the training image (`host.fit.quantize.int8_loss_db`);
    * ``novel_psnr_float_vs_int8_db``: the two reconstructions against each other at
      interpolated scores of ``n_views`` novel views (``random:N:7`` directions).

    ``quantized`` is the device model measured (default: `quantize_eigenspace` at 8 bits).

    Returns
    -------
    dict
        ``views``, ``train_psnr_float_db``, ``train_psnr_int8_db``, ``train_loss_db``,
        ``novel_psnr_float_vs_int8_db`` (floats; inf is stored as 999.0).
    """
    from host.fit.quantize import int8_loss_db, quantize_eigenspace
    from host.render.camera import parse_view_set

    if quantized is None:
        quantized = quantize_eigenspace(model)
    count = min(int(n_views), db.n_views)
    idx = np.unique(np.linspace(0, db.n_views - 1, count).round().astype(np.int64))
    images = np.stack([db.read_image(int(i)) for i in idx])
    loss = int8_loss_db(model, images, scores=model.scores_[idx], quantized=quantized)
    interp = ScoreInterpolator(db.phi_deg, db.theta_deg, model.scores_)
    views = parse_view_set(f"random:{count}:7").angles_deg()
    rec = quantized.reconstructor()
    sse = 0.0
    try:
        for phi, theta in views:
            y = interp(phi, theta)
            float_image = np.clip(np.rint(model.inverse_transform(y)), 0, 255)
            sse += float(np.square(float_image - rec.update(y).astype(np.float64)).sum())
    finally:
        rec.close()
    pixels = images[0].size * len(views)
    between = math.inf if sse == 0 else 10.0 * math.log10(255.0**2 * pixels / sse)

    def finite(v: float) -> float:
        return float(v) if math.isfinite(v) else 999.0

    return {
        "views": int(idx.size),
        "train_psnr_float_db": finite(loss.psnr_float_db),
        "train_psnr_int8_db": finite(loss.psnr_int8_db),
        "train_loss_db": finite(loss.loss_db) if math.isfinite(loss.psnr_float_db) else 0.0,
        "novel_psnr_float_vs_int8_db": finite(between),
    }


def auto_score_step(model: Any, *, mse: float = DEFAULT_SCORE_MSE) -> float:
    """Score step whose rounding noise adds ``mse`` to a cell with the mean component count.

    Uniform rounding with step ``s`` has variance ``s**2 / 12`` per coefficient;
    in orthonormal coordinates ``k`` coefficients spread it over ``d`` pixel
    values: ``mse = k * s**2 / (12 * d)``.
    """
    kept = np.asarray(model.n_components_)
    kept = kept[kept > 0]
    if kept.size == 0:
        return 1.0
    d = model.cell_shape_[0] * model.cell_shape_[1] * 3
    return score_step_for(kept, d, mse=mse)


def score_step_for(n_components: np.ndarray, cell_values: int, *, mse: float = DEFAULT_SCORE_MSE
                   ) -> float:
    """`auto_score_step` from component counts (n_cells,) and ``cell_values = cell_h*cell_w*3``."""
    kept = np.asarray(n_components)
    kept = kept[kept > 0]
    if kept.size == 0:
        return 1.0
    return float(math.sqrt(12.0 * mse * cell_values / float(kept.mean())))


def components_for_threshold(
    eigenvalues: np.ndarray,
    n_components: np.ndarray,
    total_variance: np.ndarray,
    threshold: float,
) -> np.ndarray:
    """Per-cell component counts of the adaptive rule at ``threshold``, within the kept ones.

    Parameters
    ----------
    eigenvalues : ndarray of shape (K,), float
        Kept eigenvalues, cell-major, descending within each cell.
    n_components : ndarray of shape (n_cells,), int
        Components kept per cell now.
    total_variance : ndarray of shape (n_cells,), float
        Sum of all eigenvalues of each cell (the trace).
    threshold : float in (0, 1]

    Returns
    -------
    ndarray of shape (n_cells,), int32
        For each cell the fewest ``k`` with ``sum(lambda_1..k) / trace >= threshold``, or all
        kept components when they do not reach it (a cap or a lower fitted T).
    """
    if not 0.0 < float(threshold) <= 1.0:
        raise ValueError(f"threshold={threshold} must be within (0, 1]")
    counts = np.asarray(n_components, dtype=np.int64)
    lam = np.asarray(eigenvalues, dtype=np.float64)
    total = np.asarray(total_variance, dtype=np.float64)
    if lam.shape != (int(counts.sum()),) or total.shape != counts.shape:
        raise ValueError(
            f"components_for_threshold: eigenvalues {lam.shape} / total_variance {total.shape} "
            f"do not match n_components (n_cells={counts.size}, K={int(counts.sum())})"
        )
    offsets = np.concatenate([[0], np.cumsum(counts)])
    cell_of = np.repeat(np.arange(counts.size), counts)
    cum = np.cumsum(lam)
    within = cum - np.repeat(np.concatenate([[0.0], cum])[offsets[:-1]], counts)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = within / total[cell_of]
    short = ~(ratio >= float(threshold) - _THRESHOLD_SLACK)  # NaN (zero trace): keep all
    # k = 1 + number of leading components whose cumulative ratio is still short
    out = np.minimum(np.bincount(cell_of, weights=short, minlength=counts.size).astype(np.int64)
                     + 1, counts)
    return out.astype(np.int32)


def build_image(
    model: CellEigenspace,
    db: CinemaDB,
    *,
    score_step: float | None = None,
    interpolation: str = "auto",
    extra_provenance: dict | None = None,
    measure_int8: bool = True,
    bit_budget: float = DEFAULT_BIT_BUDGET,
) -> tuple[EigenspaceImage, dict[str, np.ndarray]]:
    """Quantize ``model`` into an `EigenspaceImage` plus its host annex.

    Returns
    -------
    image : EigenspaceImage
        Manifest: view set, interpolation data, score step, provenance (fit
        parameters, solver, sign convention, the database's render settings).
    annex : dict
        ``{"training_scores": float32 (n_views, K), "eigenvalues": float64 (K,),
        "total_variance": float64 (n_cells,)}`` for the host.

    Notes
    -----
    With ``measure_int8`` the quality lost to int8 is measured now, while the float model
    exists (`int8_report`), and recorded as ``provenance["int8"]``.

    ``bit_budget`` is `host.fit.quantize.quantize_eigenspace`'s bit allocation (a fraction of the
    model's residual MSE; 0: 8 bits for every component); the bits chosen are summarised in
    ``provenance["eigen_bits"]`` and the int8 measurement covers them.
    """
    step = float(score_step) if score_step is not None else auto_score_step(model)
    if not step > 0:
        raise FitError(f"--score-step {score_step}: must be positive")
    interp = ScoreInterpolator(db.phi_deg, db.theta_deg, model.scores_, method=interpolation)
    quantized = quantize_eigenspace(model, bit_budget=bit_budget)
    bits = quantized.bits if quantized.bits is not None else np.zeros(0, np.int8)
    eigen_bits = {"bit_budget": float(bit_budget),
                  "mse_budget": float(bit_budget * residual_mse(model)),
                  "mean_bits": float(bits.mean()) if bits.size else 8.0,
                  "histogram": {str(int(b)): int(n) for b, n in
                                zip(*np.unique(bits, return_counts=True))}}
    settings = db.settings or {}
    views = {
        "spec": (settings.get("views") or {}).get("spec", "cinema"),
        "phi_deg": [float(p) for p in db.phi_deg],
        "theta_deg": [float(t) for t in db.theta_deg],
    }
    provenance = {
        "eigencast": __version__,
        "created_unix_s": int(time.time()),
        "source_database": str(db.path),
        "fit": {
            "method": model.method,
            "cell": list(model.cell_shape_),
            "components": int(model.components),
            "threshold": float(model.threshold),
            "solver": _jsonable(model.solver_),
            "solver_params": _jsonable(model.solver_params_),
            "sign_convention": SIGN_CONVENTION,
            "mean_components_per_cell": float(np.mean(model.n_components_)),
        },
        "render": settings,
        "eigen_bits": eigen_bits,
        **({"int8": int8_report(model, db, quantized=quantized)} if measure_int8 else {}),
        **(extra_provenance or {}),
    }
    image = quantized.to_image(
        method=model.method,
        image_generation=time.time_ns() // 1_000_000,
        score_quantization={"step": step},
        views=views,
        interpolation=interp.to_manifest(),
        provenance=provenance,
    )
    eigenvalues = [np.asarray(e, dtype=np.float64) for e in model.eigenvalues_]
    annex = {
        ANNEX_SCORES: np.ascontiguousarray(model.scores_, dtype=np.float32),
        ANNEX_EIGENVALUES: (np.concatenate(eigenvalues) if eigenvalues
                            else np.zeros(0, dtype=np.float64)),
        ANNEX_TOTAL_VARIANCE: np.asarray(model.total_variance_, dtype=np.float64),
    }
    return image, annex


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def save_model(
    path: str | os.PathLike,
    image: EigenspaceImage,
    annex: dict[str, np.ndarray],
    *,
    key: bytes | None = None,
) -> bytes:
    """Write the ``.ecs`` atomically; returns its digest."""
    return write_image(path, image, key=key, annex=annex)


def read_model_image(path: str | os.PathLike, *, key: bytes | None = None) -> EigenspaceImage:
    """Read and verify an ``.ecs`` file the way every host command does.

    Structure, digest, the tag when ``key`` is given (a signed image must match it), the
    host annex when the manifest declares one (missing or corrupt: refused) and no trailing
    bytes. `HostModel.load` (``view``, ``serve``, ``evaluate``) and ``provision`` use it.

    Raises
    ------
    ImageFormatError
        One line naming the problem (`ImageTagError` for a wrong tag).
    """
    return read_image(path, key=key, require_annex=True)


@dataclass
class HostModel:
    """An eigenspace image loaded on the host, ready to synthesise novel views.

    Attributes
    ----------
    image : EigenspaceImage
    training_scores : ndarray of shape (n_views, K), float32
    interpolator : ScoreInterpolator
    reconstructor : Reconstructor
        The device's reconstruction code over the int8 eigenspace.
    path : Path or None
        The ``.ecs`` it was read from (None for a model built in memory).
    eigenvalues : ndarray of shape (K,), float64, or None
        Eigenvalue of each kept component (None for images written before the annex had it).
    total_variance : ndarray of shape (n_cells,), float64, or None
        Per-cell trace.
    looks : tuple of str
        The looks of the image it was loaded from (``()``: one look).
    look : str or None
        The look this model shows (None: the image has one).
    """

    image: EigenspaceImage
    training_scores: np.ndarray
    interpolator: ScoreInterpolator
    reconstructor: Reconstructor
    path: Path | None
    eigenvalues: np.ndarray | None = None
    total_variance: np.ndarray | None = None
    looks: tuple[str, ...] = ()
    look: str | None = None

    @classmethod
    def load(
        cls, path: str | os.PathLike, *, key: bytes | None = None, interpolation: str | None = None,
        look: int | str | None = None,
    ) -> HostModel:
        """Read ``path`` (with its annex; verified with ``key`` when given).

        ``look`` (a name or an index; default the first) picks the look of an image with
        several (`device_runtime.looks.look_image`): the model is that look's, with its render
        settings; ``looks`` lists the image's look names and ``look`` the one loaded.

        Raises
        ------
        FitError
            No such look.
        """
        from device_runtime.looks import look_image, look_index, look_names

        image = read_model_image(path, key=key)
        try:
            index = look_index(image, look)
        except ValueError as exc:
            raise FitError(f"{path}: {exc}") from None
        names = look_names(image)
        from host.fit.looks import look_annex

        model = cls.from_image(look_image(image, index), look_annex(image.annex or {}, index),
                               interpolation=interpolation, path=Path(path))
        model.looks, model.look = names, (names[index] if names else None)
        return model

    @classmethod
    def from_image(
        cls,
        image: EigenspaceImage,
        annex: dict[str, np.ndarray],
        *,
        interpolation: str | None = None,
        path: Path | None = None,
    ) -> HostModel:
        """A model from an in-memory image and its annex (e.g. straight from `build_image`)."""
        if ANNEX_SCORES not in annex:
            raise FitError(
                f"{path or 'eigenspace image'}: the host annex has no {ANNEX_SCORES!r} table "
                f"(found {sorted(annex)}); refit the model"
            )
        scores = annex[ANNEX_SCORES]
        table = standalone_scores(image)
        if table is not None:  # fitted --standalone: interpolate what the device holds
            scores = table
        views = image.views or {}
        if interpolation is None:
            interp = ScoreInterpolator.from_manifest(image.interpolation, scores)
        else:
            interp = ScoreInterpolator(views["phi_deg"], views["theta_deg"], scores,
                                       method=interpolation)
        eigenvalues = annex.get(ANNEX_EIGENVALUES)
        total = annex.get(ANNEX_TOTAL_VARIANCE)
        if eigenvalues is not None and eigenvalues.shape != (image.n_coefficients,):
            raise FitError(f"{path}: annex eigenvalues {eigenvalues.shape} do not match "
                           f"K={image.n_coefficients}")
        if total is not None and total.shape != (image.n_cells,):
            raise FitError(f"{path}: annex total_variance {total.shape} does not match "
                           f"n_cells={image.n_cells}")
        return cls(image, scores, interp, Reconstructor.from_image(image), path,
                   eigenvalues, total)

    @property
    def score_step(self) -> float:
        return float(self.image.score_quantization.get("step", 1.0))

    @property
    def render_settings(self) -> dict:
        """The training database's sidecar (empty for databases from other tools)."""
        return self.image.provenance.get("render") or {}

    @property
    def threshold(self) -> float | None:
        """The threshold T the components were chosen with (adaptive), else None."""
        fit = self.image.provenance.get("fit") or {}
        if self.image.method != "adaptive" or "threshold" not in fit:
            return None
        return float(fit["threshold"])

    @property
    def digest(self) -> bytes:
        """The image's SHA-256 digest (32 zero bytes for an image never written)."""
        return self.image.digest or bytes(32)

    def scores(self, phi_deg: float, theta_deg: float) -> np.ndarray:
        """Interpolated float scores (K,) of a view."""
        return self.interpolator(phi_deg, theta_deg)

    def quantized_scores(self, phi_deg: float, theta_deg: float) -> np.ndarray:
        """Scores as a device receives them: rounded to the score step, with the components
        below the water level sent as 0 (`waterfill_mask`)."""
        return self.quantize(self.scores(phi_deg, theta_deg))

    def quantize(self, scores: np.ndarray) -> np.ndarray:
        """Float scores (K,) as a packet carries them: rounded to the score step, the
        components below the water level (`waterfill_mask`) set to 0; float32."""
        step = self.score_step
        q = np.rint(np.asarray(scores) / step)
        zero = self.waterfill_mask()
        if zero is not None:
            q[zero] = 0.0
        return (q * step).astype(np.float32)

    def project(self, image: np.ndarray) -> np.ndarray:
        """The scores (K,) float32 that best reproduce ``image`` on the device.

        ``image`` (uint8 (height, width, 3), e.g. a fresh ray-cast of any view) is fitted,
        per cell, by least squares onto the device's own basis -- the quantized eigenimages
        times their scales, which bit allocation leaves slightly non-orthogonal -- so
        ``reconstruct(project(x))`` is the closest frame to ``x`` this eigenspace can show
        (before score quantization and the uint8 clip). It is what `host.link.serving` streams in
        its ``render``/``refine`` modes: the true view's scores, with no interpolation error.

        Raises
        ------
        ValueError
            ``image`` is not (height, width, 3) of the model's image size.
        """
        from host.fit.cells import split_cells

        img = self.image
        x = np.asarray(image)
        h, w = img.image_shape
        if x.shape != (h, w, 3):
            raise ValueError(f"project: image of shape {x.shape}, the model's is {(h, w, 3)}")
        gram = self._projector()
        cells = split_cells(x[None], img.cell_shape)[0]
        out = np.zeros(img.n_coefficients, dtype=np.float32)
        for c, (lo, hi, inv) in enumerate(gram):
            if hi == lo:
                continue
            d = cells[c].astype(np.float32) - img.mean[c].astype(np.float32)
            v = img.eigenimages[lo:hi]
            scale = img.scales[lo:hi]
            fit = inv @ (v.astype(np.float32) @ d)
            out[lo:hi] = np.divide(fit, scale, out=np.zeros_like(fit), where=scale != 0)
        return out

    def _projector(self) -> list[tuple[int, int, np.ndarray]]:
        """Per cell (first row, end row, inverse Gram matrix of its int8 rows); cached."""
        cached = getattr(self, "_gram", None)
        if cached is not None:
            return cached
        img = self.image
        counts = np.asarray(img.n_components, dtype=np.int64)
        ends = np.cumsum(counts)
        out = []
        for c in range(img.n_cells):
            lo, hi = int(ends[c] - counts[c]), int(ends[c])
            v = img.eigenimages[lo:hi].astype(np.float64)
            out.append((lo, hi, np.linalg.pinv(v @ v.T).astype(np.float32)))
        self._gram = out
        return out

    def waterfill_mask(self, step: float | None = None) -> np.ndarray | None:
        """Components a packet at ``step`` sends as 0 (reverse water-filling), or None.

        Rounding at step ``s`` costs each coefficient ``s**2 / 12`` of squared error; a
        component whose eigenvalue (its scores' variance over the training views) is below
        that costs less when it is not sent at all, and its zeros shorten the packet
        (per-cell end-of-block coding). Only images whose annex holds the eigenvalues
        (every ``fit`` since they were added) have a mask; ``score_quantization["waterfill"]
        = False`` in the manifest turns it off. Images with a standalone table have none: a
        standalone device cannot apply it (`add_standalone_table` zeroes those columns of
        the table instead, so both show the same frames).

        Returns
        -------
        ndarray of shape (K,), bool, or None
        """
        quant = self.image.score_quantization
        if self.eigenvalues is None or not quant.get("waterfill", True):
            return None
        if "table_step" in quant:  # standalone: the device rounds the table's rows only
            return None
        s = self.score_step if step is None else float(step)
        cached = getattr(self, "_waterfill", None)
        if cached is None or cached[0] != s:
            cached = (s, np.asarray(self.eigenvalues) < s * s / 12.0)
            self._waterfill = cached
        return cached[1]

    def reconstruct(self, scores: np.ndarray) -> np.ndarray:
        """uint8 (H, W, 3) frame for coefficient vector ``scores`` (a copy)."""
        return self.reconstructor.update(np.asarray(scores, dtype=np.float32)).copy()

    def view(self, phi_deg: float, theta_deg: float) -> np.ndarray:
        """The frame a device shows for this view (quantized scores, int8 eigenspace)."""
        return self.reconstruct(self.quantized_scores(phi_deg, theta_deg))

    # ------------------------------------------------------------------ truncation

    def components_for(
        self, *, threshold: float | None = None, components: int | None = None
    ) -> np.ndarray:
        """Per-cell counts (n_cells,) int32 at a lower ``threshold`` or at most ``components``.

        Raises
        ------
        FitError
            ``threshold`` asked of a model without annexed eigenvalues.
        """
        counts = np.asarray(self.image.n_components, dtype=np.int32)
        if (threshold is None) == (components is None):
            raise ValueError("components_for: give exactly one of threshold, components")
        if components is not None:
            if components < 0:
                raise ValueError(f"components={components} must be >= 0")
            return np.minimum(counts, int(components)).astype(np.int32)
        if self.eigenvalues is None or self.total_variance is None:
            raise FitError(
                f"{self.path or 'model'}: no eigenvalues in the annex (written by an older "
                "eigencast); refit to truncate by threshold"
            )
        return components_for_threshold(self.eigenvalues, counts, self.total_variance,
                                         threshold)

    def truncated(
        self,
        n_components: np.ndarray,
        *,
        score_step: float | None = None,
        provenance: dict | None = None,
    ) -> HostModel:
        """The model keeping only the first ``n_components[c]`` components of each cell.

        Parameters
        ----------
        n_components : ndarray of shape (n_cells,), int
            New counts, each at most the current one.
        score_step : float, optional
            Score quantization step of the new model (default: keep the current one).
        provenance : dict, optional
            Entries merged into the new image's provenance.

        Returns
        -------
        HostModel
            In memory (``path`` None); its image keeps this image's digest until written.
        """
        old = np.asarray(self.image.n_components, dtype=np.int64)
        new = np.asarray(n_components, dtype=np.int64)
        if new.shape != old.shape or (new.size and (new.min() < 0 or np.any(new > old))):
            raise ValueError(
                f"truncated: n_components must be (n_cells={old.size},) ints within 0..current"
            )
        keep = (np.arange(int(old.sum())) - np.repeat(np.concatenate([[0], np.cumsum(old)])[:-1],
                                                       old)) < np.repeat(new, old)
        prov = dict(self.image.provenance)
        if provenance:
            prov.update(provenance)
        quant = dict(self.image.score_quantization)
        if score_step is not None:
            if not score_step > 0:
                raise ValueError(f"score_step={score_step} must be positive")
            quant["step"] = float(score_step)
        image = dataclasses.replace(
            self.image,
            eigenimages=np.ascontiguousarray(self.image.eigenimages[keep]),
            scales=np.ascontiguousarray(self.image.scales[keep]),
            n_components=new.astype(np.int32),
            score_quantization=quant,
            provenance=prov,
            annex=None,
            # a standalone score table has the old K columns: the truncated model has none
            sections={k: v for k, v in self.image.sections.items()
                      if k not in ("standalone_scores", "standalone_scores_delta")},
        )
        annex = {ANNEX_SCORES: np.ascontiguousarray(self.training_scores[:, keep])}
        if self.eigenvalues is not None:
            annex[ANNEX_EIGENVALUES] = np.ascontiguousarray(self.eigenvalues[keep])
        if self.total_variance is not None:
            annex[ANNEX_TOTAL_VARIANCE] = self.total_variance
        model = HostModel.from_image(image, annex)
        model.image.annex = annex
        return model

    def annex(self) -> dict[str, np.ndarray]:
        """The host annex to write with `save_model`."""
        annex = {ANNEX_SCORES: self.training_scores}
        if self.eigenvalues is not None:
            annex[ANNEX_EIGENVALUES] = self.eigenvalues
        if self.total_variance is not None:
            annex[ANNEX_TOTAL_VARIANCE] = self.total_variance
        return annex


# --------------------------------------------------------------------------- standalone


def add_standalone_table(
    image: EigenspaceImage,
    training_scores: np.ndarray,
    *,
    eigenvalues: np.ndarray | None = None,
    table_step: float | None = None,
    delta: bool | None = None,
) -> dict:
    """Store the training views' scores in ``image`` for a standalone device (in place).

    The scores are quantized at ``table_step`` (default: the image's packet step
    ``score_quantization["step"]``; recorded as ``"table_step"``) into int16 when every value
    fits, else int32. With ``eigenvalues``, the components a packet at the image's step sends
    as 0 (reverse water-filling, `HostModel.waterfill_mask`) are 0 in the table too, so a
    standalone device shows what a served one shows. With ``delta`` an int16 table is stored
    as `device_runtime.runtime.STANDALONE_DELTA_SECTION`: per component, the differences
    between consecutive views along theta rings (phi ascending: 3.6 degrees apart on the
    paper's grid), zigzag-mapped, in a low-byte and a high-byte plane, which zstd packs
    ~30 % smaller than the plain table (docs/rate-distortion-packets.md); the device undoes
    it once when it loads the image (`device_runtime.runtime.standalone_table`).
    ``delta=False`` writes the plain table (`device_runtime.runtime.STANDALONE_SECTION`)
    that older devices read; ``None`` (default) compresses both and keeps the smaller
    (sparse view sets, whose neighbours differ a lot, can favour the plain table; int32
    tables are always plain).

    Parameters
    ----------
    image : EigenspaceImage
        With its interpolation manifest (views in the order of ``training_scores``).
    training_scores : ndarray of shape (n_views, K), float
    eigenvalues : ndarray of shape (K,), optional
        The annex's eigenvalues (enables the water-filled zero columns).
    table_step : float, optional
        Quantization step of the table (> 0).
    delta : bool or None
        Store the delta-coded section (True), the plain one (False), or the smaller (None).

    Returns
    -------
    dict
        ``dtype``, ``shape``, ``raw_bytes`` (uncompressed), ``step``, ``section`` and
        ``zero_columns``.
    """
    from device_runtime.standalone import (
        STANDALONE_DELTA_SECTION,
        STANDALONE_SECTION,
        delta_encode,
        standalone_order,
    )

    scores = np.asarray(training_scores, dtype=np.float64)
    n_views = (image.interpolation or {}).get("n_views")
    if scores.ndim != 2 or scores.shape != (n_views, image.n_coefficients):
        raise FitError(
            f"standalone table: training scores {scores.shape} do not match the image "
            f"(n_views={n_views}, K={image.n_coefficients})"
        )
    packet_step = float(image.score_quantization.get("step", 1.0))
    step = packet_step if table_step is None else float(table_step)
    if not (math.isfinite(step) and step > 0):
        raise FitError(f"standalone table: table step {table_step!r} must be > 0")
    q = np.rint(scores / step)
    zero = np.zeros(scores.shape[1], dtype=bool)
    if eigenvalues is not None:
        lam = np.asarray(eigenvalues, dtype=np.float64)
        if lam.shape != (scores.shape[1],):
            raise FitError(f"standalone table: eigenvalues {lam.shape} do not match "
                           f"K={scores.shape[1]}")
        if image.score_quantization.get("waterfill", True):
            zero = lam < packet_step * packet_step / 12.0
            q[:, zero] = 0.0
    limit = float(np.abs(q).max()) if q.size else 0.0
    if limit > 2**31 - 1:
        raise FitError(f"standalone table: |score / step| reaches {limit:.3g}, over int32")
    dtype = np.int16 if limit <= 32767 else np.int32
    table = q.astype(dtype)
    for name in (STANDALONE_SECTION, STANDALONE_DELTA_SECTION):
        image.sections.pop(name, None)
    plain = np.ascontiguousarray(table)
    coded = None
    if dtype == np.int16 and delta is not False:
        coded = delta_encode(table, standalone_order(image, scores.shape[0]))
    if coded is not None and delta is None:
        import zstandard

        from protocol.image import DEFAULT_LEVEL

        cctx = zstandard.ZstdCompressor(level=DEFAULT_LEVEL)
        if len(cctx.compress(coded.tobytes())) >= len(cctx.compress(plain.tobytes())):
            coded = None
    if coded is not None:
        section = STANDALONE_DELTA_SECTION
    else:
        coded, section = plain, STANDALONE_SECTION
    image.sections[section] = coded
    image.score_quantization = {**image.score_quantization, "table_step": step}
    return {"dtype": np.dtype(dtype).name, "shape": list(table.shape),
            "raw_bytes": int(table.nbytes), "step": step, "section": section,
            "zero_columns": int(zero.sum())}


def standalone_scores(image: EigenspaceImage) -> np.ndarray | None:
    """The image's standalone table dequantized, float32 (n_views, K); None without one.

    ``float32(q) * float32(table_step)``: the rows a standalone device blends.
    """
    from device_runtime.runtime import standalone_table

    found = standalone_table(image)
    if found is None:
        return None
    table, step = found
    return table.astype(np.float32) * np.float32(step)
