"""3D Slicer markups files (``.mrk.json``) as the positions of the ``segment`` options.

A Slicer user's click is a markups file, not three numbers: its control points are in world
millimetres, in LPS or RAS as the markup's ``coordinateSystem`` says (Slicer's markups schema,
``{"markups": [{"type": ..., "coordinateSystem": "LPS"|"RAS", "controlPoints": [{"position":
[x, y, z]}, ...]}]}``). :func:`read_markups` reads them as RAS world points (the convention of a
NIfTI affine, :class:`segsnake.io.Volume`), and :func:`resolve_markups` replaces the option values
that name a markups file by the numbers they mean for one image: voxel indices, or world mm with
``world``, exactly as ``--world`` numbers would be read.

Which points an option takes: ``center`` and ``seed_point`` one point; ``axis_end`` one point;
``axis_start`` one point, or two (a Slicer line, or a list of two fiducials) meaning the start and
the end of the axis, when ``axis_end`` is not given.
"""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

from segsnake.config import POSITION_KEYS
from segsnake.errors import ConfigError, InputError
from segsnake.io import _LPS_TO_RAS

__all__ = ["read_markups", "read_control_points", "read_json", "read_text", "document_points",
           "resolve_markups", "is_markups_value"]

# LPS <-> RAS: the first two world axes point the other way.


def is_markups_value(value: Any) -> bool:
    """True when an option value names a file (a markups file) rather than giving numbers."""
    return isinstance(value, str)


def _points_of(markup: Any, path: str, n: int) -> list[tuple[NDArray, dict]]:
    """The defined control points of one markup: (position in RAS mm, the control point)."""
    if not isinstance(markup, dict):
        raise InputError(f"{path}: markup {n} is not a JSON object")
    system = markup.get("coordinateSystem", "LPS")  # the schema's default
    if system not in ("LPS", "RAS"):
        raise InputError(f"{path}: markup {n} has coordinateSystem {system!r}; expected LPS or RAS")
    units = markup.get("coordinateUnits", "mm")
    if units != "mm":
        raise InputError(f"{path}: markup {n} has coordinateUnits {units!r}; only mm is supported")
    points = markup.get("controlPoints", [])
    if not isinstance(points, list):
        raise InputError(f"{path}: markup {n}: controlPoints is not a list")
    out = []
    for k, cp in enumerate(points):
        if not isinstance(cp, dict):
            raise InputError(f"{path}: markup {n}, control point {k} is not a JSON object")
        # Slicer keeps placeholders ("undefined": not placed yet) in a list: they have no position.
        if cp.get("positionStatus", "defined") == "undefined":
            continue
        pos = cp.get("position")
        if not isinstance(pos, list) or len(pos) != 3 or not all(
                isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
                for x in pos):
            raise InputError(f"{path}: markup {n}, control point {k}: position must be 3 finite "
                             f"numbers, got {pos!r}")
        p = np.asarray(pos, dtype=np.float64)
        out.append((_LPS_TO_RAS @ p if system == "LPS" else p, cp))
    return out


def read_markups(path: str) -> NDArray:
    """The control points of a Slicer markups file as RAS world millimetres, shape (N, 3): the
    positions of :func:`read_control_points` (same parameter, same errors)."""
    return read_control_points(path)[0]


def read_control_points(path: str) -> tuple[NDArray, list[dict]]:
    """The control points of a Slicer markups file: RAS positions and the points' records.

    Parameters
    ----------
    path : str
        A ``.mrk.json`` file. Every markup in it contributes its defined control points, in order.

    Returns
    -------
    ndarray, shape (N, 3)
        N >= 1 points, RAS world mm (LPS points converted).
    list of dict
        Each point's record as the file holds it (``label``, ``description``, ...).

    Raises
    ------
    InputError
        The file is missing, unreadable, not JSON, not a markups document, or holds no point;
        the one-line message starts with the file.
    """
    return document_points(read_json(path, "markups file"), path)


def read_text(path: str, what: str) -> str:
    """A UTF-8 text file's content (a byte-order mark, as Excel's "CSV UTF-8" writes, dropped);
    every way reading it fails is one :class:`InputError` line.

    Parameters
    ----------
    path : str
        The file.
    what : str
        What the file should be, for the messages ("markups file", "centerline file").
    """
    try:
        with open(path, encoding="utf-8-sig", newline="") as fh:
            return fh.read()
    except FileNotFoundError:
        raise InputError(f"{path}: no such {what}") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a directory, not a {what}") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a {what} (not UTF-8 text)") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read the {what} ({exc.strerror or exc})") from None


def read_json(path: str, what: str) -> Any:
    """A JSON file's content: :func:`read_text` (same parameters, same errors), and a file that
    is not JSON is one :class:`InputError` line too."""
    text = read_text(path, what)
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: not a {what} (JSON error at line {exc.lineno}: "
                         f"{exc.msg})") from None


def document_points(doc: Any, path: str) -> tuple[NDArray, list[dict]]:
    """:func:`read_control_points` of a document already read from ``path``."""
    markups = doc.get("markups") if isinstance(doc, dict) else None
    if not isinstance(markups, list):
        raise InputError(f"{path}: not a 3D Slicer markups file (no \"markups\" list)")
    points = [p for n, m in enumerate(markups) for p in _points_of(m, path, n)]
    if not points:
        raise InputError(f"{path}: the markups file holds no control point")
    return np.stack([p for p, _ in points]), [cp for _, cp in points]


def resolve_markups(config, index_from_world: Callable[[NDArray], NDArray]):
    """``config`` with every position that names a markups file replaced by its numbers.

    Parameters
    ----------
    config : SegmentConfig
        ``center``, ``seed_point``, ``axis_start``, ``axis_end`` may be a file path.
    index_from_world : callable
        World RAS mm (N, 3) -> voxel indices (N, 3): the image's inverse affine.

    Returns
    -------
    SegmentConfig
        A copy whose positions are all numbers: voxel indices, or world mm when ``config.world``
        (the same numbers ``--world`` would take), so the rest of the pipeline sees no file.

    Raises
    ------
    InputError
        An unreadable markups file, or one with the wrong number of points for its option.
    ConfigError
        ``axis_start`` gives two points (start and end) and ``axis_end`` is given too.
    """
    changes: dict[str, list[float]] = {}

    def as_option(p: NDArray) -> list[float]:
        q = p if config.world else index_from_world(p[None])[0]
        return [float(x) for x in q]

    for key in POSITION_KEYS:
        value = getattr(config, key)
        if not is_markups_value(value):
            continue
        points = read_markups(value)
        flag = "--" + key.replace("_", "-")
        if key == "axis_start" and len(points) == 2:
            if config.axis_end is not None:
                raise ConfigError(f"{value}: holds two points (the axis start and end) but "
                                  f"--axis-end is given too; give one of them")
            changes["axis_end"] = as_option(points[1])
        elif len(points) != 1:
            allowed = "one point, or two (start and end)" if key == "axis_start" else "one point"
            raise InputError(f"{value}: holds {len(points)} control points; {flag} takes a "
                             f"markups file with {allowed}")
        changes[key] = as_option(points[0])
    return dataclasses.replace(config, **changes) if changes else config
