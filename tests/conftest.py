"""Shared test setup: no display, deterministic threads, real-data skips."""

from __future__ import annotations

import os

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
os.environ.setdefault("SDL_AUDIODRIVER", "dummy")

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
