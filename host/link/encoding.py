"""Score packets of one serving session: frame numbers, the key/delta choice, the delta base.

`FrameEncoder` codes the absolute scores ``serve`` sends to a device that does not correct
its own frames (interpolated, or recovered from a sparse ray-cast); its subclass
`host.link.correction.CorrectionEncoder` codes the corrections of the one served path.
"""

from __future__ import annotations

import secrets

import numpy as np

from host.fit.model import HostModel
from protocol.scores import DEFAULT_LEVEL as SCORE_LEVEL
from protocol.scores import EncodedScores, encode_scores

__all__ = ["SCORE_LEVEL", "FrameEncoder"]


class FrameEncoder:
    """Score packets of one session: frame numbers, key/delta choice, the delta base.

    Parameters
    ----------
    model : HostModel
    keyframe_interval : int
        0: deltas whenever possible (key frames only at the start and when asked);
        1: key frames only; N: at least one key frame every N frames.
    level : int
        zstd level of the packet payload.
    first_frame : int, optional
        Frame number of the first packet (default: random in 1..2**31).
    """

    def __init__(self, model: HostModel, *, keyframe_interval: int = 0,
                 level: int = SCORE_LEVEL, first_frame: int | None = None) -> None:
        if keyframe_interval < 0:
            raise ValueError(f"keyframe_interval={keyframe_interval} must be >= 0")
        self.model = model
        self.keyframe_interval = keyframe_interval
        self.level = level
        self.next_frame = first_frame if first_frame is not None else (
            1 + secrets.randbelow(1 << 31))
        self.base: EncodedScores | None = None
        self.last_was_key = False
        self._since_key = 0

    def reset(self) -> None:
        """Forget the base: the next packet is a key frame."""
        self.base = None

    def encode(self, view: tuple[float, float], *, key: bool = False,
               scores: np.ndarray | None = None) -> EncodedScores:
        """The packet for ``view`` (canonical), as a delta against the last one unless
        ``key``, the interval or a wrap of the frame number asks for a key frame.

        ``scores`` (float (K,)): send these (e.g. `HostModel.project` of a fresh ray-cast)
        instead of the model's interpolated scores at ``view``; quantized the same way."""
        frame = self.next_frame
        if frame > 0xFFFFFFFF:
            frame = 1
            self.base = None
        self.next_frame = frame + 1
        interval = self.keyframe_interval
        if interval == 1 or (interval > 1 and self._since_key + 1 >= interval):
            key = True
        model = self.model
        y = model.quantized_scores(*view) if scores is None else model.quantize(scores)
        base = None if key else self.base
        encoded = encode_scores(
            y, step=model.score_step, frame=frame, view=view, image_digest=model.digest,
            base=base, level=self.level, n_components=model.image.n_components,
        )
        self.last_was_key = base is None
        self._since_key = 0 if base is None else self._since_key + 1
        self.base = encoded
        return encoded
