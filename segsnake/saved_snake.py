"""A saved snake in world coordinates: ``snake.json``, or its control points as 3D Slicer markups.

The edit round trip (issue 17): ``segsnake export-points`` writes a snake's control points as a
Slicer fiducial list in world millimetres, a user moves them in Slicer and saves, and
``segsnake render`` (or ``segment --init``) rebuilds the snake from them on an image's grid.
Because the snakes are *interpolating* splines, every exported point of a sphere and every point
of rows ``l = 0..M2`` of a cylinder lies on the surface: moving it moves the surface through it.

What the markups file holds, so that Slicer keeps it when it saves the list again:

* one fiducial per control point that is a position: a sphere's interior points ``c[k, l]``
  (``l = 1..M2-1``) and its two poles, a cylinder's whole grid ``c[k, l]`` (``l = -1..M2+1``;
  rows ``-1`` and ``M2+1`` lie beyond the open ends and set their slope);
* each point's ``label`` names it (``c[3,2]``, ``north``, ``south``) and its ``description`` is a
  small JSON object (:data:`TAG`, the model kind, M1, M2 and the parameter row the point is), so
  the points may come back in any order, and a point added or deleted is noticed;
* a sphere's four pole tangent vectors (directions, not points) are stored in the two poles'
  descriptions as coefficients in the frame of three points of the ring next to the pole
  (``c[k, 1] - north`` for three k): a rigid or affine move of the whole list in Slicer moves
  the tangents with it, LPS or RAS makes no difference, and moving a pole or its ring bends the
  tangents along.

The markup is a standard ``Fiducial`` list (schema ``markups-schema-v1.0.3``) with
``fixedNumberOfControlPoints`` set, so Slicer lets the user move points but not add or delete them.
Slicer reads and writes each control point's ``id``, ``label``, ``description`` and ``position``
(``vtkMRMLMarkupsJsonStorageNode``), so the file survives being loaded, edited and saved there.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from segsnake.config import M_MAX, M_MIN
from segsnake.errors import InputError
from segsnake.io import _LPS_TO_RAS
from segsnake.markups import document_points, read_json
from segsnake.surfaces import CylinderModel, SphereModel, SplineSurface, model_from_dict

__all__ = ["MARKUPS_SCHEMA", "TAG", "load_snake", "load_snake_and_record", "read_model",
           "snake_markups",
           "world_from_image", "image_from_world"]

MARKUPS_SCHEMA = ("https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/"
                  "Markups/Resources/Schema/markups-schema-v1.0.3.json#")
#: The key of a control point's description that marks it as a segsnake snake's point (its value
#: is the format version).
TAG = "segsnake"
FORMAT = 1

_KINDS = {"sphere": SphereModel, "cylinder": CylinderModel}


# ------------------------------------------------------------------------------ coordinates
def world_from_image(model: SplineSurface, affine: NDArray, spacing) -> SplineSurface:
    """A model in mm of scaled index space (``(i sx, j sy, k sz)``) in world RAS mm.

    Parameters
    ----------
    model : SplineSurface
        As segsnake stores it (``snake.json``'s ``model``).
    affine : ndarray (4, 4)
        The image's voxel-to-world (RAS) affine.
    spacing : sequence of 3 float
        The image's voxel sizes, as the model was scaled with.
    """
    aff = np.asarray(affine, dtype=np.float64)
    A = aff[:3, :3] @ np.diag(1.0 / np.asarray(spacing, dtype=np.float64))
    return model.transformed(A, aff[:3, 3])


def image_from_world(world: SplineSurface, affine: NDArray, spacing) -> SplineSurface:
    """A world (RAS mm) model in mm of an image's scaled index space, oriented outward there.

    The inverse of :func:`world_from_image` for that image. A world model from an image of the
    other handedness comes out inside-out (the map's determinant is negative); it is then
    traversed the other way round (:meth:`SplineSurface.reversed`), the same surface.
    """
    aff = np.asarray(affine, dtype=np.float64)
    A = np.diag(np.asarray(spacing, dtype=np.float64)) @ np.linalg.inv(aff[:3, :3])
    model = world.transformed(A, -A @ aff[:3, 3])
    return model.reversed() if model.volume(order=4) < 0 else model


# ------------------------------------------------------------------------------ the points
def _position_rows(kind: str, m1: int, m2: int) -> list[tuple[int, str]]:
    """(parameter row, label) of every free parameter that is a point, in parameter order."""
    if kind == "sphere":
        rows = [(k * (m2 - 1) + (l - 1), f"c[{k},{l}]") for k in range(m1) for l in range(1, m2)]
        base = m1 * (m2 - 1)
        return rows + [(base, "north"), (base + 1, "south")]
    return [(k * (m2 + 3) + (l + 1), f"c[{k},{l}]") for k in range(m1) for l in range(-1, m2 + 2)]


def _frame_rows(m1: int, m2: int, pole: str) -> list[int]:
    """The rows of the three ring points whose differences from a pole frame its tangents."""
    l = 1 if pole == "north" else m2 - 1
    return [k * (m2 - 1) + (l - 1) for k in (0, m1 // 3, (2 * m1) // 3)]


def _pole_names(pole: str) -> tuple[str, str, str]:
    return ("cN", "T1N", "T2N") if pole == "north" else ("cS", "T1S", "T2S")


def snake_markups(world: SplineSurface, system: str = "LPS", name: str = "segsnake") -> dict:
    """A 3D Slicer markups document (a fiducial list) of a world-coordinate snake's control points.

    Parameters
    ----------
    world : SplineSurface
        The snake in world RAS mm (:func:`world_from_image`).
    system : {"LPS", "RAS"}
        The file's ``coordinateSystem`` (Slicer itself saves LPS).
    name : str
        The markup's name, shown in Slicer.

    Returns
    -------
    dict
        JSON-able; :func:`load_snake` of it rebuilds ``world`` (to rounding).
    """
    flip = _LPS_TO_RAS if system == "LPS" else np.eye(3)  # its own inverse
    head = {TAG: FORMAT, "kind": world.kind, "m1": world.m1, "m2": world.m2}
    points = []
    for n, (row, label) in enumerate(_position_rows(world.kind, world.m1, world.m2)):
        desc: dict[str, Any] = {**head, "row": row}
        if world.kind == "sphere" and label in ("north", "south"):
            c, t1, t2 = (world.pole(x) for x in _pole_names(label))
            frame_rows = _frame_rows(world.m1, world.m2, label)
            E = (world.params[frame_rows] - c).T  # columns: ring point - pole
            coef = np.linalg.lstsq(E, np.column_stack([t1, t2]), rcond=None)[0]
            desc["tangent_frame_rows"] = frame_rows
            desc["tangents"] = coef.T.tolist()
        points.append({
            "id": str(n + 1), "label": label, "description": json.dumps(desc),
            "associatedNodeID": "", "position": (flip @ world.params[row]).tolist(),
            # Slicer's default (RAS identity) in the file's coordinate system.
            "orientation": flip.ravel().tolist(),
            "selected": True, "locked": False, "visibility": True, "positionStatus": "defined"})
    markup = {"type": "Fiducial", "name": name, "coordinateSystem": system,
              "coordinateUnits": "mm", "locked": False, "fixedNumberOfControlPoints": True,
              "labelFormat": "%N-%d", "lastUsedControlPointNumber": len(points),
              "controlPoints": points}
    return {"@schema": MARKUPS_SCHEMA, "markups": [markup]}


def _description(cp: dict) -> dict | None:
    """A control point's segsnake description, or None when it has none."""
    text = cp.get("description")
    if not isinstance(text, str):
        return None
    try:
        d = json.loads(text)
    except json.JSONDecodeError:
        return None
    return d if isinstance(d, dict) and TAG in d else None


def _model_from_markups(doc: Any, path: str) -> SplineSurface:
    """The world snake a markups document of :func:`snake_markups` (perhaps edited) describes."""
    points, cps = document_points(doc, path)
    descs = [_description(cp) for cp in cps]
    first = next((d for d in descs if d is not None), None)
    if first is None:
        raise InputError(f"{path}: not a segsnake snake: its control points carry no segsnake "
                         f"description (segsnake export-points writes them; a markups file of "
                         f"clicks goes to --center, --seed-point or --axis-start)")
    kind, m1, m2 = first.get("kind"), first.get("m1"), first.get("m2")
    sizes_ok = all(isinstance(m, int) and not isinstance(m, bool) and M_MIN <= m <= M_MAX
                   for m in (m1, m2))
    if kind not in _KINDS or not sizes_ok:
        raise InputError(f"{path}: not a segsnake snake (kind {kind!r}, M1 {m1!r}, M2 {m2!r}; "
                         f"expected sphere or cylinder, M between {M_MIN} and {M_MAX})")
    template = _KINDS[kind].unit(m1, m2)
    rows = dict(_position_rows(kind, template.m1, template.m2))
    if len(points) != len(rows):
        raise InputError(f"{path}: holds {len(points)} control points, but a {kind} snake with "
                         f"M1={template.m1}, M2={template.m2} has {len(rows)} (were points added "
                         f"or deleted?)")
    params = np.full((template.n_params, 3), np.nan)
    poles: dict[str, dict] = {}
    for p, cp, d in zip(points, cps, descs):
        label = cp.get("label", "?")
        if d is None:
            raise InputError(f"{path}: control point {label!r} carries no segsnake description "
                             f"(a point added by hand?)")
        if (d.get("kind"), d.get("m1"), d.get("m2")) != (kind, m1, m2):
            raise InputError(f"{path}: control point {label!r} belongs to another snake "
                             f"({d.get('kind')} {d.get('m1')} x {d.get('m2')})")
        row = d.get("row")
        if not isinstance(row, int) or row not in rows or not np.isnan(params[row, 0]):
            raise InputError(f"{path}: control point {label!r}: row {row!r} is not a free point "
                             f"of this snake or is given twice")
        params[row] = p
        if kind == "sphere" and rows[row] in ("north", "south"):
            poles[rows[row]] = d
    if kind == "sphere":
        base = template.m1 * (template.m2 - 1)
        for pole, centre, slot in (("north", base, base + 2), ("south", base + 1, base + 4)):
            d = poles[pole]
            coef = np.asarray(d.get("tangents", []), dtype=np.float64)
            if coef.shape != (2, 3) or not np.all(np.isfinite(coef)) or \
                    d.get("tangent_frame_rows") != _frame_rows(template.m1, template.m2, pole):
                raise InputError(f"{path}: the {pole} pole's description lacks its tangents")
            E = (params[_frame_rows(template.m1, template.m2, pole)] - params[centre]).T
            params[slot:slot + 2] = coef @ E.T
    return template.with_params(params)


# ------------------------------------------------------------------------------ files
def read_model(path: str, what: str = "file") -> SplineSurface:
    """A saved model as it is stored (``snake.json``, a ``segsnake shape`` reference, a shape
    model's mean), or InputError naming the file (``what`` names it when it is missing)."""
    from segsnake.surfaces import load_model

    try:
        return load_model(path)
    except FileNotFoundError:
        raise InputError(f"{path}: no such {what}") from None
    except (OSError, ValueError, KeyError, TypeError, json.JSONDecodeError) as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise InputError(f"{path}: not a readable segsnake model ({msg})") from None


def read_prior(path: str, affine: NDArray, spacing) -> SplineSurface:
    """A ``--prior`` file's reference in an image's scaled index space (mm).

    A file that carries its own image's grid (a ``snake.json``, a fit of a mask) is placed
    through world coordinates (:func:`load_snake`, :func:`image_from_world`): its shape in
    millimetres, and its surface traversed as the start placed from the same file is (a grid
    of the other handedness reverses both alike, so the prior meets its own start point for
    point). Any other saved model (a ``segsnake shape`` reference, a shape model, whose modes
    live in its own frame) is taken as it is stored (:func:`read_model`); the prior's shape
    spaces ignore where it lies.
    """
    doc = read_json(path, "prior file")
    if isinstance(doc, dict) and doc.get("format") in ("segsnake-result", "segsnake-fit") \
            and "affine" in doc:
        return image_from_world(_snake_from_doc(doc, path)[0], affine, spacing)
    return read_model(path, "prior file")


def load_snake(path: str) -> SplineSurface:
    """A saved snake in world RAS mm, from ``snake.json`` or a markups file of ``export-points``
    (:func:`load_snake_and_record` without the record).

    Parameters
    ----------
    path : str
        A ``snake.json`` written by ``segment`` or ``render`` (its model in scaled index space,
        the image's affine and spacing), the output of ``fit`` on a mask (likewise, the mask's
        grid), or a ``.mrk.json`` written by ``export-points`` (possibly moved in Slicer and
        saved again, in LPS or RAS).

    Returns
    -------
    SplineSurface
        The snake in world RAS millimetres.

    Raises
    ------
    InputError
        Missing or unreadable file; neither a segsnake result nor a segsnake markups file; a
        model without an image grid; a markups file whose points were added or deleted, or
        lack the segsnake descriptions. The message starts with the file.
    """
    return load_snake_and_record(path)[0]


def load_snake_and_record(path: str) -> tuple[SplineSurface, dict[str, Any] | None]:
    """:func:`load_snake`, and from the same reading of the file its ``restart`` record: what
    defines the energy its last stage ended in (:func:`segsnake.region_stages.segment_region`), or
    None for a markups file, a fit, a ``render`` output or a result without one."""
    return _snake_from_doc(read_json(path, "snake file"), path)


def _snake_from_doc(doc: Any, path: str) -> tuple[SplineSurface, dict[str, Any] | None]:
    """:func:`load_snake_and_record` of the document already read from ``path``."""
    if isinstance(doc, dict) and "markups" in doc:
        return _model_from_markups(doc, path), None
    fmt = doc.get("format") if isinstance(doc, dict) else None
    if fmt == "segsnake-model":
        raise InputError(f"{path}: a segsnake model without an image grid (no affine); give a "
                         f"snake.json written by segment or render, a fit of a mask, or a "
                         f"markups file written by export-points")
    if fmt == "segsnake-fit" and "affine" not in doc:
        raise InputError(f"{path}: a segsnake fit of a mesh or point cloud, without an image grid "
                         f"(a fit of a mask carries its mask's); give a snake.json written by "
                         f"segment or render, a fit of a mask, or a markups file written by "
                         f"export-points")
    if fmt not in ("segsnake-result", "segsnake-fit"):
        raise InputError(f"{path}: neither a segsnake snake.json nor a segsnake markups file")
    try:
        model = model_from_dict(doc["model"])
        affine = np.asarray(doc["affine"], dtype=np.float64)
        # (a fit of a mask keeps its mask's spacing beside the affine; a result in its summary)
        spacing = np.asarray(doc["spacing_mm"] if fmt == "segsnake-fit"
                             else doc["summary"]["spacing_mm"], dtype=np.float64)
        if affine.shape != (4, 4) or spacing.shape != (3,) or \
                not (np.all(np.isfinite(affine)) and np.all(np.isfinite(spacing))
                     and np.all(spacing > 0)):
            raise ValueError("bad affine or spacing_mm")
        if not math.isfinite(float(np.linalg.cond(affine[:3, :3]))):
            raise ValueError("singular affine")
    except (KeyError, TypeError, ValueError) as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        what = "fit" if fmt == "segsnake-fit" else "result"
        raise InputError(f"{path}: not a readable segsnake {what} ({msg})") from None
    settings = doc.get("settings")
    record = settings.get("restart") if isinstance(settings, dict) else None
    return world_from_image(model, affine, spacing), (record if isinstance(record, dict) else None)
