"""The link engine: request ids, stale replies, timeouts, errors, priorities, latest-wins
scores, bounded inbox, and a hypothesis test of the frame dispatcher.

The image sender is tested in test_image_transfer.py, the host session (SET_BAUD) in
test_host_session.py; the ``pair`` and ``links`` fixtures are in conftest.py."""

from __future__ import annotations

import threading
import time

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from provision_helpers import mem_name

from protocol import messages as m
from protocol.errors import (
    RemoteAuthFailed,
    RemoteBusy,
    RemoteError,
    TransportClosed,
    TransportTimeout,
)
from protocol.framing import Channel, Frame, FrameDecoder, Kind, encode_frame
from protocol.link import Link
from protocol.transport import open_transport


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
