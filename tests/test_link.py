"""The link engine: request ids, stale replies, timeouts, errors, priorities, latest-wins
scores, bounded inbox, the windowed image sender, SET_BAUD, and a hypothesis test of the
frame dispatcher."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from provision_helpers import KEY, DeviceThread, mem_name, wait_for_line

from protocol import messages as m
from protocol.errors import (
    RemoteAuthFailed,
    RemoteBusy,
    RemoteError,
    TransportClosed,
    TransportTimeout,
)
from protocol.framing import Channel, Frame, FrameDecoder, Kind, encode_frame
from protocol.link import (
    IMAGE_QUEUE_FRAMES,
    HostSession,
    Link,
    negotiate_version,
    send_image,
)
from protocol.transport import open_pty_pair, open_transport

# --------------------------------------------------------------------------- fixtures


@pytest.fixture
def pair():
    """Open both ends of a fresh unpaced mem line; return (open_fn)."""
    opened = []

    def open_pair(a_opts: str = "&pace=0", b_opts: str = "&pace=0", *, baud: int = 115200):
        name = mem_name("link")
        a = open_transport(f"mem://{name}?end=a{a_opts}", baud=baud, timeout_s=5.0)
        b = open_transport(f"mem://{name}?end=b{b_opts}", baud=baud, timeout_s=5.0)
        opened.extend([a, b])
        return a, b

    yield open_pair
    for t in opened:
        t.close()


@pytest.fixture
def links():
    """Start links and close them at the end."""
    started = []

    def start(transport, **kwargs):
        link = Link(transport, **kwargs).start()
        started.append(link)
        return link

    yield start
    for link in started:
        link.close(flush_timeout_s=0.2)


class GatedTransport:
    """Wraps a transport; writes block while ``gate`` is clear and are recorded in order."""

    def __init__(self, inner) -> None:
        self.inner = inner
        self.gate = threading.Event()
        self.gate.set()
        self.writes: list[bytes] = []
        self.url = inner.url
        self.max_frame_bytes = inner.max_frame_bytes
        self.blocked = threading.Event()

    def write(self, data: bytes) -> int:
        if not self.gate.is_set():
            self.blocked.set()
            self.gate.wait(10)
        self.writes.append(bytes(data))
        return self.inner.write(data)

    def read(self, max_bytes: int, timeout_s: float) -> bytes:
        return self.inner.read(max_bytes, timeout_s)

    def set_baud(self, baud: int) -> None:
        self.inner.set_baud(baud)

    def close(self) -> None:
        self.inner.close()


def _frames(wires: list[bytes]) -> list[Frame]:
    decoder = FrameDecoder(1 << 16)
    out: list[Frame] = []
    for wire in wires:
        out.extend(decoder.feed(wire))
    return out


def _ping(n: int = 0) -> m.Ping:
    return m.Ping(payload=bytes([n]), sent_us=n)


def _pong_for(msg: m.Ping) -> m.Pong:
    return m.Pong(payload=msg.payload, ping_sent_us=msg.sent_us, sent_us=1)


# --------------------------------------------------------------------------- requests


def test_request_gets_its_reply_and_a_late_reply_to_an_old_id_is_dropped(pair, links):
    a, b = pair()
    ids: list[int] = []

    def peer(msg, frame):
        ids.append(frame.request_id)
        if len(ids) == 1:
            return None  # the first attempt goes unanswered ...
        # ... and its reply arrives late, just before the answer to the retry
        peer_link.send(_pong_for(m.Ping(payload=b"old", sent_us=9)), request_id=ids[0])
        return _pong_for(msg)

    peer_link = links(b, handler=peer)
    host = links(a)
    reply = host.request(_ping(7), timeout_s=0.2, retries=2)
    assert isinstance(reply, m.Pong) and reply.payload == bytes([7])
    assert len(ids) == 2 and ids[0] != ids[1]  # a retry carries a fresh id
    assert host.stats.request_retries == 1
    deadline = time.monotonic() + 5
    while host.stats.stale_responses < 1 and time.monotonic() < deadline:
        host.wait_closed(0.01)
    assert host.stats.stale_responses == 1


def test_silent_peer_times_out_after_bounded_retries_with_backoff(pair, links):
    a, b = pair()
    links(b, handler=lambda msg, frame: None)
    host = links(a)
    start = time.monotonic()
    with pytest.raises(TransportTimeout, match=r"no reply to PING after 3 attempts"):
        host.request(_ping(), timeout_s=0.05, retries=2, backoff=2.0)
    elapsed = time.monotonic() - start
    assert elapsed >= 0.05 + 0.1 + 0.2 - 0.02  # 50 + 100 + 200 ms: the timeout backs off
    assert host.stats.request_retries == 2


def test_a_vanished_peer_fails_the_pending_request_with_transport_closed(links):
    name = mem_name("cut")
    a = open_transport(f"mem://{name}?end=a&pace=0&disconnect_after=10", timeout_s=2)
    b = open_transport(f"mem://{name}?end=b&pace=0", timeout_s=2)
    try:
        links(b, handler=lambda msg, frame: None)
        host = links(a)
        with pytest.raises(TransportClosed):
            host.request(_ping(), timeout_s=5.0, retries=3)
        assert host.wait_closed(5) and isinstance(host.error, TransportClosed)
        with pytest.raises(TransportClosed):
            host.send(_ping())
    finally:
        a.close()
        b.close()


@pytest.mark.parametrize(
    ("raised", "expected"),
    [
        (RemoteBusy(15, "x"), RemoteBusy),
        (m.AuthenticationError("tag mismatch"), RemoteAuthFailed),
    ],
)
def test_an_error_reply_raises_the_remote_error_for_its_code(pair, links, raised, expected):
    a, b = pair()

    def peer(msg, frame):
        raise raised

    links(b, handler=peer)
    host = links(a)
    with pytest.raises(expected) as info:
        host.request(_ping(), timeout_s=2, retries=0)
    assert isinstance(info.value, RemoteError)
    assert "\n" not in str(info.value) and "PING" in str(info.value)


def test_wrong_reply_type_is_reported(pair, links):
    a, b = pair()
    links(b, handler=lambda msg, frame: m.Ok())
    host = links(a)
    with pytest.raises(m.MalformedMessage, match="answered with OK, expected PONG"):
        host.request(_ping(), timeout_s=2, retries=0)


def _raw_request(host: Link, wire_builder) -> m.Message:
    """Send a hand-made frame with a fresh id and wait for whatever answers that id."""
    got: list[m.Message] = []
    done = threading.Event()
    rid = 777

    def listener(msg):
        got.append(msg)
        done.set()

    host.add_listener(rid, listener)
    host.send_raw(wire_builder(rid))
    assert done.wait(5), "no answer"
    host.remove_listener(rid)
    return got[0]


def test_unknown_type_with_must_understand_is_answered_unknown_message(pair, links):
    a, b = pair()
    links(b, handler=lambda msg, frame: None)
    host = links(a)
    reply = _raw_request(
        host,
        lambda rid: encode_frame(channel=0, kind=0, msg_type=0xEE, request_id=rid, body=b"\xa0",
                                 flags=1),
    )
    assert isinstance(reply, m.Error) and reply.code == m.ErrorCode.UNKNOWN_MESSAGE
    assert "0xee" in reply.message


def test_unknown_type_without_must_understand_is_ignored(pair, links):
    a, b = pair()
    peer = links(b, handler=lambda msg, frame: _pong_for(msg))
    host = links(a)
    host.send_raw(encode_frame(channel=3, kind=2, msg_type=0xEF, request_id=0, body=b"\xa0"))
    assert isinstance(host.request(_ping(), timeout_s=2, retries=0), m.Pong)
    assert peer.stats.unknown == 1 and host.stats.frames_received == 1  # no ERROR came back


def test_malformed_request_body_is_answered_malformed_with_its_id(pair, links):
    a, b = pair()
    links(b, handler=lambda msg, frame: _pong_for(msg))
    host = links(a)
    reply = _raw_request(
        host,
        lambda rid: encode_frame(channel=0, kind=0, msg_type=int(m.MessageType.PING),
                                 request_id=rid, body=b"\xa1\x01\x41", flags=1),  # truncated
    )
    assert isinstance(reply, m.Error) and reply.code == m.ErrorCode.MALFORMED
    assert reply.where == "PING"


def test_channel_kind_mismatch_is_malformed(pair, links):
    a, b = pair()
    links(b, handler=lambda msg, frame: _pong_for(msg))
    host = links(a)
    body = _ping().to_body()
    reply = _raw_request(
        host,
        lambda rid: encode_frame(channel=1, kind=0, msg_type=int(m.MessageType.PING),
                                 request_id=rid, body=body, flags=1),
    )
    assert isinstance(reply, m.Error) and reply.code == m.ErrorCode.MALFORMED


def test_requests_without_a_handler_are_answered_unsupported(pair, links):
    a, b = pair()
    links(b)
    host = links(a)
    with pytest.raises(RemoteError, match="UNSUPPORTED"):
        host.request(_ping(), timeout_s=2, retries=0)


# --------------------------------------------------------------------------- writer


def test_control_frames_overtake_queued_image_chunks(pair, links):
    a, b = pair()
    links(b, handler=lambda msg, frame: _pong_for(msg) if isinstance(msg, m.Ping) else None)
    gated = GatedTransport(a)
    host = links(gated)
    gated.gate.clear()
    chunk = m.ImageChunk(offset=0, data=b"x" * 100)
    host.send_chunk(host._encode(chunk, 5))  # the writer takes this one and blocks on it
    assert gated.blocked.wait(5)
    for i in range(1, 4):
        host.send_chunk(host._encode(m.ImageChunk(offset=100 * i, data=b"y" * 100), 5))
    host.send(m.Bye(reason="urgent"))
    gated.gate.set()
    assert host.wait_writer_idle(5)
    kinds = [f.msg_type for f in _frames(gated.writes)]
    assert kinds[0] == m.MessageType.IMAGE_CHUNK  # already being written
    assert kinds[1] == m.MessageType.BYE  # jumped the three queued chunks
    assert kinds[2:] == [m.MessageType.IMAGE_CHUNK] * 3


def test_scores_are_latest_wins_in_the_send_queue(pair, links):
    a, b = pair()
    received: list[int] = []
    got_last = threading.Event()

    def peer(msg, frame):
        if isinstance(msg, m.Scores):
            received.append(msg.sequence)
            if msg.sequence == 10:
                got_last.set()

    links(b, handler=peer)
    gated = GatedTransport(a)
    host = links(gated)
    gated.gate.clear()
    host.send(m.Scores(sequence=1, packet=b"p"))  # taken by the writer, blocked
    assert gated.blocked.wait(5)
    for seq in range(2, 11):
        host.send(m.Scores(sequence=seq, packet=bytes([seq])))
    gated.gate.set()
    assert got_last.wait(5)
    assert received == [1, 10]  # 2..9 were replaced before they were sent, never retransmitted
    assert host.stats.scores_replaced == 8


def test_a_flooding_peer_cannot_grow_the_inbox_beyond_its_bound(pair, links):
    a, b = pair()
    release = threading.Event()
    handled: list[int] = []

    def slow(msg, frame):
        release.wait(10)
        handled.append(frame.request_id)
        return _pong_for(msg)

    device = links(b, handler=slow, inbox_frames=8)
    flood = Link(a)  # not started: only used to encode frames
    wire = b"".join(flood._encode(_ping(i % 256), i + 1) for i in range(200))
    a.write(wire)
    deadline = time.monotonic() + 5
    while device.stats.frames_received < 200 and time.monotonic() < deadline:
        device.wait_closed(0.01)
    assert device.stats.frames_received == 200
    assert device.stats.inbox_dropped >= 200 - 8 - 1
    assert len(device._inbox) <= 8
    release.set()


# --------------------------------------------------------------------------- image sender


class ChunkSink:
    """A minimal receiver: writes chunks into a buffer, acks cumulatively."""

    def __init__(self, size: int, credits: int = 8, window_bytes: int = 8 * 512) -> None:
        self.buf = bytearray(size)
        self.have = np.zeros(size, dtype=bool)
        self.credits = credits
        self.window_bytes = window_bytes
        self.link: Link | None = None
        self.chunks = 0

    def next_offset(self) -> int:
        missing = np.flatnonzero(~self.have)
        return int(missing[0]) if missing.size else len(self.buf)

    def __call__(self, msg, frame):
        if isinstance(msg, m.ImageChunk):
            self.chunks += 1
            end = msg.offset + len(msg.data)
            if end <= self.next_offset() + self.window_bytes:
                self.buf[msg.offset:end] = msg.data
                self.have[msg.offset:end] = True
            self.link.send(
                m.ImageAck(next_offset=self.next_offset(), credits=self.credits,
                           window_bytes=self.window_bytes),
                request_id=frame.request_id,
            )
        return None


@pytest.mark.parametrize("strategy", ["selective", "go-back-n"])
@pytest.mark.parametrize("faults", ["", "&burst=2e-4&burst_bytes=40&seed=3", "&ber=1e-4&seed=5"])
def test_send_image_delivers_every_byte_over_a_lossy_line(pair, links, strategy, faults):
    data = np.random.default_rng(4).integers(0, 256, 60_000, dtype=np.uint8).tobytes()
    a, b = pair("&pace=0" + faults)
    sink = ChunkSink(len(data), credits=16, window_bytes=16 * 1024)
    sink.link = links(b, handler=sink)
    host = links(a, tx_max_frame_bytes=4096)
    progress: list[int] = []
    stats = send_image(
        host, data, transfer_id=42,
        first_ack=m.ImageAck(next_offset=0, credits=16, window_bytes=16 * 1024),
        chunk_bytes=1024, retransmit=strategy, min_rto_s=0.05, initial_rto_s=0.2,
        on_progress=progress.append,
    )
    assert bytes(sink.buf) == data
    assert progress == sorted(progress) and progress[-1] == len(data)
    assert stats.data_bytes_sent >= len(data)
    if not faults:
        assert stats.retransmitted_chunks == 0 and stats.data_bytes_sent == len(data)
    else:
        assert stats.retransmitted_chunks > 0


def test_send_image_keeps_inside_credits_and_window(pair, links):
    data = bytes(range(256)) * 64
    a, b = pair()
    seen_beyond: list[int] = []

    class Checking(ChunkSink):
        def __call__(self, msg, frame):
            if isinstance(msg, m.ImageChunk):
                seen_beyond.append(msg.offset + len(msg.data) - self.next_offset())
            return super().__call__(msg, frame)

    sink = Checking(len(data), credits=2, window_bytes=1000)
    sink.link = links(b, handler=sink)
    host = links(a)
    send_image(host, data, transfer_id=1,
               first_ack=m.ImageAck(next_offset=0, credits=2, window_bytes=1000),
               chunk_bytes=400)
    assert bytes(sink.buf) == data
    assert max(seen_beyond) <= 1000


def test_send_image_reports_the_device_error_for_the_transfer(pair, links):
    a, b = pair()

    def refuse(msg, frame):
        if isinstance(msg, m.ImageChunk):
            device.send(m.Error(code=m.ErrorCode.TOO_LARGE_FOR_RAM, where="IMAGE_CHUNK",
                                message="needs 9 bytes"), request_id=frame.request_id)

    device = links(b, handler=refuse)
    host = links(a)
    with pytest.raises(RemoteError, match="TOO_LARGE_FOR_RAM"):
        send_image(host, b"z" * 5000, transfer_id=3,
                   first_ack=m.ImageAck(next_offset=0, credits=4, window_bytes=4096),
                   chunk_bytes=512)


def test_send_image_gives_up_after_inactivity_not_after_a_total_time(pair, links):
    a, b = pair()
    links(b, handler=lambda msg, frame: None)  # never acks
    host = links(a)
    start = time.monotonic()
    with pytest.raises(TransportTimeout, match="no progress for 1 s"):
        send_image(host, b"z" * 5000, transfer_id=3,
                   first_ack=m.ImageAck(next_offset=0, credits=4, window_bytes=4096),
                   chunk_bytes=512, inactivity_timeout_s=0.6, initial_rto_s=0.1)
    assert time.monotonic() - start < 5


def test_send_image_refuses_a_chunk_that_does_not_fit_the_frame(pair, links):
    a, _ = pair()
    host = links(a)
    with pytest.raises(ValueError, match="does not fit max_frame_bytes=1024"):
        send_image(host, b"z" * 5000, transfer_id=3,
                   first_ack=m.ImageAck(next_offset=0, credits=4, window_bytes=4096),
                   chunk_bytes=2000)
    assert IMAGE_QUEUE_FRAMES >= 1


# --------------------------------------------------------------------------- sessions, baud


def test_negotiate_version():
    assert negotiate_version((1, 3), (2, 5)) == 3
    assert negotiate_version((1, 1), (2, 2)) is None


def _session(url: str, *, baud: int, key=KEY) -> HostSession:
    link = Link(open_transport(url, baud=baud, timeout_s=5.0), owns_transport=True).start()
    session = HostSession(link, key=key, request_timeout_s=0.5)
    session.start()
    return session


def test_set_baud_switches_both_ends_of_a_paced_line(tmp_path):
    name = mem_name("baud")
    with DeviceThread(f"mem://{name}?end=b", tmp_path / "flash", baud=115200) as dev:
        session = _session(f"mem://{name}?end=a", baud=115200)
        try:
            assert session.set_baud(921600, revert_timeout_ms=1500) is True
            assert session.link.transport.baud == 921600
            assert dev.transport.baud == 921600
            session.ping(timeout_s=0.5, retries=2)
            garbage = session.link.decoder.counters()
            # The device's revert timer fires and keeps the new rate ...
            assert wait_for_line(dev, "set-baud: now 921600", 5.0)
            session.ping(timeout_s=0.5, retries=0)  # ... and still answers at it
            assert dev.transport.baud == 921600
            assert session.link.decoder.counters()["bad_crc"] == garbage["bad_crc"]
        finally:
            session.link.close()


def test_set_baud_reverts_when_the_host_never_answers_at_the_new_rate(tmp_path):
    name = mem_name("baud")
    with DeviceThread(f"mem://{name}?end=b", tmp_path / "flash", baud=115200) as dev:
        session = _session(f"mem://{name}?end=a", baud=115200)
        try:
            # The host asks for the switch but stays at 115200 (its adapter cannot do it):
            # its pings are garbled at the device until the device reverts by itself.
            session.call(m.SetBaud(baud=921600, revert_timeout_ms=400), retries=0)
            session.ping(timeout_s=0.25, retries=6)  # succeeds once the device is back
            assert dev.transport.baud == 115200
        finally:
            session.link.close()
    assert any("reverted to 115200" in line for line in dev.lines)


def test_set_baud_refuses_an_unsupported_rate_and_needs_a_signature(tmp_path):
    name = mem_name("baud")
    with DeviceThread(f"mem://{name}?end=b&pace=0", tmp_path / "flash"):
        session = _session(f"mem://{name}?end=a&pace=0", baud=115200)
        try:
            with pytest.raises(RemoteError, match=r"UNSUPPORTED.*123456"):
                session.call(m.SetBaud(baud=123456, revert_timeout_ms=100), retries=0)
            with pytest.raises(RemoteError, match=r"NOT_AUTHENTICATED \(4\)"):
                session.link.request(m.SetBaud(baud=921600, revert_timeout_ms=100), retries=0)
        finally:
            session.link.close()


@pytest.mark.skipif(not hasattr(__import__("os"), "openpty"), reason="needs POSIX ptys")
def test_set_baud_on_a_pty_is_accepted_and_the_link_keeps_working(tmp_path):
    pty = open_pty_pair()
    with DeviceThread(pty.slave_path, tmp_path / "flash", baud=115200) as dev:
        link = Link(pty.master_transport(), owns_transport=True).start()
        session = HostSession(link, key=KEY, request_timeout_s=0.5)
        try:
            session.start()
            assert session.set_baud(921600, revert_timeout_ms=800) is True
            session.ping(retries=1)
        finally:
            link.close()
            pty.close()
    assert any("set-baud" in line for line in dev.lines)


# --------------------------------------------------------------------------- dispatcher


class _NullTransport:
    url = "null://"
    max_frame_bytes = 4096

    def write(self, data):
        return len(data)

    def read(self, max_bytes, timeout_s):
        return b""

    def set_baud(self, baud):
        pass

    def close(self):
        pass


_KNOWN = [int(t) for t in m.MessageType]


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    channel=st.sampled_from(list(Channel)),
    kind=st.sampled_from(list(Kind)),
    msg_type=st.one_of(st.sampled_from(_KNOWN), st.integers(0, 255)),
    request_id=st.integers(0, 0xFFFF),
    body=st.one_of(
        st.binary(max_size=64),
        st.builds(lambda d: __import__("cbor2").dumps(d), st.dictionaries(
            st.integers(0, 30),
            st.one_of(st.integers(-5, 2**64 - 1), st.binary(max_size=40), st.text(max_size=10),
                      st.booleans(), st.floats(allow_nan=True), st.none()),
            max_size=6)),
    ),
    flags=st.sampled_from([0, 1]),
)
def test_the_dispatcher_survives_any_frame(channel, kind, msg_type, request_id, body, flags):
    calls: list[m.Message] = []

    def handler(msg, frame):
        calls.append(msg)
        raise ValueError("handler failure is answered, never propagated")

    link = Link(_NullTransport(), handler=handler, inbox_frames=4)
    frame = Frame(channel=channel, kind=kind, msg_type=msg_type, request_id=request_id,
                  body=body, flags=flags)
    link.handle_frame(frame)  # must not raise
    while link._inbox:  # run the dispatcher by hand (the link is not started)
        item = link._inbox.popleft()
        if not callable(item):
            link._dispatch(*item)
    assert len(link._control) <= 2
    for out in link._control:  # everything queued is a well-formed frame
        assert FrameDecoder(1 << 16).feed(out.data)
