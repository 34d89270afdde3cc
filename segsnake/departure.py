"""How far a finer control grid's surface departs from the coarser surface it refines.

Coarse to fine (docs/design.md, "Coarse to fine") keeps a finer grid while it *refines* the
surface: detail that the coarser grid smoothed over is shorter than the coarser grid's control
spacing, and so is the distance by which it moves the surface. A finer grid that leaks through a
gap into a neighbour of the same intensity moves part of the surface much farther than that.
:func:`departure` measures the volume that lies between the two surfaces farther than one control
spacing of the coarser grid from the coarser surface, as a fraction of the coarser volume: zero
(to a voxel or two) for a refinement, a sizeable fraction for a leak, whatever the two enclose in
all (a leak can cost the surface elsewhere as much volume as it gains).
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

from segsnake.surfaces import SplineSurface
from segsnake.window import surface_samples

__all__ = ["control_spacing", "departure"]

#: Surface samples per knot interval in u and v for the distances: a voxel's distance to the
#: coarser surface is the distance to its nearest sample, which exceeds the true one by at most
#: half the samples' spacing (a sixteenth of a knot interval).
SAMPLES_PER_INTERVAL = 8


def control_spacing(model: SplineSurface) -> float:
    """The mean distance between neighbouring control points (mm), ``sqrt(area / (M1 M2))``: the
    side of the surface's mean knot-interval patch."""
    return math.sqrt(model.area(order=4) / (model.m1 * model.m2))


def departure(coarse: SplineSurface, fine: SplineSurface,
              spacing: Sequence[float]) -> float:
    """The volume between ``coarse`` and ``fine`` farther than ``coarse``'s control spacing
    (:func:`control_spacing`) from ``coarse``, over the volume ``coarse`` encloses.

    Both surfaces are closed and in mm of scaled index space (voxel ``i`` at ``i * spacing``);
    the volume between them is counted in the voxels whose centres lie inside one of them and
    not the other, on the grid of ``spacing`` (the image's own voxel centres, wherever the
    surfaces are). When each surface's samples lie within the spacing of the other surface's,
    nothing is rasterized and the departure is 0: two closed surfaces that near enclose no voxel
    farther apart, but in a pocket of the coarser surface whose mouth is narrower than twice the
    spacing (a refinement, the common case, costs only the distances of the samples).
    """
    sp = np.asarray(spacing, dtype=np.float64)
    reach = control_spacing(coarse)
    near = surface_samples(coarse, SAMPLES_PER_INTERVAL)
    far = surface_samples(fine, SAMPLES_PER_INTERVAL)
    tree = cKDTree(near)
    if _within(tree, far, reach) and _within(cKDTree(far), near, reach):
        return 0.0
    from segsnake.rasterize import rasterize

    both = np.concatenate([near, far])
    lo = np.floor(both.min(axis=0) / sp).astype(np.int64)
    shape = tuple(int(n) for n in np.ceil(both.max(axis=0) / sp).astype(np.int64) - lo + 1)
    shift = -lo * sp  # (the box's first voxel centre to 0)
    between = rasterize(coarse.transformed(np.eye(3), shift), shape, sp) \
        ^ rasterize(fine.transformed(np.eye(3), shift), shape, sp)
    points = np.argwhere(between) * sp - shift
    beyond = np.count_nonzero(~_near(tree, points, reach))
    return float(beyond * np.prod(sp) / abs(coarse.volume(order=4)))


def _near(tree: cKDTree, points, reach: float):
    """Which of ``points`` lie within ``reach`` of one of the tree's."""
    return np.isfinite(tree.query(points, distance_upper_bound=reach)[0])


def _within(tree: cKDTree, points, reach: float) -> bool:
    return bool(_near(tree, points, reach).all())
