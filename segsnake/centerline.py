"""A cylinder snake along a centerline: a polyline of points along a tube, with its radii.

The ``centerline`` option (``segment --centerline FILE``, read by
:mod:`segsnake.centerline_files`) ends up here as rows ``[x, y, z]`` or ``[x, y, z, radius]`` in
the units of the other position options: voxel indices (radii in voxels across the tube), or
world millimetres with ``world`` (radii in mm). :func:`centerline_mm` converts them to the
snake's coordinates (mm of scaled index space) and checks them; :func:`centerline_model` builds
the initial snake with :meth:`segsnake.surfaces.CylinderModel.from_centerline`, M2 by
:func:`segsnake.surfaces.axial_rings` (two rings per diameter) unless ``m2`` is given.
Pure: arrays and options in, a model out.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from segsnake.errors import ConfigError
from segsnake.surfaces import CylinderModel

__all__ = ["polyline_problem", "centerline_mm", "centerline_model"]


def polyline_problem(points: ArrayLike, radii: ArrayLike | None = None) -> str | None:
    """What makes ``points`` (and ``radii``) unusable as a centerline, or None.

    Parameters
    ----------
    points : array_like, shape (N, 3)
    radii : array_like, shape (N,), optional

    Returns
    -------
    str or None
        The first problem, in words (points counted from 1): fewer than 2 points, a point or a
        radius that is not a finite number, two consecutive equal points, a radius <= 0.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        return "the points must be rows of 3 coordinates x, y, z"
    if len(pts) < 2:
        return f"a centerline needs at least 2 points, got {len(pts)}"
    bad = ~np.all(np.isfinite(pts), axis=1)
    if bad.any():
        return f"point {int(np.argmax(bad)) + 1} is not 3 finite numbers"
    same = np.all(pts[1:] == pts[:-1], axis=1)
    if same.any():
        k = int(np.argmax(same)) + 1
        return f"points {k} and {k + 1} are the same point (give each point once)"
    if radii is not None:
        r = np.asarray(radii, dtype=np.float64).reshape(-1)
        if len(r) != len(pts):
            return f"{len(r)} radii for {len(pts)} points"
        bad = ~(np.isfinite(r) & (r > 0))
        if bad.any():
            k = int(np.argmax(bad))
            return f"the radius of point {k + 1} must be a number > 0, got {r[k]:g}"
    return None


def _tangents(points: NDArray) -> NDArray:
    """Unit tangents of a polyline at its points (central differences, one-sided at the ends)."""
    d = np.gradient(points, axis=0)
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)


def centerline_mm(rows: ArrayLike, spacing: Sequence[float], shape: Sequence[int], *,
                  world: bool = False, radius: float | None = None,
                  index_from_world: Callable[[NDArray], NDArray] | None = None
                  ) -> tuple[NDArray, NDArray]:
    """The centerline's points and radii in mm of scaled index space.

    Parameters
    ----------
    rows : array_like, shape (N, 3) or (N, 4)
        Points ``x, y, z`` (voxel indices, or world mm with ``world``), optionally a radius each.
    spacing : 3 floats
        Voxel size (mm).
    shape : 3 ints
        The image's shape: every point must lie in it (within half a voxel of its outer centres,
        as the other positions).
    world : bool
        Points in world mm (``index_from_world`` converts them) and radii in mm; else voxel
        indices and radii in voxels, converted with the voxel size across the tube at each point
        (:func:`segsnake.pipeline.perpendicular_spacing`, as ``--radius`` for an axis).
    radius : float, optional
        The radius of every point when ``rows`` has no radius column (same units).
    index_from_world : callable, optional
        World mm (N, 3) -> voxel indices (N, 3); needed with ``world``.

    Returns
    -------
    (ndarray (N, 3), ndarray (N,))
        Points and radii in mm.

    Raises
    ------
    ConfigError
        An unusable polyline (:func:`polyline_problem`), a point outside the volume, no radius
        at all, or radii given twice (a radius column and ``radius``).
    """
    from segsnake.pipeline import perpendicular_spacing

    arr = np.asarray(rows, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] not in (3, 4):
        raise ConfigError("centerline: rows must be [x, y, z] or [x, y, z, radius]")
    pts, radii = arr[:, :3], (arr[:, 3] if arr.shape[1] == 4 else None)
    problem = polyline_problem(pts, radii)
    if problem is not None:
        raise ConfigError(f"centerline: {problem}")
    if radii is not None and radius is not None:
        raise ConfigError("centerline: has a radius for each point and --radius is given too; "
                          "give one of them")
    if radii is None:
        if radius is None:
            raise ConfigError("centerline: has no radii; give --radius (the tube's radius, "
                              "voxels across it or mm with --world)")
        radii = np.full(len(pts), float(radius))
    sp = np.asarray(spacing, dtype=np.float64)
    if world:
        if index_from_world is None:
            raise ConfigError("--world needs an image with an affine")
        index = index_from_world(pts)
    else:
        index = pts
    mm = index * sp
    ext = (np.asarray(shape) - 1) * sp
    outside = np.any((mm < -0.5 * sp) | (mm > ext + 0.5 * sp), axis=1)
    if outside.any():
        k = int(np.argmax(outside))
        raise ConfigError(f"centerline: point {k + 1} {[float(x) for x in pts[k]]} lies outside "
                          f"the volume (shape {tuple(int(n) for n in shape)})")
    if not world:
        radii = radii * np.array([perpendicular_spacing(sp, t) for t in _tangents(mm)])
    return mm, radii


def centerline_model(config, spacing: Sequence[float], shape: Sequence[int],
                     index_from_world: Callable[[NDArray], NDArray] | None = None
                     ) -> CylinderModel:
    """The initial cylinder of a ``segment`` run with a centerline (mm of scaled index space).

    Parameters
    ----------
    config : SegmentConfig
        ``centerline`` as rows (not a file: :func:`segsnake.centerline_files.resolve_centerline`
        reads it), ``world``, ``radius``, ``m1``, ``m2`` (default: two rings per diameter,
        :func:`segsnake.surfaces.axial_rings`).
    spacing, shape, index_from_world
        As for :func:`centerline_mm`.
    """
    if isinstance(config.centerline, str):
        raise ConfigError(f"{config.centerline}: the centerline file was not read")
    pts, radii = centerline_mm(config.centerline, spacing, shape, world=config.world,
                               radius=config.radius, index_from_world=index_from_world)
    sizes = {"m1": config.m1} if config.m1 is not None else {}
    return CylinderModel.from_centerline(pts, radii, m2=config.m2, **sizes)
