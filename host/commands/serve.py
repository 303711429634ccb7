"""``eigencast serve MODEL.ecs --port URL [--key KEYFILE] [--orbit SPEC] ...``."""

from __future__ import annotations

import argparse
import json
import signal
import threading
from dataclasses import replace
from pathlib import Path

from host.errors import EigencastError

HELP = "stream score packets to a device: answer its view requests, or drive an orbit"

_ORBIT_HELP = (
    "drive the view from the host instead of the device's requests: "
    "turn:SECONDS[:THETA[:TURNS]] = a full turn of phi every SECONDS seconds at elevation "
    "THETA degrees (default 15), TURNS turns (default: until interrupted); "
    "steps:N[:THETA[:TURNS]] = N evenly spaced views per turn, each sent once, as fast as "
    "--fps and the link allow (default 1 turn). Examples: turn:12:20, steps:72:15:2"
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Model, ``--port``, ``--key``, ``--orbit`` and pacing options."""
    parser.add_argument("model", metavar="MODEL.ecs", type=Path, help="eigenspace image")
    parser.add_argument("--port", required=True, metavar="URL",
                        help="device port: socket://HOST:PORT (a device started with "
                        "--listen), /dev/ttyUSB0, rfc2217://...")
    parser.add_argument("--baud", type=int, default=115200,
                        help="serial line rate (default 115200)")
    parser.add_argument("--key", metavar="KEYFILE", type=Path,
                        help="device key (needed when the device holds one)")
    parser.add_argument("--insecure", action="store_true",
                        help="with --key: serve a device that says it holds no key anyway "
                        "(unauthenticated; refused by default: it may be an impostor)")
    parser.add_argument("--orbit", metavar="SPEC", help=_ORBIT_HELP)
    parser.add_argument("--fps", type=float, default=60.0,
                        help="packets per second at most (default 60; 0: as fast as the link "
                        "carries them)")
    parser.add_argument("--keyframe-interval", metavar="N", type=int, default=0,
                        help="0: delta frames, key frames only at a (re)connect or when the "
                        "device asks (default); 1: key frames only; N: a key frame at least "
                        "every N frames")
    parser.add_argument("--deadline", metavar="MS", type=float, default=None,
                        help="milliseconds per frame the host may spend ray-casting a moving "
                        "view (default 33; a lower --fps or a slower link lengthens it): "
                        "a faster host corrects moving views more, a slower one less, never "
                        "later")
    parser.add_argument("--rest-quality", metavar="Q", default="exact",
                        help="what a view you stop on becomes: 'exact' (default: refined "
                        "until it is the ray-cast bit for bit), an object SSIM such as 0.95 "
                        "(refined until it reaches it), or 'correction' (the eigenspace's "
                        "best frame only, the fewest bytes)")
    parser.add_argument("--volume", metavar="PATH",
                        help="the volume to ray-cast (default: the source recorded in the "
                        "model; it must be the same volume)")
    parser.add_argument("--provision", action="store_true",
                        help="install the image first when the device lacks it")
    parser.add_argument("--force", action="store_true",
                        help="with --provision: install it even when it is an older image "
                        "generation than the device's (rollback)")
    parser.add_argument("--max-frames", metavar="N", type=int,
                        help="stop after sending N packets")
    parser.add_argument("--duration", metavar="S", type=float,
                        help="stop S seconds after streaming began (time spent reconnecting "
                        "counts)")
    parser.add_argument("--no-reconnect", action="store_true",
                        help="exit when the link is lost instead of reconnecting")
    parser.add_argument("--stats-every", metavar="S", type=float, default=5.0,
                        help="log a statistics line every S seconds (default 5; 0: never)")
    parser.add_argument("--json", action="store_true", help="print the final statistics as JSON")
    parser.add_argument("--quiet", action="store_true", help="no log lines")


def run(args: argparse.Namespace) -> int:
    """Serve until interrupted, the orbit ends, or a --max-frames/--duration limit."""
    from host.fit.model import HostModel
    from host.link.options import ServeOptions, ServeParts
    from host.link.serving import serve
    from protocol.keys import load_key

    options = ServeOptions.from_args(args)
    if not args.model.is_file():
        raise EigencastError(f"{args.model}: no such eigenspace image")
    if args.key is not None:
        options = replace(options, key=load_key(args.key))
    quiet = args.quiet or args.json
    say = (lambda line: None) if quiet else None
    model = HostModel.load(args.model, key=options.key)
    stop = threading.Event()
    interrupted: list[int] = []

    def on_signal(signum: int, frame: object) -> None:
        if signum == signal.SIGINT:  # Ctrl-C: exit 130 as every command; SIGTERM: 0
            interrupted.append(signum)
        stop.set()

    if threading.current_thread() is threading.main_thread():
        for signum in (signal.SIGINT, signal.SIGTERM):  # either ends serving cleanly
            signal.signal(signum, on_signal)
    stats = serve(args.model, args.port, options,
                  ServeParts(model=model, stop=stop, log=say))
    if args.json:
        print(json.dumps(stats.as_dict()))
    else:
        print(f"served {args.model} to device '{stats.device_id}': {stats.line()}")
    return 130 if interrupted else 0
