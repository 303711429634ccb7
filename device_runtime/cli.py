"""``eigencast-device``: the device program (show frames, serve a host, print status, pair a key).

Usage::

    eigencast-device (--port URL | --listen HOST:PORT) --flash DIR [--baud B]
                     [--key KEYFILE | --insecure] [--ram-budget MB] [--flash-size MB]
                     [--device-id ID] [--max-frame BYTES] [--window FRAMES] [--auth-timeout S]
                     [--headless [--frames DIR [--every N]] | --display]
                     [--standalone] [--orbit SPEC | --views LIST] [--view PHI,THETA]
                     [--look NAME] [--max-frames N] [--stats FILE] [--screenshots DIR]
                     [--zoom Z]
    eigencast-device --standalone --flash DIR [display options]     (no host at all)
    eigencast-device --flash DIR --status [--json] [--key KEYFILE] [--ram-budget MB]
    eigencast-device --pair KEYFILE --flash DIR
    eigencast-device --unpair --flash DIR

The runtime (:mod:`device_runtime.runtime`) boots the active image from flash, shows it in
a window (drag or arrow keys change the view, ``+``/``-`` zoom, ``h`` overlay, ``s``
screenshot, ``l`` the next look of an image with several, ``Esc`` quits) or, with
``--headless``, writes every N-th frame as a PNG into ``--frames DIR`` (with
``frames.csv``). Without ``--headless`` or ``--display`` it opens a window when it can and
runs headless otherwise. ``--standalone`` interpolates scores
locally from the image's table (``eigencast fit --standalone``), so no host is needed;
``--orbit`` / ``--views`` drive the view by themselves (standalone: locally; otherwise by
view requests to the host) and the program exits when they are done.

Serving logs one line per event to stderr (``eigencast-device: ...``); with
``--listen`` the first lines include ``listening on tcp-listen://HOST:PORT``
(the real port when PORT is 0). It keeps running after a host disconnects and
stops on SIGINT (Ctrl-C: exit code 130, as every eigencast command) or SIGTERM (a
service manager's stop: exit code 0). The key comes from ``--key`` or, failing that, from
the one ``--pair`` installed in the flash folder (``DIR/device.key``, mode
0600). A device without a key refuses provisioning unless ``--insecure``;
``--insecure`` is refused on a paired flash folder (``--unpair`` removes the
key first), as with ``--key``: a device with a key always authenticates.

``--status`` says per slot whether it *verifies*: its digest matches and this
device (its key, or the paired one, and ``--ram-budget``) would load it; when
not, ``problem`` says why. At boot an active image that does not load is given
up for the other slot (see :meth:`device_runtime.device.Device.fall_back`).

Every user error (bad flag, bad URL, missing key file, corrupt flash folder)
is one line on stderr and exit code 1; a command line argparse cannot parse (an unknown or
malformed flag, a missing ``--flash``) gets the usage line (:data:`USAGE`) above it.
:func:`build_parser` is the parser the runtime issue extends (``--headless --frames DIR
--standalone``).
"""

from __future__ import annotations

import argparse
import contextlib
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
    DeviceConfig,
)
from device_runtime.errors import DeviceError, FlashError
from device_runtime.flash import FlashStore, format_status
from device_runtime.image_receiver import image_problem
from protocol.errors import ProtocolError
from protocol.keys import key_fingerprint, load_key, write_key
from protocol.transport import open_transport

__all__ = ["KEY_FILE_NAME", "build_parser", "main", "paired_key_path"]

PROG = "eigencast-device"
KEY_FILE_NAME = "device.key"
"""Name of the key ``--pair`` installs in the flash folder."""
PAIRED_MARK_NAME = "device.paired"
"""What ``--pair`` also writes (the key's fingerprint): a paired folder whose key file is
gone refuses to start instead of running keyless (fail closed); ``--unpair`` removes both."""
_MB = 1024 * 1024
DEFAULT_KEEP_FRAMES = 1000
"""PNGs ``--frames`` keeps by default: a served device makes 30-60 frames a second, so every
frame of a long run fills a disk (23,340 PNGs, 549 MB in 10 minutes at 256 px)."""


class _UsageError(Exception):
    """A bad flag combination or value (one line, exit 1)."""


class _ParseError(_UsageError):
    """A command line argparse cannot parse: the usage line, then the error (exit 1)."""


USAGE = (f"{PROG} --flash DIR (--port URL | --listen HOST:PORT | --standalone | --status | "
         "--pair KEYFILE | --unpair) [options]")
"""The one usage line a bad command line gets (``--help`` lists the options)."""


class _Parser(argparse.ArgumentParser):
    """argparse that reports bad flags as the usage line, one error line and exit code 1
    (not argparse's whole usage page and 2)."""

    def error(self, message: str) -> NoReturn:
        raise _ParseError(" ".join(message.split()))


def version_line() -> str:
    """``eigencast-device VERSION (protocol N)``: the installed package's version."""
    from importlib.metadata import PackageNotFoundError, version

    from protocol.messages import PROTOCOL_VERSION

    try:
        installed = version("eigencast")
    except PackageNotFoundError:
        installed = "(not installed)"
    return f"{PROG} {installed} (protocol {PROTOCOL_VERSION})"


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
    """The ``eigencast-device`` argument parser."""
    parser = _Parser(
        prog=PROG,
        usage=USAGE,
        description="The eigencast device: answers a host over a serial port or TCP, keeps "
        "eigenspace images in a flash folder. While you drag, every display tick shows the "
        "best frame ready (the view's depth warp once it is made, else the quick blend of the "
        "neighbouring views): a slow board shows more blends while the view moves, never a "
        "late frame, and the warp as soon as it rests.",
    )
    parser.add_argument("--version", action="version", version=version_line())
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
    parser.add_argument("--auth-timeout", metavar="S", type=float, default=5.0,
                        help="keyed device on TCP: drop a connection that has not "
                        "authenticated within S seconds (default 5)")
    parser.add_argument("--status", action="store_true",
                        help="print each slot's state, digest and whether it verifies "
                        "(digest, and loads with this key and --ram-budget); exit")
    parser.add_argument("--json", action="store_true", help="with --status: print JSON")
    parser.add_argument("--pair", metavar="KEYFILE", type=Path,
                        help="install this key into the flash folder (mode 0600) and exit")
    parser.add_argument("--unpair", action="store_true",
                        help="remove the key --pair installed in the flash folder and exit")
    _add_display_arguments(parser.add_argument_group("display and runtime"))
    return parser


def _add_display_arguments(show: argparse._ArgumentGroup) -> None:
    """The options of what the device shows and how (the parser's second group)."""
    mode = show.add_mutually_exclusive_group()
    mode.add_argument("--headless", action="store_true",
                      help="no window: reconstruct frames and write them with --frames")
    mode.add_argument("--display", action="store_true",
                      help="require a window (default: a window when one can be opened, "
                      "else headless)")
    show.add_argument("--frames", metavar="DIR", type=Path,
                      help="headless: write frames as PNG (frame-NNNNNN.png, frames.csv) here")
    show.add_argument("--every", metavar="N", type=int, default=1,
                      help="with --frames: write every N-th frame (default 1)")
    show.add_argument("--keep-frames", metavar="N", type=int, default=DEFAULT_KEEP_FRAMES,
                      help="with --frames: keep the last N PNGs, deleting older ones as new ones "
                      f"come (default {DEFAULT_KEEP_FRAMES}, about {DEFAULT_KEEP_FRAMES // 40} s "
                      "of a served drag; frames.csv lists them all; 0 keeps every frame)")
    show.add_argument("--standalone", action="store_true",
                      help="no host: show every view from the image alone (its depth warp "
                      "of the neighbouring training views, or their blend; every image fit "
                      "makes can, unless fitted --no-standalone)")
    show.add_argument("--no-predict", action="store_true",
                      help="with a host: do not make this device's own frame of a new view; "
                      "show only the host's full frames (default: when the image has the "
                      "standalone table, show its own frame at once and the host's "
                      "corrections of it)")
    drive = show.add_mutually_exclusive_group()
    drive.add_argument("--orbit", metavar="SPEC", type=_orbit,
                       help="drive the view: turn:SECONDS[:THETA[:TURNS]] (a full turn every "
                       "SECONDS at elevation THETA, default 15, TURNS turns, default forever) "
                       "or steps:N[:THETA[:TURNS]] (N evenly spaced views per turn, each shown "
                       "once, default 1 turn); exits when a finite orbit is done")
    drive.add_argument("--views", metavar="LIST", type=_views,
                       help="show these views one after the other, then exit: "
                       "'PHI,THETA;PHI,THETA;...' in degrees")
    show.add_argument("--view", metavar="PHI,THETA", type=_one_view,
                      help="initial view in degrees (default 30,15)")
    show.add_argument("--look", metavar="NAME",
                      help="the look to show first of an image with several (a name or an "
                      "index; default the first; in a window 'l' shows the next)")
    show.add_argument("--max-frames", metavar="N", type=int,
                      help="exit after presenting N frames")
    show.add_argument("--fps", metavar="N", type=float,
                      help="display ticks per second (default 60 in a window, 30 headless): "
                      "at most one blend per tick while the view moves")
    show.add_argument("--request-rate", metavar="HZ", type=float, default=60.0,
                      help="view requests per second at most (default 60; latest wins)")
    show.add_argument("--stats", metavar="FILE", type=Path,
                      help="write runtime statistics as JSON here (every second and at exit)")
    show.add_argument("--screenshots", metavar="DIR", type=Path,
                      help="where 's' saves screenshots (default: --frames DIR or '.')")
    show.add_argument("--zoom", metavar="Z", type=float,
                      help="initial window zoom (default: 1, or less to fit the screen)")


def _orbit(text: str) -> Any:
    from device_runtime.orbit import parse_orbit

    try:
        return parse_orbit(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _views(text: str) -> Any:
    from device_runtime.orbit import parse_view_list

    try:
        return parse_view_list(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _one_view(text: str) -> Any:
    views = _views(text)
    if len(views) != 1:
        raise argparse.ArgumentTypeError(f"{text!r}: give one PHI,THETA pair")
    return views[0]


def paired_key_path(flash_dir: Path) -> Path:
    """Where ``--pair`` keeps the key."""
    return Path(flash_dir) / KEY_FILE_NAME


def _paired_fingerprint(flash_dir: Path) -> str | None:
    """The fingerprint ``--pair`` recorded (None: never paired, or unpaired since)."""
    try:
        return (Path(flash_dir) / PAIRED_MARK_NAME).read_text().strip() or "?"
    except FileNotFoundError:
        return None


def _missing_key(args: argparse.Namespace) -> str:
    """The one line refusing a paired folder whose key file is gone."""
    return (f"this device is paired (key {_paired_fingerprint(args.flash)}) but its key file "
            f"{paired_key_path(args.flash)} is gone: restore it, start with --key KEYFILE, or "
            f"unpair it on purpose (eigencast-device --unpair --flash {args.flash})")


def _log(line: str) -> None:
    print(f"{PROG}: {line}", file=sys.stderr, flush=True)


def _status(args: argparse.Namespace) -> int:
    if not args.flash.is_dir():
        raise _UsageError(f"no flash folder at {args.flash} (a device creates it when it "
                          "first starts)")
    store = FlashStore.open(args.flash, create=False)
    key_path = paired_key_path(args.flash)
    paired = load_key(key_path) if key_path.exists() else None
    device_key = load_key(args.key) if args.key is not None else paired
    budget = int(args.ram_budget * _MB)
    status = store.status(check_image=lambda stream: image_problem(
        stream, key=device_key, ram_budget_bytes=budget))
    key = None if paired is None else key_fingerprint(paired)
    marked = _paired_fingerprint(args.flash)
    status["paired_key_fingerprint"] = key or marked
    status["paired_key_missing"] = key is None and marked is not None
    if args.json:
        print(json.dumps(status, indent=2))
    else:
        print(format_status(status))
        if status["paired_key_missing"]:
            print(f"  key: paired, fingerprint {marked}, but the key file is missing "
                  f"({key_path}): the device refuses to start without it")
        else:
            print(f"  key: {'paired, fingerprint ' + key if key else 'none paired'}")
    return 0


def _pair(args: argparse.Namespace) -> int:
    key = load_key(args.pair)
    args.flash.mkdir(parents=True, exist_ok=True)
    target = paired_key_path(args.flash)
    write_key(target, key, force=True)
    os.chmod(target, 0o600)
    (args.flash / PAIRED_MARK_NAME).write_text(key_fingerprint(key) + "\n")
    print(f"paired key {key_fingerprint(key)} into {target} (mode 0600)")
    return 0


def _unpair(args: argparse.Namespace) -> int:
    target = paired_key_path(args.flash)
    mark = args.flash / PAIRED_MARK_NAME
    if not target.exists():
        if not mark.exists():
            raise _UsageError(f"--unpair: no paired key in {args.flash} ({target} does not "
                              "exist)")
        fingerprint = _paired_fingerprint(args.flash)
        mark.unlink()
        print(f"unpaired {args.flash} (key {fingerprint}, whose key file was already gone)")
        return 0
    fingerprint = key_fingerprint(load_key(target))
    target.unlink()
    mark.unlink(missing_ok=True)
    print(f"removed paired key {fingerprint} from {target}")
    return 0


def _config(args: argparse.Namespace) -> DeviceConfig:
    key = None
    paired = paired_key_path(args.flash)
    if args.key is not None:
        if args.insecure:
            raise _UsageError("--insecure cannot be combined with --key (a device with a key "
                              "always authenticates)")
        key = load_key(args.key)
    elif paired.exists():
        if args.insecure:
            raise _UsageError(
                f"--insecure: this device is paired ({paired} holds its key) and a device with "
                "a key always authenticates; to run it without one, unpair it first "
                f"(eigencast-device --unpair --flash {args.flash})"
            )
        key = load_key(paired)
    elif _paired_fingerprint(args.flash) is not None:
        raise _UsageError(_missing_key(args))
    if args.max_frame is not None and not 1024 <= args.max_frame <= 1 << 24:
        raise _UsageError(f"--max-frame {args.max_frame} must be in 1024..16777216")
    if not 1 <= args.window <= 65535:
        raise _UsageError(f"--window {args.window} must be in 1..65535")
    if args.baud <= 0:
        raise _UsageError(f"--baud {args.baud} must be positive")
    if not 0 < args.auth_timeout <= 3600:
        raise _UsageError(f"--auth-timeout {args.auth_timeout} must be in (0, 3600] seconds")
    return DeviceConfig(
        flash_dir=args.flash,
        key=key,
        insecure=args.insecure,
        device_id=args.device_id,
        ram_budget_bytes=int(args.ram_budget * _MB),
        slot_size_bytes=None if args.flash_size is None else int(args.flash_size * _MB),
        rx_window_frames=args.window,
        max_frame_bytes=args.max_frame,
        auth_timeout_s=args.auth_timeout,
    )


def headless_plan(args: argparse.Namespace) -> str:
    """One line: what a headless device will do (what drives its view, where frames go)."""
    if args.orbit is not None or args.views is not None:
        drive = "shows the " + ("--orbit" if args.orbit is not None else "--views")
    elif args.standalone:
        view = args.view or (30.0, 15.0)
        drive = (f"shows the view {view[0]:g},{view[1]:g} once, then waits (--orbit SPEC or "
                 "--views LIST drive it)")
    else:
        drive = "shows the views the host sends (serve --orbit drives them)"
    if args.max_frames is not None:
        drive += f", stopping after {args.max_frames} frame{'s' * (args.max_frames != 1)}"
    if args.frames is None:
        out = "writes no frames (--frames DIR writes them as PNGs)"
    else:
        which = "every frame" if args.every == 1 else f"one frame in {args.every}"
        kept = ("keeping them all" if not args.keep_frames
                else f"keeping the last {args.keep_frames} (--keep-frames)")
        out = f"writes {which} to {args.frames} as PNG, {kept}"
    return f"{drive}; {out}"


def _presenter(args: argparse.Namespace, image_shape: tuple[int, int]
               ) -> tuple[Any, str | None]:
    """The window (at ``image_shape``, the active image's), or the headless presenter and the
    line that says what it will do (logged once the device is ready to run)."""
    from device_runtime.display import HeadlessPresenter, Window, WindowUnavailable

    screenshots = args.screenshots or args.frames or Path(".")
    if args.headless or args.frames is not None:
        return HeadlessPresenter(args.frames, every=args.every, keep=args.keep_frames or None,
                                 screenshot_dir=screenshots), f"headless: {headless_plan(args)}"
    try:
        return Window(image_shape, title=f"eigencast - {args.device_id}",
                      screenshot_dir=screenshots, zoom=args.zoom), None
    except WindowUnavailable as exc:
        if args.display:
            raise _UsageError(f"--display: {exc}") from None
        return (HeadlessPresenter(None, screenshot_dir=screenshots),
                f"{exc}: running headless: {headless_plan(args)}")


def _check_runtime_args(args: argparse.Namespace) -> None:
    if args.every < 1:
        raise _UsageError(f"--every {args.every} must be >= 1")
    if args.keep_frames < 0:
        raise _UsageError(f"--keep-frames {args.keep_frames} must be >= 0 (0 keeps every frame)")
    if args.frames is not None and args.display:
        raise _UsageError("--frames writes frames headless; it cannot be combined with --display")
    if args.max_frames is not None and args.max_frames < 1:
        raise _UsageError(f"--max-frames {args.max_frames} must be >= 1")
    if not args.request_rate > 0:
        raise _UsageError(f"--request-rate {args.request_rate} must be > 0")
    if args.zoom is not None and not 0.125 <= args.zoom <= 8:
        raise _UsageError(f"--zoom {args.zoom} must be within 0.125..8")
    if args.fps is not None and not 0 < args.fps <= 1000:
        raise _UsageError(f"--fps {args.fps} must be within 0..1000 (exclusive of 0)")


def _write_stats(path: Path, device: Any) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(device.stats_dict(), indent=1))
    os.replace(tmp, path)


def _serve(args: argparse.Namespace) -> int:
    _check_runtime_args(args)
    config = _config(args)
    url, transport = _open_port(args, config)
    device, presenter, plan = _start_device(args, config, transport)
    if args.standalone and url is None and device._decoder_model is None:
        device.close()
        presenter.close()
        raise _UsageError(
            f"--standalone: no image to show in {args.flash} (provision one made with "
            "eigencast fit --standalone, serving --port/--listen meanwhile)"
        )
    if plan is not None:
        _log(plan)
    stop = threading.Event()
    interrupted: list[int] = []
    if threading.current_thread() is threading.main_thread():

        def on_signal(signum: int, frame: Any) -> None:
            if signum == signal.SIGINT:  # Ctrl-C: exit 130; SIGTERM (a service's stop): 0
                interrupted.append(signum)
            stop.set()

        signal.signal(signal.SIGTERM, on_signal)
        signal.signal(signal.SIGINT, on_signal)
    failure = _run_until_stopped(args, device, url, transport, stop)
    if failure:
        raise failure[0]
    stats = device.runtime_stats
    _log(f"presented {stats.frames_presented} frames; decoded {stats.key_frames} key, "
         f"{stats.delta_frames} delta and {stats.correction_packets} correction packets"
         + (f" ({stats.stale_dropped} for views already left)" if stats.stale_dropped else ""))
    _log("interrupted" if interrupted else "stopped")
    return 130 if interrupted else 0


def _open_port(args: argparse.Namespace, config: DeviceConfig) -> tuple[str | None, Any]:
    """The host's port, opened (a bad URL fails here, before the flash folder is touched),
    and one line on what it accepts; (None, None) without --port/--listen."""
    if not (args.port or args.listen):
        return None, None
    url = args.port if args.port else f"tcp-listen://{args.listen}"
    transport = open_transport(url, baud=args.baud, max_frame_bytes=config.max_frame_bytes)
    if config.insecure:
        _log("WARNING: --insecure: ANYONE who can reach this device can install images on "
             "it and change what it shows (no authentication, unsigned images and "
             "untagged scores accepted)")
    elif config.key is None:
        _log("no key: provisioning is refused (pair one with --pair KEYFILE, or --insecure)")
    else:
        _log(f"key fingerprint {key_fingerprint(config.key)}")
    return url, transport


def _start_device(args: argparse.Namespace, config: DeviceConfig, transport: Any
                  ) -> tuple[Any, Any, str | None]:
    """The runtime device (it boots from its flash), its presenter and the presenter's
    plan line. A failure closes the transport and the presenter."""
    from device_runtime.runtime import DEFAULT_VIEW, RuntimeDevice

    presenter = None
    try:
        device = RuntimeDevice(
            config,
            standalone=args.standalone,
            predict=not args.no_predict,
            view=args.view or DEFAULT_VIEW,
            orbit=args.orbit,
            views=args.views,
            request_rate_hz=args.request_rate,
            max_frames=args.max_frames,
            look=args.look,
            log=_log,
        )
        # the window opens once, at the size of the image the device booted with
        loaded = device._decoder_model
        if args.look is not None and loaded is not None:
            from device_runtime.looks import look_index

            try:
                look_index(loaded.base or loaded.image, args.look)
            except ValueError as exc:
                device.close_display()
                device.close()
                raise _UsageError(f"--look {args.look}: {exc}") from None
        presenter, plan = _presenter(args, loaded.image.image_shape if loaded is not None
                                     else (256, 256))
        device.use_presenter(presenter, fps=args.fps)
    except BaseException:
        if transport is not None:
            transport.close()
        if presenter is not None:
            presenter.close()
        raise
    return device, presenter, plan


def _run_until_stopped(args: argparse.Namespace, device: Any, url: str | None, transport: Any,
                       stop: threading.Event) -> list[BaseException]:
    """Serve the host on a thread (with a port), write the statistics file every second
    (--stats), run the display on this thread until ``stop``; what the device thread
    raised."""

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
        finally:
            stop.set()

    runner = None
    if url is not None:
        runner = threading.Thread(target=run, name="device", daemon=True)
        runner.start()
    stats_stop = threading.Event()
    if args.stats is not None:

        def stats_loop() -> None:
            while not stats_stop.wait(1.0):
                with contextlib.suppress(OSError, ValueError, RuntimeError):
                    _write_stats(args.stats, device)

        threading.Thread(target=stats_loop, name="stats", daemon=True).start()
    try:
        device.run_display(stop)  # the main thread: pygame wants it
    finally:
        stop.set()
        stats_stop.set()
        if runner is not None:
            while runner.is_alive():
                runner.join(0.2)
        else:
            device.close()
        if args.stats is not None:
            with contextlib.suppress(OSError, ValueError):
                _write_stats(args.stats, device)
        device.close_display()
    return failure


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``eigencast-device``; return the exit code."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        if args.pair is not None and args.unpair:
            raise _UsageError("--pair and --unpair cannot be combined")
        if args.pair is not None:
            return _pair(args)
        if args.unpair:
            return _unpair(args)
        if args.status:
            return _status(args)
        if args.json:
            raise _UsageError("--json goes with --status")
        if not args.port and not args.listen and not args.standalone:
            raise _UsageError("give --port URL or --listen HOST:PORT (or --standalone, --status, "
                              "--pair)")
        return _serve(args)
    except KeyboardInterrupt:  # before the signal handlers are set (booting)
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    except _UsageError as exc:
        if isinstance(exc, _ParseError):
            print(f"usage: {USAGE}", file=sys.stderr)
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
