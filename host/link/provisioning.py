"""Provisioning: install an eigenspace image (``.ecs``) on a device over any transport.

:func:`provision` does, in order (docs/protocol.md, "Provisioning"):

1. validate the whole file as ``view``/``serve``/``evaluate`` do
   (:func:`host.fit.model.read_model_image`: sections, tag, declared annex, no
   trailing bytes), read its header and manifest, hash the *device image* (the
   first ``image_size`` bytes; a host annex after it stays on the host);
2. connect, HELLO (version negotiation), mutual AUTH (session key);
3. compare digests with the device's slots: the active slot already holds the
   image -> nothing to do; the other slot holds it (verified, not bad) ->
   SLOT_SET ACTIVATE instead of a transfer;
4. check what the device declared (format versions, slot size, RAM budget,
   image generation) so a refusal is one clear line before any byte is sent;
5. IMAGE_STATUS (resume point), IMAGE_BEGIN (signed), windowed chunks with a
   progress bar (bytes, rate, ETA);
6. on a disconnect or a silent device: reconnect with exponential backoff,
   HELLO, AUTH, IMAGE_STATUS, IMAGE_BEGIN and carry on from the offset the
   device names (after a device reboot: its journal's verified prefix);
7. IMAGE_VERIFY (the device re-reads the slot: SHA-256 and the HMAC tag with
   its key), IMAGE_COMMIT (test state), and wait briefly for the device's
   NOTICE that it loaded and confirmed the image.

The steps are the methods of ``_Provisioning`` (``_open``, ``_first_contact``, ``_begin``,
``_send_image``, ``_verify``, ``_commit``, ``_await_confirmation``, ``_back_off``), in that
order in ``_Provisioning._attempt``; :func:`provision` only inspects the image, maps it and
runs them.

Refusals by the device arrive as :class:`~protocol.errors.RemoteError`
subclasses (one line each); the host's own pre-checks raise
:class:`ProvisionError`. Both are user errors (exit code 1 in the CLI).
"""

from __future__ import annotations

import contextlib
import hashlib
import mmap
import os
import queue
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from device_runtime.image_receiver import required_ram_bytes
from host.errors import EigencastError
from host.link.options import ProvisionOptions, ProvisionParts
from protocol import messages as m
from protocol.errors import (
    ImageFormatError,
    RemoteNoImage,
    TransportClosed,
    TransportError,
    TransportTimeout,
)
from protocol.host_session import HostSession
from protocol.image import (
    HEADER_SIZE,
    ImageTagError,
    parse_header,
    read_manifest,
    verify_stream,
)
from protocol.image_transfer import send_image
from protocol.link import CHUNK_OVERHEAD_BYTES, Link
from protocol.transport import open_transport

__all__ = [
    "CHUNK_LATENCY_S",
    "ImageInfo",
    "ProvisionError",
    "ProvisionOptions",
    "ProvisionParts",
    "ProvisionResult",
    "choose_chunk_bytes",
    "inspect_image",
    "provision",
]

CHUNK_LATENCY_S = 0.08
"""On a serial line a chunk takes at most about this long on the wire, so a
control or score frame never waits longer than that behind one (seconds)."""
_MIN_SERIAL_CHUNK = 256
_SERIAL_SCHEMES = ("", "mem", "rfc2217", "loop")
_MB = 1024 * 1024


class ProvisionError(EigencastError):
    """The image cannot be installed on this device (found before sending it)."""


# --------------------------------------------------------------------------- image


@dataclass(frozen=True)
class ImageInfo:
    """What provisioning needs to know about a ``.ecs`` file.

    Attributes
    ----------
    path : Path
    size_bytes : int
        Size of the device image (what is sent; an annex after it is not).
    digest : bytes
        SHA-256 of those ``size_bytes`` bytes (the slot digest a device reports).
    tag : bytes
        The image's HMAC tag (its last 32 bytes; zeros when unsigned).
    signed : bool
    tag_verified : bool
        The tag was checked with the host's key and matched.
    format_version : int
    generation : int
    ram_bytes : int
        RAM the device needs for it (:func:`device_runtime.image_receiver.required_ram_bytes`).
    """

    path: Path
    size_bytes: int
    digest: bytes
    tag: bytes
    signed: bool
    tag_verified: bool
    format_version: int
    generation: int
    ram_bytes: int


def inspect_image(
    path: str | os.PathLike, *, key: bytes | None = None, whole_file: bool = True
) -> ImageInfo:
    """Read an image's header and manifest, hash its device part, check its tag with ``key``.

    Parameters
    ----------
    path : path-like
    key : bytes, optional
        A signed image's tag must match it.
    whole_file : bool
        Also validate the whole file as ``view``, ``serve`` and ``evaluate`` do
        (:func:`host.fit.model.read_model_image`: every section, the declared annex, no
        trailing bytes). Off only to send malformed images on purpose (device tests).

    Raises
    ------
    ProvisionError
        Missing file, not an eigencast image, corrupt (digest, sections, annex), trailing
        bytes, or signed with another key; one line that ends "nothing was installed".
    """
    path = Path(path)
    if not path.is_file():
        raise ProvisionError(f"image '{path}' not found; nothing was installed")
    if whole_file:
        from host.fit.model import read_model_image

        try:
            read_model_image(path, key=key)
        except ImageTagError:
            pass  # said below, with what the device would answer
        except ImageFormatError as exc:
            raise ProvisionError(f"{exc}; nothing was installed") from None
    try:
        with open(path, "rb") as handle:
            header = parse_header(handle.read(HEADER_SIZE), what=f"image '{path}'")
            handle.seek(0)
            manifest = read_manifest(handle)
            handle.seek(0)
            _, tag_ok = verify_stream(handle, key)
            handle.seek(0)
            hasher = hashlib.sha256()
            left = header.image_size
            while left:
                block = handle.read(min(left, 1 << 20))
                if not block:
                    raise ProvisionError(f"image '{path}' is truncated")
                hasher.update(block)
                left -= len(block)
            handle.seek(header.image_size - 32)
            tag = handle.read(32)
        ram = required_ram_bytes(manifest)
    except ImageFormatError as exc:
        raise ProvisionError(f"{exc}; nothing was installed") from None
    if key is not None and header.signed and not tag_ok:
        raise ProvisionError(
            f"image '{path}' was signed with a different key than the one given "
            "(the device would refuse it: TAG_MISMATCH); nothing was installed"
        )
    generation = manifest.get("image_generation")
    return ImageInfo(
        path=path,
        size_bytes=header.image_size,
        digest=hasher.digest(),
        tag=tag,
        signed=header.signed,
        tag_verified=bool(tag_ok),
        format_version=header.format_version,
        generation=int(generation) if isinstance(generation, int) else 0,
        ram_bytes=ram,
    )


# --------------------------------------------------------------------------- result


@dataclass
class ProvisionResult:
    """What :func:`provision` did.

    Attributes
    ----------
    outcome : str
        ``"installed"`` (sent and committed), ``"already-active"`` (nothing to
        do) or ``"activated"`` (the other slot already held it).
    device_id : str
    slot : str
        ``"A"`` or ``"B"``: where the image is active now.
    digest : str
        Hex SHA-256 of the device image.
    size_bytes : int
    resumed_from : int
        Offset the first transfer attempt started at (0: from scratch).
    reconnects : int
        Reconnections after a lost link.
    data_bytes_sent, wire_bytes_sent : int
        Image bytes in chunk frames (retransmissions included) and their encoded size.
    retransmitted_chunks, timeouts : int
    transfer_seconds : float
        Time spent streaming chunks (all attempts).
    seconds : float
        Whole run.
    confirmed : bool or None
        The device reported it loaded and confirmed the image (None: no report in time).
    verified : bool
        The device re-read the slot and its digest (and tag) matched.
    """

    outcome: str
    device_id: str
    slot: str
    digest: str
    size_bytes: int
    resumed_from: int = 0
    resume_offsets: list[int] = field(default_factory=list)
    reconnects: int = 0
    data_bytes_sent: int = 0
    wire_bytes_sent: int = 0
    retransmitted_chunks: int = 0
    timeouts: int = 0
    transfer_seconds: float = 0.0
    seconds: float = 0.0
    confirmed: bool | None = None
    verified: bool = False

    @property
    def rate_bytes_per_s(self) -> float:
        """Image bytes delivered per second of transfer."""
        sent = self.size_bytes - self.resumed_from
        return sent / self.transfer_seconds if self.transfer_seconds > 0 else 0.0

    def as_dict(self) -> dict[str, Any]:
        """JSON-serialisable summary."""
        out = dict(self.__dict__)
        out["rate_bytes_per_s"] = self.rate_bytes_per_s
        return out


# --------------------------------------------------------------------------- progress


class _TransferProgress:
    """Bytes, rate and ETA: a rich bar on a terminal, a line per 10 % elsewhere."""

    def __init__(self, total: int, description: str, *, enabled: bool) -> None:
        self.total = total
        self.description = description
        self.enabled = enabled
        self._rich: Any = None
        self._task: Any = None
        self._start = time.monotonic()
        self._start_bytes = 0
        self._next = 0.1
        self.done = 0

    def __enter__(self) -> _TransferProgress:
        if self.enabled and sys.stderr.isatty():
            from rich.progress import (
                BarColumn,
                DownloadColumn,
                Progress,
                TextColumn,
                TimeRemainingColumn,
                TransferSpeedColumn,
            )

            self._rich = Progress(
                TextColumn("{task.description}"),
                BarColumn(),
                DownloadColumn(binary_units=True),
                TransferSpeedColumn(),
                TextColumn("ETA"),
                TimeRemainingColumn(),
                transient=False,
            )
            self._rich.__enter__()
            self._task = self._rich.add_task(self.description, total=self.total)
        return self

    def start_at(self, offset: int) -> None:
        self._start = time.monotonic()
        self._start_bytes = offset
        self.update(offset)

    def update(self, done: int) -> None:
        self.done = done
        if not self.enabled:
            return
        if self._rich is not None:
            self._rich.update(self._task, completed=done)
            return
        frac = done / self.total if self.total else 1.0
        if frac + 1e-12 < self._next and done < self.total:
            return
        while self._next <= frac:
            self._next += 0.1
        elapsed = max(time.monotonic() - self._start, 1e-9)
        rate = (done - self._start_bytes) / elapsed
        eta = (self.total - done) / rate if rate > 0 else float("nan")
        print(
            f"{self.description}: {done}/{self.total} bytes ({100 * frac:.0f}%), "
            f"{rate / 1024:.1f} KiB/s, ETA {eta:.1f} s",
            file=sys.stderr,
            flush=True,
        )

    def __exit__(self, *exc: object) -> None:
        if self._rich is not None:
            self._rich.__exit__(None, None, None)


# --------------------------------------------------------------------------- provisioning


def choose_chunk_bytes(transport: Any, hello: m.HelloReply, link: Link,
                       requested: int | None = None) -> int:
    """Chunk data size: the device's receive buffer and frame limit, and on a serial line
    no more than ``CHUNK_LATENCY_S`` of wire time (so view requests never wait long)."""
    limit = min(hello.rx_buffer_bytes, link.tx_max_frame_bytes - CHUNK_OVERHEAD_BYTES)
    if requested is not None:
        if requested < 1:
            raise ValueError(f"chunk_bytes={requested} must be >= 1")
        return min(requested, limit)
    scheme = getattr(transport, "scheme", None)
    baud = getattr(transport, "baud", None)
    if scheme in _SERIAL_SCHEMES and baud:
        target = int(baud / 10 * CHUNK_LATENCY_S) // 64 * 64
        limit = min(limit, max(_MIN_SERIAL_CHUNK, target))
    return max(1, limit)


def _precheck(info: ImageInfo, hello: m.HelloReply, *, force: bool) -> None:
    name = f"device '{hello.device_id}'"
    versions = tuple(hello.image_format_versions)
    if versions and info.format_version not in versions:
        raise ProvisionError(
            f"{name} reads image format versions {', '.join(map(str, versions))}; this image "
            f"is version {info.format_version} (UNSUPPORTED_FORMAT)"
        )
    if info.size_bytes > hello.slot_size_bytes:
        raise ProvisionError(
            f"the image is {info.size_bytes} bytes ({info.size_bytes / _MB:.1f} MiB); a flash "
            f"slot of {name} holds {hello.slot_size_bytes} bytes "
            f"({hello.slot_size_bytes / _MB:.1f} MiB) (TOO_LARGE_FOR_FLASH)"
        )
    if info.ram_bytes > hello.ram_budget_bytes:
        raise ProvisionError(
            f"the eigenspace needs {info.ram_bytes} bytes ({info.ram_bytes / _MB:.1f} MiB) of "
            f"RAM; {name} has a budget of {hello.ram_budget_bytes} bytes "
            f"({hello.ram_budget_bytes / _MB:.1f} MiB) (TOO_LARGE_FOR_RAM; fit fewer "
            "components or raise the device's --ram-budget)"
        )
    active = [s for s in hello.slots if s.active]
    if active and info.generation < active[0].generation and not force:
        raise ProvisionError(
            f"image generation {info.generation} is older than the generation "
            f"{active[0].generation} active on {name}; pass --force to roll back "
            "(ROLLBACK_REFUSED)"
        )
    if hello.has_key and not info.signed:
        raise ProvisionError(
            f"the image is not signed and {name} only accepts images signed with its key "
            "(eigencast fit --key KEYFILE) (TAG_MISMATCH)"
        )


class _Notices:
    """Collects NOTICE events from the device (the host link's handler)."""

    def __init__(self) -> None:
        self.queue: queue.Queue[m.Notice] = queue.Queue()

    def __call__(self, msg: m.Message, frame: Any) -> None:
        if isinstance(msg, m.Notice):
            self.queue.put(msg)
        return None

    def wait_confirm(self, timeout_s: float) -> bool | None:
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            try:
                notice = self.queue.get(timeout=left)
            except queue.Empty:
                return None
            event = (notice.detail or {}).get("event")
            if event == "confirmed":
                return True
            if event == "load-failed":
                return False


def provision(
    image_path: str | os.PathLike,
    url: str,
    options: ProvisionOptions | None = None,
    parts: ProvisionParts | None = None,
) -> ProvisionResult:
    """Install the image at ``image_path`` on the device at ``url``.

    Parameters
    ----------
    image_path : path-like
        An ``.ecs`` file (only its device image is sent).
    url : str
        Port URL (``/dev/ttyUSB0``, ``socket://HOST:PORT``, ``mem://...``).
    options : ProvisionOptions, optional
        What the user chose (line rate, key, rollback, chunk size, loss recovery, timeouts
        ...; default: ``ProvisionOptions()``), validated when it was built.
    parts : ProvisionParts, optional
        What the caller hands in: a transport factory, progress and stage callbacks, where
        log lines go.

    Returns
    -------
    ProvisionResult

    Raises
    ------
    ProvisionError
        A pre-check failed (one line).
    RemoteError
        The device refused (one line with its error code).
    TransportError
        The device could not be reached, or the link kept failing.
    """
    o = options if options is not None else ProvisionOptions()
    p = parts if parts is not None else ProvisionParts()
    started = time.monotonic()
    info = inspect_image(image_path, key=o.key if o.precheck else None, whole_file=o.precheck)
    settings = _Settings(
        key=o.key, insecure=o.insecure, force=o.force, chunk_bytes=o.chunk_bytes,
        retransmit=o.retransmit, precheck=o.precheck, request_timeout_s=o.request_timeout_s,
        inactivity_timeout_s=o.inactivity_timeout_s, max_reconnects=o.max_reconnects,
        confirm_timeout_s=o.confirm_timeout_s, host_id=o.host_id,
    )
    factory = p.transport_factory or (
        lambda attempt: open_transport(url, baud=o.baud, timeout_s=max(5.0, o.request_timeout_s))
    )
    with open(info.path, "rb") as handle:
        mapped = mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ)
    try:
        with _TransferProgress(info.size_bytes, "provision", enabled=o.show_progress) as bar:
            run = _Provisioning(
                info, memoryview(mapped)[: info.size_bytes], settings, bar=bar,
                factory=factory, started=started, on_progress=p.on_progress,
                say=p.log or (lambda line: print(f"eigencast provision: {line}",
                                                 file=sys.stderr, flush=True)),
                stage=p.on_stage or (lambda name: None),
            )
            return run.run()
    finally:
        with contextlib.suppress(BufferError):
            mapped.close()


# --------------------------------------------------------------------------- the steps


@dataclass(frozen=True)
class _Settings:
    """The options of :func:`provision` that the steps read (see its parameters)."""

    key: bytes | None
    insecure: bool
    force: bool
    chunk_bytes: int | None
    retransmit: str
    precheck: bool
    request_timeout_s: float
    inactivity_timeout_s: float
    max_reconnects: int
    confirm_timeout_s: float
    host_id: str


@dataclass
class _Connection:
    """One attempt's way to the device: the transport, the link engine on it, the session."""

    transport: Any
    link: Link
    session: HostSession
    notices: _Notices


@dataclass
class _Provisioning:
    """One run of :func:`provision`: its steps in order, and what carries over a reconnect.

    :meth:`run` repeats :meth:`_attempt` (open, handshake, first contact or resume, begin,
    send the image, verify, commit, wait for the confirmation) until one returns, backing
    off between attempts after a lost link (:meth:`_back_off`). ``result`` is None until
    the first handshake passed the pre-checks; from then on an attempt resumes the transfer.
    """

    info: ImageInfo
    data: memoryview
    settings: _Settings
    bar: _TransferProgress
    factory: Callable[[int], Any]
    started: float
    on_progress: Callable[[int, int], None] | None
    say: Callable[[str], None]
    stage: Callable[[str], None]
    result: ProvisionResult | None = None
    link: Link | None = None
    failures: int = 0
    progress_mark: int = -1
    transfer_seconds: float = 0.0
    learned_chunk_bytes: int | None = None

    def run(self) -> ProvisionResult:
        """Attempt until the image is installed (or was there); reconnect on a lost link."""
        attempt = 0
        while True:
            self.stage("connect")
            self.link = None
            try:
                return self._attempt(attempt)
            except (TransportClosed, TransportTimeout, RemoteNoImage) as exc:
                if self.link is not None:
                    self.link.close(flush_timeout_s=0.0)
                if self.result is None and isinstance(exc, RemoteNoImage):
                    raise
                self._back_off(exc)
                attempt += 1
            finally:
                if self.link is not None and not self.link.closed:
                    self.link.close(flush_timeout_s=0.5)

    def _attempt(self, attempt: int) -> ProvisionResult:
        conn = self._open(attempt)
        self.stage("hello")
        hello = conn.session.start()
        if self.result is not None and _holds_active(hello, self.info):
            return self._committed_before_the_link_dropped(conn, hello)
        if self.result is None:
            done = self._first_contact(conn, hello)
            if done is not None:
                return done
        else:
            self.result.reconnects += 1
        ack, transfer_id = self._begin(conn)
        self._send_image(conn, hello, ack, transfer_id)
        verify = self._verify(conn, hello)
        self._commit(conn, verify)
        self._await_confirmation(conn)
        return self._finish(conn, self._started_result(), "provisioned")

    def _started_result(self) -> ProvisionResult:
        assert self.result is not None, "the first contact creates the result"
        return self.result

    def _open(self, attempt: int) -> _Connection:
        """Open the transport and start the link engine and a host session on it."""
        transport = self.factory(attempt)
        notices = _Notices()
        self.link = Link(transport, handler=notices, owns_transport=True).start()
        session = HostSession(
            self.link, key=self.settings.key, host_id=self.settings.host_id,
            request_timeout_s=self.settings.request_timeout_s, insecure=self.settings.insecure,
        )
        return _Connection(transport, self.link, session, notices)

    def _committed_before_the_link_dropped(
        self, conn: _Connection, hello: m.HelloReply
    ) -> ProvisionResult:
        result = self._started_result()
        result.reconnects += 1
        result.verified = True
        result.slot = _active_slot(hello.slots)
        return self._finish(conn, result, "done")

    def _first_contact(self, conn: _Connection, hello: m.HelloReply) -> ProvisionResult | None:
        """Name the device, skip the transfer if a slot holds the image, pre-check the rest.

        Returns the finished result when there is nothing to send; otherwise creates
        ``self.result`` and returns None.
        """
        session = conn.session
        self.say(
            f"device '{hello.device_id}' ({hello.software or 'unknown software'}"
            f", protocol {session.version}"
            f"{', authenticated' if session.authenticated else ', no key'})"
        )
        if self.settings.key is not None and not session.authenticated:
            self.say(f"WARNING: --insecure: device '{hello.device_id}' holds no key; "
                     "sending the image unauthenticated")
        done = _already_there(session, hello, self.info, force=self.settings.force, say=self.say)
        if done is not None:
            return self._finish(conn, done, "done")
        if self.settings.precheck:
            _precheck(self.info, hello, force=self.settings.force)
        self.result = ProvisionResult(
            outcome="installed",
            device_id=hello.device_id,
            slot="",
            digest=self.info.digest.hex(),
            size_bytes=self.info.size_bytes,
        )
        return None

    def _begin(self, conn: _Connection) -> tuple[m.ImageAck, int]:
        """IMAGE_STATUS, then IMAGE_BEGIN: the device names the offset to carry on from."""
        info, result = self.info, self._started_result()
        self.stage("status")
        status = conn.session.call(m.ImageStatus(digest=info.digest, size_bytes=info.size_bytes))
        assert isinstance(status, m.ImageStatusReply)
        self.stage("begin")
        answered: dict[str, int] = {}
        ack = conn.session.call(
            m.ImageBegin(
                size_bytes=info.size_bytes,
                digest=info.digest,
                image_tag=info.tag,
                format_version=info.format_version,
                generation=info.generation,
                force=self.settings.force,
            ),
            on_reply=lambda rid, reply, box=answered: box.__setitem__("id", rid),
        )
        assert isinstance(ack, m.ImageAck)
        result.resume_offsets.append(ack.next_offset)
        if len(result.resume_offsets) == 1:
            result.resumed_from = ack.next_offset
        if ack.next_offset:
            self.say(f"resuming at byte {ack.next_offset} of {info.size_bytes}")
        return ack, answered["id"]

    def _send_image(
        self, conn: _Connection, hello: m.HelloReply, ack: m.ImageAck, transfer_id: int
    ) -> None:
        """Stream the chunks from ``ack.next_offset`` (windowed, with retransmission)."""
        result = self._started_result()
        chunk = choose_chunk_bytes(conn.transport, hello, conn.link, self.settings.chunk_bytes)
        if getattr(conn.transport, "scheme", None) in _SERIAL_SCHEMES:
            # keep about one chunk in the port's buffer: frames that jump the
            # queue then wait behind at most ~CHUNK_LATENCY_S of wire time
            conn.link.tx_low_water_bytes = chunk + CHUNK_OVERHEAD_BYTES
        self.stage("transfer")
        self.bar.start_at(ack.next_offset)
        t0 = time.monotonic()
        try:
            stats = send_image(
                conn.link,
                self.data,
                transfer_id=transfer_id,
                first_ack=ack,
                chunk_bytes=chunk,
                inactivity_timeout_s=self.settings.inactivity_timeout_s,
                retransmit=self.settings.retransmit,
                on_progress=self._progressed,
                initial_chunk_bytes=self.learned_chunk_bytes,
                tag=conn.session.tag_event,
            )
            self.learned_chunk_bytes = stats.final_chunk_bytes
        finally:
            self.transfer_seconds += time.monotonic() - t0
            result.transfer_seconds = self.transfer_seconds
        result.data_bytes_sent += stats.data_bytes_sent
        result.wire_bytes_sent += stats.wire_bytes_sent
        result.retransmitted_chunks += stats.retransmitted_chunks
        result.timeouts += stats.timeouts

    def _progressed(self, offset: int) -> None:
        self.bar.update(offset)
        if self.on_progress is not None:
            self.on_progress(offset, self.info.size_bytes)

    def _verify(self, conn: _Connection, hello: m.HelloReply) -> m.ImageVerifyReply:
        """IMAGE_VERIFY: the device re-reads the slot; its digest must be the image's."""
        info = self.info
        self.stage("verify")
        verify = conn.session.call(
            m.ImageVerify(digest=info.digest),
            timeout_s=max(self.settings.request_timeout_s, 2.0 + info.size_bytes / (10 * _MB)),
            retries=3,
        )
        assert isinstance(verify, m.ImageVerifyReply)
        if not verify.ok or verify.digest != info.digest:
            raise ProvisionError(
                f"device '{hello.device_id}' could not verify the image it received"
            )
        self._started_result().verified = True
        return verify

    def _commit(self, conn: _Connection, verify: m.ImageVerifyReply) -> None:
        """IMAGE_COMMIT: the slot becomes active in the test state."""
        info, result = self.info, self._started_result()
        self.stage("commit")
        status_reply = conn.session.call(m.ImageCommit(digest=info.digest))
        assert isinstance(status_reply, m.SlotStatus)
        result.slot = _active_slot(status_reply.slots)
        self.say(
            f"sent {info.size_bytes} bytes, verified (sha256 "
            f"{info.digest.hex()[:16]}, tag {'ok' if verify.tag_ok else 'unchecked'})"
            f", committed to slot {result.slot}"
        )

    def _await_confirmation(self, conn: _Connection) -> None:
        """Wait briefly for the device's NOTICE that it loaded and confirmed the image."""
        result = self._started_result()
        result.confirmed = conn.notices.wait_confirm(self.settings.confirm_timeout_s)
        if result.confirmed:
            self.say(f"device confirmed the image in slot {result.slot}")
        elif result.confirmed is False:
            self.say("device could not load the image and reverted")

    def _finish(self, conn: _Connection, result: ProvisionResult, why: str) -> ProvisionResult:
        """BYE with ``why``; the run's time; the "done" stage."""
        conn.session.bye(why)
        result.seconds = time.monotonic() - self.started
        self.stage("done")
        return result

    def _back_off(self, exc: BaseException) -> None:
        """Wait before reconnecting (exponential); give up after too many without progress."""
        mark = self.bar.done
        self.failures = 0 if mark > self.progress_mark else self.failures + 1
        self.progress_mark = max(self.progress_mark, mark)
        if self.failures > self.settings.max_reconnects:
            raise TransportError(
                f"gave up after {self.failures} reconnects without progress: {exc}"
            ) from None
        delay = min(0.05 * 2**self.failures, 2.0)
        self.say(f"link lost ({_short(exc)}); reconnecting in {delay:.2f} s")
        time.sleep(delay)  # reconnect backoff (a protocol timer)


def _short(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text if len(text) <= 120 else text[:117] + "..."


def _active_slot(slots: tuple[m.SlotInfo, ...]) -> str:
    for info in slots:
        if info.active:
            return "AB"[info.slot] if info.slot < 2 else str(info.slot)
    return "?"


def _holds_active(hello: m.HelloReply, info: ImageInfo) -> bool:
    return any(
        s.active and s.digest == info.digest
        and s.state in (m.SlotState.TEST, m.SlotState.CONFIRMED)
        for s in hello.slots
    )


def _already_there(
    session: HostSession,
    hello: m.HelloReply,
    info: ImageInfo,
    *,
    force: bool,
    say: Callable[[str], None],
) -> ProvisionResult | None:
    """Skip the transfer when a slot already holds this image (see the module docstring)."""
    usable = (m.SlotState.TEST, m.SlotState.CONFIRMED)
    for slot in hello.slots:
        if slot.digest != info.digest or slot.state not in usable:
            continue
        name = "AB"[slot.slot] if slot.slot < 2 else str(slot.slot)
        base = ProvisionResult(
            outcome="already-active",
            device_id=hello.device_id,
            slot=name,
            digest=info.digest.hex(),
            size_bytes=info.size_bytes,
            verified=True,
            confirmed=slot.state == m.SlotState.CONFIRMED,
        )
        if slot.active:
            state = "confirmed" if slot.state == m.SlotState.CONFIRMED else "test"
            say(f"slot {name} already holds this image and it is active ({state}); "
                "nothing to send")
            return base
        reply = session.call(m.SlotSet(action=m.SlotAction.ACTIVATE, slot=slot.slot, force=force))
        assert isinstance(reply, m.SlotStatus)
        base.outcome = "activated"
        base.slot = _active_slot(reply.slots)
        say(f"slot {name} already held this image; activated it instead of sending it again")
        return base
    return None

