"""The warp worker: a device's depth warps made on a thread of their own, so that the display
never waits on one (`device_runtime.scheduler`). What it warps and when: `WarpWorker`."""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from device_runtime.orbit import canonical_view
from device_runtime.warping import WarpCancelled

__all__ = ["WarpWorker"]


class WarpWorker:
    """The warp of the latest requested view, made on a thread of its own.

    A served device that predicts shows the score blend of a new view at once (a
    reconstruction) and asks for the view's warp here; its display thread keeps taking input
    and host frames while the warp is made (numpy releases the GIL in its array work, and a
    warp costs several blends), and shows the warp only if its view is still the one on show
    and no host frame for it came first. At most one warp is in flight.

    Never a warp whose view will be gone before it is shown: while views are requested
    faster than a warp takes (a fast drag, a 60 Hz orbit), a requested view waits before
    its warp starts (`hold_s`: two recent request intervals, at most a warp's time); a
    newer request in that time replaces it unstarted (``skipped``), and the warp starts
    once the view rests; every `PROBE_S` of holding one view's warp starts anyway and
    measures a warp's time again, to its end (an estimate is not left stale by a motion that
    holds every view). Only warm warps set the estimate: one that made its neighbours (a
    cold start, a cache miss) can only lower it, so a drag that begins cold is not held.
    A view requested while a warp is in flight gives that warp up at
    its next check (`ViewSynthesizer.frame`'s ``cancel``: a neighbour already made stays
    cached). Where warps take less than the request interval every view's warp starts at
    once, as before.

    A view led: while views are held on steady motion (requests come faster than a warp
    takes), the worker warps the view the motion reaches as many steps ahead as a warp
    takes intervals, plus one (`_lead_view`, at most `LEAD_STEPS`); a request on the way
    there does not give it up, and its frame waits for its view like a view made ahead.
    Its time measures a warp again, so a slow estimate left by other work does not hold a
    quick motion's views.

    Any caller can always get the frame of a view: ``take(view, timeout_s)`` with a timeout
    asks for the view if it is neither asked nor made, starts it at once (no hold) and
    waits for it; the frame is `ViewSynthesizer.frame`'s, bit for bit.

    A view made ahead: while views come at a steady step and pace (an orbit, a steady drag:
    the last `AHEAD_VIEWS` requests a straight line in time and angle) and the next one is
    not due yet, an idle worker warps the view that line predicts (`predicted_view`,
    canonical as the device's views are). When that exact view is asked, its frame is
    there at once; another view asked gives it up (a wrong guess costs at most the warp
    time that was idle anyway). The frame is the view's, bit for bit: only an exact match
    is used; the display snaps a view asked within `AHEAD_SNAP_DEG` of it to it (`snap`:
    float32 views of the same motion differ by a step or two).

    Parameters
    ----------
    synthesis : ViewSynthesizer
        Used by this worker's thread only (it has its own reconstructor and cache).
    on_made : callable, optional
        Called (on the worker's thread, without arguments) when the warp of a requested
        view is made and waits to be taken: the display wakes for it instead of polling.

    Attributes
    ----------
    made, dropped, cancelled, skipped, errors : int
        Warps made; made but superseded by a newer request before anyone took them; given
        up for a newer request; requests replaced before their warp started; failed
        (counted, never raised: the blend stays on show).
    ahead_made, ahead_used : int
        Views warped ahead (made or begun; counted in ``made`` / ``cancelled`` too), and
        those asked for after all.
    warp_s : float or None
        The recent time a warp takes (exponential average of the warps made that made no
        neighbour, lowered by those that did, raised by a warp given up later than that that
        made no neighbour, replaced by a probe's); None until the first warm one.
    """

    #: Request intervals longer than this are a view at rest, not a drag.
    REST_S = 0.25
    #: While views are held (`hold_s`), one starts anyway once no warp has started for this
    #: long: a probe that measures a warp again (the estimate may come from a warp that made
    #: its neighbours, or from another motion), at most one warp's CPU per this period.
    PROBE_S = 0.5
    #: Weight of the newest sample in the averages of warp time and request interval.
    SMOOTHING = 0.3
    #: Requests that predict the next view (`predicted_view`): at least three.
    AHEAD_VIEWS = 3
    #: A view asked this close (degrees, each angle) to the view made ahead is that view:
    #: a few float32 steps of an angle, far below what a pixel shows.
    AHEAD_SNAP_DEG = 1e-4
    #: How far (degrees) a request may be from the line through the last ones and still be
    #: steady motion (the float32 rounding of constant steps: a hand's drag is not; a guess
    #: that will not be asked costs a warp); how far apart in time (of the interval).
    AHEAD_ANGLE_TOL = AHEAD_SNAP_DEG
    AHEAD_TIME_TOL = 1.0
    #: The farthest (in request steps) a warp leads steady motion that requests views
    #: faster than a warp takes (`_lead_view`).
    LEAD_STEPS = 8
    #: The longest a warp waits at one check for the display to finish its frame, seconds.
    YIELD_S = 0.1

    def __init__(self, synthesis: Any, on_made: Callable[[], None] | None = None, *,
                 start: bool = True) -> None:
        self.synthesis = synthesis
        self._on_made = on_made
        self._cond = threading.Condition()
        self._pending: tuple[float, float] | None = None
        self._pending_t = 0.0
        self._started_t = time.monotonic()  # when the last warp started
        self._probe = False  # the warp in flight re-measures a held worker's warp time
        self._urgent = False  # someone waits for the pending view: start it at once
        self._result: tuple[tuple[float, float], np.ndarray] | None = None
        self._current: tuple[float, float] | None = None  # the view being warped
        self._closed = False
        self._display_idle = threading.Event()  # cleared while the display makes a frame
        self._display_idle.set()
        self._last_request_t: float | None = None
        self.interval_s: float | None = None  # recent request interval (None: at rest)
        self.warp_s: float | None = None
        self.made = self.dropped = self.cancelled = self.skipped = self.errors = 0
        self.ahead_made = self.ahead_used = 0
        self._history: list[tuple[float, float, float]] = []  # (time, phi, theta) requested
        self._ahead: tuple[tuple[float, float], np.ndarray] | None = None  # made ahead
        self._guessed: tuple[float, float] | None = None  # the last view warped ahead
        self._speculative = False  # the warp in flight is a view made ahead
        self._lead = False  # ... and leads the motion by more than a step (`_lead_view`)
        self._thread = threading.Thread(target=self._run, name="eigencast-warp", daemon=True)
        if start:
            self._thread.start()

    def start(self) -> None:
        """Start the thread of a worker made with ``start=False`` (views asked before wait
        for it); nothing when it runs (or ran) already."""
        if self._thread.ident is None:
            self._thread.start()

    @staticmethod
    def hold_for(warp_s: float | None, interval_s: float | None) -> float:
        """How long a requested view waits before its warp starts (`hold_s`): 0 when warps
        are known to take no longer than the interval between requests (or either is
        unknown: a view at rest, the first warp), else two intervals (a request that did
        not come: the drag stopped or slowed; one late request is not a stop), at most one
        warp's time."""
        if warp_s is None or interval_s is None or warp_s <= interval_s:
            return 0.0
        return min(2.0 * interval_s, warp_s)

    def hold_s(self) -> float:
        """The hold of a view requested now (`hold_for` of the current averages)."""
        return self.hold_for(self.warp_s, self.interval_s)

    def request(self, view: tuple[float, float]) -> None:
        """Warp ``view`` next (any thread); an older result not taken is forgotten."""
        now = time.monotonic()
        with self._cond:
            view = (float(view[0]), float(view[1]))
            if self._last_request_t is not None:
                gap = now - self._last_request_t
                if gap > self.REST_S:
                    self.interval_s = None
                else:
                    self.interval_s = gap if self.interval_s is None else (
                        self.interval_s + self.SMOOTHING * (gap - self.interval_s))
            self._last_request_t = now
            self._history = [*self._history[1 - self.AHEAD_VIEWS:], (now, *view)]
            ahead, self._ahead = self._ahead, None
            if ahead is not None and ahead[0] != view and self._still_ahead(ahead[0]):
                self._ahead, ahead = ahead, None  # a lead further on: kept for its view
            if ahead is not None and ahead[0] == view:  # made ahead: there at once
                self.ahead_used += 1
                self._pending, self._urgent = None, False
                self._result = ahead
                self._cond.notify_all()
                return
            if self._pending is not None and self._pending != view:
                self.skipped += 1
                self._urgent = False
            if self._speculative and self._current == view:  # being made ahead: keep it
                self.ahead_used += 1
            self._pending, self._pending_t = view, now
            self._result = None
            self._cond.notify_all()

    def take(self, view: tuple[float, float], timeout_s: float = 0.0) -> np.ndarray | None:
        """The warp of ``view`` if it is made (waiting up to ``timeout_s``), else None.

        With a timeout, a view neither made, in flight nor asked is asked now, and its warp
        starts at once (no hold): the caller waits for it."""
        want = (float(view[0]), float(view[1]))
        with self._cond:
            if timeout_s > 0:
                made = self._result is not None and self._result[0] == want
                if not made and self._current != want and self._pending != want:
                    self._pending, self._pending_t = want, time.monotonic()
                    self._result = None
                if self._pending == want:
                    self._urgent = True
                    self._cond.notify_all()
                self._cond.wait_for(lambda: self._closed or (
                    self._result is not None and self._result[0] == want), timeout_s)
            if self._result is None or self._result[0] != want:
                return None
            frame, self._result = self._result[1], None
            self._cond.notify_all()  # the worker may warp ahead now
            return frame

    def close(self) -> None:
        """Stop the thread (a warp in flight is given up at its next check)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        if self._thread.ident is not None:
            self._thread.join(timeout=10.0)

    @classmethod
    def predicted_view(cls, history: list[tuple[float, float, float]], steps: int = 1
                       ) -> tuple[float, float] | None:
        """The next view of steady motion: ``history`` holds the last requests as (time,
        phi, theta), oldest first; when at least `AHEAD_VIEWS` of them lie on a straight
        line in angle (within `AHEAD_ANGLE_TOL`) with one step between each and evenly in
        time (within `AHEAD_TIME_TOL` of the interval), the view ``steps`` more steps on, by
        the least-squares line through them (its rounding averaged out: the device's views
        are float32), canonical. None: no steady motion."""
        line = cls._motion_line(history)
        return None if line is None else cls._on_line(line, steps)

    @classmethod
    def _motion_line(cls, history: list[tuple[float, float, float]]
                     ) -> tuple[tuple[float, float, float], ...] | None:
        """The least-squares line through ``history``'s angles (`predicted_view`): per
        angle (phi unwrapped, theta) its intercept, slope and last requested value, with the
        number of requests; None: no steady motion."""
        if len(history) < cls.AHEAD_VIEWS:
            return None
        t, phi, theta = (np.asarray(a, dtype=np.float64) for a in zip(*history))
        phi = phi[0] + np.concatenate([[0.0], np.cumsum((np.diff(phi) + 180.0) % 360.0
                                                        - 180.0)])  # unwrapped
        gaps = np.diff(t)
        if gaps.min() <= 0 or gaps.max() - gaps.min() > cls.AHEAD_TIME_TOL * gaps.mean():
            return None
        k = np.arange(len(phi), dtype=np.float64)
        out = []
        for a in (phi, theta):
            slope, icpt = np.polyfit(k, a, 1)
            if np.abs(icpt + slope * k - a).max() > cls.AHEAD_ANGLE_TOL:
                return None
            out.append((icpt, slope, a[-1]))
        return (*out, (float(len(phi)), 0.0, 0.0))

    @staticmethod
    def _on_line(line: tuple[tuple[float, float, float], ...], steps: int
                 ) -> tuple[float, float] | None:
        """The view ``steps`` requests on along `_motion_line`'s ``line``, canonical; None
        when the line does not move."""
        (i_phi, s_phi, last_phi), (i_theta, s_theta, last_theta), (n, _, _) = line
        phi, theta = i_phi + s_phi * (n - 1 + steps), i_theta + s_theta * (n - 1 + steps)
        if abs(phi - last_phi) + abs(theta - last_theta) < 1e-6 * steps:
            return None  # not moving
        return canonical_view(phi, theta)

    def snap(self, view: tuple[float, float]) -> tuple[float, float]:
        """``view``, or the view made (or being made) ahead when each angle is within
        `AHEAD_SNAP_DEG` of it (any thread)."""
        with self._cond:
            ahead = self._ahead[0] if self._ahead is not None else (
                self._current if self._speculative else None)
        return ahead if ahead is not None and self.same_view(ahead, view) else view

    @classmethod
    def same_view(cls, a: tuple[float, float], b: tuple[float, float]) -> bool:
        """Whether views ``a`` and ``b`` are the same to the device: each angle within
        `AHEAD_SNAP_DEG` (phi across 360)."""
        return all(abs((x - y + 180.0) % 360.0 - 180.0) <= cls.AHEAD_SNAP_DEG
                   for x, y in zip(a, b))

    def _still_ahead(self, view: tuple[float, float]) -> bool:
        """Whether ``view`` lies ahead on the line of the steady motion requested (one to
        `LEAD_STEPS` steps on); under the lock, or read without it (a stale answer costs
        one warp)."""
        line = self._motion_line(list(self._history))  # one fit for every step
        return line is not None and any(
            v is not None and self.same_view(v, view)
            for v in (self._on_line(line, k) for k in range(1, self.LEAD_STEPS + 1)))

    def _lead_view(self) -> tuple[float, float] | None:
        """While requests come faster than a warp takes (a held view) on steady motion: the
        view as many steps ahead as a warp takes intervals, plus one, so that its warp is
        made before it is asked (under the lock). None: no steady motion, or that view is
        made (or was begun) already."""
        if self.warp_s is None or self.interval_s is None or not self.interval_s > 0:
            return None
        steps = min(self.LEAD_STEPS, math.ceil(self.warp_s / self.interval_s) + 1)
        view = self.predicted_view(self._history, steps)
        if view is None or view == self._guessed or (
                self._ahead is not None and self._still_ahead(self._ahead[0])):
            return None
        return view

    def _ahead_view(self, now: float) -> tuple[float, float] | None:
        """The view to warp ahead now (under the lock), or None: only while the next request
        of steady motion is not due yet, once per predicted view, with no frame made or
        waiting to be taken."""
        if (self.interval_s is None or self._last_request_t is None or self._result is not None
                or self._ahead is not None
                or now >= self._last_request_t + self.interval_s):
            return None
        view = self.predicted_view(self._history)
        if view is None or view == self._guessed or view == self._history[-1][1:]:
            return None
        return view

    @contextlib.contextmanager
    def display_first(self) -> Iterator[None]:
        """While the display thread makes and presents a frame, the warp in flight pauses at
        its next check (`YIELD_S` at most): on one core the display's tick comes first, and
        two threads sharing the interpreter lock would otherwise hand it over at every numpy
        call of the blend."""
        self._display_idle.clear()
        try:
            yield
        finally:
            self._display_idle.set()

    def _superseded(self) -> bool:
        """Another view was asked (or the worker is closing): the warp in flight is moot.
        Waits first while the display makes a frame (`display_first`). Read without the
        lock: attribute reads, and a stale answer only delays the give-up to the next
        check."""
        self._display_idle.wait(self.YIELD_S)
        pending, current = self._pending, self._current
        if self._closed:
            return True
        if pending is None or pending == current or self._probe:
            return False  # (a probe measures a warp's time: it runs to its end)
        # a lead stays wanted while the motion still comes its way
        return not (self._lead and current is not None and self._still_ahead(current))

    def _next_view(self) -> tuple[tuple[float, float], bool] | None:
        """The view to warp next, once it has waited its hold, and whether it is made ahead
        (nothing asked: `_ahead_view`); under the lock. None: closing."""
        while True:
            if self._closed:
                return None
            now = time.monotonic()
            if self._pending is None:
                ahead = self._ahead_view(now)
                if ahead is not None:
                    self._guessed = ahead
                    return ahead, True
                self._cond.wait()  # a request, a frame taken, or closing
                continue
            hold = self.hold_s()
            wait = self._pending_t + hold - now
            if hold > 0.0 and not self._urgent:
                lead = self._lead_view()
                if lead is not None:
                    self._guessed = lead
                    self._lead = True
                    return lead, True
            probe = hold > 0.0 and now - self._started_t >= self.PROBE_S
            if self._urgent or wait <= 0.0 or probe:
                view, self._pending, self._urgent = self._pending, None, False
                self._probe = probe and wait > 0.0
                return view, False
            # a newer request, a waiting caller, the hold or the probe's time is over
            self._cond.wait(min(wait, self._started_t + self.PROBE_S - now))

    def _run(self) -> None:
        while True:
            with self._cond:
                got = self._next_view()
                if got is None:
                    return
                view, ahead = got
                self._current, self._speculative = view, ahead
                self.ahead_made += ahead
                self._started_t = t0 = time.monotonic()
            misses = getattr(self.synthesis, "misses", 0)
            try:
                frame = self.synthesis.frame(*view, cancel=self._superseded)
            except WarpCancelled:
                with self._cond:
                    self.cancelled += 1
                    spent = time.monotonic() - t0
                    # a warp takes at least this long, unless it was making neighbours: they
                    # stay cached, so the next warp is shorter (a drag that began before any
                    # warp was made would otherwise hold every view until it stopped)
                    warm = getattr(self.synthesis, "misses", 0) == misses
                    if warm and not self._speculative and (self.warp_s is None
                                                           or spent > self.warp_s):
                        self.warp_s = spent
                    self._current, self._speculative, self._probe = None, False, False
                    self._lead = False
                continue
            except Exception:  # the blend stays on show; a device must not stop on it
                with self._cond:
                    self.errors += 1
                    self._current, self._speculative, self._probe = None, False, False
                    self._lead = False
                    self._cond.notify_all()
                continue
            spent = time.monotonic() - t0
            warm = getattr(self.synthesis, "misses", 0) == misses
            with self._cond:
                self.made += 1
                if warm:  # a probe's time replaces the estimate it was started to check
                    self.warp_s = spent if self.warp_s is None or self._probe else (
                        self.warp_s + self.SMOOTHING * (spent - self.warp_s))
                elif self.warp_s is not None and spent < self.warp_s:
                    # a warp that made its neighbours says how long a warp takes at most
                    self.warp_s += self.SMOOTHING * (spent - self.warp_s)
                self._probe = False
                self._current = None
                ahead, self._speculative = self._speculative, False
                lead, self._lead = self._lead, False
                made = False
                if self._pending == view:
                    self._pending, self._urgent = None, False
                    self._result, made = (view, frame), True
                    self._cond.notify_all()
                elif ahead and (self._pending is None or lead):
                    self._ahead = (view, frame)  # until its view is asked
                elif self._pending is None:
                    if ahead:
                        self._ahead = (view, frame)  # until its view is asked
                    else:
                        self._result, made = (view, frame), True
                        self._cond.notify_all()
                else:
                    self.dropped += 1
            if made and self._on_made is not None:
                self._on_made()
