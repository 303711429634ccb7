"""The options of :func:`host.link.serving.serve` and :func:`host.link.provisioning.provision`.

What a user chooses (the device key, the line rate, an orbit, the frame rate ...) is one
frozen, validated object, `ServeOptions` or `ProvisionOptions`; what a caller hands in to
work with (a transport factory, a loaded model, a renderer, a stop event, where log lines
go ...) is `ServeParts` or `ProvisionParts`, mostly seams for tests and benchmarks. Every
caller builds them the same way: the command line (``host/commands/serve.py``,
``provision.py``) with `ServeOptions.from_args` / `ProvisionOptions.from_args`, the demo,
the benchmarks and the tests with the constructors.

An invalid option fails where the options are built, as one `OptionError` line that names
the option, its value and what is allowed (``fps=-1.0: expected a number >= 0``; on the
command line ``--fps -1.0: expected a number >= 0``), from one table of constraints per
object (`SERVE_CONSTRAINTS`, `PROVISION_CONSTRAINTS`), as scikit-learn's
``_parameter_constraints``.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from numbers import Integral, Real
from typing import Any

from device_runtime.orbit import OrbitSpec
from host.errors import EigencastError
from protocol.image_transfer import RETRANSMIT_STRATEGIES

__all__ = [
    "DEFAULT_DEADLINE_S",
    "PROVISION_CONSTRAINTS",
    "SCORE_MODES",
    "SERVE_CONSTRAINTS",
    "Constraint",
    "OptionError",
    "ProvisionOptions",
    "ProvisionParts",
    "ServeOptions",
    "ServeParts",
]

#: What ``serve`` streams (`host.link.serving`): ``auto`` is the one served path
#: (corrections of the device's own frames where the device takes them, else the sparse
#: ray-cast's scores, else interpolated ones); ``motion`` and ``interpolate`` force the
#: absolute scores of the fallbacks (for measurements: what an older device gets).
SCORE_MODES = ("auto", "motion", "interpolate")
#: The frame deadline when ``fps`` sets none (a frame rate of 30), seconds.
DEFAULT_DEADLINE_S = 1.0 / 30.0
#: A frame deadline at least this long is a mistake (the command line's 1e6 ms), seconds.
_MAX_DEADLINE_S = 1000.0


class OptionError(EigencastError, ValueError):
    """An option's value is not allowed: one line naming the option, its value and what is
    allowed. A `ValueError` too (what the functions raised for a bad argument)."""

    def __init__(self, option: str, value: Any, allowed: str) -> None:
        self.option, self.value, self.allowed = option, value, allowed
        super().__init__(f"{option}={value!r}: expected {allowed}")


@dataclass(frozen=True)
class Constraint:
    """What one option allows: ``test(value)`` is true for an allowed value, ``allowed``
    says which in words; ``flag`` is the command-line option that sets it (None: none)."""

    test: Callable[[Any], bool]
    allowed: str
    flag: str | None = None


def _number(v: Any) -> bool:
    return isinstance(v, Real) and not isinstance(v, bool)


def _integer(v: Any) -> bool:
    return isinstance(v, Integral) and not isinstance(v, bool)


def _optional(test: Callable[[Any], bool]) -> Callable[[Any], bool]:
    return lambda v: v is None or test(v)


def _flag(v: Any) -> bool:
    return isinstance(v, bool)


def _path(v: Any) -> bool:
    return isinstance(v, (str, os.PathLike))


def _key(v: Any) -> bool:
    return v is None or isinstance(v, (bytes, bytearray))


def _rest(v: Any) -> bool:
    return v in ("exact", "correction") or (_number(v) and 0.0 < float(v) < 1.0)


#: `ServeOptions`' fields: what each allows.
SERVE_CONSTRAINTS: Mapping[str, Constraint] = {
    "key": Constraint(_key, "the device key as bytes, or None", "--key"),
    "insecure": Constraint(_flag, "True or False", "--insecure"),
    "baud": Constraint(lambda v: _integer(v) and v > 0, "an integer > 0", "--baud"),
    "orbit": Constraint(lambda v: v is None or isinstance(v, OrbitSpec),
                        "an OrbitSpec (device_runtime.orbit.parse_orbit) or None", "--orbit"),
    "fps": Constraint(lambda v: _number(v) and not v < 0, "a number >= 0", "--fps"),
    "keyframe_interval": Constraint(lambda v: _integer(v) and v >= 0, "an integer >= 0",
                                    "--keyframe-interval"),
    "provision_missing": Constraint(_flag, "True or False", "--provision"),
    "force": Constraint(_flag, "True or False", "--force"),
    "max_frames": Constraint(_optional(lambda v: _integer(v) and v >= 1),
                             "an integer >= 1 or None", "--max-frames"),
    "duration_s": Constraint(_optional(lambda v: _number(v) and v > 0), "a number > 0 or None",
                             "--duration"),
    "reconnect": Constraint(_flag, "True or False", "--no-reconnect"),
    "max_reconnects": Constraint(_optional(lambda v: _integer(v) and v >= 0),
                                 "an integer >= 0 or None"),
    "stats_every_s": Constraint(lambda v: _number(v) and not v < 0, "a number >= 0",
                                "--stats-every"),
    "request_timeout_s": Constraint(lambda v: _number(v) and v > 0, "a number > 0"),
    "host_id": Constraint(lambda v: isinstance(v, str), "a string"),
    "scores": Constraint(lambda v: v in SCORE_MODES, "one of " + ", ".join(SCORE_MODES)),
    "volume": Constraint(_optional(_path), "a path or None", "--volume"),
    "deadline_s": Constraint(lambda v: _number(v) and 0 < v < _MAX_DEADLINE_S,
                             f"a number of seconds > 0 and < {_MAX_DEADLINE_S:g}", "--deadline"),
    "rest": Constraint(_rest, "'exact', 'correction' or an object SSIM in (0, 1)",
                       "--rest-quality"),
}

#: `ProvisionOptions`' fields: what each allows.
PROVISION_CONSTRAINTS: Mapping[str, Constraint] = {
    "baud": Constraint(lambda v: _integer(v) and v > 0, "an integer > 0", "--baud"),
    "key": Constraint(_key, "the device key as bytes, or None", "--key"),
    "insecure": Constraint(_flag, "True or False", "--insecure"),
    "force": Constraint(_flag, "True or False", "--force"),
    "chunk_bytes": Constraint(_optional(lambda v: _integer(v) and v >= 1),
                              "an integer >= 1 or None", "--chunk"),
    "retransmit": Constraint(lambda v: v in RETRANSMIT_STRATEGIES,
                             "one of " + ", ".join(RETRANSMIT_STRATEGIES), "--retransmit"),
    "precheck": Constraint(_flag, "True or False"),
    "show_progress": Constraint(_flag, "True or False", "--quiet"),
    "request_timeout_s": Constraint(lambda v: _number(v) and v > 0, "a number > 0",
                                    "--timeout"),
    "inactivity_timeout_s": Constraint(lambda v: _number(v) and v > 0, "a number > 0"),
    "max_reconnects": Constraint(lambda v: _integer(v) and v >= 0, "an integer >= 0"),
    "confirm_timeout_s": Constraint(lambda v: _number(v) and v > 0, "a number > 0"),
    "host_id": Constraint(lambda v: isinstance(v, str), "a string"),
}


def _validate(options: Any, constraints: Mapping[str, Constraint]) -> None:
    """Raise `OptionError` for the first field of ``options`` its constraint refuses."""
    for f in fields(options):
        value = getattr(options, f.name)
        if not constraints[f.name].test(value):
            raise OptionError(f.name, value, constraints[f.name].allowed)


def _from_cli(cls: type, constraints: Mapping[str, Constraint], values: dict,
              typed: Mapping[str, tuple[Any, str]] | None = None) -> Any:
    """``cls(**values)``; an `OptionError` said with the command line's flag and text
    (``typed``: field -> what was typed and what the command line allows, where they differ
    from the field's value and its constraint, e.g. milliseconds for seconds)."""
    try:
        return cls(**values)
    except OptionError as exc:
        flag = constraints[exc.option].flag
        if flag is None:
            raise
        text, allowed = (typed or {}).get(exc.option, (exc.value, exc.allowed))
        raise EigencastError(f"{flag} {text}: expected {allowed}") from None


@dataclass(frozen=True)
class ServeOptions:
    """What a user chooses for :func:`host.link.serving.serve` (validated when built).

    Attributes
    ----------
    key : bytes, optional
        Device key (needed when the device holds one; also verifies the image's tag).
    insecure : bool
        With ``key``: serve a device that says it holds no key anyway (unauthenticated; said
        once through the log). Without it such a device is refused (AuthenticationError).
    baud : int
        Serial line rate.
    orbit : OrbitSpec, optional
        Drive the view from the host (VIEW_REQUESTs are then only counted).
    fps : float
        Packets per second at most (0: as fast as the link carries them).
    keyframe_interval : int
        See `host.link.encoding.FrameEncoder` (1: key frames only).
    provision_missing : bool
        Install the image first when the device's active image is another one.
    force : bool
        With ``provision_missing``: install it even when it is an older generation than
        the device's active image (a rollback; see `host.link.provisioning.provision`).
    max_frames, duration_s : optional
        Stop after this many packets / this many seconds after the first session began
        (time spent reconnecting counts).
    reconnect : bool
        Reconnect after a lost link (with backoff); False: return. A first connection
        that fails raises (reconnecting is for a link that was up).
    max_reconnects : int, optional
        Give up after this many failed connection attempts in a row (default: never).
    stats_every_s : float
        Period of the statistics line (0: none).
    request_timeout_s : float
        First reply timeout of each request, seconds.
    host_id : str
        How the host names itself in HELLO.
    scores : {"auto", "motion", "interpolate"}
        ``"auto"``: the one served path (`host.link.serving`). ``"motion"``: the scores of a
        sparse ray-cast of every view to any device, as an older device gets them;
        ``"interpolate"``: the training views' scores interpolated at the view (no ray-cast).
    volume : str, optional
        The volume to ray-cast instead of the one the model records (a moved file).
    deadline_s : float
        The frame budget, seconds; ``fps`` and the link's measured time per packet lengthen
        it when they are slower.
    rest : {"exact", "correction"} or float
        What a view the user stops on becomes: the exact ray-cast, the eigenspace's best
        frame only, or refined until its object SSIM reaches the number.
    """

    key: bytes | None = None
    insecure: bool = False
    baud: int = 115200
    orbit: OrbitSpec | None = None
    fps: float = 60.0
    keyframe_interval: int = 0
    provision_missing: bool = False
    force: bool = False
    max_frames: int | None = None
    duration_s: float | None = None
    reconnect: bool = True
    max_reconnects: int | None = None
    stats_every_s: float = 5.0
    request_timeout_s: float = 1.0
    host_id: str = "eigencast serve"
    scores: str = "auto"
    volume: str | None = None
    deadline_s: float = DEFAULT_DEADLINE_S
    rest: str | float = "exact"

    def __post_init__(self) -> None:
        _validate(self, SERVE_CONSTRAINTS)

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> ServeOptions:
        """The options ``eigencast serve``'s parsed command line chooses; a bad one is one
        line naming its flag, its value and what is allowed. The key stays None: the
        command reads ``--key``'s file once the options are valid
        (``dataclasses.replace(options, key=...)``)."""
        from device_runtime.orbit import parse_orbit

        if args.force and not args.provision:
            raise EigencastError("--force only applies with --provision (it allows installing "
                                 "an older image generation)")
        orbit = None
        if args.orbit is not None:
            try:
                orbit = parse_orbit(args.orbit)
            except ValueError as exc:
                raise EigencastError(f"--orbit: {exc}") from None
        rest: Any = args.rest_quality
        if rest not in ("exact", "correction"):
            with contextlib.suppress(ValueError):
                rest = float(rest)
        deadline_ms = args.deadline
        values = dict(
            insecure=args.insecure, baud=args.baud, orbit=orbit, fps=args.fps,
            keyframe_interval=args.keyframe_interval, provision_missing=args.provision,
            force=args.force, max_frames=args.max_frames, duration_s=args.duration,
            reconnect=not args.no_reconnect, stats_every_s=args.stats_every,
            volume=args.volume, rest=rest,
            deadline_s=DEFAULT_DEADLINE_S if deadline_ms is None else deadline_ms / 1000.0,
        )
        return _from_cli(cls, SERVE_CONSTRAINTS, values, {
            "rest": (args.rest_quality, SERVE_CONSTRAINTS["rest"].allowed),
            "deadline_s": (deadline_ms, "a number of milliseconds > 0 and < "
                                        f"{_MAX_DEADLINE_S * 1000:g}"),
        })


@dataclass(frozen=True)
class ServeParts:
    """What a caller hands :func:`host.link.serving.serve` to work with (all optional:
    the defaults are what ``eigencast serve`` uses).

    Attributes
    ----------
    model : HostModel, optional
        Already loaded from the model path.
    renderer : host.render.settings.ViewRenderer, optional
        The ray-caster (default: the model's recorded render settings and volume, or the
        options' ``volume``; when that cannot be loaded, ``"auto"`` says so in one line and
        sends what needs no ray-cast).
    motion : host.fit.motion.MotionScores, optional
        The sparse source (default: built on the renderer when a session needs it): built
        with ``own`` (its frames are corrections) it serves devices that correct their own
        frames, else those that do not. A caller may pass one already prepared
        (`MotionScores.prepare`: its recovery factors computed) and keep it across calls.
    transport_factory : callable, optional
        ``factory(attempt) -> Transport`` instead of opening the URL.
    stop : threading.Event, optional
        Set it to end serving (the session ends with BYE).
    log : callable, optional
        One line per event (default: stderr).
    on_frame : callable, optional
        ``on_frame(encoded, view)`` after each packet is queued.
    """

    model: Any | None = None
    renderer: Any | None = None
    motion: Any | None = None
    transport_factory: Callable[[int], Any] | None = None
    stop: threading.Event | None = None
    log: Callable[[str], None] | None = None
    on_frame: Callable[[Any, tuple[float, float]], None] | None = None


@dataclass(frozen=True)
class ProvisionOptions:
    """What a user chooses for :func:`host.link.provisioning.provision` (validated when
    built).

    Attributes
    ----------
    baud : int
        Serial line rate.
    key : bytes, optional
        The device key (needed when the device holds one).
    insecure : bool
        With ``key``: install on a device that says it holds no key anyway (unauthenticated;
        said once through the log). Without it such a device is refused
        (:class:`~protocol.errors.AuthenticationError`) before anything is sent.
    force : bool
        Allow installing an older image generation (rollback).
    chunk_bytes : int, optional
        Data bytes per chunk (default: `host.link.provisioning.choose_chunk_bytes`).
    retransmit : {"selective", "go-back-n"}
        Loss recovery of the chunk window (:func:`protocol.image_transfer.send_image`).
    precheck : bool
        Refuse on the host what the device would refuse (off in tests of the device).
    show_progress : bool
        Progress bar / lines on stderr.
    request_timeout_s : float
        First reply timeout of each request (retries back off).
    inactivity_timeout_s : float
        A transfer with no progress for this long counts as a lost link.
    max_reconnects : int
        Reconnections in a row without progress before giving up.
    confirm_timeout_s : float
        How long to wait for the device's "confirmed" NOTICE after the commit.
    host_id : str
        How the host names itself in HELLO.
    """

    baud: int = 115200
    key: bytes | None = None
    insecure: bool = False
    force: bool = False
    chunk_bytes: int | None = None
    retransmit: str = "selective"
    precheck: bool = True
    show_progress: bool = True
    request_timeout_s: float = 1.0
    inactivity_timeout_s: float = 15.0
    max_reconnects: int = 8
    confirm_timeout_s: float = 5.0
    host_id: str = "eigencast"

    def __post_init__(self) -> None:
        _validate(self, PROVISION_CONSTRAINTS)

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> ProvisionOptions:
        """The options ``eigencast provision``'s parsed command line chooses; a bad one is
        one line naming its flag, its value and what is allowed. The key stays None, as
        `ServeOptions.from_args`'s."""
        values = dict(
            baud=args.baud, insecure=args.insecure, force=args.force,
            chunk_bytes=args.chunk, retransmit=args.retransmit, request_timeout_s=args.timeout,
            show_progress=not (args.quiet or args.json),
        )
        return _from_cli(cls, PROVISION_CONSTRAINTS, values)


@dataclass(frozen=True)
class ProvisionParts:
    """What a caller hands :func:`host.link.provisioning.provision` to work with (all
    optional).

    Attributes
    ----------
    transport_factory : callable, optional
        ``factory(attempt) -> Transport`` instead of opening the URL.
    on_progress : callable, optional
        ``on_progress(acked_offset, size_bytes)`` during the transfer.
    on_stage : callable, optional
        ``on_stage(name)`` at "connect", "hello", "status", "begin", "transfer",
        "verify", "commit", "done".
    log : callable, optional
        One line per step (default: stderr).
    """

    transport_factory: Callable[[int], Any] | None = None
    on_progress: Callable[[int, int], None] | None = None
    on_stage: Callable[[str], None] | None = None
    log: Callable[[str], None] | None = None


