"""A served device's display and warp worker under a 60 Hz drag or orbit, in-process: the CPU
it takes and the warps it shows, with the next view warped ahead and without, in one run.

Usage (one core, as a board has)::

    OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 taskset -c 0 .venv/bin/python \\
        benchmarks/bench_served_drag.py IMAGE.ecs [IMAGE.ecs ...] [--seconds 6] [--steps 3,0.5]

What runs (no host, no link: the device's own frames only): a display thread that, every
1/60 s, moves the view ``step`` degrees of phi (a steady motion: an orbit, a constant drag),
takes the view the worker made ahead when it is a float32 step away (`WarpWorker.snap`, as
`RuntimeDevice.set_view` does), shows the warp at once when it is made already, else the
score blend of the view (the reconstruction a served device shows first), asks the worker
for the view's warp (`WarpWorker.request`) and looks for it until the next tick. The worker
warps with its own lean reconstructor, as a served device's does. Each image is run with
the worker as shipped (``ahead``) and with warping ahead off (``baseline``: the worker before
it), alternately, so both see the same load; each starts at rest on the first view, its warp
made (the worker's first estimate of a warp's time includes making its neighbours; while it
holds views the worker measures a warp again every `WarpWorker.PROBE_S`).

Printed per image and step: CPU cores used (process CPU seconds per wall second), display
ticks whose frame was a warp of the view, warps made / made ahead / used, and the ratio of
the two runs' CPU. The image needs depth and the standalone table (``fit`` defaults).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from device_runtime.orbit import canonical_view
from device_runtime.reconstruct import Reconstructor
from device_runtime.standalone import StandaloneScores
from device_runtime.synthesis import WORKER_SCRATCH_BYTES, ViewSynthesizer
from device_runtime.warp_worker import WarpWorker
from protocol.image import read_image

TICK_S = 1.0 / 60.0


class NoAhead(WarpWorker):
    """The worker with warping ahead off: no number of requests predicts a view."""

    AHEAD_VIEWS = 1 << 30


def session(image, worker_class: type, seconds: float, step: float) -> dict:
    """One 60 Hz session of ``seconds`` (module docstring)."""
    standalone = StandaloneScores(image)
    display = Reconstructor.from_image(image, threads="auto")
    worker = worker_class(ViewSynthesizer(image, standalone, Reconstructor.from_image(
        image, threads=1, scratch_bytes=WORKER_SCRATCH_BYTES)))
    start = canonical_view(17.0, 15.0)  # at rest there first: its warp made (and timed)
    worker.request(start)
    worker.take(start, timeout_s=60.0)
    warped_ticks = ticks = 0
    c0, t0 = time.process_time(), time.perf_counter()
    try:
        while time.perf_counter() - t0 < seconds:
            view = worker.snap(canonical_view(17.0 + step * (ticks + 1), 15.0))
            worker.request(view)
            shown = worker.take(view) is not None
            if not shown:
                display.update(standalone.scores(*view))  # the blend first
            end = t0 + (ticks + 1) * TICK_S
            while not shown and time.perf_counter() < end:
                shown = worker.take(view) is not None
                time.sleep(0.002)  # the display's turn: input, host frames
            warped_ticks += shown
            time.sleep(max(0.0, end - time.perf_counter()))
            ticks += 1
        cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    finally:
        worker.close()
        display.close()
    return {"cores": cpu / wall, "ticks": ticks, "warped_ticks": warped_ticks,
            "made": worker.made, "ahead_made": worker.ahead_made,
            "ahead_used": worker.ahead_used}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("images", nargs="+", type=Path)
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--steps", default="3,0.5", help="degrees of phi a tick")
    args = ap.parse_args()
    steps = [float(s) for s in args.steps.split(",") if s.strip()]
    for path in args.images:
        try:
            image = read_image(path, read_annex=False)
            if image.synthesis is None:
                raise ValueError("no depth (fit it with the defaults)")
        except (OSError, ValueError) as exc:
            print(f"bench_served_drag: {path}: {exc}", file=sys.stderr)
            return 2
        for step in steps:
            base = session(image, NoAhead, args.seconds, step)
            ahead = session(image, WarpWorker, args.seconds, step)
            print(f"{path.name}, {step:g} deg a tick, {args.seconds:g} s at 60 Hz: "
                  f"baseline {base['cores']:.2f} cores, {base['warped_ticks']} of "
                  f"{base['ticks']} ticks warped ({base['made']} warps made); ahead "
                  f"{ahead['cores']:.2f} cores ({ahead['cores'] / base['cores']:.2f}x), "
                  f"{ahead['warped_ticks']} of {ahead['ticks']} ticks warped ({ahead['made']} "
                  f"made, {ahead['ahead_made']} ahead, {ahead['ahead_used']} of those used)",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
