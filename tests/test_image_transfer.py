"""The windowed image sender (protocol/image_transfer.py): every byte over a lossy line with
either retransmission strategy, credits and window kept, the device's error, inactivity
timeout, a chunk too big for the frame. Fixtures ``pair`` and ``links``: conftest.py."""

from __future__ import annotations

import time

import numpy as np
import pytest

from protocol import messages as m
from protocol.errors import RemoteError, TransportTimeout
from protocol.image_transfer import send_image
from protocol.link import IMAGE_QUEUE_FRAMES, Link

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
        # a clean line loses nothing: no loss-driven (fast) retransmit; a chunk is sent again
        # only when its timer fired first, which a heavily loaded shared CPU can cause
        assert stats.fast_retransmits == 0
        assert stats.retransmitted_chunks == 0 or stats.timeouts > 0
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


def test_the_link_module_still_exports_the_sender_and_the_session():
    import protocol.link as link_module
    from protocol import host_session, image_transfer

    assert link_module.send_image is image_transfer.send_image
    assert link_module.TransferStats is image_transfer.TransferStats
    assert link_module.RETRANSMIT_STRATEGIES == ("selective", "go-back-n")
    assert link_module.HostSession is host_session.HostSession
    with pytest.raises(AttributeError, match="no attribute 'no_such_name'"):
        link_module.no_such_name  # noqa: B018
