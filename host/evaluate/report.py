"""HTML report of an `host.evaluate.Evaluation`: a Table-1-style table, plots and images.

`write_report(evaluation, folder)` writes into ``folder``:

* ``index.html`` -- the model laid out like the paper's Table 1, the per-method means (whole
  image and object pixels), the int8 loss recorded by ``fit``, the time spent per phase;
* ``rd.png`` -- rate-distortion: SSIM and FLIP against bytes per view for the PCA model at
  several settings (lower thresholds / fewer components, coarser score steps) and JPEG and
  WebP at several qualities, with the model's own point and the equal-bytes codec means marked;
* ``per_view.png`` -- SSIM and FLIP of every view against its elevation;
* ``rest.png`` -- for a model with the standalone table, given ``serve``'s planner: object
  SSIM and FLIP against cumulative bytes of every step of the resting views (the own frame,
  the correction, each layer, the exact frame) beside the JPEG, WebP and AVIF curves and the
  ray-cast's PNG and WebP lossless files;
* ``views/view_NN.png`` -- side by side: for a model with the standalone table the device's
  own frame | that frame served at rest (corrected) | each refinement layer and the exact
  frame (given a planner) | the ray-cast, then the other methods' frames (served while
  moving, interpolated and ray-cast scores, equal-bytes codecs, ...) and FLIP error maps
  (magma, 0..1);
* ``summary.json`` -- `Evaluation.summary`.

Plots use matplotlib's Agg backend (no display needed).
"""

from __future__ import annotations

import html
import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from host.evaluate.engine import METHODS

__all__ = ["compose_side_by_side", "write_report"]

#: The resting chain's stages in the report (colour, marker, name).
_REST_KINDS = {"correction": ("#543005", "o", "own frame + complete correction"),
               "layer": ("#1b7837", "s", "refinement layer"),
               "exact": ("#000000", "*", "exact frame (the ray-cast)")}

#: Side-by-side panels smaller than this are zoomed (nearest neighbour) to at least it.
MIN_PANEL_HEIGHT = 256
_COLORS = {"projection": "#000000", "pca": "#1b7837", "jpeg": "#b2182b", "webp": "#2166ac",
           "nearest": "#8c6bb1", "webp_db": "#e08214", "pca_render": "#35978f",
           "pca_motion": "#7fbc41", "avif": "#c51b7d", "pca_predict": "#543005",
           "pca_warp": "#01665e"}
_NAMES = {"projection": "PCA, true view's own scores (oracle)", "pca": "PCA (device)",
          "pca_render": "PCA, ray-cast scores (key packets)",
          "pca_motion": "PCA, served while moving (sparse ray-cast)",
          "pca_predict": "PCA, served at rest (own frame + complete correction)",
          "jpeg": "JPEG, equal bytes", "webp": "WebP, equal bytes",
          "avif": "AVIF, equal bytes",
          "nearest": "nearest training view",
          "webp_db": "WebP image database on the device",
          "pca_warp": "PCA, the device's own frame (depth warp or score blend)"}


def _fmt(value: Any, digits: int = 3) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        if math.isnan(value):
            return "–"
        if math.isinf(value):
            return "∞"
        return f"{value:.{digits}f}"
    return html.escape(str(value))


def _bytes(n: Any) -> str:
    if n is None or (isinstance(n, float) and not math.isfinite(n)):
        return "–"
    n = float(n)
    if n >= 1e6:
        return f"{n / 1e6:.2f} MB"
    if n >= 1e4:
        return f"{n / 1e3:.1f} kB"
    return f"{n:,.0f} B"


def _colormap(values: np.ndarray) -> np.ndarray:
    """Magma-coloured uint8 (h, w, 3) of values in [0, 1]."""
    from matplotlib import colormaps

    rgba = colormaps["magma"](np.clip(values, 0.0, 1.0))
    return (rgba[..., :3] * 255.0 + 0.5).astype(np.uint8)


def _font(size: int) -> Any:
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1
        return ImageFont.load_default()


def compose_side_by_side(
    panels: list[tuple[str, np.ndarray]], *, gap: int = 6, label_height: int = 0
) -> np.ndarray:
    """Place labelled images side by side.

    Parameters
    ----------
    panels : list of (label, image)
        Images uint8 (h, w, 3) of equal height.
    gap : int
        Pixels between panels (white).
    label_height : int
        Height of the caption strip above the images (0: about 5 % of the height, >= 18).

    Returns
    -------
    ndarray of shape (label_height + h, total_width, 3), uint8
    """
    from PIL import Image, ImageDraw

    h = panels[0][1].shape[0]
    zoom = max(1, -(-MIN_PANEL_HEIGHT // h))  # small images: nearest-neighbour zoom
    images = [np.repeat(np.repeat(np.ascontiguousarray(p), zoom, 0), zoom, 1) for _, p in panels]
    h *= zoom
    lines = max(len(label.split("\n")) for label, _ in panels)
    line_height = max(14, min(26, images[0].shape[1] // 22))
    label_height = label_height or line_height * lines + 8
    width = sum(p.shape[1] for p in images) + gap * (len(panels) - 1)
    canvas = Image.new("RGB", (width, h + label_height), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    font = _font(int(line_height * 0.8))
    x = 0
    for (label, _), image in zip(panels, images):
        canvas.paste(Image.fromarray(image), (x, label_height))
        for j, text in enumerate(label.split("\n")):
            draw.text((x + 4, 4 + j * line_height), text, fill=(20, 20, 20), font=font)
        x += image.shape[1] + gap
    return np.asarray(canvas)


def _save_png(path: Path, image: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(image).save(path, format="PNG", optimize=True)


def _rd_plot(evaluation: Any, path: Path) -> None:
    import matplotlib.pyplot as plt

    fig = _rd_figure(evaluation)
    fig.savefig(path)
    plt.close(fig)


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _rd_figure(evaluation: Any) -> Any:
    """The rate-distortion figure (SSIM and FLIP against bytes per view); its legend sits
    below both plots, clear of their axis titles (constrained layout, "outside")."""
    plt = _pyplot()
    summary = evaluation.summary()
    fig, axes = plt.subplots(1, 2, figsize=(11, 6.0), dpi=110, layout="constrained")
    for ax, metric, label in ((axes[0], "ssim", "SSIM (higher is better)"),
                              (axes[1], "flip", "FLIP (lower is better)")):
        for kind, marker in (("pca", "o"), ("jpeg", "s"), ("webp", "^"), ("avif", "v")):
            pts = [p for p in evaluation.rd if p["kind"] == kind and p["label"].startswith(
                ("T=", "k=", "q="))]
            pts.sort(key=lambda p: p["bytes_per_view"])
            if pts:
                ax.plot([p["bytes_per_view"] for p in pts], [p[metric] for p in pts],
                        marker=marker, color=_COLORS[kind], label=_NAMES[kind].split(",")[0],
                        linewidth=1.5, markersize=5)
                if kind == "pca":  # alternate sides so that close points stay legible
                    for i, p in enumerate(pts):
                        ax.annotate(p["label"], (p["bytes_per_view"], p[metric]),
                                    textcoords="offset points",
                                    xytext=(4, -11) if i % 2 == 0 else (-4, -11),
                                    ha="left" if i % 2 == 0 else "right", fontsize=7,
                                    color=_COLORS[kind])
        steps = [p for p in evaluation.rd if p["kind"] == "pca" and p["label"].startswith("step")]
        if steps:
            ax.plot([p["bytes_per_view"] for p in steps], [p[metric] for p in steps], "x",
                    color=_COLORS["pca"], label="PCA, score step x2 x4 ...", markersize=7)
            for p in steps:
                ax.annotate(p["label"].replace("step ", ""), (p["bytes_per_view"], p[metric]),
                            textcoords="offset points", xytext=(0, 6), ha="center",
                            fontsize=7, color=_COLORS["pca"])
        oracle = [p for p in evaluation.rd if p["kind"] == "projection"]
        if oracle:
            ax.plot([p["bytes_per_view"] for p in oracle], [p[metric] for p in oracle], "P",
                    color="black", markerfacecolor="none", markersize=9,
                    label="PCA, true views' own scores (oracle)")
        own = summary.get("pca") or {}
        if own:
            ax.plot([own["bytes_per_view"]], [own[metric]], "*", color="black", markersize=13,
                    label="this model (all views)", zorder=5)
        rendered = summary.get("pca_render") or {}
        if rendered:
            ax.plot([rendered["bytes_per_view"]], [rendered[metric]], "*",
                    color=_COLORS["pca_render"], markersize=13, zorder=5,
                    label="this model, ray-cast scores (all views)")
        moving = summary.get("pca_motion") or {}
        if moving and moving["bytes_per_view"]:
            ax.plot([moving["bytes_per_view"]], [moving[metric]], "*",
                    color=_COLORS["pca_motion"], markersize=13, zorder=5,
                    label="this model, served while moving (streamed, all views)")
        corrected = summary.get("pca_predict") or {}
        if corrected and corrected["bytes_per_view"]:
            ax.plot([corrected["bytes_per_view"]], [corrected[metric]], "*",
                    color=_COLORS["pca_predict"], markersize=13, zorder=5,
                    label="this model, served at rest: own frame + correction (all views)")
        own_frame = summary.get("pca_warp") or {}
        if own_frame and own_frame.get(metric) is not None:
            ax.axhline(own_frame[metric], color=_COLORS["pca_warp"], linestyle=":", linewidth=1.4,
                       label="the device's own frame (0 B/frame)")
        db = summary.get("webp_db") or {}
        if db and db.get(metric) is not None:
            ax.axhline(db[metric], color=_COLORS["webp_db"], linestyle="--", linewidth=1.2,
                       label=f"WebP database q{db['quality']:.0f} on the device (0 B/frame, "
                             f"{_bytes(db.get('storage_bytes'))} stored)")
        for codec in ("jpeg", "webp", "avif"):
            c = summary.get(codec) or {}
            if c:
                ax.plot([c["bytes_per_view"]], [c[metric]], "D", color=_COLORS[codec],
                        markerfacecolor="white", markersize=8, zorder=5,
                        label=f"{codec.upper()} at equal bytes (all views)")
        ax.set_xscale("log")
        ax.set_xlabel("bytes per view")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=8, loc="outside lower center", ncol=3, frameon=False)
    n = evaluation.info.get("rd_views", 0)
    fig.suptitle(f"Rate-distortion (sweep over {n} views; markers at equal bytes over all views)",
                 fontsize=10)
    return fig


def _rest_plot(evaluation: Any, path: Path) -> None:
    import matplotlib.pyplot as plt

    fig = _rest_figure(evaluation)
    fig.savefig(path)
    plt.close(fig)


def _rest_figure(evaluation: Any) -> Any:
    """Object SSIM and FLIP against cumulative bytes of every resting view's steps (a thin
    line per view from its first step sent to its exact frame, the medians marked), beside
    the codecs' curves of the rate-distortion sweep, the ray-cast's PNG and WebP lossless
    files and the own frame (0 bytes: a line)."""
    from matplotlib.ticker import NullFormatter

    plt = _pyplot()
    summary = evaluation.summary()
    rest = summary.get("rest") or {}
    recs = [v["rest"] for v in evaluation.views if v.get("rest")]
    fig, axes = plt.subplots(1, 2, figsize=(11, 6.0), dpi=110, layout="constrained")
    for ax, metric, label, perfect in ((axes[0], "ssim_object", "object SSIM (higher is better)",
                                        1.0),
                                       (axes[1], "flip", "FLIP, whole frame (lower is better)",
                                        0.0)):
        for r in recs:
            sent = [s for s in r["steps"] if s["kind"] != "own"]
            ax.plot([s["bytes"] for s in sent], [s[metric] for s in sent], color="#999999",
                    linewidth=0.6, alpha=0.5, zorder=1)
        for kind, (color, marker, name) in _REST_KINDS.items():
            pts = [s for r in recs for s in r["steps"] if s["kind"] == kind]
            if pts:
                ax.scatter([s["bytes"] for s in pts], [s[metric] for s in pts], s=14,
                           color=color, marker=marker, alpha=0.55, linewidths=0, zorder=3,
                           label=f"{name} (each view)")
        for stage, row in (rest.get("stages") or {}).items():
            if stage == "own" or row.get("bytes") is None or row.get(metric) is None:
                continue
            kind = "layer" if stage.startswith("layer") else stage
            ax.plot([row["bytes"]], [row[metric]], _REST_KINDS[kind][1], color="white",
                    markeredgecolor=_REST_KINDS[kind][0], markersize=11, zorder=5,
                    label=None)
        for codec, marker in (("jpeg", "s"), ("webp", "^"), ("avif", "v")):
            pts = sorted((p for p in evaluation.rd if p["kind"] == codec),
                         key=lambda p: p["bytes_per_view"])
            if pts and pts[0].get(metric) is not None:
                ax.plot([p["bytes_per_view"] for p in pts], [p[metric] for p in pts],
                        marker=marker, color=_COLORS[codec], linewidth=1.2, markersize=4,
                        label=f"{codec.upper() if codec != 'webp' else 'WebP'} of the ray-cast "
                              "(mean over the sweep's views)")
        exact = (rest.get("stages") or {}).get("exact") or {}
        for key, marker, name in (("png_bytes", "P", "PNG (optimized)"),
                                  ("webp_lossless_bytes", "X", "WebP lossless")):
            if exact.get(key):
                ax.plot([exact[key]], [perfect], marker, color="#666666", markersize=10,
                        zorder=4, label=f"{name} of the ray-cast (median)")
        corrected = summary.get("pca_predict") or {}
        if corrected.get("bytes_per_view") and corrected.get(metric) is not None:
            ax.plot([corrected["bytes_per_view"]], [corrected[metric]], "D",
                    color=_COLORS["pca_predict"], markerfacecolor="white", markersize=8,
                    zorder=5, label="own frame + complete correction, sent or not (mean)")
        own = (rest.get("stages") or {}).get("own") or {}
        if own.get(metric) is not None:
            ax.axhline(own[metric], color=_COLORS["pca_warp"], linestyle=":", linewidth=1.4,
                       label="the device's own frame (0 B, median)")
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(NullFormatter())  # (minor labels collide)
        ax.set_xlabel("bytes sent for the view (cumulative)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=8, loc="outside lower center", ncol=3, frameon=False)
    fig.suptitle(f"At rest: quality against bytes, {len(recs)} views (large open markers: "
                 "medians of each step)", fontsize=10)
    return fig


def _per_view_plot(evaluation: Any, path: Path) -> None:
    import matplotlib.pyplot as plt

    fig = _per_view_figure(evaluation)
    fig.savefig(path)
    plt.close(fig)


def _per_view_figure(evaluation: Any) -> Any:
    """Per-view SSIM and FLIP against elevation, one colour per method; the legend sits
    below both plots, off the data."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6), dpi=110, layout="constrained")
    theta = np.array([v["theta_deg"] for v in evaluation.views])
    for ax, metric, label in ((axes[0], "ssim", "SSIM"), (axes[1], "flip", "FLIP")):
        # dodge the methods sideways so that views at equal elevations stay visible
        for dodge, method in zip((-3.6, -2.8, -2.0, -1.2, -0.4, 0.4, 1.2, 2.0, 2.8, 3.6),
                                 ("nearest", "jpeg", "webp", "avif", "webp_db", "pca",
                                  "pca_motion", "pca_render", "pca_predict", "pca_warp")):
            if evaluation.views and method in evaluation.views[0]:
                vals = np.array([v[method][metric] for v in evaluation.views], dtype=float)
                ax.scatter(theta + dodge, vals, s=10, color=_COLORS[method],
                           label=_NAMES[method], alpha=0.7, linewidths=0)
        ax.set_xlabel("elevation theta (degrees)")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, fontsize=7, loc="outside lower center", ncol=3,
                   frameon=False, markerscale=1.5)
    fig.suptitle("Per-view quality against elevation", fontsize=10)
    return fig


def _panel(sample: dict, method: str, title: str) -> tuple[str, np.ndarray] | None:
    rec = sample["record"].get(method)
    if sample.get(method) is None or rec is None:
        return None
    return (f"{title}, {rec['bytes_per_view']} B\nSSIM {rec['ssim']:.3f}  "
            f"FLIP {rec['flip']:.3f}", sample[method])


def _rest_panels(sample: dict) -> list[tuple[str, np.ndarray]]:
    """The resting chain's layers and exact frame, each with the bytes sent so far."""
    rest = sample["record"].get("rest")
    frames = sample.get("rest_frames")
    if not rest or frames is None:
        return []
    panels, n = [], 0
    for step, frame in zip(rest["steps"], frames):
        if step["kind"] == "layer":
            n += 1
            what = "residual" if step["residual"] else "ray-cast"
            panels.append((f"layer {n} ({what}), {step['bytes']} B in all\n"
                           f"SSIM {step['ssim']:.3f} (obj. {step['ssim_object']:.3f})  "
                           f"FLIP {step['flip']:.3f}", frame))
        elif step["kind"] == "exact":
            wll = step.get("webp_lossless_bytes")
            ratio = f"  {step['bytes'] / wll:.2f}x WebP lossless" if wll else ""
            panels.append((f"exact at rest, {step['bytes']} B in all\n"
                           f"(= the ray-cast){ratio}", frame))
    return panels


def _sample_figure(sample: dict) -> np.ndarray:
    rec = sample["record"]
    truth = (f"ray-cast\nphi {sample['phi_deg']:.1f}, theta {sample['theta_deg']:.1f}",
             sample["raycast"])
    panels: list[tuple[str, np.ndarray] | None] = []
    if sample.get("pca_warp") is not None:  # the served path: own frame | corrected | truth
        skipped = (rec.get("rest") or {}).get("skip_correction")
        panels += [_panel(sample, "pca_warp", "own frame"),
                   _panel(sample, "pca_predict", "own + correction (not sent)" if skipped
                          else "served at rest"), *_rest_panels(sample), truth]
        if "pca_motion" in rec:
            r = rec["pca_motion"]
            panels.append(_panel(sample, "pca_motion", f"served moving (s={r['stride']})"))
        panels.append(_panel(sample, "pca", "PCA, interpolated scores"))
    else:
        panels += [truth, _panel(sample, "pca", "PCA (device)")]
        if "pca_motion" in rec:
            r = rec["pca_motion"]
            panels.append(_panel(sample, "pca_motion", f"PCA, moving (s={r['stride']})"))
    panels.append(_panel(sample, "pca_render", "PCA, ray-cast scores"))
    for codec in ("jpeg", "webp", "avif"):
        c = rec.get(codec)
        if c is not None and sample.get(codec) is not None:
            panels.append((f"{codec.upper() if codec != 'webp' else 'WebP'} q{c['quality']}, "
                           f"{c['bytes_per_view']} B"
                           f"{'' if c['within_budget'] else ' (over budget)'}\n"
                           f"SSIM {c['ssim']:.3f}  FLIP {c['flip']:.3f}", sample[codec]))
    db = rec.get("webp_db")
    if db is not None and sample.get("webp_db") is not None:
        panels.append((f"WebP database q{db['quality']}, 0 B\n"
                       f"SSIM {db['ssim']:.3f}  FLIP {db['flip']:.3f}", sample["webp_db"]))
    for method, title in (("pca_warp", "own frame"), ("pca_predict", "served at rest"),
                          ("pca", "PCA"), ("jpeg", "JPEG")):
        if sample.get(f"flip_{method}") is not None:
            panels.append((f"FLIP error map\n{title}", _colormap(sample[f"flip_{method}"])))
    return compose_side_by_side([p for p in panels if p is not None])


_CSS = """
body { font-family: -apple-system, "Segoe UI", Roboto, Helvetica, Arial, sans-serif;
       margin: 2em auto; max-width: 1200px; color: #222; padding: 0 1em; }
h1 { font-size: 1.6em; margin-bottom: .2em; } h2 { font-size: 1.25em; margin-top: 1.6em; }
p.sub { color: #555; margin-top: 0; }
table { border-collapse: collapse; margin: .6em 0; font-size: .92em; }
th, td { padding: .35em .8em; border-bottom: 1px solid #ddd; text-align: right; }
th:first-child, td:first-child { text-align: left; }
thead th { border-bottom: 2px solid #888; background: #f5f5f5; }
tr.best td { font-weight: 600; }
td.win { color: #1b7837; font-weight: 600; } td.lose { color: #b2182b; }
img { max-width: 100%; border: 1px solid #ddd; }
.note { color: #555; font-size: .9em; }
code { background: #f3f3f3; padding: 0 .25em; }
"""


def _table(headers: list[str], rows: list[list[str]], cls: list[str] | None = None) -> str:
    head = "".join(f"<th>{h}</th>" for h in headers)
    body = []
    for i, row in enumerate(rows):
        c = f' class="{cls[i]}"' if cls and cls[i] else ""
        body.append(f"<tr{c}>" + "".join(f"<td>{v}</td>" for v in row) + "</tr>")
    return f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def _compare_cell(value: float, reference: float, higher_better: bool, digits: int) -> str:
    text = _fmt(value, digits)
    if not (isinstance(value, float) and isinstance(reference, float)) or not (
        math.isfinite(value) and math.isfinite(reference)
    ):
        return text
    better = value > reference if higher_better else value < reference
    return f'<span class="{"win" if better else "lose"}">{text}</span>'


def _served_note(m: dict) -> str:
    if m.get("gain_over_own") is None:
        return ""
    return (f"; {m['gain_over_own']:+.4f} object SSIM over the own frame, worst view "
            f"{m['worst_gain_over_own']:+.4f}, {m['views_below_own']} views more than 0.01 "
            "below it")


def _equal_quality_html(summary: dict) -> str:
    rows = []
    for method in ("pca_predict", "pca_motion"):
        eq = (summary.get(method) or {}).get("equal_quality")
        if not eq:
            continue
        row = [_NAMES[method], str(eq["views"]), _fmt(eq["ssim_object"], 4),
               _bytes(eq["bytes_per_view"])]
        for codec in ("webp", "avif"):
            c = eq.get(codec) or {}
            row += [_bytes(c.get("bytes_for_ssim")), _fmt(c.get("ssim_at_bytes"), 4)]
        rows.append(row)
    if not rows:
        return ""
    return ("<h2>Served frames against the codecs</h2>"
            + _table(["method", "views", "SSIM obj.", "bytes/view", "WebP bytes for that SSIM",
                      "WebP SSIM at those bytes", "AVIF bytes for that SSIM",
                      "AVIF SSIM at those bytes"], rows)
            + "<p class='note'>From the codecs' rate-distortion curves on the sweep's views "
              "(interpolated between swept qualities: SSIM linear, bytes log-linear); – "
              "outside the swept qualities.</p>")


def _ratio(stats: dict | None) -> str:
    if not stats or stats.get("median") is None:
        return "–"
    return f"{stats['median']:.2f} ({stats['worst']:.2f})"


def _rest_html(summary: dict) -> str:
    rest = summary.get("rest")
    if not rest:
        return ""
    rows = []
    for stage, r in rest["stages"].items():
        rows.append([html.escape(stage), str(r["views"]), _bytes(r.get("bytes")),
                     _fmt(r.get("ssim_object"), 4), _fmt(r.get("ssim"), 4),
                     _fmt(r.get("flip"), 4), _ratio(r.get("x_webp")), _ratio(r.get("x_avif")),
                     _ratio(r.get("x_jpeg"))])
    exact = rest["stages"].get("exact")
    exact_html = ""
    if exact:
        exact_html = (
            f"<p>The exact frame costs {_bytes(exact.get('bytes'))} in all (median): "
            f"{_ratio(exact.get('x_webp_lossless'))} times the ray-cast's WebP lossless file "
            f"({_bytes(exact.get('webp_lossless_bytes'))}), {_ratio(exact.get('x_png'))} its "
            f"optimized PNG ({_bytes(exact.get('png_bytes'))}); the exact layer alone "
            f"{_ratio(exact.get('layer_x_webp_lossless'))} the WebP lossless file.</p>")
    bar = rest.get("from_ssim_0.9") or {}
    return ("<h2>At rest: layers to the exact frame</h2>"
            f"<p class='note'>What <code>serve</code> sends a resting view after its own frame, "
            f"{rest['views']} views (the complete correction skipped on "
            f"{rest['correction_skipped']}: it did not pay for itself). Medians of the "
            "cumulative bytes and of the metrics after each stage; ×codec: the cumulative "
            "bytes over the smallest file of the ray-cast reaching the stage's object SSIM, "
            "median (worst), on the sweep's views.</p>"
            + _table(["stage", "views", "bytes in all", "SSIM obj.", "SSIM", "FLIP",
                      "×WebP", "×AVIF", "×JPEG"], rows)
            + exact_html
            + f"<p class='note'>From object SSIM 0.9 up ({bar.get('steps', 0)} steps): "
              f"×WebP {_ratio(bar.get('x_webp'))}, ×AVIF {_ratio(bar.get('x_avif'))}.</p>"
            + "<img src='rest.png' alt='quality against bytes at rest'>")


def write_report(evaluation: Any, folder: str | os.PathLike) -> Path:
    """Write the HTML report (and its PNGs and summary.json) into ``folder``; returns index.html."""
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    (out / "views").mkdir(exist_ok=True)
    summary = evaluation.summary()
    (out / "summary.json").write_text(json.dumps(summary, indent=2, allow_nan=False) + "\n")
    if evaluation.rd:
        _rd_plot(evaluation, out / "rd.png")
    _per_view_plot(evaluation, out / "per_view.png")
    if summary.get("rest"):
        _rest_plot(evaluation, out / "rest.png")
    figures = []
    for i, sample in enumerate(evaluation.samples):
        name = f"views/view_{i:02d}.png"
        _save_png(out / name, _sample_figure(sample))
        figures.append(name)
    (out / "index.html").write_text(_html(evaluation, summary, figures), encoding="utf-8")
    return out / "index.html"


def _table1(info: dict, summary: dict) -> list[list[str]]:
    """The model's rows, laid out like the paper's Table 1."""
    dims = (info.get("volume") or {}).get("dims")
    h, w = info["image_shape"]
    pca, jpeg, webp = summary.get("pca", {}), summary.get("jpeg", {}), summary.get("webp", {})
    avif = summary.get("avif", {})
    t = info.get("threshold")
    return [
        ["volume dimensions", " × ".join(str(d) for d in dims) if dims else "–"],
        ["image size", f"{w} × {h}"],
        ["training views", f"{info['training_views']} ({_fmt(info.get('training_view_spec'))})"],
        ["method, cell", f"{info['method']}, {info['cell_shape'][1]} × {info['cell_shape'][0]}"],
        ["mean number of dimensions per cell", _fmt(info["components_per_cell"], 2)],
        ["T", f"{100 * t:.4g}%" if t is not None else "–"],
        ["eigenspace (device image)", _bytes(info["eigenspace_bytes"])],
        ["bytes per view (score packet, mean)", _bytes(pca.get("bytes_per_view"))],
        ["mean SSIM of PCA", _fmt(pca.get("ssim"), 4)],
        ["mean SSIM of equal-bytes JPEG", _fmt(jpeg.get("ssim"), 4)],
        ["mean SSIM of equal-bytes WebP", _fmt(webp.get("ssim"), 4)],
        ["mean SSIM of equal-bytes AVIF", _fmt(avif.get("ssim"), 4)],
        ["mean FLIP of PCA", _fmt(pca.get("flip"), 4)],
        ["mean FLIP of equal-bytes JPEG", _fmt(jpeg.get("flip"), 4)],
        ["mean FLIP of equal-bytes WebP", _fmt(webp.get("flip"), 4)],
        ["mean FLIP of equal-bytes AVIF", _fmt(avif.get("flip"), 4)],
    ]


def _method_note(method: str, m: dict, summary: dict) -> str:
    """The last column of a method's row: its quality, distance or what it shows."""
    extra = ""
    if method == "webp_db":
        extra = (f"q={m.get('quality', math.nan):.0f}, device storage "
                 f"{_bytes(m.get('storage_bytes'))}"
                 f"{' (estimated)' if m.get('storage_estimated') else ''}")
    if method in ("jpeg", "webp", "avif"):
        extra = f"q≈{m.get('quality', math.nan):.0f}"
        if m.get("over_budget_views"):
            extra += f", {m['over_budget_views']} views over budget at q=1"
    elif method == "nearest":
        extra = f"{m.get('angle_deg', math.nan):.2f}° away (PNG)"
    elif method == "pca_warp":
        extra = ("shown at once, no packets: the 4 neighbouring training views "
                 + ("warped by their depth" if m.get("own_frame") == "warp"
                    else "blended by the predicted scores (an image without depth)"))
    elif method == "pca_render":
        extra = "key packets of the ray-cast's own scores (no view interpolation)"
    elif method == "pca_predict":
        extra = ("what a resting view converges to: the own frame plus the complete "
                 "correction at the model's step (a version-3 packet; 0 B when nothing "
                 "is worth sending)" + _served_note(m))
    elif method == "pca_motion":
        extra = (f"stride {m.get('stride', math.nan):.0f} at a "
                 f"{m.get('deadline_ms', math.nan):.0f} ms deadline, "
                 f"{m.get('step_deg', math.nan):g}°/frame; "
                 + ("own frame + sparse correction, bytes as streamed" + _served_note(m)
                    if "pca_predict" in summary else "delta packets of a drag"))
    return extra


def _method_rows(summary: dict) -> list[list[str]]:
    """One row per method evaluated: bytes, PSNR/SSIM/FLIP against the PCA's, object-only
    metrics, blockiness and its note."""
    pca = summary.get("pca", {})
    rows = []
    for method in METHODS:
        m = summary.get(method)
        if not m:
            continue
        rows.append([
            _NAMES[method],
            _bytes(m.get("bytes_per_view")),
            _compare_cell(m.get("psnr"), pca.get("psnr"), True, 2) if method != "pca"
            else _fmt(m.get("psnr"), 2),
            _compare_cell(m.get("ssim"), pca.get("ssim"), True, 4) if method != "pca"
            else _fmt(m.get("ssim"), 4),
            _compare_cell(m.get("flip"), pca.get("flip"), False, 4) if method != "pca"
            else _fmt(m.get("flip"), 4),
            _fmt(m.get("psnr_object"), 2), _fmt(m.get("ssim_object"), 4),
            _fmt(m.get("flip_object"), 4), _fmt(m.get("blockiness"), 3),
            _method_note(method, m, summary),
        ])
    return rows


def _int8_text(info: dict) -> str:
    """What int8 quantization costs, as ``fit`` measured it."""
    int8 = info.get("int8") or {}
    if not int8:
        return "not recorded (model fitted by an older eigencast)"
    return (
        f"measured by <code>fit</code> on {int8.get('views', '?')} training views: PSNR "
        f"float {_fmt(int8.get('train_psnr_float_db'), 2)} dB, int8 "
        f"{_fmt(int8.get('train_psnr_int8_db'), 2)} dB, loss "
        f"<b>{_fmt(int8.get('train_loss_db'), 3)} dB</b>; float vs int8 at interpolated "
        f"novel scores: {_fmt(int8.get('novel_psnr_float_vs_int8_db'), 1)} dB"
    )


def _rd_rows(evaluation: Any) -> list[list[str]]:
    """The rate-distortion table's rows."""
    rd_rows = []
    for p in evaluation.rd:
        series = _NAMES[p["kind"]].split(",")[0] + ("  (this model)" if p.get("own") else "")
        rd_rows.append([series,
                        html.escape(p["label"]), _bytes(p["bytes_per_view"]),
                        _fmt(p.get("components_per_cell"), 2) if p["kind"] == "pca" else "–",
                        _fmt(p["psnr"], 2), _fmt(p["ssim"], 4), _fmt(p["flip"], 4)])
    return rd_rows


def _target_html(info: dict) -> str:
    """What ``fit --target`` chose, when it did."""
    target = info.get("target")
    if not target:
        return ""
    choice = target.get("choice") or {}
    return (
        f"<p>Chosen by <code>fit --target {html.escape(str(target.get('metric')))}="
        f"{target.get('value')}</code> on {html.escape(str(target.get('holdout')))}: "
        f"{html.escape(json.dumps(choice))}</p>"
    )


def _html(evaluation: Any, summary: dict, figures: list[str]) -> str:
    info = evaluation.info
    name = (info.get("volume") or {}).get("name") or "volume"
    table1 = _table1(info, summary)
    rows = _method_rows(summary)
    int8_text = _int8_text(info)
    rd_rows = _rd_rows(evaluation)
    timing = evaluation.timing_s
    total = sum(timing.values()) or 1.0
    timing_rows = [[html.escape(k), f"{v:.1f}", f"{100 * v / total:.0f}%"]
                   for k, v in timing.items()]
    target_html = _target_html(info)
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'>",
        f"<title>eigencast evaluation: {html.escape(name)}</title>",
        f"<style>{_CSS}</style></head><body>",
        f"<h1>eigencast evaluation: {html.escape(name)} — {html.escape(info['method'])}</h1>",
        f"<p class='sub'>{html.escape(str(info.get('path') or 'model in memory'))} · "
        f"{len(evaluation.views)} novel views ({html.escape(str(info.get('view_spec', '')))}) "
        f"ray-cast with the model's own render settings · transfer function "
        f"{html.escape(str(info.get('transfer_function')))} · interpolation "
        f"{html.escape(str(info.get('interpolation')))}</p>",
        "<h2>The model, laid out like the paper's Table 1</h2>",
        _table(["", html.escape(name)], table1),
        "<p class='note'>The paper reports HDR-VDP-2 Q-values; eigencast uses SSIM "
        "(scikit-image) and FLIP (NVIDIA, LDR, 67 pixels per degree). Bytes per view: the real "
        "key score packet (header + zstd-compressed varints) at the model's score step "
        f"{info['score_step']:.4g}; equal-bytes codecs use the highest quality whose file is "
        "not larger than that view's packet.</p>",
        target_html,
        "<h2>Novel views: means over all views</h2>",
        _table(["method", "bytes/view", "PSNR dB", "SSIM", "FLIP", "PSNR obj.", "SSIM obj.",
                "FLIP obj.", "blockiness", ""], rows),
        "<p class='note'>Green: better than the PCA reconstruction, red: worse. “obj.”: over "
        "object pixels only (ray-cast alpha ≥ 0.5/255). The nearest training view costs a "
        "lossless PNG download and is what a client would show with no interpolation at all. "
        f"Training images for it came from the {html.escape(str(info.get('nearest_source')))}."
        f"</p><p class='note'>Blockiness: the mean absolute difference of neighbouring object "
        f"pixels across cell borders over that inside cells (1: no seams); the ray-cast's own "
        f"is {_fmt(summary.get('raycast_blockiness'), 3)}.</p>",
        _equal_quality_html(summary),
        _rest_html(summary),
        f"<p><b>int8 quantization</b>: {int8_text}.</p>",
    ]
    if evaluation.rd:
        parts += [
            "<h2>Rate-distortion</h2>",
            "<img src='rd.png' alt='rate-distortion plot'>",
            "<p class='note'>PCA points truncate this model to lower thresholds (or fewer "
            "components) through the eigenvalues kept in its annex, with the score step scaled "
            "like the model's; crosses use coarser score steps at the model's own components. "
            "The open plus is an oracle: the true views projected onto this eigenspace and "
            "sent through the same packet and reconstruction; the gap between it and the star "
            "is what interpolating between training views costs. "
            "JPEG/WebP points encode the same ray-casts at fixed qualities.</p>",
            _table(["series", "setting", "bytes/view", "dims/cell", "PSNR dB", "SSIM", "FLIP"],
                   rd_rows),
        ]
    parts += ["<h2>Per view</h2>", "<img src='per_view.png' alt='per-view quality'>"]
    if figures:
        parts.append("<h2>Side by side</h2><p class='note'>the device's own frame | served at "
                     "rest | its refinement layers and exact frame | ray-cast (a model with "
                     "the standalone table), then the other methods; FLIP error maps (black "
                     "0, yellow 1)</p>")
        parts += [f"<p><a href='{f}'><img src='{f}' alt='view {i}'></a></p>"
                  for i, f in enumerate(figures)]
    parts += [
        "<h2>Where the time went</h2>",
        _table(["phase", "seconds", "share"], timing_rows),
        "</body></html>",
    ]
    return "\n".join(parts)
