"""`render` / `fit` with ``--scheduler``: a real Dask LocalCluster (two worker processes).

The cluster paths must give the same bytes as the in-process paths, survive a worker killed
mid-run (Dask reruns its tasks), resume after a killed client, and fail in one line when Dask
is missing or the scheduler cannot be reached.
"""

from __future__ import annotations

import os
import signal
import sys
import types
from pathlib import Path

import distributed
import pytest
from cli_helpers import kill_render_halfway, run_cli, snapshot

import host.cluster
import host.fit.model
from host.cli import main
from host.progress import Progress
from host.render.cinema import CinemaDB, CinemaWriter

VIEWS = "grid:30x6"  # 180 views: long enough to catch a client halfway
SMALL = ["--size", "40", "--samples", "150"]
FIT = ["--cell", "8"]


@pytest.fixture(scope="module")
def scheduler():
    """Address of a LocalCluster with two single-threaded worker processes."""
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=":0") as cluster:
        yield cluster.scheduler_address


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The in-process render of the test database."""
    db = tmp_path_factory.mktemp("ref") / "ref.cdb"
    assert main(["render", "builtin:tooth", "-o", str(db), "--views", VIEWS, *SMALL]) == 0
    return db


@pytest.fixture
def frozen_clock(monkeypatch):
    """The .ecs records its creation time; freeze it so two fits can be compared byte for byte."""
    monkeypatch.setattr(host.fit.model, "time", types.SimpleNamespace(
        time=lambda: 1_700_000_000.0, time_ns=lambda: 1_700_000_000 * 10**9))


def _kill_one_worker_on_first_call(monkeypatch, scheduler, owner, name):
    """Patch ``owner.name`` to SIGKILL one worker process the first time it is called."""
    killed: list[int] = []
    original = getattr(owner, name)

    def wrapper(*args, **kwargs):
        if not killed:
            with distributed.Client(scheduler, timeout="20s") as client:
                pid = sorted(client.run(os.getpid).values())[0]
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)
        return original(*args, **kwargs)

    monkeypatch.setattr(owner, name, wrapper)
    return killed


def test_local_n_render_is_byte_identical_to_in_process(tmp_path, reference):
    """Depth maps included (render stores them by default, on a cluster too)."""
    db = tmp_path / "local.cdb"
    assert main(["render", "builtin:tooth", "-o", str(db), "--views", VIEWS, *SMALL,
                 "--scheduler", "local:2"]) == 0
    assert CinemaDB.open(reference).depth is not None
    assert sum(name.startswith("depth/view_") for name in snapshot(db)) == 180
    assert snapshot(db) == snapshot(reference)


def test_a_cinematic_render_on_the_cluster_is_byte_identical(tmp_path, scheduler):
    """The workers compute the same light field (or read the client's from the cache)."""
    args = ["render", "builtin:tooth", "--views", "grid:8x3", *SMALL, "--lighting", "cinematic"]
    assert main([*args, "-o", str(tmp_path / "here.cdb")]) == 0
    assert main([*args, "-o", str(tmp_path / "there.cdb"), "--scheduler", scheduler]) == 0
    here, there = snapshot(tmp_path / "here.cdb"), snapshot(tmp_path / "there.cdb")
    assert here == there and sum(name.startswith("images/") for name in here) == 24


def test_render_survives_a_killed_worker(tmp_path, reference, scheduler, monkeypatch):
    killed = _kill_one_worker_on_first_call(monkeypatch, scheduler, CinemaWriter, "write_png")
    db = tmp_path / "killed.cdb"
    assert main(["render", "builtin:tooth", "-o", str(db), "--views", VIEWS, *SMALL,
                 "--scheduler", scheduler]) == 0
    assert len(killed) == 1
    with pytest.raises(ProcessLookupError):
        os.kill(killed[0], 0)  # the worker really died mid-run
    assert snapshot(db) == snapshot(reference)


def test_killed_client_resumes_to_the_same_database(tmp_path, reference, scheduler):
    db = tmp_path / "resumed.cdb"
    args = ["render", "builtin:tooth", "-o", str(db), "--views", VIEWS, *SMALL,
            "--scheduler", scheduler]
    written = kill_render_halfway(args, db, 1)
    assert 1 <= written < 180
    out = run_cli(*args)
    assert "resuming" in out.stderr
    assert snapshot(db) == snapshot(reference)


def test_fit_is_byte_identical_and_survives_a_killed_worker(
    tmp_path, reference, scheduler, monkeypatch, frozen_clock
):
    local, remote = tmp_path / "local.ecs", tmp_path / "cluster.ecs"
    assert main(["fit", str(reference), "-o", str(local), *FIT]) == 0
    killed = _kill_one_worker_on_first_call(monkeypatch, scheduler, Progress, "advance")
    assert main(["fit", str(reference), "-o", str(remote), *FIT,
                 "--scheduler", scheduler]) == 0
    assert len(killed) == 1
    assert remote.read_bytes() == local.read_bytes()


def _synthetic_database(path: Path, n_views: int = 600, size: int = 60) -> Path:
    """Smooth images that vary with the view, written as a Cinema database (no ray-casting)."""
    import numpy as np

    from host.render.camera import parse_view_set

    rng = np.random.default_rng(0)
    views = parse_view_set(f"fibonacci:{n_views}").views
    yy, xx = np.mgrid[0:size, 0:size] / size
    basis = np.stack([np.sin((i + 1) * np.pi * xx) * np.cos((i % 5 + 1) * np.pi * yy)
                      for i in range(12)])  # (12, size, size)
    cam = {"position": [0.0, 0.0, 1.0], "look_at": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0]}
    writer = CinemaWriter(path, {"synthetic": True},
                          [(v.phi_deg, v.theta_deg, cam) for v in views], (size, size))
    for i in range(n_views):
        coeff = rng.normal(size=(12, 3))
        image = (128 + 20 * np.einsum("khw,kc->hwc", basis, coeff)
                 + rng.normal(0, 3, (size, size, 3)))
        writer.write_image(i, np.clip(image, 0, 255).astype(np.uint8))
    writer.write_csv()
    return path


def test_fit_matches_in_process_where_blas_runs_threads(tmp_path, scheduler, frozen_clock):
    """600 views x 2700-entry cells: big enough for OpenBLAS to split work across threads,
    which changes the fitted bits unless the workers use the client's thread counts."""
    db = _synthetic_database(tmp_path / "synthetic.cdb")
    local, remote = tmp_path / "local.ecs", tmp_path / "cluster.ecs"
    assert main(["fit", str(db), "-o", str(local), "--cell", "30"]) == 0
    assert main(["fit", str(db), "-o", str(remote), "--cell", "30",
                 "--scheduler", scheduler]) == 0
    assert remote.read_bytes() == local.read_bytes()


def test_fit_blocks_split_cells_across_tasks(reference, scheduler):
    """More than one block and more than one group of views: the stack is really cut up."""
    from host.fit.pca import CellEigenspace
    from host.render.cinema import CinemaDB

    db = CinemaDB.open(reference)
    model = CellEigenspace("adaptive", cell=8)
    cluster = host.cluster.Cluster(scheduler)
    try:
        seen = []
        original = cluster.client.submit

        def submit(func, *args, **kwargs):
            seen.append(func.__name__ if hasattr(func, "__name__") else str(func))
            return original(func, *args, **kwargs)

        cluster.client.submit = submit
        host.cluster.fit_blocks(cluster, model, db, (8, 8), progress=False)
    finally:
        cluster.close()
    assert seen.count("_fit_block") > 1 and seen.count("_stack_pieces") > 1
    assert model.n_components_.shape == (25,)


@pytest.mark.parametrize("command", ["render", "fit"])
def test_missing_dask_is_one_line(tmp_path, reference, monkeypatch, capsys, command):
    monkeypatch.setitem(sys.modules, "distributed", None)  # `import distributed` fails
    if command == "render":
        argv = ["render", "builtin:sphere", "-o", str(tmp_path / "x.cdb"), "--views",
                "list:0,0", *SMALL, "--scheduler", "local:2"]
    else:
        argv = ["fit", str(reference), "-o", str(tmp_path / "x.ecs"), "--scheduler", "local:2"]
    assert main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "pip install 'eigencast[cluster]'" in err


@pytest.mark.parametrize("address,message", [
    ("tcp://127.0.0.1:9", "cannot reach the scheduler"),
    ("local:zero", "expected local:N"),
])
def test_bad_scheduler_is_one_line(tmp_path, reference, monkeypatch, capsys, address, message):
    monkeypatch.setattr(host.cluster, "CONNECT_TIMEOUT_S", 2.0)
    assert main(["fit", str(reference), "-o", str(tmp_path / "x.ecs"),
                 "--scheduler", address]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err
    assert not (tmp_path / "x.ecs").exists()
