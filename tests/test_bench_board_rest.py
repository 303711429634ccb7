"""The board and resting benchmarks still run against today's device and host code (a
benchmark that fails to import or to drive the device measures nothing): one short case of
each on a 40 px model. No timing is asserted; the figures are BENCHMARKS.md's."""

from __future__ import annotations

import math
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from host.cli import main as eigencast

BENCH = Path(__file__).resolve().parent.parent / "benchmarks"


@pytest.fixture(scope="module")
def depth_model(tmp_path_factory) -> Path:
    """An unsigned tooth model with depth and the standalone table (fit's defaults), 40 px."""
    root = tmp_path_factory.mktemp("bench-smoke")
    db, out = root / "tooth.cdb", root / "tooth.ecs"
    assert eigencast(["render", "builtin:tooth", "-o", str(db), "--views", "grid:16x5",
                      "--size", "40", "--samples", "80"]) == 0
    assert eigencast(["fit", str(db), "-o", str(out), "--cell", "12", "--threshold",
                      "0.99"]) == 0
    return out


@pytest.fixture(scope="module")
def bench_path():
    sys.path.insert(0, str(BENCH))
    yield
    sys.path.remove(str(BENCH))


@pytest.mark.parametrize("link", ["standalone", "serial"])
def test_bench_board_drives_the_real_display_loop(depth_model, bench_path, tmp_path, link):
    """A rest after a jump on the device's real display loop, standalone and served by a real
    ``eigencast serve`` process over the relayed ``mem://`` line: every tick measured, and
    the final view's warp (served: and a corrected frame or layer of it) shown."""
    import bench_board
    from link_real import provisioned_flash

    flash = provisioned_flash(depth_model, tmp_path)
    r = bench_board.session(depth_model, flash, "rest", 1.0, link, tmp_path)
    assert r["ticks"] > 20 and 0.0 <= r["on_time"] <= 1.0
    assert r["warp_share"] > 0.0 and math.isfinite(r["rest_to_warp_board_ms"])
    if link == "standalone":
        assert r["rest_to_corrected_board_ms"] is None
    else:
        assert math.isfinite(r["rest_to_corrected_board_ms"])
    assert r["worker"]["made"] >= 1


def test_bench_rest_plans_and_times_the_layers(depth_model, bench_path):
    """Two views' resting chains planned as serve plans them, split as serve splits them,
    and each layer applied as the device applies it (chunks joined, one decode) against the
    blend: every label has a positive time and ratio."""
    import bench_rest

    planned = bench_rest.plan_views(depth_model, 2, 1, 1 << 16, [600])
    assert len(planned["chains"]) == 2
    for chain in planned["chains"]:
        assert chain.steps[-1].kind == "exact"
        assert np.array_equal(chain.steps[-1].frame, chain.truth)
    cores = os.sched_getaffinity(0)
    try:
        timed = bench_rest.time_device(planned, min(cores), 1, [600])
    finally:
        os.sched_setaffinity(0, cores)  # it pins the process to the one core it times on
    assert timed["blend_ms"] > 0
    assert {"exact", "exact@600"} <= set(timed["layer_ms"])
    assert all(v > 0 for v in timed["x_blend"].values())
