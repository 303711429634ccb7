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
* :class:`OwnFrames` is the device's own *frame* of a view, the picture it shows at once:
  the depth warp of its neighbouring training views when the image has depth
  (`device_runtime.synthesis.ViewSynthesizer`), else the blend of its predicted scores;
  and that frame corrected by a version-3 packet (`Reconstructor.correct`). The host runs
  it to compute the correction of exactly the frame the device synthesized (issue 23).

The host imports this module (``host.link`` may import ``device_runtime``;
docs/architecture.md), so there is one implementation. Memory is the table the image
already holds plus one score vector per query; everything is numpy.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from device_runtime.orbit import canonical_view
from device_runtime.reconstruct import Reconstructor
from device_runtime.standalone import StandaloneScores, standalone_table
from device_runtime.synthesis import ViewSynthesizer
from protocol.image import EigenspaceImage
from protocol.scores import VERSIONS

__all__ = [
    "PREDICTION_PACKET_VERSION",
    "SYNTHESIS_PACKET_VERSION",
    "OwnFrames",
    "Predictor",
    "can_predict",
    "corrected",
    "prediction_view",
]

#: The score packet version that carries corrections (PREDICTED base kind).
PREDICTION_PACKET_VERSION = 2
#: The score packet version that carries corrections of the synthesized frame (SYNTHESIZED).
SYNTHESIS_PACKET_VERSION = 3


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


class OwnFrames:
    """The device's own frame of any view, and that frame corrected (host and device).

    Parameters
    ----------
    image : EigenspaceImage
        With a standalone table (and depth, for the warp).
    predictor : Predictor, optional
        The image's predictor (default: a new one).
    reconstructor : Reconstructor, optional
        Makes the blend and the corrected frames (default: a new single-threaded one).
    synthesis_reconstructor : Reconstructor, optional
        Reconstructs the warp's neighbours (default: ``reconstructor``; they run one after
        the other, never at once).

    Attributes
    ----------
    synthesis : ViewSynthesizer or None
        The depth warp (None: the image has no depth; frames are blends).
    """

    def __init__(self, image: EigenspaceImage, *, predictor: Predictor | None = None,
                 reconstructor: Reconstructor | None = None,
                 synthesis_reconstructor: Reconstructor | None = None) -> None:
        self.predictor = predictor if predictor is not None else Predictor(image)
        self.reconstructor = (reconstructor if reconstructor is not None
                              else Reconstructor.from_image(image, threads=1))
        self.synthesis = (ViewSynthesizer(image, self.predictor.standalone,
                                          synthesis_reconstructor or self.reconstructor)
                          if image.synthesis is not None else None)

    @property
    def warps(self) -> bool:
        """Frames are depth warps (else score blends)."""
        return self.synthesis is not None

    def frame(self, phi_deg: float, theta_deg: float,
              cancel: Callable[[], bool] | None = None) -> np.ndarray:
        """The device's own frame of the view (made canonical): uint8 (h, w, 3), a new array.

        ``cancel`` is the warp's (`ViewSynthesizer.frame`)."""
        view = prediction_view(phi_deg, theta_deg)
        if self.synthesis is not None:
            return self.synthesis.frame(*view, cancel=cancel)
        return self.reconstructor.update(self.predictor(*view)).copy()

    def corrected(self, synth: np.ndarray, delta: np.ndarray) -> np.ndarray:
        """``synth`` corrected by ``delta`` (`Reconstructor.correct`): a new array."""
        return self.reconstructor.correct(delta, synth).copy()
