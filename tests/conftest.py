"""Shared test setup: no display, deterministic threads, real-data skips, the tiny model,
the small tooth database."""

from __future__ import annotations

import os

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
os.environ.setdefault("SDL_AUDIODRIVER", "dummy")
os.environ.setdefault("EIGENCAST_CACHE_DIR", "")  # no light fields cached on disk by tests

import pytest

from host.shared_data import SHARED_VOLUMES, shared_volume


@pytest.fixture
def shared_path():
    """Return a function name -> Path that skips (with the reason) when absent."""

    def get(name: str):
        path = shared_volume(name)
        if path is None:
            pytest.skip(
                f"../shared/data/{SHARED_VOLUMES[name]} not found "
                "(the shared real-volume folder is absent; set EIGENCAST_SHARED_DATA)"
            )
        return path

    return get


@pytest.fixture(scope="session")
def tooth_db(tmp_path_factory):
    """A small Cinema database of the built-in tooth (grid:24x6 views, 40 px, 120 samples, no
    depth: its models blend), rendered once per session; shared by the evaluate and target
    tests."""
    from host.cli import main as eigencast

    db = tmp_path_factory.mktemp("tooth-db") / "tooth.cdb"
    assert eigencast(["render", "builtin:tooth", "-o", str(db), "--views", "grid:24x6",
                      "--size", "40", "--samples", "120", "--no-depth"]) == 0
    return db


@pytest.fixture(scope="session")
def depth_model_path(tmp_path_factory):
    """A tooth model with depth and the standalone table (the defaults), 48 px, signed with
    `provision_helpers.KEY`; its database ``tooth.cdb`` and key file ``device.key`` lie beside
    it. Built once per session."""
    from provision_helpers import KEY

    from host.cli import main as eigencast
    from protocol.keys import write_key

    root = tmp_path_factory.mktemp("depth-model")
    db, out, key = root / "tooth.cdb", root / "tooth.ecs", root / "device.key"
    write_key(key, KEY, force=True)
    assert eigencast(["render", "builtin:tooth", "-o", str(db), "--views", "grid:24x6",
                      "--size", "48", "--samples", "80"]) == 0
    assert eigencast(["fit", str(db), "-o", str(out), "--cell", "12", "--threshold", "0.99",
                      "--key", str(key)]) == 0
    return out


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    """The signed, standalone tiny tooth model of `runtime_helpers.tiny_model` (built once
    per session; a module may define its own ``model_path``)."""
    from runtime_helpers import tiny_model

    return tiny_model(tmp_path_factory)


@pytest.fixture(scope="module")
def model(model_path):
    """`host.fit.model.HostModel` of ``model_path``."""
    from host.fit.model import HostModel

    return HostModel.load(model_path)


@pytest.fixture
def pair():
    """Open both ends of a fresh mem line: ``pair(a_opts, b_opts, baud=)`` -> (a, b) transports
    (unpaced by default); closed at the end. Link-engine and image-transfer tests."""
    from provision_helpers import mem_name

    from protocol.transport import open_transport

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
    """Start links: ``links(transport, **Link kwargs)`` -> started Link; closed at the end."""
    from protocol.link import Link

    started = []

    def start(transport, **kwargs):
        link = Link(transport, **kwargs).start()
        started.append(link)
        return link

    yield start
    for link in started:
        link.close(flush_timeout_s=0.2)
