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
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from segsnake.surfaces import SplineSurface
from segsnake.window import surface_samples

__all__ = ["control_spacing", "departure"]

#: Surface samples per knot interval in u and v (and across a tube's end caps, from their
#: centre to their rim) for the distances: a voxel's distance to the coarser surface is the
#: distance to its nearest sample, too far by at most half a sample cell's diagonal (about a
#: knot interval / 11), and by about ``s^2 / (8 h)`` at the distance ``h`` that counts, ``s``
#: the samples' spacing.
SAMPLES_PER_INTERVAL = 8
#: Voxels whose distances are found at once: bounds the memory of a large leak's count (a
#: 14 x leak of a brain-sized surface is some 20 million voxels).
CHUNK_VOXELS = 1 << 20


def control_spacing(model: SplineSurface) -> float:
    """The mean distance between neighbouring control points (mm), ``sqrt(area / (M1 M2))``: the
    side of the surface's mean knot-interval patch (a tube's lateral surface)."""
    return math.sqrt(model.area(order=4) / (model.m1 * model.m2))


def departure(coarse: SplineSurface, fine: SplineSurface,
              spacing: Sequence[float]) -> float:
    """The volume between ``coarse`` and ``fine`` farther than ``coarse``'s control spacing
    (:func:`control_spacing`) from ``coarse``, over the volume ``coarse`` encloses (``inf`` for
    a surface that encloses none).

    Both surfaces are closed (a tube by its planar end caps, as it is rasterized) and in mm of
    scaled index space (voxel ``i`` at ``i * spacing``); the volume between them is counted in
    the voxels whose centres lie inside one of them and not the other, on the grid of
    ``spacing`` (the image's own voxel centres, wherever the surfaces are). When each surface's
    samples lie within the spacing of the other surface's, nothing is rasterized and the
    departure is 0: two closed surfaces that near enclose no voxel farther apart, but in a
    pocket of the coarser surface whose mouth is narrower than twice the spacing (a refinement,
    the common case, costs only the distances of the samples).
    """
    volume = abs(coarse.volume(order=4))
    if volume == 0:
        return math.inf
    sp = np.asarray(spacing, dtype=np.float64)
    reach = control_spacing(coarse)
    near, far = _samples(coarse), _samples(fine)
    tree = cKDTree(near)
    if _near(tree, far, reach).all() and _near(cKDTree(far), near, reach).all():
        return 0.0
    from segsnake.rasterize import rasterize

    # (a voxel beyond the samples' box on each side: the rasterizer's mesh is not the samples)
    both = np.concatenate([near, far])
    lo = np.floor(both.min(axis=0) / sp).astype(np.int64) - 1
    shape = tuple(int(n) for n in np.ceil(both.max(axis=0) / sp).astype(np.int64) + 1 - lo + 1)
    shift = -lo * sp  # (the box's first voxel centre to 0)
    between = rasterize(coarse.transformed(np.eye(3), shift), shape, sp) \
        ^ rasterize(fine.transformed(np.eye(3), shift), shape, sp)
    beyond = 0
    rows = max(1, CHUNK_VOXELS // (shape[1] * shape[2]))
    for i in range(0, shape[0], rows):
        idx = np.argwhere(between[i:i + rows])
        idx[:, 0] += i
        beyond += int(np.count_nonzero(~_near(tree, (idx + lo) * sp, reach)))
    return float(beyond * np.prod(sp) / volume)


def _samples(model: SplineSurface) -> NDArray:
    """The closed surface's samples ``(n, 3)``: :func:`segsnake.window.surface_samples`, and a
    tube's end caps (each end ring drawn in towards its mean point, the rasterizer's fan)."""
    pts = [surface_samples(model, SAMPLES_PER_INTERVAL)]
    if model.kind == "cylinder":
        t = np.arange(SAMPLES_PER_INTERVAL)[:, None, None] / SAMPLES_PER_INTERVAL
        for ring in model.end_rings(SAMPLES_PER_INTERVAL * model.m1):
            centre = ring.mean(axis=0)
            pts.append((centre + t * (ring - centre)).reshape(-1, 3))
    return np.concatenate(pts)


def _near(tree: cKDTree, points: NDArray, reach: float) -> NDArray[np.bool_]:
    """Which of ``points`` lie within ``reach`` of one of the tree's."""
    return np.isfinite(tree.query(points, distance_upper_bound=reach)[0])
