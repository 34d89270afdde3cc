"""Centerline files (``segment --centerline FILE``): a polyline of points along a tube.

Three formats, by the file's name:

* ``.csv``: a header row naming the columns ``x``, ``y``, ``z`` and optionally ``radius`` (any
  order, any case), then one point per row;
* ``.json``: ``{"points": [[x, y, z], ...], "radii": [r, ...]}``, or ``"radii": r`` for all, or
  no ``radii``;
* ``.mrk.json``: a 3D Slicer markups file holding one ``Curve`` (or ``Fiducial`` list, taken in
  order, or ``Line``); a ``ClosedCurve`` is refused (a tube has two ends). Its points are world
  mm in LPS or RAS as its ``coordinateSystem`` says (read by :mod:`segsnake.markups`); it has no
  radii.

CSV and JSON points are in the units of the other positions: voxel indices, or world mm with
``--world``; radii in voxels across the tube, or mm with ``--world``. :func:`resolve_centerline`
puts the file's points in those units into the options (a markups file's world points are
converted through the image's affine, as :func:`segsnake.markups.resolve_markups` does), so the
pipeline sees rows of numbers, never a file.

Errors: a file that cannot be read or is not one of these formats, fewer than 2 points, a point
or radius that is not a finite number, two consecutive equal points, a radius <= 0:
:class:`InputError` (exit 3). Points outside the image, no radius (neither in the file nor
``--radius``), radii in the file and ``--radius`` too: :class:`ConfigError` (exit 2, like any
initialization outside the volume). Every message starts with the file.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import os
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

from segsnake.centerline import centerline_mm, polyline_problem
from segsnake.errors import ConfigError, InputError
from segsnake.markups import document_points, read_json, read_text

__all__ = ["CenterlineFile", "read_centerline", "resolve_centerline"]

#: Markup types that are an ordered list of points along a tube.
OPEN_TYPES = ("Curve", "Fiducial", "Line")
CSV_COLUMNS = ("x", "y", "z", "radius")


@dataclass(frozen=True)
class CenterlineFile:
    """What a centerline file holds.

    Attributes
    ----------
    points : ndarray (N, 3)
        In file order; RAS world mm when ``world``, else as the file gives them.
    radii : ndarray (N,) or None
        One per point, or None.
    world : bool
        The points are world mm whatever the options say (a markups file).
    """

    points: NDArray
    radii: NDArray | None
    world: bool


def _number(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return float(value)


def _read_csv(path: str) -> CenterlineFile:
    text = read_text(path, "centerline file")
    rows = [r for r in csv.reader(io.StringIO(text)) if any(c.strip() for c in r)]
    if not rows:
        raise InputError(f"{path}: empty centerline file (expected a header x,y,z[,radius] and "
                         f"one point per row)")
    header = [c.strip().lower() for c in rows[0]]
    unknown = [c for c in header if c not in CSV_COLUMNS]
    missing = [c for c in ("x", "y", "z") if c not in header]
    if unknown or missing or len(set(header)) != len(header):
        raise InputError(f"{path}: the header must name the columns x, y, z and optionally "
                         f"radius, each once; got {','.join(rows[0])!r}")
    values = np.empty((len(rows) - 1, len(header)))
    for n, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise InputError(f"{path}:{n}: {len(row)} values for {len(header)} columns")
        try:
            values[n - 2] = [float(c) for c in row]
        except ValueError:
            raise InputError(f"{path}:{n}: not numbers: {','.join(row)!r}") from None
    cols = {name: values[:, header.index(name)] for name in header}
    points = np.column_stack([cols["x"], cols["y"], cols["z"]])
    return CenterlineFile(points, cols.get("radius"), world=False)


def _read_plain_json(doc: Any, path: str) -> CenterlineFile:
    points = doc.get("points") if isinstance(doc, dict) else None
    if not isinstance(points, list) or not all(
            isinstance(p, list) and len(p) == 3 and all(_number(x) is not None for x in p)
            for p in points):
        raise InputError(f"{path}: not a centerline JSON file (expected {{\"points\": [[x, y, z], "
                         f"...], \"radii\": [r, ...] or r}})")
    pts = np.array(points, dtype=np.float64).reshape(-1, 3)
    radii = doc.get("radii")
    if radii is None:
        return CenterlineFile(pts, None, world=False)
    if _number(radii) is not None:
        return CenterlineFile(pts, np.full(len(pts), float(radii)), world=False)
    if not isinstance(radii, list) or not all(_number(r) is not None for r in radii):
        raise InputError(f"{path}: \"radii\" must be a number or a list of numbers")
    if len(radii) != len(pts):
        raise InputError(f"{path}: {len(radii)} radii for {len(pts)} points")
    return CenterlineFile(pts, np.array(radii, dtype=np.float64), world=False)


def _read_markups(doc: Any, path: str) -> CenterlineFile:
    markups = doc.get("markups") if isinstance(doc, dict) else None
    if not isinstance(markups, list):
        raise InputError(f"{path}: not a 3D Slicer markups file (no \"markups\" list)")
    if len(markups) != 1:
        raise InputError(f"{path}: holds {len(markups)} markups; a centerline is one Curve")
    kind = markups[0].get("type") if isinstance(markups[0], dict) else None
    if kind == "ClosedCurve":
        raise InputError(f"{path}: is a ClosedCurve; a centerline is an open Curve (a tube has "
                         f"two ends)")
    if kind not in OPEN_TYPES:
        raise InputError(f"{path}: markup type {kind!r}; a centerline is a Curve (or an ordered "
                         f"Fiducial list)")
    points, _ = document_points(doc, path)
    return CenterlineFile(points, None, world=True)


def read_centerline(path: str) -> CenterlineFile:
    """Read a centerline file (``.csv``, ``.json``, ``.mrk.json``; see the module's notes).

    Raises
    ------
    InputError
        Missing or unreadable file, an unknown format, or unusable points (one line starting
        with the file).
    """
    name = os.path.basename(path).lower()
    if name.endswith(".csv"):
        found = _read_csv(path)
    elif name.endswith(".json"):
        doc = read_json(path, "centerline file")
        found = (_read_markups(doc, path) if name.endswith(".mrk.json") or
                 (isinstance(doc, dict) and "markups" in doc) else _read_plain_json(doc, path))
    else:
        raise InputError(f"{path}: not a centerline file (expected .csv, .json or .mrk.json)")
    problem = polyline_problem(found.points, found.radii)
    if problem is not None:
        raise InputError(f"{path}: {problem}")
    return found


def resolve_centerline(config, found: CenterlineFile | None,
                       index_from_world: Callable[[NDArray], NDArray], spacing, shape):
    """``config`` with a ``centerline`` file replaced by its rows, in the options' units.

    Parameters
    ----------
    config : SegmentConfig
        ``centerline`` may be a file; ``world``, ``radius`` say the units and the radius.
    found : CenterlineFile, optional
        That file as :func:`read_centerline` read it (read here when None), so that a bad file
        can be refused before the image is loaded.
    index_from_world : callable
        The image's world (RAS mm) -> voxel index map.
    spacing, shape
        The image's voxel size and shape: the rows are checked against them here, so that a
        point outside the image is reported with the file.

    Returns
    -------
    SegmentConfig
        ``centerline`` as rows ``[x, y, z]`` or ``[x, y, z, radius]`` (voxel indices, or world
        mm with ``world``), unchanged when it was not a file.

    Raises
    ------
    InputError
        The file cannot be read or its points are unusable (exit 3).
    ConfigError
        A point outside the image; no radius; radii in the file and ``radius`` too (exit 2).
    """
    path = config.centerline
    if not isinstance(path, str):
        return config
    if found is None:
        found = read_centerline(path)
    points = found.points
    if found.world and not config.world:
        points = index_from_world(points)
    rows = points if found.radii is None else np.column_stack([points, found.radii])
    try:
        centerline_mm(rows, spacing, shape, world=config.world, radius=config.radius,
                      index_from_world=index_from_world)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {str(exc).removeprefix('centerline: ')}") from None
    values = [[float(x) for x in row] for row in rows]
    if not all(math.isfinite(x) for row in values for x in row):  # an affine gone wrong
        raise InputError(f"{path}: points not finite in the image's coordinates")
    return dataclasses.replace(config, centerline=values)
