"""Which views a device shows by itself: orbits and view lists.

:func:`parse_orbit` (shared with ``eigencast serve --orbit``) and :func:`parse_view_list`
(``eigencast-device --views``) read the command-line forms; :class:`Orbit` yields the view
for a moment of an orbit; :func:`canonical_view` is the view both sides use for any
(phi, theta): phi wrapped, theta clipped, both as a score packet's header carries them.

Orbits (:func:`parse_orbit`, shared with ``eigencast serve --orbit``)::

    turn:SECONDS[:THETA_DEG[:TURNS]]   a full turn of phi every SECONDS at elevation
                                       THETA_DEG (default 15), TURNS turns (default: forever)
    steps:N[:THETA_DEG[:TURNS]]        N evenly spaced views per turn (phi = 360 i / N),
                                       each shown once, TURNS turns (default 1)
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

__all__ = ["Orbit", "OrbitSpec", "canonical_view", "parse_orbit", "parse_view_list"]


def canonical_view(phi_deg: float, theta_deg: float) -> tuple[float, float]:
    """The view both sides use: phi wrapped to [0, 360), theta clipped to [-90, 90], both
    rounded to float32 (what a score packet's header carries).

    The host interpolates at exactly these values, so the view in a packet names the
    scores it carries bit for bit.
    """
    phi = float(np.float32(float(phi_deg) % 360.0))
    if phi >= 360.0:
        phi = 0.0
    theta = float(np.float32(min(90.0, max(-90.0, float(theta_deg)))))
    return phi, theta


@dataclass(frozen=True)
class OrbitSpec:
    """A parsed ``--orbit`` spec (see the module docstring).

    Attributes
    ----------
    kind : {"turn", "steps"}
    seconds_per_turn : float or None
        ``turn`` only.
    steps_per_turn : int or None
        ``steps`` only.
    theta_deg : float
    turns : float or None
        None: forever (``turn`` only).
    spec : str
        The text it was parsed from.
    """

    kind: str
    seconds_per_turn: float | None
    steps_per_turn: int | None
    theta_deg: float
    turns: float | None
    spec: str

    @property
    def total_steps(self) -> int | None:
        """Views of a ``steps`` orbit (None for ``turn``)."""
        if self.kind != "steps" or self.steps_per_turn is None:
            return None
        return round(self.steps_per_turn * (self.turns or 1))

    def start(self, now_s: float | None = None, phi0_deg: float = 0.0) -> Orbit:
        """A running orbit from ``now_s`` (monotonic seconds), starting at ``phi0_deg``."""
        return Orbit(self, time.monotonic() if now_s is None else now_s, phi0_deg)


class Orbit:
    """A running orbit: :meth:`next_view` yields its views (None when finished)."""

    def __init__(self, spec: OrbitSpec, start_s: float, phi0_deg: float) -> None:
        self.spec = spec
        self.start_s = start_s
        self.phi0_deg = phi0_deg
        self.index = 0

    def next_view(self, now_s: float) -> tuple[float, float] | None:
        """The next view: for ``turn`` where the orbit is at ``now_s``, for ``steps`` the
        next step (each once); None once the orbit is over."""
        spec = self.spec
        if spec.kind == "turn":
            assert spec.seconds_per_turn is not None
            elapsed = max(0.0, now_s - self.start_s)
            if spec.turns is not None and elapsed >= spec.turns * spec.seconds_per_turn:
                return None
            phi = self.phi0_deg + 360.0 * elapsed / spec.seconds_per_turn
        else:
            total = spec.total_steps
            assert total is not None and spec.steps_per_turn is not None
            if self.index >= total:
                return None
            phi = self.phi0_deg + 360.0 * self.index / spec.steps_per_turn
        self.index += 1
        return canonical_view(phi, spec.theta_deg)


def parse_orbit(text: str) -> OrbitSpec:
    """Parse ``turn:SECONDS[:THETA_DEG[:TURNS]]`` or ``steps:N[:THETA_DEG[:TURNS]]``.

    Raises
    ------
    ValueError
        The spec does not parse; the message gives the accepted forms.
    """
    forms = "turn:SECONDS[:THETA_DEG[:TURNS]] or steps:N[:THETA_DEG[:TURNS]]"
    parts = str(text).strip().split(":")
    kind = parts[0].lower()
    if kind not in ("turn", "steps") or not 2 <= len(parts) <= 4:
        raise ValueError(f"orbit {text!r}: expected {forms}, e.g. turn:12:20 or steps:72:15")
    try:
        values = [float(p) for p in parts[1:]]
    except ValueError:
        raise ValueError(f"orbit {text!r}: SECONDS/N, THETA_DEG and TURNS must be numbers "
                         f"({forms})") from None
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"orbit {text!r}: values must be finite")
    theta = values[1] if len(values) > 1 else 15.0
    if not -90.0 <= theta <= 90.0:
        raise ValueError(f"orbit {text!r}: THETA_DEG={theta:g} must be within [-90, 90]")
    turns = values[2] if len(values) > 2 else None
    if turns is not None and not turns > 0:
        raise ValueError(f"orbit {text!r}: TURNS={turns:g} must be > 0")
    if kind == "turn":
        if not values[0] > 0:
            raise ValueError(f"orbit {text!r}: SECONDS={values[0]:g} must be > 0")
        return OrbitSpec("turn", values[0], None, theta, turns, str(text))
    if values[0] != int(values[0]) or not 1 <= values[0] <= 1_000_000:
        raise ValueError(f"orbit {text!r}: N={values[0]:g} must be an integer in 1..1000000")
    return OrbitSpec("steps", None, int(values[0]), theta, turns if turns else 1.0, str(text))


def parse_view_list(text: str) -> list[tuple[float, float]]:
    """Parse ``PHI,THETA;PHI,THETA;...`` (degrees) into canonical views.

    Raises
    ------
    ValueError
        A pair does not parse or theta is outside [-90, 90].
    """
    views = []
    for item in str(text).replace(" ", "").split(";"):
        if not item:
            continue
        try:
            phi, theta = (float(v) for v in item.split(","))
        except ValueError:
            raise ValueError(f"views {text!r}: {item!r} is not PHI,THETA") from None
        if not (math.isfinite(phi) and -90.0 <= theta <= 90.0):
            raise ValueError(f"views {text!r}: {item!r}: phi must be finite and theta within "
                             "[-90, 90]")
        views.append(canonical_view(phi, theta))
    if not views:
        raise ValueError(f"views {text!r}: no PHI,THETA pair")
    return views
