"""The files a batch names must be there before any case runs.

:func:`segsnake.batch.load_batch` validates the YAML itself; this module then looks for every
image, truth, prior and markups file (a position given as a file) it names, so that a batch of twenty cases whose images were never made
stops at once with the list of what is missing, instead of recording twenty "file not found"
failures one case process after another. Paths are checked as this machine sees them.
"""

from __future__ import annotations

import os
import re
from typing import Any

from segsnake.config import PATH_KEYS
from segsnake.errors import InputError

__all__ = ["missing_inputs", "check_inputs"]

ROLES = ("image", "truth") + PATH_KEYS


def _problem(path: str) -> str | None:
    """Why ``path`` cannot be read, or None. A directory passes (a reader may take one)."""
    if not os.path.exists(path):
        return "no such file"
    if not os.access(path, os.R_OK):
        return "permission denied"
    return None


def missing_inputs(spec: Any) -> list[dict[str, Any]]:
    """Every input file of a validated batch that cannot be read, in the order the file names them.

    Parameters
    ----------
    spec : BatchSpec
        From :func:`segsnake.batch.load_batch` (``check_files=False``).

    Returns
    -------
    list of dict
        ``where`` (``FILE:LINE:COL`` of the key), ``line``, ``case``, ``role`` (image, truth,
        prior, or the position a markups file gives: center, seed_point, ...), ``path`` (absolute) and ``problem``; a file named once for several cases (a
        prior in ``defaults:``) is listed once.
    """
    found: dict[tuple[str, str], dict[str, Any]] = {}
    for case in spec.cases:
        # Positions given as numbers are not files (a prior is always a path or None).
        paths = {"image": case.image, "truth": case.truth,
                 **{key: value for key in PATH_KEYS
                    if isinstance(value := getattr(case.config, key), str)}}
        for role in ROLES:
            path = paths.get(role)
            if path is None:
                continue
            problem = _problem(path)
            if problem is None:
                continue
            where = case.where.get(role, spec.path)
            key = (where, path)
            if key not in found:
                m = re.search(r":(\d+):\d+$", where)
                found[key] = {"where": where, "line": int(m.group(1)) if m else None,
                              "case": case.name, "role": role, "path": path, "problem": problem}
    return sorted(found.values(), key=lambda item: (item["line"] or 0, item["where"]))


def check_inputs(spec: Any, *, source: str | None = None) -> None:
    """Raise :class:`InputError` listing every missing input file of ``spec``, if there is one.

    Parameters
    ----------
    spec : BatchSpec
        A validated batch.
    source : str, optional
        The batch file as the user named it (default: its absolute path).

    Raises
    ------
    InputError
        One summary line naming the batch file, then one line per missing file:
        ``FILE:LINE:COL: role PATH: problem`` (the details hold them as a list under ``missing``).
    """
    missing = missing_inputs(spec)
    if not missing:
        return
    src = source or spec.path
    n = len(missing)
    head = (f"{src}: {n} input file{'s' if n > 1 else ''} of the batch cannot be read "
            f"(nothing was run):")
    lines = [f"  {m['where']}: {m['role']} {m['path']}: {m['problem']}" for m in missing]
    raise InputError("\n".join([head, *lines]), details={"missing": missing})
