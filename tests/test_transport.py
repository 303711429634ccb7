"""Transports: the in-memory line, pyserial adapters, tcp-listen, pty pair."""

from __future__ import annotations

import itertools
import math
import os
import sys
import threading
import time

import numpy as np
import pytest
import serial

from protocol import messages as m
from protocol.errors import TransportClosed, TransportError, TransportTimeout
from protocol.framing import FrameDecoder
from protocol.transport import (
    FdTransport,
    SerialTransport,
    TcpListenTransport,
    Transport,
    known_schemes,
    open_pty_pair,
    open_transport,
    register_url_handlers,
)

_names = itertools.count()


@pytest.fixture
def line():
    """Return a function opening both ends of a fresh mem line with per-end options."""
    opened = []

    def open_pair(
        a_opts: str = "", b_opts: str = "", *, baud: int = 115200, timeout_s: float = 5.0
    ):
        name = f"t{os.getpid()}-{next(_names)}"
        a = open_transport(f"mem://{name}?end=a{a_opts}", baud=baud, timeout_s=timeout_s)
        b = open_transport(f"mem://{name}?end=b{b_opts}", baud=baud, timeout_s=timeout_s)
        opened.extend([a, b])
        return a, b

    yield open_pair
    for t in opened:
        t.close()


def _read_exactly(t: Transport, n: int, timeout_s: float = 10.0) -> bytes:
    out = bytearray()
    deadline = time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() < deadline:
        out += t.read(n - len(out), 0.5)
    return bytes(out)


def _drain(t: Transport) -> bytes:
    """Everything already delivered on an unpaced line."""
    out = bytearray()
    while chunk := t.read(1 << 22, 0.05):
        out += chunk
    return bytes(out)


# --------------------------------------------------------------------------- mem line


def test_transports_satisfy_the_protocol(line):
    a, _ = line("&pace=0", "&pace=0")
    assert isinstance(a, Transport) and isinstance(a, SerialTransport)
    assert a.max_frame_bytes == 4096 and a.url.startswith("mem://")


def test_one_mebibyte_round_trip_is_paced_at_the_baud_rate(line):
    baud = 8_000_000
    a, b = line(baud=baud)
    data = np.random.default_rng(1).integers(0, 256, 1 << 20, dtype=np.uint8).tobytes()
    received = bytearray()
    done = threading.Event()

    def reader():
        while len(received) < len(data):
            received.extend(b.read(1 << 16, 1.0))
        done.set()

    thread = threading.Thread(target=reader, daemon=True)
    start = time.monotonic()
    thread.start()
    assert a.write(data) == len(data)
    assert done.wait(60)
    elapsed = time.monotonic() - start
    assert bytes(received) == data
    # 10 bits per byte on the wire: it cannot arrive faster than that.
    assert elapsed >= 10 * len(data) / baud


def test_reads_are_partial_while_bytes_are_still_arriving(line):
    a, b = line(baud=9600)
    data = bytes(range(256)) * 2 + b"tail"
    a.write(data)
    first = b.read(len(data), 5.0)
    assert 0 < len(first) < len(data)  # 516 bytes take 0.54 s at 9600 baud
    rest = _read_exactly(b, len(data) - len(first))
    assert first + rest == data


def test_pyserial_semantics_through_serial_for_url():
    register_url_handlers()
    name = f"ps{next(_names)}"
    a = serial.serial_for_url(f"mem://{name}?end=a&pace=0&rx_buffer=16", baudrate=115200, timeout=5)
    b = serial.serial_for_url(
        f"mem://{name}?end=b&pace=0", baudrate=115200, timeout=5, write_timeout=0.1
    )
    try:
        b.write(b"0123456789")
        assert a.in_waiting == 10
        assert a.read(10) == b"0123456789"  # read(n) waits for n bytes (pyserial contract)
        with pytest.raises(serial.SerialTimeoutException):
            b.write(b"x" * 17)  # a's 16-byte buffer fills and nobody reads
        assert a.read(16) == b"x" * 16
    finally:
        a.close()
        b.close()


def test_a_writer_without_a_reader_times_out_instead_of_buffering(line):
    a, b = line("&pace=0", "&pace=0&rx_buffer=2048", timeout_s=0.2)
    with pytest.raises(TransportTimeout, match="peer not reading"):
        a.write(bytes(100_000))
    assert b.port.in_waiting == 2048  # exactly the receive buffer, nothing more
    # Once the reader catches up the line works again.
    assert len(_drain(b)) == 2048
    a.write(b"again")
    assert _drain(b) == b"again"


def test_without_flow_control_excess_bytes_are_lost_and_counted(line):
    a, b = line("&pace=0", "&pace=0&rx_buffer=1000&flow=0")
    a.write(bytes(range(250)) * 10)  # 2500 bytes, returns at once
    assert _drain(b) == (bytes(range(250)) * 10)[:1000]
    assert b.port.line_end.stats["overrun"] == 1500


def _statistics(opts: str, n: int, seed: int = 1) -> tuple[bytes, bytes, dict]:
    name = f"st{next(_names)}"
    a = open_transport(f"mem://{name}?end=a&pace=0&seed={seed}{opts}")
    b = open_transport(f"mem://{name}?end=b&pace=0&rx_buffer={4 * n}")
    try:
        data = np.random.default_rng(seed + 100).integers(0, 256, n, dtype=np.uint8).tobytes()
        a.write(data)
        return data, _drain(b), a.port.line_end.stats
    finally:
        a.close()
        b.close()


def _within(count: int, trials: int, rate: float, sigmas: float = 6.0) -> bool:
    mean = trials * rate
    return abs(count - mean) <= sigmas * math.sqrt(trials * rate * (1 - rate))


def test_bit_errors_at_the_configured_rate():
    data, got, stats = _statistics("&ber=1e-3", 50_000)
    assert len(got) == len(data)
    flipped = int(np.unpackbits(np.frombuffer(data, np.uint8) ^ np.frombuffer(got, np.uint8)).sum())
    assert flipped == stats["bits_flipped"]
    assert _within(flipped, 8 * len(data), 1e-3)


def test_dropped_bytes_at_the_configured_rate():
    data, got, stats = _statistics("&drop=0.01", 200_000)
    assert len(data) - len(got) == stats["dropped"]
    assert _within(stats["dropped"], len(data), 0.01)


def test_duplicated_bytes_at_the_configured_rate():
    data, got, stats = _statistics("&dup=0.01", 200_000)
    assert len(got) - len(data) == stats["duplicated"]
    assert _within(stats["duplicated"], len(data), 0.01)

    # Removing each byte equal to its predecessor from both sides gives the same text.
    def squeeze(b: bytes) -> bytes:
        arr = np.frombuffer(b, np.uint8)
        return arr[np.r_[True, arr[1:] != arr[:-1]]].tobytes()

    assert squeeze(got) == squeeze(data)


def test_reordered_bytes_at_the_configured_rate():
    data, got, stats = _statistics("&reorder=0.01", 200_000)
    assert sorted(got) == sorted(data) and got != data
    # Disjoint adjacent swaps: the expected count is a little under n * rate.
    assert _within(stats["reordered"], len(data), 0.01 * (1 - 0.02), sigmas=8)


def test_bursts_drop_runs_of_bytes():
    data, got, stats = _statistics("&burst=2e-4&burst_bytes=32", 200_000)
    assert len(data) - len(got) == stats["burst_dropped"] > 0
    assert stats["burst_dropped"] <= 32 * _upper(200_000, 2e-4)


def _upper(trials: int, rate: float) -> float:
    return trials * rate + 6 * math.sqrt(trials * rate)


def test_faults_are_reproducible_with_a_seed():
    opts = "&ber=1e-3&drop=1e-3&dup=1e-3&reorder=1e-3"
    _, got1, _ = _statistics(opts, 20_000, seed=7)
    _, got2, _ = _statistics(opts, 20_000, seed=7)
    _, got3, _ = _statistics(opts, 20_000, seed=8)
    assert got1 == got2 and got1 != got3


def test_disconnect_after_cuts_the_line_for_both_ends(line):
    a, b = line("&pace=0&disconnect_after=1000", "&pace=0")
    with pytest.raises(TransportClosed, match="disconnect_after"):
        a.write(bytes(range(200)) * 25)
    assert _read_exactly(b, 1000, timeout_s=2) == (bytes(range(200)) * 25)[:1000]
    with pytest.raises(TransportClosed):
        b.read(10, 1.0)
    with pytest.raises(TransportClosed):
        b.write(b"x")
    with pytest.raises(TransportClosed):
        a.write(b"x")


def test_reconnect_after_a_cut_gets_a_fresh_line():
    name = f"rc{next(_names)}"
    a = open_transport(f"mem://{name}?end=a&pace=0&disconnect_after=10")
    b = open_transport(f"mem://{name}?end=b&pace=0")
    with pytest.raises(TransportClosed):
        a.write(bytes(20))
    a.close()
    a2 = open_transport(f"mem://{name}?end=a&pace=0")  # b still holds the dead line
    with pytest.raises(TransportClosed):
        b.read(100, 0.5) and b.read(100, 0.5)
    b.close()
    b2 = open_transport(f"mem://{name}?end=b&pace=0")
    try:
        a2.write(b"hello again")
        assert _drain(b2) == b"hello again"
    finally:
        a2.close()
        b2.close()


def test_bytes_sent_to_an_absent_peer_are_lost():
    name = f"ab{next(_names)}"
    a = open_transport(f"mem://{name}?end=a&pace=0")
    try:
        a.write(b"nobody listens")
        b = open_transport(f"mem://{name}?end=b&pace=0")
        a.write(b"now")
        assert _drain(b) == b"now"
        assert a.port.line_end.stats["lost_no_peer"] == len(b"nobody listens")
        b.close()
    finally:
        a.close()


def test_baud_mismatch_garbles_and_matching_again_heals(line):
    a, b = line(baud=1_000_000)
    b.set_baud(500_000)
    a.write(bytes(range(200)))
    assert _read_exactly(b, 200) != bytes(range(200))
    assert b.port.line_end.stats["garbled"] == 200
    b.set_baud(1_000_000)
    a.write(bytes(range(200)))
    assert _read_exactly(b, 200) == bytes(range(200))


def test_latency_delays_delivery(line):
    a, b = line("&pace=0&latency_ms=300", "&pace=0")
    a.write(b"late")
    assert b.read(10, 0.0) == b""  # nothing yet: it is still on the wire
    assert _read_exactly(b, 4) == b"late"


def test_frames_survive_a_noisy_line(line):
    a, b = line("&pace=0&ber=2e-4&drop=1e-4&dup=1e-4&seed=5", "&pace=0&rx_buffer=1000000")
    sent = {}
    for i in range(300):
        msg = m.Ping(payload=bytes([i % 256]) * 20, sent_us=i)
        sent[i] = msg
        a.write(msg.encode(request_id=i))
    decoder = FrameDecoder(1024)
    frames = decoder.feed(_drain(b))
    assert len(frames) >= 240
    for frame in frames:
        assert m.decode_message(frame) == sent[frame.request_id]  # nothing corrupt gets through
    dropped = decoder.bad_cobs + decoder.bad_crc + decoder.bad_header + decoder.oversize
    assert dropped >= 1


@pytest.mark.parametrize(
    ("url", "problem"),
    [
        ("mem://x?end=c", "end='c' must be a or b"),
        ("mem://x", "missing end=a or end=b"),
        ("mem://x?end=a&bogus=1", "unknown option 'bogus'"),
        ("mem://x?end=a&ber=2", "ber=2.0 must be in"),
        ("mem://x?end=a&flow=yes", "flow='yes'"),
        ("mem://?end=a", "missing NAME"),
    ],
)
def test_bad_mem_urls_are_rejected_with_the_format(url, problem):
    with pytest.raises(TransportError, match="mem://NAME") as info:
        open_transport(url)
    assert problem in str(info.value)


def test_an_end_cannot_be_opened_twice(line):
    a, _ = line("&pace=0")
    with pytest.raises(TransportError, match="already open"):
        open_transport(a.url)


# --------------------------------------------------------------------------- registry


def test_unknown_scheme_lists_the_known_ones():
    with pytest.raises(TransportError) as info:
        open_transport("carrier-pigeon://coop")
    text = str(info.value)
    assert "unknown scheme 'carrier-pigeon'" in text
    for scheme in ("tcp-listen://", "mem://", "socket://", "rfc2217://", "loop://"):
        assert scheme in text
    assert {"tcp-listen", "mem", "socket", "loop", "rfc2217"} <= set(known_schemes())


def test_bad_arguments_are_value_errors():
    with pytest.raises(ValueError, match="baud"):
        open_transport("loop://", baud=0)
    with pytest.raises(ValueError, match="max_frame_bytes"):
        open_transport("loop://", max_frame_bytes=10)


def test_loop_is_a_self_loop():
    t = open_transport("loop://", baud=115200)
    try:
        assert t.max_frame_bytes == 1024
        t.write(b"\x00echo\x00")
        assert _read_exactly(t, 6, timeout_s=2) == b"\x00echo\x00"
        assert t.read(10, 0.05) == b""
        with pytest.raises(ValueError, match="max_bytes"):
            t.read(0, 1.0)
    finally:
        t.close()


# --------------------------------------------------------------------------- TCP


def test_socket_url_talks_to_tcp_listen_and_reconnects():
    device = open_transport("tcp-listen://127.0.0.1:0", timeout_s=2.0)
    assert isinstance(device, TcpListenTransport) and isinstance(device, Transport)
    try:
        with pytest.raises(TransportClosed, match="no host connected"):
            device.write(b"x")
        assert device.read(10, 0.05) == b""  # nobody there yet
        host = open_transport(f"socket://127.0.0.1:{device.port}", timeout_s=2.0)
        host.write(m.Ping(sent_us=1).encode(request_id=1))
        (frame,) = FrameDecoder(256).feed(_read_exactly(device, len(m.Ping(sent_us=1).encode())))
        assert m.decode_message(frame) == m.Ping(sent_us=1)
        assert device.connected
        # pyserial's socket:// read(n) would wait for n bytes; the adapter returns what came.
        device.write(b"hello")
        start = time.monotonic()
        assert host.read(65536, 20.0) == b"hello"
        assert time.monotonic() - start < 10.0  # returned before its timeout
        host.close()
        with pytest.raises(TransportClosed, match="host disconnected"):
            _read_exactly(device, 1, timeout_s=5)
        assert not device.connected
        # The next host is accepted by the next read.
        host2 = open_transport(f"socket://127.0.0.1:{device.port}", timeout_s=2.0)
        host2.write(b"second host")
        assert _read_exactly(device, 11) == b"second host"
        device.write(b"ack")
        assert _read_exactly(host2, 3) == b"ack"
        device.disconnect()
        with pytest.raises(TransportClosed):
            _read_exactly(host2, 1, timeout_s=5)
        host2.close()
    finally:
        device.close()


def test_tcp_listen_url_forms():
    with pytest.raises(TransportError, match=r"tcp-listen://HOST:PORT"):
        open_transport("tcp-listen://127.0.0.1")
    with pytest.raises(TransportError, match=r"tcp-listen://HOST:PORT"):
        open_transport("tcp-listen://127.0.0.1:1234?opt=1")


# --------------------------------------------------------------------------- pty


@pytest.mark.skipif(sys.platform == "win32", reason="ptys are POSIX only")
def test_pty_pair_carries_frames_through_pyserial_in_raw_mode():
    with open_pty_pair() as pty:
        host = open_transport(pty.slave_path, baud=921600, timeout_s=2.0)
        device = pty.master_transport(timeout_s=2.0)
        assert isinstance(device, FdTransport) and isinstance(host, Transport)
        try:
            raw = b"\x00\x03\x11\x13\r\n\x7f\x1a"  # NUL, ^C, XON, XOFF, CR LF, DEL, ^Z
            host.write(raw)
            assert _read_exactly(device, len(raw)) == raw
            device.write(raw[::-1])
            assert _read_exactly(host, len(raw)) == raw[::-1]
            frames = b"".join(
                m.Scores(sequence=i, packet=bytes(range(256))).encode() for i in range(20)
            )
            device.write(frames)
            decoded = FrameDecoder(4096).feed(_read_exactly(host, len(frames)))
            assert [m.decode_message(f).sequence for f in decoded] == list(range(20))
        finally:
            host.close()
            device.close()
