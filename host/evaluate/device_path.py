"""The device path: the frames a device shows and the bytes each costs on the link.

`DevicePath` is what a device shows: interpolated scores -> a real key score packet
(`protocol.scores.encode_scores` at the model's step; its length is the bytes per view) ->
`protocol.scores.ScoreDecoder` -> the device's `Reconstructor` (through `host.fit.model.HostModel`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = [
    "DevicePath",
]


class DevicePath:
    """Frames exactly as a device shows them, with the bytes each one costs on the link.

    Interpolated float scores -> `protocol.scores.encode_scores` (key packet, the model's
    step) -> `protocol.scores.ScoreDecoder` -> the device's reconstruction.

    Parameters
    ----------
    model : host.fit.model.HostModel
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
        (`host.fit.model.HostModel.project`, least squares per cell), then sent through the same
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

    def motion_frame(self, previous: np.ndarray, scores: np.ndarray) -> tuple[np.ndarray, int]:
        """The frame of ``scores`` (float (K,)) sent as ``serve`` streams a drag: a delta
        packet against the frame before it (``previous``, sent as a key packet first).

        Returns the frame and the size of the delta packet (the bytes per frame of a
        streamed drag).
        """
        from protocol.scores import ScoreDecoder, encode_scores

        decoder = ScoreDecoder(self.model.image.n_coefficients, self.digest,
                               n_components=self.model.image.n_components)
        packets = []
        base = None
        for y in (previous, scores):
            self._frame = (self._frame + 1) & 0xFFFFFFFF or 1
            base = encode_scores(self.model.quantize(y), step=self.model.score_step,
                                 frame=self._frame, view=(0.0, 0.0), image_digest=self.digest,
                                 base=base, n_components=self.model.image.n_components)
            packets.append(base.packet)
        decoder.decode(packets[0])
        return self.model.reconstruct(decoder.decode(packets[1]).y), len(packets[1])

    def correction_frame(self, phi_deg: float, theta_deg: float, image: np.ndarray,
                         mask: np.ndarray | None = None) -> tuple[np.ndarray, int] | None:
        """What a predicting device shows at rest under ``serve --scores predict``: its own
        prediction of the view plus the host's correction, and the correction's bytes.

        ``image`` (the view's ray-cast) is projected; the device's prediction
        (`device_runtime.prediction.Predictor` of the image's standalone table) is subtracted
        and the difference RD-quantized at ``serve``'s defaults
        (`host.fit.rate.DEFAULT_CORRECTION_STEP_FACTOR` x the score step,
        `~host.fit.rate.DEFAULT_CORRECTION_KAPPA`, SSIM cell weights from ``image`` and
        ``mask``), coded as a version-2 correction packet, decoded and added to the
        prediction as the device does. None for a model without the standalone table.
        """
        from device_runtime.prediction import Predictor, can_predict, corrected, prediction_view
        from host.fit.rate import encode_correction, ssim_cell_weights

        model = self.model
        if getattr(self, "_predictor", None) is None:
            if not can_predict(model.image):
                return None
            self._predictor = Predictor(model.image)
        view = prediction_view(phi_deg, theta_deg)
        prediction = self._predictor(*view)
        weights = ssim_cell_weights(image, model.image.cell_shape, mask)
        self._frame = (self._frame + 1) & 0xFFFFFFFF
        packet = encode_correction(model, model.project(image), prediction, view,
                                   frame=self._frame, weights=weights).packet
        d = self.decoder.decode(packet)
        return model.reconstruct(corrected(prediction, d.y)), len(packet)
