"""``eigencast keygen -o KEYFILE``: create a device key file (32 random bytes, mode 0600)."""

from __future__ import annotations

import argparse
import json

from protocol.keys import key_fingerprint, write_key

HELP = "create a device key file (32 random bytes, hex, mode 0600) for signing images"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``-o/--output``, ``--force`` and ``--json``."""
    parser.add_argument(
        "-o", "--output", required=True, metavar="KEYFILE", help="key file to create"
    )
    parser.add_argument(
        "--force", action="store_true", help="replace an existing key file (atomically)"
    )
    parser.add_argument("--json", action="store_true", help="print the result as JSON")


def run(args: argparse.Namespace) -> int:
    """Write the key file and print its path and fingerprint (never the key)."""
    key = write_key(args.output, force=args.force)
    fingerprint = key_fingerprint(key)
    if args.json:
        print(json.dumps({"path": str(args.output), "fingerprint": fingerprint}))
    else:
        print(f"wrote key {args.output} (fingerprint {fingerprint}); keep it secret")
    return 0
