"""The ``eigencast`` command line.

Each sub-command lives in its own module under ``host/commands/`` and exposes
``HELP`` (one line), ``add_arguments(parser)`` and ``run(args) -> int``.
This module only dispatches and turns user errors into one line on stderr
with exit code 1 (a traceback means a bug). A command line that cannot be parsed (an
unknown option, a missing or malformed argument) is a user error too: the sub-command's
own usage line (`short_usage`: its positionals and required options, then ``[options]``),
then one error line, exit code 1. Exit codes: 0 done, 1 a user error, 130 interrupted.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from typing import NoReturn

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


USAGE_ERROR = 1
"""Exit code of a command line that cannot be parsed (as of every other user error)."""


class _Parser(argparse.ArgumentParser):
    """argparse that answers a bad command line with its usage line, one error line and
    exit code `USAGE_ERROR` (argparse prints the whole usage page and exits 2)."""

    def error(self, message: str) -> NoReturn:
        self.exit(USAGE_ERROR, f"usage: {self.format_usage().split(':', 1)[1].strip()}\n"
                               f"{self.prog}: error: {' '.join(message.split())}\n")


def short_usage(parser: argparse.ArgumentParser) -> str:
    """``PROG POSITIONAL... -o METAVAR [options]``: what must be given, on one line."""
    must, positional = [], []
    for action in parser._actions:
        if action.option_strings:
            if action.required:
                must.append(f"{action.option_strings[0]} {action.metavar or action.dest.upper()}")
        elif action.nargs != argparse.SUPPRESS:
            positional.append(action.metavar or action.dest)
    return " ".join(["%(prog)s", *positional, *must, "[options]"])


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="eigencast",
        description="PCA eigenspace volume visualization for small, slow devices.",
    )
    parser.add_argument("--version", action="version", version=f"eigencast {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, module in _available_commands().items():
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.usage = short_usage(p)
        p.set_defaults(_run=module.run, _parser=p)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # argparse would blame the top-level parser: the sub-command's usage instead
        args._parser.error(f"unrecognized arguments: {' '.join(unknown)}")
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
