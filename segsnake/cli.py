"""The ``segsnake`` command: a thin dispatcher over :mod:`segsnake.commands`.

Each sub-command lives in its own module under ``segsnake/commands`` and exposes
``add_parser(subparsers)`` and ``run(args) -> int``. This module only parses,
dispatches, and maps :class:`segsnake.errors.SegsnakeError` to a one-line
message and its exit code (``--debug`` re-raises for the traceback).
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys
import threading
from typing import Sequence

from segsnake.errors import SegsnakeError

DESCRIPTION = ("Segment 3D structures in medical volumes with smooth spline snakes "
               "(deformable spheres and cylinders).")

# Order is the order shown in ``segsnake --help``.
COMMANDS = ("segment", "demo", "phantom", "evaluate", "batch", "shape", "shape-model")


class _Parser(argparse.ArgumentParser):
    """argparse exits with 2 on usage errors already; keep its one-line message."""

    def error(self, message: str) -> None:  # pragma: no cover - exercised via CLI tests
        self.exit(2, f"segsnake: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="segsnake", description=DESCRIPTION,
                     epilog="Run 'segsnake COMMAND --help' for the options of a command.")
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for name in COMMANDS:
        module_name = "segsnake.commands." + name.replace("-", "_")
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name == module_name:  # command not built yet
                continue
            raise
        module.add_parser(sub)
    return parser


def _terminate(signum: int, frame: object) -> None:
    # A SIGTERM (a scheduler's kill, a timeout) unwinds like Ctrl-C, so the cleanup of partial
    # outputs runs instead of leaving a staging directory behind.
    raise KeyboardInterrupt


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    args = parser.parse_args(argv)
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _terminate)
    try:
        return int(args.func(args) or 0)
    except SegsnakeError as exc:
        if args.debug:
            raise
        print(f"segsnake {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"segsnake {args.command}: interrupted", file=sys.stderr)
        return 130
    except MemoryError:
        if args.debug:
            raise
        print(f"segsnake {args.command}: error: out of memory (crop or resample the image first)",
              file=sys.stderr)
        return 3


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
