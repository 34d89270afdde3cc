"""How every command reports: ``--quiet``, ``--json``, result lines, warnings, the error object.

Every command takes the same two options, with the same meaning:

* ``--quiet`` / ``-q``: nothing on stdout and no progress display. Warnings and errors still go
  to stderr: they say something about the result that a script must not miss.
* ``--json``: the result as one JSON object on stdout, ``{"status": "ok", ...}``, and no progress
  display (also with ``--quiet``). On failure the object is :func:`error_object` instead, and the
  usual one-line message still goes to stderr.

Only the command layer uses this module: the core returns values and raises
:class:`segsnake.errors.SegsnakeError`, it never prints.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any, Iterable, Sequence

from segsnake.jsonable import jsonable

__all__ = ["add_output_options", "progress_off", "emit", "warn", "error_object", "print_json"]


def add_output_options(parser: argparse.ArgumentParser) -> None:
    """Add ``--quiet/-q`` and ``--json`` to a command's parser."""
    parser.add_argument("--quiet", "-q", action="store_true",
                        help="print nothing on stdout and show no progress (warnings and errors "
                             "still go to stderr)")
    parser.add_argument("--json", action="store_true",
                        help="print the result as one JSON object on stdout, or on failure a JSON "
                             "error object (status, code, message, file)")


def progress_off(args: argparse.Namespace) -> bool:
    """True when the progress display must stay off (``--quiet`` or ``--json``)."""
    return bool(getattr(args, "quiet", False) or getattr(args, "json", False))


def print_json(record: dict[str, Any]) -> None:
    """Print ``record`` as one line of strict JSON (non-finite numbers as null) on stdout."""
    sys.stdout.write(json.dumps(jsonable(record), allow_nan=False) + "\n")


def emit(args: argparse.Namespace, record: dict[str, Any], lines: Sequence[str]) -> None:
    """Report a command's result: ``record`` as JSON with ``--json``, else ``lines`` unless quiet.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options (``json``, ``quiet``).
    record : dict
        The result; printed after ``"status": "ok"``.
    lines : sequence of str
        The human-readable result.
    """
    if getattr(args, "json", False):
        print_json({"status": "ok", **record})
    elif not getattr(args, "quiet", False):
        for line in lines:
            sys.stdout.write(line + "\n")


def warn(command: str, warnings: Iterable[str]) -> None:
    """Print each warning as ``segsnake COMMAND: warning: ...`` on stderr (also when quiet)."""
    for w in warnings:
        sys.stderr.write(f"segsnake {command}: warning: {w}\n")
    sys.stderr.flush()


def error_object(command: str | None, code: int, message: str, *, file: str | None = None,
                 line: int | None = None, kind: str | None = None,
                 details: dict[str, Any] | None = None) -> dict[str, Any]:
    """The JSON object ``--json`` prints on stdout when a command fails.

    Parameters
    ----------
    command : str or None
        The sub-command (None when the command line could not be parsed).
    code : int
        The exit code (the README's table).
    message : str
        The error message as printed on stderr after ``segsnake COMMAND: error:``.
    file, line : optional
        The file (and line of a YAML file) the error is about.
    kind : str, optional
        The error class (``InputError``, ``ConfigError``, ...).
    details : dict, optional
        Further facts (a batch's missing files, its counts).

    Returns
    -------
    dict
        ``{"status": "error", "command", "code", "error", "message", "file", "line", ...}``.
    """
    record: dict[str, Any] = {"status": "error", "command": command, "code": int(code),
                              "error": kind, "message": message, "file": file, "line": line}
    record.update(details or {})
    return record
