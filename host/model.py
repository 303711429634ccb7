"""The fitted model on the host: database -> eigenspace image (.ecs) -> novel views.

`fit_database` streams a Cinema database into a cell-major stack and fits a
`CellEigenspace`; `build_image` quantizes it and fills the manifest (view set,
interpolation data, score quantization, provenance including the render
settings); `save_model` writes the ``.ecs`` with the float training scores in
the host annex. `HostModel` loads it back and synthesises novel views with the
device's own code (`device_runtime.reconstruct`, `device_runtime.interpolation`),
so what the host measures is what a device shows.
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from device_runtime.reconstruct import Reconstructor
from host import __version__
from host.cinema import CinemaDB
from host.errors import FitError
from host.interpolate import ScoreInterpolator
from host.pca import SIGN_CONVENTION, CellEigenspace, CellStack
from host.quantize import quantize_eigenspace
from protocol.image import EigenspaceImage, read_image, write_image

__all__ = [
    "DEFAULT_SCORE_MSE",
    "HostModel",
    "auto_score_step",
    "build_image",
    "fit_database",
    "save_model",
    "stack_for",
]

#: Default score quantization: the step whose uniform rounding noise adds this
#: mean squared error (in 0..255 pixel units) to a cell with the mean number
#: of components. 0.25 is ~54 dB: invisible next to the interpolation error.
DEFAULT_SCORE_MSE = 0.25

ANNEX_SCORES = "training_scores"


def _cache_dir(db: CinemaDB, cache_dir: str | os.PathLike | None) -> Path:
    if cache_dir is not None:
        path = Path(cache_dir)
    else:
        path = db.path / ".eigencast-cache"
        if not os.access(db.path, os.W_OK):
            path = Path(tempfile.gettempdir()) / "eigencast-cache" / db.path.resolve().name
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

    The stack lives in ``DB.cdb/.eigencast-cache/`` (or ``cache_dir``) and is
    rebuilt when any image file changes (names, sizes, mtimes).
    """
    height, width = db.image_shape
    cache = _cache_dir(db, cache_dir)
    name = f"stack-{height}x{width}-cell{cell_shape[0]}x{cell_shape[1]}.u8"
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
) -> CellEigenspace:
    """Fit an eigenspace to every image of ``db`` (streams from a memory-mapped stack)."""
    if method == "standard":
        cell_shape = db.image_shape
    else:
        if not isinstance(cell, int) or cell < 1:
            raise FitError(f"--cell {cell!r}: must be a positive integer")
        cell_shape = (min(cell, db.image_shape[0]), min(cell, db.image_shape[1]))
    stack = stack_for(db, cell_shape, cache_dir=cache_dir, progress=progress)
    model = CellEigenspace(method, cell=cell, components=components, threshold=threshold)
    return model.fit(stack)


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
    return float(math.sqrt(12.0 * mse * d / float(kept.mean())))


def build_image(
    model: CellEigenspace,
    db: CinemaDB,
    *,
    score_step: float | None = None,
    interpolation: str = "auto",
    extra_provenance: dict | None = None,
) -> tuple[EigenspaceImage, dict[str, np.ndarray]]:
    """Quantize ``model`` into an `EigenspaceImage` plus its host annex.

    Returns
    -------
    image : EigenspaceImage
        Manifest: view set, interpolation data, score step, provenance (fit
        parameters, solver, sign convention, the database's render settings).
    annex : dict
        ``{"training_scores": float32 (n_views, K)}`` for the host.
    """
    step = float(score_step) if score_step is not None else auto_score_step(model)
    if not step > 0:
        raise FitError(f"--score-step {score_step}: must be positive")
    interp = ScoreInterpolator(db.phi_deg, db.theta_deg, model.scores_, method=interpolation)
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
        **(extra_provenance or {}),
    }
    image = quantize_eigenspace(model).to_image(
        method=model.method,
        image_generation=time.time_ns() // 1_000_000,
        score_quantization={"step": step},
        views=views,
        interpolation=interp.to_manifest(),
        provenance=provenance,
    )
    return image, {ANNEX_SCORES: np.ascontiguousarray(model.scores_, dtype=np.float32)}


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
    path : Path
    """

    image: EigenspaceImage
    training_scores: np.ndarray
    interpolator: ScoreInterpolator
    reconstructor: Reconstructor
    path: Path

    @classmethod
    def load(
        cls, path: str | os.PathLike, *, key: bytes | None = None, interpolation: str | None = None
    ) -> HostModel:
        """Read ``path`` (with its annex; verified with ``key`` when given)."""
        image = read_image(path, key=key, require_annex=True)
        scores = image.annex[ANNEX_SCORES]
        views = image.views or {}
        if interpolation is None:
            interp = ScoreInterpolator.from_manifest(image.interpolation, scores)
        else:
            interp = ScoreInterpolator(views["phi_deg"], views["theta_deg"], scores,
                                       method=interpolation)
        return cls(image, scores, interp, Reconstructor.from_image(image), Path(path))

    @property
    def score_step(self) -> float:
        return float(self.image.score_quantization.get("step", 1.0))

    @property
    def render_settings(self) -> dict:
        """The training database's sidecar (empty for databases from other tools)."""
        return self.image.provenance.get("render") or {}

    def scores(self, phi_deg: float, theta_deg: float) -> np.ndarray:
        """Interpolated float scores (K,) of a view."""
        return self.interpolator(phi_deg, theta_deg)

    def quantized_scores(self, phi_deg: float, theta_deg: float) -> np.ndarray:
        """Scores as a device receives them: rounded to the score step."""
        step = self.score_step
        return (np.rint(self.scores(phi_deg, theta_deg) / step) * step).astype(np.float32)

    def reconstruct(self, scores: np.ndarray) -> np.ndarray:
        """uint8 (H, W, 3) frame for coefficient vector ``scores`` (a copy)."""
        return self.reconstructor.update(np.asarray(scores, dtype=np.float32)).copy()

    def view(self, phi_deg: float, theta_deg: float) -> np.ndarray:
        """The frame a device shows for this view (quantized scores, int8 eigenspace)."""
        return self.reconstruct(self.quantized_scores(phi_deg, theta_deg))
