"""Hostile inputs for the attack tests and the long fuzz benchmark (``benchmarks/bench_fuzz.py``).

An attacker here is anyone who can reach the link and has no key: they know the wire format,
and everything a score packet header carries in clear (K and the 4-byte image tag), so the
packets below are built by hand (``protocol.scores.encode_scores`` refuses what an attacker
sends on purpose: non-finite or overflowing steps).

* :class:`RawPeer` speaks raw frames over any transport (``socket://`` to a device process,
  ``mem://`` to an in-process one) and collects what the device answers.
* :func:`score_packet` builds a score packet field by field; :func:`zstd_bomb` a payload that
  expands to far more than any packet may hold.
* :func:`overflow_packets`, :func:`parser_attacks`, :func:`unauthenticated_state_changes`:
  the groups of the attack suite, as ``(label, wire bytes)`` pairs.
* :func:`mutated_frames`: seeded mutations of valid frames of every message type, plus random
  bytes (the benchmark's stream).
* :func:`flash_fingerprint`: what a flash folder stores, to show an attack changed nothing.
"""

from __future__ import annotations

import contextlib
import hashlib
import random
import struct
import threading
import time
import zlib
from collections.abc import Iterator
from pathlib import Path

import cbor2
import numpy as np
import zstandard as zstd

from protocol import messages as m
from protocol._cobs import cobs_encode
from protocol.framing import CRC, FRAME_VERSION, HEADER, FrameDecoder, encode_frame
from protocol.scores import MAGIC

__all__ = [
    "RawPeer",
    "flash_fingerprint",
    "mutated_frames",
    "overflow_packets",
    "parser_attacks",
    "raw_frame",
    "score_packet",
    "scores_frame",
    "unauthenticated_state_changes",
    "zstd_bomb",
]

_HEADER = struct.Struct("<2sBBIIffI4sf")
FLAG_DELTA = 0x01
FLAG_ZSTD = 0x02


def _varint(value: int) -> bytes:
    zig = (value << 1) ^ (value >> 63)
    zig &= (1 << 64) - 1
    out = bytearray()
    while True:
        byte = zig & 0x7F
        zig >>= 7
        if zig:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def score_packet(
    k: int,
    tag: bytes,
    *,
    q: list[int] | None = None,
    step: float = 1.0,
    step_mode: int = 0,
    steps: list[float] | None = None,
    view: tuple[float, float] = (0.0, 0.0),
    frame: int = 1,
    base_frame: int = 0,
    flags: int = 0,
    payload: bytes | None = None,
    version: int = 1,
) -> bytes:
    """A score packet built field by field (CODING 0 varints unless ``payload`` is given).

    ``q`` (default all zeros) is padded with zeros to ``k`` entries; ``steps`` is the float32
    step array of STEP_MODE 1 or 2, written before the varints.
    """
    if payload is None:
        values = list(q or []) + [0] * (k - len(q or []))
        body = b"".join(_varint(int(v)) for v in values)
        if steps is not None:
            body = np.asarray(steps, dtype="<f4").tobytes() + body
        payload = body
    header = _HEADER.pack(MAGIC, version, flags | (step_mode << 2), frame, base_frame,
                          view[0], view[1], k, tag[:4], step)
    return header + payload


def zstd_bomb(expanded_bytes: int, *, content_size: bool) -> bytes:
    """One zstd frame of zeros that expands to ``expanded_bytes`` (recorded or not)."""
    params = zstd.ZstdCompressionParameters.from_level(19, write_content_size=content_size)
    cctx = zstd.ZstdCompressor(compression_params=params)
    if content_size:
        return cctx.compress(bytes(expanded_bytes))
    chunk = bytes(1 << 20)
    out = cctx.compressobj()
    parts = []
    left = expanded_bytes
    while left > 0:
        parts.append(out.compress(chunk[: min(left, len(chunk))]))
        left -= len(chunk)
    parts.append(out.flush())
    return b"".join(parts)


def raw_frame(
    body: bytes,
    *,
    msg_type: int,
    channel: int = 0,
    kind: int = 1,
    request_id: int = 1,
    declared_length: int | None = None,
    flags: int = 1,
) -> bytes:
    """A COBS frame with a correct CRC whose header may declare another body length."""
    n = len(body) if declared_length is None else declared_length
    raw = HEADER.pack((FRAME_VERSION << 4) | flags, channel, kind, msg_type, request_id, n) + body
    raw += CRC.pack(zlib.crc32(raw))
    return cobs_encode(raw) + b"\x00"


def scores_frame(packet: bytes, *, sequence: int = 0, request_id: int = 0) -> bytes:
    """A SCORES event frame carrying ``packet`` (no tag: what a keyless attacker can send)."""
    return m.Scores(sequence=sequence, packet=packet).encode(request_id=request_id)


def overflow_packets(k: int, tag: bytes, view: tuple[float, float]) -> list[tuple[str, bytes]]:
    """Score packets whose scores are not finite or overflow float32 once dequantized.

    Each is a SCORES frame the right size for the image (K and tag right), so only the check
    of the dequantized values can stop it.
    """
    big = 2**31 - 1
    huge = [3e38] * k
    nan_steps = [float("nan")] + [1.0] * (k - 1)
    inf_steps = [float("inf")] + [1.0] * (k - 1)
    packets = [
        ("header step 3e38, q0 = 2^31-1", score_packet(k, tag, q=[big], step=3e38, view=view)),
        ("header step 3e38, q0 = -2^31", score_packet(k, tag, q=[-(2**31)], step=3e38,
                                                     view=view, frame=2)),
        ("step mode 2, steps 3e38", score_packet(k, tag, q=[big] * k, step=0.0, step_mode=2,
                                                steps=huge, view=view, frame=3)),
        ("header step NaN", score_packet(k, tag, q=[1], step=float("nan"), view=view, frame=4)),
        ("header step inf", score_packet(k, tag, q=[1], step=float("inf"), view=view, frame=5)),
        ("header step -inf", score_packet(k, tag, q=[1], step=float("-inf"), view=view,
                                          frame=6)),
        ("step mode 2, a NaN step", score_packet(k, tag, q=[1], step=0.0, step_mode=2,
                                                steps=nan_steps, view=view, frame=7)),
        ("step mode 2, an inf step", score_packet(k, tag, q=[1], step=0.0, step_mode=2,
                                                 steps=inf_steps, view=view, frame=8)),
        ("view NaN", score_packet(k, tag, q=[1], step=1.0, view=(float("nan"), 0.0), frame=9)),
        ("view inf", score_packet(k, tag, q=[1], step=1.0, view=(0.0, float("inf")),
                                  frame=10)),
    ]
    return [(label, scores_frame(p, sequence=i + 1)) for i, (label, p) in enumerate(packets)]


def correction_attacks(k: int, tag: bytes, view: tuple[float, float]) -> list[tuple[str, bytes]]:
    """Version-2 (predicted correction) score packets with every new field wrong: DELTA and
    PREDICTED together (an unknown base), PREDICTED in a version-1 packet, the reserved bit 7,
    a NaN / infinite / huge / out-of-range view, an overflowing step; last a well-formed one.

    The right K and tag: only the checks of the new fields can stop them (the last one is
    valid and must still not be shown by a device that does not predict or whose view is
    another one).
    """
    big = float(2**31 - 1)
    packets = [
        ("DELTA and PREDICTED", score_packet(k, tag, flags=0x41, base_frame=3, view=view,
                                             version=2)),
        ("PREDICTED in version 1", score_packet(k, tag, flags=0x40, view=view, version=1)),
        ("reserved bit 7 in version 2", score_packet(k, tag, flags=0xC0, view=view,
                                                     version=2)),
        ("unknown version 3", score_packet(k, tag, flags=0x40, view=view, version=3)),
        ("view NaN", score_packet(k, tag, flags=0x40, view=(float("nan"), 0.0), version=2)),
        ("view inf", score_packet(k, tag, flags=0x40, view=(0.0, float("-inf")), version=2)),
        ("view huge", score_packet(k, tag, flags=0x40, view=(3e38, 0.0), version=2)),
        ("phi 360", score_packet(k, tag, flags=0x40, view=(360.0, 0.0), version=2)),
        ("theta 90.5", score_packet(k, tag, flags=0x40, view=(10.0, 90.5), version=2)),
        ("step 3e38, q = 2^31-1", score_packet(k, tag, flags=0x40, q=[int(big)], step=3e38,
                                               view=view, version=2)),
    ]
    valid = ("well-formed correction", score_packet(k, tag, flags=0x40, q=[3, -2], view=view,
                                                    version=2, frame=99))
    return [(label, scores_frame(p, sequence=i + 1))
            for i, (label, p) in enumerate([*packets, valid])]


def _deep(depth: int) -> bytes:
    return b"\x81" * depth + b"\x00"


def parser_attacks(rng: random.Random, k: int, tag: bytes) -> list[tuple[str, bytes]]:
    """Random bytes, garbage CBOR in valid frames, deep nesting, huge declared lengths (CBOR
    and frame), zstd bombs with and without a content size, score packets with a wrong K."""
    out: list[tuple[str, bytes]] = []
    for i in range(20):
        blob = bytearray(rng.randbytes(rng.randrange(1, 3000)))
        for _ in range(rng.randrange(0, 4)):
            blob[rng.randrange(len(blob))] = 0
        out.append((f"random bytes {i}", bytes(blob)))
    for msg_type in m.MessageType:
        cls = m.MESSAGE_CLASSES.get(msg_type)
        channel = int(getattr(cls, "CHANNEL", 0))
        kind = int(getattr(cls, "KIND", 1))
        for label, body in (
            ("garbage CBOR", rng.randbytes(rng.randrange(1, 200))),
            ("deep nesting", _deep(rng.choice([64, 500, 5000]))),
            ("indefinite nesting", b"\x9f" * 2000),
            ("byte string of 2^62 bytes", b"\xa1\x01\x5b" + struct.pack(">Q", 2**62)),
            ("text of 4 GiB", b"\xa1\x01\x7a\xff\xff\xff\xff"),
            ("map of 2^40 pairs", b"\xbb" + struct.pack(">Q", 2**40)),
            ("array of 2^32-1 items", b"\x9b" + struct.pack(">Q", 2**32 - 1)),
            ("tagged bignum", b"\xc2\x58\x20" + b"\xff" * 32),
            ("float keys", cbor2.dumps({1.5: 1, float("nan"): 2})),
        ):
            out.append((f"{msg_type.name}: {label}",
                        raw_frame(body, msg_type=int(msg_type), channel=channel, kind=kind,
                                  request_id=rng.randrange(1, 65536))))
        out.append((f"{msg_type.name}: frame declares 2^32-1 body bytes",
                    raw_frame(b"\xa0", msg_type=int(msg_type), channel=channel, kind=kind,
                              declared_length=2**32 - 1)))
    out.append(("a frame of 1 MiB without a delimiter", b"\x01" * (1 << 20) + b"\x00"))
    for content_size in (True, False):
        bomb = zstd_bomb(64 << 20, content_size=content_size)
        label = "with" if content_size else "without"
        packet = score_packet(k, tag, flags=FLAG_ZSTD, payload=bomb)
        out.append((f"SCORES: zstd bomb (64 MiB) {label} a content size", scores_frame(packet)))
        out.append((f"IMAGE_CHUNK: zstd bomb {label} a content size",
                    m.ImageChunk(offset=0, data=bomb[:4000]).encode(request_id=7)))
    for wrong_k in (0, 1, k - 1, k + 1, 2**32 - 1):
        packet = score_packet(max(0, min(wrong_k, k + 1)), tag)
        packet = packet[:20] + struct.pack("<I", wrong_k) + packet[24:]
        out.append((f"SCORES: K={wrong_k} (the image has {k})", scores_frame(packet)))
    out.append(("SCORES: wrong image tag", scores_frame(score_packet(k, b"\x00\x01\x02\x03"))))
    out.append(("SCORES: truncated header", scores_frame(MAGIC + b"\x01")))
    out.append(("SCORES: delta with an unknown base",
                scores_frame(score_packet(k, tag, flags=FLAG_DELTA, base_frame=77, frame=78))))
    return out


def unauthenticated_state_changes(rng: random.Random) -> list[tuple[str, bytes]]:
    """Every request that changes what a device stores or runs, unsigned and badly signed."""
    digest = rng.randbytes(32)
    out = []
    for counter, tag in ((None, None), (1, bytes(32)), (2**63, rng.randbytes(32))):
        sign = {} if counter is None else {"session_counter": counter, "session_tag": tag}
        what = "unsigned" if counter is None else f"forged tag, counter {counter}"
        for msg in (
            m.ImageBegin(size_bytes=4096, digest=digest, image_tag=bytes(32), format_version=1,
                         generation=99, **sign),
            m.ImageCommit(digest=digest, **sign),
            m.SlotSet(action=m.SlotAction.ACTIVATE, slot=1, **sign),
            m.SlotSet(action=m.SlotAction.REVERT, slot=0, **sign),
            m.SlotSet(action=m.SlotAction.CONFIRM, slot=0, **sign),
            m.ImageAbort(**sign),
            m.Reset(reason="attack", **sign),
            m.SetBaud(baud=300, revert_timeout_ms=100, **sign),
        ):
            wire = msg.encode(request_id=rng.randrange(1, 65536))
            out.append((f"{msg.TYPE.name} ({what})", wire))
    for offset in (0, 4096, 2**40):
        out.append((f"IMAGE_CHUNK at {offset}",
                    m.ImageChunk(offset=offset, data=rng.randbytes(512)).encode(request_id=1)))
    out.append(("IMAGE_VERIFY", m.ImageVerify(digest=digest).encode(request_id=2)))
    return out


def _constructible(cls: type) -> bool:
    try:
        cls()
    except TypeError:
        return False
    return True


def _valid_messages(k: int, tag: bytes) -> list[m.Message]:
    """One valid message of every host -> device type (the seeds of the mutations)."""
    digest = bytes(range(32))
    sign = {"session_counter": 1, "session_tag": bytes(32)}
    msgs: list[m.Message] = [
        m.Hello(min_version=1, max_version=m.PROTOCOL_VERSION, nonce=bytes(16)),
        m.AuthChallenge(host_proof=bytes(32)),
        m.Ping(payload=b"x" * 50, sent_us=5),
        m.Bye(reason="fuzz"),
        m.SetBaud(baud=921600, revert_timeout_ms=100, **sign),
        m.Reset(reason="fuzz", **sign),
        m.SlotSet(action=m.SlotAction.ACTIVATE, slot=1, **sign),
        m.ImageBegin(size_bytes=5000, digest=digest, image_tag=bytes(32), format_version=1,
                     generation=1, **sign),
        m.ImageStatus(digest=digest, size_bytes=100),
        m.ImageChunk(offset=0, data=b"\x01" * 300),
        m.ImageVerify(digest=digest),
        m.ImageCommit(digest=digest, **sign),
        m.Scores(sequence=1, packet=score_packet(k, tag, q=[3, -2, 1], step=0.5)),
        m.Scores(sequence=2, packet=score_packet(k, tag, flags=FLAG_DELTA, base_frame=1,
                                                 frame=2)),
        m.Notice(level=1, text="fuzz"),
        m.KeyframeRequest(sequence=1),
        m.ViewRequest(phi_deg=10.0, theta_deg=5.0, sequence=1),
    ]
    msgs.append(m.ImageAbort(**sign))
    return msgs


def mutated_frames(rng: random.Random, k: int, tag: bytes) -> Iterator[bytes]:
    """An endless stream of hostile wire frames: mutations (byte flips, truncation, splices,
    random field values) of a valid frame of every host -> device type, and random bytes."""
    seeds = [(type(msg), msg.to_body()) for msg in _valid_messages(k, tag)]
    while True:
        choice = rng.randrange(10)
        if choice == 0:
            blob = bytearray(rng.randbytes(rng.randrange(1, 400)))
            if rng.random() < 0.5:
                blob[rng.randrange(len(blob))] = 0
            yield bytes(blob)
            continue
        cls, body = rng.choice(seeds)
        mutated = bytearray(body)
        if choice <= 4:  # flip bytes
            for _ in range(rng.randrange(1, 5)):
                mutated[rng.randrange(len(mutated))] = rng.randrange(256)
        elif choice == 5:  # truncate
            del mutated[rng.randrange(len(mutated)):]
        elif choice == 6:  # splice in random bytes
            at = rng.randrange(len(mutated) + 1)
            mutated[at:at] = rng.randbytes(rng.randrange(1, 40))
        elif choice == 7 and cls is m.Scores:  # a valid SCORES with a mutated packet
            packet = bytearray(score_packet(k, tag, q=[rng.randrange(-9, 9)], step=0.5))
            for _ in range(rng.randrange(1, 4)):
                packet[rng.randrange(len(packet))] = rng.randrange(256)
            mutated = bytearray(m.Scores(sequence=1, packet=bytes(packet)).to_body())
        elif choice == 8:  # keep the body, mutate the header (channel, kind, type, flags)
            yield raw_frame(bytes(mutated), msg_type=rng.choice([int(cls.TYPE),
                                                                rng.randrange(256)]),
                            channel=rng.randrange(4), kind=rng.randrange(4),
                            request_id=rng.randrange(65536), flags=rng.randrange(2))
            continue
        yield encode_frame(channel=cls.CHANNEL, kind=cls.KIND, msg_type=int(cls.TYPE),
                           request_id=rng.randrange(65536), body=bytes(mutated),
                           flags=rng.randrange(2))


def flash_fingerprint(flash_dir: Path) -> dict[str, str]:
    """SHA-256 of every slot and journal file of a flash folder (the key file excluded)."""
    out = {}
    for path in sorted(Path(flash_dir).rglob("*")):
        if path.is_file() and path.name != "device.key":
            out[str(path.relative_to(flash_dir))] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


class RawPeer:
    """A keyless peer speaking raw frames over a transport (``socket://``, ``mem://``).

    A reader thread decodes what the device sends into :attr:`received` (messages).
    """

    def __init__(self, transport, *, max_frame_bytes: int = 1 << 16) -> None:
        self.transport = transport
        self.received: list[tuple[int, m.Message]] = []
        """(request id, message) of every frame the device sent that decoded."""
        self.closed_by_peer = threading.Event()
        self._decoder = FrameDecoder(max_frame_bytes)
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self.pings_sent = 0
        """PINGs the last :meth:`barrier` needed (more than 1: the device dropped some)."""
        self._thread = threading.Thread(target=self._read, daemon=True, name="raw-peer")
        self._thread.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.transport.read(1 << 16, 0.05)
            except Exception:  # the device dropped us
                self.closed_by_peer.set()
                return
            for frame in self._decoder.feed(data):
                try:
                    msg = m.decode_message(frame)
                except Exception:
                    continue
                with self._lock:
                    self.received.append((frame.request_id, msg))

    def send(self, wire: bytes) -> None:
        """Write raw bytes (ignoring a device that closed the connection meanwhile)."""
        try:
            self.transport.write(wire)
        except Exception:
            self.closed_by_peer.set()

    def wait_for(self, predicate, timeout_s: float = 10.0) -> m.Message | None:
        """The first received message ``msg`` with ``predicate(request_id, msg)`` true
        (None after ``timeout_s`` or once the device closed the connection)."""
        deadline = time.monotonic() + timeout_s
        while True:
            with self._lock:
                for request_id, msg in self.received:
                    if predicate(request_id, msg):
                        return msg
            if time.monotonic() >= deadline or not self._thread.is_alive():
                return None
            threading.Event().wait(0.01)

    def request(self, msg: m.Message, request_id: int, timeout_s: float = 10.0) -> m.Message | None:
        """Send ``msg``; return the device's response (or ERROR) to ``request_id``."""
        self.send(msg.encode(request_id=request_id))
        return self.wait_for(lambda rid, r: rid == request_id and r.KIND == m.Kind.RESPONSE,
                             timeout_s)

    def barrier(self, timeout_s: float = 10.0) -> bool:
        """PING until a PONG comes back: everything sent before has been dispatched.

        The PING is repeated every 0.25 s: a device whose receive queue a flood filled drops
        frames (the PING among them) rather than block its reader."""
        payloads: set[bytes] = set()
        self.pings_sent = 0
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            payload = random.randbytes(12)
            payloads.add(payload)
            self.pings_sent += 1
            self.send(m.Ping(payload=payload, sent_us=1).encode(request_id=65000))
            wait = min(0.25, max(0.0, deadline - time.monotonic()))
            if self.wait_for(lambda rid, r: isinstance(r, m.Pong) and r.payload in payloads,
                             wait) is not None:
                return True
            if not self._thread.is_alive():
                return False
        return False

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        with contextlib.suppress(Exception):
            self.transport.close()
