"""Figures and tables of docs/rate-distortion.md from rd_interp.py / rd_density.py results.

Usage::

    .venv/bin/python scripts/rd_plots.py --interp tooth-256.json vismale_head-256.json ... \\
        --density density-tooth-256.json ... --out docs/images

writes ``rd-interp.png`` (methods vs the oracle, object pixels), ``rd-storage.png`` (device
storage vs quality: eigencast standalone image vs WebP image database), ``rd-density.png``
(blend quality vs training-grid density against the oracle) and prints the Markdown tables.

Produces: docs/rate-distortion.md, the figures and tables of sections 2 "View interpolation"
and 5 (storage).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def _label(r: dict) -> str:
    name = Path(r["model"]).stem
    return name.replace("vismale_head", "head")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--interp", nargs="*", default=[])
    ap.add_argument("--density", nargs="*", default=[])
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    runs = [json.loads(Path(p).read_text()) for p in args.interp]
    dens = [json.loads(Path(p).read_text()) for p in args.density]

    # ---------------------------------------------------------------- tables
    for r in runs:
        print(f"\n{_label(r)}: {r['views']} views, {r['components_per_cell']:.2f} comp/cell, "
              f"T={r['threshold']}, cell {r['cell_shape'][1]}, eigenspace image "
              f"{r['eigenspace_bytes'] / 1e6:.2f} MB (standalone {r['standalone']}), "
              f"ms/frame {r['timing_ms_per_frame']}")
        print("| method | SSIM obj | FLIP obj | PSNR obj dB | SSIM | FLIP | seam / inside |")
        print("|---|---|---|---|---|---|---|")
        for m, v in r["means"].items():
            print(f"| {m} | {v['ssim_object']:.4f} | {v['flip_object']:.4f} | "
                  f"{v['psnr_object']:.2f} | {v['ssim']:.4f} | {v['flip']:.4f} | "
                  f"{v['seam_ratio']:.2f} |")
        print("webp_db storage:", {q: f"{b / 1e6:.2f} MB"
                                   for q, b in r["webp_db_storage_bytes"].items()})
    for d in dens:
        print(f"\ndensity {d['test_db']}")
        for x in d["results"]:
            print(f"| {x['grid']} | {x['method']} | {x['training_views']} | "
                  f"{x['phi_step_deg']:.2f} x {x['theta_step_deg']:.1f} | "
                  f"{x['ssim_object']:.4f} | {x['flip_object']:.4f} |")

    # ---------------------------------------------------------------- interpolation methods
    if runs:
        methods = [m for m in ("oracle", "bilinear", "bicubic", "barycentric", "bspline",
                               "ls16", "blend_bilinear", "blend_bicubic")
                   if all(m in r["means"] for r in runs)]
        fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), dpi=90)
        width = 0.8 / len(runs)
        for ax, key, title in ((axes[0], "ssim_object", "SSIM, object pixels (higher better)"),
                               (axes[1], "flip_object", "FLIP, object pixels (lower better)")):
            for j, r in enumerate(runs):
                vals = [r["means"][m][key] for m in methods]
                ax.bar(np.arange(len(methods)) + (j - (len(runs) - 1) / 2) * width, vals,
                       width, label=_label(r))
            ax.set_xticks(np.arange(len(methods)))
            ax.set_xticklabels(methods, rotation=30, ha="right", fontsize=8)
            ax.set_title(title, fontsize=10)
            ax.grid(True, axis="y", alpha=0.3)
            if key == "ssim_object":
                lo = min(r["means"][m][key] for r in runs for m in methods)
                ax.set_ylim(max(0.0, lo - 0.05), 1.0)
        axes[0].legend(fontsize=8)
        fig.suptitle("Novel views at the paper's grid density (grid:100x15): interpolation "
                     "methods vs the oracle projection", fontsize=10)
        fig.tight_layout()
        fig.savefig(out / "rd-interp.png")
        plt.close(fig)

        # ------------------------------------------------------------ storage vs quality
        fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), dpi=90)
        for ax, key, title in ((axes[0], "ssim_object", "SSIM, object pixels"),
                               (axes[1], "flip_object", "FLIP, object pixels")):
            for j, r in enumerate(runs):
                color = f"C{j}"
                qs = sorted(r["webp_db_storage_bytes"], key=int)
                xs = [r["webp_db_storage_bytes"][q] / 1e6 for q in qs]
                ys = [r["means"][f"webp_db_q{q}"][key] for q in qs]
                ax.plot(xs, ys, "s--", color=color, label=f"{_label(r)}: WebP database")
                for x, y, q in zip(xs, ys, qs):
                    ax.annotate(f"q{q}", (x, y), textcoords="offset points", xytext=(4, 2),
                                fontsize=7, color=color)
                m = r["default_method"]
                ax.plot([r["eigenspace_bytes"] / 1e6], [r["means"][m][key]], "o",
                        color=color, markersize=8,
                        label=f"{_label(r)}: eigencast standalone ({m})")
                if "oracle" in r["means"]:
                    ax.plot([r["eigenspace_bytes"] / 1e6], [r["means"]["oracle"][key]], "P",
                            color=color, markerfacecolor="none", markersize=9)
            ax.set_xscale("log")
            ax.set_xlabel("device storage (MB)")
            ax.set_title(title + " (open plus: eigenspace oracle)", fontsize=10)
            ax.grid(True, which="both", alpha=0.3)
        axes[0].legend(fontsize=7)
        fig.suptitle("Standalone device: storage vs quality of interpolated novel views",
                     fontsize=10)
        fig.tight_layout()
        fig.savefig(out / "rd-storage.png")
        plt.close(fig)

    # ---------------------------------------------------------------- density
    if dens:
        fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), dpi=90)
        for j, d in enumerate(dens):
            name = Path(d["test_db"]).name.replace("-test.cdb", "").replace("vismale_head",
                                                                             "head")
            rows = [x for x in d["results"] if x["method"] == "bilinear"]
            rows.sort(key=lambda x: x["training_views"])
            oracle = next((r["means"]["oracle"] for r in runs
                           if Path(r["test_db"]).name == Path(d["test_db"]).name), None)
            for ax, key in ((axes[0], "ssim_object"), (axes[1], "flip_object")):
                ax.plot([x["training_views"] for x in rows], [x[key] for x in rows], "o-",
                        color=f"C{j}", label=f"{name}: bilinear blend of true views")
                for x in rows:
                    ax.annotate(x["grid"], (x["training_views"], x[key]),
                                textcoords="offset points", xytext=(3, 3), fontsize=7)
                if oracle is not None:
                    ax.axhline(oracle[key], color=f"C{j}", linestyle=":",
                               label=f"{name}: oracle (paper grid eigenspace)")
        for ax, key in ((axes[0], "SSIM, object pixels"), (axes[1], "FLIP, object pixels")):
            ax.set_xscale("log")
            ax.set_xlabel("training views (grid:NPHIxNTHETA)")
            ax.set_title(key, fontsize=10)
            ax.grid(True, which="both", alpha=0.3)
        axes[0].legend(fontsize=7)
        fig.suptitle("View blending vs training-grid density", fontsize=10)
        fig.tight_layout()
        fig.savefig(out / "rd-density.png")
        plt.close(fig)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
