"""Streams on an orbit: interpolated vs ray-cast (projected) scores vs WebP/JPEG frames.

    .venv/bin/python scripts/rd_stream.py MODEL.ecs -o OUT.json
        [--orbits steps:120:15,steps:120:42] [--factors 1,2,4,8] [--match-every 8]
        [--frames N]

For each orbit view the volume is ray-cast with the model's recorded settings (the truth;
object pixels: alpha >= `host.render.settings.OBJECT_ALPHA_MIN`), and two packet streams are
made exactly as ``eigencast serve`` sends them (`host.link.serving.FrameEncoder`: one key frame,
then deltas against the previous packet):

* ``interpolate``: the training views' scores interpolated at the view (``--scores
  interpolate``);
* ``render``: the scores of the ray-cast itself, fitted onto the device's eigenimages
  (`host.fit.model.HostModel.project`; ``--scores render``, and what ``refine`` sends once a
  view rests).

Each at score steps ``factor x`` the model's step. Every frame is decoded and reconstructed
as on the device and measured (object PSNR, SSIM, FLIP). On every ``--match-every``-th
view the smallest WebP and JPEG file of the ray-cast reaching the frame's object SSIM *and*
FLIP is found (`scripts/rdp_common.smallest_codec_file`), as in
docs/rate-distortion-packets.md. Also recorded: WebP's own curve on those views (quality
1..95) and the ray-cast time per view.

Produces: docs/rate-distortion.md, section 4 "Streaming the true view's scores"
(through rd_stream_plot.py).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from rdp_common import Timer, quality, save_json, smallest_codec_file

from host.evaluate import encode_image
from host.fit.model import HostModel
from host.link.serving import FrameEncoder, open_true_view_scores
from host.render.settings import OBJECT_ALPHA_MIN
from protocol.scores import ScoreDecoder

WEBP_CURVE = (1, 5, 10, 20, 30, 50, 70, 80, 90, 95)


def orbit_views(spec: str) -> list[tuple[float, float]]:
    kind, n, theta = spec.split(":")[:3]
    if kind != "steps":
        raise SystemExit(f"{spec}: only steps:N:THETA orbits")
    n = int(n)
    return [(float(np.float32(360.0 * i / n)), float(np.float32(theta))) for i in range(n)]


def with_step(model: HostModel, factor: float) -> HostModel:
    if factor == 1:
        return model
    return model.truncated(np.asarray(model.image.n_components), score_step=model.score_step
                           * factor)


def save_figure(path: str, truth: np.ndarray, mask: np.ndarray, shown: dict, spec: str,
                view: tuple[float, float]) -> None:
    """Truth | interpolated | ray-cast scores | WebP of the ray-cast at the render frame's
    quality, each titled with its bytes and object SSIM / FLIP."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cell = shown["render"][1]
    size, qual, m = smallest_codec_file(truth, mask, "webp", ssim=cell["ssim"], flip=cell["flip"])
    webp = encode_image(truth, "webp", qual).decode()
    panels = [("ray-cast (truth)", truth, ""),
              ("interpolated scores", shown["interpolate"][0],
               f"{shown['interpolate'][1]['bytes']} B"),
              ("ray-cast view's scores", shown["render"][0], f"{cell['bytes']} B"),
              (f"WebP q{qual}, equal quality", webp, f"{size} B")]
    fig, axes = plt.subplots(1, 4, figsize=(16, 4.6))
    for ax, (title, img, size_text) in zip(axes, panels, strict=True):
        ax.imshow(img)
        ax.set_axis_off()
        q = (shown["interpolate"][1] if title.startswith("interp") else cell
             if title.startswith("ray-cast view") else m if title.startswith("WebP") else None)
        sub = f"\n{size_text}, SSIM {q['ssim']:.3f}, FLIP {q['flip']:.3f}" if q else ""
        ax.set_title(title + sub, fontsize=10)
    fig.suptitle(f"{spec}, view phi {view[0]:.1f}, theta {view[1]:.1f} (object-pixel metrics; "
                 "packet bytes as sent in the key+delta stream)", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.94))
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("-o", "--output", required=True)
    ap.add_argument("--orbits", default="steps:120:15,steps:120:42")
    ap.add_argument("--factors", default="1,2,4,8")
    ap.add_argument("--match-every", type=int, default=8)
    ap.add_argument("--frames", type=int, default=None, help="first N views of each orbit")
    ap.add_argument("--figure", default=None, metavar="PNG",
                    help="a side-by-side figure of one view (truth, interpolated, ray-cast "
                    "scores, equal-quality WebP) at the default step")
    ap.add_argument("--figure-view", type=int, default=8, help="orbit view index of --figure")
    args = ap.parse_args(argv)
    t = Timer()
    base = HostModel.load(args.model)
    factors = [float(f) for f in args.factors.split(",")]
    models = {f: with_step(base, f) for f in factors}
    true_views = open_true_view_scores(base)
    out: dict = {"model": str(args.model), "image_shape": list(base.image.image_shape),
                 "K": int(base.image.n_coefficients), "step": base.score_step,
                 "factors": factors, "orbits": {}}
    for spec in args.orbits.split(","):
        views = orbit_views(spec)[: args.frames]
        encoders = {(mode, f): FrameEncoder(models[f], first_frame=1)
                    for mode in ("interpolate", "render") for f in factors}
        decoders = {k: ScoreDecoder(base.image.n_coefficients, base.digest,
                                    n_components=base.image.n_components) for k in encoders}
        rows = []
        render_s = []
        shown: dict = {}
        figure_done = bool(out["orbits"])  # one figure, from the first orbit
        for i, view in enumerate(views):
            t0 = time.perf_counter()
            truth, alpha = true_views.renderer.render(*view)
            y_true = base.project(truth)
            render_s.append(time.perf_counter() - t0)
            mask = alpha >= OBJECT_ALPHA_MIN
            match = i % args.match_every == 0
            row: dict = {"view": list(view), "object_fraction": float(mask.mean())}
            for (mode, f), enc in encoders.items():
                key = i == 0
                packet = enc.encode(view, key=key, scores=y_true if mode == "render" else None)
                key_packet = FrameEncoder(models[f], first_frame=1).encode(
                    view, key=True, scores=y_true if mode == "render" else None)
                # as on the device: deltas decode against this stream's previous packet
                frame = base.reconstruct(decoders[mode, f].decode(packet.packet).y)
                q = quality(truth, frame, mask, flip=True)
                cell = {"bytes": len(packet.packet), "key_bytes": len(key_packet.packet), **q}
                if match:
                    for codec in ("webp", "jpeg"):
                        size, qual, _m = smallest_codec_file(truth, mask, codec, ssim=q["ssim"],
                                                             flip=q["flip"])
                        cell[f"{codec}_equal_bytes"] = size
                        cell[f"{codec}_equal_quality"] = qual
                row[f"{mode}@{f:g}"] = cell
                if args.figure and i == args.figure_view and f == factors[0]:
                    shown[mode] = (frame, cell)
            if args.figure and i == args.figure_view and not figure_done:
                figure_done = True
                save_figure(args.figure, truth, mask, shown, spec, view)
            if match:
                row["webp_curve"] = []
                for qv in WEBP_CURVE:
                    coded = encode_image(truth, "webp", qv)
                    row["webp_curve"].append({"quality": qv, "bytes": coded.size_bytes,
                                              **quality(truth, coded.decode(), mask, flip=True)})
            rows.append(row)
            if i % 10 == 0:
                r = row[f"render@{factors[0]:g}"]
                p = row[f"interpolate@{factors[0]:g}"]
                t.say(f"{spec} {i + 1}/{len(views)}: interpolate {p['bytes']} B ssim "
                      f"{p['ssim']:.3f}; render {r['bytes']} B ssim {r['ssim']:.3f}")
        summary = {}
        for mode in ("interpolate", "render"):
            for f in factors:
                cells = [r[f"{mode}@{f:g}"] for r in rows]
                matched = [c for c in cells if "webp_equal_bytes" in c]
                s = {k: float(np.mean([c[k] for c in cells]))
                     for k in ("bytes", "key_bytes", "psnr", "ssim", "flip")}
                for codec in ("webp", "jpeg"):
                    s[f"{codec}_equal_bytes"] = float(np.mean(
                        [c[f"{codec}_equal_bytes"] for c in matched]))
                    # packet bytes on the same matched views, for a like-for-like ratio
                    s[f"bytes_vs_{codec}"] = float(np.mean([c["bytes"] for c in matched])
                                                   / s[f"{codec}_equal_bytes"])
                summary[f"{mode}@{f:g}"] = s
        curve = {}
        for qv in WEBP_CURVE:
            pts = [p for r in rows if "webp_curve" in r for p in r["webp_curve"]
                   if p["quality"] == qv]
            curve[qv] = {k: float(np.mean([p[k] for p in pts]))
                         for k in ("bytes", "psnr", "ssim", "flip")}
        out["orbits"][spec] = {"views": len(views), "summary": summary, "webp_curve": curve,
                               "render_seconds_mean": float(np.mean(render_s)), "rows": rows}
        for name, s in summary.items():
            t.say(f"{spec} {name}: {s['bytes']:.0f} B/frame (key {s['key_bytes']:.0f}), ssim "
                  f"{s['ssim']:.4f} flip {s['flip']:.4f}; webp equal {s['webp_equal_bytes']:.0f}"
                  f" B ({s['bytes_vs_webp']:.2f}x), jpeg equal {s['jpeg_equal_bytes']:.0f} B")
        save_json(args.output, out)
    save_json(args.output, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

