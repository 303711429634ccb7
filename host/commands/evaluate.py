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

HELP = ("ray-cast novel views with the model's own render settings and compare what the device "
        "shows (its own frame, served at rest and while moving, and at rest each refinement "
        "layer up to the exact frame) with JPEG/WebP/AVIF and the nearest training view "
        "(PSNR, SSIM, FLIP, blockiness)")

#: Files and folders a report folder holds; an existing folder with anything else is refused.
REPORT_ENTRIES = {"index.html", "rd.png", "per_view.png", "rest.png", "summary.json", "views"}
_FOREIGN_ONLY = ("tf", "size", "projection", "fov", "background", "frame", "samples", "step",
                 "lighting")


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
    parser.add_argument("--look", metavar="NAME",
                        help="evaluate this look of an image with several (a name or an index; "
                             "default: each look in turn, each against ray-casts with its own "
                             "render settings)")
    parser.add_argument("--rd-views", type=int, default=8, metavar="N",
                        help="views used by the rate-distortion sweep (default 8; 0 skips it)")
    parser.add_argument("--rd-codecs-only", action="store_true",
                        help="the rate-distortion sweep codes only JPEG/WebP/AVIF (whose curves "
                             "give the bytes they need for the served frames' quality), not "
                             "the model's truncations (much faster)")
    parser.add_argument("--samples-shown", type=int, default=4, metavar="N",
                        help="views shown side by side in the report (default 4)")
    parser.add_argument("--no-nearest", action="store_true",
                        help="skip the nearest-training-view comparison")
    parser.add_argument("--motion-deadline", type=float, default=1000.0 / 30.0, metavar="MS",
                        help="pca_motion: serve's frame deadline while the view moves, in "
                        "milliseconds (default 33; 0: skip pca_motion)")
    parser.add_argument("--motion-stride", type=int, metavar="S",
                        help="pca_motion: ray-cast every S-th pixel instead of the stride the "
                             "deadline picks on this machine (0: none, the device's own "
                             "frame); figures that do not depend on the machine's load")
    parser.add_argument("--motion-slowdown", type=float, default=1.0, metavar="N",
                        help="pca_motion: pick the stride as a host whose ray-casts take N "
                             "times longer would (default 1)")
    parser.add_argument("--webp-db-quality", type=int, default=80, metavar="Q",
                        help="the on-device image database baseline (webp_db): every training "
                             "view stored as WebP at quality Q and blended with the model's "
                             "interpolation weights; 0 skips it (default 80)")
    parser.add_argument("--metric-workers", type=int, metavar="N",
                        help="processes computing the metrics alongside the ray-caster "
                             "(default: 2 on a multi-core machine; 0 computes them inline)")
    add_volume_arguments(parser)
    add_render_arguments(parser, foreign=True)
    foreign = next(g for g in parser._action_groups if g.title.startswith("rendering a model"))
    add_transfer_function_argument(foreign, foreign=True)
    # render options only apply to models whose database recorded no settings: detect them
    parser.set_defaults(projection=None, fov=None, background=None, frame=None)


def _check_report_folder(path: Path, looks: tuple[str, ...] = ()) -> None:
    if path.exists():
        if not path.is_dir():
            raise EigencastError(f"--report {path}: exists and is not a folder")
        allowed = REPORT_ENTRIES | set(looks)
        foreign = sorted(p.name for p in path.iterdir() if p.name not in allowed)
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
                f"{what} records its render settings and evaluate ray-casts with them: "
                f"{', '.join(given)} apply only to a model fitted from another tool's database"
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
    if args.motion_stride is not None and not 0 <= args.motion_stride <= 64:
        raise EigencastError(f"--motion-stride {args.motion_stride}: must be within 0..64")
    if not (1.0 <= args.motion_slowdown <= 1e4):
        raise EigencastError(f"--motion-slowdown {args.motion_slowdown}: must be within "
                             "1..10000")
    if not 0 <= args.webp_db_quality <= 100:
        raise EigencastError(f"--webp-db-quality {args.webp_db_quality}: must be within 0..100 "
                             "(0 skips the WebP database baseline)")
    if args.metric_workers is not None and not 0 <= args.metric_workers <= 64:
        raise EigencastError(f"--metric-workers {args.metric_workers}: must be within 0..64")
    views = parse_view_set(args.views)
    report = Path(args.report) if args.report else None
    key = load_key(args.key) if args.key else None
    model = HostModel.load(args.model, key=key, look=args.look)
    looks = [model.look] if args.look is not None or not model.looks else list(model.looks)
    if report is not None:
        _check_report_folder(report, tuple(looks) if len(looks) > 1 else ())
    from host.link.layers import RestPlanner

    summaries = {}
    for name in looks:
        if name != model.look:
            model = HostModel.load(args.model, key=key, look=name)
        scene = _scene(args, model)
        # the resting views' layers as serve plans them (its default targets, exact at the end)
        planner = RestPlanner(model.digest)
        evaluation = evaluate_model(
            model, scene, views.views, nearest=not args.no_nearest, rd_views=args.rd_views,
            sample_views=args.samples_shown if report is not None else 0,
            metric_workers=args.metric_workers,
            webp_db_quality=args.webp_db_quality or None,
            motion_deadline_s=args.motion_deadline / 1000.0 or None,
            motion_stride=args.motion_stride, motion_slowdown=args.motion_slowdown,
            rd_pca=not args.rd_codecs_only, rest_planner=planner,
            info={"view_spec": views.spec, **({"look": name} if name else {})},
        )
        folder = None
        if report is not None:
            folder = report if len(looks) == 1 else report / name
            if folder is not report:
                report.mkdir(exist_ok=True)
                _check_report_folder(folder)
            _write_report_atomically(evaluation, folder)
        summary = evaluation.summary()
        summaries[name] = summary
        if not args.json:
            if name is not None:
                print(f"look {name}:")
            print(_text_summary(summary))
            if folder is not None:
                print(f"report: {folder / 'index.html'}")
    if args.json:
        out = (summaries[looks[0]] if len(looks) == 1 else
               {"looks": summaries, "look_names": looks})
        print(json.dumps(out, allow_nan=False))
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


_CODEC_NAMES = {"webp": "WebP", "avif": "AVIF"}


def _vs_own(r: dict) -> str:
    return (f"object SSIM {r['gain_over_own']:+.4f} over the own frame on average, worst view "
            f"{r['worst_gain_over_own']:+.4f}, {r['views_below_own']} views more than 0.01 "
            "below it") if r.get("gain_over_own") is not None else "-"


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
    if "pca_warp" in s:
        own = "depth warp" if s["pca_warp"].get("own_frame") == "warp" else "score blend"
        lines.append(f"pca_warp: the device's own frame of every view (its {own} of the "
                     "neighbouring training views), shown at once, no bytes")
    if "pca_predict" in s:
        p = s["pca_predict"]
        lines.append(f"pca_predict: served, at rest: the own frame plus the complete "
                     f"correction at the model's step; bytes/view = the correction packet; "
                     f"{_vs_own(p)}")
    if "pca_motion" in s:
        mo = s["pca_motion"]
        how = ("served, while moving: the own frame plus the sparse correction"
               if "pca_predict" in s else "the sparse ray-cast's scores as a delta packet")
        stride = int(mo["stride"])
        lines.append(f"pca_motion: {how} during a {mo['step_deg']:g} deg/frame drag, "
                     f"stride {stride if stride else 'none (the own frame)'} "
                     + ("given" if mo.get("stride_given") else
                        f"at a {mo['deadline_ms']:.0f} ms deadline on this machine"
                        + (f", ray-casts {mo['slowdown']:g}x slower"
                           if mo.get("slowdown", 1) != 1 else ""))
                     + "; bytes/view = as streamed"
                     + (f"; {_vs_own(mo)}" if "views_below_own" in mo else ""))
    rest = s.get("rest")
    if rest:
        parts = []
        for name, r in rest["stages"].items():
            ratio = (r.get("x_webp") or {}).get("median")
            parts.append(f"{name} {f(r['ssim_object'], 4)} at {f(r['bytes'], 0)} B"
                         + (f" ({ratio:.2f}x WebP)" if ratio else ""))
        exact = rest["stages"].get("exact")
        if exact:
            parts.append(f"exact {f((exact['x_webp_lossless'] or {}).get('median'), 2)}x "
                         "WebP lossless")
        lines.append(f"rest ({rest['views']} views, correction skipped on "
                     f"{rest['correction_skipped']}; medians of object SSIM at cumulative "
                     "bytes): " + "; ".join(parts))
    for m in ("pca_predict", "pca_motion"):
        eq = (s.get(m) or {}).get("equal_quality")
        if eq:
            parts = []
            for codec in ("webp", "avif"):
                c = eq.get(codec) or {}
                parts.append(f"{_CODEC_NAMES[codec]} needs {f(c.get('bytes_for_ssim'), 0)} B for "
                             f"its object SSIM and reaches {f(c.get('ssim_at_bytes'), 4)} at "
                             "its bytes")
            lines.append(f"{m} on {eq['views']} views (SSIM obj {f(eq['ssim_object'], 4)} at "
                         f"{f(eq['bytes_per_view'], 0)} B): " + "; ".join(parts))
    blocks = {m: s[m]["blockiness"] for m in METHODS if m in s and s[m].get("blockiness")}
    if blocks:
        lines.append("blockiness (cell borders / inside, object pixels): ray-cast "
                     f"{f(s.get('raycast_blockiness'))}, "
                     + ", ".join(f"{m} {f(v)}" for m, v in blocks.items()))
    if "webp_db" in s:
        db = s["webp_db"]
        lines.append(f"webp_db: training views as WebP q{db['quality']:.0f}, device storage "
                     f"{db['storage_bytes'] / 1e6:.2f} MB"
                     f"{' (estimated)' if db.get('storage_estimated') else ''} vs eigenspace "
                     f"image {s['eigenspace_bytes'] / 1e6:.2f} MB")
    int8 = s.get("int8") or {}
    if int8.get("train_loss_db") is not None:
        lines.append(f"int8 loss vs float (fit, training views): {int8['train_loss_db']:.3f} dB")
    print("timing (s): " + ", ".join(f"{k} {v:.1f}" for k, v in s["timing_s"].items()),
          file=sys.stderr)
    return "\n".join(lines)
