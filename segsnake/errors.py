"""Error hierarchy shared by the numerical core and the command line.

The core raises these; only :mod:`segsnake.cli` turns them into a one-line
message and an exit code. Each class carries the exit code documented in the
README, so a new error kind needs no change in the CLI.
"""

from __future__ import annotations


class SegsnakeError(Exception):
    """Base class of every error segsnake reports to a user."""

    exit_code = 1


class ConfigError(SegsnakeError):
    """Bad command-line usage or configuration (YAML syntax, keys, types, ranges)."""

    exit_code = 2


class InputError(SegsnakeError):
    """An input file is missing, unreadable or not a usable image or mask."""

    exit_code = 3


class SegmentationError(SegsnakeError):
    """The segmentation ran but failed: NaN energy, collapsed or escaped snake, no edges."""

    exit_code = 4


class OutputError(SegsnakeError):
    """An output cannot be written (exists without --overwrite, read-only, disk full)."""

    exit_code = 5


class BatchError(SegsnakeError):
    """A batch finished but some of its cases failed."""

    exit_code = 6
