"""``eigencast fit``: fit an eigenspace to a Cinema database and write MODEL.ecs.

With ``--target METRIC=VALUE`` the setting (threshold T for adaptive, components per cell
otherwise, and the score step) is chosen automatically: the model is fitted once at the top of
the search range and truncated to cheaper settings, each measured on held-out views through
the device's path (`host.evaluate.target`). Held-out views, in order of preference:
``--test-db``; views ray-cast with the database's recorded settings (``--holdout`` spec) when
its volume can be loaded (``--volume`` or the recorded source); else views held out of the
database itself (the search model is fitted without them, the written model is refitted on
every view).

Several databases of the same views (other transfer functions or lightings) make one image
with a look per database (`host.fit.looks`: each look its own eigenspace and table, fitted
as its database alone would be; the depth shared where the looks' depth is the same);
``--look-names`` names them.
"""

from __future__ import annotations

import argparse
import functools
import math
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

from host.errors import EigencastError
from host.fit.model import (
    HostModel,
    auto_score_step,
    build_image,
    fit_database,
    save_model,
    stack_cache,
    subset_database,
    truncate_eigenspace,
)
from host.fit.quantize import DEFAULT_BIT_BUDGET
from host.render.cinema import CinemaDB, with_recorded_lighting

HELP = "fit a PCA eigenspace to a Cinema database and write the eigenspace image (MODEL.ecs)"

DEFAULT_THRESHOLD = 0.98
#: Threshold fitted (the search's upper bound) when --target is given without --threshold.
TARGET_FIT_THRESHOLD = 0.999
DEFAULT_HOLDOUT = "random:30:1"
#: What the depth eigenspace and the standalone table cost, as ``fit --help`` says it
#: (BENCHMARKS.md, "Depth by default": the shared tooth and head, 1500 views at 128 and 256).
TABLE_COST = "30-35 %% of the device image at 1500 views, no fit time"
DEPTH_COST = "8-40 %% of the device image and 10-17 %% more fit time"
#: Render settings that may differ between a training and a test database.
_VIEW_KEYS = ("views", "eigencast")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from host.volume import add_volume_arguments

    parser.add_argument("database", metavar="DB.cdb", nargs="+",
                        help="Cinema Spec D database folder; several databases of the same "
                             "views (other transfer functions or lightings) make one image "
                             "with a look per database, the first shown first")
    parser.add_argument("--look-names", metavar="A,B,...",
                        help="names of the looks, one per database (default: what sets the "
                             "databases apart: their lighting or transfer function)")
    parser.add_argument("-o", "--output", required=True, metavar="MODEL.ecs")
    parser.add_argument("--method", choices=("standard", "cell", "adaptive"), default="adaptive",
                        help="eigenspace layout (default adaptive)")
    parser.add_argument("--cell", type=int, default=30, metavar="S",
                        help="cell size in pixels for cell/adaptive (default 30)")
    parser.add_argument("--components", type=int, default=100, metavar="K",
                        help="components per cell (standard/cell), cap for adaptive "
                             "(default 100)")
    parser.add_argument("--threshold", type=float, default=None, metavar="T",
                        help=f"adaptive: cumulative variance each cell keeps (default "
                             f"{DEFAULT_THRESHOLD}; with --target the search's upper bound, "
                             f"default {TARGET_FIT_THRESHOLD})")
    parser.add_argument("--score-step", type=float, metavar="S",
                        help="score quantization step in orthonormal coordinates "
                             "(default: the step whose rounding adds MSE 1.0 to a mean cell, "
                             "docs/rate-distortion-packets.md; with --target it is searched)")
    parser.add_argument("--bit-budget", type=float, default=DEFAULT_BIT_BUDGET, metavar="F",
                        help="eigenimage bit allocation: low-variance components get fewer "
                             "levels (2..8 bits) while the added error stays within F times "
                             f"the model's own residual MSE (default {DEFAULT_BIT_BUDGET}; "
                             "0: 8 bits for all)")
    parser.add_argument("--key", metavar="KEYFILE", help="sign the image with this device key")
    table = parser.add_mutually_exclusive_group()
    table.add_argument("--no-standalone", dest="standalone", action="store_false",
                       default=None,
                       help="leave out the training views' scores (the standalone table: "
                            f"{TABLE_COST}; implies --no-depth): a device then cannot show a "
                            "view by itself, neither with no host (eigencast-device "
                            "--standalone) nor at once while the host's frame is on its way")
    table.add_argument("--standalone", dest="standalone", action="store_true",
                       help="store the standalone table (the default; kept for old scripts)")
    depth = parser.add_mutually_exclusive_group()
    depth.add_argument("--no-depth", dest="depth", action="store_false", default=None,
                       help="leave out the depth eigenspace of the database's depth maps "
                            f"(it costs {DEPTH_COST}): a device then blends its neighbouring "
                            "views (edges show twice) where it would warp them by their depth")
    depth.add_argument("--depth", dest="depth", action="store_true",
                       help="require the depth eigenspace (the default stores it when the "
                            "database has depth maps and says so when it has none)")
    parser.add_argument("--depth-threshold", type=float, default=None, metavar="T",
                        help="cumulative variance each depth cell keeps (default: the "
                             "colour's --threshold)")
    parser.add_argument("--interpolation", choices=("auto", "bilinear", "bicubic", "barycentric"),
                        default="auto",
                        help="how novel views' scores are interpolated between training views "
                             "(auto: the measured best for the view set; see "
                             "docs/design-notes.md)")
    parser.add_argument("--incomplete", action="store_true",
                        help="fit an interrupted render's views as they are (refused by "
                             "default: its views cover part of the view set, and views outside "
                             "it come out blurred)")
    parser.add_argument("--cache", metavar="DIR",
                        help="where to keep the image stack the fit streams from, uncompressed "
                             "(3 bytes per pixel per view: 330 MB for 1500 views at 256 px, "
                             "several times the PNGs), so that the next fit with the same "
                             "--cell starts at once; default DB.cdb/.eigencast-cache, which "
                             "holds the last fit's stack only and may be deleted at any time")
    parser.add_argument("--no-cache", action="store_true",
                        help="do not keep the image stack: build it in a temporary folder "
                             "and delete it after the fit")
    g = parser.add_argument_group("automatic setting (--target)")
    g.add_argument("--target", metavar="METRIC=VALUE",
                   help="pick the cheapest setting (fewest score bytes per view) whose held-out "
                        "views reach this quality: ssim=0.95, flip=0.05 or psnr=35")
    g.add_argument("--holdout", default=DEFAULT_HOLDOUT, metavar="SPEC",
                   help=f"held-out views to ray-cast (a view-set spec, default {DEFAULT_HOLDOUT})"
                        "; without a loadable volume, that many views of DB.cdb are held out")
    g.add_argument("--test-db", metavar="T.cdb",
                   help="a database of held-out views (same image size and render settings)")
    g.add_argument("--volume", metavar="VOLUME",
                   help="the volume to ray-cast held-out views from (default: the source the "
                        "database records)")
    add_volume_arguments(parser)
    from host.cluster import add_scheduler_argument

    add_scheduler_argument(parser)


def run(args: argparse.Namespace) -> int:
    from host.cluster import open_cluster

    if args.no_cache and args.cache:
        raise EigencastError("--cache DIR keeps the image stack there, --no-cache keeps none: "
                             "pick one")
    temporary = None
    if args.no_cache:
        temporary = tempfile.mkdtemp(prefix="eigencast-stack-")
        args.cache = temporary
    cluster = open_cluster(args.scheduler)  # None: in-process; connects before the long fit
    try:
        return _run(args, cluster)
    finally:
        if cluster is not None:
            cluster.close()
        if temporary is not None:
            shutil.rmtree(temporary, ignore_errors=True)


def _run(args: argparse.Namespace, cluster) -> int:  # noqa: ANN001
    from protocol.keys import load_key

    target = None
    if args.target is not None:
        from host.evaluate.target import parse_target

        target = parse_target(args.target)
    elif args.test_db or args.volume:
        raise EigencastError("--test-db and --volume are used only with --target")
    threshold = args.threshold
    if threshold is None:
        threshold = TARGET_FIT_THRESHOLD if target is not None else DEFAULT_THRESHOLD
    if not 0.0 < threshold <= 1.0:
        raise EigencastError(f"--threshold {threshold}: must be within (0, 1]")
    if args.score_step is not None and not args.score_step > 0:
        raise EigencastError(f"--score-step {args.score_step}: must be positive")
    if not (math.isfinite(args.bit_budget) and args.bit_budget >= 0):
        raise EigencastError(f"--bit-budget {args.bit_budget}: must be a number >= 0")
    key = load_key(args.key) if args.key else None
    out = Path(args.output)
    if not out.parent.exists():
        raise EigencastError(f"{out.parent}: output folder does not exist")
    if len(args.database) > 1:
        return _fit_looks(args, cluster, threshold, target, key, out)
    if args.look_names is not None:
        raise EigencastError("--look-names names the looks of several databases; one was given")
    args.database = args.database[0]
    db = CinemaDB.open(args.database)
    _check_complete(db, args)
    depth_threshold = args.depth_threshold if args.depth_threshold is not None else threshold
    _choose_depth(args, db)
    if args.depth_threshold is not None and not args.depth:
        raise EigencastError("--depth-threshold is used only with depth (a database with "
                             "depth maps, without --no-depth)")
    if args.depth and not 0.0 < depth_threshold <= 1.0:
        raise EigencastError(f"--depth-threshold {depth_threshold}: must be within (0, 1]")
    _check_interpolation(args, db)
    options = _fit_options(args, threshold, cluster, args.cache)
    extra: dict = {}
    if target is None:
        model = fit_database(db, **options)
        score_step = args.score_step
    else:
        model, score_step, extra = _fit_to_target(args, db, target, options)
    image, annex = build_image(model, db, score_step=score_step, extra_provenance=extra,
                               interpolation=args.interpolation, bit_budget=args.bit_budget)
    standalone = _add_table(image, annex) if args.standalone else None
    depth = None
    if args.depth:
        from host.evaluate.splat_filter import choose_splat_tent
        from host.fit.depth import add_depth
        from host.fit.floor import add_noise_floor

        depth = add_depth(image, db, depth_threshold)
        depth["floor"] = add_noise_floor(image, db).summary()
        depth["splat"] = choose_splat_tent(image, db)
    save_model(out, image, annex, key=key)
    if standalone is not None:
        print(_standalone_line(out, standalone))
    if depth is not None:
        print(f"depth: {depth['components']} components ({depth['components_per_cell']:.2f}/"
              f"cell at T={depth['threshold']}), table noise {depth['score_mse']:.3g} mm², "
              f"{depth['raw_bytes'] / 1e6:.2f} MB raw ({depth['section']}); "
              f"synthesis {image.synthesis['method']}")
        print(_floor_line(depth["floor"]))
        print(_splat_line(depth["splat"]))
    device_bytes = image_device_bytes(out)
    annex_bytes = out.stat().st_size - device_bytes
    int8 = image.provenance["int8"]
    print(
        f"wrote {out}: {args.method}, {db.n_views} views at "
        f"{db.image_shape[1]}x{db.image_shape[0]}, {model.grid_shape_[0]}x"
        f"{model.grid_shape_[1]} cells, {model.n_components_.mean():.2f} components/cell "
        f"(K={int(model.n_components_.sum())}), device image {device_bytes / 1e6:.2f} MB"
        f"{', signed' if key else ''} + host annex {annex_bytes / 1e6:.2f} MB (float training "
        "scores and eigenvalues for serve and evaluate; never sent to the device); score "
        f"step {image.score_quantization['step']:.3g}; int8 loss {int8['train_loss_db']:.3f} dB"
    )
    if not args.no_cache:
        _say_cache(db, args.cache)
    return 0


def _check_interpolation(args: argparse.Namespace, db: CinemaDB) -> None:
    """Refuse, before the (long) fit, ``--interpolation bilinear|bicubic`` for views that
    are not a full phi x theta grid."""
    if args.interpolation in ("bilinear", "bicubic"):
        from device_runtime.interpolation import detect_grid

        reason = detect_grid(db.phi_deg, db.theta_deg)[1]
        if reason:
            raise EigencastError(f"--interpolation {args.interpolation} needs a full phi x theta "
                                 f"grid of views: {reason}; use auto or barycentric")


def _fit_options(args: argparse.Namespace, threshold: float, cluster,  # noqa: ANN001
                 cache_dir: str | Path | None) -> dict:
    """`fit_database`'s keyword arguments from the command's options (``cluster``: fit
    its cells there; None: in-process), its image stack kept in ``cache_dir``."""
    from host.cluster import fit_blocks  # no Dask import until a cluster is used

    return {"method": args.method, "cell": args.cell, "components": args.components,
            "threshold": threshold, "cache_dir": None if cache_dir is None else str(cache_dir),
            "fit_elsewhere": None if cluster is None else functools.partial(fit_blocks, cluster)}


def _add_table(image, annex: dict) -> dict:  # noqa: ANN001
    """Add the standalone table of the training scores in ``annex`` to ``image``; what
    `add_standalone_table` says of it."""
    from host.fit.model import ANNEX_EIGENVALUES, ANNEX_SCORES, add_standalone_table

    return add_standalone_table(image, annex[ANNEX_SCORES],
                                eigenvalues=annex.get(ANNEX_EIGENVALUES))


def _looks_depth(image, dbs: list, names: list[str], depth_threshold: float  # noqa: ANN001
                 ) -> list[str]:
    """The looks' depth (shared by the looks whose depth maps are the first's, else each
    its own), noise floor and splat filter, added to ``image``; the lines to print."""
    from device_runtime.looks import look_image
    from device_runtime.synthesis import DEPTH_DELTA_SECTION, DEPTH_SECTIONS, NOISE_FLOOR_SECTION
    from host.evaluate.splat_filter import choose_splat_tent
    from host.fit.depth import add_depth
    from host.fit.floor import add_noise_floor
    from host.fit.looks import add_look_sections, same_depth

    lines: list[str] = []
    depth = add_depth(image, dbs[0], depth_threshold)
    shared = [names[0]]
    for look in range(1, len(dbs)):
        if same_depth(dbs[0], dbs[look]):
            shared.append(names[look])
            continue
        view = look_image(image, look, decode=False)
        own = add_depth(view, dbs[look], depth_threshold)
        add_look_sections(image, look, view, (*DEPTH_SECTIONS, DEPTH_DELTA_SECTION))
        lines.append(f"look {names[look]}: its own depth (other depth maps than "
                     f"{names[0]}'s): {own['components']} components")
    lines.insert(0, f"depth: {depth['components']} components "
                    f"({depth['components_per_cell']:.2f}/cell at T={depth['threshold']}) "
                    f"shared by {', '.join(shared)}")
    for look, db in enumerate(dbs):
        view = image if look == 0 else look_image(image, look, decode=False)
        floor = add_noise_floor(view, db).summary()
        add_look_sections(image, look, view, (NOISE_FLOOR_SECTION,))
        view = image if look == 0 else look_image(image, look, decode=False)
        splat = choose_splat_tent(view, db)
        add_look_sections(image, look, view, ())
        lines.append(f"look {names[look]}: {_floor_line(floor)}")
        lines.append(f"look {names[look]}: {_splat_line(splat)}")
    return lines


def _fit_looks(args: argparse.Namespace, cluster, threshold: float, target, key,  # noqa: ANN001
               out: Path) -> int:
    """``fit A.cdb B.cdb ...``: one image with a look per database, each look an eigenspace
    of its own fitted as its database alone would be (`host.fit.looks`)."""
    from host.fit.looks import build_looks_image, check_same_views, look_names_for

    if target is not None:
        raise EigencastError("--target chooses the setting of one database; fit the looks "
                             "with --threshold (or --components)")
    dbs = [CinemaDB.open(path) for path in args.database]
    check_same_views(dbs)
    for db in dbs:
        _check_complete(db, args)
    names = look_names_for(dbs, args.look_names.split(",") if args.look_names else None)
    depth_threshold = args.depth_threshold if args.depth_threshold is not None else threshold
    want_depth = args.depth
    for path, db in zip(args.database, dbs):
        args.database, args.depth = path, want_depth
        _choose_depth(args, db)
        if not args.depth:
            break
    if args.depth_threshold is not None and not args.depth:
        raise EigencastError("--depth-threshold is used only with depth (databases with "
                             "depth maps, without --no-depth)")
    if args.depth and not 0.0 < depth_threshold <= 1.0:
        raise EigencastError(f"--depth-threshold {depth_threshold}: must be within (0, 1]")
    if args.cell < 1:
        raise EigencastError(f"--cell {args.cell!r}: must be a positive integer")
    _check_interpolation(args, dbs[0])  # (the looks' views are the same)
    parts, models = [], []
    for i, db in enumerate(dbs):
        print(f"look {names[i]} ({i + 1}/{len(dbs)}): fitting {db.path}", flush=True)
        cache = None if args.cache is None else Path(args.cache) / f"look{i}"
        model = fit_database(db, **_fit_options(args, threshold, cluster, cache))
        image, annex = build_image(model, db, score_step=args.score_step,
                                   interpolation=args.interpolation, bit_budget=args.bit_budget)
        if args.standalone:
            _add_table(image, annex)
        parts.append((image, annex))
        models.append(model)
    image, annex = build_looks_image(parts, dbs, names)
    lines = _looks_depth(image, dbs, names, depth_threshold) if args.depth else []
    save_model(out, image, annex, key=key)
    for line in lines:
        print(line)
    device_bytes = image_device_bytes(out)
    annex_bytes = out.stat().st_size - device_bytes
    per_look = ", ".join(f"{name} K={int(m.n_components_.sum())} "
                         f"({rec['int8']['train_loss_db']:.3f} dB int8 loss)"
                         for name, m, rec in zip(names, models, image.provenance["looks"]))
    print(f"wrote {out}: {len(dbs)} looks, each its own {args.method} eigenspace ({per_look}), "
          f"{dbs[0].n_views} views at {dbs[0].image_shape[1]}x{dbs[0].image_shape[0]}, "
          f"device image {device_bytes / 1e6:.2f} MB{', signed' if key else ''} + host annex "
          f"{annex_bytes / 1e6:.2f} MB")
    if not args.no_cache:
        for i, db in enumerate(dbs):
            _say_cache(db, None if args.cache is None else str(Path(args.cache) / f"look{i}"))
    return 0


def _say_cache(db: CinemaDB, cache_dir: str | None) -> None:
    """One line: where the image stack stays, its size, and how not to keep it."""
    folder = stack_cache(db, cache_dir)
    if not folder.is_dir():
        return
    size = sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())
    if size:
        print(f"kept the image stack this fit streamed from, {size / 1e6:.0f} MB, in {folder} "
              "so the next fit with the same --cell starts at once (--no-cache keeps none; "
              "deleting the folder is always safe)")


def _splat_line(splat: dict) -> str:
    """What `choose_splat_tent` found, in one line."""
    if not splat["views"]:
        return ("splat filter [1, 6, 1] (no theta row of three views to choose another on)")
    found = ", ".join(f"{t}: {s:.4f}" for t, s in splat["ssim"].items())
    return (f"splat filter [1, {splat['tent']}, 1], chosen on {splat['views']} training views "
            f"warped from their row neighbours (object SSIM by centre weight: {found})")


def _floor_line(floor: dict) -> str:
    """What `host.fit.floor.measure_noise_floor` found, in one line."""
    return (f"noise floor: in {floor['cells']} cells the warp paints pixels at or below a level "
            f"of {floor['median']:.0f} (median; at most {floor['max']}) black, measured on "
            f"{floor['views']} training views: the eigenspace's haze on the black background")


def _choose_depth(args: argparse.Namespace, db: CinemaDB) -> None:
    """Settle ``args.standalone`` and ``args.depth`` (None: the default) for ``db``.

    By default the image carries the standalone table and, when ``db`` has depth maps its
    framing allows, the depth eigenspace; without them one line says that the device will
    blend instead of warp, and how to get depth. ``--depth`` refuses a database without.
    """
    from host.render.cinema import depth_problem

    if args.standalone is False:
        if args.depth:
            raise EigencastError("--depth needs the standalone table: drop --no-standalone")
        args.depth = False
    args.standalone = True if args.standalone is None else args.standalone
    if args.depth is False:
        return
    framing = depth_problem(db.settings, db.image_shape) if db.settings else None
    cure = "render it perspective, on black, at an even size"
    if db.depth is None and db.settings is None:  # another tool's database
        problem, cure = "has no depth maps", ("render the volume with eigencast render, which "
                                              "stores depth")
    elif db.depth is None:
        problem = "has no depth maps" + (f", rendered with {framing}" if framing else "")
        if not framing:
            cure = "render it again with eigencast render, which stores depth unless --no-depth"
    else:
        problem = framing
    if problem is None:
        args.depth = True
        return
    if args.depth:
        raise EigencastError(f"{args.database}: --depth: {problem}; {cure}")
    args.depth = False
    print(f"{args.database}: {problem}; a device will blend neighbouring views instead of "
          f"warping them by depth ({cure})", file=sys.stderr)


def _check_complete(db: CinemaDB, args: argparse.Namespace) -> None:
    """Refuse an interrupted render (fewer views in data.csv than its view set) unless
    ``--incomplete``: a model of part of the view set blurs every view outside it."""
    expected = db.expected_views
    if expected is None or db.n_views >= expected:
        return
    missing = expected - db.n_views
    if args.incomplete:
        print(f"{db.path}: fitting {db.n_views} of the view set's {expected} views "
              f"(--incomplete; {missing} not rendered)", file=sys.stderr)
        return
    raise EigencastError(
        f"{db.path}: an interrupted render: {missing} of its {expected} views are missing "
        f"(data.csv lists {db.n_views}); rerun the same eigencast render command to render "
        "them, or pass --incomplete to fit the views it has"
    )


def _fit_to_target(args: argparse.Namespace, db: CinemaDB, target, options: dict):  # noqa: ANN001
    """Fit, search the target on held-out views, return (final model, score step, provenance)."""
    from host.evaluate.target import search_target

    heldout, keep = _heldout_views(args, db)
    print(f"target {target}: held-out views from {heldout.source}", file=sys.stderr)
    fit_db = db if keep is None else subset_database(db, keep)
    cache = args.cache
    if keep is not None:
        cache = str(Path(args.cache) / "holdout") if args.cache else str(
            db.path / ".eigencast-cache" / "holdout")
        try:
            Path(cache).mkdir(parents=True, exist_ok=True)
        except OSError:
            cache = None  # fit_database falls back to a temporary folder
    full = fit_database(fit_db, **{**options, "cache_dir": cache})
    image, annex = build_image(full, fit_db, score_step=args.score_step, measure_int8=False,
                               interpolation=args.interpolation, bit_budget=args.bit_budget)
    result = search_target(HostModel.from_image(image, annex), heldout, target,
                           score_step=args.score_step)
    print(result.table())
    choice = result.choice
    kwargs = ({"threshold": choice.level} if choice.knob == "threshold"
              else {"components": int(choice.level)})
    if keep is None:
        model = truncate_eigenspace(full, choice.counts, **kwargs)
    else:  # the search model lacked the held-out views: refit on every view at the choice
        model = fit_database(db, **{**options, **kwargs})
    step = args.score_step if args.score_step is not None else (
        choice.step_factor * auto_score_step(model))
    fitted = options["threshold"] if choice.knob == "threshold" else options["components"]
    record = {**result.provenance(), "fitted_" + choice.knob: fitted,
              "refitted_on_all_views": keep is not None}
    return model, step, {"target": record}


def _heldout_views(args: argparse.Namespace, db: CinemaDB):
    """(HeldOutViews, indices of db views to fit on or None)."""
    from host.evaluate.target import HeldOutViews, holdout_indices
    from host.progress import progress
    from host.render.camera import parse_view_set
    from host.render.settings import RenderSettings, ViewRenderer

    if args.test_db:
        test = CinemaDB.open(args.test_db)
        if tuple(test.image_shape) != tuple(db.image_shape):
            raise EigencastError(
                f"--test-db {args.test_db}: images are {test.image_shape[1]}x"
                f"{test.image_shape[0]}, {db.path} has {db.image_shape[1]}x{db.image_shape[0]}"
            )
        if test.settings and db.settings:
            ours = with_recorded_lighting(db.settings)
            theirs = with_recorded_lighting(test.settings)
            differ = sorted(k for k in set(theirs) | set(ours)
                            if k not in _VIEW_KEYS and theirs.get(k) != ours.get(k))
            if differ:
                raise EigencastError(
                    f"--test-db {args.test_db}: rendered with other settings than {db.path} "
                    f"({', '.join(differ)} differ)"
                )
        images = np.stack(list(test.iter_images()))
        return HeldOutViews(test.phi_deg, test.theta_deg, images,
                            f"test database {args.test_db} ({test.n_views} views)"), None
    views = parse_view_set(args.holdout)
    settings = None
    if db.settings:
        settings = RenderSettings.from_record(db.settings, what=str(db.path))
        source = args.volume or settings.volume_source
        loadable = args.volume is not None or source.startswith("builtin:") or Path(
            source).exists()
        if loadable:
            scene = ViewRenderer.open(settings, args.volume, args, what=str(db.path))
            angles = views.angles_deg()
            images = np.empty((len(angles), *db.image_shape, 3), dtype=np.uint8)
            with progress("render held-out views", len(angles), unit=" views") as bar:
                for i, (phi, theta) in enumerate(angles):
                    images[i] = scene.render_rgb8(phi, theta)
                    bar.advance()
            return HeldOutViews(angles[:, 0].copy(), angles[:, 1].copy(), images,
                                f"{len(angles)} ray-cast views ({views.spec})"), None
    count = len(views)
    held = holdout_indices(db.n_views, count, seed=1)
    keep = np.setdiff1d(np.arange(db.n_views), held)
    images = np.stack([db.read_image(int(i)) for i in held])
    why = "no render settings" if settings is None else "its volume is not loadable"
    return HeldOutViews(db.phi_deg[held].copy(), db.theta_deg[held].copy(), images,
                        f"{count} views held out of {db.path} ({why}; the search model is "
                        "fitted without them)"), keep


def _standalone_line(path: Path, info: dict) -> str:
    """One line on the standalone table's size against the eigenimages' (compressed)."""
    from protocol.image import read_manifest

    with open(path, "rb") as f:
        sizes = {e["name"]: e["size"] for e in read_manifest(f)["sections"]}
    table, eig = sizes[info["section"]], sizes["eigenimages"]
    return (f"standalone table: {info['dtype']} {info['shape'][0]}x{info['shape'][1]} at step "
            f"{info['step']:.3g}, {info['raw_bytes'] / 1e3:.1f} kB raw, {table / 1e3:.1f} kB "
            f"compressed = {100 * table / max(eig, 1):.0f}% of the eigenimages "
            f"({eig / 1e3:.1f} kB compressed)")


def image_device_bytes(path: Path) -> int:
    """Size of the device part of an .ecs (what provisioning sends)."""
    from protocol.image import HEADER_SIZE, image_size

    with open(path, "rb") as f:
        return image_size(f.read(HEADER_SIZE))
