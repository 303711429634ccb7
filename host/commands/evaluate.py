"""``eigencast evaluate``: score a model's device frames on novel views against fresh ray-casts."""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path

from host.errors import EigencastError

HELP = ("ray-cast novel views with the model's own render settings and compare the device "
        "reconstruction, equal-bytes JPEG/WebP and the nearest training view (PSNR, SSIM, FLIP)")

#: Files and folders a report folder holds; an existing folder with anything else is refused.
REPORT_ENTRIES = {"index.html", "rd.png", "per_view.png", "summary.json", "views"}
_FOREIGN_ONLY = ("tf", "size", "projection", "fov", "background", "frame", "samples", "step")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from host.commands._render_options import add_render_arguments
    from host.render.transfer import add_transfer_function_argument
    from host.volume import add_volume_arguments

    parser.add_argument("model", metavar="MODEL.ecs")
    parser.add_argument("volume", metavar="VOLUME", nargs="?",
                        help="the volume the model was rendered from (a file, folder or "
                             "builtin:NAME; default: the source recorded in the model)")
    parser.add_argument("--views", default="random:100", metavar="SPEC",
                        help="novel views: random:N[:SEED], fibonacci:N, grid:NPHIxNTHETA, "
                             "list:P,T;... or a CSV with phi,theta (default random:100)")
    parser.add_argument("--report", metavar="DIR", help="write an HTML report (index.html + PNGs)")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object with the results on stdout")
    parser.add_argument("--key", metavar="KEYFILE", help="verify the image's tag with this key")
    parser.add_argument("--rd-views", type=int, default=8, metavar="N",
                        help="views used by the rate-distortion sweep (default 8; 0 skips it)")
    parser.add_argument("--samples-shown", type=int, default=4, metavar="N",
                        help="views shown side by side in the report (default 4)")
    parser.add_argument("--no-nearest", action="store_true",
                        help="skip the nearest-training-view comparison")
    parser.add_argument("--motion-deadline", type=float, default=1000.0 / 30.0, metavar="MS",
                        help="pca_motion: the frame deadline of serve --scores motion, in "
                        "milliseconds (default 33; 0: skip pca_motion)")
    parser.add_argument("--webp-db-quality", type=int, default=80, metavar="Q",
                        help="the on-device image database baseline (webp_db): every training "
                             "view stored as WebP at quality Q and blended with the model's "
                             "interpolation weights; 0 skips it (default 80)")
    parser.add_argument("--metric-workers", type=int, metavar="N",
                        help="processes computing the metrics alongside the ray-caster "
                             "(default: 2 on a multi-core machine; 0 computes them inline)")
    add_volume_arguments(parser)
    add_transfer_function_argument(parser)
    add_render_arguments(parser)
    # render options only apply to models whose database recorded no settings: detect them
    parser.set_defaults(size=None, projection=None, fov=None, background=None, frame=None)


def _check_report_folder(path: Path) -> None:
    if path.exists():
        if not path.is_dir():
            raise EigencastError(f"--report {path}: exists and is not a folder")
        foreign = sorted(p.name for p in path.iterdir() if p.name not in REPORT_ENTRIES)
        if foreign:
            raise EigencastError(
                f"--report {path}: the folder holds files that are not an eigencast report "
                f"({', '.join(foreign[:3])}); choose a new or empty folder"
            )
    elif not path.parent.exists():
        raise EigencastError(f"--report {path}: parent folder {path.parent} does not exist")


def _scene(args: argparse.Namespace, model):  # noqa: ANN001
    from host.commands._render_options import settings_from_args
    from host.render.settings import RenderSettings, ViewRenderer

    what = str(args.model)
    if model.render_settings:
        given = [f"--{name}" for name in _FOREIGN_ONLY
                 if getattr(args, name, None) not in (None, False)]
        if args.no_shading:
            given.append("--no-shading")
        if given:
            raise EigencastError(
                f"{what} records its render settings; {', '.join(given)} apply only to models "
                "fitted from databases of other tools"
            )
        settings = RenderSettings.from_record(model.render_settings, what=what)
        return ViewRenderer.open(settings, args.volume, args, workers=args.workers, what=what)
    # a foreign database: the user states how its images were made
    if args.volume is None or args.tf is None:
        raise EigencastError(
            f"{what} was fitted from a database without eigencast render settings; give "
            "VOLUME and --tf (and --projection/--fov/--background/--frame/--samples if they "
            "differ from the defaults) so novel views can be ray-cast like its images"
        )
    from host.commands._render_options import parse_size
    from host.volume import volume_from_args

    h, w = model.image.image_shape
    size = parse_size(args.size) if args.size else (w, h)
    if size != (w, h):
        raise EigencastError(f"--size {args.size}: the model's images are {w}x{h}")
    args.projection = args.projection or "perspective"
    args.fov = 30.0 if args.fov is None else args.fov
    args.background = args.background or "0,0,0"
    args.frame = args.frame or "visible"
    volume = volume_from_args(args.volume, args)
    record = settings_from_args(args, volume, size)
    settings = RenderSettings.from_record(record, what=what)
    return ViewRenderer(settings, volume, workers=args.workers, what=what)


def run(args: argparse.Namespace) -> int:
    from host.evaluate import evaluate_model
    from host.fit.model import HostModel
    from host.render.camera import parse_view_set
    from protocol.keys import load_key

    if args.rd_views < 0 or args.samples_shown < 0:
        raise EigencastError("--rd-views and --samples-shown must be >= 0")
    if not (0 <= args.motion_deadline < 1e6):
        raise EigencastError(f"--motion-deadline {args.motion_deadline}: must be >= 0 "
                             "milliseconds (0: skip pca_motion)")
    if not 0 <= args.webp_db_quality <= 100:
        raise EigencastError(f"--webp-db-quality {args.webp_db_quality}: must be within 0..100 "
                             "(0 skips the WebP database baseline)")
    if args.metric_workers is not None and not 0 <= args.metric_workers <= 64:
        raise EigencastError(f"--metric-workers {args.metric_workers}: must be within 0..64")
    views = parse_view_set(args.views)
    report = Path(args.report) if args.report else None
    if report is not None:
        _check_report_folder(report)
    model = HostModel.load(args.model, key=load_key(args.key) if args.key else None)
    scene = _scene(args, model)
    evaluation = evaluate_model(
        model, scene, views.views, nearest=not args.no_nearest, rd_views=args.rd_views,
        sample_views=args.samples_shown if report is not None else 0,
        metric_workers=args.metric_workers,
        webp_db_quality=args.webp_db_quality or None,
        motion_deadline_s=args.motion_deadline / 1000.0 or None,
        info={"view_spec": views.spec},
    )
    if report is not None:
        _write_report_atomically(evaluation, report)
    summary = evaluation.summary()
    if args.json:
        print(json.dumps(summary, allow_nan=False))
    else:
        print(_text_summary(summary))
        if report is not None:
            print(f"report: {report / 'index.html'}")
    return 0


def _write_report_atomically(evaluation, folder: Path) -> None:  # noqa: ANN001
    from host.evaluate.report import write_report

    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    try:
        write_report(evaluation, tmp)
        if folder.exists():
            old = folder.with_name(f".{folder.name}.old-{os.getpid()}")
            os.replace(folder, old)
            os.replace(tmp, folder)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, folder)
        os.chmod(folder, 0o755)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _text_summary(s: dict) -> str:
    from host.evaluate import METHODS

    def f(v, d=3):  # noqa: ANN001
        return "-" if v is None else f"{v:.{d}f}"

    t = s["threshold"]
    lines = [
        f"{s['method']} model, T={t if t is not None else '-'}, "
        f"{s['components_per_cell']:.2f} components/cell, eigenspace "
        f"{s['eigenspace_bytes'] / 1e6:.2f} MB, {s['views']} novel views "
        f"({s.get('view_spec')}), score step {s['score_step']:.4g}",
        f"{'method':<11} {'bytes/view':>10} {'PSNR':>7} {'SSIM':>7} {'FLIP':>7}",
    ]
    lines[-1] += f" {'SSIM obj':>8} {'FLIP obj':>8}"
    for m in METHODS:
        if m in s:
            r = s[m]
            lines.append(f"{m:<11} {r['bytes_per_view']:>10.0f} {f(r['psnr'], 2):>7} "
                         f"{f(r['ssim'], 4):>7} {f(r['flip'], 4):>7} "
                         f"{f(r.get('ssim_object'), 4):>8} {f(r.get('flip_object'), 4):>8}")
    if "pca_motion" in s:
        mo = s["pca_motion"]
        lines.append(f"pca_motion: the frame serve --scores motion sends during a "
                     f"{mo['step_deg']:g} deg/frame drag, stride {mo['stride']:.0f} at a "
                     f"{mo['deadline_ms']:.0f} ms deadline on this machine; bytes/view = its "
                     "delta packet")
    if "pca_predict" in s:
        lines.append("pca_predict: what serve --scores predict makes a predicting device show "
                     "first at rest (its own prediction + the host's step-x2 correction); "
                     "bytes/view = the correction packet. After 0.15 s at rest serve sharpens "
                     "it to pca_render's quality (a second correction at the model's step)")
    if "webp_db" in s:
        db = s["webp_db"]
        lines.append(f"webp_db: training views as WebP q{db['quality']:.0f}, device storage "
                     f"{db['storage_bytes'] / 1e6:.2f} MB"
                     f"{' (estimated)' if db.get('storage_estimated') else ''} vs eigenspace "
                     f"image {s['eigenspace_bytes'] / 1e6:.2f} MB")
    if "pca_warp" in s:
        lines.append("pca_warp: what eigencast-device --standalone shows with this image's "
                     "depth (the 4 neighbouring training views warped by depth, no packets)")
    int8 = s.get("int8") or {}
    if int8.get("train_loss_db") is not None:
        lines.append(f"int8 loss vs float (fit, training views): {int8['train_loss_db']:.3f} dB")
    print("timing (s): " + ", ".join(f"{k} {v:.1f}" for k, v in s["timing_s"].items()),
          file=sys.stderr)
    return "\n".join(lines)
