"""Where a tube branches: a single cylinder ends there.

A tube snake has one lumen in every cross-section. Where its structure divides (an airway at its
carina, an artery at a bifurcation) no single tube fits the image: past the division its rings
span both branches and the wall between them, and the region energy keeps rewarding the branches'
lumen, so the end creeps on down them for as long as the iterations last (measured on the
lung2 trachea: every stage stopped by the iteration cap, 4 slices of both main bronchi in the
result). The division shows in the image itself: a cross-section of the tube in which what
looks like the click falls apart into two sizeable pieces.

:func:`find_cuts` walks the tube's cross-sections from its middle towards each end, as the
benchmark's trachea reference is tracked slice by slice from the top. A section is the disk of
the ring's radius about the ring's centre, across the tube's tangent, sampled in the smoothed
image; its *lumen pieces* are the connected components of the points the click's band calls
inside (:func:`segsnake.region.region_density` < 0), and those that *continue* the lumen lie
within a step or two of the previous section's lumen (a neighbour that the disk reaches
alongside does not). A section *branches* when its second continuing piece holds at least
``branch_fraction`` of the tube's lumen (the median of the lumen's areas before it): a
division's branches are of the trunk's order of size, a noise speck beside a tapering end is not.
It is a *division* when, over a lumen diameter past it, the tube keeps spanning both branches or
keeps its centre on the wall between them; a tube whose centre enters one branch while the other
leaves its section follows that branch (a centerline drawn from a trunk into one branch). Beyond
the division's plane, within ``cut_radii`` lumen radii of its centre or a lumen radius past the
tube's own reach beyond the plane, whichever is further, the density is that beyond the field of
view (:class:`Cut`), so the tube's end is drawn back to the plane as to a face of the volume (both
constants are :class:`segsnake.region.RegionParams`').
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.spatial import cKDTree

from segsnake.region import IntensityModel, RegionParams, region_density
from segsnake.surfaces import CylinderModel

__all__ = ["Cut", "Section", "find_cuts", "section"]


@dataclass(frozen=True)
class Cut:
    """Beyond the plane through ``centre`` with the outward normal ``normal`` and within ``radius``
    of ``centre`` (mm of scaled index space), the tube's density is that beyond the field of view."""

    centre: tuple[float, float, float]
    normal: tuple[float, float, float]
    radius: float
    #: the tube's lumen radius there (of a disk of its area): how near the plane an end is on it
    lumen_radius: float

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

    def holds(self, point: NDArray) -> bool:
        """Whether a tube's end whose ring is centred at ``point`` ends on the division: within
        a lumen radius of its plane (an end that had crept far past it before it was seen may
        stay there)."""
        offset = np.asarray(point, dtype=float) - np.asarray(self.centre)
        return abs(float(offset @ np.asarray(self.normal))) <= self.lumen_radius

    def to_dict(self) -> dict:
        return {"centre": list(self.centre), "normal": list(self.normal), "radius": self.radius,
                "lumen_radius": self.lumen_radius}

    @classmethod
    def from_dict(cls, d: dict) -> "Cut":
        return cls(tuple(map(float, d["centre"])), tuple(map(float, d["normal"])),
                   float(d["radius"]), float(d["lumen_radius"]))


@dataclass(frozen=True)
class Section:
    """The lumen pieces of one cross-section: each piece's sample points (mm of scaled index
    space, ``(k, 3)``), largest first, sampled ``h`` mm apart."""

    pieces: list[NDArray]
    h: float
    #: whether the section's centre (the tube's) lies in a piece
    centred: bool = False

    @property
    def areas(self) -> NDArray:
        """The pieces' areas (mm^2)."""
        return _areas(self.pieces, self.h)


def _areas(pieces: list[NDArray], h: float) -> NDArray:
    """The areas (mm^2) of pieces sampled ``h`` mm apart."""
    return np.array([len(p) for p in pieces], dtype=float) * h * h


def section(image_s: NDArray, spacing: Sequence[float], intensity: IntensityModel,
            centre: NDArray, tangent: NDArray, radius: float) -> Section:
    """The lumen pieces of one cross-section: the connected components of the disk of ``radius``
    about ``centre`` across ``tangent`` where the click's band calls the smoothed image inside;
    sampled at half the finest voxel size."""
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
    # the points of each piece at once (a noisy section holds many specks): sorted by label
    flat = labels.ravel()
    order = np.argsort(flat, kind="stable")
    sizes = np.bincount(flat, minlength=count + 1)
    pieces = np.split(points.reshape(-1, 3)[order], np.cumsum(sizes)[:-1])[1:]
    return Section(sorted(pieces, key=len, reverse=True), h, bool(labels[n, n] > 0))


def find_cuts(model: CylinderModel, image_s: NDArray, spacing: Sequence[float],
              intensity: IntensityModel,
              branch_fraction: float = RegionParams.branch_fraction,
              cut_radii: float = RegionParams.cut_radii,
              step_mm: float | None = None) -> dict[int, Cut]:
    """The cut at each end of the tube that reached a division (``0``: the end ``v = 0``, ``1``:
    ``v = 1``).

    Walking from the middle (``v = 1/2``) towards each end (see the module's notes), the lumen
    is tracked from the first section that is one piece (its second, if any, below
    ``branch_fraction`` of its largest); sections with no piece continuing it are passed over.

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
        The cut's reach beyond its plane, in radii of the lumen (of a disk of its area); at
        least the tube's own reach beyond the plane plus a lumen radius.
    step_mm : float, optional
        Sections every this many mm of the centerline (default: half the finest voxel size:
        just past a division the branches are a second piece over a fraction of a mm only).
    """
    # (here: every region run imports this module, a sphere's never calls this, and
    # segsnake.profile with its scipy.interpolate is a tube's)
    from segsnake.profile import ring_centroids

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
        lumen: list[float] = []  # the areas of the lumen's piece in the sections walked
        previous = None  # the last section's lumen (its points)
        division = None  # a branching section not yet confirmed: (index, arc length)
        for i, (centre, tangent, radius) in enumerate(zip(centres, tangents, radii)):
            sec = section(image_s, sp, intensity, centre, tangent, float(radius))
            areas = sec.areas
            if previous is None:
                if len(areas) == 1 or (len(areas) and areas[1] < branch_fraction * areas[0]):
                    lumen.append(float(areas[0]))
                    previous = sec.pieces[0]
                continue
            # the pieces that continue the lumen, as the reference's slice-by-slice tracking
            # reads it: a neighbour that the ring's disk reaches alongside does not
            near = cKDTree(previous)
            tol = 2 * step + 2 * sec.h
            on = [p for p in sec.pieces
                  if np.isfinite(near.query(p, distance_upper_bound=tol)[0]).any()]
            if not on:
                continue
            on_areas = _areas(on, sec.h)
            trunk = float(np.median(lumen))
            r = float(np.sqrt(trunk / np.pi))
            branches = len(on) > 1 and on_areas[1] >= branch_fraction * trunk
            if branches and division is None:
                division = (i, abs(s[i] - s[0]))
            elif division is not None and not branches and sec.centred:
                # within a lumen diameter of the division the tube's centre entered one branch
                # and the other left its section: it follows that branch (a centerline drawn
                # from a trunk into one of its branches), no division for this tube
                division = None
            if division is None:
                lumen.append(float(on_areas[0]))
                previous = on[0]
                continue
            # a division while the tube spans both branches, or its centre stays on the wall
            # between them, over a lumen diameter past it
            previous = np.concatenate(on)
            if abs(s[i] - s[0]) - division[1] >= 2 * r:
                break
        if division is not None:
            i = division[0]
            centre, tangent = centres[i], tangents[i]
            out = tangent / np.linalg.norm(tangent) * (1.0 if end else -1.0)
            # (r: the lumen's radius, from the trunk's areas, which stop growing at a division)
            # past the reach of the tube's end beyond the plane (from the division on): a tube
            # that crept on across both branches is drawn back from all of it
            tail = v[v >= vs[i]] if end else v[v <= vs[i]]
            ends = model.grid_basis((np.arange(nu) + 0.5) / nu, tail).positions(
                model.control_points()).reshape(-1, 3)
            beyond = ends[(ends - centre) @ out > 0]
            reach = float(np.linalg.norm(beyond - centre, axis=1).max()) if len(beyond) else 0.0
            cuts[end] = Cut(tuple(map(float, centre)), tuple(map(float, out)),
                            max(cut_radii * r, reach + r), r)
    return cuts
