"""Rerun the paper reproduction (docs/paper-reproduction.md) end to end, through the CLI.

    .venv/bin/python scripts/reproduce_paper.py [--cache /work/cache/repro] [--views 100]
        [--datasets tooth,vismale_head] [--targets ssim=0.95,flip=0.1] [--docs-images DIR]
        [--size 512] [--scheduler ADDRESS|local:N] [--evaluate-options '...']

The paper's own 1080 x 1080 Table 1, through a Dask LocalCluster (issue 16; what ran here)::

    nice -n 19 .venv/bin/python scripts/reproduce_paper.py --cache /work/cache/repro1080 \
        --studies adaptive --size 1080 --scheduler local:2 --targets "" \
        --evaluate-options "--webp-db-quality 0 --motion-deadline 0 --rd-views 0"

For each dataset (real volumes from ../shared/data, located with `host.shared_data`):

1. ``eigencast render`` the paper's 1500-view grid (``grid:100x15``: 3.6 x 12 degrees) at
   300x300 and 512x512 into ``CACHE/NAME-SIZE.cdb`` (resumable; never inside the repo);
2. feasibility study (section 4), 300x300: ``fit --method standard --components 100`` and
   ``fit --method cell --cell 20 --components 100``, evaluated off-grid on a seeded random
   subset of the paper's 2400 test views (0.9 degrees in phi x 30 degrees in theta);
3. adaptive study (section 5, Table 1), 512x512 (``--size``): ``fit --method adaptive --cell 30
   --threshold T`` with the paper's T (98 % head, 99.7 % tooth), evaluated on ``random:N``
   (the paper used 100 random views);
4. automatic threshold: ``fit --target METRIC=VALUE`` for each ``--targets`` entry, evaluated
   the same way.

Every fit runs as its own process; its wall time and peak resident memory (``wait4``) are
recorded. Steps whose outputs exist are skipped, so an interrupted run resumes. Results go to
``CACHE/results.json`` and ``CACHE/results.md`` (markdown tables); HTML reports to
``CACHE/reports/``; small figures for the docs (rate-distortion plots, a side-by-side view,
each well under 300 KB) to ``--docs-images``.

Produces: docs/paper-reproduction.md (every section's figures and tables).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from host.shared_data import shared_volume

REPO = Path(__file__).resolve().parent.parent
CLI = [sys.executable, "-m", "host.cli"]
#: The paper's thresholds (Table 1).
PAPER_T = {"tooth": 0.997, "vismale_head": 0.98}
LABEL = {"tooth": "Tooth", "vismale_head": "VisMale head"}
#: Paper figures, for the tables.
PAPER = {
    "vismale_head": {"dims": "128 × 256 × 256", "k": 46.27, "T": "98%", "q_pca": "60%",
                     "q_jpeg": "66.8%", "kb": "59 kB"},
    "tooth": {"dims": "140 × 120 × 161", "k": 26.4, "T": "99.7%", "q_pca": "62.2%",
              "q_jpeg": "60.1%", "kb": "36 kB"},
}


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def run_measured(args: list[str], log_path: Path, *, allow_fail: bool = False) -> dict:
    """Run a CLI command; return wall seconds, peak RSS (MB) and stdout.

    A failure raises SystemExit, or with ``allow_fail`` returns ``{"error": last line}``.
    """
    t0 = time.perf_counter()
    with open(log_path, "w") as err:
        proc = subprocess.Popen([*CLI, *args], stdout=subprocess.PIPE, stderr=err, text=True,
                                cwd=REPO)
        out = proc.stdout.read() if proc.stdout else ""
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        if allow_fail:
            lines = log_path.read_text().strip().splitlines()
            return {"error": lines[-1] if lines else f"exit {proc.returncode}", "stdout": out}
        raise SystemExit(f"failed ({proc.returncode}): eigencast {' '.join(args)}; see {log_path}")
    return {"wall_s": round(wall, 1), "peak_rss_mb": round(usage.ru_maxrss / 1024, 1),
            "stdout": out}


def paper_test_views(path: Path, count: int, seed: int = 0) -> Path:
    """A seeded random subset of the paper's 2400 test views, as a phi,theta CSV."""
    phis = np.arange(400) * 0.9
    thetas = np.array([-75.0, -45.0, -15.0, 15.0, 45.0, 75.0])
    grid = np.array([(p, t) for p in phis for t in thetas])
    pick = np.sort(np.random.default_rng(seed).choice(len(grid), size=count, replace=False))
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["phi", "theta"])
        w.writerows(grid[pick].tolist())
    return path


class Study:
    def __init__(self, cache: Path, views: int, results: dict,
                 scheduler: str | None = None, evaluate_options: list[str] | None = None) -> None:
        self.cache = cache
        self.views = views
        self.results = results
        #: ``--scheduler`` for render and fit (a Dask address or ``local:N``), or in-process.
        self.cluster = ["--scheduler", scheduler] if scheduler else []
        self.evaluate_options = evaluate_options or []
        (cache / "logs").mkdir(parents=True, exist_ok=True)
        (cache / "reports").mkdir(exist_ok=True)

    def save(self) -> None:
        (self.cache / "results.json").write_text(json.dumps(self.results, indent=2) + "\n")

    def database(self, name: str, volume: Path, size: int) -> Path:
        db = self.cache / f"{name}-{size}.cdb"
        key = f"render/{name}-{size}"
        if key not in self.results:
            log(f"render {db.name} (1500 views at {size}x{size})")
            r = run_measured(["render", str(volume), "-o", str(db), "--views", "grid:100x15",
                              "--size", str(size), "--no-depth", *self.cluster],
                             self.cache / "logs" / f"render-{name}-{size}.log")
            self.results[key] = {k: v for k, v in r.items() if k != "stdout"}
            self.save()
        return db

    def fit(self, key: str, db: Path, options: list[str]) -> Path | None:
        """Fit (or reuse) a model; None when the fit failed (e.g. an unreachable target)."""
        model = self.cache / f"{key}.ecs"
        rkey = f"fit/{key}"
        if rkey not in self.results or ("error" not in self.results[rkey]
                                        and not model.exists()):
            log(f"fit {key}: {' '.join(options)}")
            r = run_measured(["fit", str(db), "-o", str(model), *options, "--no-standalone",
                              *self.cluster],
                             self.cache / "logs" / f"fit-{key}.log", allow_fail=True)
            self.results[rkey] = {"options": options, **r}
            self.save()
        if "error" in self.results[rkey]:
            log(f"fit {key} failed: {self.results[rkey]['error']}")
            return None
        return model

    def evaluate(self, key: str, model: Path, views: str, report: bool = True) -> dict:
        rkey = f"evaluate/{key}"
        if rkey not in self.results:
            log(f"evaluate {key} on {views}")
            args = ["evaluate", str(model), "--views", views, "--json", *self.evaluate_options]
            if report:
                args += ["--report", str(self.cache / "reports" / key)]
            r = run_measured(args, self.cache / "logs" / f"evaluate-{key}.log")
            summary = json.loads(r["stdout"])
            self.results[rkey] = {"wall_s": r["wall_s"], "peak_rss_mb": r["peak_rss_mb"],
                                  "summary": summary}
            self.save()
        return self.results[rkey]["summary"]


def _f(v: float | None, d: int = 3) -> str:
    return "–" if v is None else f"{v:.{d}f}"


def markdown(results: dict, datasets: list[str], size: int = 512) -> str:
    """The result tables of docs/paper-reproduction.md."""
    out = ["### Feasibility study (300 × 300, 1500 training views, 100 components)", "",
           "| dataset | method | dims/cell | eigenspace | bytes/view | PSNR | SSIM | FLIP | "
           "JPEG SSIM / FLIP | WebP SSIM / FLIP | nearest SSIM / FLIP | fit s / MB |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name in datasets:
        for method in ("standard", "cell20"):
            ev = results.get(f"evaluate/{name}-300-{method}", {}).get("summary")
            fit = results.get(f"fit/{name}-300-{method}", {})
            if not ev:
                continue
            out.append(
                f"| {LABEL[name]} | {method} | {ev['components_per_cell']:.1f} | "
                f"{ev['eigenspace_bytes'] / 1e6:.1f} MB | {ev['pca']['bytes_per_view']:.0f} | "
                f"{_f(ev['pca']['psnr'], 2)} | {_f(ev['pca']['ssim'], 4)} | "
                f"{_f(ev['pca']['flip'], 4)} | {_f(ev['jpeg']['ssim'], 4)} / "
                f"{_f(ev['jpeg']['flip'], 4)} | {_f(ev['webp']['ssim'], 4)} / "
                f"{_f(ev['webp']['flip'], 4)} | {_f(ev['nearest']['ssim'], 4)} / "
                f"{_f(ev['nearest']['flip'], 4)} | {fit.get('wall_s', '–')} / "
                f"{fit.get('peak_rss_mb', '–')} |")
    out += ["", f"### Adaptive-cell study ({size} × {size}, cells 30 × 30)", "",
            "| dataset | setting | T | dims/cell | eigenspace | bytes/view | PSNR | SSIM | FLIP "
            "| JPEG (q) SSIM / FLIP | WebP (q) SSIM / FLIP | nearest SSIM / FLIP | int8 loss dB "
            "| fit s / MB |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name in datasets:
        prefix = f"fit/{name}-{size}-"
        found = sorted(k[len(prefix):] for k in results if k.startswith(prefix + "target-"))
        for setting in ["paper-T", *found]:
            key = f"{name}-{size}-{setting}"
            ev = results.get(f"evaluate/{key}", {}).get("summary")
            fit = results.get(f"fit/{key}", {})
            if "error" in fit:
                out.append(f"| {LABEL[name]} | {setting} | {fit['error']} |" + " |" * 11)
                continue
            if not ev:
                continue
            j, w, n = ev["jpeg"], ev["webp"], ev["nearest"]
            out.append(
                f"| {LABEL[name]} | {setting} | {_f(ev['threshold'], 4)} | "
                f"{ev['components_per_cell']:.2f} | {ev['eigenspace_bytes'] / 1e6:.1f} MB | "
                f"{ev['pca']['bytes_per_view']:.0f} | {_f(ev['pca']['psnr'], 2)} | "
                f"{_f(ev['pca']['ssim'], 4)} | {_f(ev['pca']['flip'], 4)} | "
                f"({j['quality']:.0f}) {_f(j['ssim'], 4)} / {_f(j['flip'], 4)} | "
                f"({w['quality']:.0f}) {_f(w['ssim'], 4)} / {_f(w['flip'], 4)} | "
                f"{_f(n['ssim'], 4)} / {_f(n['flip'], 4)} | "
                f"{_f((ev.get('int8') or {}).get('train_loss_db'), 3)} | "
                f"{fit.get('wall_s', '–')} / {fit.get('peak_rss_mb', '–')} |")
    return "\n".join(out) + "\n"


def docs_images(cache: Path, dest: Path, datasets: list[str], setting: str,
                size: int = 512) -> None:
    """Small copies of the figures for the docs (each < 300 KB)."""
    from PIL import Image

    dest.mkdir(parents=True, exist_ok=True)
    for name in datasets:
        report = cache / "reports" / f"{name}-{size}-{setting}"
        if not (report / "rd.png").exists():
            continue
        with Image.open(report / "rd.png") as im:
            im.convert("RGB").save(dest / f"repro-{name}-rd.png", optimize=True)
        view = report / "views" / "view_00.png"
        if view.exists():
            with Image.open(view) as im:
                im = im.convert("RGB")
                width = 1600
                im = im.resize((width, round(im.height * width / im.width)), Image.LANCZOS)
                im.save(dest / f"repro-{name}-views.jpg", quality=85, optimize=True)
    for p in dest.glob("repro-*"):
        if p.stat().st_size > 300_000:
            log(f"warning: {p} is {p.stat().st_size} bytes (> 300 KB)")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cache", default="/work/cache/repro", type=Path,
                        help="where databases, models and reports go (default /work/cache/repro)")
    parser.add_argument("--views", type=int, default=100, help="novel views per evaluation")
    parser.add_argument("--datasets", default="tooth,vismale_head")
    parser.add_argument("--targets", default="ssim=0.95",
                        help="comma-separated fit --target values for the adaptive study")
    parser.add_argument("--docs-images", type=Path, default=None,
                        help="copy small figures here (e.g. docs/images)")
    parser.add_argument("--studies", default="feasibility,adaptive",
                        help="which studies to run (default feasibility,adaptive)")
    parser.add_argument("--size", type=int, default=512,
                        help="image size of the adaptive study (default 512; the paper's 1080)")
    parser.add_argument("--scheduler", default=None,
                        help="run render and fit on a Dask cluster: an address or local:N")
    parser.add_argument("--evaluate-options", default="",
                        help="extra options for every evaluate, e.g. '--webp-db-quality 0 "
                             "--motion-deadline 0 --rd-views 0' to skip baselines at 1080")
    args = parser.parse_args()
    datasets = [d for d in args.datasets.split(",") if d]
    targets = [t for t in args.targets.split(",") if t]
    cache = args.cache
    cache.mkdir(parents=True, exist_ok=True)
    results_path = cache / "results.json"
    results = json.loads(results_path.read_text()) if results_path.exists() else {}
    study = Study(cache, args.views, results, args.scheduler, shlex.split(args.evaluate_options))
    size = args.size
    test_views = paper_test_views(cache / f"paper-test-views-{args.views}.csv", args.views)
    for name in datasets:
        volume = shared_volume(name)
        if volume is None:
            log(f"skipping {name}: ../shared/data is absent")
            continue
        if "feasibility" in args.studies:
            db = study.database(name, volume, 300)
            for method, options in (("standard", ["--method", "standard", "--components", "100"]),
                                    ("cell20", ["--method", "cell", "--cell", "20",
                                                "--components", "100"])):
                model = study.fit(f"{name}-300-{method}", db, options)
                study.evaluate(f"{name}-300-{method}", model, str(test_views))
        if "adaptive" not in args.studies:
            continue
        db = study.database(name, volume, size)
        model = study.fit(f"{name}-{size}-paper-T", db, ["--method", "adaptive", "--cell", "30",
                                                      "--threshold", str(PAPER_T[name])])
        study.evaluate(f"{name}-{size}-paper-T", model, f"random:{args.views}")
        for target in targets:
            key = f"{name}-{size}-target-{target}"
            model = study.fit(key, db, ["--method", "adaptive", "--cell", "30",
                                        "--target", target])
            if model is not None:
                study.evaluate(key, model, f"random:{args.views}")
    table = markdown(results, datasets, size)
    (cache / "results.md").write_text(table)
    print(table)
    if args.docs_images is not None:
        docs_images(cache, args.docs_images, datasets, "paper-T", size)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
