"""Seeded perturbations of an initialization: the clicks a user would make instead of the ideal one.

An initialization is a dict in the ``segment`` command's terms (voxel indices along the array
axes): ``{"shape": "sphere", "center": [i, j, k], "radii": [ri, rj, rk]}`` or
``{"shape": "cylinder", "axis_start": [...], "axis_end": [...], "radius": r}`` (the cylinder
radius in voxels across the axis, see :func:`segsnake.pipeline.perpendicular_spacing`). Phantoms
suggest one (``Phantom.init``) and the real-data benchmark derives one from its reference masks;
both are derived from the truth, so tests and benchmarks perturb them to start where a user would.

The perturbation (issue 14's definition, the same for every tool that is compared):

- the centre (a cylinder: its axis' midpoint) moves by a vector drawn uniformly from the ball of
  radius ``shift`` x the initial radius (in mm, the sphere's geometric-mean radius);
- the radius is multiplied by a factor drawn uniformly from ``scale``;
- a cylinder's axis turns about its midpoint by an angle drawn uniformly from ``[0, tilt_deg]``
  about a uniformly drawn direction perpendicular to it (its length is kept).
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
from numpy.typing import NDArray

#: Largest centre move, as a fraction of the initial radius (issue 14: "up to half the radius").
SHIFT = 0.5
#: Range of the radius factor (issue 14: "radius x0.6-1.4").
SCALE = (0.6, 1.4)
#: Largest axis tilt of a cylinder, degrees (issue 14: "axis tilted up to 10 degrees").
TILT_DEG = 10.0


def _in_ball(rng: np.random.Generator, radius: float) -> NDArray:
    """A point drawn uniformly from the ball of ``radius`` around the origin."""
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    return d * radius * rng.uniform() ** (1.0 / 3.0)


def _perpendicular_unit(rng: np.random.Generator, axis: NDArray) -> NDArray:
    """A unit vector drawn uniformly from the circle of directions perpendicular to ``axis``."""
    a = axis / np.linalg.norm(axis)
    helper = np.eye(3)[int(np.argmin(np.abs(a)))]
    u = np.cross(a, helper)
    u /= np.linalg.norm(u)
    v = np.cross(a, u)
    t = rng.uniform(0.0, 2.0 * np.pi)
    return np.cos(t) * u + np.sin(t) * v


def _rounded(x: NDArray | float) -> Any:
    return np.round(np.asarray(x, dtype=float), 3).tolist()


def perturb_init(init: dict, spacing: Sequence[float], seed: int, *, shift: float = SHIFT,
                 scale: tuple[float, float] = SCALE, tilt_deg: float = TILT_DEG) -> dict:
    """A seeded random perturbation of ``init`` (see the module docstring).

    Parameters
    ----------
    init : dict
        Sphere or cylinder initialization in voxel indices (the ``segment`` command's terms).
    spacing : sequence of 3 floats
        Voxel size in mm along the array axes: moves and tilts are isotropic in mm.
    seed : int
        Seed of the random generator; the same seed gives the same perturbation.
    shift, scale, tilt_deg : float, (float, float), float
        Largest centre move (fraction of the radius), radius factor range, largest tilt (deg).

    Returns
    -------
    dict
        A new initialization of the same shape, other keys of ``init`` copied unchanged.
    """
    from .pipeline import perpendicular_spacing  # the cylinder radius' voxel convention

    if init.get("world"):
        raise ValueError("perturb_init takes voxel-index initializations, not world ones")
    rng = np.random.default_rng(seed)
    sp = np.asarray(spacing, dtype=np.float64)
    out = dict(init)
    factor = rng.uniform(*scale)
    if init["shape"] == "sphere":
        radii_mm = np.asarray(init["radii"], dtype=np.float64) * sp
        r = float(np.exp(np.mean(np.log(radii_mm))))
        center_mm = np.asarray(init["center"], dtype=np.float64) * sp + _in_ball(rng, shift * r)
        out["center"] = _rounded(center_mm / sp)
        out["radii"] = _rounded(radii_mm * factor / sp)
        return out
    if init["shape"] == "cylinder":
        a0 = np.asarray(init["axis_start"], dtype=np.float64) * sp
        a1 = np.asarray(init["axis_end"], dtype=np.float64) * sp
        axis = a1 - a0
        r = float(init["radius"]) * perpendicular_spacing(sp, axis)
        mid = 0.5 * (a0 + a1) + _in_ball(rng, shift * r)
        angle = np.deg2rad(rng.uniform(0.0, tilt_deg))
        half = 0.5 * np.linalg.norm(axis)
        u = axis / np.linalg.norm(axis)
        w = np.cos(angle) * u + np.sin(angle) * _perpendicular_unit(rng, u)
        b0, b1 = mid - half * w, mid + half * w
        out["axis_start"] = _rounded(b0 / sp)
        out["axis_end"] = _rounded(b1 / sp)
        out["radius"] = round(r * factor / perpendicular_spacing(sp, b1 - b0), 3)
        return out
    raise ValueError(f"unknown initialization shape {init['shape']!r} (expected sphere or cylinder)")
