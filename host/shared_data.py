"""Locate the real volumes in ``../shared/data`` (tests and benchmarks only).

The built-in procedural volumes are the default that always works; these
files are optional. ``EIGENCAST_SHARED_DATA`` overrides the location.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["SHARED_VOLUMES", "shared_data_dir", "shared_volume"]

_REPO = Path(__file__).resolve().parent.parent

# name -> path relative to the shared data folder
SHARED_VOLUMES: dict[str, str] = {
    "tooth": "tooth/tooth.mhd",
    "vismale_head": "vismale_head/vismale_head.nhdr",
    "engine": "engine/engine_small.mhd",
    "headsq": "headsq/headsq.dat",
    "brainsmall": "brainsmall/brainsmall.tif",
    "mni152": "mni152/mni152_t1.nii.gz",
}


def shared_data_dir() -> Path | None:
    """The shared data folder, or None when it is absent."""
    env = os.environ.get("EIGENCAST_SHARED_DATA")
    candidates = [Path(env)] if env else []
    candidates.append(_REPO.parent / "shared" / "data")
    for c in candidates:
        if c.is_dir():
            return c
    return None


def shared_volume(name: str) -> Path | None:
    """Path of a named shared volume, or None when the shared data is absent."""
    root = shared_data_dir()
    if root is None:
        return None
    path = root / SHARED_VOLUMES[name]
    return path if path.exists() else None
