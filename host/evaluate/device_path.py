"""The device path: the frames a device shows and the bytes each costs on the link.

`DevicePath` is what a device shows from score packets: interpolated scores -> a real key
score packet (`protocol.scores.encode_scores` at the model's step; its length is the bytes per
view) -> `protocol.scores.ScoreDecoder` -> the device's `Reconstructor` (through
`host.fit.model.HostModel`).

`ServedFrames` is what the one served path makes a device show (a device whose image has
the standalone table): its own frame of the view (`device_runtime.prediction.OwnFrames`: the
depth warp, or the blend of its predicted scores), that frame corrected at rest (the complete
correction at the model's step) and while moving (the sparse correction at the stride the
frame deadline allows), each correction a real version-3 packet decoded by
`protocol.scores.ScoreDecoder` and added by the device's own `Reconstructor.correct`.
At rest, ``ServedFrames.rest`` gives the whole chain ``serve`` sends a resting view: the
complete correction (when the plan sends it) and the refinement layers planned by the
session's planner (``host.link.layers.RestPlanner``, handed in by the caller: evaluate and
link never import each other) from the same inputs ``serve`` plans them from -- the view's
full ray-cast, the device's own frame and that frame with the complete correction -- each
step's frame as the device shows it (`RestSteps`).

`SlowRenderer` makes a renderer's ray-casts slower, to see what the deadline does on a
slower host.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = [
    "DevicePath",
    "RestStep",
    "RestSteps",
    "ServedFrames",
    "SlowRenderer",
]

#: ``ServedFrames``: the budget of the frame sources it measures with, seconds: always enough
#: (the stride is fixed; only the warm-up drag that picks it runs against the deadline).
UNBOUNDED_S = 3600.0
#: The drag a moving view is measured in, degrees per frame.
MOTION_STEP_DEG = 3.0
#: Frames of the warm-up drag whose last stride is used for every view.
MOTION_WARMUP = 8


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
        what the eigenspace can represent from what view interpolation loses (``serve``
        streamed it before the device's own frame was corrected instead).
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


@dataclass
class RestStep:
    """One step of a resting view: what the device shows after it, and what it cost.

    Attributes
    ----------
    kind : {"own", "correction", "layer", "exact"}
        The device's own frame (nothing sent), its complete correction, a lossy refinement
        layer, the exact layer.
    frame : ndarray (height, width, 3) uint8
        The device's frame once the step is applied (the exact step's is the ray-cast).
    bytes : int
        Packet bytes sent for the view up to and including this step (cumulative).
    step_bytes : int
        This step's own packet bytes (all its strips).
    packets : list of bytes
        Its packets as planned (a layer's strips, top to bottom; the correction's one; none
        for the own frame).
    codec : str or None
        A layer's codec (``"webp"``, ``"webp-lossless"``, ``"png"``, or both joined by ``+``).
    residual : bool
        A layer coded against the device's frame (else the ray-cast's pixels).
    planned_quality : float or None
        The object SSIM the planner measured for a layer (its own measure: the ray-cast's
        non-black pixels); evaluate's metrics are computed separately.
    """

    kind: str
    frame: np.ndarray
    bytes: int
    step_bytes: int
    packets: list[bytes] = field(default_factory=list)
    codec: str | None = None
    residual: bool = False
    planned_quality: float | None = None


@dataclass
class RestSteps:
    """What ``serve`` sends a resting view and what the device shows after each packet.

    Attributes
    ----------
    view : (float, float)
        The canonical view.
    truth : ndarray (height, width, 3) uint8
        The view's full ray-cast the plan refines to (serve's, of the canonical view).
    correction_bytes : int
        The complete correction's packet (0: nothing worth sending), sent or not.
    skip_correction : bool
        The plan sends no correction (it does not pay for itself, or there is none).
    steps : list of RestStep
        In order: the own frame, the correction when sent, each layer.
    """

    view: tuple[float, float]
    truth: np.ndarray
    correction_bytes: int
    skip_correction: bool
    steps: list[RestStep] = field(default_factory=list)

    @property
    def exact(self) -> RestStep | None:
        """The exact step (None: the planner stops before it)."""
        return next((s for s in self.steps if s.kind == "exact"), None)


class _OwnOnce:
    """`OwnFrames` that makes each view's own frame once (the last view's is kept): the
    frame sources and evaluate ask for the same view's frame several times."""

    def __init__(self, own: Any) -> None:
        self.own = own
        self._view: tuple[float, float] | None = None
        self._frame: np.ndarray | None = None

    def frame(self, phi_deg: float, theta_deg: float, cancel: Any = None) -> np.ndarray:
        from device_runtime.prediction import prediction_view

        view = prediction_view(phi_deg, theta_deg)
        if view != self._view or self._frame is None:
            self._frame = self.own.frame(*view)
            self._view = view
        return self._frame.copy()

    def corrected(self, synth: np.ndarray, delta: np.ndarray) -> np.ndarray:
        return self.own.corrected(synth, delta)


class ServedFrames:
    """The frames of the one served path, exactly as a correcting device shows them.

    Parameters
    ----------
    model : host.fit.model.HostModel
        With the standalone table (`host.fit.rate` ... ``can_predict``).
    scene : host.render.settings.ViewRenderer
        The model's renderer (the host's ray-caster).
    planner : host.link.layers.RestPlanner, optional
        Plans a resting view's refinement layers as ``serve`` does (`rest`); None: no
        layers (`rest` says None).

    Attributes
    ----------
    own : OwnFrames
        The device's own frames (`device_runtime.prediction.OwnFrames`, the device's code).
    kind : {"warp", "blend"}
        What the own frame is.
    stride : int or None
        The moving frames' stride (`set_stride` / `pick_stride`; 0: none fitted the deadline,
        a moving frame is the own frame).
    """

    def __init__(self, model: Any, scene: Any, *, planner: Any = None) -> None:
        from device_runtime.prediction import OwnFrames
        from host.fit.motion import MotionScores
        from protocol.scores import ScoreDecoder

        self.model = model
        self.scene = scene
        self.own = _OwnOnce(OwnFrames(model.image))
        self.kind = "warp" if self.own.own.warps else "blend"
        self.decoder = ScoreDecoder(model.image.n_coefficients, model.digest,
                                    n_components=model.image.n_components)
        # at rest: every pixel ray-cast exactly, the complete correction (serve's last step)
        self._rest = MotionScores(model, scene, own=self.own, strides=(1,), coarse=1.0,
                                  budget_s=UNBOUNDED_S)
        self._moving: Any = None
        self.stride: int | None = None
        self.planner = planner
        if planner is not None:  # its layers decode through pygame: no banner on stdout
            import os

            os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
        self._frame = 0
        self._resting: tuple[tuple[float, float], Any, Any] | None = None  # view, step, packet

    def own_frame(self, phi_deg: float, theta_deg: float) -> np.ndarray:
        """The device's own frame of the view (uint8 (h, w, 3)): no bytes."""
        return self.own.frame(phi_deg, theta_deg)

    def _encode(self, view: tuple[float, float], step: Any, *, fine: bool) -> Any:
        """The correction packet of ``step`` (`EncodedScores`; None: nothing worth sending)."""
        from host.fit.rate import encode_correction

        self._frame = (self._frame % 0xFFFFFFFF) + 1
        return (None if step.scores is None else
                encode_correction(self.model, step.scores, view, frame=self._frame,
                                  fine=fine, weights=step.weights))

    def _shown(self, view: tuple[float, float], encoded: Any) -> tuple[np.ndarray, int]:
        synth = self.own.frame(*view)
        if encoded is None:  # nothing worth sending: the device keeps its own frame
            return synth, 0
        decoded = self.decoder.decode(encoded.packet)
        return self.own.corrected(synth, decoded.y), len(encoded.packet)

    def _rest_step(self, view: tuple[float, float]) -> tuple[Any, Any]:
        """The resting view's full ray-cast step and its complete correction's packet (made
        once per view: evaluate asks `at_rest` and `rest` of the same view)."""
        if self._resting is None or self._resting[0] != view:
            step = self._rest.frame(view)
            self._resting = (view, step, self._encode(view, step, fine=True))
        return self._resting[1], self._resting[2]

    def at_rest(self, phi_deg: float, theta_deg: float) -> tuple[np.ndarray, int]:
        """The frame a resting view converges to (its own frame plus the complete correction
        at the model's step), and the correction packet's bytes (0: none sent)."""
        from device_runtime.prediction import prediction_view

        view = prediction_view(phi_deg, theta_deg)
        return self._shown(view, self._rest_step(view)[1])

    def rest(self, phi_deg: float, theta_deg: float) -> RestSteps | None:
        """Everything ``serve`` sends a resting view (its complete correction, unless the
        plan skips it, then the refinement layers) and the device's frame after each
        packet; None without a planner or when the view's full ray-cast is not at hand.

        The plan is ``planner.plan`` of the same inputs ``serve``'s `RestSender` gives it:
        the full ray-cast and own frame of the view (`MotionScores.rest_images`), the own
        frame corrected by the decoded complete correction and that packet's size and frame
        number."""
        from device_runtime.prediction import prediction_view

        if self.planner is None:
            return None
        view = prediction_view(phi_deg, theta_deg)
        _, encoded = self._rest_step(view)
        images = self._rest.rest_images(view)
        if images is None:
            return None
        truth, own = (np.array(a, copy=True) for a in images)
        corrected, size = self._shown(view, encoded)
        base = 0 if encoded is None else encoded.frame
        plan = self.planner.plan(view, truth, corrected, own, size, base_frame=base,
                                 first_frame=self._frame + 1)
        out = RestSteps(view, truth, size, plan.skip_correction or encoded is None,
                        [RestStep("own", own, 0, 0)])
        total = 0
        if not out.skip_correction:
            total = size
            out.steps.append(RestStep("correction", corrected, size, size, [encoded.packet]))
        for layer in plan.layers:
            total += layer.size_bytes
            out.steps.append(RestStep("exact" if layer.exact else "layer", layer.frame, total,
                                      layer.size_bytes, list(layer.packets), layer.codec,
                                      layer.residual, float(layer.quality)))
        return out

    def pick_stride(self, deadline_s: float, start: tuple[float, float], *,
                    slowdown: float = 1.0) -> int:
        """The stride a drag at `MOTION_STEP_DEG` per frame from ``start`` uses most at the
        ``deadline_s`` budget on this machine (with a renderer ``slowdown`` times slower), after
        its first frame: serve's frame source, the device's own frames included in its
        measured cost. 0: none fits (the moving frames are the own frames)."""
        from device_runtime.prediction import OwnFrames, prediction_view
        from host.fit.motion import MotionScores

        scene = self.scene if slowdown == 1.0 else SlowRenderer(self.scene, slowdown)
        probe = MotionScores(self.model, scene, budget_s=deadline_s,
                             own=OwnFrames(self.model.image))
        probe.prepare()
        strides = [probe.frame(prediction_view(start[0] + MOTION_STEP_DEG * i, start[1])).stride
                   for i in range(MOTION_WARMUP)]
        # the drag's usual stride once measured (the first frame is the sparsest, unmeasured;
        # when none fits, every PROBE_EVERY-th frame still ray-casts to measure again)
        later = strides[1:]
        self.set_stride(max(reversed(later), key=later.count))
        assert self.stride is not None
        return self.stride

    def set_stride(self, stride: int) -> None:
        """Moving frames at ``stride`` (0: none, the own frame)."""
        from host.fit.motion import MotionScores

        self.stride = int(stride)
        self._moving = (None if self.stride == 0 else
                        MotionScores(self.model, self.scene, own=self.own,
                                     strides=(self.stride,), budget_s=UNBOUNDED_S))

    def moving(self, phi_deg: float, theta_deg: float) -> tuple[np.ndarray, int]:
        """The frame a device shows while the view moves through it (its own frame plus the
        sparse correction at `stride`, serve's moving quantizer), and the bytes streamed."""
        from device_runtime.prediction import prediction_view

        if self.stride is None:
            raise ValueError("ServedFrames.moving: no stride yet (set_stride / pick_stride)")
        view = prediction_view(phi_deg, theta_deg)
        if self._moving is None:
            return self.own.frame(*view), 0
        return self._shown(view, self._encode(view, self._moving.frame(view), fine=False))


class _SlowCaster:
    """A ray-caster whose `render_pixels` takes ``factor`` times as long (it sleeps the
    difference); everything else is the wrapped caster's."""

    def __init__(self, caster: Any, factor: float) -> None:
        self._caster = caster
        self._factor = float(factor)

    def render_pixels(self, *args: Any, **kwargs: Any) -> np.ndarray:
        import time

        t0 = time.perf_counter()
        out = self._caster.render_pixels(*args, **kwargs)
        time.sleep((self._factor - 1.0) * (time.perf_counter() - t0))
        return out

    def coarser(self, factor: float) -> _SlowCaster:
        return _SlowCaster(self._caster.coarser(factor), self._factor)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._caster, name)


class SlowRenderer:
    """``scene`` (a `host.render.settings.ViewRenderer`) with every ray-cast ``factor``
    times slower: a slower host, as the frame deadline sees it.

    Raises
    ------
    ValueError
        ``factor`` below 1 or not finite.
    """

    def __init__(self, scene: Any, factor: float) -> None:
        if not (factor >= 1.0 and np.isfinite(factor)):
            raise ValueError(f"SlowRenderer: factor={factor} must be >= 1")
        self.settings = scene.settings
        self.image_shape = scene.image_shape
        self.renderer = _SlowCaster(scene.renderer, factor)
