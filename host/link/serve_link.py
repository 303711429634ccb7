"""The link side of ``serve``: one session's connection to the device and its events.

:class:`DeviceEvents` is the host link's handler (the newest VIEW_REQUEST, KEYFRAME_REQUESTs,
NOTICEs); :class:`Connection` is one session's link, host session and stream state;
:func:`device_opener` opens the device's port with frames as large as the model's largest
packet. :mod:`host.link.serving` runs the sessions on them.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from device_runtime.orbit import canonical_view
from protocol import messages as m
from protocol.host_session import HostSession
from protocol.link import Link
from protocol.scores import max_packet_size
from protocol.transport import open_transport

if TYPE_CHECKING:
    from host.fit.model import HostModel
    from host.link.serve_stats import ServeStats

__all__ = ["Connection", "DeviceEvents", "device_opener"]


class DeviceEvents:
    """The host link's handler: newest VIEW_REQUEST (and the look on show it names),
    KEYFRAME_REQUESTs, NOTICEs."""

    def __init__(self, stats: ServeStats, say: Callable[[str], None]) -> None:
        self._cond = threading.Condition()
        self.view: tuple[float, float] | None = None
        self.sequence = 0
        self.fresh = False
        self.keyframe = False
        self.look = 0
        self.taken_look = 0
        self.stats = stats
        self.say = say

    def __call__(self, msg: m.Message, frame: Any) -> None:
        with self._cond:
            if isinstance(msg, m.ViewRequest):
                self.stats.requests += 1
                if self.fresh:
                    self.stats.coalesced += 1
                self.view = canonical_view(msg.phi_deg, msg.theta_deg)
                self.sequence = msg.sequence
                self.look = msg.look or 0
                self.fresh = True
            elif isinstance(msg, m.KeyframeRequest):
                self.stats.keyframe_requests += 1
                self.keyframe = True
            elif isinstance(msg, m.Notice):
                self.say(f"device: {msg.text}")
            self._cond.notify_all()
        return None

    def wait(self, timeout_s: float) -> None:
        with self._cond:
            if not (self.fresh or self.keyframe):
                self._cond.wait(timeout_s)

    def take(self) -> tuple[tuple[float, float] | None, int, bool, bool]:
        """(view, sequence, fresh, keyframe wanted) and clear the flags; ``taken_look`` is
        then the look the taken request named."""
        with self._cond:
            out = (self.view, self.sequence, self.fresh, self.keyframe)
            self.taken_look = self.look
            self.fresh = False
            self.keyframe = False
            return out


@dataclass
class Connection:
    """One session's way to the device (the link engine, the host session on it, the
    device's events) and its stream's state: ``sent`` is set while no packet is in flight,
    ``clock`` and the link's byte counts are what the statistics already hold, ``next_due``
    is the earliest time of the next packet (``fps``), ``linger_until`` the end of an
    orbit's linger."""

    link: Link
    session: HostSession
    events: DeviceEvents
    sent: threading.Event = field(default_factory=threading.Event)
    clock: float = 0.0
    bytes_sent: int = 0
    bytes_received: int = 0
    next_due: float = 0.0
    linger_until: float | None = None

    def __post_init__(self) -> None:
        self.sent.set()


def device_opener(
    url: str, baud: int, request_timeout_s: float, model: HostModel
) -> Callable[[int], Any]:
    """``factory(attempt)`` opening ``url``, its frames as large as the model's largest packet."""
    # this end sends frames as large as the model's largest score packet; the device's own
    # limit (HELLO's max_frame_bytes, eigencast-device --max-frame) is the one that binds
    k, n_cells = model.image.n_coefficients, model.image.n_cells
    frame_limit = max(16384, max_packet_size(k, max(k, n_cells), n_cells=n_cells) + 256)
    return lambda attempt: open_transport(url, baud=baud, timeout_s=max(5.0, request_timeout_s),
                                          max_frame_bytes=frame_limit)
