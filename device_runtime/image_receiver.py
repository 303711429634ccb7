"""The device's image receiver: what it accepts as an image, and the IMAGE_* handlers.

Two halves of one job, receiving an eigenspace image (docs/protocol.md, "Provisioning"):

* what this device can load: :func:`required_ram_bytes` (the RAM an image's manifest
  declares it needs), :func:`read_device_image` (read and check an image within a RAM
  budget) and :func:`image_problem` (the same, as one line or None);
* :class:`ImageReceiver`, the transfer state machine of :class:`~device_runtime.device.Device`
  (IMAGE_STATUS, IMAGE_BEGIN, IMAGE_CHUNK, IMAGE_VERIFY, IMAGE_COMMIT, IMAGE_ABORT) over
  the flash store's :class:`~device_runtime.image_writer.ImageWriter`: the header and
  manifest checked as soon as their bytes arrive, acks with credits, verify by re-reading
  the slot, commit as a test image. See the transfer state machine in
  :mod:`device_runtime.device`.

:class:`ImageReceiver` is a mixin: it holds no state of its own and uses the device's
(``session``, ``store``, ``config``, ``stats``, ``link``, ``log``, ``notice``, ``_send``,
``_slot_infos``, ``_load_and_confirm``, ``_after_activation``, ``_map_error``); the
session/auth dispatcher that routes messages to these handlers stays in ``device.py``.
"""

from __future__ import annotations

import contextlib
import hmac
import io
import time
from dataclasses import dataclass, field
from typing import Any

from device_runtime.errors import BudgetError, DeviceError, FlashError
from device_runtime.image_writer import ImageWriter
from device_runtime.reconstruct import reconstruction_memory_bytes
from device_runtime.synthesis import check_synthesis, synthesis_memory_bytes
from device_runtime.wire_errors import DeviceRefusal, _one_line
from protocol import messages as m
from protocol.errors import ImageFormatError, NotAuthenticated, ProtocolError
from protocol.framing import Frame
from protocol.image import (
    DEVICE_SECTIONS,
    HEADER_SIZE,
    MAX_MANIFEST_BYTES,
    SUPPORTED_VERSIONS,
    ImageTagError,
    parse_header,
    read_image,
    read_manifest,
)

__all__ = ["ImageReceiver", "image_problem", "read_device_image", "required_ram_bytes"]

_MAX_TOLD_NO_TRANSFER = 64


def required_ram_bytes(manifest: dict) -> int:
    """RAM an image needs on the device, from its manifest's declared sizes, in bytes.

    The reconstruction's arrays, frame buffers and scratch
    (:func:`device_runtime.reconstruct.reconstruction_memory_bytes`, from the
    image and cell shapes and the number of components) plus the decompressed
    size of every extra section, plus the view synthesis' cache and scratch when the
    image names one (:func:`device_runtime.synthesis.synthesis_memory_bytes`). A
    synthesis method this device does not know refuses the image here (one line).

    Parameters
    ----------
    manifest : dict
        As returned by :func:`protocol.image.read_manifest` (untrusted).

    Raises
    ------
    ImageFormatError
        A field this needs is missing or of the wrong type.
    """

    def ints(value: Any, n: int | None, what: str) -> list[int]:
        if not isinstance(value, list) or (n is not None and len(value) != n) or not all(
            isinstance(v, int) and not isinstance(v, bool) and 0 <= v < 1 << 62 for v in value
        ):
            raise ImageFormatError(f"image manifest: '{what}' is not a list of non-negative ints")
        return value

    image_shape = ints(manifest.get("image_shape"), 2, "image_shape")
    cell_shape = ints(manifest.get("cell_shape"), 2, "cell_shape")
    if min(*image_shape, *cell_shape) < 1:
        raise ImageFormatError("image manifest: image_shape and cell_shape must be positive")
    sections = manifest.get("sections")
    if not isinstance(sections, list):
        raise ImageFormatError("image manifest: 'sections' is not a list")
    n_coefficients = 0
    extra = 0
    for entry in sections:
        if not isinstance(entry, dict) or not isinstance(entry.get("name"), str):
            raise ImageFormatError("image manifest: a section entry has no name")
        raw = entry.get("raw_size")
        if not isinstance(raw, int) or isinstance(raw, bool) or raw < 0:
            raise ImageFormatError(f"image manifest: section '{entry['name'][:64]}' raw_size")
        if entry["name"] == "eigenimages":
            shape = ints(entry.get("shape"), None, "eigenimages shape")
            n_coefficients = shape[0] if shape else 0
        elif entry["name"] not in DEVICE_SECTIONS:
            extra += raw
    base = reconstruction_memory_bytes(
        (image_shape[0], image_shape[1]), (cell_shape[0], cell_shape[1]), n_coefficients
    )
    check_synthesis(manifest.get("synthesis"), (image_shape[0], image_shape[1]))
    return int(base + extra + synthesis_memory_bytes(manifest))


def read_device_image(stream: Any, *, key: bytes | None, ram_budget_bytes: int) -> Any:
    """Read and validate an image exactly as a device with ``key`` and budget loads it.

    The RAM the image needs (:func:`required_ram_bytes`, from its manifest) must fit
    ``ram_budget_bytes``; then the whole image is read within that budget: structure,
    digest and, on a device with a key, a tag made with that key (unsigned images are
    refused). Boot, the fallback and ``eigencast-device --status`` use this one check.

    Parameters
    ----------
    stream : binary file
        Seekable, positioned at the image's first byte (a flash slot).
    key : bytes or None
        The device key (None: a keyless device, which does not check tags).
    ram_budget_bytes : int

    Returns
    -------
    EigenspaceImage

    Raises
    ------
    ImageFormatError, ImageTagError, BudgetError
    """
    max_manifest = min(MAX_MANIFEST_BYTES, ram_budget_bytes)
    manifest = read_manifest(stream, max_manifest_bytes=max_manifest)
    need = required_ram_bytes(manifest)
    if need > ram_budget_bytes:
        raise BudgetError(f"the image needs {need} bytes of RAM, the budget is {ram_budget_bytes}")
    stream.seek(0)
    return read_image(
        stream,
        key=key,
        require_tag=key is not None,
        max_manifest_bytes=max_manifest,
        max_section_bytes=ram_budget_bytes,
        max_total_bytes=ram_budget_bytes,
        read_annex=False,
    )


def image_problem(stream: Any, *, key: bytes | None, ram_budget_bytes: int) -> str | None:
    """None when :func:`read_device_image` accepts the image, else why not (one line)."""
    try:
        read_device_image(stream, key=key, ram_budget_bytes=ram_budget_bytes)
    except (ProtocolError, DeviceError, OSError, ValueError) as exc:
        return _one_line(str(exc), 200) or type(exc).__name__
    return None


@dataclass
class _Transfer:
    request_id: int
    digest: bytes
    size_bytes: int
    image_tag: bytes
    format_version: int
    generation: int
    force: bool
    writer: ImageWriter
    window_bytes: int
    header_checked: bool = False
    manifest_checked: bool = False
    verified: bool = False
    tag_ok: bool = False
    chunks_since_ack: int = 0
    last_flush: float = field(default_factory=time.monotonic)
    manifest_size: int = 0


class ImageReceiver:
    """The IMAGE_* handlers of :class:`~device_runtime.device.Device` (see the module docstring)."""

    def handle_image_status(self, msg: m.ImageStatus, frame: Frame) -> m.Message:
        """Where would a transfer of that image resume? (keyed device: after AUTH only)"""
        if self.config.key is not None and not self.session.authenticated:
            raise NotAuthenticated(
                "IMAGE_STATUS needs an authenticated session (HELLO, then AUTH_CHALLENGE)"
            )
        transfer = self.session.transfer
        if transfer is not None and transfer.digest == msg.digest and not transfer.writer.closed:
            return m.ImageStatusReply(next_offset=transfer.writer.next_offset, in_progress=True)
        journal = self.store.status(verify=False)["journal"]
        if (
            journal is None
            or journal["sha256"] != msg.digest.hex()
            or journal["size_bytes"] != msg.size_bytes
        ):
            return m.ImageStatusReply(next_offset=0, in_progress=False)
        return m.ImageStatusReply(
            next_offset=self.store.image_status(msg.digest), in_progress=True
        )

    def handle_image_begin(self, msg: m.ImageBegin, frame: Frame) -> m.Message:
        """Open (or resume) a transfer into the inactive slot; answer the first IMAGE_ACK."""
        if msg.format_version not in SUPPORTED_VERSIONS:
            raise DeviceRefusal(
                m.ErrorCode.UNSUPPORTED_FORMAT,
                f"image format version {msg.format_version} is not supported (this device "
                f"reads {', '.join(map(str, SUPPORTED_VERSIONS))})",
                {"format_version": msg.format_version},
            )
        if msg.size_bytes < HEADER_SIZE + 64:
            raise DeviceRefusal(
                m.ErrorCode.UNSUPPORTED_FORMAT,
                f"{msg.size_bytes} bytes is too small for an eigenspace image (header and "
                f"trailer alone take {HEADER_SIZE + 64})",
            )
        if msg.size_bytes > self.store.capacity_bytes:
            raise DeviceRefusal(
                m.ErrorCode.TOO_LARGE_FOR_FLASH,
                f"the image is {msg.size_bytes} bytes, a flash slot holds "
                f"{self.store.capacity_bytes}",
                {"size_bytes": msg.size_bytes, "limit_bytes": self.store.capacity_bytes},
            )
        self.session.transfer = None
        writer = self.store.begin_image(
            size_bytes=msg.size_bytes,
            sha256=msg.digest,
            image_generation=msg.generation,
            force=msg.force,
            window_bytes=self.window_bytes,
        )
        transfer = _Transfer(
            request_id=frame.request_id,
            digest=msg.digest,
            size_bytes=msg.size_bytes,
            image_tag=msg.image_tag,
            format_version=msg.format_version,
            generation=msg.generation,
            force=msg.force,
            writer=writer,
            window_bytes=self.window_bytes,
        )
        self.session.transfer = transfer
        self._told_no_transfer.discard(frame.request_id)
        try:
            self._check_prefix(transfer)
        except Exception:
            self._drop_transfer()
            raise
        resumed = f", resuming at {writer.next_offset}" if writer.next_offset else ""
        self.log(
            f"image begin: {msg.size_bytes} bytes, sha256 {msg.digest.hex()[:16]}, generation "
            f"{msg.generation} -> slot {writer.slot}{resumed}"
        )
        return m.ImageAck(
            next_offset=writer.next_offset,
            credits=self.config.rx_window_frames,
            window_bytes=min(self.window_bytes, 0xFFFFFFFF),
        )

    def _drop_transfer(self) -> None:
        self.session.transfer = None
        with contextlib.suppress(FlashError):
            self.store.abort_image()

    def _read_slot(self, transfer: _Transfer, offset: int, size: int) -> bytes:
        with open(transfer.writer.path, "rb") as handle:
            handle.seek(offset)
            return handle.read(size)

    def _check_prefix(self, transfer: _Transfer) -> None:
        """Check the header, then the manifest, as soon as their bytes have arrived."""
        received = transfer.writer.next_offset
        if not transfer.header_checked and received >= HEADER_SIZE:
            head = self._read_slot(transfer, 0, HEADER_SIZE)
            try:
                header = parse_header(head, max_manifest_bytes=self._max_manifest_bytes(),
                                      what="received image")
            except ImageFormatError as exc:
                raise DeviceRefusal(m.ErrorCode.UNSUPPORTED_FORMAT, str(exc)) from None
            if header.format_version != transfer.format_version:
                raise DeviceRefusal(
                    m.ErrorCode.UNSUPPORTED_FORMAT,
                    f"IMAGE_BEGIN announced format version {transfer.format_version}, the "
                    f"image header says {header.format_version}",
                )
            if header.image_size != transfer.size_bytes:
                raise DeviceRefusal(
                    m.ErrorCode.MALFORMED,
                    f"IMAGE_BEGIN announced {transfer.size_bytes} bytes, the image header "
                    f"says {header.image_size}",
                )
            transfer.header_checked = True
            transfer.manifest_size = header.manifest_size
        end = HEADER_SIZE + transfer.manifest_size
        if transfer.header_checked and not transfer.manifest_checked and received >= end:
            data = self._read_slot(transfer, 0, end)
            try:
                manifest = read_manifest(io.BytesIO(data),
                                         max_manifest_bytes=self._max_manifest_bytes())
                need = required_ram_bytes(manifest)
                generation = manifest.get("image_generation")
            except ImageFormatError as exc:
                raise DeviceRefusal(m.ErrorCode.UNSUPPORTED_FORMAT, str(exc)) from None
            if need > self.config.ram_budget_bytes:
                raise DeviceRefusal(
                    m.ErrorCode.TOO_LARGE_FOR_RAM,
                    f"the eigenspace needs {need} bytes of RAM, this device's budget is "
                    f"{self.config.ram_budget_bytes}",
                    {"need_bytes": need, "limit_bytes": self.config.ram_budget_bytes},
                )
            if generation != transfer.generation:
                raise DeviceRefusal(
                    m.ErrorCode.MALFORMED,
                    f"IMAGE_BEGIN announced generation {transfer.generation}, the image "
                    f"manifest says {generation!r}",
                )
            transfer.manifest_checked = True

    def handle_image_chunk(self, msg: m.ImageChunk, frame: Frame) -> None:
        """Write a chunk (idempotent by offset) and acknowledge cumulatively."""
        transfer = self.session.transfer
        tid = frame.request_id
        if transfer is None or tid != transfer.request_id:
            self.stats.chunks_stale += 1
            if transfer is None and tid not in self._told_no_transfer and tid != 0:
                if len(self._told_no_transfer) >= _MAX_TOLD_NO_TRANSFER:
                    self._told_no_transfer.clear()  # bounded: a peer picks the ids
                self._told_no_transfer.add(tid)
                self.stats.errors_sent += 1
                self._send(
                    m.Error(
                        code=m.ErrorCode.NO_IMAGE,
                        where="IMAGE_CHUNK",
                        message=f"no image transfer {tid} in this session (send IMAGE_BEGIN)",
                    ),
                    tid,
                )
            return None
        writer = transfer.writer
        data = msg.data
        end = msg.offset + len(data)
        try:
            if len(data) > self.rx_buffer_bytes:
                raise DeviceRefusal(
                    m.ErrorCode.LIMIT_EXCEEDED,
                    f"chunk of {len(data)} bytes exceeds rx_buffer_bytes={self.rx_buffer_bytes}",
                )
            if end > transfer.size_bytes:
                raise DeviceRefusal(
                    m.ErrorCode.BAD_OFFSET,
                    f"chunk at {msg.offset} + {len(data)} bytes runs past the image size "
                    f"{transfer.size_bytes}",
                )
            if end > writer.next_offset + transfer.window_bytes:
                self.stats.chunks_out_of_window += 1
            else:
                writer.write_chunk(msg.offset, data)
                self.stats.chunks += 1
                self.stats.chunk_bytes += len(data)
                if not transfer.manifest_checked:
                    self._check_prefix(transfer)
                now = time.monotonic()
                if now - transfer.last_flush >= self.config.flush_interval_s:
                    transfer.last_flush = now
                    writer.flush()
                    self.stats.flushes += 1
        except (DeviceRefusal, FlashError) as exc:
            error = self._map_error(exc, "IMAGE_CHUNK")
            if error.code in (m.ErrorCode.BAD_OFFSET, m.ErrorCode.LIMIT_EXCEEDED):
                self._send(error, tid)
                return None
            self.log(f"image transfer refused: {error.message}")
            self._drop_transfer()
            self._told_no_transfer.add(tid)  # its chunks still in flight are dropped quietly
            self._send(error, tid)
            return None
        transfer.chunks_since_ack += 1
        link = self.link
        busy = link is not None and link.inbox_image_frames() > 0
        if not busy or transfer.chunks_since_ack >= max(1, self.config.rx_window_frames // 4):
            transfer.chunks_since_ack = 0
            self.stats.acks += 1
            self._send(
                m.ImageAck(
                    next_offset=writer.next_offset,
                    credits=self.config.rx_window_frames,
                    window_bytes=min(transfer.window_bytes, 0xFFFFFFFF),
                ),
                tid,
            )
        return None

    def handle_image_verify(self, msg: m.ImageVerify, frame: Frame) -> m.Message:
        """Re-read the slot: SHA-256 of the whole image, then its structure, digest and tag."""
        transfer = self.session.transfer
        if transfer is None or transfer.digest != msg.digest:
            raise DeviceRefusal(
                m.ErrorCode.NO_IMAGE,
                f"no transfer of image {msg.digest.hex()[:16]} in this session "
                "(IMAGE_BEGIN first)",
            )
        writer = transfer.writer
        if writer.next_offset < transfer.size_bytes:
            raise DeviceRefusal(
                m.ErrorCode.BAD_STATE,
                f"received {writer.next_offset} of {transfer.size_bytes} bytes; send the rest "
                "before IMAGE_VERIFY",
                {"next_offset": writer.next_offset},
            )
        if not transfer.verified:
            if not writer.verify():
                self.session.transfer = None  # verify() already dropped the journal
                raise DeviceRefusal(
                    m.ErrorCode.DIGEST_MISMATCH,
                    f"the {transfer.size_bytes} bytes received do not hash to the announced "
                    f"SHA-256 {transfer.digest.hex()[:16]}...; the transfer was discarded",
                )
            try:
                self._check_prefix(transfer)
                tag_ok = self._validate_slot(transfer)
            except Exception:
                self._drop_transfer()
                raise
            transfer.verified = True
            transfer.tag_ok = tag_ok
            self.log(f"image verified: sha256 {transfer.digest.hex()[:16]}, tag "
                     f"{'ok' if tag_ok else 'not checked (--insecure)'}")
        return m.ImageVerifyReply(
            ok=True,
            digest=transfer.digest,
            tag_ok=transfer.tag_ok,
            size_bytes=transfer.size_bytes,
        )

    def _validate_slot(self, transfer: _Transfer) -> bool:
        """Read the written image like a boot would (bounded); True when its tag verified."""
        tail = self._read_slot(transfer, transfer.size_bytes - 32, 32)
        if self.config.key is not None and not hmac.compare_digest(tail, transfer.image_tag):
            raise DeviceRefusal(
                m.ErrorCode.TAG_MISMATCH,
                "the image's tag differs from the one announced in IMAGE_BEGIN",
            )
        with open(transfer.writer.path, "rb") as handle:
            try:
                image = read_image(
                    handle,
                    key=self.config.key,
                    require_tag=self.config.key is not None,
                    max_manifest_bytes=self._max_manifest_bytes(),
                    max_section_bytes=self.config.ram_budget_bytes,
                    max_total_bytes=self.config.ram_budget_bytes,
                    read_annex=False,
                )
            except ImageTagError as exc:
                raise DeviceRefusal(m.ErrorCode.TAG_MISMATCH, str(exc)) from None
            except ImageFormatError as exc:
                raise DeviceRefusal(
                    m.ErrorCode.UNSUPPORTED_FORMAT, f"the image does not read: {exc}"
                ) from None
        return bool(image.tag_verified)

    def handle_image_commit(self, msg: m.ImageCommit, frame: Frame) -> m.Message:
        """Make the verified image active for a test boot; then load and confirm it."""
        transfer = self.session.transfer
        if transfer is None or transfer.digest != msg.digest:
            raise DeviceRefusal(
                m.ErrorCode.NO_IMAGE,
                f"no transfer of image {msg.digest.hex()[:16]} in this session",
            )
        if not transfer.verified:
            raise DeviceRefusal(
                m.ErrorCode.BAD_STATE, "IMAGE_COMMIT before a successful IMAGE_VERIFY"
            )
        self.store.commit_test()
        self.session.transfer = None
        self.log(f"image committed to slot {self.store.active_slot} (test)")
        self._after_activation()
        return m.SlotStatus(slots=self._slot_infos())

    def handle_image_abort(self, msg: m.ImageAbort, frame: Frame) -> m.Message:
        """Drop the transfer in progress and its journal."""
        transfer = self.session.transfer
        if msg.digest is not None and transfer is not None and transfer.digest != msg.digest:
            raise DeviceRefusal(m.ErrorCode.NO_IMAGE, "no transfer of that image to abort")
        self._drop_transfer()
        self.log("image transfer aborted by the host")
        return m.Ok()
