"""The device's own frames under each lighting look: evaluate's ``pca_warp`` per look.

    .venv/bin/python scripts/lighting_warp.py --dbs DIR [--volumes builtin:head,tooth]
        [--size 256] [--views grid:100x15] [--test-views random:20:15]

For each volume and look (``headlight``, ``cinematic``) it uses ``DIR/NAME-LOOK.cdb`` (as
``benchmarks/bench_lighting.py --output DIR`` leaves them; rendered here with ``eigencast
render --lighting LOOK`` when absent), fits it with the default ``eigencast fit`` (the
standalone table and the depth eigenspace: the device warps its training views by their
depth) into ``DIR/NAME-LOOK.ecs`` when absent, and runs ``eigencast evaluate`` on the same
novel views for both looks (each against a fresh ray-cast in its own look). It prints
object SSIM of the device's own frame (``pca_warp``), of the plain score blend (``pca``)
and of the projection oracle (``pca_render``), the share of the blend-to-oracle gap the warp
closes, and on how many views the cinematic warp scores higher than the headlight's.

Produces: BENCHMARKS.md, "Lighting looks", the pca_warp table.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from host.shared_data import shared_volume

LOOKS = ("headlight", "cinematic")
METHODS = ("pca", "pca_warp", "pca_render")


def _eigencast(*args: str) -> str:
    result = subprocess.run([sys.executable, "-m", "host.cli", *args], check=True,
                            stdout=subprocess.PIPE, text=True)
    return result.stdout


def _spec(name: str) -> str:
    if name.startswith("builtin:"):
        return name
    path = shared_volume(name)
    if path is None:
        raise SystemExit(f"lighting_warp: {name} is not in ../shared/data")
    return str(path)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dbs", type=Path, required=True)
    parser.add_argument("--volumes", default="builtin:head,tooth")
    parser.add_argument("--size", default="256")
    parser.add_argument("--views", default="grid:100x15")
    parser.add_argument("--test-views", default="random:20:15")
    args = parser.parse_args()
    args.dbs.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in args.volumes.split(","):
        label = name.replace("builtin:", "")
        results = {}
        for look in LOOKS:
            db = args.dbs / f"{label}-{look}.cdb"
            model = args.dbs / f"{label}-{look}.ecs"
            if not (db / "data.csv").is_file():
                _eigencast("render", _spec(name), "-o", str(db), "--size", args.size,
                           "--views", args.views, "--lighting", look)
            if not model.is_file():
                _eigencast("fit", str(db), "-o", str(model))
            out = args.dbs / f"{label}-{look}.evaluate.json"
            if not out.is_file():
                text = _eigencast("evaluate", str(model), "--views", args.test_views, "--json",
                                  "--rd-views", "0", "--no-nearest", "--motion-deadline", "0",
                                  "--webp-db-quality", "0")
                out.write_text(text)
            results[look] = json.loads(out.read_text())
        per_view = {look: [v["pca_warp"]["ssim_object"] for v in results[look]["per_view"]]
                    for look in LOOKS}
        better = sum(c > h for h, c in zip(per_view["headlight"], per_view["cinematic"]))
        for look in LOOKS:
            r = results[look]
            s = {m: r[m]["ssim_object"] for m in METHODS}
            gap = (s["pca_warp"] - s["pca"]) / max(1e-9, s["pca_render"] - s["pca"])
            rows.append((label, look, s["pca"], s["pca_warp"], s["pca_render"], gap,
                         f"{better}/{len(per_view[look])}" if look == "cinematic" else "",
                         r["components_per_cell"], r["eigenspace_bytes"] / 1e6))
    print(f"object SSIM on {args.test_views}, databases {args.views} at {args.size} px, "
          "default fit")
    print("| volume | look | blend (`pca`) | **own frame (`pca_warp`)** | projection "
          "(`pca_render`) | gap closed by the warp | views where cinematic's warp is higher "
          "| components / cell | eigenspace MB |")
    print("|---|---|---|---|---|---|---|---|---|")
    for label, look, blend, warp, oracle, gap, better, k, mb in rows:
        print(f"| {label} | {look} | {blend:.4f} | **{warp:.4f}** | {oracle:.4f} | {gap:.2f} "
              f"| {better} | {k:.1f} | {mb:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
