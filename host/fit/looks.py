"""Several looks in one image: a joint eigenspace of databases of the same views.

``eigencast fit A.cdb B.cdb ...`` takes databases of one view set rendered with other
transfer functions or lightings (the *looks*) and writes one image that shows any of them
(`device_runtime.looks`). Per cell, each view's pixel vectors of all looks are stacked into
one vector (`JointStack`) and one PCA is fitted (`fit_looks`): every look shares the scores,
so the image holds one standalone table and a device is sent one score vector per view
whatever the look; each look's eigenimages are its slice of the joint components, which is
also the least-squares fit of that look's pixels to the shared scores
(`split_looks`). Its slices are not orthonormal; each is quantized on its own
(`quantize_look`: a scale per row and look, and the bits of `allocate_bits` within the
look's own error budget).

The adaptive rule keeps, per cell, the fewest joint components whose eigenvalues reach T of
the joint variance (the sum of the looks'); the score step is the one whose rounding adds
`DEFAULT_SCORE_MSE` to a look's mean cell (`score_step_for` on ``looks x cell_values``).
What it costs (BENCHMARKS.md, "Looks in one image"): the joint eigenspace needs more
components than any one look (K 1016 for three looks of the built-in head at 128 px, against
552-705 fitted one by one), and every look stores all of them, so the colour sections of
three looks are about 1.5x those of three single-look images; the shared table and depth do
not make that up. The depth of looks that differ only in lighting is
the same bit for bit (lighting changes colours, never opacity): they share the first look's
depth eigenspace; a look with other depth maps (another transfer function) gets its own
(`add_look_depth`). Each look gets its own noise floor and splat filter (the command
measures them on the look's single-look image).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from host.errors import FitError
from host.fit.cells import CellStack
from host.fit.pca import CellEigenspace
from host.fit.quantize import (
    QuantizedEigenspace,
    allocate_bits,
    quantize_components,
    quantize_mean,
)
from host.render.cinema import CinemaDB
from protocol.image import MAX_LOOK_NAME, MAX_LOOKS, EigenspaceImage

__all__ = [
    "JointStack",
    "add_look_sections",
    "build_looks_image",
    "check_same_views",
    "fit_looks",
    "look_names_for",
    "look_section",
    "look_traces",
    "quantize_look",
    "same_depth",
    "split_looks",
]


class JointStack(CellStack):
    """The cell stacks of several looks side by side: cell vectors of ``looks x cell_size``.

    Reads each look's `CellStack` (same views, image and cell shape) and joins a cell's
    rows, so `CellEigenspace.fit` decomposes the looks' pixels of a view as one vector.

    Parameters
    ----------
    stacks : sequence of CellStack
    """

    def __init__(self, stacks: Sequence[CellStack]) -> None:
        first = stacks[0]
        for other in stacks[1:]:
            if (other.n_views, other.image_shape, other.cell_shape) != (
                    first.n_views, first.image_shape, first.cell_shape):
                raise FitError(f"looks: {other!r} does not match {first!r}")
        super().__init__(first.n_views, first.image_shape, first.cell_shape)
        self.stacks = list(stacks)
        self.look_size = first.cell_size
        self.cell_size = first.cell_size * len(self.stacks)

    def __repr__(self) -> str:
        return f"JointStack({len(self.stacks)} looks of {self.stacks[0]!r})"

    def read_cells(self, start: int, stop: int) -> np.ndarray:
        """Whole cells ``start..stop-1``, uint8 (stop - start, n_views, looks x cell_size)."""
        return np.concatenate([s.read_cells(start, stop) for s in self.stacks], axis=2)

    def read_block(self, cell: int, rows: slice, cols: slice) -> np.ndarray:
        """Part of one cell's joint vectors (columns across looks are joined)."""
        r0, r1, _ = rows.indices(self.n_views)
        c0, c1, _ = cols.indices(self.cell_size)
        d = self.look_size
        parts = []
        for look, stack in enumerate(self.stacks):
            lo, hi = max(c0, look * d), min(c1, (look + 1) * d)
            if lo < hi:
                parts.append(stack.read_block(cell, slice(r0, r1),
                                              slice(lo - look * d, hi - look * d)))
        return np.concatenate(parts, axis=1)

    def memmap(self) -> np.ndarray:  # pragma: no cover - the fit reads cells and blocks
        raise NotImplementedError("JointStack has no single file to map")


def check_same_views(dbs: Sequence[CinemaDB]) -> None:
    """Refuse databases that are not one view set at one image size (one line).

    Raises
    ------
    FitError
        Fewer than 2 or more than `MAX_LOOKS` databases, another image size, another
        number of views or other view angles.
    """
    if not 2 <= len(dbs) <= MAX_LOOKS:
        raise FitError(f"looks: {len(dbs)} databases; an image holds 2..{MAX_LOOKS} looks")
    first = dbs[0]
    for db in dbs[1:]:
        if tuple(db.image_shape) != tuple(first.image_shape):
            raise FitError(f"looks: {db.path} has {db.image_shape[1]}x{db.image_shape[0]} "
                           f"images, {first.path} {first.image_shape[1]}x"
                           f"{first.image_shape[0]}; render the looks at one size")
        if db.n_views != first.n_views or not (
                np.allclose(np.mod(db.phi_deg, 360.0), np.mod(first.phi_deg, 360.0),
                            atol=1e-6) and np.allclose(db.theta_deg, first.theta_deg,
                                                       atol=1e-6)):
            raise FitError(f"looks: {db.path} and {first.path} are not the same views "
                           f"({db.n_views} and {first.n_views} views, in the same order); "
                           "render every look with the same --views")


def _look_parts(settings: dict | None) -> tuple[str, str]:
    """(transfer function, lighting) a database records ("?" when it does not)."""
    settings = settings or {}
    tf = settings.get("transfer_function") or {}
    lighting = (settings.get("renderer") or {}).get("lighting") or {}
    return (str(tf.get("name") or "?"),
            str(lighting.get("name") or ("headlight" if settings else "?")))


def look_names_for(dbs: Sequence[CinemaDB], names: Sequence[str] | None = None) -> list[str]:
    """The looks' names: ``names`` when given, else what sets the databases apart (their
    lighting when they share a transfer function, their transfer function when they share a
    lighting, else both: ``ct-skin-cinematic``), else the databases' folder names.

    Raises
    ------
    FitError
        ``names`` of another count, names that repeat, are empty or longer than
        `MAX_LOOK_NAME`.
    """
    if names is not None:
        out = [str(n).strip() for n in names]
        if len(out) != len(dbs):
            raise FitError(f"--look-names: {len(out)} names for {len(dbs)} databases")
    else:
        parts = [_look_parts(db.settings) for db in dbs]
        tfs, lights = {p[0] for p in parts}, {p[1] for p in parts}
        if "?" in tfs | lights:
            out = [db.path.name.removesuffix(".cdb") for db in dbs]
        elif len(tfs) == 1:
            out = [p[1] for p in parts]
        elif len(lights) == 1:
            out = [p[0] for p in parts]
        else:
            out = [f"{tf}-{light}" for tf, light in parts]
        if len(set(out)) != len(out):
            out = [db.path.name.removesuffix(".cdb") for db in dbs]
    for name in out:
        if not 1 <= len(name) <= MAX_LOOK_NAME or not name.isprintable() or "," in name:
            raise FitError(f"look name {name[:40]!r}: needs 1..{MAX_LOOK_NAME} printable "
                           "characters and no comma (--look-names)")
    if len(set(out)) != len(out):
        raise FitError(f"look names repeat ({', '.join(out)}); name them with --look-names")
    return out


def fit_looks(
    stacks: Sequence[CellStack],
    *,
    method: str = "adaptive",
    cell: int = 30,
    components: int = 100,
    threshold: float = 0.98,
    progress: bool = True,
) -> CellEigenspace:
    """Fit one eigenspace to the looks' cell stacks joined (`JointStack`).

    Returns
    -------
    CellEigenspace
        Its ``mean_`` and ``components_`` have ``looks x cell_values`` columns (look after
        look); ``scores_`` are the shared scores. `split_looks` cuts it into the looks.
    """
    model = CellEigenspace(method, cell=cell, components=components, threshold=threshold,
                           progress=progress)
    return model.fit(JointStack(stacks))


def look_traces(stacks: Sequence[CellStack]) -> np.ndarray:
    """Per look and cell, the total variance (trace, ddof=1) of the training views:
    float64 (looks, n_cells). A look's residual error is its trace less what the joint
    components capture of it (`split_looks`)."""
    out = np.zeros((len(stacks), stacks[0].n_cells))
    for look, stack in enumerate(stacks):
        batch = max(1, (64 << 20) // max(1, stack.n_views * stack.cell_size * 8))
        for start in range(0, stack.n_cells, batch):
            x = stack.read_cells(start, min(stack.n_cells, start + batch)).astype(np.float64)
            x -= x.mean(axis=1, keepdims=True)
            out[look, start:start + x.shape[0]] = np.einsum("cnd,cnd->c", x, x) / max(
                1, stack.n_views - 1)
    return out


def split_looks(joint: CellEigenspace, traces: np.ndarray) -> list[CellEigenspace]:
    """The looks of a joint eigenspace: one model per look, sharing its scores.

    Look ``l``'s model is a shallow copy of ``joint`` with each cell's mean and components
    cut to the look's columns (not orthonormal: ``inverse_transform`` reconstructs the look,
    ``transform`` does not apply); ``eigenvalues_`` stay the joint ones (the variance of
    each shared score), ``total_variance_`` is the look's own trace, and ``captured_`` (per
    cell) what the joint components reconstruct of it.
    """
    n_looks = traces.shape[0]
    values = joint.mean_.shape[1] // n_looks
    out = []
    for look in range(n_looks):
        cols = slice(look * values, (look + 1) * values)
        model = copy.copy(joint)
        model.mean_ = np.ascontiguousarray(joint.mean_[:, cols])
        model.components_ = [np.ascontiguousarray(c[:, cols]) for c in joint.components_]
        model.total_variance_ = np.asarray(traces[look], dtype=np.float64)
        model.captured_ = np.array([float(np.dot(lam, np.square(c).sum(axis=1)))
                                    for lam, c in zip(joint.eigenvalues_, model.components_)])
        out.append(model)
    return out


def quantize_look(model: CellEigenspace, *, bit_budget: float = 0.0) -> QuantizedEigenspace:
    """Quantize one look of `split_looks` to the device's int8 model.

    As `host.fit.quantize.quantize_eigenspace`, with the look's own error budget: the bits
    of `allocate_bits` keep the noise the eigenimages' quantization adds to this look within
    ``bit_budget`` times the look's residual (its trace less what the joint components
    capture), each row's noise weighted by its shared score's variance (the joint
    eigenvalue) and its own peak.
    """
    mean = np.asarray(model.mean_)
    values = mean.shape[1]
    comps = [np.asarray(c, dtype=np.float64) for c in model.components_]
    stacked = np.concatenate(comps, axis=0) if comps else np.zeros((0, values))
    bits = None
    if bit_budget > 0 and stacked.shape[0]:
        lam = np.concatenate([np.asarray(e, dtype=np.float64) for e in model.eigenvalues_])
        residual = float(max(0.0, np.sum(model.total_variance_ - model.captured_))
                         / (mean.shape[0] * values))
        if residual > 0:
            bits = allocate_bits(lam, np.abs(stacked).max(axis=1), n_cells=mean.shape[0],
                                 mse_budget=bit_budget * residual)
    eigenimages, scales = quantize_components(stacked, bits=bits)
    return QuantizedEigenspace(
        mean=quantize_mean(mean), eigenimages=eigenimages, scales=scales,
        n_components=np.asarray(model.n_components_, dtype=np.int32),
        image_shape=tuple(int(v) for v in model.image_shape_),
        cell_shape=tuple(int(v) for v in model.cell_shape_),
        bits=bits if bits is not None else np.full(stacked.shape[0], 8, np.int8),
    )


def look_section(look: int, name: str) -> str:
    """The image section holding look ``look``'s own ``name`` section: ``look1_mean``."""
    return f"look{look}_{name}"


def build_looks_image(
    joint: CellEigenspace,
    stacks: Sequence[CellStack],
    dbs: Sequence[CinemaDB],
    names: Sequence[str],
    *,
    score_step: float | None = None,
    interpolation: str = "auto",
    bit_budget: float = 0.0,
    measure_int8: bool = True,
    extra_provenance: dict | None = None,
) -> tuple[EigenspaceImage, dict[str, np.ndarray]]:
    """Quantize a joint eigenspace into one image with a look per database.

    The image is the first look's, as `host.fit.model.build_image` makes it (its colour
    sections, interpolation, score step, provenance and annex of the shared scores and
    joint eigenvalues); each further look adds its ``look{i}_mean``, ``_scales`` and
    ``_eigenimages`` sections, and the manifest's ``looks`` names them. ``provenance
    ["looks"]`` records per look its name, database, render settings, int8 loss and bits.
    The score step (default) adds `DEFAULT_SCORE_MSE` to a look's mean cell.

    Returns
    -------
    image, annex
    """
    from host.fit.model import DEFAULT_SCORE_MSE, build_image, int8_report, score_step_for

    traces = look_traces(stacks)
    looks = split_looks(joint, traces)
    values = looks[0].mean_.shape[1]
    step = (float(score_step) if score_step is not None else
            score_step_for(joint.n_components_, values * len(looks), mse=DEFAULT_SCORE_MSE))
    quantized = [quantize_look(m, bit_budget=bit_budget) for m in looks]
    records = []
    for look, (model, q, db, name) in enumerate(zip(looks, quantized, dbs, names)):
        residual = float(np.sum(model.total_variance_ - model.captured_)
                         / max(1, model.total_variance_.size * values))
        record: dict[str, Any] = {
            "name": name, "source_database": str(db.path), "render": db.settings or {},
            "residual_mse": residual,
            "mean_bits": float(np.mean(q.bits)) if q.bits is not None and q.bits.size else 8.0,
        }
        if measure_int8 and look > 0:  # the first look's is build_image's "int8"
            record["int8"] = int8_report(model, db, quantized=q)
        records.append(record)
    image, annex = build_image(
        looks[0], dbs[0], score_step=step, interpolation=interpolation,
        measure_int8=measure_int8, bit_budget=bit_budget, quantized=quantized[0],
        extra_provenance={"looks": records, **(extra_provenance or {})})
    image.provenance["fit"]["joint_looks"] = len(looks)
    image.provenance["fit"]["joint_total_variance"] = float(np.sum(joint.total_variance_))
    annex["total_variance"] = np.asarray(joint.total_variance_, dtype=np.float64)
    entries: list[dict] = [{"name": names[0], "sections": {}}]
    for look in range(1, len(looks)):
        q = quantized[look]
        mapping = {}
        for key, arr in (("mean", q.mean), ("scales", q.scales),
                         ("eigenimages", q.eigenimages)):
            image.sections[look_section(look, key)] = arr
            mapping[key] = look_section(look, key)
        entries.append({"name": names[look], "sections": mapping})
    image.looks = entries
    return image, annex


def add_look_sections(image: EigenspaceImage, look: int, view: EigenspaceImage,
                      names: Sequence[str]) -> None:
    """Copy the sections ``names`` of a look's single-look image ``view`` (as the fit's
    depth, noise floor and splat filter left them) into ``image`` as that look's own, and
    its synthesis record into the look's entry. Look 0 is the image itself: nothing to do."""
    if look == 0:
        return
    entry = image.looks[look]
    mapping = entry.setdefault("sections", {})
    for name in names:
        if name in view.sections:
            image.sections[look_section(look, name)] = view.sections[name]
            mapping[name] = look_section(look, name)
    if view.synthesis is not None:
        entry["synthesis"] = dict(view.synthesis)


def same_depth(a: CinemaDB, b: CinemaDB) -> bool:
    """Whether two databases of the same views hold the same depth maps (lighting changes
    colours only: same volume, transfer function and camera give the same depth, bit for
    bit), compared view by view."""
    if a.depth is None or b.depth is None:
        return a.depth is None and b.depth is None
    if not math.isclose(float(a.depth["offset_mm"]), float(b.depth["offset_mm"])):
        return False
    for i in range(a.n_views):
        if not np.array_equal(a.read_depth(i), b.read_depth(i), equal_nan=True):
            return False
    return True
