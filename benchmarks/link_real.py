"""``bench_link.py --parts real``: real serve sessions against a WebP stream (issue 23).

A real `host.link.serving.serve` (ray-casting on this machine's CPU) and a real
`device_runtime.runtime.RuntimeDevice` (its own threads, its display loop at a window's
60 Hz, its warp worker) talk over a paced ``mem://`` line at each baud, in this process.
The trace's view is set on the device at each tick (as a drag in the window does). Modes:

* ``served``: the one served path, ``serve()`` as it is by default, to a device that
  synthesizes its own frames: the model has depth and the standalone table (``fit``'s
  default), so the device shows its blend at once, then its warp, and the host's
  corrections of exactly that frame (sparse while the view moves, complete at rest);
* ``served-blend``: the same with the same database fitted ``--no-depth`` (``--blend-cache``
  holds ``VOLUME-SIZE.ecs``): the device's own frame is the blend of its predicted scores;
* ``motion``: what an older device gets: ``ServeOptions(scores="motion")`` (absolute scores
  of a sparse ray-cast, key and delta packets) to a device that does not predict;
* ``webp`` (``webpN``: N line ticks): a stream of WebP files, each the highest quality
  whose frame takes at most N ticks of the line (``webp`` = ``webp1``: one per tick, so it
  keeps up with every tick), simulated on the same trace and line
  (`bench_link.simulate`: the fresh ray-cast of the latest view is encoded the moment the
  line is free; no host compute time, which favours the stream).

The host's sparse source of each mode is made and prepared once and shared by that mode's
sessions, as a long-running ``serve`` keeps it (``--cold-host``: each session's ``serve``
makes and prepares its own).

Per tick the frame the device shows ``sample_delay_s`` after the tick's view was set (two
display ticks) is compared with a fresh ray-cast of the tick's view (object SSIM, FLIP; mask:
ray-cast alpha); ``fps`` counts ticks showing a frame not shown at the previous tick; bytes
are wire bytes per score packet received during the trace; "view to frame" is the median
time from setting a view to the first frame of it on show. The verdict per trace (issue
23): the served path's object SSIM minus the best WebP stream's whose fps is not above it.

``bench_link.py --parts rest`` (`rest_part`): one real session per baud in which the
device rests on each of ``--rest-views`` random views in turn until the frame on show is
the exact ray-cast (`rest_session`): per view the time from setting the view to its
corrected frame (the first layer when the plan skips the correction), to object SSIM 0.95
and 0.99 (of whatever frame is on show, the own frame included) and to the exact frame,
when the host had the view's layers planned, against the time the smallest WebP and AVIF
of each quality (and the WebP lossless file) take on the same line (`codec_times`: one
frame, no host time); medians over the views.
"""

from __future__ import annotations

import itertools
import math
import shutil
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

#: When a tick's frame is sampled, after the tick's view was set: two 60 Hz display ticks.
SAMPLE_DELAY_S = 2.0 / 60.0
#: The real modes: (serve's ``scores``, the device predicts).
SESSION_MODES = {"served": ("auto", True), "served-blend": ("auto", True),
                 "motion": ("motion", False)}
DEFAULT_REAL_MODES = "served,served-blend,motion,webp1,webp2,webp4"
#: The verdict counts a WebP stream as "no more frames per second" up to this many more
#: (a tick or two of a 4 s trace: the sessions' own spread).
FPS_TOLERANCE = 0.5


class _Presenter:
    """A window-like presenter that shows nothing: the runtime's display loop then runs at a
    window's 60 Hz (a headless presenter polls at 20 Hz)."""

    headless = False
    overlay = False
    zoom = 1.0

    def poll(self) -> list:
        return []

    def present(self, frame: np.ndarray, info: dict | None = None, *,
                overlay_lines: list[str] | None = None) -> bool:
        return True

    def close(self) -> None:
        pass


class DeviceThreads:
    """A keyless (``--insecure``) `RuntimeDevice` on ``url``: its link and its display loop
    on threads; ``shown`` records (monotonic time, frame, info) per present."""

    def __init__(self, flash: Path, url: str, baud: int, *, predict: bool,
                 view: tuple[float, float], record: bool = True,
                 max_frame_bytes: int = 65536) -> None:
        from device_runtime.device import DeviceConfig
        from device_runtime.runtime import RuntimeDevice

        self.shown: list[tuple[float, np.ndarray, dict]] = []
        on_frame = ((lambda f, info: self.shown.append((time.monotonic(), f.copy(),
                                                        dict(info or {}))))
                    if record else None)
        # frames as large as the model's key packets (eigencast-device --max-frame 65536)
        config = DeviceConfig(flash_dir=flash, key=None, insecure=True,
                              max_frame_bytes=max_frame_bytes)
        self.device = RuntimeDevice(config, predict=predict, view=view, on_frame=on_frame,
                                    presenter=_Presenter(), log=lambda line: None)
        self.stop_event = threading.Event()
        ready = threading.Event()
        self.threads = [
            threading.Thread(target=self.device.run, args=(url,), daemon=True,
                             kwargs={"baud": baud, "stop": self.stop_event,
                                     "on_ready": lambda t: ready.set()}),
            threading.Thread(target=self.device.run_display, args=(self.stop_event,),
                             daemon=True)]
        for t in self.threads:
            t.start()
        ready.wait(10)

    def stop(self) -> None:
        self.stop_event.set()
        for t in self.threads:
            t.join(10)
        self.device.close_display()


def wait_for(predicate: Any, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return False


def provisioned_flash(model_path: Path, work: Path) -> Path:
    """A flash folder holding ``model_path``'s image (provisioned once, unpaced)."""
    from host.link.options import ProvisionOptions, ProvisionParts
    from host.link.provisioning import provision

    flash = work / f"flash-{model_path.parent.name}-{model_path.stem}"
    if (flash / ".done").exists():
        return flash
    shutil.rmtree(flash, ignore_errors=True)
    name = f"bench-prov-{uuid.uuid4().hex[:8]}"
    dev = DeviceThreads(flash, f"mem://{name}?end=b&pace=0", 115200, predict=False,
                        view=(0.0, 0.0), record=False)
    try:
        provision(model_path, f"mem://{name}?end=a&pace=0",
                  ProvisionOptions(insecure=True, show_progress=False),
                  ProvisionParts(log=lambda line: None))
    finally:
        dev.stop()
    (flash / ".done").write_text("ok")
    return flash


def settle(dev: DeviceThreads, view: tuple[float, float], quiet_s: float = 0.6,
           timeout_s: float = 60.0) -> None:
    """Wait until the device shows a host frame of ``view`` and then nothing new for
    ``quiet_s`` (the resting view's corrections are done): the steady state before a trace."""
    from device_runtime.orbit import canonical_view

    want = canonical_view(*view)

    def hosts() -> bool:
        return any(i.get("sequence") and (i.get("phi_deg"), i.get("theta_deg")) == want
                   for _, _, i in dev.shown)

    if not wait_for(hosts, timeout_s):
        raise RuntimeError(f"no host frame for the first view {view} in {timeout_s:g} s")
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        last = dev.shown[-1][0]
        if time.monotonic() - last >= quiet_s:
            return
        time.sleep(0.05)


def prepared_source(case: Any, mode: str) -> Any:
    """The host's sparse source for ``mode``'s sessions, prepared (`MotionScores.prepare`:
    every stride's recovery factors and the model's projectors) and kept across sessions as
    one long-running ``serve`` keeps it: the sessions measure a host in its steady state,
    its cost model warm. (Before ``serve`` prepared the sources it makes, a fresh one
    computed them on its loop at the first rest, seconds without answering a request.)"""
    from device_runtime.prediction import OwnFrames
    from host.fit.motion import MotionScores

    own = OwnFrames(case.model.image) if SESSION_MODES[mode][1] else None
    source = MotionScores(case.model, case.renderer, own=own)
    source.prepare()  # the recovery factors of every stride and the model's projectors
    return source


def real_session(case: Any, model_path: Path, flash0: Path, trace: list[tuple[float, float]],
                 fps: float, baud: int, mode: str, work: Path,
                 sample_delay_s: float = SAMPLE_DELAY_S, source: Any = None) -> dict[str, Any]:
    """One real serve session of ``mode`` (`SESSION_MODES`) over a paced mem:// line,
    driven by ``trace``; each tick's frame is the one on show ``sample_delay_s`` after the
    tick's view was set, scored against ``case.render`` of the tick's view. ``source``:
    the host's sparse source (`prepared_source`; default: serve builds a fresh one)."""
    from device_runtime.orbit import canonical_view
    from device_runtime.warp_worker import WarpWorker
    from host.link.options import ServeOptions, ServeParts
    from host.link.serving import serve

    scores, predict = SESSION_MODES[mode]
    flash = work / f"flash-run-{uuid.uuid4().hex[:8]}"
    shutil.copytree(flash0, flash)
    name = f"bench-real-{uuid.uuid4().hex[:8]}"
    dev = DeviceThreads(flash, f"mem://{name}?end=b", baud, predict=predict, view=trace[0])
    device = dev.device
    stop = threading.Event()
    out: dict[str, Any] = {}
    sent: list[float] = []  # when the host queued each packet

    def host() -> None:
        try:
            out["stats"] = serve(model_path, f"mem://{name}?end=a",
                                 ServeOptions(baud=baud, insecure=True, scores=scores,
                                              stats_every_s=0),
                                 ServeParts(stop=stop, log=lambda line: None, model=case.model,
                                            renderer=case.renderer, motion=source,
                                            on_frame=lambda enc, view: sent.append(
                                                time.monotonic())))
        except BaseException as exc:  # reported below
            out["error"] = exc

    thread = threading.Thread(target=host, daemon=True)
    thread.start()
    try:
        settle(dev, trace[0])
        if "error" in out:
            raise RuntimeError(f"serve failed: {out['error']!r}")
        link = device.link
        wire0 = link.stats.bytes_received if link else 0
        rs = device.runtime_stats
        counts0 = (rs.packets, rs.predicted_frames, rs.corrected_frames, rs.stale_dropped,
                   rs.synthesized_frames)
        n_shown0 = len(dev.shown)
        dt = 1.0 / fps
        t0 = time.monotonic()
        moves: list[tuple[float, tuple[float, float]]] = []  # (when, the device's view) set
        views_set: list[tuple[float, float]] = []  # per tick, the device's view
        for i, view in enumerate(trace):
            target = t0 + i * dt
            time.sleep(max(0.0, target - time.monotonic()))
            if not WarpWorker.same_view(canonical_view(*view), device.view):  # a resting hand
                when = time.monotonic()
                device.set_view(*view)  # (a view made ahead a float32 step away is taken)
                moves.append((when, device.view))
            views_set.append(device.view)
        time.sleep(max(0.0, t0 + len(trace) * dt - time.monotonic()))
        t_end = time.monotonic()
        wire = (link.stats.bytes_received if link else 0) - wire0
        counts = [a - b for a, b in zip((rs.packets, rs.predicted_frames, rs.corrected_frames,
                                         rs.stale_dropped, rs.synthesized_frames), counts0,
                                        strict=True)]
    finally:
        stop.set()
        thread.join(30)
        dev.stop()
        shutil.rmtree(flash, ignore_errors=True)
    stats = out.get("stats")
    shown = dev.shown
    ticks = [min(t0 + i * dt + sample_delay_s, t_end) for i in range(len(trace))]
    ssims, flips, new, kinds = _score_ticks(case, trace, shown, views_set, ticks)
    seconds = len(trace) * dt
    packets = counts[0]
    # from each view change to the first frame of that view on show (own or host's)
    waits = [next((t - when for t, _, i in shown[n_shown0:] if t >= when
                   and (i.get("phi_deg"), i.get("theta_deg")) == v), math.inf)
             for when, v in moves]
    # ... and to the first warp of it (the device's synthesis, an image with depth)
    warps = [next((t - when for t, _, i in shown[n_shown0:] if t >= when and i.get(
        "synthesized") and (i.get("phi_deg"), i.get("theta_deg")) == v), math.inf)
             for when, v in moves]
    return {"fps": new / seconds,
            "view_ms": 1e3 * float(np.median(waits)) if waits else float("nan"),
            "warp_ms": 1e3 * float(np.median(warps)) if warps else float("nan"),
            "warps_shown": sum(math.isfinite(w) for w in warps), "moves": len(moves),
            "ssim_object": float(np.mean(ssims)), "flip_object": float(np.mean(flips)),
            "ssim_ticks": [round(s, 4) for s in ssims],
            "bytes_per_frame": wire / packets if packets else float("nan"),
            "bytes_per_s": wire / seconds, "line_use": wire / (baud / 10.0) / seconds,
            "packets": packets, "predicted": counts[1], "corrected": counts[2],
            "stale": counts[3], "warped": counts[4],
            "strides": dict(stats.stride_frames) if stats else {},
            "shown": {k: [len(v), round(float(np.mean(v)), 4)] for k, v in sorted(kinds.items())},
            "host_packets": sum(t0 <= t <= t_end for t in sent),
            "host_gap_s": max_gap([t for t in sent if t0 <= t <= t_end], t0, t_end),
            "unchanged": stats.unchanged_frames if stats else 0,
            "converged": stats.converged_frames if stats else 0}


def _score_ticks(case: Any, trace: list[tuple[float, float]], shown: list, views_set: list,
                 ticks: list[float]) -> tuple[list[float], list[float], int, dict]:
    """Score the frame on show at each tick's sample time against ``case.render`` of the
    tick's view: (SSIMs, FLIPs, how many times a new frame was on show, SSIMs per kind of
    frame, `frame_kind`)."""
    from bench_link import quality

    ssims, flips, new = [], [], 0
    kinds: dict[str, list[float]] = {}  # what was on show at the samples: SSIMs per kind
    prev = None
    for i, view in enumerate(trace):
        k = max((j for j, (t, _, _) in enumerate(shown) if t <= ticks[i]), default=None)
        if k is None:
            continue
        if prev is not None and k != prev:
            new += 1
        prev = k
        rgb, mask = case.render(view)
        s_, f_ = quality(rgb, shown[k][1], mask)
        ssims.append(s_)
        flips.append(f_)
        kinds.setdefault(frame_kind(shown[k][2], views_set[i]), []).append(s_)
    return ssims, flips, new, kinds


def frame_kind(info: dict, view: tuple[float, float]) -> str:
    """What a shown frame was: the device's ``blend`` or ``warp``, a ``corrected`` own
    frame, a ``host`` frame (key/delta scores), each of ``view`` or else ``... of another
    view`` (an older one still on show)."""
    kind = ("corrected" if info.get("corrected") else "warp" if info.get("synthesized")
            else "blend" if info.get("predicted") else "host")
    same = (info.get("phi_deg"), info.get("theta_deg")) == view
    return kind if same else f"{kind} of another view"


def merge_shown(runs: list[dict[str, list]]) -> dict[str, list]:
    """Sessions' ``shown`` summaries (kind: [ticks, mean SSIM]) as one."""
    out: dict[str, list] = {}
    for shown in runs:
        for kind, (n, mean) in shown.items():
            m, total = out.get(kind, [0, 0.0])
            out[kind] = [m + n, total + n * mean]
    return {k: [n, round(total / n, 4)] for k, (n, total) in sorted(out.items())}


def max_gap(times: list[float], t0: float, t1: float) -> float:
    """The longest time in [t0, t1] without an event of ``times`` (sorted), seconds."""
    edges = [t0, *times, t1]
    return float(max(b - a for a, b in itertools.pairwise(edges)))


def webp_budget(baud: int, fps: float, ticks: int) -> int:
    """The largest WebP payload whose frame takes at most ``ticks`` display ticks of the
    line (95 % of them: a frame lands before the tick that shows it)."""
    from bench_link import FRAME_OVERHEAD, wire_bytes

    room = 0.95 * ticks * baud / 10.0 / fps
    payload = int((room - FRAME_OVERHEAD - 1) * 254 / 255)
    while payload > 64 and wire_bytes(payload) > room:
        payload -= 1
    return max(64, payload)


def webp_stream(case: Any, trace: list[tuple[float, float]], fps: float, baud: int,
                ticks: int, rd: tuple[float, float]) -> dict[str, Any]:
    """The simulated WebP stream whose frames each take at most ``ticks`` line ticks."""
    from bench_link import simulate

    budget = webp_budget(baud, fps, ticks)
    r = simulate(case, trace, fps, baud, "webp", rd=rd, budget=budget)
    r["budget"] = budget
    r["bytes_per_s"] = r["line_use"] * baud / 10.0
    return r


def verdict(modes: dict[str, dict]) -> str:
    """Issue 23's check: ``served`` at least 0.1 object SSIM above the best WebP stream
    whose fps is not above the served path's."""
    served = modes.get("real served")
    streams = [(k, r) for k, r in modes.items() if k.startswith("sim webp")]
    if served is None or not streams:
        return ""
    head = f"served {served['ssim_object']:.4f} at {served['fps']:.1f} fps"
    fastest_name, fastest = max(streams, key=lambda kr: kr[1]["fps"])
    fps_ok = served["fps"] >= fastest["fps"] - FPS_TOLERANCE
    fair = [(k, r) for k, r in streams if r["fps"] <= served["fps"] + FPS_TOLERANCE]
    if not fair:
        return (f"{head}: every WebP stream shows more frames (NOT met: the slowest, "
                f"{min(r['fps'] for _, r in streams):.1f} fps)")
    name, best = max(fair, key=lambda kr: kr[1]["ssim_object"])
    gap = served["ssim_object"] - best["ssim_object"]
    met = fps_ok and gap >= 0.1
    slower = ("" if fps_ok else f"; fewer frames than {fastest_name} "
              f"({fastest['ssim_object']:.4f} at {fastest['fps']:.1f} fps)")
    return (f"{head} vs the best WebP stream at no more fps ({name}: "
            f"{best['ssim_object']:.4f} at {best['fps']:.1f} fps): {gap:+.4f}{slower} "
            f"({'met' if met else 'NOT met'}: >= +0.1 at no fewer fps)")


def real_table(title: str, res: dict[int, dict[str, dict]]) -> str:
    lines = [f"**{title}**", "",
             "| baud | mode | fps shown | SSIM obj | FLIP obj | bytes/frame | B/s | "
             "predicted / corrected / stale / warped | strides (host) | host packets "
             "(longest gap) | view to frame ms (to its warp) | "
             "on show at the samples: ticks (SSIM) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for baud, modes in res.items():
        for mode, r in modes.items():
            if "packets" in r:
                extra = f"{r['predicted']} / {r['corrected']} / {r['stale']} / {r['warped']}"
                strides = ", ".join(f"{k}: {v}" for k, v in sorted(
                    r["strides"].items(), key=lambda kv: int(kv[0]))) or "-"
                wait = f"{r['view_ms']:.0f}"
                if r.get("warps_shown"):
                    wait += (f" (warp {r['warp_ms']:.0f}, {r['warps_shown']} of "
                             f"{r['moves']} views)")
                host = f"{r['host_packets']} ({r['host_gap_s']:.1f} s)"
                on_show = ", ".join(f"{k} {n} ({m:.2f})" for k, (n, m) in r["shown"].items())
            else:
                extra, strides, wait = f"budget {r['budget']} B", "", ""
                host = on_show = ""
            lines.append(f"| {baud} | {mode} | {r['fps']:.1f} | {r['ssim_object']:.4f} | "
                         f"{r['flip_object']:.4f} | {r['bytes_per_frame']:.0f} | "
                         f"{r['bytes_per_s']:.0f} | {extra} | {strides} | {host} | {wait} | "
                         f"{on_show} |")
        v = verdict(modes)
        if v:
            lines.append(f"\n{baud}: {v}")
    return "\n".join(lines)


def real_part(case: Any, blend_case: Any | None, path: Path, blend_path: Path | None,
              desc: str, traces: list[str], bauds: list[int], modes: list[str],
              seconds: float, fps: float, work: Path, rd: tuple[float, float],
              sample_ticks: float, repeats: int = 1, prepare: bool = True
              ) -> tuple[list[str], dict[str, Any]]:
    """The real part for one model: tables (markdown) and the record. ``prepare``: the
    sessions of each mode share one prepared host source (`prepared_source`); else each
    ``serve`` builds its own (a cold host)."""
    from bench_link import TRACES

    tables, record = [], {}
    flashes = {"served": None, "served-blend": None, "motion": None}
    sources: dict[str, Any] = {}
    for mode in modes:
        if mode not in SESSION_MODES:
            continue
        if mode == "served-blend" and blend_case is None:
            print(f"skip served-blend of {path.name}: no --no-depth model "
                  "(--blend-cache DIR/VOLUME-SIZE.ecs)", flush=True)
            continue
        flashes[mode] = provisioned_flash(blend_path if mode == "served-blend" else path,
                                          work)
        if prepare:
            t0 = time.perf_counter()
            sources[mode] = prepared_source(blend_case if mode == "served-blend" else case,
                                            mode)
            print(f"  {mode}: host source prepared in {time.perf_counter() - t0:.1f} s",
                  flush=True)
    # warm the ray-caster once, so the first session does not pay for it alone
    case.renderer.render(*TRACES[traces[0]](1.0, 1.0)[0])
    for trace_name in traces:
        t0 = time.perf_counter()
        trace = TRACES[trace_name](seconds, fps)
        res: dict[int, dict[str, dict]] = {}
        for baud in bauds:
            res[baud] = {}
            for mode in modes:
                if mode.startswith("webp"):
                    ticks = int(mode[4:] or 1)
                    r = webp_stream(case, trace, fps, baud, ticks, rd)
                    res[baud][f"sim {mode}"] = r
                    print(f"  {trace_name} {baud} {mode}: fps {r['fps']:.1f} SSIM "
                          f"{r['ssim_object']:.4f} budget {r['budget']} B", flush=True)
                    continue
                if flashes.get(mode) is None:
                    continue
                blend = mode == "served-blend"
                for k in range(repeats):
                    r = real_session(blend_case if blend else case,
                                     blend_path if blend else path, flashes[mode], trace,
                                     fps, baud, mode, work, sample_delay_s=sample_ticks / 60.0,
                                     source=sources.get(mode))
                    label = f"real {mode}" + (f" #{k + 1}" if repeats > 1 else "")
                    res[baud][label] = r
                    print(f"  {trace_name} {baud} {label}: fps {r['fps']:.1f} SSIM "
                          f"{r['ssim_object']:.4f} B/frame {r['bytes_per_frame']:.0f} "
                          f"strides {r['strides']} view->frame {r['view_ms']:.0f} ms",
                          flush=True)
            if repeats > 1:  # the verdict on the mean of the repeats
                for mode in SESSION_MODES:
                    runs = [r for k, r in res[baud].items() if k.startswith(f"real {mode} #")]
                    if runs:
                        res[baud][f"real {mode}"] = {
                            **runs[0], **{key: float(np.nanmean([r[key] for r in runs]))
                                          for key in ("fps", "ssim_object", "flip_object",
                                                      "bytes_per_frame", "bytes_per_s",
                                                      "view_ms", "warp_ms")},
                            "warps_shown": sum(r["warps_shown"] for r in runs),
                            "moves": sum(r["moves"] for r in runs),
                            "packets": sum(r["packets"] for r in runs), "mean_of": len(runs),
                            "host_packets": sum(r["host_packets"] for r in runs),
                            "host_gap_s": max(r["host_gap_s"] for r in runs),
                            "shown": merge_shown([r["shown"] for r in runs])}
        sampled = ("" if sample_ticks == SAMPLE_DELAY_S * 60.0 else
                   f", sampled {sample_ticks:g} display ticks after the view")
        table = real_table(
            f"real session: {desc}, {trace_name} {seconds:g} s at {fps:g} ticks/s (serve + "
            f"RuntimeDevice over a paced mem:// line; host ray-casts on this CPU{sampled})",
            res)
        print(table + f"\n({time.perf_counter() - t0:.0f} s)\n", flush=True)
        tables.append(table)
        record[trace_name] = {str(k): v for k, v in res.items()}
    return tables, record


# --------------------------------------------------------------------------- at rest

#: The object SSIMs whose time from rest ``--parts rest`` reports (and the codecs' files).
REST_QUALITIES = (0.95, 0.99)
#: How long a resting view may take to reach its exact frame before it counts as missed.
REST_TIMEOUT_S = 60.0
#: Sessions whose serve fails (a new one takes the views left) before a baud gives up.
REST_RETRIES = 3
#: The resting device's frames (eigencast-device --max-frame): 16 KiB, the host's own
#: frames at most (serve's transport to a model whose score packets fit 16 KiB). With 64 KiB
#: frames serve plans layer strips up to a quarter second of a 921600-baud line (23040 B)
#: and fails sending the first one over 16 KiB (its planner reads the device's limit, not
#: its own link's).
REST_MAX_FRAME_BYTES = 16384


def _at(shown: list[tuple[float, np.ndarray, dict]], view: tuple[float, float],
        since: float) -> list[tuple[float, np.ndarray, dict]]:
    """The frames of ``view`` presented from ``since`` on."""
    return [(t, f, i) for t, f, i in shown
            if t >= since and (i.get("phi_deg"), i.get("theta_deg")) == view]


def rest_session(case: Any, model_path: Path, flash0: Path, views: list[tuple[float, float]],
                 baud: int, work: Path, source: Any = None,
                 timeout_s: float = REST_TIMEOUT_S) -> tuple[list[dict[str, Any]], str | None]:
    """One real serve session over a paced mem:// line in which the device rests on each of
    ``views`` in turn until its exact frame is on show (or ``timeout_s``): per view the
    times from setting the view to its first frame, to the corrected frame (the first layer
    when the plan skips the correction), to each of `REST_QUALITIES` (object SSIM of the
    frame on show against the ray-cast) and to the exact frame; when the host queued the
    view's first layer (its ray-cast and plan done) and the bytes it queued for the view.
    A session whose ``serve`` fails ends there: the views done so far and the error (else
    None)."""
    from bench_link import quality

    from device_runtime.orbit import canonical_view
    from host.link.layers import EncodedLayer
    from host.link.options import ServeOptions, ServeParts
    from host.link.serving import serve

    flash = work / f"flash-rest-{uuid.uuid4().hex[:8]}"
    shutil.copytree(flash0, flash)
    name = f"bench-rest-{uuid.uuid4().hex[:8]}"
    start = canonical_view(views[0][0] + 180.0, 0.0)  # rested on before the first view
    dev = DeviceThreads(flash, f"mem://{name}?end=b", baud, predict=True, view=start,
                        max_frame_bytes=REST_MAX_FRAME_BYTES)
    device = dev.device
    stop = threading.Event()
    out: dict[str, Any] = {}
    sent: list[tuple[float, bool, tuple[float, float], int]] = []  # (when, layer, view, B)

    def queued(enc: Any, view: tuple[float, float]) -> None:
        sent.append((time.monotonic(), isinstance(enc, EncodedLayer), tuple(view),
                     len(enc.packet)))

    def host() -> None:
        try:
            out["stats"] = serve(model_path, f"mem://{name}?end=a",
                                 ServeOptions(baud=baud, insecure=True, stats_every_s=0),
                                 ServeParts(stop=stop, log=lambda line: None, model=case.model,
                                            renderer=case.renderer, motion=source,
                                            on_frame=queued))
        except BaseException as exc:  # reported below
            out["error"] = exc

    def exact_of(view: tuple[float, float], since: float) -> bool:
        return any(i.get("exact") for _, _, i in _at(dev.shown, view, since))

    thread = threading.Thread(target=host, daemon=True)
    thread.start()
    runs = []
    try:
        if not wait_for(lambda: exact_of(start, 0.0) or "error" in out, timeout_s):
            raise RuntimeError(f"no exact frame of the first view {start} in {timeout_s:g} s")
        for view in views:
            if "error" in out:
                break
            view = canonical_view(*view)
            time.sleep(0.3)  # a hand that just let go of the previous view
            t_set = time.monotonic()
            device.set_view(*view)
            view = device.view
            done = wait_for(lambda v=view, t=t_set: exact_of(v, t) or "error" in out,
                            timeout_s)
            if "error" in out:  # serve died on this view: it counts for nothing
                break
            runs.append({"view": view, "t_set": t_set, "done": done})
    finally:
        stop.set()
        thread.join(30)
        dev.stop()
        shutil.rmtree(flash, ignore_errors=True)
    results = []
    for k, run in enumerate(runs):
        view, t_set = run["view"], run["t_set"]
        t_end = runs[k + 1]["t_set"] if k + 1 < len(runs) else math.inf
        frames = [(t, f, i) for t, f, i in _at(dev.shown, view, t_set) if t < t_end]
        rgb, mask = case.render(view)
        r: dict[str, Any] = {"view": view, "exact": run["done"],
                             **rest_milestones(frames, t_set,
                                               lambda f, rgb=rgb, mask=mask:
                                               quality(rgb, f, mask)[0])}
        mine = [(t, lay, b) for t, lay, v, b in sent if v == view and t_set <= t < t_end]
        r["host_ready_s"] = next((t - t_set for t, lay, _ in mine if lay), math.inf)
        r["complete_sent"] = complete_correction_sent(mine, t_set)
        r["bytes"] = sum(b for _, _, b in mine)
        results.append(r)
    error = out.get("error")
    return results, None if error is None else f"{type(error).__name__}: {error}"


def complete_correction_sent(queued: list[tuple[float, bool, int]], t_set: float) -> bool:
    """Whether the host sent a resting view its complete correction, from what it queued
    for the view (``(time, a layer, bytes)`` in order): a score packet right before the
    first strip (queued back to back, within 0.3 s), which is not the sparse correction of
    the view's first frame (the view's first packet, queued within 0.3 s of rest)."""
    first = next((k for k, (_, layer, _) in enumerate(queued) if layer), None)
    if not first or queued[first - 1][1] or queued[first][0] - queued[first - 1][0] > 0.3:
        return False
    return first >= 2 or queued[0][0] - t_set > 0.3


def rest_milestones(frames: list[tuple[float, np.ndarray, dict]], t_set: float,
                    score: Any) -> dict[str, Any]:
    """When a resting view's frames (``(time, frame, info)`` as presented, in order) reached
    each milestone, seconds after ``t_set``: ``first_s`` (any frame of it), ``corrected_s``
    (its corrected frame, or its first layer when that came first: the plan skipped the
    correction), ``ssim0.95_s`` / ``ssim0.99_s`` (the first frame on show, the own frame
    included, whose ``score`` reaches it; an exact frame scores 1), ``exact_s``; inf where
    never. Also ``corrected_ssim`` (the first refined frame's score), ``own_ssim``,
    ``correction_sent`` and ``layers_shown``."""
    r: dict[str, Any] = {"first_s": frames[0][0] - t_set if frames else math.inf}
    corrected = next((t for t, _, i in frames if i.get("corrected")), None)
    layer = next((t for t, _, i in frames if i.get("layer") is not None), None)
    first_layer = layer if layer is not None else math.inf
    r["corrected_s"] = (corrected if corrected is not None and corrected <= first_layer
                        else first_layer) - t_set
    r["correction_sent"] = corrected is not None
    r["exact_s"] = next((t - t_set for t, _, i in frames if i.get("exact")), math.inf)
    ssims = []  # (when, score, refined: the correction or a layer) per frame
    for t, f, i in frames:
        refined = bool(i.get("corrected") or i.get("layer") is not None)
        ssims.append((t, 1.0 if i.get("exact") else float(score(f)), refined))
    for q in REST_QUALITIES:  # whatever is on show: the own frame may reach it already
        r[f"ssim{q:g}_s"] = next((t - t_set for t, s, _ in ssims if s >= q), math.inf)
    r["corrected_ssim"] = next((s for _, s, refined in ssims if refined), math.nan)
    r["own_ssim"] = next((s for _, s, refined in ssims if not refined), math.nan)
    r["layers_shown"] = sum(i.get("layer") is not None for _, _, i in frames)
    return r


def codec_times(case: Any, view: tuple[float, float], baud: int,
                corrected_ssim: float) -> dict[str, float]:
    """Seconds the smallest WebP and AVIF file of the view's ray-cast reaching the corrected
    frame's object SSIM and each of `REST_QUALITIES` take on the line (one frame each; no
    host time: the codec is favoured), and its WebP lossless file (the exact frame); and
    ``raycast_s``: one full ray-cast of the view on this machine now (what a codec stream
    waits for before it can code the view)."""
    import io

    from bench_link import smallest_file, wire_bytes
    from PIL import Image

    rgb, mask = case.render(view)
    rate = baud / 10.0
    t0 = time.perf_counter()  # what a codec stream needs before it can code the view
    case.renderer.render(*view)
    out: dict[str, float] = {"raycast_s": time.perf_counter() - t0}
    ladders: dict[str, dict] = {"webp": {}, "avif": {}}
    targets = {"corrected": corrected_ssim, **{f"ssim{q:g}": q for q in REST_QUALITIES}}
    for label, target in targets.items():
        for codec in ("webp", "avif"):
            size = (smallest_file(rgb, mask, target, codec, ladders[codec])
                    if math.isfinite(target) else math.nan)
            out[f"{codec}_{label}_s"] = (wire_bytes(int(size)) / rate if math.isfinite(size)
                                         else math.nan)
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, "WEBP", lossless=True, exact=True)
    out["webp_lossless_s"] = wire_bytes(len(buf.getvalue())) / rate
    out["webp_lossless_bytes"] = len(buf.getvalue())
    return out


def rest_table(title: str, res: dict[int, list[dict]]) -> str:
    """Medians over the views per baud: ours against the codecs' files."""
    def med(rows: list[dict], key: str) -> str:
        vals = np.array([r[key] for r in rows], dtype=np.float64)
        if not vals.size:
            return "-"
        m = float(np.median(vals))  # (a missed view counts as infinitely late)
        return "missed" if not math.isfinite(m) else f"{m:.2f}"

    lines = [f"**{title}**", "",
             "| baud | views (exact, complete correction sent) | first frame s | corrected s "
             "(SSIM) | SSIM 0.95 s | SSIM 0.99 s | exact s | host ready s | after host ready: "
             "0.95 / exact s | bytes to exact | WebP / AVIF at the corrected SSIM s | "
             "WebP / AVIF 0.95 s | WebP / AVIF 0.99 s | WebP lossless s | a ray-cast s |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for baud, rows in res.items():
        if not rows:
            lines.append(f"| {baud} | 0 |" + " - |" * 13)
            continue
        rows = [{**r, "line0.95_s": r["ssim0.95_s"] - r["host_ready_s"],
                 "line_exact_s": r["exact_s"] - r["host_ready_s"]} for r in rows]
        n_exact = sum(r["exact"] for r in rows)
        n_corr = sum(r.get("complete_sent", False) for r in rows)
        corr_ssim = float(np.nanmedian([r["corrected_ssim"] for r in rows]))
        lines.append(
            f"| {baud} | {len(rows)} ({n_exact}, {n_corr}) | {med(rows, 'first_s')} | "
            f"{med(rows, 'corrected_s')} ({corr_ssim:.3f}) | {med(rows, 'ssim0.95_s')} | "
            f"{med(rows, 'ssim0.99_s')} | {med(rows, 'exact_s')} | {med(rows, 'host_ready_s')}"
            f" | {med(rows, 'line0.95_s')} / {med(rows, 'line_exact_s')}"
            f" | {float(np.median([r['bytes'] for r in rows])):.0f} | "
            f"{med(rows, 'webp_corrected_s')} / {med(rows, 'avif_corrected_s')} | "
            f"{med(rows, 'webp_ssim0.95_s')} / {med(rows, 'avif_ssim0.95_s')} | "
            f"{med(rows, 'webp_ssim0.99_s')} / {med(rows, 'avif_ssim0.99_s')} | "
            f"{med(rows, 'webp_lossless_s')} | {med(rows, 'raycast_s')} |")
    return "\n".join(lines)


def rest_part(case: Any, path: Path, desc: str, bauds: list[int], n_views: int,
              work: Path, seed: int = 11) -> tuple[list[str], dict[str, Any]]:
    """Resting sessions of one model at each baud (`rest_session`) against the codecs'
    files on the same line (`codec_times`): the table (markdown) and the record."""
    from host.render.camera import parse_view_set

    flash = provisioned_flash(path, work)
    t0 = time.perf_counter()
    source = prepared_source(case, "served")
    print(f"  rest: host source prepared in {time.perf_counter() - t0:.1f} s", flush=True)
    views = [(v.phi_deg, v.theta_deg) for v in
             parse_view_set(f"random:{n_views}:{seed}").views]
    res: dict[int, list[dict]] = {}
    errors: dict[int, list[str]] = {}
    for baud in bauds:
        t0 = time.perf_counter()
        rows: list[dict] = []
        while len(rows) < len(views) and len(errors.get(baud, [])) < REST_RETRIES:
            done, error = rest_session(case, path, flash, views[len(rows):], baud, work,
                                       source=source)
            rows += done
            if error is not None:  # a new session for the views left (the failed one skipped)
                errors.setdefault(baud, []).append(error)
                print(f"  serve failed after {len(rows)} views: {error}", flush=True)
                rows.append({"view": views[len(rows)], "failed": error})
        rows = [r for r in rows if "failed" not in r]
        for r in rows:
            r.update(codec_times(case, r["view"], baud, r["corrected_ssim"]))
        res[baud] = rows
        print(rest_table(f"{desc} at rest, {baud} baud", {baud: rows})
              + f"\n({time.perf_counter() - t0:.0f} s)", flush=True)
    table = rest_table(f"at rest: {desc}, {n_views} views random:{n_views}:{seed} (serve + "
                       "RuntimeDevice over a paced mem:// line, 16 KiB frames; medians; "
                       "codecs: one file's time on the line, no host time)", res)
    for baud, errs in errors.items():
        table += (f"\n\n{baud}: serve failed {len(errs)} time(s) (the view it failed on is "
                  f"left out, a new session took the rest): {errs[0]}")
    record: dict[str, Any] = {
        str(b): [{k: (list(v) if isinstance(v, tuple) else v) for k, v in r.items()}
                 for r in rows] for b, rows in res.items()}
    record["errors"] = {str(b): e for b, e in errors.items()}
    return [table], record
