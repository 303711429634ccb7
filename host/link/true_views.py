"""The scores of freshly ray-cast views, and the renderer `serve`'s frame sources ray-cast with.

:class:`TrueViewScores` ray-casts a view with the model's recorded render settings and
projects it on the eigenspace (the frame a device makes from it has no view-interpolation
error); :func:`open_true_view_scores` builds it from a model (`host.link.serving` takes its
renderer for the sparse ray-casts of `host.fit.motion.MotionScores`).
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from typing import Any

import numpy as np

from host.fit.model import HostModel
from host.link.errors import ServeError

__all__ = ["TrueViewScores", "open_true_view_scores"]


class TrueViewScores:
    """Scores of freshly ray-cast views: ``model.project(renderer.render(view)[0])``.

    The frame a device makes from them is the eigenspace's best approximation of the true
    view (the *projection*, docs/design-notes.md), with no view-interpolation error.
    The last ``cache`` views are remembered (a device asking for a key frame, or going back
    and forth, costs no new ray-cast).

    Parameters
    ----------
    model : HostModel
    renderer : host.render.settings.ViewRenderer
        Built from the model's recorded render settings (`open_true_view_scores`).
    cache : int
    """

    def __init__(self, model: HostModel, renderer: Any, *, cache: int = 64) -> None:
        if tuple(renderer.image_shape) != tuple(model.image.image_shape):
            raise ServeError(
                f"the renderer makes {renderer.image_shape[1]}x{renderer.image_shape[0]} "
                f"images, the model is {model.image.image_shape[1]}x"
                f"{model.image.image_shape[0]}")
        self.model = model
        self.renderer = renderer
        self._cache: OrderedDict[tuple[float, float], np.ndarray] = OrderedDict()
        self._size = max(1, int(cache))
        self._lock = threading.Lock()
        self.renders = 0
        self.render_seconds = 0.0

    def __call__(self, view: tuple[float, float]) -> np.ndarray:
        """Float32 scores (K,) of ``view`` (canonical: phi in [0, 360), degrees)."""
        key = (float(view[0]), float(view[1]))
        with self._lock:
            hit = self._cache.get(key)
            if hit is not None:
                self._cache.move_to_end(key)
                return hit
        t0 = time.perf_counter()
        rgb, _alpha = self.renderer.render(*key)
        y = self.model.project(rgb)
        with self._lock:
            self.renders += 1
            self.render_seconds += time.perf_counter() - t0
            self._cache[key] = y
            while len(self._cache) > self._size:
                self._cache.popitem(last=False)
        return y


def open_true_view_scores(
    model: HostModel, volume: str | None = None, *, workers: int | None = None
) -> TrueViewScores:
    """`TrueViewScores` for ``model``, ray-casting with its recorded render settings.

    ``volume`` replaces the recorded volume source (a moved file); the model's render
    settings check that it is the same volume (dims, spacing).

    Raises
    ------
    EigencastError
        The model records no render settings, or the volume cannot be loaded or is
        another one (one line for the user).
    """
    from host.render.settings import RenderSettings, ViewRenderer

    recorded = model.render_settings
    if not recorded:
        raise ServeError(
            f"{model.path or 'the model'} records no render settings (its training database "
            "was not made by eigencast render), so its views cannot be ray-cast")
    settings = RenderSettings.from_record(recorded, what=str(model.path or "the model"))
    renderer = ViewRenderer.open(settings, volume, workers=workers,
                                 what=str(model.path or "the model"))
    return TrueViewScores(model, renderer)
