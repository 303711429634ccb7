"""Provisioning end to end: mem line, pty, TCP with the device as a separate process; faults,
resume after a disconnect and after a device reboot, power cuts, and every refusal."""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import random
import socket
import struct
import threading
import time

import cbor2
import pytest
from provision_helpers import (
    KEY,
    OTHER_KEY,
    DeviceProcess,
    DeviceThread,
    make_image,
    mem_name,
    reseal,
)

from device_runtime.device import Device, DeviceConfig
from device_runtime.flash import FlashStore
from host.cli import main as cli_main
from host.link.options import ProvisionOptions, ProvisionParts
from host.link.provisioning import ProvisionError, choose_chunk_bytes, inspect_image, provision
from protocol import auth
from protocol import messages as m
from protocol.errors import (
    AuthenticationError,
    ProtocolError,
    RemoteAuthFailed,
    RemoteNotAuthenticated,
    RemoteReplayed,
    RemoteRollbackRefused,
    RemoteTagMismatch,
    RemoteTooLargeForFlash,
    RemoteTooLargeForRam,
    RemoteUnsupportedFormat,
    RemoteUnsupportedVersion,
)
from protocol.host_session import HostSession
from protocol.keys import write_key
from protocol.link import Link
from protocol.transport import open_pty_pair, open_transport

QUIET = ProvisionParts(log=lambda line: None)


def _check_device_holds(flash_dir, image: bytes, *, slot: str | None = None) -> None:
    """The flash store's active slot holds exactly ``image`` and its digest verifies."""
    store = FlashStore.open(flash_dir, create=False)
    status = store.status()
    active = [s for s in status["slots"] if s["active"]]
    assert len(active) == 1
    assert active[0]["sha256"] == hashlib.sha256(image).hexdigest()
    assert active[0]["verifies"] is True
    assert active[0]["size_bytes"] == len(image)
    if slot is not None:
        assert active[0]["slot"] == slot
    with store.open_active() as stream:
        assert stream.read() == image


@pytest.fixture
def model(tmp_path):
    path = tmp_path / "model.ecs"
    return path, make_image(path, size_bytes=150_000)


# --------------------------------------------------------------------------- transports


def test_provision_over_the_mem_line_verifies_and_confirms(tmp_path, model):
    path, image = model
    name = mem_name("prov")
    with DeviceThread(f"mem://{name}?end=b&pace=0", tmp_path / "flash") as dev:
        result = provision(path, f"mem://{name}?end=a&pace=0",
                           ProvisionOptions(key=KEY, show_progress=False),
                           QUIET)
        again = provision(path, f"mem://{name}?end=a&pace=0",
                          ProvisionOptions(key=KEY, show_progress=False),
                          QUIET)
    assert result.outcome == "installed" and result.verified and result.confirmed
    assert result.slot == "A" and result.size_bytes == len(image)
    assert result.digest == hashlib.sha256(image).hexdigest()
    assert again.outcome == "already-active" and again.data_bytes_sent == 0
    _check_device_holds(tmp_path / "flash", image, slot="A")
    assert any("loaded and confirmed" in line for line in dev.lines)
    assert FlashStore.open(tmp_path / "flash").slots[0].state.label == "confirmed"


def test_provision_over_a_pty_pair_through_pyserial(tmp_path, model):
    path, image = model
    pty = open_pty_pair()
    try:
        with DeviceThread(pty.slave_path, tmp_path / "flash"):
            master = pty.master_transport()
            result = provision(path, "pty", ProvisionOptions(key=KEY, show_progress=False),
                               ProvisionParts(transport_factory=lambda n: master,
                                              log=lambda line: None))
    finally:
        pty.close()
    assert result.outcome == "installed" and result.verified
    _check_device_holds(tmp_path / "flash", image)


def test_provision_over_tcp_to_a_separate_device_process(tmp_path, model):
    path, image = model
    write_key(tmp_path / "dev.key", KEY)
    dev = DeviceProcess(tmp_path / "flash", key_file=tmp_path / "dev.key")
    try:
        result = provision(path, dev.url, ProvisionOptions(key=KEY, show_progress=False),
                           QUIET)
    finally:
        assert dev.stop() == 0
    assert result.outcome == "installed" and result.verified and result.confirmed
    _check_device_holds(tmp_path / "flash", image)
    assert any("image verified" in line for line in dev.lines)


def test_cli_provision_prints_a_summary_and_json(tmp_path, model, capsys):
    path, image = model
    write_key(tmp_path / "k.key", KEY)
    name = mem_name("cli")
    with DeviceThread(f"mem://{name}?end=b&pace=0", tmp_path / "flash"):
        rc = cli_main(["provision", str(path), "--port", f"mem://{name}?end=a&pace=0",
                       "--key", str(tmp_path / "k.key"), "--quiet"])
        assert rc == 0
        assert "installed" in capsys.readouterr().out
        rc = cli_main(["provision", str(path), "--port", f"mem://{name}?end=a&pace=0",
                       "--key", str(tmp_path / "k.key"), "--json"])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    assert out["outcome"] == "already-active" and out["digest"] == hashlib.sha256(image).hexdigest()


def test_cli_provision_errors_are_one_line(tmp_path, capsys):
    rc = cli_main(["provision", str(tmp_path / "missing.ecs"), "--port", "mem://x?end=a"])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and err.count("\n") == 0 and "not found" in err
    path = tmp_path / "m.ecs"
    make_image(path, size_bytes=20_000)
    rc = cli_main(["provision", str(path), "--port", "nope://x"])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and err.count("\n") == 0 and "unknown scheme 'nope'" in err


# --------------------------------------------------------------------------- faults


@pytest.mark.parametrize(
    "faults",
    [
        "&ber=1e-4&seed=11",  # about 1 bit in 10^4 flipped
        "&burst=3e-6&burst_bytes=200&drop=1e-6&dup=1e-6&seed=12",  # ~1-2 % of frames lost
    ],
)
def test_provision_completes_verified_under_line_faults(tmp_path, faults):
    path = tmp_path / "m.ecs"
    image = make_image(path, size_bytes=100_000)
    name = mem_name("noisy")
    with DeviceThread(f"mem://{name}?end=b&pace=0&{faults[1:]}", tmp_path / "flash"):
        result = provision(path, f"mem://{name}?end=a&pace=0{faults}",
                           ProvisionOptions(key=KEY, request_timeout_s=0.3, show_progress=False),
                           QUIET)
    assert result.outcome == "installed" and result.verified
    assert result.retransmitted_chunks > 0  # the faults did hit the transfer
    _check_device_holds(tmp_path / "flash", image)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_resume_after_a_disconnect_at_a_random_offset(tmp_path, seed):
    path = tmp_path / "m.ecs"
    image = make_image(path, size_bytes=400_000, seed=seed)
    cut = random.Random(seed).randrange(150_000, 380_000)
    name = mem_name("cut")

    def factory(attempt: int):
        extra = f"&disconnect_after={cut}" if attempt == 0 else ""
        return open_transport(f"mem://{name}?end=a&pace=0{extra}", timeout_s=5)

    with DeviceThread(f"mem://{name}?end=b&pace=0", tmp_path / "flash"):
        result = provision(path, "mem", ProvisionOptions(key=KEY, show_progress=False),
                           ProvisionParts(transport_factory=factory, log=lambda line: None))
    assert result.reconnects >= 1
    assert result.resume_offsets[0] == 0
    resumed = result.resume_offsets[1]
    assert 0 < resumed <= cut and resumed % 65536 == 0  # journalled 64 KiB blocks
    assert result.verified
    _check_device_holds(tmp_path / "flash", image)


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_resume_after_the_device_process_is_killed_and_restarted(tmp_path):
    path = tmp_path / "m.ecs"
    image = make_image(path, size_bytes=2_500_000)
    write_key(tmp_path / "dev.key", KEY)
    dev = DeviceProcess(tmp_path / "flash", key_file=tmp_path / "dev.key")
    port = dev.port
    state: dict = {"killed_at": None, "devices": [dev]}

    def on_progress(offset: int, size: int) -> None:
        if state["killed_at"] is None and offset >= 0.6 * size:
            state["killed_at"] = offset
            dev.kill()  # a reboot mid-transfer: SIGKILL, then start again on the same flash
            state["devices"].append(
                DeviceProcess(tmp_path / "flash", port=port, key_file=tmp_path / "dev.key")
            )

    try:
        result = provision(path, dev.url,
                           ProvisionOptions(key=KEY, request_timeout_s=0.5, show_progress=False),
                           ProvisionParts(on_progress=on_progress, log=lambda line: None))
    finally:
        for d in state["devices"]:
            d.stop()
    assert state["killed_at"] is not None and result.reconnects >= 1
    resumed = result.resume_offsets[-1]
    # The restarted device resumed from its journal: >= one 16-block flush (1 MiB) in.
    assert 1 << 20 <= resumed <= state["killed_at"]
    assert result.verified
    _check_device_holds(tmp_path / "flash", image)
    restarted = state["devices"][-1].lines
    assert any(f"resuming at {resumed}" in line for line in restarted)


def test_power_cuts_during_writing_and_committing_always_boot_old_or_new(tmp_path):
    old_path, new_path = tmp_path / "old.ecs", tmp_path / "new.ecs"
    old = make_image(old_path, size_bytes=1_500_000, generation=1, seed=1)
    new = make_image(new_path, size_bytes=1_500_000, generation=2, seed=2)
    digests = {hashlib.sha256(old).hexdigest(): "old", hashlib.sha256(new).hexdigest(): "new"}
    write_key(tmp_path / "dev.key", KEY)
    flash = tmp_path / "flash"
    dev = DeviceProcess(flash, key_file=tmp_path / "dev.key")
    try:
        provision(old_path, dev.url, ProvisionOptions(key=KEY, show_progress=False),
                  QUIET)
    finally:
        dev.stop()
    rng = random.Random(7)
    cuts = [("transfer", rng.uniform(0.05, 0.95)) for _ in range(2)] + [("commit", 0.0)]
    outcomes = []
    for where, fraction in cuts:
        dev = DeviceProcess(flash, key_file=tmp_path / "dev.key")
        killer: dict = {}

        def on_progress(offset, size, fraction=fraction, where=where, dev=dev, killer=killer):
            if where == "transfer" and offset >= fraction * size and not killer:
                killer["done"] = True
                dev.kill()

        def on_stage(name, where=where, dev=dev, killer=killer):
            if where == "commit" and name == "commit" and not killer:
                killer["done"] = True
                timer = threading.Timer(rng.uniform(0.0, 0.01), dev.kill)
                timer.start()
                killer["timer"] = timer

        try:
            provision(new_path, dev.url,
                      ProvisionOptions(key=KEY, max_reconnects=0, request_timeout_s=0.3,
                                       confirm_timeout_s=0.5, show_progress=False),
                      ProvisionParts(on_progress=on_progress, on_stage=on_stage,
                                     log=lambda line: None))
            finished = True
        except Exception:  # the link drops in some way; which one does not matter here
            finished = False
        assert where == "commit" or not finished  # a cut mid-transfer cannot finish
        if "timer" in killer:
            killer["timer"].join()
        dev.kill()
        store = FlashStore.open(flash, create=False)
        boot = store.boot()  # what the device does at power-up
        assert boot.ok and boot.verified, boot.reason
        outcomes.append(digests[boot.sha256.hex()])
        store.close()
    assert outcomes[0] == "old" and outcomes[1] == "old"  # the transfer never finished
    # And after all that, a clean run installs the new image.
    dev = DeviceProcess(flash, key_file=tmp_path / "dev.key")
    try:
        result = provision(new_path, dev.url, ProvisionOptions(key=KEY, show_progress=False),
                           QUIET)
    finally:
        dev.stop()
    assert result.outcome in ("installed", "already-active", "activated")
    _check_device_holds(flash, new)


# --------------------------------------------------------------------------- refusals


@pytest.fixture
def device(tmp_path):
    """A device thread on a fresh unpaced mem line; yields (url_for_host, DeviceThread)."""
    started = []

    def start(**config):
        name = mem_name("dev")
        dev = DeviceThread(f"mem://{name}?end=b&pace=0", tmp_path / f"flash{len(started)}",
                           **config)
        started.append(dev)
        return f"mem://{name}?end=a&pace=0", dev

    yield start
    for dev in started:
        dev.stop()


def _open_session(url: str, key=KEY, *, auth: bool = True) -> HostSession:
    link = Link(open_transport(url, timeout_s=5), owns_transport=True).start()
    link.set_tx_max_frame_bytes(4096)
    session = HostSession(link, key=key, request_timeout_s=0.5)
    if auth:
        session.start()
    return session


def _say_hello(session: HostSession) -> m.HelloReply:
    """HELLO at this protocol version, and nothing more (no AUTH): the device's reply."""
    version = m.PROTOCOL_VERSION
    return session.link.request(m.Hello(min_version=version, max_version=version,
                                        nonce=bytes(16)))


def test_no_common_protocol_version_is_one_clear_error(device):
    url, _ = device()
    link = Link(open_transport(url, timeout_s=5), owns_transport=True).start()
    try:
        # a protocol-1 host (untagged scores and chunks) meets a protocol-2 device
        session = HostSession(link, key=KEY, versions=(1, 1), request_timeout_s=0.5)
        with pytest.raises(RemoteUnsupportedVersion,
                           match=r"1\.\.1, this device 2\.\.2: update the older side") as info:
            session.start()
        assert "\n" not in str(info.value)
        assert info.value.detail == {"min_version": 2, "max_version": 2}
    finally:
        link.close()


def test_host_without_the_key_is_refused_before_sending(device, model):
    url, _ = device()
    with pytest.raises(AuthenticationError, match="holds a key"):
        provision(model[0], url, ProvisionOptions(key=None, precheck=False, show_progress=False),
                  QUIET)


def test_unauthenticated_signed_request_is_refused_not_authenticated(device):
    url, _ = device()
    session = _open_session(url, auth=False)
    try:
        _say_hello(session)
        with pytest.raises(RemoteNotAuthenticated):
            session.link.request(m.ImageAbort(), retries=0)
    finally:
        session.link.close()


def test_wrong_key_is_refused_auth_failed(device, model):
    url, dev = device()
    with pytest.raises(RemoteAuthFailed):
        provision(model[0], url,
                  ProvisionOptions(key=OTHER_KEY, precheck=False, show_progress=False),
                  QUIET)
    assert any("auth failed" in line for line in dev.lines)


def test_replayed_and_cross_session_frames_are_refused(device):
    url, _ = device()
    session = _open_session(url)
    try:
        first = session.sign(m.ImageAbort())
        assert isinstance(session.link.request(first, retries=0), m.Ok)
        assert isinstance(session.call(m.ImageAbort(), retries=0), m.Ok)  # counter 2
        # An exact repeat of the LAST accepted frame is a host retry: answered, not re-run ...
        second = session.sign(m.ImageAbort())
        assert isinstance(session.link.request(second, retries=0), m.Ok)
        assert isinstance(session.link.request(second, retries=0), m.Ok)
        # ... but an older frame is a replay.
        with pytest.raises(RemoteReplayed):
            session.link.request(first, retries=0)
    finally:
        session.link.close()
    other = _open_session(url)  # a new session: new nonces, new session key
    try:
        with pytest.raises(RemoteAuthFailed):
            other.link.request(second, retries=0)
    finally:
        other.link.close()


def test_device_without_a_key_refuses_provisioning_unless_insecure(device, tmp_path):
    path = tmp_path / "unsigned.ecs"
    image = make_image(path, size_bytes=30_000, key=None)
    url, _ = device(key=None)
    with pytest.raises(RemoteNotAuthenticated, match="no key"):
        provision(path, url, ProvisionOptions(key=None, show_progress=False),
                  QUIET)
    url, dev = device(key=None, insecure=True)
    result = provision(path, url, ProvisionOptions(key=None, show_progress=False),
                       QUIET)
    assert result.outcome == "installed" and result.confirmed
    _check_device_holds(dev.config.flash_dir, image)


def _record_received(dev: DeviceThread, *types: m.MessageType) -> list[m.MessageType]:
    """Count what the device is sent of ``types`` (then handle it as usual: the per-message
    handler method is wrapped on the instance, so authorization still runs before it)."""
    seen: list[m.MessageType] = []
    for msg_type in types:
        name = Device.HANDLERS[msg_type]
        original = getattr(dev.device, name)

        def handler(msg, frame, original=original, msg_type=msg_type):
            seen.append(msg_type)
            return original(msg, frame)

        setattr(dev.device, name, handler)
    return seen


_IMAGE_TYPES = (m.MessageType.IMAGE_STATUS, m.MessageType.IMAGE_BEGIN, m.MessageType.IMAGE_CHUNK,
                m.MessageType.IMAGE_COMMIT, m.MessageType.SLOT_SET)


def test_a_host_with_a_key_refuses_a_device_that_says_it_has_none(device, model):
    """Item 4 of issue 11: an impostor (or a man in the middle clearing has_key) gets nothing."""
    path, image = model
    url, dev = device(key=None, insecure=True)  # answers HELLO_REPLY has_key=false
    seen = _record_received(dev, *_IMAGE_TYPES)
    with pytest.raises(AuthenticationError, match=r"says it holds no key.*--insecure"):
        provision(path, url, ProvisionOptions(key=KEY, show_progress=False),
                  QUIET)
    assert seen == []
    assert FlashStore.open(dev.config.flash_dir).active_slot is None
    lines: list[str] = []
    result = provision(path, url, ProvisionOptions(key=KEY, insecure=True, show_progress=False),
                       ProvisionParts(log=lines.append))
    assert result.outcome == "installed" and result.confirmed
    assert m.MessageType.IMAGE_CHUNK in seen
    _check_device_holds(dev.config.flash_dir, image)
    assert sum("--insecure" in line for line in lines) == 1


def test_cli_provision_with_a_key_to_a_keyless_device_is_one_line_and_sends_nothing(
    device, model, tmp_path, capsys
):
    path, _ = model
    write_key(tmp_path / "k.key", KEY)
    url, dev = device(key=None, insecure=True)
    seen = _record_received(dev, *_IMAGE_TYPES)
    rc = cli_main(["provision", str(path), "--port", url, "--key", str(tmp_path / "k.key"),
                   "--quiet"])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and err.count("\n") == 0
    assert "holds no key" in err and "--pair" in err and "--insecure" in err
    assert seen == []
    rc = cli_main(["provision", str(path), "--port", url, "--key", str(tmp_path / "k.key"),
                   "--insecure", "--quiet"])
    assert rc == 0 and m.MessageType.IMAGE_CHUNK in seen


def _with_annex(tmp_path, damage: str):
    """A signed image with a host annex, then damaged as ``view`` would refuse it."""
    import numpy as np

    from protocol.image import read_image, write_image

    plain = tmp_path / "plain.ecs"
    make_image(plain, size_bytes=30_000)
    image = read_image(plain)
    path = tmp_path / f"{damage}.ecs"
    annex = {"training_scores": np.arange(6 * image.n_coefficients, dtype=np.float32).reshape(
        6, image.n_coefficients)}
    write_image(path, image, key=KEY, annex=annex)
    data = bytearray(path.read_bytes())
    size = struct.unpack_from("<Q", data, 20)[0]
    assert len(data) > size  # the annex follows the device image
    if damage == "missing-annex":
        del data[size:]
    elif damage == "corrupt-annex":
        data[size + (len(data) - size) // 2] ^= 0xFF
    elif damage == "trailing-garbage":
        data += b"garbage after the end"
    path.write_bytes(bytes(data))
    return path


@pytest.mark.parametrize("damage, text", [("missing-annex", "annex"),
                                          ("corrupt-annex", "annex"),
                                          ("trailing-garbage", "trailing bytes")])
def test_provision_validates_the_file_as_view_does_before_sending(device, tmp_path, capsys,
                                                                  damage, text):
    """Item 6 of issue 11: what view/serve/evaluate refuse, provision refuses, in one line,
    before anything is sent."""
    from host.fit.model import HostModel, read_model_image
    from protocol.errors import ImageFormatError

    path = _with_annex(tmp_path, damage)
    with pytest.raises(ImageFormatError):  # the validation view, serve and evaluate use
        HostModel.load(path, key=KEY)
    with pytest.raises(ImageFormatError):
        read_model_image(path)
    url, dev = device()
    seen = _record_received(dev, *_IMAGE_TYPES)
    with pytest.raises(ProvisionError, match=f"{text}.*nothing was installed"):
        provision(path, url, ProvisionOptions(key=KEY, show_progress=False),
                  QUIET)
    write_key(tmp_path / "k.key", KEY)
    rc = cli_main(["provision", str(path), "--port", url, "--key", str(tmp_path / "k.key")])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and err.count("\n") == 0 and text in err and "nothing was installed" in err
    assert seen == []
    assert FlashStore.open(dev.config.flash_dir).active_slot is None


def test_provision_sends_an_intact_image_with_its_annex(device, tmp_path):
    path = _with_annex(tmp_path, "none")
    url, dev = device()
    result = provision(path, url, ProvisionOptions(key=KEY, show_progress=False),
                       QUIET)
    assert result.outcome == "installed" and result.confirmed
    size = struct.unpack_from("<Q", path.read_bytes(), 20)[0]
    _check_device_holds(dev.config.flash_dir, path.read_bytes()[:size])  # not the annex


def test_image_signed_with_another_key_is_refused_at_verify(device, tmp_path):
    path = tmp_path / "other.ecs"
    make_image(path, size_bytes=40_000, key=OTHER_KEY)
    with pytest.raises(ProvisionError, match="different key"):
        inspect_image(path, key=KEY)
    url, dev = device()
    with pytest.raises(RemoteTagMismatch):
        provision(path, url, ProvisionOptions(key=KEY, precheck=False, show_progress=False),
                  QUIET)
    store = FlashStore.open(dev.config.flash_dir)
    assert store.active_slot is None  # nothing was committed
    assert store.status()["journal"] is None  # and the transfer was discarded


def _refused_by_host_and_device(path, url: str, host_match: str, remote: type[Exception],
                                remote_match: str | None = None) -> Exception:
    """Provisioning ``path`` to ``url`` is refused twice: by the host's precheck (a
    `ProvisionError` matching ``host_match``) and, with the precheck off, by the device
    (``remote``, matching ``remote_match``); the device's error."""
    with pytest.raises(ProvisionError, match=host_match):
        provision(path, url, ProvisionOptions(key=KEY, show_progress=False), QUIET)
    with pytest.raises(remote, match=remote_match) as info:
        provision(path, url, ProvisionOptions(key=KEY, precheck=False, show_progress=False),
                  QUIET)
    return info.value


def test_ram_budget_is_enforced_by_host_and_device(device, model):
    path, _ = model
    url, _ = device(ram_budget_bytes=1 << 20)
    error = _refused_by_host_and_device(path, url, "TOO_LARGE_FOR_RAM", RemoteTooLargeForRam,
                                        r"budget is 1048576")
    assert error.detail["limit_bytes"] == 1 << 20


def test_flash_size_is_enforced_by_host_and_device(device, model):
    path, _ = model
    url, _ = device(slot_size_bytes=100_000)
    _refused_by_host_and_device(path, url, "TOO_LARGE_FOR_FLASH", RemoteTooLargeForFlash)


def test_unsupported_format_version_is_refused(device, model):
    url, _ = device()
    session = _open_session(url)
    try:
        begin = m.ImageBegin(size_bytes=1000, digest=bytes(32), image_tag=bytes(32),
                             format_version=4, generation=1)
        with pytest.raises(RemoteUnsupportedFormat, match="format version 4"):
            session.call(begin, retries=0)
    finally:
        session.link.close()
    hello = session.hello
    info = dataclasses.replace(inspect_image(model[0]), format_version=4)
    from host.link.provisioning import _precheck

    with pytest.raises(ProvisionError, match="UNSUPPORTED_FORMAT"):
        _precheck(info, hello, force=False)


def test_an_image_whose_header_lies_about_its_version_is_refused_mid_transfer(device, tmp_path):
    path = tmp_path / "m.ecs"
    image = make_image(path, size_bytes=60_000)
    url, _ = device()
    session = _open_session(url)
    try:
        begin = m.ImageBegin(size_bytes=len(image), digest=hashlib.sha256(image).digest(),
                             image_tag=image[-32:], format_version=1, generation=1)
        bad = bytearray(image)
        struct.pack_into("<H", bad, 8, 7)  # header: format version 7
        bad = reseal(bytes(bad))
        box = {}
        ack = session.call(dataclasses.replace(begin, digest=hashlib.sha256(bad).digest()),
                           on_reply=lambda rid, r: box.setdefault("id", rid))
        from protocol.image_transfer import send_image

        with pytest.raises(RemoteUnsupportedFormat):
            send_image(session.link, bad, transfer_id=box["id"], first_ack=ack, chunk_bytes=1024,
                       tag=session.tag_event)
    finally:
        session.link.close()


def _bomb(image: bytes) -> bytes:
    """The image with a manifest that declares an enormous eigenspace (same compressed data)."""
    header = struct.unpack_from("<8sHHHHIQI", image)
    manifest_size = header[5]
    manifest = cbor2.loads(image[32:32 + manifest_size])
    for entry in manifest["sections"]:
        if entry["name"] == "eigenimages":
            entry["shape"][0] *= 100_000
            entry["raw_size"] *= 100_000
    encoded = cbor2.dumps(manifest, canonical=True)
    rest = image[32 + manifest_size:]
    head = bytearray(image[:32])
    struct.pack_into("<I", head, 16, len(encoded))
    return reseal(bytes(head) + encoded + rest)


def test_a_decompression_bomb_manifest_is_refused_before_anything_is_inflated(device, tmp_path):
    path = tmp_path / "m.ecs"
    image = make_image(path, size_bytes=60_000)
    bomb_path = tmp_path / "bomb.ecs"
    bomb_path.write_bytes(_bomb(image))
    url, _ = device()
    # the host's file validation (the one view/serve use) refuses it before connecting
    _refused_by_host_and_device(bomb_path, url, r"over the limit.*nothing was installed",
                                RemoteTooLargeForRam)
    # The device is still fine and takes the honest image.
    assert provision(path, url, ProvisionOptions(key=KEY, show_progress=False),
                     QUIET).outcome == "installed"


def test_rollback_is_refused_unless_forced_and_known_images_are_activated(device, tmp_path):
    v1, v2 = tmp_path / "v1.ecs", tmp_path / "v2.ecs"
    image1 = make_image(v1, size_bytes=40_000, generation=1, seed=1)
    make_image(v2, size_bytes=40_000, generation=2, seed=2)
    url, dev = device()
    assert provision(v2, url, ProvisionOptions(key=KEY, show_progress=False),
                     QUIET).outcome == "installed"
    _refused_by_host_and_device(v1, url, "ROLLBACK_REFUSED", RemoteRollbackRefused)
    forced = provision(v1, url, ProvisionOptions(key=KEY, force=True, show_progress=False),
                       QUIET)
    assert forced.outcome == "installed" and forced.slot == "B"
    _check_device_holds(dev.config.flash_dir, image1, slot="B")
    # v2 is still in slot A (confirmed): asking for it again activates it, nothing is sent.
    back = provision(v2, url, ProvisionOptions(key=KEY, show_progress=False),
                     QUIET)
    assert back.outcome == "activated" and back.slot == "A" and back.data_bytes_sent == 0


# --------------------------------------------------------------------------- units


def test_chunk_size_follows_the_line_rate_and_device_buffers():
    hello = m.HelloReply(
        min_version=1, max_version=1, device_id="d", nonce=bytes(16), max_frame_bytes=4096,
        ram_budget_bytes=1, slot_size_bytes=1, display_width=0, display_height=0,
        rx_window_frames=8, rx_buffer_bytes=4000, slots=(), has_key=True,
    )

    class Serial:
        scheme, baud, max_frame_bytes = "", 115200, 4096

    class Tcp:
        scheme, baud, max_frame_bytes = "socket", 115200, 16384

    link = Link(Tcp())  # only its frame limit is used
    link.set_tx_max_frame_bytes(4096)
    assert choose_chunk_bytes(Serial(), hello, link) == 896  # 80 ms at 115200 baud
    assert choose_chunk_bytes(Tcp(), hello, link) == 4000  # the device's buffer
    assert choose_chunk_bytes(Tcp(), hello, link, 100) == 100


def test_device_config_checks_its_inputs(tmp_path):
    with pytest.raises(ValueError, match="insecure"):
        DeviceConfig(flash_dir=tmp_path, key=KEY, insecure=True)
    with pytest.raises(ValueError, match="device_id"):
        DeviceConfig(flash_dir=tmp_path, device_id="")
    with pytest.raises(ValueError, match="rx_window_frames"):
        DeviceConfig(flash_dir=tmp_path, rx_window_frames=0)
    assert Device(DeviceConfig(flash_dir=tmp_path / "f"), log=lambda s: None).store is not None


# ------------------------------------------------------------------ hostile peers (issue 11)


def test_hello_reply_before_auth_hides_slots_and_budgets(tmp_path, model, device):
    path, image = model
    url, dev = device()
    provision(path, url, ProvisionOptions(key=KEY, show_progress=False),
              QUIET)
    raw = _open_session(url, auth=False)
    try:
        hello = _say_hello(raw)
        # what starting a session needs, nothing about the installed images or budgets
        assert hello.has_key and hello.device_id == dev.config.device_id
        assert hello.max_frame_bytes >= 1024 and hello.rx_window_frames >= 1
        assert hello.slots == () and hello.ram_budget_bytes == 0 and hello.slot_size_bytes == 0
        with pytest.raises(RemoteNotAuthenticated, match="IMAGE_STATUS needs an authenticated"):
            raw.link.request(m.ImageStatus(digest=hashlib.sha256(image).digest(),
                                           size_bytes=len(image)), retries=0)
    finally:
        raw.link.close()
    # an authenticated host gets the real slots and budgets (prechecks keep working)
    session = _open_session(url)
    try:
        full = session.hello
        assert full.ram_budget_bytes == dev.config.ram_budget_bytes
        assert full.slot_size_bytes == dev.device.store.capacity_bytes
        active = [s for s in full.slots if s.active]
        assert len(active) == 1 and active[0].digest == hashlib.sha256(image).digest()
    finally:
        session.link.close()
    # a keyless device answers as before
    url2, _ = device(key=None, insecure=True)
    raw = _open_session(url2, key=None, auth=False)
    try:
        hello = _say_hello(raw)
        assert len(hello.slots) == 2 and hello.ram_budget_bytes > 0
    finally:
        raw.link.close()


def test_untagged_bad_tag_and_replayed_chunks_are_not_stored(tmp_path, device):
    image = make_image(tmp_path / "m.ecs", size_bytes=20_000)
    url, dev = device()
    session = _open_session(url)
    stats = dev.device.stats
    try:
        begin = m.ImageBegin(size_bytes=len(image), digest=hashlib.sha256(image).digest(),
                             image_tag=image[-32:], format_version=1, generation=1)
        box = {}
        session.call(begin, on_reply=lambda rid, r: box.setdefault("id", rid))
        chunk = m.ImageChunk(offset=0, data=image[:512])
        session.link.send(chunk, request_id=box["id"])  # untagged
        session.link.send(auth.tag_event(chunk, OTHER_KEY, 1), request_id=box["id"])  # bad tag

        def dropped() -> int:
            return stats.dropped_unauthenticated + stats.dropped_bad_tag

        _wait(lambda: dropped() == 2, "the two chunks dropped")
        assert stats.dropped_unauthenticated == 1 and stats.dropped_bad_tag == 1
        assert stats.chunks == 0  # nothing written
        tagged = session.tag_event(chunk)
        session.link.send(tagged, request_id=box["id"])
        _wait(lambda: stats.chunks == 1, "the tagged chunk stored")
        session.link.send(tagged, request_id=box["id"])  # the same frame again
        _wait(lambda: stats.dropped_replayed == 1, "the replayed chunk dropped")
        assert stats.chunks == 1
    finally:
        session.link.close()


def _wait(predicate, what: str, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        threading.Event().wait(0.01)


def _tcp(dev: DeviceThread) -> str:
    return f"socket://127.0.0.1:{dev.transport.port}"


def test_auth_deadline_drops_a_hello_and_ping_hog(tmp_path):
    with DeviceThread("tcp-listen://127.0.0.1:0", tmp_path / "flash",
                      auth_timeout_s=0.5) as dev:
        hog = _open_session(_tcp(dev), auth=False)
        try:
            _say_hello(hog)
            pings = 0
            deadline = time.monotonic() + 10
            while not hog.link.closed and time.monotonic() < deadline:
                with contextlib.suppress(ProtocolError):
                    hog.ping(timeout_s=0.2, retries=0)  # valid frames: they do not extend it
                    pings += 1
                threading.Event().wait(0.05)
            assert hog.link.closed and pings >= 2
            assert dev.device.stats.auth_timeouts == 1
            assert any("did not authenticate within 0.5 s" in line for line in dev.lines)
        finally:
            hog.link.close()


def test_a_host_gets_in_beside_an_unauthenticated_connection(tmp_path, model):
    """The lobby serves connections side by side: a host authenticates while a peer that said
    HELLO holds its place, and nobody is replaced (the deadline does not explain it)."""
    path, image = model
    with DeviceThread("tcp-listen://127.0.0.1:0", tmp_path / "flash",
                      auth_timeout_s=600) as dev:
        hog = _open_session(_tcp(dev), auth=False)
        try:
            _say_hello(hog)
            result = provision(path, _tcp(dev), ProvisionOptions(key=KEY, show_progress=False),
                               QUIET)
            assert result.outcome == "installed" and result.confirmed
            assert dev.device.stats.preempted == 0 and not hog.link.closed
            assert dev.device.lobby.stats.admitted >= 1
            hog.link.request(m.Ping(sent_us=1), timeout_s=2.0)  # still served, unauthenticated
        finally:
            hog.link.close()
        _check_device_holds(tmp_path / "flash", image)


def test_the_lobby_is_paused_while_a_host_is_served(tmp_path):
    """Connections in the lobby wait, their clocks stopped, while a host is served: a peer
    given 2 s to authenticate is still there after a 2.5 s session, and dropped after."""
    with DeviceThread("tcp-listen://127.0.0.1:0", tmp_path / "flash",
                      auth_timeout_s=2.0) as dev:
        peer = _open_session(_tcp(dev), auth=False)
        try:
            _say_hello(peer)
            host = _open_session(_tcp(dev))
            threading.Event().wait(2.5)  # the session outlasts the peer's deadline
            host.ping(timeout_s=1.0)
            host.link.close()
            peer.link.request(m.Ping(sent_us=1), timeout_s=0.5, retries=0)  # still served
            _wait(lambda: peer.link.closed, "the peer dropped at its deadline")
            assert dev.device.stats.auth_timeouts == 1
        finally:
            peer.link.close()


def test_a_reconnecting_peer_does_not_displace_a_host_between_hello_and_auth(tmp_path):
    with DeviceThread("tcp-listen://127.0.0.1:0", tmp_path / "flash",
                      auth_timeout_s=600) as dev:
        host = _open_session(_tcp(dev), auth=False)
        newcomers = []
        authenticate = host.authenticate

        def slow_authenticate() -> None:  # the hog connects after our HELLO, before AUTH
            newcomers.append(_open_session(_tcp(dev), auth=False))
            _wait(lambda: dev.device.lobby.peers[0] == 2, "the newcomer in the lobby")
            threading.Event().wait(0.3)  # a slow host
            authenticate()

        host.authenticate = slow_authenticate
        try:
            host.start()
            assert host.authenticated
            host.ping(timeout_s=1.0, retries=0)
            assert dev.device.stats.preempted == 0
        finally:
            for newcomer in newcomers:
                newcomer.link.close()
            host.link.close()


def test_an_authenticated_host_is_not_displaced_by_a_newcomer(tmp_path):
    with DeviceThread("tcp-listen://127.0.0.1:0", tmp_path / "flash",
                      auth_timeout_s=0.3) as dev:
        host = _open_session(_tcp(dev))
        assert host.authenticated
        newcomer = _open_session(_tcp(dev), auth=False)
        try:
            with pytest.raises(ProtocolError):  # waits in the backlog: no answer
                newcomer.link.request(m.Ping(sent_us=1), timeout_s=0.3, retries=2)
            host.ping(timeout_s=1.0, retries=0)  # past the auth deadline: still served
            assert dev.device.stats.preempted == 0 and dev.device.stats.auth_timeouts == 0
        finally:
            newcomer.link.close()
            host.link.close()


def test_a_signed_request_with_an_added_handler_still_needs_authentication(tmp_path):
    calls = []
    with DeviceThread("tcp-listen://127.0.0.1:0", tmp_path / "flash") as dev:
        dev.device.on(m.MessageType.RESET, lambda msg, frame: calls.append(msg) or m.Ok())
        raw = _open_session(_tcp(dev), auth=False)
        try:
            _say_hello(raw)
            with pytest.raises(RemoteNotAuthenticated):
                raw.link.request(m.Reset(), timeout_s=2.0, retries=0)
            assert calls == []
        finally:
            raw.link.close()


def test_an_unauthenticated_peer_cannot_flood_the_device_log(tmp_path):
    """30 connections, each HELLO, a bad AUTH, a NOTICE and a BYE, then gone: one line of
    each kind (and of "host disconnected": none, it was never a host)."""
    with DeviceThread("tcp-listen://127.0.0.1:0", tmp_path / "flash",
                      auth_timeout_s=600) as dev:
        version = m.PROTOCOL_VERSION
        wire = b"".join(msg.encode(request_id=i + 1) for i, msg in enumerate((
            m.Hello(min_version=version, max_version=version, nonce=bytes(16)),
            m.AuthChallenge(host_proof=bytes(32)),
            m.Notice(level=1, text="x" * 200),
            m.Bye(reason="y" * 50))))
        for _ in range(30):
            with socket.create_connection(("127.0.0.1", dev.transport.port)) as raw:
                raw.sendall(wire)
        _wait(lambda: dev.device.lobby.stats.frames >= 4 * 30, "the 120 frames handled")
        assert dev.device.stats.sessions >= 30
        for what in ("hello from host", "auth failed", "host notice", "bye from host"):
            assert sum(what in line for line in dev.lines) == 1, what
        assert not any("disconnected" in line for line in dev.lines)
