"""``eigencast demo [--headless] [--volume VOLUME]``: render, fit, provision and serve a device."""

from __future__ import annotations

import argparse
import json

from host.errors import EigencastError

HELP = ("one-command demo: render a volume, fit it, start a device process on TCP loopback, "
        "provision it and serve it (a window, or a headless orbit with a summary)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from host.demo import DemoSettings

    d = DemoSettings()
    parser.add_argument("--headless", action="store_true",
                        help="no window: serve an orbit, write frames and print a summary "
                        "(default when no display can be opened)")
    parser.add_argument("--window", action="store_true",
                        help="require a window (fails when no display can be opened)")
    parser.add_argument("--volume", default=d.volume, metavar="VOLUME",
                        help=f"volume to show (default {d.volume})")
    parser.add_argument("--work", default="demo-out", metavar="DIR",
                        help="work folder, kept as the cache for the next run (default "
                        "demo-out)")
    parser.add_argument("--views", default=d.views, metavar="SPEC",
                        help=f"training views (default {d.views})")
    parser.add_argument("--size", type=int, default=d.size, metavar="N",
                        help=f"image size in pixels (default {d.size})")
    parser.add_argument("--samples", type=int, default=d.samples, metavar="N",
                        help=f"ray samples (default {d.samples})")
    parser.add_argument("--orbit", default=d.orbit, metavar="SPEC",
                        help=f"headless orbit (default {d.orbit})")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON too")


def run(args: argparse.Namespace) -> int:
    from device_runtime.runtime import parse_orbit
    from host.demo import DemoSettings, display_available, run_demo

    if args.headless and args.window:
        raise EigencastError("--headless and --window exclude each other")
    try:
        parse_orbit(args.orbit)
    except ValueError as exc:
        raise EigencastError(f"--orbit: {exc}") from None
    if not 16 <= args.size <= 1024:
        raise EigencastError(f"--size {args.size}: must be within 16..1024 for the demo")
    headless = True if args.headless else (False if args.window else None)
    if headless is False and not display_available():
        raise EigencastError("--window: no display can be opened here (DISPLAY unset or "
                             "unusable); use --headless")
    settings = DemoSettings(volume=args.volume, views=args.views, size=args.size,
                            samples=args.samples, orbit=args.orbit)
    summary = run_demo(args.work, settings=settings, headless=headless)
    if args.json:
        print(json.dumps(summary, default=str))
    return 0
