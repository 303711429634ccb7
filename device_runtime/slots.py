"""Thread mailboxes of the device runtime: the latest-item slot and the request limiter.

:class:`LatestSlot` hands decoded frames from the link's dispatcher to the display loop
(a newer frame replaces one not shown yet: a device that falls behind shows the newest and
counts the rest as coalesced); :class:`RequestLimiter` keeps VIEW_REQUESTs to a rate, the
latest view winning in between. Both are importable from :mod:`device_runtime.runtime`.
"""

from __future__ import annotations

import math
import threading
from typing import Any

__all__ = ["LatestSlot", "RequestLimiter"]


class LatestSlot:
    """A one-item mailbox between threads: :meth:`put` replaces, :meth:`take` empties.

    Attributes
    ----------
    replaced : int
        Items overwritten before anyone took them (coalesced).
    """

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: Any = None
        self._full = False
        self._woken = False
        self.replaced = 0

    def put(self, item: Any) -> None:
        """Store ``item``, replacing an untaken one."""
        with self._cond:
            if self._full:
                self.replaced += 1
            self._item = item
            self._full = True
            self._cond.notify_all()

    def take(self, timeout_s: float = 0.0) -> Any:
        """Return the item and empty the slot; None if nothing arrives within ``timeout_s``
        or `wake` is called meanwhile."""
        with self._cond:
            if not self._full and not self._woken and timeout_s > 0:
                self._cond.wait_for(lambda: self._full or self._woken, timeout_s)
            self._woken = False
            if not self._full:
                return None
            item, self._item, self._full = self._item, None, False
            return item

    def wake(self) -> None:
        """Make the current or next waiting :meth:`take` return at once (None when the slot
        is empty): something else is ready for the taker."""
        with self._cond:
            self._woken = True
            self._cond.notify_all()


class RequestLimiter:
    """At most one request per ``min_interval_s``; in between, the latest offer wins.

    Parameters
    ----------
    rate_hz : float
        Requests per second at most (> 0).
    """

    def __init__(self, rate_hz: float) -> None:
        if not rate_hz > 0:
            raise ValueError(f"RequestLimiter: rate_hz={rate_hz} must be > 0")
        self.min_interval_s = 1.0 / rate_hz
        self._lock = threading.Lock()
        self._pending: Any = None
        self._last_s = -math.inf
        self.coalesced = 0

    def offer(self, item: Any) -> None:
        """Queue ``item`` (replacing one not sent yet); any thread."""
        with self._lock:
            if self._pending is not None:
                self.coalesced += 1
            self._pending = item

    def due(self, now_s: float) -> Any:
        """The item to send now (and forget), or None (nothing pending, or too soon)."""
        with self._lock:
            if self._pending is None or now_s - self._last_s < self.min_interval_s:
                return None
            item, self._pending = self._pending, None
            self._last_s = now_s
            return item

    @property
    def pending(self) -> bool:
        """An offer waits to be sent."""
        return self._pending is not None
