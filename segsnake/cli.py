"""The ``segsnake`` command: a thin dispatcher over :mod:`segsnake.commands`.

Each sub-command lives in its own module under ``segsnake/commands`` and exposes
``add_parser(subparsers)`` and ``run(args) -> int``. This module only parses, dispatches, and
turns every way a run can end into an exit code and at most one line on stderr (and, with
``--json``, an error object on stdout): a :class:`segsnake.errors.SegsnakeError` gives its
message and documented code, Ctrl-C or SIGTERM 130, a closed stdout (``| head``) 141 in silence,
anything unexpected 1 with a one-line description. ``--debug`` re-raises for the traceback.
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
import threading
from typing import Any, Sequence

from segsnake import __version__, cancel
from segsnake.allocator import return_freed_memory
from segsnake.errors import SegsnakeError

DESCRIPTION = ("Segment 3D structures in medical volumes with smooth spline snakes "
               "(deformable spheres and cylinders).")

# Order is the order shown in ``segsnake --help``.
COMMANDS = ("segment", "demo", "phantom", "evaluate", "batch", "shape", "shape-model",
            "export-points", "render", "fit", "morph", "measure")

# Exit codes decided here rather than by an error class (the README's table lists every code).
EXIT_UNEXPECTED = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = cancel.EXIT_INTERRUPTED
# A reader that closed our stdout (``segsnake evaluate ... | head -1``): the code of a tool that
# the shell saw die of SIGPIPE, as ``seq``, ``cat`` or ``git`` do in the same place.
EXIT_CLOSED_PIPE = 128 + signal.SIGPIPE


class UsageError(SegsnakeError):
    """A command line argparse cannot parse (unknown flag, missing argument)."""

    exit_code = EXIT_USAGE

    def __init__(self, message: str, command: str | None) -> None:
        super().__init__(message)
        self.command = command


class _Parser(argparse.ArgumentParser):
    """argparse, but a usage error is raised (so that ``--json`` can report it) and not printed."""

    def error(self, message: str) -> None:  # type: ignore[override]
        words = self.prog.split()
        raise UsageError(message, words[1] if len(words) > 1 else None)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``segsnake`` parser with every sub-command that is installed, or only ``command``
    (a run of one command imports only its module: the others' imports cost it start-up time,
    0.1 s for the phantom and fit commands' numerical modules)."""
    parser = _Parser(prog="segsnake", description=DESCRIPTION,
                     epilog="Run 'segsnake COMMAND --help' for the options of a command.")
    parser.add_argument("--version", action="version", version=f"segsnake {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for name in (command,) if command in COMMANDS else COMMANDS:
        module_name = "segsnake.commands." + name.replace("-", "_")
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name == module_name:  # command not built yet
                continue
            raise
        module.add_parser(sub)
    return parser


def _mute_output() -> None:
    """Point stdout and stderr at /dev/null: their reader is gone, and the interpreter's final
    flush must not fail again (Python would print 'Exception ignored ... BrokenPipeError')."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        for stream in (sys.stdout, sys.stderr):
            try:
                fd = stream.fileno()
            except (AttributeError, OSError, ValueError):  # a replaced stream (tests): no fd
                continue
            os.dup2(devnull, fd)
    finally:
        os.close(devnull)


def _report(command: str | None, want_json: bool, code: int, message: str,
            exc: BaseException | None = None, verb: str = "error: ") -> int:
    """One line on stderr (``verb`` before the message) and, with ``--json``, the error object on
    stdout; returns ``code``."""
    from segsnake.commands.reporting import error_object, print_json

    where = f"segsnake {command}" if command else "segsnake"
    try:
        if want_json:
            seg = exc if isinstance(exc, SegsnakeError) else None
            print_json(error_object(
                command, code, message, file=seg.file if seg else None,
                line=seg.line if seg else None,
                kind=type(exc).__name__ if exc is not None else None,
                details=seg.details if seg else None))
            sys.stdout.flush()
        sys.stderr.write(f"{where}: {verb}{message}\n")
        sys.stderr.flush()
    except BrokenPipeError:
        _mute_output()
    return code


_reported = threading.Lock()


def _report_interrupted(state: dict[str, Any]) -> int:
    """The "interrupted" line, once (the main thread and the watchdog of :mod:`segsnake.cancel`
    may both get here); returns 130."""
    if _reported.acquire(blocking=False):
        try:
            _report(state["command"], state["json"], EXIT_INTERRUPTED, "interrupted", verb="")
        finally:
            state["reported"] = True
    return EXIT_INTERRUPTED


def main(argv: Sequence[str] | None = None, *,
         parser: argparse.ArgumentParser | None = None,
         exit_process: bool | None = None) -> int:
    """Run ``segsnake ARGV`` and return its exit code (README, "Exit codes and errors").

    Parameters
    ----------
    argv : sequence of str, optional
        The arguments (default ``sys.argv[1:]``).
    parser : argparse.ArgumentParser, optional
        Another parser (default :func:`build_parser`): its sub-commands set ``func``, ``command``
        and ``debug`` as the real ones do (tests give one whose command misbehaves).
    exit_process : bool, optional
        End the process with the exit code (``os._exit`` after flushing) instead of returning,
        and let a watchdog end it (exit 130) when the main thread has not finished within
        :data:`segsnake.cancel.GRACE_S` of a Ctrl-C or SIGTERM. The interpreter's shutdown
        would wait for pool threads still inside a C call, and it resets the signal handlers,
        so that a signal during it would end the process with the signal's own status (default:
        when ``argv`` is None, i.e. when this is the ``segsnake`` program).

    Returns
    -------
    int
        The exit code.
    """
    if exit_process is None:
        exit_process = argv is None
    argv = list(sys.argv[1:] if argv is None else argv)
    # Known before parsing, so that a command line argparse refuses is reported in JSON too, and
    # an interrupt during the start-up's imports names its command.
    first = next((a for a in argv if not a.startswith("-")), None)
    state: dict[str, Any] = {"command": first if first in COMMANDS else None,
                             "json": "--json" in argv, "debug": False}
    if _reported.locked():  # an earlier main() in this process (tests) reported its interrupt
        _reported.release()
    try:
        code = _main(argv, parser, state, exit_process)
        if exit_process:
            cancel.exit_now(code)
    except KeyboardInterrupt:  # also one that arrived while an error was being reported
        code = _report_interrupted(state)
        if exit_process:
            cancel.exit_now(code)
    return code


def _main(argv: list[str], parser: argparse.ArgumentParser | None, state: dict[str, Any],
          exit_process: bool) -> int:
    # First, before the imports of the commands: a SIGTERM (a scheduler's kill, a timeout) ends a
    # run like Ctrl-C, the cleanup of partial outputs runs instead of leaving a staging directory.
    cancel.install(grace=cancel.GRACE_S if exit_process else None,
                   on_exit=lambda: _report_interrupted(state))
    if exit_process:  # the segsnake program: its freed volumes go back to the system
        return_freed_memory()
    try:
        if parser is None:
            parser = build_parser(state["command"])
        try:
            args = parser.parse_args(argv)
        except SystemExit:  # --help, --version: flushed here, where a closed pipe is handled
            sys.stdout.flush()
            raise
        state.update(command=args.command, json=bool(getattr(args, "json", False)),
                     debug=args.debug)
        # (BLAS in one thread for every command: fits, shape models and segmentations alike give
        # the same numbers on any number of cores; imported here, after the parse, with numpy)
        from segsnake.parallel import one_blas_thread

        code = int(one_blas_thread(args.func)(args) or 0)
        cancel.check()  # an interrupt a library destructor swallowed still ends the run as one
        sys.stdout.flush()  # here, where a closed pipe can still be handled
        return code
    except BrokenPipeError:
        _mute_output()
        return EXIT_CLOSED_PIPE
    except UsageError as exc:
        help_command = f"segsnake {exc.command} --help" if exc.command else "segsnake --help"
        return _report(exc.command, state["json"], exc.exit_code, f"{exc} (see '{help_command}')",
                       exc)
    except SegsnakeError as exc:
        if state["debug"]:
            raise
        return _report(state["command"], state["json"], exc.exit_code, str(exc), exc)
    except KeyboardInterrupt:
        return _report_interrupted(state)
    except MemoryError as exc:
        if state["debug"]:
            raise
        return _report(state["command"], state["json"], 3,
                       "out of memory (crop or resample the image first)", exc)
    except Exception as exc:  # noqa: BLE001 - the promise: never a traceback without --debug
        if state["debug"]:
            raise
        return _report(state["command"], state["json"], EXIT_UNEXPECTED,
                       f"unexpected error: {type(exc).__name__}: {' '.join(str(exc).split())} "
                       f"(a bug: run with --debug for the traceback and please report it)", exc)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
