"""``pca_warp``: the frames a standalone device with depth shows (issue 15).

An image fitted with ``eigencast fit --depth`` makes novel views by warping the 4 neighbouring
training views by their depth (`device_runtime.synthesis.ViewSynthesizer`). `WarpFrames`
runs exactly the device's code on the host, so the frames ``eigencast evaluate`` scores as
``pca_warp`` are the device's, bit for bit (a test checks this against ``eigencast-device
--standalone``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from device_runtime.reconstruct import Reconstructor
from device_runtime.standalone import StandaloneScores
from device_runtime.synthesis import ViewSynthesizer

__all__ = ["WarpFrames"]


class WarpFrames:
    """The device's depth-warped frames of a model (`device_runtime.synthesis`).

    Parameters
    ----------
    model : HostModel
        Its image has a standalone table and depth (``fit --depth``).

    Raises
    ------
    ImageFormatError
        The image has no depth or no standalone table.
    """

    def __init__(self, model: Any) -> None:
        image = model.image
        self.synthesizer = ViewSynthesizer(image, StandaloneScores(image),
                                           Reconstructor.from_image(image))

    def frame(self, phi_deg: float, theta_deg: float) -> np.ndarray:
        """uint8 (height, width, 3): what ``eigencast-device --standalone`` shows."""
        return self.synthesizer.frame(phi_deg, theta_deg)
