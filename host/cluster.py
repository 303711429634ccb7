"""Render and fit on a Dask cluster: ``eigencast render|fit ... --scheduler ADDRESS``.

Both heavy steps are embarrassingly parallel, so they map onto Dask distributed tasks
(``pip install 'eigencast[cluster]'``; Dask is imported only when ``--scheduler`` is given):

* **render**: the pending views are cut into batches (`views_per_task`); each task ray-casts
  its batch on a worker and returns PNG bytes (and each view's depth map, as the in-process
  render makes it), which the client writes into the Cinema
  database exactly as the in-process render does (atomic writes, ``data.csv``, progress bar,
  resume). A worker builds its `host.render.raycast.Renderer` once per scene from the command's own
  options (`scene_recipe`): built-in volumes are regenerated there, file volumes are read
  from their (absolute) path, which every worker must be able to read. The worker checks
  that its scene has the client's fingerprint (`scene_fingerprint`) before rendering.
* **fit**: the cell-major stack is built in parallel (one task per group of views decodes
  its PNGs, read by path from the database folder, and cuts them into cells, one piece per
  block of cells) and each fit task joins one block's pieces, ``(cells, n_views,
  cell_size)``, and decomposes it with the same `host.fit.CellEigenspace` loop as the
  in-process fit (``_fit_cells``). A cell's fit does not depend on the batch or block it is
  in, and fit tasks use the client's BLAS thread counts (`blas_threads`), so the model, and
  the ``.ecs`` written from it, are byte-identical (with the same numpy/scipy builds on a
  CPU of the same kind: OpenBLAS picks its kernels by CPU).

  Memory: a fit task's working set is its block (at most `FIT_BLOCK_BYTES` of uint8, held
  twice while its pieces are joined) plus one batch of floats (``batch_bytes``, as
  in-process), whatever the database's size. The pieces themselves wait in the workers'
  memory between the two steps: the whole stack spread over the cluster (Dask spills them to
  disk past its memory thresholds), where the in-process fit keeps it in a file.

Dask reruns the tasks of a worker that dies (the pieces of the stack it held are rebuilt
from the PNGs), so a lost worker costs time, not the run; a killed client keeps every
image already written and resumes like an interrupted in-process render.

``ADDRESS`` is a scheduler address (``tcp://host:8786``) or ``local:N``, which starts a
`distributed.LocalCluster` with N single-threaded worker processes for this command.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import math
import operator
import uuid
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from host.errors import EigencastError, FitError

__all__ = [
    "CONNECT_TIMEOUT_S",
    "FIT_BLOCK_BYTES",
    "STACK_GROUP_BYTES",
    "Cluster",
    "ClusterError",
    "add_scheduler_argument",
    "blas_threads",
    "fit_blocks",
    "open_cluster",
    "render_pngs",
    "scene_fingerprint",
    "scene_recipe",
    "views_per_task",
]

#: Seconds to wait for a scheduler (and for its first worker) before giving up.
CONNECT_TIMEOUT_S = 20.0
#: Tasks per worker thread a run is cut into, at least (load balance vs. task overhead).
TASKS_PER_THREAD = 4
#: Most views one render task holds (a killed client loses at most the tasks in flight).
MAX_VIEWS_PER_TASK = 16
#: Bound of one fit task's uint8 block of the stack (cells x all views); its float working
#: set is bounded separately by `host.fit.CellEigenspace.batch_bytes`.
FIT_BLOCK_BYTES = 128 * 2**20
#: Bound of the decoded images one stack-building task holds.
STACK_GROUP_BYTES = 64 * 2**20
#: Scenes a worker keeps loaded (a worker serves one run at a time in practice).
_SCENE_CACHE_SIZE = 2
_SCENES: dict[str, Any] = {}

INSTALL_HINT = "pip install 'eigencast[cluster]'"


class ClusterError(EigencastError):
    """The cluster cannot be used (Dask missing, scheduler unreachable, worker failure)."""


def add_scheduler_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--scheduler ADDRESS`` (default: in-process threads) to ``parser``."""
    parser.add_argument(
        "--scheduler", metavar="ADDRESS", default=None,
        help="run on a Dask cluster: a scheduler address (tcp://host:8786) or local:N for N "
             f"local worker processes (needs {INSTALL_HINT}; default: in-process threads)")


# --------------------------------------------------------------------------
# connecting


class Cluster:
    """A connected Dask client (and the `LocalCluster` it started, for ``local:N``).

    Parameters
    ----------
    address : str
        ``tcp://host:port`` (any address `distributed.Client` accepts) or ``local:N``.

    Raises
    ------
    ClusterError
        Dask is not installed, ``local:N`` is malformed, the scheduler cannot be reached
        within `CONNECT_TIMEOUT_S`, or no worker joins it within that time.
    """

    def __init__(self, address: str) -> None:
        try:
            import distributed
            import threadpoolctl  # noqa: F401 (fit tasks match the client's BLAS threads)
        except ImportError:
            raise ClusterError(
                f"--scheduler needs Dask distributed and threadpoolctl, which are not "
                f"installed: {INSTALL_HINT}"
            ) from None
        self.address = address
        self._local = None
        timeout = f"{CONNECT_TIMEOUT_S}s"
        if address.startswith("local:"):
            text = address[len("local:"):]
            if not text.isdigit() or not 1 <= int(text) <= 256:
                raise ClusterError(f"--scheduler {address!r}: expected local:N with 1 <= N <= 256")
            try:
                self._local = distributed.LocalCluster(
                    n_workers=int(text), threads_per_worker=1, processes=True,
                    dashboard_address=":0", silence_logs=logging.ERROR)
            except Exception as exc:  # Dask raises RuntimeError, OSError, ... here
                raise ClusterError(
                    f"--scheduler {address}: cannot start a local cluster: "
                    f"{' '.join(str(exc).split()) or type(exc).__name__}"
                ) from None
            self.client = distributed.Client(self._local, timeout=timeout)
        else:
            try:
                self.client = distributed.Client(address, timeout=timeout)
            except (OSError, TimeoutError, ValueError, TypeError) as exc:
                reason = " ".join(str(exc).split()) or type(exc).__name__
                raise ClusterError(
                    f"--scheduler {address}: cannot reach the scheduler ({reason}); start one "
                    "with `dask scheduler` and workers with `dask worker ADDRESS`"
                ) from None
        try:
            self.client.wait_for_workers(1, timeout=CONNECT_TIMEOUT_S)
        except (TimeoutError, OSError):
            self.close()
            raise ClusterError(
                f"--scheduler {address}: no worker joined within {CONNECT_TIMEOUT_S:g} s; "
                "start workers with `dask worker ADDRESS`"
            ) from None

    def threads(self) -> int:
        """Worker threads now connected (at least 1)."""
        info = self.client.scheduler_info(n_workers=-1)["workers"]
        return max(1, sum(int(w.get("nthreads", 1)) for w in info.values()))

    def close(self) -> None:
        """Disconnect (and stop a ``local:N`` cluster)."""
        self.client.close()
        if self._local is not None:
            self._local.close()
            self._local = None

    def __enter__(self) -> Cluster:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_cluster(address: str | None) -> Cluster | None:
    """`Cluster` for a ``--scheduler`` value, or None when it is absent (in-process)."""
    return None if address is None else Cluster(address)


# --------------------------------------------------------------------------
# render


def scene_recipe(args: argparse.Namespace) -> argparse.Namespace:
    """The options a worker rebuilds the renderer from (`host.render.scene.render_setup`).

    File paths (the volume, a ``--tf`` file) are made absolute, so workers started in
    another folder read the same files.
    """
    from host.render.cinema import absolute_source

    recipe = {k: v for k, v in vars(args).items() if not k.startswith("_")}
    recipe["volume"] = absolute_source(recipe["volume"])
    tf = recipe.get("tf")
    if tf:
        path = tf.split("#", 1)
        if Path(path[0]).exists():
            recipe["tf"] = "#".join([str(Path(path[0]).resolve()), *path[1:]])
    recipe["scheduler"] = None
    return argparse.Namespace(**recipe)


def scene_fingerprint(volume: Any, tf: Any, renderer: Any) -> str:
    """SHA-256 of what determines the images: volume identity, transfer function, renderer."""
    record = {
        "volume": [volume.name, list(volume.dims), [float(s) for s in volume.spacing]],
        "transfer_function": tf.to_dict(),
        "window": [float(w) for w in tf.resolve_window(volume)],
        "renderer": renderer.settings(),
    }
    text = json.dumps(record, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def _scene(recipe: argparse.Namespace, fingerprint: str) -> Any:
    """The worker's renderer for ``recipe``, loaded once per worker process."""
    renderer = _SCENES.get(fingerprint)
    if renderer is not None:
        return renderer
    from host.render.scene import render_setup

    volume, tf, renderer = render_setup(recipe)
    if scene_fingerprint(volume, tf, renderer) != fingerprint:
        raise ClusterError(
            f"a worker loaded a different scene from {recipe.volume} than the client did "
            "(is the same file at that path on every worker?)"
        )
    while len(_SCENES) >= _SCENE_CACHE_SIZE:
        _SCENES.pop(next(iter(_SCENES)))
    _SCENES[fingerprint] = renderer
    return renderer


def _render_batch(
    recipe: argparse.Namespace, fingerprint: str, jobs: list, width: int, height: int,
    depth_offset: float | None = None,
) -> list[tuple[int, bytes, bytes | None]]:
    """Worker task: ray-cast ``jobs`` [(index, camera)] and return [(index, PNG bytes, depth
    npz bytes or None)]; with ``depth_offset`` each view's depth map as the in-process render
    makes it (`host.render.cinema.encode_depth`, one ray-cast for both)."""
    from host.render.cinema import encode_depth, encode_png

    renderer = _scene(recipe, fingerprint)
    out = []
    for i, cam in jobs:
        if depth_offset is None:
            out.append((i, encode_png(renderer.render_rgb8(cam, width, height)), None))
        else:
            rgba, depth = renderer.render_with_depth(cam, width, height)
            out.append((i, encode_png(renderer.composite(rgba)),
                        encode_depth(depth, depth_offset)))
    return out


def views_per_task(n_views: int, threads: int) -> int:
    """Views per render task: at least `TASKS_PER_THREAD` tasks per thread, at most
    `MAX_VIEWS_PER_TASK` views each."""
    return max(1, min(MAX_VIEWS_PER_TASK, n_views // max(1, TASKS_PER_THREAD * threads)))


def render_pngs(
    cluster: Cluster,
    args: argparse.Namespace,
    scene: tuple[Any, Any, Any],
    cameras: Sequence[Any],
    pending: Sequence[int],
    width: int,
    height: int,
    *,
    depth_offset: float | None = None,
) -> Iterator[tuple[int, bytes, bytes | None]]:
    """Ray-cast views ``pending`` on the cluster; yield ``(index, PNG bytes, depth npz bytes
    or None)`` as they finish.

    Parameters
    ----------
    cluster : Cluster
    args : argparse.Namespace
        The render command's options (the workers rebuild the scene from them).
    scene : (volume, tf, renderer)
        The client's scene, whose `scene_fingerprint` the workers must reproduce.
    cameras : sequence of Camera
        One per database row.
    pending : sequence of int
        The rows to render.
    width, height : int
    depth_offset : float or None
        Also make each view's depth map with this offset (``render``'s default).

    Notes
    -----
    Closing the generator early (an interrupted client) cancels the tasks not yet done.
    """
    from distributed import as_completed

    client = cluster.client
    recipe = scene_recipe(args)
    fingerprint = scene_fingerprint(*scene)
    per_task = views_per_task(len(pending), cluster.threads())
    run = uuid.uuid4().hex[:12]
    futures = [
        client.submit(_render_batch, recipe, fingerprint,
                      [(i, cameras[i]) for i in pending[s:s + per_task]], width, height,
                      depth_offset, pure=False, key=f"render-views-{pending[s]}-{run}")
        for s in range(0, len(pending), per_task)
    ]
    try:
        for future in as_completed(futures):
            yield from _result(future)
            future.release()
    finally:
        client.cancel(futures)


# --------------------------------------------------------------------------
# fit


def _result(future: Any) -> Any:
    """A task's result; the cluster's own failures (a task that killed its workers, a lost
    scheduler) become a one-line `ClusterError`, the task's own errors pass through."""
    from distributed import KilledWorker

    try:
        return future.result()
    except (EigencastError, ValueError):
        raise
    except (KilledWorker, OSError, TimeoutError) as exc:
        reason = " ".join(str(exc).split()) or type(exc).__name__
        raise ClusterError(f"cluster task {future.key} failed: {type(exc).__name__}: "
                           f"{reason}") from None


def _bounds(total: int, per: int) -> list[tuple[int, int]]:
    return [(s, min(total, s + per)) for s in range(0, total, per)]


def _stack_pieces(
    files: list[str], image_shape: tuple[int, int], cell_shape: tuple[int, int],
    blocks: list[tuple[int, int]],
) -> tuple[np.ndarray, ...]:
    """Worker task: decode a group of views and cut them cell-major, one piece per block.

    Returns one uint8 array ``(c1 - c0, len(files), cell_size)`` per block ``(c0, c1)``.
    """
    from host.fit.cells import split_cells
    from host.render.cinema import _read_png

    h, w = image_shape
    images = np.empty((len(files), h, w, 3), dtype=np.uint8)
    for i, name in enumerate(files):
        image = _read_png(Path(name))
        if image.shape != (h, w, 3):
            raise FitError(f"{name}: size {image.shape[1]}x{image.shape[0]} differs from the "
                           f"first image's {w}x{h}")
        images[i] = image
    cells = split_cells(images, cell_shape)  # (n, n_cells, d)
    return tuple(np.ascontiguousarray(cells[:, c0:c1].transpose(1, 0, 2)) for c0, c1 in blocks)


def blas_threads() -> dict[str, int]:
    """Threads of each BLAS library loaded here (numpy's and scipy's), by library prefix.

    OpenBLAS sums in another order with another thread count, so the fitted bits depend on
    it: fit tasks run with the client's counts (Dask starts workers with one BLAS thread).
    """
    import scipy.linalg  # noqa: F401 (loads scipy's BLAS, which the fit uses too)
    from threadpoolctl import threadpool_info

    return {i["prefix"]: int(i["num_threads"]) for i in threadpool_info()
            if i["user_api"] == "blas"}


def _fit_block(
    params: dict, n_views: int, image_shape: tuple[int, int], cell_shape: tuple[int, int],
    first: int, last: int, pieces: list[np.ndarray], blas: dict[str, int],
) -> list:
    """Worker task: fit cells ``first..last-1`` from their pieces (one per group of views)
    with ``blas`` threads per BLAS library (`blas_threads` of the client)."""
    from threadpoolctl import threadpool_limits

    from host.fit.pca import CellEigenspace
    from host.progress import Progress

    block = np.concatenate(pieces, axis=1) if len(pieces) > 1 else pieces[0]
    del pieces
    model = CellEigenspace(**params)
    stack = _block_stack(n_views, image_shape, cell_shape, block, first)
    model._prepare_solver(stack.n_views, stack.cell_size)
    with threadpool_limits(limits=blas or None):
        return model._fit_cells(stack, first, last, Progress("", last - first, quiet=True))


def _block_stack(
    n_views: int, image_shape: tuple[int, int], cell_shape: tuple[int, int], block: np.ndarray,
    first: int,
) -> Any:
    """A `host.fit.CellStack` of cells ``first..`` held in memory, addressed by global index."""
    from host.fit.cells import CellStack  # (imported only where it is used)

    class BlockStack(CellStack):
        def read_cells(self, start: int, stop: int) -> np.ndarray:
            return self._array[start - first:stop - first]

        def read_block(self, cell: int, rows: slice, cols: slice) -> np.ndarray:
            return self._array[cell - first][rows, cols]

    return BlockStack(n_views, image_shape, cell_shape, array=block)


def fit_blocks(
    cluster: Cluster, model: Any, db: Any, cell_shape: tuple[int, int], *,
    progress: bool = True,
) -> Any:
    """Fit ``model`` (an unfitted `host.fit.CellEigenspace`) to ``db`` on the cluster.

    Parameters
    ----------
    cluster : Cluster
    model : CellEigenspace
        Its parameters are used as they are; it is fitted in place and returned.
    db : CinemaDB
        Its folder must be readable at the same (absolute) path on every worker.
    cell_shape : (int, int)
        The method's cell shape (the whole image for ``standard``).
    progress : bool
        Report cells fitted / total on stderr.

    Returns
    -------
    CellEigenspace
        Byte-identical to ``model.fit(stack)`` in-process.
    """
    from distributed import as_completed

    from host.fit.cells import CellStack
    from host.progress import progress as _progress

    model._validate_params()
    n, (h, w) = db.n_views, db.image_shape
    if n < 2:
        raise FitError(f"fit needs at least 2 views to estimate variance, got n_views={n}")
    meta = CellStack(n, (h, w), cell_shape)  # shape only: the data live on the workers
    d = meta.cell_size
    tasks = TASKS_PER_THREAD * cluster.threads()
    per_block = max(1, min(FIT_BLOCK_BYTES // (n * d), math.ceil(meta.n_cells / tasks)))
    per_group = max(1, min(STACK_GROUP_BYTES // (h * w * 3), math.ceil(n / tasks)))
    blocks = _bounds(meta.n_cells, per_block)
    files = [str((Path(db.path) / f).resolve()) for f in db.files]
    params = {k: getattr(model, k) for k in
              ("method", "cell", "components", "threshold", "solver", "batch_bytes",
               "random_state")}
    client = cluster.client
    run = uuid.uuid4().hex[:12]
    groups = [client.submit(_stack_pieces, files[g0:g1], (h, w), cell_shape, blocks,
                            pure=False, key=f"stack-views-{g0}-{g1}-{run}")
              for g0, g1 in _bounds(n, per_group)]
    pieces = [[client.submit(operator.getitem, g, b, pure=False) for g in groups]
              for b in range(len(blocks))]
    blas = blas_threads()
    fits = [client.submit(_fit_block, params, n, (h, w), cell_shape, c0, c1, pieces[b], blas,
                          pure=False, key=f"fit-cells-{c0}-{c1}-{run}")
            for b, (c0, c1) in enumerate(blocks)]
    del groups, pieces  # the scheduler keeps them while a fit task needs them
    order = {f.key: b for b, f in enumerate(fits)}
    results: list[list | None] = [None] * len(blocks)
    try:
        with _progress("fitting eigenspace on the cluster", meta.n_cells, unit=" cells",
                       quiet=not progress) as bar:
            for future in as_completed(fits):
                b = order[future.key]
                results[b] = _result(future)
                future.release()
                bar.advance(blocks[b][1] - blocks[b][0])
    finally:
        client.cancel(fits)
    model._prepare_solver(n, d)
    model._store([fit for block in results for fit in block], meta)
    return model
