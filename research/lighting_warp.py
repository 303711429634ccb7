"""The device's own frames under each lighting look: evaluate's ``pca_warp`` per look.

    .venv/bin/python research/lighting_warp.py --dbs DIR [--volumes builtin:head,tooth]
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

``--true-colour`` adds a diagnostic that takes the eigenspace out: the device's warp (its
code, its depth eigenspace) of the *training images themselves* (the database's PNGs in
place of their reconstructions), on the same views, against the same fresh ray-casts. It
separates what the lighting does to the warp from what it does to the eigenspace.

Produces: BENCHMARKS.md, "Lighting looks", the pca_warp figures.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from host.shared_data import shared_volume

LOOKS = ("headlight", "cinematic")


class _TrainingImages:
    """Stands in for the device's reconstructor and score table: a training view's colour
    is the database's image (``update`` receives the view's index, not its scores)."""

    def __init__(self, db_path: Path, standalone: object) -> None:
        from host.render.cinema import CinemaDB

        self.db = CinemaDB.open(db_path)
        self.interpolator = standalone.interpolator

    def training_scores(self, view: int) -> int:
        return view

    def update(self, view: int) -> np.ndarray:
        return self.db.read_image(view)


def _true_colour_warp(db: Path, model: Path, test_views: str) -> list[float]:
    """Object SSIM per view of the device's warp of the true training images."""
    from device_runtime.standalone import StandaloneScores
    from device_runtime.synthesis import ViewSynthesizer
    from host.evaluate import alpha_object_mask, compare_images
    from host.fit.model import HostModel
    from host.render.camera import parse_view_set
    from host.render.settings import RenderSettings, ViewRenderer

    host_model = HostModel.load(model)
    stand_in = _TrainingImages(db, StandaloneScores(host_model.image))
    warp = ViewSynthesizer(host_model.image, stand_in, stand_in)
    scene = ViewRenderer.open(RenderSettings.from_record(host_model.render_settings,
                                                         what=str(model)))
    out = []
    for phi, theta in parse_view_set(test_views).angles_deg():
        truth, alpha = scene.render(phi, theta)
        frame = warp.frame(phi, theta)
        out.append(compare_images(truth, frame, mask=alpha_object_mask(alpha),
                                  metrics=("ssim",)).ssim_object)
    return out
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
    parser.add_argument("--true-colour", action="store_true",
                        help="also warp the true training images (the diagnostic above)")
    args = parser.parse_args()
    args.dbs.mkdir(parents=True, exist_ok=True)
    rows = []
    true_rows = []
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
            if args.true_colour:
                true_out = args.dbs / f"{label}-{look}.true-colour.json"
                if not true_out.is_file():
                    true_out.write_text(json.dumps(_true_colour_warp(db, model,
                                                                     args.test_views)))
                results[look]["true_colour"] = json.loads(true_out.read_text())
        per_view = {look: [v["pca_warp"]["ssim_object"] for v in results[look]["per_view"]]
                    for look in LOOKS}
        if args.true_colour:
            true_rows.append((label, results["headlight"]["true_colour"],
                              results["cinematic"]["true_colour"]))
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
    if true_rows:
        print("\nthe device's warp of the true training images (no eigenspace), object SSIM")
        print("| volume | headlight | cinematic | views where cinematic's is higher |")
        print("|---|---|---|---|")
        for label, head, cine in true_rows:
            better = sum(c > h for h, c in zip(head, cine))
            print(f"| {label} | {np.mean(head):.4f} | {np.mean(cine):.4f} | "
                  f"{better}/{len(head)} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
