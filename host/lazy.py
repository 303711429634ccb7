"""Lazy re-exports for the stage packages (``host/volume/``, ``host/render/`` ...).

Each stage's ``__init__.py`` names its public API once per module in an ``EXPORTS`` table
and lists it in ``__all__``; `attach` gives the package a PEP 562 ``__getattr__`` that
imports a module only when one of its names is first used. So ``from host.render import
Camera`` does not import numba (the ray-caster), and ``eigencast --help`` stays fast
although every command names its stage's public API (the same reason `host.cli` imports
each command lazily).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping, Sequence
from typing import Any

__all__ = ["attach"]


def attach(
    package: str, exports: Mapping[str, Sequence[str]]
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """``__getattr__`` and ``__dir__`` for ``package`` that import its names on demand.

    Parameters
    ----------
    package : str
        The package's ``__name__``.
    exports : mapping of str to sequence of str
        Module name inside the package (``"camera"``) -> the public names it defines.

    Returns
    -------
    (__getattr__, __dir__)
        Assign both at module level in the package's ``__init__.py``.
    """
    owner = {name: module for module, names in exports.items() for name in names}

    def __getattr__(name: str) -> Any:
        if name not in owner:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{owner[name]}"), name)
        return value

    def __dir__() -> list[str]:
        return sorted(owner)

    return __getattr__, __dir__
