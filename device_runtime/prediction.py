"""The device predicts, the host corrects (issue 14): the prediction both sides compute.

A device whose image carries the standalone training-score table (``eigencast fit
--standalone``) can interpolate the scores of any view itself, with no bytes and no
latency. The host then sends only a *correction*: a version-2 score packet with the
PREDICTED base kind (`protocol.scores`) whose scores are added to the device's own
prediction of the packet's view. For the sum to be the frame the host meant, both sides
must compute the same prediction bit for bit, so both call this module:

* :func:`prediction_view` is the view a prediction is made at: `canonical_view` (phi
  wrapped to [0, 360), theta clipped, both rounded to float32), exactly what the packet
  header carries, so the device recomputes it from the header alone;
* :class:`Predictor` is `device_runtime.standalone.StandaloneScores` at that view (the
  table's rows dequantized as float32, blended with `device_runtime.interpolation`'s
  weights, rounded to the image's score step): the frame a standalone device shows;
* :func:`corrected` is what the device shows on a correction: ``prediction + y`` in float32.

The host imports this module (``host.link`` may import ``device_runtime``;
docs/architecture.md), so there is one implementation. Memory is the table the image
already holds plus one score vector per query; everything is numpy.
"""

from __future__ import annotations

import numpy as np

from device_runtime.orbit import canonical_view
from device_runtime.standalone import StandaloneScores, standalone_table
from protocol.image import EigenspaceImage
from protocol.scores import VERSIONS

__all__ = [
    "PREDICTION_PACKET_VERSION",
    "Predictor",
    "can_predict",
    "corrected",
    "prediction_view",
]

#: The score packet version that carries corrections (PREDICTED base kind).
PREDICTION_PACKET_VERSION = 2


def prediction_view(phi_deg: float, theta_deg: float) -> tuple[float, float]:
    """The view a prediction is made at: the canonical view (float32, as the header)."""
    return canonical_view(phi_deg, theta_deg)


def can_predict(image: EigenspaceImage) -> bool:
    """Whether ``image`` holds a standalone table (and this code reads corrections)."""
    return PREDICTION_PACKET_VERSION in VERSIONS and standalone_table(image) is not None


def corrected(prediction: np.ndarray, correction: np.ndarray) -> np.ndarray:
    """The scores (K,) float32 a device shows for a correction: ``prediction + correction``."""
    return (np.asarray(prediction, dtype=np.float32)
            + np.asarray(correction, dtype=np.float32)).astype(np.float32)


class Predictor:
    """The device's own prediction of any view's scores (from the image's standalone table).

    Parameters
    ----------
    image : EigenspaceImage
        With a standalone table and interpolation manifest.

    Raises
    ------
    ImageFormatError
        No table, or a malformed table or interpolation manifest.
    """

    def __init__(self, image: EigenspaceImage) -> None:
        self.standalone = StandaloneScores(image)
        self.n_coefficients = int(image.n_coefficients)

    def __call__(self, phi_deg: float, theta_deg: float) -> np.ndarray:
        """Predicted scores (K,) float32 of the view (made canonical first)."""
        return self.standalone.scores(*prediction_view(phi_deg, theta_deg))
