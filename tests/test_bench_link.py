"""The bookkeeping of ``benchmarks/bench_link.py --parts real`` (`link_real`): the WebP
stream's frame budget, the issue-23 verdict, and how the shown frames are classified."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import link_real
from bench_link import wire_bytes


@pytest.mark.parametrize("baud,fps,ticks", [(115200, 10.0, 1), (115200, 10.0, 4),
                                             (921600, 30.0, 2)])
def test_a_webp_frame_fits_its_ticks_of_the_line(baud, fps, ticks):
    budget = link_real.webp_budget(baud, fps, ticks)
    seconds = wire_bytes(budget) / (baud / 10.0)
    assert seconds <= 0.95 * ticks / fps  # lands before the tick that shows it
    assert wire_bytes(budget + 30) / (baud / 10.0) > 0.95 * ticks / fps  # and is the largest


def _row(fps, ssim):
    return {"fps": fps, "ssim_object": ssim}


def test_the_verdict_compares_with_the_best_webp_stream_at_no_more_frames():
    modes = {"real served": _row(9.5, 0.74), "sim webp1": _row(9.8, 0.72),
             "sim webp2": _row(5.2, 0.49)}
    v = link_real.verdict(modes)
    # webp1 is 0.3 fps faster: within the sessions' spread, so it is the stream compared
    assert "sim webp1" in v and "+0.0200" in v and "NOT met" in v
    modes["sim webp1"] = _row(9.5 + link_real.FPS_TOLERANCE + 0.5, 0.6)  # clearly faster
    v = link_real.verdict(modes)  # well above webp2, but showing fewer frames than webp1
    assert "sim webp2" in v and "+0.2500" in v and "fewer frames than sim webp1" in v
    assert "NOT met" in v
    del modes["sim webp1"]
    assert "(met" in link_real.verdict(modes)
    assert link_real.verdict({"sim webp1": _row(9.8, 0.7)}) == ""


def test_shown_frames_are_classified_by_kind_and_view():
    view = (17.0, 20.0)
    at = {"phi_deg": 17.0, "theta_deg": 20.0}
    assert link_real.frame_kind({**at, "predicted": True}, view) == "blend"
    assert link_real.frame_kind({**at, "predicted": True, "synthesized": True}, view) == "warp"
    assert link_real.frame_kind({**at, "corrected": True, "sequence": 3}, view) == "corrected"
    assert link_real.frame_kind({**at, "sequence": 3}, view) == "host"
    other = {"phi_deg": 14.0, "theta_deg": 20.0, "predicted": True}
    assert link_real.frame_kind(other, view) == "blend of another view"


def test_merged_summaries_weigh_each_session_by_its_ticks():
    merged = link_real.merge_shown([{"blend": [30, 0.7], "warp": [10, 0.9]},
                                    {"blend": [10, 0.5]}])
    assert merged == {"blend": [40, pytest.approx(0.65)], "warp": [10, 0.9]}


def test_the_longest_gap_counts_the_trace_edges():
    assert link_real.max_gap([], 0.0, 4.0) == 4.0
    assert link_real.max_gap([1.0, 1.5, 3.0], 0.0, 4.0) == 1.5


def _shown(*rows):
    """Presented frames ``(time, score, info)``: the frame is its score (a 1x1 image)."""
    import numpy as np

    return [(t, np.full((1, 1, 3), score), info) for t, score, info in rows]


def _score(frame):
    return float(frame[0, 0, 0])


def test_a_resting_views_milestones_count_from_the_moment_it_rests():
    """The corrected frame, object SSIM 0.95 / 0.99 (of whatever is on show) and the exact
    frame, in seconds after the view was set; a plan that skips the correction reaches its
    'corrected' step with its first layer; a milestone never reached is infinitely late."""
    import math

    sent = _shown((10.2, 0.80, {"predicted": True}), (10.5, 0.85, {"synthesized": True}),
                  (11.0, 0.90, {"corrected": True}), (11.4, 0.96, {"layer": 0}),
                  (12.0, 0.98, {"layer": 1}), (13.0, 0.2, {"layer": 1, "exact": True}))
    r = link_real.rest_milestones(sent, 10.0, _score)
    assert r["first_s"] == pytest.approx(0.2) and r["corrected_s"] == pytest.approx(1.0)
    assert r["ssim0.95_s"] == pytest.approx(1.4) and r["ssim0.99_s"] == pytest.approx(3.0)
    assert r["exact_s"] == pytest.approx(3.0)  # (an exact frame scores 1 whatever it is)
    assert r["correction_sent"] and r["corrected_ssim"] == 0.90 and r["own_ssim"] == 0.80
    assert r["layers_shown"] == 3
    skipped = _shown((5.1, 0.96, {"synthesized": True}), (6.5, 0.97, {"layer": 0}))
    r = link_real.rest_milestones(skipped, 5.0, _score)
    assert not r["correction_sent"] and r["corrected_s"] == pytest.approx(1.5)
    assert r["ssim0.95_s"] == pytest.approx(0.1)  # the own frame reached it already
    assert r["exact_s"] == math.inf and r["ssim0.99_s"] == math.inf


def test_the_rest_table_takes_medians_and_says_missed():
    import math

    row = {"exact": True, "correction_sent": False, "corrected_ssim": 0.95, "first_s": 0.01,
           "corrected_s": 1.0, "ssim0.95_s": 1.0, "ssim0.99_s": 4.0, "exact_s": 4.0,
           "host_ready_s": 0.5, "bytes": 30000, "webp_corrected_s": 0.3,
           "avif_corrected_s": 0.25, "webp_ssim0.95_s": 0.3, "avif_ssim0.95_s": 0.25,
           "webp_ssim0.99_s": 1.0, "avif_ssim0.99_s": 0.8, "webp_lossless_s": 2.7,
           "raycast_s": 0.4}
    rows = [{**row, "exact_s": v, "ssim0.99_s": v} for v in (3.0, 4.0, math.inf)]
    line = link_real.rest_table("t", {115200: rows}).splitlines()[-1]
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[0] == "115200" and cells[1] == "3 (3, 0)"
    assert cells[5] == "4.00" and cells[6] == "4.00"  # the median of 3, 4 and a miss
    rows = [{**row, "exact_s": math.inf} for _ in range(3)]
    assert "missed" in link_real.rest_table("t", {115200: rows})


def test_the_complete_correction_is_the_score_packet_just_before_the_first_strip():
    sparse, complete, strip = (10.1, False, 60), (11.9, False, 300), (12.0, True, 2800)
    assert link_real.complete_correction_sent([sparse, complete, strip], 10.0)
    assert not link_real.complete_correction_sent([sparse, strip], 10.0)  # skipped
    assert not link_real.complete_correction_sent([sparse, (11.9, True, 2800)], 10.0)
    # no sparse correction (nothing worth sending): the complete one alone, late
    assert link_real.complete_correction_sent([complete, strip], 10.0)
    assert not link_real.complete_correction_sent([(10.1, False, 60), (10.2, True, 9)], 10.0)
    assert not link_real.complete_correction_sent([sparse], 10.0)  # no layers at all
