"""Several looks in one image: an eigenspace per look, sharing what the looks share.

``eigencast fit A.cdb B.cdb ...`` takes databases of one view set rendered with other
transfer functions or lightings (the *looks*) and writes one image that shows any of them
(`device_runtime.looks`). Each look is fitted and quantized as a one-look image of its
database would be (its own eigenspace, standalone table and score step); `build_looks_image`
then keeps the first look's sections under the standard names and adds each further look's
as ``look{i}_NAME``, named in the manifest's ``looks`` (format version 3). The looks share
the view set and its interpolation, and the depth eigenspace where their depth is the same
(lighting changes colours, never opacity: `same_depth`; `add_look_sections` adds a look's
own depth, noise floor and splat filter). The host annex keeps each further look's float
training scores and eigenvalues as ``look{i}_NAME`` (`look_annex`).

Why not one eigenspace of all looks with shared scores (the design this replaced): the
joint eigenspace needs more components than any one look (K 1016 for three looks of the
built-in head at 128 px against 552-705 one by one), every look stores all of them, and each
look needs 916-1009 of them to reach its own threshold, so three looks cost 3.4x one look's
flash where looks of their own cost about 2.5x, and every frame blended the joint K
(docs/design-notes.md, "Several looks in one image").
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from typing import Any

import numpy as np

from host.errors import FitError
from host.render.cinema import CinemaDB
from protocol.image import MAX_LOOK_NAME, MAX_LOOKS, EigenspaceImage

__all__ = [
    "add_look_sections",
    "build_looks_image",
    "check_same_views",
    "look_annex",
    "look_names_for",
    "look_section",
    "same_depth",
]

#: The sections of a look's own eigenspace and table that a further look always has.
_OWN = ("n_components", "mean", "scales", "eigenimages")
_LOOK_KEY = re.compile(r"look\d+_")


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


def look_section(look: int, name: str) -> str:
    """The image section holding look ``look``'s own ``name`` section: ``look1_mean``."""
    return f"look{look}_{name}"


def build_looks_image(
    parts: Sequence[tuple[EigenspaceImage, dict[str, np.ndarray]]],
    dbs: Sequence[CinemaDB],
    names: Sequence[str],
) -> tuple[EigenspaceImage, dict[str, np.ndarray]]:
    """One image of the looks ``parts`` (each look's one-look image and host annex, as
    ``fit`` makes them from its database, standalone table included; before depth).

    The first look's image is the result's (its sections, interpolation, score step and
    provenance); each further look adds its colour sections, its standalone table (when it
    has one) and its annex arrays as ``look{i}_NAME``, its score step in its ``looks`` entry,
    and ``provenance["looks"]`` records per look its name, database, render settings, int8
    loss and components.

    Raises
    ------
    FitError
        The looks' view interpolations differ (not one view set).
    """
    from device_runtime.standalone import STANDALONE_DELTA_SECTION, STANDALONE_SECTION

    image, annex = parts[0]
    annex = dict(annex)
    records: list[dict[str, Any]] = []
    entries: list[dict[str, Any]] = []
    for look, ((view, view_annex), db, name) in enumerate(zip(parts, dbs, names)):
        records.append({"name": name, "source_database": str(db.path),
                        "render": db.settings or {}, "int8": view.provenance.get("int8"),
                        "components": int(view.n_coefficients)})
        if look == 0:
            entries.append({"name": name, "sections": {}})
            continue
        if view.interpolation != image.interpolation:
            raise FitError(f"looks: {db.path} has another view interpolation than "
                           f"{dbs[0].path}; render every look with the same --views")
        mapping = {}
        own = {key: getattr(view, key) for key in _OWN}
        for key in (STANDALONE_DELTA_SECTION, STANDALONE_SECTION):
            if key in view.sections:
                own[key] = view.sections[key]
        for key, arr in own.items():
            image.sections[look_section(look, key)] = arr
            mapping[key] = look_section(look, key)
        entries.append({"name": name, "sections": mapping,
                        "score_quantization": dict(view.score_quantization or {})})
        for key, arr in view_annex.items():
            annex[look_section(look, key)] = arr
    image.looks = entries
    image.provenance["looks"] = records
    return image, annex


def look_annex(annex: dict[str, np.ndarray], look: int) -> dict[str, np.ndarray]:
    """The host annex of look ``look`` of an image with several: the first look's arrays
    with the look's own (``look{i}_NAME``) in their place."""
    out = {k: v for k, v in annex.items() if not _LOOK_KEY.match(k)}
    if look > 0:
        prefix = look_section(look, "")
        out.update({k[len(prefix):]: v for k, v in annex.items() if k.startswith(prefix)})
    return out


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
