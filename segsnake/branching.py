"""Where a tube branches: a single cylinder ends there.

A tube snake has one lumen in every cross-section. Where its structure divides (an airway at its
carina, an artery at a bifurcation) no single tube fits the image: past the division its rings
span both branches and the wall between them, and the region energy keeps rewarding the branches'
lumen, so the end creeps on down them for as long as the iterations last (measured on the
lung2 trachea: every stage stopped by the iteration cap, 4 slices of both main bronchi in the
result). The division shows in the image itself: a cross-section of the tube in which what
looks like the click falls apart into two sizeable pieces.

:func:`find_cuts` walks the tube's cross-sections from its middle towards each end. A section is
the disk of the ring's radius about the ring's centre, across the tube's tangent, sampled in the
smoothed image; its *lumen pieces* are the connected components of the points the click's band
calls inside (:func:`segsnake.region.region_density` < 0). A section *branches* when its second
piece holds at least ``branch_fraction`` of the tube's lumen (the median of the largest pieces of
the sections before it): both branches of a division are of the trunk's order of size, while a
noise speck beside a tapering end is not (the S6 phantom's end at 0.6 x 0.6 x 2.5 mm: pieces of
20 and 12 mm^2 where the lumen is 51). The first branching section is the cut: beyond its plane,
within ``cut_radii`` lumen radii (of a disk of the lumen's area) of its centre, the density is that beyond the field of view
(:class:`Cut`), so the tube's end is drawn back to the plane as to a face of the volume (both
constants are :class:`segsnake.region.RegionParams`').
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from segsnake.profile import ring_centroids
from segsnake.region import IntensityModel, RegionParams, region_density
from segsnake.surfaces import CylinderModel

__all__ = ["Cut", "find_cuts", "section_pieces"]


@dataclass(frozen=True)
class Cut:
    """Beyond the plane through ``centre`` with the outward normal ``normal`` and within ``radius``
    of ``centre`` (mm of scaled index space), the tube's density is that beyond the field of view."""

    centre: tuple[float, float, float]
    normal: tuple[float, float, float]
    radius: float

    def apply(self, out: NDArray, lo: Sequence[int], spacing: Sequence[float],
              value: float) -> None:
        """Set ``out`` (a window whose first voxel is the volume's ``lo``) to ``value`` in the cut."""
        sp = np.asarray(spacing, dtype=float)
        c, n = np.asarray(self.centre), np.asarray(self.normal)
        first = np.maximum(np.floor((c - self.radius) / sp).astype(int) - np.asarray(lo), 0)
        last = np.minimum(np.ceil((c + self.radius) / sp).astype(int) - np.asarray(lo) + 1,
                          out.shape)
        if np.any(last <= first):
            return
        axes = [(np.arange(a, b) + o) * h - x
                for a, b, o, h, x in zip(first, last, lo, sp, c)]
        dx, dy, dz = np.meshgrid(*axes, indexing="ij", sparse=True)
        cut = (dx * n[0] + dy * n[1] + dz * n[2] > 0) & \
            (dx * dx + dy * dy + dz * dz <= self.radius ** 2)
        out[tuple(slice(a, b) for a, b in zip(first, last))][cut] = value

    def to_dict(self) -> dict:
        return {"centre": list(self.centre), "normal": list(self.normal), "radius": self.radius}

    @classmethod
    def from_dict(cls, d: dict) -> "Cut":
        return cls(tuple(map(float, d["centre"])), tuple(map(float, d["normal"])),
                   float(d["radius"]))


def section_pieces(image_s: NDArray, spacing: Sequence[float], intensity: IntensityModel,
                   centre: NDArray, tangent: NDArray, radius: float) -> NDArray:
    """Areas (mm^2, largest first) of the lumen pieces of one cross-section: the connected
    components of the disk of ``radius`` about ``centre`` across ``tangent`` where the click's
    band calls the smoothed image inside; sampled at half the finest voxel size."""
    sp = np.asarray(spacing, dtype=float)
    t = tangent / np.linalg.norm(tangent)
    a = np.cross(t, np.eye(3)[int(np.argmin(np.abs(t)))])
    a /= np.linalg.norm(a)
    b = np.cross(t, a)
    h = 0.5 * float(sp.min())
    n = int(np.ceil(radius / h))
    g = np.arange(-n, n + 1) * h
    U, V = np.meshgrid(g, g, indexing="ij")
    points = centre + U[..., None] * a + V[..., None] * b
    values = ndimage.map_coordinates(image_s, (points / sp).reshape(-1, 3).T, order=1,
                                     mode="nearest").reshape(U.shape)
    inside = (region_density(values[None].astype(np.float32), intensity)[0] < 0) & \
        (U * U + V * V <= radius * radius)
    labels, count = ndimage.label(inside)
    return np.sort(np.bincount(labels.ravel(), minlength=count + 1)[1:])[::-1] * h * h


def find_cuts(model: CylinderModel, image_s: NDArray, spacing: Sequence[float],
              intensity: IntensityModel,
              branch_fraction: float = RegionParams.branch_fraction,
              cut_radii: float = RegionParams.cut_radii,
              step_mm: float | None = None) -> dict[int, Cut]:
    """The cut at each end of the tube that reached a division (``0``: the end ``v = 0``, ``1``:
    ``v = 1``).

    Walking from the middle (``v = 1/2``) towards each end, the tube's *lumen* is the median of
    the largest pieces of the sections walked, from the first that is one piece (its second, if
    any, below ``branch_fraction`` of its largest); sections with no piece are passed over. The
    division is the first section after that whose second piece holds ``branch_fraction`` of
    the lumen.

    Parameters
    ----------
    model : CylinderModel
        The tube (mm of scaled index space).
    image_s : ndarray
        The image smoothed as the intensity model reads it.
    spacing : (3,) float
        Voxel size (mm).
    intensity : IntensityModel
        The click's: what it calls inside.
    branch_fraction : float
        A section branches when its second lumen piece holds this fraction of the lumen.
    cut_radii : float
        The cut's reach beyond its plane, in radii of the lumen (of a disk of its area).
    step_mm : float, optional
        Sections every this many mm of the centerline (default: half the finest voxel size:
        just past a division the branches are a second piece over a fraction of a mm only).
    """
    sp = np.asarray(spacing, dtype=float)
    step = 0.5 * float(sp.min()) if step_mm is None else float(step_mm)
    # the centerline's arc length on a fine grid, to step along it evenly
    v = np.linspace(0.0, 1.0, 64 * model.m2 + 1)
    c, _ = ring_centroids(model, v)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(c, axis=0), axis=1))])
    nu = 4 * model.m1
    cuts: dict[int, Cut] = {}
    for end, target in ((0, 0.0), (1, arc[-1])):
        s = np.arange(arc[-1] / 2, target, step if end else -step)
        vs = np.interp(s, arc, v)
        rings = model.grid_basis((np.arange(nu) + 0.5) / nu, vs).positions(
            model.control_points())  # (nu, n, 3)
        centres, tangents = ring_centroids(model, vs)
        radii = np.linalg.norm(rings - centres[None], axis=2).max(axis=0)
        lumen: list[float] = []
        for centre, tangent, radius in zip(centres, tangents, radii):
            areas = section_pieces(image_s, sp, intensity, centre, tangent, float(radius))
            if not len(areas):
                continue
            if not lumen:
                if len(areas) == 1 or areas[1] < branch_fraction * areas[0]:
                    lumen.append(float(areas[0]))
                continue
            trunk = float(np.median(lumen))
            if len(areas) > 1 and areas[1] >= branch_fraction * trunk:
                out = tangent / np.linalg.norm(tangent) * (1.0 if end else -1.0)
                cuts[end] = Cut(tuple(map(float, centre)), tuple(map(float, out)),
                                cut_radii * float(np.sqrt(trunk / np.pi)))
                break
            lumen.append(float(areas[0]))
    return cuts
