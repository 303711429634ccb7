"""Figures and tables of docs/rate-distortion-packets.md from the ``rdp_*.py`` JSON outputs.

    .venv/bin/python research/rdp_plots.py --results /work/cache/h12 --docs docs/images

Reads ``packets-NAME.json``, ``table-NAME.json``, ``eigen-NAME.json`` and
``storage-NAME.json`` for every NAME found (e.g. ``tooth-256``) and writes
``rdp-packets.png``, ``rdp-storage.png`` and ``rdp-eigenbits.png`` (each well under 200 KB)
plus ``rdp-tables.md`` (markdown tables) into the results folder and the figures into
``--docs``.

Produces: docs/rate-distortion-packets.md, the figures and tables of sections 1-4.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib
import matplotlib.ticker

matplotlib.use("Agg")
import matplotlib.pyplot as plt


def load(folder: Path, kind: str) -> dict[str, dict]:
    out = {}
    for p in sorted(folder.glob(f"{kind}-*.json")):
        out[p.stem[len(kind) + 1:]] = json.loads(p.read_text())
    return out


def packets_figure(packets: dict[str, dict], path: Path) -> None:
    names = list(packets)
    cols = min(2, len(names))
    rows_n = -(-len(names) // cols)
    fig, axes = plt.subplots(rows_n, cols, figsize=(4.6 * cols, 3.4 * rows_n), squeeze=False)
    for ax, name in zip(axes.ravel(), names):
        r = packets[name]
        rows = [s for s in r["steps"] if "waterfill" in s]
        ssim = [s["waterfill"]["quality"]["ssim"] for s in rows]
        key = [s["waterfill"]["packet_bytes"] for s in rows]
        old = [s["uniform"]["packet_bytes_v1_level3"] for s in rows]
        deltas = [sum(o["delta"] for o in s["waterfill"]["orbits"].values())
                  / len(s["waterfill"]["orbits"]) for s in rows]
        ax.plot(old, [s["uniform"]["quality"]["ssim"] for s in rows], "o:", color="0.6",
                label="v1 packet (zstd 3, varints)")
        ax.plot(key, ssim, "o-", label="key packet (now)")
        ax.plot(deltas, ssim, "s-", label="key+delta, orbit")
        for codec, marker in (("webp", "^"), ("jpeg", "v")):
            # at the frames' SSIM (all views); the codec bytes match each frame of a subset
            pts = [(s["codecs"][codec]["bytes"], s["waterfill"]["quality"]["ssim"])
                   for s in rows if "codecs" in s]
            if pts:
                ax.plot(*zip(*pts), marker, ls="none",
                        label=f"{codec.upper()} at >= PCA SSIM & FLIP")
        for s, x, y in zip(rows, key, ssim):
            ax.annotate(f"x{s['factor']:g}", (x, y), fontsize=7, xytext=(3, -9),
                        textcoords="offset points")
        ax.axhline(r["float"]["ssim"], color="k", lw=0.6, ls="--")
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_title(f"{name} ({r['views']} views)", fontsize=9)
        ax.set_xlabel("bytes per frame")
        ax.set_ylabel("object SSIM")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=6.5, loc="lower right")
    for ax in axes.ravel()[len(names):]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def storage_figure(storage: dict[str, dict], tables: dict[str, dict], path: Path) -> None:
    names = list(storage)
    cols = min(2, len(names))
    rows_n = -(-len(names) // cols)
    fig, axes = plt.subplots(rows_n, cols, figsize=(4.6 * cols, 3.4 * rows_n), squeeze=False)
    for ax, name in zip(axes.ravel(), names):
        rows = storage[name]["rows"]
        for budget, marker, color in ((0.0, "o", "C0"), (0.03, "s", "C2"), (0.2, "D", "C4")):
            for factor, ls in ((1.0, "-"), (2.0, "--"), (4.0, ":")):
                pts = sorted((r["device_bytes"] / 1e6, r["quality"]["ssim"]) for r in rows
                             if r["bit_budget"] == budget and r["table_factor"] == factor)
                if pts:
                    ax.plot(*zip(*pts), marker=marker, ls=ls, ms=4, color=color,
                            label=f"bits {budget:g}, table x{factor:g}")
        db = storage[name].get("webp_db") or tables.get(name, {}).get("webp_db")
        if db:
            pts = [(d["bytes"] / 1e6, d["metrics"]["ssim"]) for d in db]
            ax.plot(*zip(*pts), "k^-", label="WebP image database")
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_title(name, fontsize=9)
        ax.legend(fontsize=6, loc="lower right")
        ax.set_xlabel("device storage, MB")
        ax.set_ylabel("object SSIM (standalone)")
        ax.grid(alpha=0.3)
    for ax in axes.ravel()[len(names):]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def eigen_figure(eigen: dict[str, dict], path: Path) -> None:
    fig, ax = plt.subplots(figsize=(5, 3.6))
    for name, r in eigen.items():
        rows = r["rows"]
        base = rows[0]
        x = [row["eigen_bytes"] / base["eigen_bytes"] for row in rows]
        y = [row["quality"]["ssim"] - base["quality"]["ssim"] for row in rows]
        ax.plot(x, y, "o-", label=name)
        for row, xi, yi in zip(rows, x, y):
            ax.annotate(f"{row['budget']:g}", (xi, yi), fontsize=6, xytext=(2, 3),
                        textcoords="offset points")
    ax.set_xlabel("eigenimage bytes (compressed) / int8")
    ax.set_ylabel("object SSIM change")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def tables_md(packets: dict, tables: dict, eigen: dict, storage: dict) -> str:
    lines = ["## packets", "", "| case | step | SSIM | PSNR | v1 bytes | key | key+delta | "
             "dict (cell) | entropy bound | WebP eq. | JPEG eq. |", "|" + "---|" * 11]
    for name, r in packets.items():
        lines.append(f"| {name} | float | {r['float']['ssim']:.4f} | {r['float']['psnr']:.2f} "
                     "| | | | | | | |")
        for s in r["steps"]:
            w = s["waterfill"]
            od = sum(o["delta"] for o in w["orbits"].values()) / len(w["orbits"])
            c = s.get("codecs", {})
            lines.append(
                f"| {name} | x{s['factor']:g} ({s['step']:.3g}) | {w['quality']['ssim']:.4f} | "
                f"{w['quality']['psnr']:.2f} | {s['uniform']['packet_bytes_v1_level3']:.0f} | "
                f"{w['packet_bytes']:.0f} | {od:.0f} | "
                f"{w['layout_bytes'].get('cell_varint_dict', float('nan')):.0f} | "
                f"{w['entropy_bytes']:.0f} | "
                f"{c.get('webp', {}).get('bytes', float('nan')):.0f} | "
                f"{c.get('jpeg', {}).get('bytes', float('nan')):.0f} |")
    lines += ["", "## eigen bits", "", "| case | budget (MSE) | mean bits | eigen MB | "
              "measured MSE vs int8 | SSIM | PSNR |", "|" + "---|" * 7]
    for name, r in eigen.items():
        for row in r["rows"]:
            lines.append(f"| {name} | {row['budget']:g} | {row['mean_bits']:.2f} | "
                         f"{row['eigen_bytes'] / 1e6:.3f} | {row['measured_mse_vs_int8']:.3f} | "
                         f"{row['quality']['ssim']:.4f} | {row['quality']['psnr']:.2f} |")
    lines += ["", "## standalone table", "", "| case | kind | factor | bytes | SSIM |",
              "|" + "---|" * 5]
    for name, r in tables.items():
        for v in r["variants"]:
            for k, b in v.get("bytes", {}).items():
                lines.append(f"| {name} | {v['kind']}/{k} | {v['factor']:g} | {b} | "
                             f"{v['quality']['ssim']:.4f} |")
        for d in r.get("webp_db", []):
            lines.append(f"| {name} | webp db q{d['quality']} | | {d['bytes']} | "
                         f"{d['metrics']['ssim']:.4f} |")
    for name, r in storage.items():
        for d in r.get("webp_db", []):
            lines.append(f"| {name} | webp db (storage views) q{d['quality']} | | "
                         f"{d['bytes']} | {d['metrics']['ssim']:.4f} |")
    lines += ["", "## storage", "", "| case | T | bits | table x | K | MB | eigen MB | "
              "table MB | SSIM | PSNR |", "|" + "---|" * 10]
    for name, r in storage.items():
        for row in r["rows"]:
            sec = row["sections"]
            lines.append(
                f"| {name} | {row['threshold']:g} | {row['bit_budget']:g} | "
                f"{row['table_factor']:g} | {row['K']} | {row['device_bytes'] / 1e6:.3f} | "
                f"{sec['eigenimages'] / 1e6:.3f} | {sec[row['table_section']] / 1e6:.3f} | "
                f"{row['quality']['ssim']:.4f} | {row['quality']['psnr']:.2f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="/work/cache/h12")
    ap.add_argument("--docs", default="docs/images")
    args = ap.parse_args(argv)
    res, docs = Path(args.results), Path(args.docs)
    docs.mkdir(parents=True, exist_ok=True)
    packets, tables = load(res, "packets"), load(res, "table")
    eigen, storage = load(res, "eigen"), load(res, "storage")
    if packets:
        packets_figure(packets, docs / "rdp-packets.png")
    if storage:
        storage_figure(storage, tables, docs / "rdp-storage.png")
    if eigen:
        eigen_figure(eigen, docs / "rdp-eigenbits.png")
    (res / "rdp-tables.md").write_text(tables_md(packets, tables, eigen, storage))
    print(f"wrote figures to {docs} and {res / 'rdp-tables.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
