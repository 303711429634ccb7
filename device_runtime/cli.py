"""``eigencast-device``: the device program (serve a host, print status, pair a key).

Usage::

    eigencast-device (--port URL | --listen HOST:PORT) --flash DIR [--baud B]
                     [--key KEYFILE | --insecure] [--ram-budget MB] [--flash-size MB]
                     [--device-id ID] [--max-frame BYTES] [--window FRAMES]
    eigencast-device --flash DIR --status [--json]
    eigencast-device --pair KEYFILE --flash DIR

Serving logs one line per event to stderr (``eigencast-device: ...``); with
``--listen`` the first lines include ``listening on tcp-listen://HOST:PORT``
(the real port when PORT is 0). It keeps running after a host disconnects and
stops on SIGINT/SIGTERM. The key comes from ``--key`` or, failing that, from
the one ``--pair`` installed in the flash folder (``DIR/device.key``, mode
0600). A device without a key refuses provisioning unless ``--insecure``.

Every user error (bad flag, bad URL, missing key file, corrupt flash folder)
is one line on stderr and exit code 1. :func:`build_parser` is the parser the
runtime issue extends (``--headless --frames DIR --standalone``).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn

from device_runtime.device import (
    DEFAULT_DEVICE_ID,
    DEFAULT_RAM_BUDGET_BYTES,
    DEFAULT_RX_WINDOW_FRAMES,
    Device,
    DeviceConfig,
)
from device_runtime.errors import DeviceError, FlashError
from device_runtime.flash import FlashStore, format_status
from protocol.errors import ProtocolError
from protocol.keys import key_fingerprint, load_key, write_key
from protocol.transport import open_transport

__all__ = ["KEY_FILE_NAME", "build_parser", "main", "paired_key_path"]

PROG = "eigencast-device"
KEY_FILE_NAME = "device.key"
"""Name of the key ``--pair`` installs in the flash folder."""
_MB = 1024 * 1024


class _UsageError(Exception):
    """A bad flag combination or value (one line, exit 1)."""


class _Parser(argparse.ArgumentParser):
    """argparse that reports bad flags as one line and exit code 1 (not 2)."""

    def error(self, message: str) -> NoReturn:
        raise _UsageError(message)


def _positive_mb(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of MB") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"{text} must be > 0 MB")
    return value


def _listen_address(text: str) -> str:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise argparse.ArgumentTypeError(f"{text!r} is not HOST:PORT (PORT 0..65535)")
    return text


def build_parser() -> argparse.ArgumentParser:
    """The ``eigencast-device`` argument parser (later issues add their flags to it)."""
    parser = _Parser(
        prog=PROG,
        description="The eigencast device: answers a host over a serial port or TCP, keeps "
        "eigenspace images in a flash folder.",
    )
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--port", metavar="URL",
                       help="serial port or pyserial URL to serve (e.g. /dev/ttyUSB0, mem://...)")
    where.add_argument("--listen", metavar="HOST:PORT", type=_listen_address,
                       help="serve hosts over TCP (PORT 0 picks a free port)")
    parser.add_argument("--flash", metavar="DIR", required=True, type=Path,
                        help="flash folder (created and formatted when new)")
    parser.add_argument("--baud", type=int, default=115200, help="serial line rate (default "
                        "115200)")
    parser.add_argument("--key", metavar="KEYFILE", type=Path,
                        help="device key file (default: the key --pair installed in DIR)")
    parser.add_argument("--insecure", action="store_true",
                        help="accept provisioning without a key (unauthenticated, unsigned)")
    parser.add_argument("--ram-budget", metavar="MB", type=_positive_mb,
                        default=DEFAULT_RAM_BUDGET_BYTES / _MB,
                        help="RAM the eigenspace may use "
                        f"(default {DEFAULT_RAM_BUDGET_BYTES // _MB})")
    parser.add_argument("--flash-size", metavar="MB", type=_positive_mb,
                        help="capacity of each flash slot when formatting DIR (default 64)")
    parser.add_argument("--device-id", default=DEFAULT_DEVICE_ID,
                        help=f"device identifier (default {DEFAULT_DEVICE_ID})")
    parser.add_argument("--max-frame", metavar="BYTES", type=int,
                        help="largest frame (default: 4096 serial, 16384 TCP)")
    parser.add_argument("--window", metavar="FRAMES", type=int,
                        default=DEFAULT_RX_WINDOW_FRAMES,
                        help=f"image receive buffers (default {DEFAULT_RX_WINDOW_FRAMES})")
    parser.add_argument("--status", action="store_true",
                        help="print each slot's state, digest and whether it verifies; exit")
    parser.add_argument("--json", action="store_true", help="with --status: print JSON")
    parser.add_argument("--pair", metavar="KEYFILE", type=Path,
                        help="install this key into the flash folder (mode 0600) and exit")
    return parser


def paired_key_path(flash_dir: Path) -> Path:
    """Where ``--pair`` keeps the key."""
    return Path(flash_dir) / KEY_FILE_NAME


def _log(line: str) -> None:
    print(f"{PROG}: {line}", file=sys.stderr, flush=True)


def _status(args: argparse.Namespace) -> int:
    if not args.flash.is_dir():
        raise _UsageError(f"no flash folder at {args.flash} (a device creates it when it "
                          "first starts)")
    store = FlashStore.open(args.flash, create=False)
    status = store.status()
    key_path = paired_key_path(args.flash)
    key = None
    if key_path.exists():
        key = key_fingerprint(load_key(key_path))
    status["paired_key_fingerprint"] = key
    if args.json:
        print(json.dumps(status, indent=2))
    else:
        print(format_status(status))
        print(f"  key: {'paired, fingerprint ' + key if key else 'none paired'}")
    return 0


def _pair(args: argparse.Namespace) -> int:
    key = load_key(args.pair)
    args.flash.mkdir(parents=True, exist_ok=True)
    target = paired_key_path(args.flash)
    write_key(target, key, force=True)
    os.chmod(target, 0o600)
    print(f"paired key {key_fingerprint(key)} into {target} (mode 0600)")
    return 0


def _config(args: argparse.Namespace) -> DeviceConfig:
    key = None
    if args.key is not None:
        key = load_key(args.key)
    elif paired_key_path(args.flash).exists() and not args.insecure:
        key = load_key(paired_key_path(args.flash))
    if key is not None and args.insecure:
        raise _UsageError("--insecure cannot be combined with --key (a device with a key "
                          "always authenticates)")
    if args.max_frame is not None and not 1024 <= args.max_frame <= 1 << 24:
        raise _UsageError(f"--max-frame {args.max_frame} must be in 1024..16777216")
    if not 1 <= args.window <= 65535:
        raise _UsageError(f"--window {args.window} must be in 1..65535")
    if args.baud <= 0:
        raise _UsageError(f"--baud {args.baud} must be positive")
    return DeviceConfig(
        flash_dir=args.flash,
        key=key,
        insecure=args.insecure,
        device_id=args.device_id,
        ram_budget_bytes=int(args.ram_budget * _MB),
        slot_size_bytes=None if args.flash_size is None else int(args.flash_size * _MB),
        rx_window_frames=args.window,
        max_frame_bytes=args.max_frame,
    )


def _serve(args: argparse.Namespace) -> int:
    config = _config(args)
    url = args.port if args.port else f"tcp-listen://{args.listen}"
    transport = open_transport(
        url, baud=args.baud, max_frame_bytes=config.max_frame_bytes
    )  # a bad URL fails here, before the flash folder is touched
    if config.insecure:
        _log("WARNING: --insecure: ANYONE who can reach this device can install images on it "
             "(no authentication, unsigned images accepted)")
    elif config.key is None:
        _log("no key: provisioning is refused (pair one with --pair KEYFILE, or --insecure)")
    else:
        _log(f"key fingerprint {key_fingerprint(config.key)}")
    try:
        device = Device(config, log=_log)
    except BaseException:
        transport.close()
        raise
    stop = threading.Event()
    if threading.current_thread() is threading.main_thread():

        def on_signal(signum: int, frame: Any) -> None:
            stop.set()

        signal.signal(signal.SIGTERM, on_signal)
        signal.signal(signal.SIGINT, on_signal)

    def ready(transport: Any) -> None:
        if args.listen:
            _log(f"listening on {transport.url}")
        else:
            _log(f"serving {url} at {args.baud} baud")

    failure: list[BaseException] = []

    def run() -> None:
        try:
            device.run(url, baud=args.baud, stop=stop, on_ready=ready, transport=transport)
        except BaseException as exc:  # reported by the main thread
            failure.append(exc)

    runner = threading.Thread(target=run, name="device", daemon=True)
    runner.start()
    while runner.is_alive():  # the main thread stays free for signals
        runner.join(0.2)
    if failure:
        raise failure[0]
    _log("stopped")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``eigencast-device``; return the exit code."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        if args.pair is not None:
            return _pair(args)
        if args.status:
            return _status(args)
        if args.json:
            raise _UsageError("--json goes with --status")
        if not args.port and not args.listen:
            raise _UsageError("give --port URL or --listen HOST:PORT (or --status / --pair)")
        return _serve(args)
    except _UsageError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 1
    except (DeviceError, FlashError, ProtocolError, ValueError, OSError) as exc:
        text = " ".join(str(exc).split()) or type(exc).__name__
        if isinstance(exc, OSError) and exc.filename and str(exc.filename) not in text:
            text = f"{exc.filename}: {text}"
        print(f"{PROG}: error: {text}", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
