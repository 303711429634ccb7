"""What ``serve`` sends a resting view once its ray-cast is whole: the complete correction
and the refinement layers, planned off the serving loop.

`RestSender` belongs to one serving session. When a view's full ray-cast is done it codes
the view's complete correction, computes the frame the device shows with it (the device's
code: `device_runtime.prediction.OwnFrames`) and hands the planning of the layers
(`host.link.layers.RestPlanner`: seconds of encodes and SSIMs at 512) to a thread of its own,
so the loop keeps answering the device: a new view cancels the plan (its result is thrown
away) and the view's layers still queued. Once the plan is ready, `next` gives the packets in
order: the correction unless the plan skips it, then every chunk, each numbered as it is
sent (the frame counter is the session's).
"""

from __future__ import annotations

import collections
import concurrent.futures
from typing import Any

import numpy as np

from host.link.layers import EncodedLayer, Plan, RestPlanner
from protocol.scores import EncodedScores, ScoreDecoder

__all__ = ["RestSender"]


class RestSender:
    """The resting view's correction and layers of one session (module docstring).

    Parameters
    ----------
    model : HostModel
    planner : RestPlanner
    """

    def __init__(self, model: Any, planner: RestPlanner) -> None:
        self.model = model
        self.planner = planner
        self._decoder = ScoreDecoder(model.image.n_coefficients, model.digest,
                                     n_components=model.image.n_components)
        self._pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="rest-plan")
        self._job: tuple[tuple[float, float], EncodedScores | None, Any] | None = None
        self._queue: collections.deque[EncodedScores | EncodedLayer] = collections.deque()
        self.view: tuple[float, float] | None = None

    @property
    def planning(self) -> bool:
        """A plan is being made."""
        return self._job is not None

    @property
    def pending(self) -> bool:
        """A plan is being made or has packets left to send."""
        return self._job is not None or bool(self._queue)

    def start(self, view: tuple[float, float], truth: np.ndarray, own: np.ndarray,
              correction: EncodedScores | None, own_frames: Any) -> None:
        """Plan the layers of ``view`` (its full ray-cast ``truth``, the device's ``own``
        frame, the complete ``correction`` coded already, or None when it has nothing worth
        sending) on the planning thread; forget any earlier view's."""
        self.cancel()
        if correction is None:
            corrected, size, base = own, 0, 0
        else:
            corrected = own_frames.corrected(own, self._decoder.decode(correction.packet).y)
            size, base = len(correction.packet), correction.frame
        # the arrays are copied: the frame source reuses its own for the next view
        future = self._pool.submit(self.planner.plan, view, truth.copy(), corrected,
                                   own.copy(), size, base_frame=base, first_frame=1)
        self._job = (view, correction, future)
        self.view = view

    def cancel(self) -> None:
        """A new view: the plan in the making and the packets not sent are moot."""
        if self._job is not None:
            self._job[2].cancel()  # (one already running finishes; its result is dropped)
        self._job = None
        self._queue.clear()
        self.view = None

    def next(self, frame_number: int) -> EncodedScores | EncodedLayer | None:
        """The next packet of the resting view (a chunk numbered ``frame_number``), or None:
        nothing (yet). Raises what the planning raised (the view's layers are dropped)."""
        if self._job is not None:
            _, correction, future = self._job
            if not future.done():
                return None
            self._job = None
            plan: Plan = future.result()
            if correction is not None and not plan.skip_correction:
                self._queue.append(correction)
            self._queue.extend(plan.sends())
        if not self._queue:
            return None
        packet = self._queue.popleft()
        if isinstance(packet, EncodedLayer):
            packet = packet.numbered(frame_number)
        return packet

    def close(self) -> None:
        """Stop the planning thread (a plan in the making is dropped)."""
        self.cancel()
        self._pool.shutdown(wait=False, cancel_futures=True)
