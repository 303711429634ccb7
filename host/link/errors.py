"""The link stage's own errors (one line for the user, exit code 1 in the CLI)."""

from __future__ import annotations

from host.errors import EigencastError

__all__ = ["ServeError"]


class ServeError(EigencastError):
    """Serving cannot go on (the device lacks the image, ...): one line for the user."""
