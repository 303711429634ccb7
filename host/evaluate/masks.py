"""Object masks: which pixels of a view show the object.

Ray-casts have a black background, so a metric averaged over every pixel flatters a view
that is mostly background; the evaluation (and the research scripts) average over the
*object pixels* instead. Two ways to find them:

* `alpha_object_mask`: from the ray-caster's accumulated opacity (``alpha >=
  host.render.settings.OBJECT_ALPHA_MIN``), exact, when the view is ray-cast at hand;
* `object_mask`: from the image alone (a channel above `OBJECT_LEVEL`), for stored views
  whose opacity was not kept (a Cinema database's PNGs).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from host.render.settings import OBJECT_ALPHA_MIN

__all__ = ["OBJECT_LEVEL", "alpha_object_mask", "object_mask"]

#: A pixel whose largest channel is above this (0..255) is an object pixel (`object_mask`).
OBJECT_LEVEL = 2


def object_mask(image: Any) -> np.ndarray:
    """Bool (height, width): the pixels the object covers (black background elsewhere).

    Parameters
    ----------
    image : array-like of shape (height, width, 3), uint8
    """
    return np.asarray(image).max(axis=2) > OBJECT_LEVEL


def alpha_object_mask(alpha: Any) -> np.ndarray:
    """Bool (height, width): object pixels from a ray-cast's accumulated opacity.

    Parameters
    ----------
    alpha : array-like of shape (height, width), float in 0..1
        The opacity `host.render.settings.ViewRenderer.render` returns with the image.
    """
    return np.asarray(alpha) >= OBJECT_ALPHA_MIN
