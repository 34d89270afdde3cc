"""Binary masks from closed spline surfaces, on the input's voxel grid.

A voxel is inside when its centre is inside the closed surface. The surface is tessellated
finely (so the polygon error is far below a voxel) and scan-converted along the last axis:
every voxel column ``(i, j)`` is a ray, each triangle whose projection on the first two axes
holds the ray's foot crosses it once, and a voxel centre is inside when an odd number of
crossings lie below it (the even-odd rule of VTK's ``vtkPolyDataToImageStencil``, which this
replaced: the same masks without importing VTK, whose 60 MB of libraries were a large share of a
run's peak memory, issue 18).

Rays that meet an edge or a vertex exactly are counted once: a triangle's projection holds the
points strictly inside it and those of its edges that satisfy a half-plane rule on the edge's
direction (the "top-left" rule of GPU rasterizers), with the edge's test computed from its two
vertices in a fixed order, so the two triangles that share an edge decide the same point the
same way to the last bit. The cylinder is closed by planar caps through its end rings. The same
scan gives the mesh's winding numbers (:func:`windings`), whether it crosses itself. The loops
are compiled (``segsnake/_scan.c``).
"""

from __future__ import annotations

from functools import cached_property
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from segsnake.surfaces import SplineSurface

__all__ = ["rasterize", "mesh_for_mask", "scan_convert", "windings", "crossing_volume",
           "SelfCrossing"]

#: Triangles per batch of :func:`scan_convert`: their vertex coordinates, the compiled scan's
#: input, take 72 bytes a triangle (9 MB a batch; a brain's mask mesh has 660 000 triangles).
BATCH_TRIANGLES = 1 << 17


def mesh_for_mask(model: SplineSurface, spacing: Sequence[float]) -> tuple[NDArray, NDArray]:
    """A closed triangle mesh of ``model`` whose chords deviate from it by well under a voxel:
    points ``(n, 3)`` (mm) and triangles ``(f, 3)``.

    The sampling per control interval grows with the interval length in voxels: with chords of
    at most ~1/2 voxel, the sagitta error is below 1/100 voxel for any curvature a snake with
    these control points can carry.
    """
    C = model.control_points()
    step = float(min(spacing))
    du = np.linalg.norm(np.diff(C, axis=0), axis=-1).max() / step  # voxels per u interval
    dv = np.linalg.norm(np.diff(C, axis=1), axis=-1).max() / step
    per_u = int(np.clip(np.ceil(2 * du), 4, 64))
    per_v = int(np.clip(np.ceil(2 * dv), 4, 64))
    return model.triangles(per_u * model.m1, per_v * model.m2, caps=True)


#: Vertices per control interval of the mesh :func:`crossing_volume` measures: its chords are a
#: third of an interval (its cost then does not depend on the surface's size).
CROSSING_PER_INTERVAL = 3


def crossing_volume(model: SplineSurface) -> float:
    """The volume (mm^3) the closed surface (a cylinder with its caps) wraps other than once or
    not at all, each part weighted by how many times too many: ``integral |k - clip(k, 0, 1)|
    dx``, ``k`` the winding number; 0 for an embedded surface (:class:`SelfCrossing`)."""
    return SelfCrossing(model).volume


#: How far off the surface :meth:`SelfCrossing.outside_windings` reads the winding number, in
#: units of the rays' spacing ``h``: beyond the mesh's sagitta (its chords, about 2 h long, cut
#: the surface by about ``h^2 / 2R`` where its radius of curvature is R: below h / 4 wherever
#: R > 2 h).
OFFSET_PER_SPACING = 0.25
#: How far beyond the box of the rays' over-wound stretches :meth:`SelfCrossing.outside_windings`
#: looks, in ray spacings. (4 drops none of the nodes below, but moved the leaked thalamus'
#: path off its failure warning and left a 1 mm arch with a profile row 79 % off; not kept
#: until that is understood: docs/benchmarks.md, session 14.)
BOX_MARGIN = 1.5


class SelfCrossing:
    """Where a closed surface (a cylinder with its caps) crosses itself, measured on a mesh with
    :data:`CROSSING_PER_INTERVAL` vertices per control interval.

    ``volume``: ``integral |k - clip(k, 0, 1)| dx`` (mm^3), ``k`` the winding number, summed
    along rays parallel to the last axis (:func:`windings`) half the mesh's mean chord ``h``
    apart, each standing for ``h^2`` of area: a crossing narrower than that may be missed until
    it grows to it. ``box``: the bounds ``(lo, hi)`` (mm) of the rays' stretches wound other
    than 0 or 1 times (None when there are none).
    """

    def __init__(self, model: SplineSurface) -> None:
        from segsnake._scan import edge_lengths, windings as kernel

        # (the gathers and shifts below are compiled: in numpy they took 1.5 ms of a 21 x 21
        # surface's 2.5, a tenth of a brain's run; the same numbers to the bit)
        n = CROSSING_PER_INTERVAL
        points, tris = model.triangles(n * model.m1, n * model.m2)
        points = np.ascontiguousarray(points, dtype=np.float64)
        self._points, self._tris = points, np.ascontiguousarray(tris, dtype=np.int64)
        lengths = np.empty(self._tris.shape)
        edge_lengths(points, self._tris, lengths)
        self.h = 0.5 * float(lengths.mean())
        rays, origin = _on_rays(points, self._tris, self.h)
        excess, box = kernel(rays)[2:]
        self.volume = excess * self.h ** 3
        self.box = None
        if excess > 0:
            box = np.asarray(box).reshape(3, 2).T + origin
            self.box = (box[0] * self.h, box[1] * self.h)

    @cached_property
    def corners(self) -> NDArray:
        """The mesh's triangles' vertex coordinates ``(f, 3, 3)`` in units of ``h``."""
        return self._points[self._tris] / self.h

    def outside_windings(self, points: NDArray, normals: NDArray) -> NDArray:
        """The winding number just outside each surface point: about ``points +
        OFFSET_PER_SPACING h normals / |normals|`` (``points``, ``normals`` ``(n, 3)``, mm;
        ``normals`` outward). 0 everywhere on an embedded surface; where the surface runs inside
        another part of itself, 1 or more (or -1 or less where it runs through a part turned
        inside out). Such a point borders a region wound other than 0 or 1 times, so only the
        points within :attr:`box` grown by :data:`BOX_MARGIN` ray spacings are computed: the
        box holds the rays' stretches, and a tilted or thin part of the region reaches past the
        nearest ray (measured on touching, rotated hairpin legs: 45 of 2972 such nodes lay more
        than 1.5 spacings beyond the box, 1 more than 2.5, none more than 4); what lies further
        gets no gradient, as a crossing narrower than the spacing is missed by the volume."""
        from segsnake._scan import winding_at

        out = np.zeros(len(points), dtype=np.int64)
        if self.box is None:
            return out
        unit = normals / np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-300)
        queries = points / self.h + OFFSET_PER_SPACING * unit
        lo, hi = self.box[0] / self.h - BOX_MARGIN, self.box[1] / self.h + BOX_MARGIN
        near = np.flatnonzero(np.all((queries >= lo) & (queries <= hi), axis=1))
        found = np.zeros(len(near), dtype=np.int64)
        winding_at(np.ascontiguousarray(self.corners),
                   np.ascontiguousarray(queries[near], dtype=np.float64), found)
        out[near] = found
        return out


def rasterize(model: SplineSurface, shape: Sequence[int], spacing: Sequence[float]) -> NDArray[np.bool_]:
    """Boolean mask of the voxels whose centres lie inside the closed surface.

    Parameters
    ----------
    model : SplineSurface
        Surface in scaled index space (mm): voxel (i, j, k) sits at (i sx, j sy, k sz).
    shape : (nx, ny, nz)
        Grid shape.
    spacing : (sx, sy, sz)
        Voxel size in mm.
    """
    points, tris = mesh_for_mask(model, spacing)
    return scan_convert(points / np.asarray(spacing, dtype=np.float64), tris, shape)


def scan_convert(points: NDArray, tris: NDArray, shape: Sequence[int]) -> NDArray[np.bool_]:
    """The voxels of ``shape`` whose centres (integer coordinates) lie inside a closed mesh.

    Parameters
    ----------
    points : ndarray (n, 3)
        Vertices in voxel index coordinates.
    tris : ndarray (f, 3)
        Vertex ids of the triangles (either orientation: the even-odd rule ignores it).
    shape : (nx, ny, nz)
        Grid shape.
    """
    from segsnake._scan import parity

    nx, ny, nz = (int(n) for n in shape)
    # flips[i, j, k]: the parity of the crossings of ray (i, j) between centres k - 1 and k
    # (k = nz collects those above the grid); its running XOR along k is the mask.
    flips = np.zeros((nx, ny, nz + 1), dtype=np.uint8)
    points = np.asarray(points, dtype=np.float64)
    tris = np.asarray(tris, dtype=np.int64)
    for start in range(0, len(tris), BATCH_TRIANGLES):
        parity(np.ascontiguousarray(points[tris[start:start + BATCH_TRIANGLES]]), (nx, ny, nz),
               flips)
    np.bitwise_xor.accumulate(flips, axis=2, out=flips)
    return flips[:, :, :nz].astype(bool)


def windings(points: NDArray, tris: NDArray) -> tuple[int, int, float]:
    """The least and greatest winding number of a closed, consistently oriented mesh about the
    points of the rays at integer ``(x, y)`` (parallel to the last axis), and the volume it
    wraps other than 0 or 1 times (each part weighted by how many times too many).

    Along a ray, each crossing changes the winding number by one, down where the face's normal
    points along the ray (the ray leaves) and up where it points against it; crossings at one
    height (a ray along a silhouette edge) count as one. An embedded surface with outward faces
    has winding numbers 0 and 1 only; one that crosses itself or turns inside out anywhere has
    a region of -1 or 2 beyond the crossing (two sheets that cross bound regions of windings
    ``w, w + a, w + b, w + a + b``, ``a, b = +-1``, which cannot all be 0 or 1), which every ray
    through that region sees. The volume sums, over the rays, the length of their stretches
    wound beyond 0 or 1 (each ray standing for a unit of area).

    Parameters
    ----------
    points : ndarray (n, 3)
        Vertices, in units of the rays' spacing.
    tris : ndarray (f, 3)
        Vertex ids of the triangles (each in ``[0, n)``), all oriented the same way (outward:
        ``(0, 1, 0.0)`` when embedded; inward: ``(-1, 0, volume)``).
    """
    from segsnake._scan import windings as kernel

    return kernel(_on_rays(np.ascontiguousarray(points, dtype=np.float64),
                           np.ascontiguousarray(tris, dtype=np.int64), 1.0)[0])[:3]


def _on_rays(points: NDArray, tris: NDArray, h: float) -> tuple[NDArray, NDArray]:
    """The triangles' vertex coordinates ``(f, 3, 3)`` in units of ``h``, moved by whole ray
    spacings so that ``x, y >= 0`` (the winding kernel's input; the rays stay at integer
    ``(x, y)``), and the shift ``origin`` (the input is the output plus it). ``points``
    C-contiguous float64 ``(n, 3)``, ``tris`` C-contiguous int64 ``(f, 3)``."""
    from segsnake._scan import on_rays

    rays = np.empty(tris.shape + (3,))
    return rays, np.array([*on_rays(points, tris, h, rays), 0.0])
