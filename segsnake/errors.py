"""Error hierarchy shared by the numerical core and the command line.

The core raises these; only :mod:`segsnake.cli` turns them into a one-line
message and an exit code. Each class carries the exit code documented in the
README, so a new error kind needs no change in the CLI.

Messages follow one convention: ``FILE[:LINE[:COL]]: problem`` when they are about a file, so
the file (and the line of a YAML file) can be read back from the message (:attr:`file`,
:attr:`line`) for the ``--json`` error object without every raise site naming it twice.
"""

from __future__ import annotations

import os
import re
from typing import Any

# "FILE: problem" or "FILE:LINE: problem" or "FILE:LINE:COL: problem", FILE up to the first ": ".
_LOCATION = re.compile(r"^(?P<file>.+?)(?::(?P<line>\d+)(?::(?P<col>\d+))?)?: ")


def message_location(message: str) -> tuple[str | None, int | None]:
    """The file (and line) a ``FILE[:LINE[:COL]]: problem`` message is about, else ``(None, None)``.

    The prefix counts as a file when it has no blank in it (``--resume and --overwrite ...`` is
    prose) or when it exists on disk (a path with a blank).

    Parameters
    ----------
    message : str
        An error message.

    Returns
    -------
    (str or None, int or None)
        The file and its line (None when the message gives none).
    """
    m = _LOCATION.match(message)
    if m is None:
        return None, None
    path = m.group("file")
    if any(c.isspace() for c in path) and not os.path.lexists(path):
        return None, None
    line = m.group("line")
    return path, (int(line) if line is not None else None)


class SegsnakeError(Exception):
    """Base class of every error segsnake reports to a user.

    Parameters
    ----------
    message : str
        One line, ``FILE[:LINE[:COL]]: problem`` when about a file; further lines, if any, list
        the items of a problem that has several (each missing file of a batch).
    file : str, optional
        The file the error is about, when the message does not start with it.
    details : dict, optional
        JSON-able facts for the ``--json`` error object (the list of missing files, the counts of
        a batch).
    """

    exit_code = 1

    def __init__(self, message: str = "", *, file: str | None = None,
                 details: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self._file = file
        self.details = dict(details or {})

    @property
    def file(self) -> str | None:
        """The file this error is about (given, or read from the message), or None."""
        if self._file is not None:
            return self._file
        return message_location(str(self))[0]

    @property
    def line(self) -> int | None:
        """The line of :attr:`file` the message points at (a YAML key), or None."""
        if self._file is not None:
            return None
        return message_location(str(self))[1]


class ConfigError(SegsnakeError):
    """Bad command-line usage or configuration (YAML syntax, keys, types, ranges)."""

    exit_code = 2


class InputError(SegsnakeError):
    """An input file is missing, unreadable or not a usable image or mask."""

    exit_code = 3


class SegmentationError(SegsnakeError):
    """The segmentation ran but failed: NaN energy, collapsed or escaped snake, no edges."""

    exit_code = 4


class NoBoundaryError(SegmentationError):
    """The image holds no boundary where the surface is: its inside and outside do not differ."""


class OutputError(SegsnakeError):
    """An output cannot be written (exists without --overwrite, read-only, disk full)."""

    exit_code = 5


class BatchError(SegsnakeError):
    """A batch finished but some of its cases failed."""

    exit_code = 6
