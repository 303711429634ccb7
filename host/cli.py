"""The ``eigencast`` command line.

Each sub-command lives in its own module under ``host/commands/`` and exposes
``HELP`` (one line), ``add_arguments(parser)`` and ``run(args) -> int``.
This module only dispatches and turns user errors into one line on stderr
with exit code 1 (a traceback means a bug).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from device_runtime.errors import DeviceError
from host import __version__
from host.errors import EigencastError
from protocol.errors import ProtocolError

# name -> module; import is lazy so `eigencast --help` stays fast.
COMMANDS: dict[str, str] = {
    "render": "host.commands.render",
    "render-view": "host.commands.render_view",
    "fit": "host.commands.fit",
    "evaluate": "host.commands.evaluate",
    "view": "host.commands.view",
    "keygen": "host.commands.keygen",
    "provision": "host.commands.provision",
    "serve": "host.commands.serve",
    "demo": "host.commands.demo",
}

USER_ERRORS: tuple[type[BaseException], ...] = (
    EigencastError,
    ProtocolError,
    DeviceError,
    ValueError,
    OSError,
)


def _available_commands() -> dict[str, object]:
    modules = {}
    for name, path in COMMANDS.items():
        try:
            modules[name] = importlib.import_module(path)
        except ModuleNotFoundError as exc:
            if exc.name != path:  # a real missing dependency: surface it
                raise
    return modules


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="eigencast",
        description="PCA eigenspace volume visualization for small, slow devices.",
    )
    parser.add_argument("--version", action="version", version=f"eigencast {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, module in _available_commands().items():
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        print("eigencast: interrupted", file=sys.stderr)
        return 130
    except USER_ERRORS as exc:
        print(f"eigencast {args.command}: error: {_one_line(exc)}", file=sys.stderr)
        return 1


def _one_line(exc: BaseException) -> str:
    text = str(exc) or type(exc).__name__
    if isinstance(exc, OSError) and exc.filename and str(exc.filename) not in text:
        text = f"{exc.filename}: {text}"
    return " ".join(text.split())


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
