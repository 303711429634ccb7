"""The active image on a device, and everything the device holds of it, in one object.

`LoadedModel` is built when an image is activated (at boot, or when a new image is
committed) and replaced whole on the next activation: its reconstruction, its score decoder
(delta bases), its standalone table or predictor, its view synthesis and warp worker, and
what the display has made of it (the own frame on show, the warp due, a correction waiting
for its warp, the scores of the frame on show). Nothing about an image lives in a loose
attribute of the runtime, so a live image swap cannot leave a frame of the old image to be
corrected with the new image's scores. `ScoreItem` is a decoded packet bound to the model
that decoded it: the display drops one whose model is no longer on show.

An image with several looks (`device_runtime.looks`) is loaded as one of them: ``image`` is
that look's single-look image, ``base`` the whole image. Showing another look is
`LoadedModel.for_look`: a new model of the same image, replaced whole like any other (the
display's reconstruction, the warp worker and its cached views of the old look go with the
old model), that shares what the looks share: the score decoder (its delta bases are
scores, the same for every look), the standalone table and the predictor.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from device_runtime.layers import RestFrame
from device_runtime.looks import look_image, look_names, own_scores
from device_runtime.prediction import Predictor, can_predict
from device_runtime.reconstruct import Reconstructor
from device_runtime.standalone import StandaloneScores
from device_runtime.synthesis import WORKER_SCRATCH_BYTES, ViewSynthesizer
from device_runtime.warp_worker import WarpWorker
from protocol.image import EigenspaceImage
from protocol.layers import LayerAssembly, LayerChunk
from protocol.scores import DecodedScores, ScoreDecoder, score_bound

__all__ = ["LayerItem", "LoadedModel", "ScoreItem", "ShownState"]

View = tuple[float, float]


@dataclass
class ShownState:
    """What the display has made of one image (display thread only; replaced with it).

    Attributes
    ----------
    synth_view : (float, float) or None
        The view whose own frame the display reconstructor holds for corrections (the frame
        last handed to `Reconstructor.correct`): another correction of it needs no frame.
    own_warp : ((float, float), ndarray) or None
        The newest warp the worker made for the display: a correction of its view corrects
        it.
    warp_due : (float, float) or None
        The view whose warp the display waits for (its blend is on show).
    correction_due : ScoreItem or None
        A correction that came before the warp of its view.
    last_y : ndarray or None
        The scores of the frame on show.
    blend_s : float
        When the display last made a blend of a moved view (one per tick at most).
    settled : (float, float) or None
        The view whose best own frame is on show (its warp, its blend when the image does
        not warp, or a host's frame of it): a scripted view moves on once it is.
    base : ((float, float), int) or None
        What refinement layers may refine on show now: a view and the frame number of its
        correction (0: the device's own frame of it, uncorrected); None: nothing (a blend
        while the warp is made, a host's full frame).
    rest : RestFrame or None
        The resting view's frame that layers refine (made from the frame on show at the
        first layer; gone when the view or its correction changes).
    assembly : LayerAssembly
        The layer file whose chunks are being joined.
    layers_heard : ((float, float), float) or None
        The view a layer chunk last came for, and when: a view whose last planned layer has
        not come in a while after that is asked for again.
    """

    synth_view: View | None = None
    own_warp: tuple[View, np.ndarray] | None = None
    warp_due: View | None = None
    correction_due: ScoreItem | None = None
    last_y: np.ndarray | None = None
    blend_s: float = -math.inf
    settled: View | None = None
    base: tuple[View, int] | None = None
    rest: RestFrame | None = None
    assembly: LayerAssembly = field(default_factory=LayerAssembly)
    layers_heard: tuple[View, float] | None = None


@dataclass
class LoadedModel:
    """An active eigenspace ready to show, and what the display has made of it.

    Attributes
    ----------
    image : EigenspaceImage
    reconstructor : Reconstructor
        The display's (blends, host frames, corrected frames).
    decoder : ScoreDecoder
        Bounded by the image's K; keeps this image's delta bases.
    slot, generation, test, confirmed
        Where the image lives in flash and whether its TEST boot is confirmed yet.
    standalone : StandaloneScores or None
        A standalone device's scores of any view (its table).
    predictor : Predictor or None
        A served device's own prediction of any view (the same table), which the host's
        corrections add to.
    synthesis : ViewSynthesizer or None
        The depth warp (an image fitted with depth and a table), on the worker's own
        reconstructor.
    warp_worker : WarpWorker or None
        Makes the warps off the display thread (standalone and served alike).
    shown : ShownState
        What the display has made of this image.
    base : EigenspaceImage or None
        The whole image when it has several looks (``image`` is the look on show); None:
        one look.
    look : int
        The look on show (0 for an image with one).
    """

    image: EigenspaceImage
    reconstructor: Reconstructor
    decoder: ScoreDecoder
    slot: str
    generation: int
    test: bool
    standalone: StandaloneScores | None = None
    confirmed: bool = False
    predictor: Predictor | None = None
    synthesis: ViewSynthesizer | None = None
    warp_worker: WarpWorker | None = None
    shown: ShownState = field(default_factory=ShownState)
    base: EigenspaceImage | None = None
    look: int = 0
    #: per look of ``base`` whose scores are its own: (standalone, predictor), made once
    #: and shared by the models of its looks (a switch back builds no table again)
    look_scores: dict = field(default_factory=dict, repr=False)

    @classmethod
    def build(cls, image: EigenspaceImage, *, slot: str, generation: int, test: bool,
              max_packet_bytes: int | None = None, want_standalone: bool = False,
              want_predictor: bool = False,
              on_warp: Callable[[], None] | None = None, look: int = 0) -> LoadedModel:
        """Reconstructor, decoder (bounded by the image's K) and, if asked, standalone data
        and (``want_predictor``, when the image has a table) the predictor; with either and
        an image with depth, the view synthesis (sharing the table) and its warp worker
        (``on_warp`` is called when a warp the display asked for is made). An image with
        several looks shows ``look`` (an index, `device_runtime.looks.look_index`).

        The display's reconstructor runs on two threads when the machine has two CPUs and
        the eigenspace is large (``threads="auto"``); its frames are the same bit for bit.
        The warp worker reconstructs the neighbours with a single-threaded one of its own.
        """
        base = image if image.looks is not None else None
        image = look_image(image, look)
        standalone = StandaloneScores(image) if want_standalone else None
        decoder = _decoder(image, max_packet_bytes)
        predictor = (Predictor(image) if want_predictor and not want_standalone
                     and can_predict(image) else None)
        table = standalone if standalone is not None else (
            predictor.standalone if predictor is not None else None)
        reconstructor, synthesis, worker = _frames(image, table, on_warp)
        return cls(image, reconstructor, decoder, slot, generation, test, standalone,
                   predictor=predictor, synthesis=synthesis, warp_worker=worker, base=base,
                   look=look if base is not None else 0)

    @property
    def looks(self) -> tuple[str, ...]:
        """The image's look names (``()``: one look)."""
        return look_names(self.base) if self.base is not None else ()

    @property
    def look_name(self) -> str | None:
        """The name of the look on show (None: the image has one)."""
        names = self.looks
        return names[self.look] if names else None

    def for_look(self, look: int, *, on_warp: Callable[[], None] | None = None,
                 start_worker: bool = True) -> LoadedModel:
        """The same image showing look ``look``: a new model with the look's reconstructor,
        synthesis and warp worker and a fresh `ShownState`, sharing this one's decoder,
        standalone table and predictor, slot and confirmation. This model stays as it is
        (the caller closes it once the new one is on show, and makes no frame with it: the
        new look's display reconstructor takes over its scratch). ``start_worker=False``: the warp
        worker's thread is started by the caller (`WarpWorker.start`), after the new look's
        first frame is on show (a thread's start costs a frame on a loaded core)."""
        if self.base is None:
            raise ValueError("the image has one look")
        image = look_image(self.base, look)
        decoder, standalone, predictor = self.decoder, self.standalone, self.predictor
        if own_scores(self.base, look) or own_scores(self.base, self.look):
            # the looks' eigenspaces differ: the new look's scores, table and predictor
            self.look_scores.setdefault(self.look, (standalone, predictor))
            decoder = _decoder(image, None)
            if look not in self.look_scores:
                self.look_scores[look] = (
                    StandaloneScores(image) if standalone is not None else None,
                    Predictor(image) if predictor is not None else None)
            standalone, predictor = self.look_scores[look]
        table = standalone if standalone is not None else (
            predictor.standalone if predictor is not None else None)
        reconstructor, synthesis, worker = _frames(image, table, on_warp,
                                                   start_worker=start_worker,
                                                   scratch_of=self.reconstructor)
        return LoadedModel(image, reconstructor, decoder, self.slot, self.generation,
                           self.test, standalone, confirmed=self.confirmed,
                           predictor=predictor, synthesis=synthesis, warp_worker=worker,
                           base=self.base, look=look, look_scores=self.look_scores)

    @property
    def own_frames(self) -> bool:
        """The device makes its own frames of any view (standalone, or a predicting device)."""
        return self.standalone is not None or self.predictor is not None

    def own_scores(self, view: View) -> np.ndarray:
        """The device's own scores (K,) float32 of a canonical view: the table interpolated."""
        if self.standalone is not None:
            return self.standalone.scores(*view)
        assert self.predictor is not None
        return self.predictor(*view)

    def close(self) -> None:
        """Stop the warp worker, then free the reconstructors its warps and the display use."""
        if self.warp_worker is not None:  # before the reconstructor its warps use
            self.warp_worker.close()
        self.reconstructor.close()
        if self.synthesis is not None:
            self.synthesis.reconstructor.close()


def _decoder(image: EigenspaceImage, max_packet_bytes: int | None) -> ScoreDecoder:
    """The score packet decoder of ``image`` (a look's image: its own K), bounded by it."""
    return ScoreDecoder(
        image.n_coefficients,
        image.digest or bytes(32),
        n_components=image.n_components,
        max_packet_bytes=max_packet_bytes,
        max_abs_score=score_bound(max(1, int(np.asarray(image.mean).shape[-1]))),
    )


def _frames(image: EigenspaceImage, table: StandaloneScores | None,
            on_warp: Callable[[], None] | None, *, start_worker: bool = True,
            scratch_of: Reconstructor | None = None
            ) -> tuple[Reconstructor, ViewSynthesizer | None, WarpWorker | None]:
    """The display's reconstructor and, with a table and depth, the view synthesis on a
    reconstructor of its own and its warp worker (its thread started unless
    ``start_worker`` is False); ``scratch_of``: the display's reconstructor of the look
    left, whose scratch the new one takes over (the display makes no more frames of it)."""
    reconstructor = Reconstructor.from_image(image, threads="auto", scratch_of=scratch_of)
    synthesis = worker = None
    try:
        if table is not None and image.synthesis is not None:
            synthesis = ViewSynthesizer(image, table, Reconstructor.from_image(
                image, threads=1, scratch_bytes=WORKER_SCRATCH_BYTES))
            worker = WarpWorker(synthesis, on_made=on_warp, start=start_worker)
    except BaseException:
        reconstructor.close()
        raise
    return reconstructor, synthesis, worker


@dataclass(frozen=True)
class LayerItem:
    """A refinement layer's chunk (header checked) handed from the dispatcher to the
    display."""

    model: LoadedModel
    packet: LayerChunk


@dataclass(frozen=True)
class ScoreItem:
    """One decoded packet handed from the dispatcher to the display loop."""

    model: LoadedModel
    scores: DecodedScores
    sequence: int
    received_s: float
