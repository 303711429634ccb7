"""Lazy re-exports for the stage packages (``host/volume/``, ``host/render/`` ...).

Each stage's ``__init__.py`` lists its public API in ``__all__``; `attach` gives the package a
PEP 562 ``__getattr__`` that imports the module defining a name only when the name is first
used. So ``from host.render import Camera`` does not import numba (the ray-caster), and
``eigencast --help`` stays fast although every command names its stage's API (the reason
`host.cli` imports each command lazily too).

Which module defines a name is read from the package's source files (a top-level ``def``,
``class`` or assignment in a module whose name has no leading underscore); a name defined in
no module or in two is an error on first use, and ``tests/test_architecture.py`` checks every
stage's ``__all__`` resolves.
"""

from __future__ import annotations

import importlib
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

__all__ = ["attach", "defining_modules"]

# ``def f``, ``class C``, ``X = ...``, ``X: T = ...``, ``A, B = ...`` at the start of a line
_DEFINITION = re.compile(
    r"^(?:(?:async\s+)?def|class)\s+(\w+)|^(\w+(?:\s*,\s*\w+)*)\s*(?::[^=\n]*)?=(?!=)", re.M
)


def defining_modules(package: str, names: Sequence[str]) -> dict[str, list[str]]:
    """Name -> the modules of ``package`` (already imported) that define it at top level.

    Parameters
    ----------
    package : str
        A package's ``__name__``.
    names : sequence of str
        The names to look for.

    Returns
    -------
    dict
        Every name in ``names`` (an empty list where no module defines it).
    """
    wanted = {name: [] for name in names}
    folder = Path(sys.modules[package].__path__[0])
    for path in sorted(folder.glob("*.py")):
        if path.name.startswith("_"):
            continue
        found = {
            name.strip()
            for m in _DEFINITION.finditer(path.read_text())
            for name in (m.group(1) or m.group(2)).split(",")
        }
        for name in found & wanted.keys():
            wanted[name].append(path.stem)
    return wanted


def attach(
    package: str, names: Sequence[str]
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """``__getattr__`` and ``__dir__`` for ``package`` that import its names on demand.

    Parameters
    ----------
    package : str
        The package's ``__name__``.
    names : sequence of str
        Its public names (its ``__all__``).

    Returns
    -------
    (__getattr__, __dir__)
        Assign both at module level in the package's ``__init__.py``.
    """
    public = frozenset(names)
    owner: dict[str, str] = {}

    def __getattr__(name: str) -> Any:
        if name not in public:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        if not owner:
            for each, modules in defining_modules(package, sorted(public)).items():
                if len(modules) == 1:
                    owner[each] = modules[0]
        if name not in owner:
            raise ImportError(f"{package}.{name}: not defined by exactly one module of {package}")
        return getattr(importlib.import_module(f"{package}.{owner[name]}"), name)

    def __dir__() -> list[str]:
        return sorted(public)

    return __getattr__, __dir__
