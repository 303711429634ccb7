"""Several looks in one image: the single-look image a device shows for one of them.

An image with looks (``.ecs`` format version 3, `protocol.image`) holds several pictures of
the same views -- transfer functions or lightings -- each as an eigenspace of its own
(`host.fit.looks`): its colour sections (counts, eigenimages, scales, mean), its standalone
table and score step, its noise floor, and, when its transfer function differs from the
first look's, its own depth eigenspace and synthesis record; looks share the view set, its
interpolation and, where their depth is the same, the depth eigenspace. The manifest's
``looks`` list names, per look, the sections that replace the standard ones. (Format version
2, read as well, has looks sharing one eigenspace's scores: the first look's counts and
table.)

`look_image` is the image of one look: the image with that look's sections under the
standard names, its synthesis record, and the render settings (and database, int8 loss) it
records as its provenance. Everything that takes an image -- `Reconstructor.from_image`,
`StandaloneScores`, `Predictor`, `ViewSynthesizer`, the host's `HostModel` -- takes it as it
takes an image with one look, so a look is shown exactly as a one-look image of its
sections would be. It shares the image's arrays (no copy) and keeps its digest: score
packets and layers name the image, and a device drops what it decoded for the look it
left (`device_runtime.loaded.LoadedModel.for_look`).

Delta-coded tables (the standalone table, depth tables) are decoded in place once, in the
image itself, before its first look is made, so all looks share the decoded tables.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from device_runtime.standalone import (
    STANDALONE_DELTA_SECTION,
    STANDALONE_SECTION,
    delta_decode,
    standalone_order,
    standalone_table,
)
from device_runtime.synthesis import DEPTH_DELTA_SECTION
from protocol.errors import ImageFormatError
from protocol.image import DEVICE_SECTIONS, LOOK_SCORE_SECTIONS, EigenspaceImage

__all__ = ["look_image", "look_index", "look_names", "own_scores"]

_PLAIN_DEPTH = "depth_scores"
#: What ``provenance["looks"][i]`` records of look i that a look's image shows as its own
#: provenance (the first look's are the image's).
_RECORDED = ("render", "source_database", "int8")


def look_names(image: EigenspaceImage) -> tuple[str, ...]:
    """The image's look names in order; ``()`` for an image with one look."""
    return tuple(str(look["name"]) for look in image.looks or ())


def own_scores(image: EigenspaceImage, look: int) -> bool:
    """Whether look ``look`` of ``image`` has scores of its own (format version 3: its own
    eigenspace and table); False: it shares the first look's (and for an image with one
    look)."""
    if image.looks is None or look == 0:
        return False
    mapping = image.looks[look].get("sections") or {}
    return bool(LOOK_SCORE_SECTIONS & set(mapping))


def look_index(image: EigenspaceImage, look: int | str | None) -> int:
    """The index of ``look`` (a name or an index; None: the first look).

    Raises
    ------
    ValueError
        No such look (one line naming the image's looks).
    """
    names = look_names(image)
    if look is None:
        return 0
    if isinstance(look, str) and not look.isdigit():
        if look in names:
            return names.index(look)
        known = ", ".join(names) if names else "none: the image has one look"
        raise ValueError(f"no look '{look[:40]}' in the image (its looks: {known})")
    index = int(look)
    count = max(1, len(names))
    if not 0 <= index < count:
        raise ValueError(f"look {index} is out of range: the image has {count} look"
                         f"{'s' if count != 1 else ''}"
                         + (f" ({', '.join(names)})" if names else ""))
    return index


def look_image(image: EigenspaceImage, look: int | str | None = 0, *,
               decode: bool = True) -> EigenspaceImage:
    """The single-look image of ``look`` (an index or a name) of ``image``.

    ``decode`` (default) first decodes the image's delta-coded tables in place, once, so the
    looks share them (a device, `eigencast view`); ``decode=False`` leaves ``image`` as it
    is (a fit that still writes it): the view then holds the coded tables, and whoever loads
    them must work on copies, as the fit's measurements do.

    An image with one look is returned as it is (look 0). Otherwise a new `EigenspaceImage`
    sharing ``image``'s arrays: the look's sections under the standard names, the other
    looks' sections left out, the look's ``synthesis`` (else the image's), its recorded
    render settings as ``provenance["render"]`` (``provenance["looks"][i]["render"]``), no
    ``looks``, its ``score_quantization`` (else the image's), and the image's digest, tag
    state and annex. What the image's provenance
    records of the look (``provenance["looks"][i]``: its render settings, database and int8
    loss) replaces the image's own entries.

    Raises
    ------
    ValueError
        No such look.
    ImageFormatError
        A look's section does not fit the image (shapes, dtypes), or a table cannot be
        decoded.
    """
    index = look_index(image, look)
    if image.looks is None:
        return image
    if decode:
        _decode_tables(image)
    entry = image.looks[index]
    mapping = dict(entry.get("sections") or {})
    own = {name for other in image.looks for name in (other.get("sections") or {}).values()}
    sections = {k: v for k, v in image.sections.items() if k not in own}
    colour = {k: image.sections[mapping[k]] for k in DEVICE_SECTIONS if k in mapping}
    if any(k.startswith("depth_") for k in mapping):
        # a look with its own depth: none of the first look's depth sections stay
        sections = {k: v for k, v in sections.items() if not k.startswith("depth_")}
    for standard, section in mapping.items():
        if standard not in DEVICE_SECTIONS:
            sections[standard] = image.sections[section]
    provenance = dict(image.provenance)
    recorded = provenance.get("looks")
    if isinstance(recorded, list) and index < len(recorded) and isinstance(
            recorded[index], dict):
        for key in _RECORDED:
            if key in recorded[index]:
                provenance[key] = recorded[index][key]
    view = dataclasses.replace(
        image,
        n_components=colour.get("n_components", image.n_components),
        mean=colour.get("mean", image.mean),
        scales=colour.get("scales", image.scales),
        eigenimages=colour.get("eigenimages", image.eigenimages),
        sections=sections,
        synthesis=entry.get("synthesis", image.synthesis),
        score_quantization=entry.get("score_quantization", image.score_quantization),
        provenance=provenance,
        looks=None,
    )
    try:
        view.check()
    except ValueError as exc:
        raise ImageFormatError(f"look '{entry['name']}': {exc}") from None
    return view


def _decode_tables(image: EigenspaceImage) -> None:
    """Decode the image's delta-coded tables in place, once, so every look shares them: the
    standalone table, the first look's depth table and each look's own standalone and depth
    tables (renamed to their plain form in the image and in the look's map)."""
    if STANDALONE_DELTA_SECTION in image.sections:
        standalone_table(image)
    if DEPTH_DELTA_SECTION in image.sections:
        _decode_depth(image, DEPTH_DELTA_SECTION, _PLAIN_DEPTH)
    for entry in image.looks or ():
        mapping = entry.get("sections") or {}
        for delta, plain_name in ((DEPTH_DELTA_SECTION, _PLAIN_DEPTH),
                                  (STANDALONE_DELTA_SECTION, STANDALONE_SECTION)):
            coded = mapping.get(delta)
            if coded is None:
                continue
            rows = None
            if delta == STANDALONE_DELTA_SECTION:  # the look's own eigenspace's K
                counts = image.sections.get(mapping.get("n_components", ""), image.n_components)
                rows = int(np.asarray(counts).sum())
            plain = f"{coded}:plain"
            _decode_depth(image, coded, plain, rows=rows)
            del mapping[delta]
            mapping[plain_name] = plain


def _decode_depth(image: EigenspaceImage, name: str, plain: str, *,
                  rows: int | None = None) -> None:
    """Replace the delta-coded table ``name`` (a depth table, or with ``rows`` components a
    look's standalone table) by its int16 table ``plain``."""
    coded = image.sections[name]
    n_views = (image.interpolation or {}).get("n_views")
    if (not isinstance(n_views, int) or coded.dtype != np.uint8 or coded.ndim != 3
            or coded.shape[1:] != (2, n_views) or rows not in (None, coded.shape[0])):
        raise ImageFormatError(f"image section {name!r}: expected uint8 of shape "
                               f"(K{'' if rows is None else f'={rows}'}, 2, "
                               f"n_views={n_views}), got {coded.dtype} {coded.shape}")
    if plain in image.sections:
        raise ImageFormatError(f"image sections {plain!r} and {name!r} are both present")
    image.sections[plain] = delta_decode(coded, standalone_order(image, n_views))
    del image.sections[name]
