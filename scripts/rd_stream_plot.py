"""Figure and tables of docs/rate-distortion.md section 4 from rd_stream.py results.

    .venv/bin/python scripts/rd_stream_plot.py stream-*.json -o docs/images/rd-stream.png

One column per result file (orbits pooled): object SSIM (top) and object FLIP (bottom)
against mean bytes per frame of the key+delta stream, for interpolated and ray-cast
(projected) scores at each score step, and WebP's own curve on the matched views. Prints
the Markdown table (bytes, quality, equal-quality WebP/JPEG and the ratio).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def pooled(run: dict) -> tuple[dict, dict]:
    """Summaries averaged over the orbits (weighted by views), and the WebP curve."""
    orbits = list(run["orbits"].values())
    weights = np.array([o["views"] for o in orbits], float)
    names = orbits[0]["summary"].keys()
    summary = {n: {k: float(np.average([o["summary"][n][k] for o in orbits], weights=weights))
                   for k in orbits[0]["summary"][n]} for n in names}
    curve = {q: {k: float(np.mean([o["webp_curve"][q][k] for o in orbits]))
                 for k in orbits[0]["webp_curve"][q]} for q in orbits[0]["webp_curve"]}
    return summary, curve


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", nargs="+")
    ap.add_argument("-o", "--output", required=True)
    args = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    runs = [json.loads(Path(p).read_text()) for p in args.results]
    fig, axes = plt.subplots(2, len(runs), figsize=(4.6 * len(runs), 7.5), squeeze=False)
    print("| case | scores, step | B/frame key+delta (key only) | SSIM obj | FLIP obj | "
          "WebP equal | JPEG equal | packets / WebP |")
    print("|---|---|---|---|---|---|---|---|")
    for col, (path, run) in enumerate(zip(args.results, runs, strict=True)):
        name = Path(path).stem.replace("stream-", "").replace("vismale_head", "head")
        summary, curve = pooled(run)
        for mode, colour in (("interpolate", "tab:orange"), ("render", "tab:blue")):
            keys = sorted((k for k in summary if k.startswith(mode + "@")),
                          key=lambda k: float(k.split("@")[1]))
            pts = [summary[k] for k in keys]
            for row, metric in enumerate(("ssim", "flip")):
                axes[row][col].plot([p["bytes"] for p in pts], [p[metric] for p in pts], "o-",
                                    color=colour, label=f"{mode} scores (steps x"
                                    f"{', x'.join(k.split('@')[1] for k in keys)})")
            for k, p in zip(keys, pts, strict=True):
                print(f"| {name} | {mode}, x{k.split('@')[1]} | {p['bytes']:.0f} "
                      f"({p['key_bytes']:.0f}) | {p['ssim']:.3f} | {p['flip']:.3f} | "
                      f"{p['webp_equal_bytes']:.0f} | {p['jpeg_equal_bytes']:.0f} | "
                      f"{p['bytes_vs_webp']:.2f}x |")
        qs = sorted(curve, key=lambda q: int(q))
        for row, metric in enumerate(("ssim", "flip")):
            ax = axes[row][col]
            ax.plot([curve[q]["bytes"] for q in qs], [curve[q][metric] for q in qs], "s--",
                    color="tab:green", label="WebP of the ray-cast (q 1..95)")
            ax.set_xscale("log")
            ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
            ax.set_xlabel("bytes per frame")
            ax.set_ylabel(f"object {metric.upper()}" + (" (lower is better)"
                                                        if metric == "flip" else ""))
            ax.grid(alpha=0.3)
            if row == 0:
                ax.set_title(f"{name}: {run['orbits'] and ', '.join(run['orbits'])}",
                             fontsize=9)
        axes[0][col].legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.output, dpi=90)
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
