"""Section x of ``bench_device.py``: what a correction of the device's own frame costs it.

On the served path (issue 23) a device shows its own frame ``S`` of every new view (the depth
warp, or the blend of its predicted scores) and the host sends a version-3 correction of
that frame; the device shows ``Reconstructor.correct(delta, S)``. This section times that
call against the blend (``Reconstructor.update(y)`` of a new view's predicted scores: every
cell whose scores changed recomputed), on the same reconstructor, interleaved view by view
in one run, so the ratio holds under any load.

The deltas are the ones the host really sends: per view of a 3 degree/frame drag the host
(`host.fit.motion.MotionScores` with the device's own frames, `device_runtime.prediction.
OwnFrames`) makes

* a *moving* correction: a sparse ray-cast at ``stride`` (the default coarse renderer),
  its residual recovered with the learned prior, RD-quantized at the moving step; and
* the *complete* correction at rest: every pixel ray-cast exactly, ``project(truth) -
  project(S)`` at the model's own step (`CorrectionEncoder`, ``fine=True``),

each coded as the version-3 packet ``serve`` sends and decoded as the device decodes it
(`ScoreDecoder`): ``delta`` is the packet's ``y``. A correction whose coefficients all
quantize to zero is not sent, so it costs the device nothing and is left out (counted).

Timed per view (median over views, wall and thread CPU time, one thread):

* ``blend``: ``update(predictor(view))`` after a frame of another view (every cell changes
  but those whose scores are all zero in both);
* ``moving``: ``correct(moving delta, S)`` (the first correction of a frame passes it);
* ``rest``: ``correct(complete delta)`` of the frame already held (how the device applies
  the correction of a view whose moving correction it showed: ``synth=None``);
* ``rest + frame``: ``correct(complete delta, S)`` (a view whose first correction is the
  complete one);
* ``rest unsmoothed``: ``rest`` with the cell-border smoothing off (what it costs).

Target (issue 23): a correction costs at most one blend. Run on one core::

    OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 taskset -c 0 .venv/bin/python \\
        benchmarks/bench_device.py --sections x --correction-images A.ecs,B.ecs

(images fitted with ``--standalone``; with ``--depth`` the frames are warps).
"""

from __future__ import annotations

import os
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

MODES = ("blend", "moving", "rest", "rest + frame", "rest unsmoothed")
#: The modes the target holds for (the last is the rest correction with the cell-border
#: smoothing off, `Reconstructor.seam_strength` 0: what the smoothing costs, in the same run).
TARGET_MODES = MODES[1:4]


def drag_views(n: int, *, start: float = 17.0, step: float = 3.0,
               theta: float = 15.0) -> list[tuple[float, float]]:
    """``n`` canonical views of a drag ``step`` degrees of phi apart at ``theta``."""
    from device_runtime.orbit import canonical_view

    return [canonical_view(start + step * i, theta) for i in range(n)]


def host_corrections(model: Any, views: list[tuple[float, float]], stride: int
                     ) -> list[dict[str, Any]]:
    """Per view: the device's own frame and the decoded deltas of its moving (``stride``)
    and complete corrections, as ``serve`` sends them (None: nothing worth sending)."""
    from device_runtime.prediction import OwnFrames
    from host.fit.motion import MotionScores
    from host.link.correction import CorrectionEncoder
    from host.link.true_views import open_true_view_scores
    from protocol.scores import ScoreDecoder

    renderer = open_true_view_scores(model).renderer
    own = OwnFrames(model.image)
    moving = MotionScores(model, renderer, own=own, strides=(stride,), budget_s=3600.0)
    rest = MotionScores(model, renderer, own=own, strides=(1,), budget_s=3600.0, coarse=1.0)
    encoder = CorrectionEncoder(model)
    decoder = ScoreDecoder(model.image.n_coefficients, model.digest,
                           n_components=model.image.n_components)
    out = []
    for view in views:
        synth = own.frame(*view)
        row: dict[str, Any] = {"view": view, "synth": synth}
        for name, source in (("moving", moving), ("rest", rest)):
            step = source.frame(view)
            packet = encoder.encode(view, scores=step.scores, fine=step.complete,
                                    weights=step.weights)
            row[name] = None if packet is None else decoder.decode(packet.packet).y
            row[f"{name}_bytes"] = 0 if packet is None else len(packet.packet)
        out.append(row)
    return out


def _changed_cells(image: Any, delta: np.ndarray) -> int:
    offsets = np.concatenate([[0], np.cumsum(np.asarray(image.n_components, dtype=np.int64))])
    nz = np.concatenate([[0], np.cumsum(delta != 0)])
    return int(np.count_nonzero(nz[offsets[1:]] - nz[offsets[:-1]]))


def section_correction(path: Path, n_views: int, stride: int, repeat: int = 3) -> dict:
    """(x) one image: correction vs blend on one reconstructor, interleaved per view."""
    from device_runtime.prediction import Predictor
    from device_runtime.reconstruct import SEAM_STRENGTH, Reconstructor
    from host.fit.model import HostModel

    model = HostModel.load(path)
    image = model.image
    t0 = time.perf_counter()
    views = drag_views(n_views)
    rows = host_corrections(model, views, stride)
    setup_s = time.perf_counter() - t0
    predictor = Predictor(image)
    rec = Reconstructor.from_image(image, threads=1)
    other = predictor(*drag_views(1, start=200.0)[0])  # a far view: the blend changes most
    wall: dict[str, list[float]] = {k: [] for k in MODES}
    cpu: dict[str, list[float]] = {k: [] for k in MODES}

    def timed(name: str, call: Any, held: np.ndarray | None = None) -> None:
        """Time ``call`` after a frame of another view (``held``: after the reconstructor
        took this frame for a correction, as a moving correction leaves it)."""
        for _ in range(repeat):
            rec.update(other)  # the previous frame is another view's blend
            if held is not None:
                rec.correct(np.zeros(image.n_coefficients, np.float32), held)
            c0, t0 = time.thread_time(), time.perf_counter()
            call()
            t1, c1 = time.perf_counter(), time.thread_time()
            wall[name].append(t1 - t0)
            cpu[name].append(c1 - c0)

    skipped = {"moving": 0, "rest": 0}
    for row in rows:
        y = predictor(*row["view"])
        timed("blend", lambda y=y: rec.update(y))
        if row["moving"] is not None:
            timed("moving", lambda row=row: rec.correct(row["moving"], row["synth"]))
        else:
            skipped["moving"] += 1
        if row["rest"] is not None:
            timed("rest", lambda row=row: rec.correct(row["rest"]), held=row["synth"])
            timed("rest + frame", lambda row=row: rec.correct(row["rest"], row["synth"]))
            rec.seam_strength = 0.0
            timed("rest unsmoothed", lambda row=row: rec.correct(row["rest"]),
                  held=row["synth"])
            rec.seam_strength = SEAM_STRENGTH
        else:
            skipped["rest"] += 1
    rec.close()
    n_cells = int(np.count_nonzero(np.asarray(image.n_components)))

    def cells(name: str) -> float:
        ds = [r[name] for r in rows if r[name] is not None]
        return float(np.mean([_changed_cells(image, d) for d in ds]) / n_cells) if ds else 0.0

    def med(xs: list[float]) -> float:
        return 1e3 * statistics.median(xs) if xs else float("nan")

    blend_ms, blend_cpu = med(wall["blend"]), med(cpu["blend"])
    out: dict[str, Any] = {
        "image": path.name, "size": int(image.image_shape[0]), "views": n_views,
        "stride": stride, "warp": image.synthesis is not None,
        "K": int(image.n_coefficients), "setup_s": setup_s, "skipped": skipped,
        "affinity": sorted(os.sched_getaffinity(0)), "load": os.getloadavg()[0],
        "cells_moving": cells("moving"), "cells_rest": cells("rest"),
        "bytes_moving": float(np.mean([r["moving_bytes"] for r in rows if r["moving_bytes"]]
                                      or [0])),
        "bytes_rest": float(np.mean([r["rest_bytes"] for r in rows if r["rest_bytes"]] or [0])),
    }
    for name in MODES:
        out[f"{name}_ms"], out[f"{name}_cpu_ms"] = med(wall[name]), med(cpu[name])
        out[f"{name}_ratio"] = med(wall[name]) / blend_ms
        out[f"{name}_cpu_ratio"] = med(cpu[name]) / blend_cpu
    return out


def print_correction(r: dict) -> None:
    parts = [f"blend {r['blend_ms']:.2f} ms (CPU {r['blend_cpu_ms']:.2f})"]
    for name in MODES[1:]:
        parts.append(f"{name} {r[f'{name}_ms']:.2f} ms = {r[f'{name}_ratio']:.2f}x "
                     f"(CPU {r[f'{name}_cpu_ms']:.2f} = {r[f'{name}_cpu_ratio']:.2f}x)")
    worst = max(r[f"{name}_cpu_ratio"] for name in TARGET_MODES)
    ok = "within" if worst <= 1.0 else "OVER"
    print(f"  {r['image']} ({r['size']} px, K {r['K']}, "
          f"{'warp' if r['warp'] else 'blend'} frames): " + "; ".join(parts)
          + f"; {ok} one blend (worst CPU ratio {worst:.2f}). Corrections touch "
          f"{100 * r['cells_moving']:.0f} % (moving, stride {r['stride']}, "
          f"{r['bytes_moving']:.0f} B) / {100 * r['cells_rest']:.0f} % (rest, "
          f"{r['bytes_rest']:.0f} B) of the cells; not sent (all zero): {r['skipped']}; "
          f"host setup {r['setup_s']:.0f} s; CPUs {r['affinity']}, load {r['load']:.1f}",
          flush=True)
