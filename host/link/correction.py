"""The one served path: the device shows its own frame, the host corrects that frame.

A device whose image carries the standalone table synthesizes every new view itself, at
once and with no bytes: the depth warp of its neighbouring training views when the image
has depth, the blend of its predicted scores otherwise (`device_runtime.prediction.OwnFrames`).
The host runs the same code on the same image, so it knows that frame ``S`` bit for bit; it
ray-casts the view (sparsely while it moves, within the frame's deadline, every pixel once
it rests: `host.fit.motion.MotionScores` with ``own``), and sends the *correction*
``d = s(truth) - s(S)`` per cell, rate-distortion quantized (`host.fit.rate.rd_quantize`),
as a version-3 score packet with the SYNTHESIZED base kind. The device shows
``clip(rint(S + V d))`` (`device_runtime.reconstruct.Reconstructor.correct`).

Why that frame is never worse than ``S``: ``V s(.)`` projects onto the span of each cell's
own basis, so before quantization the full correction moves ``S`` towards the truth in L2 and
keeps whatever detail ``S`` holds outside the eigenspace; quantizing a coefficient to the
nearest multiple of the step (or to 0) never moves it further from its target than 0 does.
A sparse correction is the MAP estimate of ``d`` under the residual's learned statistics
(`host.fit.motion.ResidualPrior`), prior zero: no samples, no change. A correction whose
quantized coefficients are all zero has no expected gain and is not sent: the device keeps
the frame it made.

Quantization: a moving view's correction at `DEFAULT_CORRECTION_STEP_FACTOR` times the
model's score step with the RD factor `DEFAULT_CORRECTION_KAPPA` and SSIM cell weights; the
complete correction of a resting view at the model's own step by plain rounding (the
quality of a key frame).

:func:`cannot_correct` reads a device's HELLO_REPLY (why it cannot take corrections, or
None); :class:`CorrectionEncoder` is the `FrameEncoder` of such sessions.
"""

from __future__ import annotations

import numpy as np

from device_runtime.prediction import SYNTHESIS_PACKET_VERSION, can_predict
from host.fit.model import HostModel
from host.fit.rate import (
    DEFAULT_CORRECTION_KAPPA,
    DEFAULT_CORRECTION_STEP_FACTOR,
    encode_correction,
    quantize_correction,
)
from host.link.encoding import SCORE_LEVEL, FrameEncoder
from protocol import messages as m
from protocol.scores import EncodedScores

__all__ = [
    "DEFAULT_CORRECTION_KAPPA",
    "DEFAULT_CORRECTION_STEP_FACTOR",
    "CorrectionEncoder",
    "can_correct",
    "cannot_correct",
]

def can_correct(model: HostModel) -> bool:
    """Whether a device can synthesize ``model``'s views itself (its image has the table)."""
    return can_predict(model.image)


def cannot_correct(hello: m.HelloReply) -> str | None:
    """Why the device of ``hello`` cannot take corrections of its own frames, or None."""
    versions = hello.score_versions or (1,)
    if SYNTHESIS_PACKET_VERSION not in versions:
        return (f"reads score packets of version {'/'.join(map(str, versions))} only "
                "(an older eigencast-device)")
    if not hello.predicts:
        return "does not synthesize its own frames (its image has no standalone table, " \
               "or it runs with --no-predict)"
    return None


class CorrectionEncoder(FrameEncoder):
    """The packets of a session with a device that takes corrections of its own frames.

    ``encode(view, scores=d, fine=..., weights=...)`` quantizes the correction ``d`` and
    codes it as a version-3 SYNTHESIZED packet for ``view`` (canonical), or returns None when
    every quantized coefficient is zero (nothing worth sending). With ``enabled`` off (a
    device that cannot take corrections: it gets absolute scores) it is a plain
    `FrameEncoder`.

    Parameters
    ----------
    model : HostModel
    step_factor, kappa : float
        A moving view's step (model score steps) and RD factor.
    keyframe_interval, level, first_frame
        As `FrameEncoder` (they apply while ``enabled`` is off).

    Attributes
    ----------
    enabled : bool
        Set per session from the device's HELLO_REPLY (`cannot_correct`).
    last_kind : {"key", "delta", "correction"}
    """

    def __init__(self, model: HostModel, *,
                 step_factor: float = DEFAULT_CORRECTION_STEP_FACTOR,
                 kappa: float = DEFAULT_CORRECTION_KAPPA, keyframe_interval: int = 0,
                 level: int = SCORE_LEVEL, first_frame: int | None = None) -> None:
        super().__init__(model, keyframe_interval=keyframe_interval, level=level,
                         first_frame=first_frame)
        if not (step_factor > 0 and np.isfinite(step_factor)):
            raise ValueError(f"step_factor={step_factor} must be > 0")
        if not (kappa >= 0 and np.isfinite(kappa)):
            raise ValueError(f"kappa={kappa} must be >= 0")
        self.step = float(model.score_step * step_factor)
        self.kappa = float(kappa)
        self.enabled = True
        self.last_kind = "key"

    def quantize(self, delta: np.ndarray, *, fine: bool = False,
                 weights: np.ndarray | None = None) -> tuple[np.ndarray, float]:
        """The correction as a packet carries it (K,) float32, and its step
        (`host.fit.rate.quantize_correction` at this encoder's moving step and kappa)."""
        return quantize_correction(self.model, delta, fine=fine, step=self.step,
                                   kappa=self.kappa, weights=weights)

    def encode(self, view: tuple[float, float], *, key: bool = False,
               scores: np.ndarray | None = None, fine: bool = False,
               weights: np.ndarray | None = None, always: bool = False
               ) -> EncodedScores | None:
        """The correction packet of ``view`` for the correction ``scores``, or None when it
        has nothing worth sending (``always``: an empty correction then, which tells the
        device to show its own frame of ``view``: a host-driven view). While ``enabled``
        is off, `FrameEncoder.encode` (``fine``, ``weights`` and ``always`` unused)."""
        if not self.enabled:
            encoded = super().encode(view, key=key, scores=scores)
            self.last_kind = "key" if self.last_was_key else "delta"
            return encoded
        if scores is None:  # no ray-cast: an empty correction at the moving step
            scores, fine = np.zeros(self.model.image.n_coefficients, np.float32), False
        frame = self.next_frame if self.next_frame <= 0xFFFFFFFF else 1
        encoded = encode_correction(self.model, scores, view, frame=frame, always=always,
                                    level=self.level, fine=fine, step=self.step,
                                    kappa=self.kappa, weights=weights)
        if encoded is None:
            return None
        self.next_frame = frame + 1
        self.last_was_key = False
        self.last_kind = "correction"
        return encoded
