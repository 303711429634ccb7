"""The host session (protocol/host_session.py): version negotiation and SET_BAUD against a
device thread on a paced mem line and a pty. HELLO/AUTH are exercised by every provisioning
and serving test (test_provision.py, test_serve.py)."""

from __future__ import annotations

import pytest
from provision_helpers import KEY, DeviceThread, mem_name, wait_for_line

from protocol import messages as m
from protocol.errors import RemoteError
from protocol.host_session import HostSession, negotiate_version
from protocol.link import Link
from protocol.transport import open_pty_pair, open_transport

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
