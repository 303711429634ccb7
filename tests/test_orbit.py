"""Orbits and view lists (device_runtime/orbit.py): the command-line forms and their errors,
the views an orbit yields over time, canonical float32 views."""

from __future__ import annotations

import numpy as np
import pytest

from device_runtime.orbit import canonical_view, parse_orbit, parse_view_list


def test_parse_orbit_forms_and_errors():
    turn = parse_orbit("turn:12:20:2")
    assert (turn.kind, turn.seconds_per_turn, turn.theta_deg, turn.turns) == ("turn", 12, 20, 2)
    assert parse_orbit("turn:5").turns is None and parse_orbit("turn:5").theta_deg == 15.0
    steps = parse_orbit("steps:4:-30")
    orbit = steps.start(now_s=0.0)
    views = [orbit.next_view(0.0) for _ in range(5)]
    assert views == [(0.0, -30.0), (90.0, -30.0), (180.0, -30.0), (270.0, -30.0), None]
    assert parse_orbit("steps:3:0:2").total_steps == 6
    running = turn.start(now_s=100.0)
    assert running.next_view(103.0) == (90.0, 20.0)  # a quarter of 12 s
    assert running.next_view(100.0 + 24.0) is None  # two turns done
    for bad, text in [("spin:3", "turn:SECONDS"), ("turn:0", "SECONDS=0"),
                      ("steps:2.5", "integer"), ("steps:4:95", "THETA_DEG=95"),
                      ("turn:3:10:-1", "TURNS=-1"), ("steps:x", "numbers"), ("turn", "expected")]:
        with pytest.raises(ValueError, match=text):
            parse_orbit(bad)


def test_views_are_canonical_float32_wrapped():
    phi, theta = canonical_view(-30.1, 95.0)
    assert phi == float(np.float32(329.9)) and theta == 90.0
    assert canonical_view(720.0, 0.0) == (0.0, 0.0)
    assert canonical_view(359.99999999, 0.0)[0] < 360.0
    assert parse_view_list("10,5; 370,-5") == [(10.0, 5.0), (10.0, -5.0)]
    for bad in ("10", "10,100", "a,b", ""):
        with pytest.raises(ValueError):
            parse_view_list(bad)
