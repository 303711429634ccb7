"""The device installs on a board from Debian stable's own packages (docs/board-install.md):
every device dependency's lower bound in pyproject.toml is at or below the version Debian
stable ships, and the page's table says the same. No network: the versions are recorded
here; scripts/board_versions.sh checks that the device really runs on them."""

from __future__ import annotations

import re
import sys
from pathlib import Path

from packaging.requirements import Requirement
from packaging.version import Version

REPO = Path(__file__).resolve().parents[1]
#: Debian 13 "trixie" (stable; Raspberry Pi OS is built on it): python3-numpy,
#: python3-serial, python3-cbor2, python3-zstandard, python3-pygame.
DEBIAN_STABLE = {"numpy": "2.2", "pyserial": "3.5", "cbor2": "5.6", "zstandard": "0.23",
                 "pygame": "2.6"}


def _device_requirements() -> list[Requirement]:
    """The base dependencies and the ``device`` extra, from pyproject.toml."""
    if sys.version_info >= (3, 11):
        import tomllib

        project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
        texts = [*project["dependencies"], *project["optional-dependencies"]["device"]]
    else:  # the installed metadata (make venv reinstalls when pyproject.toml changes)
        from importlib.metadata import requires

        texts = [t for t in requires("eigencast") or []
                 if ";" not in t or 'extra == "device"' in t]
    return [Requirement(t) for t in texts]


def _lower_bound(req: Requirement) -> Version:
    bounds = [Version(s.version) for s in req.specifier if s.operator in (">=", "==", "~=")]
    assert len(bounds) == 1, f"{req}: give the device dependency one lower bound"
    return bounds[0]


def test_device_lower_bounds_are_within_debian_stable():
    reqs = {r.name.lower(): r for r in _device_requirements()}
    assert set(reqs) == set(DEBIAN_STABLE), (
        "a device dependency was added or removed: record Debian stable's version of it here "
        "and in docs/board-install.md")
    for name, debian in DEBIAN_STABLE.items():
        bound = _lower_bound(reqs[name])
        assert bound.release[:2] <= Version(debian).release[:2], (
            f"{name}>={bound} is above Debian stable's {debian}: a board could not install "
            "from its own packages (docs/board-install.md)")


def test_the_board_page_states_the_same_versions():
    page = (REPO / "docs" / "board-install.md").read_text()
    rows = dict(re.findall(r"^\| (\w+) \| ([\d.]+) \| >= [\d.]+ \|$", page, flags=re.M))
    assert rows == DEBIAN_STABLE
    bounds = dict(re.findall(r"^\| (\w+) \| [\d.]+ \| >= ([\d.]+) \|$", page, flags=re.M))
    assert {n: Version(b) for n, b in bounds.items()} == {
        r.name.lower(): _lower_bound(r) for r in _device_requirements()}


def test_the_board_page_updates_the_package_lists_before_installing():
    """On a fresh Debian 13 (under arm64 emulation) the page's `apt install` failed with
    "Unable to locate package python3-numpy": a fresh system has no package lists until
    `apt update`. The page's command block says it first."""
    page = (REPO / "docs" / "board-install.md").read_text()
    block = re.search(r"```sh\n(.*?)```", page, flags=re.S).group(1)
    commands = [line.split("#")[0].strip() for line in block.splitlines()]
    update = next(i for i, c in enumerate(commands) if re.fullmatch(r"sudo apt(-get)? update", c))
    install = next(i for i, c in enumerate(commands) if c.startswith("sudo apt install"))
    assert update < install
