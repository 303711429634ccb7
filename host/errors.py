"""Error tree of the host side.

`EigencastError` and its subclasses mean *bad input from a user* (a corrupt
file, an impossible option); the CLI prints them as one line and exits 1.
A traceback from the CLI means a bug in eigencast.
"""

from __future__ import annotations

__all__ = [
    "CinemaError",
    "EigencastError",
    "FitError",
    "TransferFunctionError",
    "ViewSpecError",
    "VolumeError",
]


class EigencastError(Exception):
    """Base class of every user-facing host error."""


class VolumeError(EigencastError):
    """A volume could not be loaded; the message names the file and the problem."""


class TransferFunctionError(EigencastError):
    """A transfer function preset or file is unknown or malformed."""


class ViewSpecError(EigencastError):
    """A view-set specification (``grid:100x15``, ``fibonacci:N`` ...) is malformed."""


class CinemaError(EigencastError):
    """A Cinema database is missing, malformed or inconsistent."""


class FitError(EigencastError):
    """Eigenspace fitting was asked something impossible."""
