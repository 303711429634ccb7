"""``eigencast provision MODEL.ecs --port URL [--baud B] [--key KEYFILE [--insecure]] [--force]
[--json]``."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

from host.link.options import ProvisionOptions, ProvisionParts
from host.link.provisioning import provision
from protocol.image_transfer import RETRANSMIT_STRATEGIES
from protocol.keys import load_key

HELP = "install an eigenspace image on a device (resumable, verified, authenticated)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the image, ``--port``, ``--baud``, ``--key``, ``--insecure``, ``--force``, tuning."""
    parser.add_argument("model", metavar="MODEL.ecs", type=Path, help="eigenspace image")
    parser.add_argument("--port", required=True, metavar="URL",
                        help="device port: /dev/ttyUSB0, socket://HOST:PORT, rfc2217://...")
    parser.add_argument("--baud", type=int, default=115200,
                        help="serial line rate (default 115200)")
    parser.add_argument("--key", metavar="KEYFILE", type=Path,
                        help="device key (needed when the device holds one)")
    parser.add_argument("--insecure", action="store_true",
                        help="with --key: install on a device that says it holds no key anyway "
                        "(unauthenticated; refused by default: it may be an impostor)")
    parser.add_argument("--force", action="store_true",
                        help="allow installing an older image generation (rollback)")
    parser.add_argument("--chunk", metavar="BYTES", type=int,
                        help="largest chunk (default: from the device's buffers and the line)")
    parser.add_argument("--retransmit", choices=RETRANSMIT_STRATEGIES, default="selective",
                        help="loss recovery (default selective)")
    parser.add_argument("--timeout", metavar="S", type=float, default=1.0,
                        help="first reply timeout of each request, seconds (retries back off)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    parser.add_argument("--quiet", action="store_true", help="no progress output")


def run(args: argparse.Namespace) -> int:
    """Provision and print a one-line summary (or JSON)."""
    options = ProvisionOptions.from_args(args)
    if args.key is not None:
        options = replace(options, key=load_key(args.key))
    quiet = args.json or args.quiet
    result = provision(args.model, args.port, options,
                       ProvisionParts(log=(lambda line: None) if quiet else None))
    if args.json:
        print(json.dumps(result.as_dict()))
    else:
        rate = result.rate_bytes_per_s
        extra = f", {rate / 1024:.1f} KiB/s" if result.outcome == "installed" else ""
        print(
            f"{result.outcome}: {args.model} ({result.size_bytes} bytes) on device "
            f"'{result.device_id}', slot {result.slot}{extra}"
        )
    return 0
