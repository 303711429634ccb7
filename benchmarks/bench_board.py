"""A board's display rate on this machine: the device's real display loop on one core, its
tick shortened by the board's slowness S.

Usage (the device threads pin themselves to core 0, a served case's host to core 1)::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_board.py IMAGE.ecs [IMAGE.ecs ...]
        [--slowdown 1,3,6] [--links standalone,serial,tcp] [--traces human,drag3,orbit1,rest]

A board S times slower than this machine's core shows a 30 Hz display with a 33 ms tick;
here that tick is 33/S ms, and every time measured here is S times as long on the board
("board ms"). The real `RuntimeDevice` runs its display loop and warp worker on core 0 (as
one board core), its input coming through a presenter that plays a trace of view changes as
a window's input would, at the board's times:

* ``human``: a drag as a hand makes it (a minimum-jerk stroke of 90 degrees over 1.5 s with
  a little theta, mouse events every 8 ms), then rest;
* ``drag3``: 3 degrees of phi per tick for 60 ticks, then rest;
* ``orbit1``: 1 degree per tick for 90 ticks, then rest;
* ``rest``: one jump of 25 degrees, then rest.

Links: ``standalone`` (no host: the device's own frames), ``serial`` (a served device over
the in-process ``mem://`` line at 115200 baud) and ``tcp`` (a served device over TCP
loopback). The rest of the world runs S times faster too, so a served case keeps board
time consistent: the line runs at 115200 x S baud and the host's frame deadline is 33 / S
ms, its rate 60 x S packets per second (the host on core 1 is then S times weaker than the
workstation it stands for: its moving corrections are sparser than a real host's).

Printed per case, over the ticks from the trace's first move until 1 s of board time after
it rests: ``on time``, the share of ticks at whose end the screen shows the view the input
set at the tick's start (or a newer one); ``stall``, the longest run of ticks that were not,
in board ms; ``warp``, the share of ticks whose frame on show is the view's warp or a
corrected frame of it; ``rest->warp`` and ``rest->corr``, board ms from the last input to
the first warp (or corrected frame) of the final view. The image needs depth and the
standalone table (``fit``'s defaults); a served case ray-casts with the image's recorded
render settings, so its volume must be where the database was rendered from.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

BOARD_TICK_S = 1.0 / 30.0
BAUD = 115200
MOUSE_S = 0.008
"""Board seconds between two mouse events of the human trace."""
AFTER_REST_S = 1.0
"""Board seconds measured after the trace rests."""
START = (20.0, 15.0)


# --------------------------------------------------------------------------- traces


def _min_jerk(s: float) -> float:
    s = min(max(s, 0.0), 1.0)
    return s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)


def trace_view(name: str, t: float) -> tuple[float, float]:
    """The view the input has set ``t`` board seconds after the trace began (each trace
    rests from `trace_rest_s` on)."""
    phi0, theta0 = START
    if name == "human":
        t = math.floor(t / MOUSE_S) * MOUSE_S  # mouse events, not a continuum
        s = _min_jerk(t / 1.5)
        return phi0 + 90.0 * s, theta0 + 8.0 * math.sin(math.pi * s)
    ticks = math.floor(t / BOARD_TICK_S)
    if name == "drag3":
        return phi0 + 3.0 * min(ticks, 60), theta0
    if name == "orbit1":
        return phi0 + 1.0 * min(ticks, 90), theta0
    if name == "rest":
        return (phi0 + 25.0, theta0) if t >= 0 else START
    raise ValueError(f"unknown trace {name!r}")


def trace_rest_s(name: str) -> float:
    """Board seconds after which the trace's view no longer changes."""
    return {"human": 1.5, "drag3": 60 * BOARD_TICK_S, "orbit1": 90 * BOARD_TICK_S,
            "rest": 0.0}[name]


class TracePresenter:
    """A window that shows nothing and whose input plays a trace: each poll turns the view
    from the device's current one to the trace's view at this moment (board time). Records
    every present as (time, view, kind)."""

    headless = False
    overlay = False
    zoom = 1.0

    def __init__(self, device_view: Any, slowdown: float) -> None:
        self.device_view = device_view
        self.slowdown = slowdown
        self.start: float | None = None
        self.trace: str | None = None
        self.shown: list[tuple[float, tuple[float, float], str]] = []
        self.inputs: list[tuple[float, tuple[float, float]]] = []  # (when, view) as set

    def play(self, trace: str, start: float) -> None:
        self.trace, self.start = trace, start

    def poll(self) -> list:
        from device_runtime.display import ViewDelta

        if self.trace is None or self.start is None:
            return []
        now = time.monotonic()
        if now < self.start:
            return []
        phi, theta = trace_view(self.trace, (now - self.start) * self.slowdown)
        if not self.inputs or not _same((phi, theta), self.inputs[-1][1]):
            self.inputs.append((now, (phi, theta)))
        cur = self.device_view()
        dphi = (phi - cur[0] + 180.0) % 360.0 - 180.0
        dtheta = theta - cur[1]
        if abs(dphi) < 1e-4 and abs(dtheta) < 1e-4:
            return []
        return [ViewDelta(dphi, dtheta)]

    def present(self, frame: np.ndarray, info: dict | None = None, *,
                overlay_lines: list[str] | None = None) -> bool:
        info = info or {}
        kind = ("corrected" if info.get("corrected") else "warp" if info.get("synthesized")
                else "blend" if info.get("predicted") or not info.get("packet_bytes")
                else "host")
        self.shown.append((time.monotonic(), (info.get("phi_deg"), info.get("theta_deg")),
                           kind))
        return True

    def close(self) -> None:
        pass


# --------------------------------------------------------------------------- a session


def _pin(cores: set[int]) -> None:
    """Pin the calling thread (and the threads it starts) to ``cores`` where there are."""
    have = os.sched_getaffinity(0) | set(range(os.cpu_count() or 1))
    with_cores = cores & have
    if with_cores:
        os.sched_setaffinity(0, with_cores)


def _same(a: tuple[float, float], b: Any) -> bool:
    if b is None or b[0] is None:
        return False
    return (abs((a[0] - b[0] + 180.0) % 360.0 - 180.0) < 1e-3 and abs(a[1] - b[1]) < 1e-3)


def session(image_path: Path, flash0: Path, trace: str, slowdown: float, link: str,
            work: Path) -> dict[str, Any]:
    """One case: the device at a tick of 33/S ms, driven by ``trace``; its measures."""
    from link_real import wait_for

    from device_runtime.device import DeviceConfig
    from device_runtime.orbit import canonical_view
    from device_runtime.runtime import RuntimeDevice

    flash = work / f"flash-run-{uuid.uuid4().hex[:8]}"
    shutil.copytree(flash0, flash)
    tick = BOARD_TICK_S / slowdown
    holder: dict[str, Any] = {}
    presenter = TracePresenter(lambda: holder["device"].view, slowdown)
    config = DeviceConfig(flash_dir=flash, key=None, insecure=True, max_frame_bytes=65536)
    device = RuntimeDevice(config, presenter=presenter, standalone=link == "standalone",
                           predict=link != "standalone", view=START, fps=1.0 / tick,
                           log=lambda line: None)
    holder["device"] = device
    stop = threading.Event()
    threads = [threading.Thread(target=device.run_display, args=(stop,), daemon=True)]
    host_out: dict[str, Any] = {}
    url_host = None
    if link != "standalone":
        if link == "serial":
            name = f"bench-board-{uuid.uuid4().hex[:8]}"
            url_dev, url_host = f"mem://{name}?end=b", f"mem://{name}?end=a"
        else:
            url_dev = "tcp-listen://127.0.0.1:0"
        ready = threading.Event()
        bound: dict[str, Any] = {}

        def on_ready(transport: Any) -> None:
            bound["url"] = transport.url
            ready.set()

        threads.append(threading.Thread(target=device.run, args=(url_dev,), daemon=True,
                                        kwargs={"baud": int(BAUD * slowdown), "stop": stop,
                                                "on_ready": on_ready}))
    for t in threads:
        t.start()
    if link != "standalone":
        ready.wait(10)
        if url_host is None:
            url_host = "socket://" + bound["url"].split("://", 1)[1]

        def host() -> None:
            from host.link.options import ServeOptions, ServeParts
            from host.link.serving import serve

            _pin({1})
            try:
                host_out["stats"] = serve(image_path, url_host,
                                          ServeOptions(baud=int(BAUD * slowdown), insecure=True,
                                                       deadline_s=0.033 / slowdown,
                                                       fps=60.0 * slowdown, stats_every_s=0),
                                          ServeParts(stop=stop, log=lambda line: None))
            except BaseException as exc:  # reported below
                host_out["error"] = exc

        threading.Thread(target=host, daemon=True).start()
    try:
        # at rest on the first view, its best frame on show
        want = canonical_view(*START)
        best = ("warp",) if link == "standalone" else ("corrected",)
        if not wait_for(lambda: any(k in best and _same(want, v)
                                    for _, v, k in presenter.shown), 120):
            raise RuntimeError(f"no {best[0]} frame of the first view ({host_out})")
        time.sleep(0.2)
        t0 = device._next_tick(time.monotonic())  # the trace starts on a tick
        presenter.play(trace, t0)
        t_rest = t0 + trace_rest_s(trace) / slowdown
        t_end = t_rest + AFTER_REST_S / slowdown
        time.sleep(max(0.0, t_end - time.monotonic()) + tick)
        worker = device._model.warp_worker if device._model is not None else None
        workload = ({k: getattr(worker, k) for k in ("made", "ahead_made", "ahead_used",
                                                      "cancelled", "skipped", "dropped")}
                    | {"warp_ms": round(1e3 * (worker.warp_s or 0.0), 1)}) if worker else {}
    finally:
        stop.set()
        for t in threads:
            t.join(10)
        device.close_display()
        if link != "standalone":
            device.close()
        shutil.rmtree(flash, ignore_errors=True)
    if "error" in host_out:
        raise RuntimeError(f"serve failed: {host_out['error']!r}")
    return measure(presenter.shown, presenter.inputs, trace, t0, t_rest, t_end, tick,
                   slowdown, link) | {"worker": workload}


def measure(shown: list, inputs: list, trace: str, t0: float, t_rest: float, t_end: float,
            tick: float, slowdown: float, link: str) -> dict[str, Any]:
    """The case's measures from the presents (module docstring)."""
    from device_runtime.orbit import canonical_view

    times = np.array([t for t, _, _ in shown])
    n_ticks = round((t_end - t0) / tick)
    on_time, warp, late_run, worst = 0, 0, 0, 0
    in_times = np.array([t for t, _ in inputs])
    for k in range(n_ticks):
        start, end = t0 + k * tick, t0 + (k + 1) * tick
        i = int(np.searchsorted(times, end, side="right")) - 1
        if i < 0:
            late_run += 1
            continue
        _, view, kind = shown[i]
        # the view the input had set at the tick's start, or one it set since
        first = max(0, int(np.searchsorted(in_times, start, side="right")) - 1)
        last = int(np.searchsorted(in_times, end, side="left"))
        wanted = [canonical_view(*v) for _, v in inputs[first:last]] or [
            canonical_view(*trace_view(trace, -1.0))]
        ok = any(_same(w, view) for w in wanted)
        on_time += ok
        late_run = 0 if ok else late_run + 1
        worst = max(worst, late_run)
        warp += ok and kind in ("warp", "corrected")
    final = canonical_view(*trace_view(trace, trace_rest_s(trace) + 1.0))
    to_warp = next((t - t_rest for t, v, k in shown if t >= t_rest - tick
                    and k in ("warp", "corrected") and _same(final, v)), math.inf)
    to_corr = next((t - t_rest for t, v, k in shown if t >= t_rest - tick
                    and k == "corrected" and _same(final, v)), math.inf)
    return {"trace": trace, "link": link, "slowdown": slowdown, "ticks": n_ticks,
            "on_time": on_time / max(1, n_ticks), "stall_board_ms": 1e3 * worst * tick
            * slowdown, "warp_share": warp / max(1, n_ticks),
            "rest_to_warp_board_ms": 1e3 * max(0.0, to_warp) * slowdown,
            "rest_to_corrected_board_ms": (1e3 * max(0.0, to_corr) * slowdown
                                           if link != "standalone" else None)}


def fmt(ms: float | None) -> str:
    if ms is None:
        return "-"
    return "never" if not math.isfinite(ms) else f"{ms:.0f}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("images", nargs="+", type=Path)
    parser.add_argument("--slowdown", default="1,3,6")
    parser.add_argument("--links", default="standalone,serial,tcp")
    parser.add_argument("--traces", default="human,drag3,orbit1,rest")
    parser.add_argument("--work", type=Path, default=Path("bench-out/board"))
    parser.add_argument("--verbose", action="store_true", help="the warp worker's counts")
    args = parser.parse_args()
    from link_real import provisioned_flash

    from protocol.image import read_image

    _pin({0})  # the device's threads: one core, as a board's
    args.work.mkdir(parents=True, exist_ok=True)
    print(f"{'image':>18} {'S':>3} {'link':>10} {'trace':>7} {'on time':>8} {'stall':>6} "
          f"{'warp':>6} {'rest->warp':>10} {'rest->corr':>10}   (times in board ms)")
    for path in args.images:
        image = read_image(path)
        size = image.image_shape[0]
        flash0 = provisioned_flash(path, args.work)
        for s in (float(x) for x in args.slowdown.split(",")):
            for link in args.links.split(","):
                for trace in args.traces.split(","):
                    r = session(path, flash0, trace, s, link, args.work)
                    print(f"{path.stem[:12] + f'@{size}':>18} {s:>3g} {link:>10} {trace:>7} "
                          f"{r['on_time']:>8.0%} {fmt(r['stall_board_ms']):>6} "
                          f"{r['warp_share']:>6.0%} {fmt(r['rest_to_warp_board_ms']):>10} "
                          f"{fmt(r['rest_to_corrected_board_ms']):>10}"
                          + (f"   {r['worker']}" if args.verbose else ""), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
