"""A tube swept by disks along a centreline: the truth of the tube phantoms and its diameter profile.

Definition. Given a centreline ``c(s)`` (``s`` its arc length in mm, ``0 <= s <= L``) and a radius
``r(s)``, the tube is the union of the disks of radius ``r(s)`` centred on ``c(s)`` in the planes
normal to ``c'(s)``, with flat ends. While every radius stays below the centreline's radius of
curvature and distant parts of the tube stay apart, a point belongs to the disk of its nearest
centreline point, so membership is a nearest-point query: with ``s*`` the arc length of the nearest
point and ``rho`` the distance to it, the signed function ``max(rho - r(s*), -s*, s* - L)`` is
negative exactly inside (and about the signed distance in mm near the surface, which is what the
partial-volume images need).

Closed forms that follow (used by the phantoms' records and checked by the tests): the section in
the plane normal to the centreline at ``s`` is the disk of radius ``r(s)`` (area ``pi r(s)^2``, every
diameter ``2 r(s)``), and the volume is ``pi * integral r(s)^2 ds`` (the tube formula: over each
disk the curvature's first-order term integrates to zero).

:meth:`SweptTube.profile` does not use those closed forms: it *measures* the section in the normal
plane from the membership test (rays from the centreline point, each boundary crossing found by
bisection to 1e-6 mm), optionally clipped to the volume's box, so it also holds where the box cuts
a tube that leaves the field of view. Everything here is in mm of scaled index space
(``p = (i sx, j sy, k sz)``), as in :mod:`segsnake.phantoms`.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

__all__ = ["SweptTube"]

#: Rays per section in :meth:`SweptTube.profile` (diameters are measured along 180 directions).
PROFILE_RAYS = 360
#: Bisection steps per ray: the boundary radius to (1.5 r_max) / 2^steps, below 1e-6 mm.
_BISECTIONS = 34


def _unit(v: NDArray) -> NDArray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


class SweptTube:
    """A tube of disks normal to a polyline centreline (see the module docstring).

    Parameters
    ----------
    points : (N, 3) array
        Centreline samples in mm, in order, spaced finely enough that the polyline is the curve
        (the phantoms use 1/4 of the smallest voxel size or less).
    radii : (N,) array
        Radius at each sample, mm (linear in arc length between samples).
    """

    def __init__(self, points: NDArray, radii: NDArray) -> None:
        pts = np.asarray(points, dtype=np.float64)
        rad = np.broadcast_to(np.asarray(radii, dtype=np.float64), (len(pts),)).copy()
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2:
            raise ValueError("points must be an (N >= 2, 3) array")
        if not np.all(rad > 0):
            raise ValueError("radii must be positive")
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        if not np.all(seg > 0):
            raise ValueError("consecutive centreline points must differ")
        self.points = pts
        self.radii = rad
        self.arc = np.concatenate([[0.0], np.cumsum(seg)])
        self.length = float(self.arc[-1])
        self.r_max = float(rad.max())
        # Straight extensions beyond both ends along the end tangents, so that a point beyond a
        # flat end still has a perpendicular foot (with s* < 0 or s* > L) and the end caps are
        # planes, not the half balls a nearest-point rule would give there.
        step = float(seg.min())
        ext = 2.0 * self.r_max + 4.0
        n_ext = int(np.ceil(ext / step))
        t0 = _unit(pts[1] - pts[0])
        t1 = _unit(pts[-1] - pts[-2])
        k = np.arange(n_ext, 0, -1)[:, None] * step
        before = pts[0] - k * t0
        after = pts[-1] + k[::-1] * t1
        self._all = np.concatenate([before, pts, after])
        self._arc_all = np.concatenate([-k[:, 0], self.arc, self.length + k[::-1, 0]])
        self._tree = cKDTree(self._all)

    # ---------------------------------------------------------------------------------------
    # Along the centreline
    # ---------------------------------------------------------------------------------------

    def radius_at(self, s: NDArray | float) -> NDArray:
        """Radius at arc length ``s`` (mm), the end radii beyond the ends."""
        return np.interp(s, self.arc, self.radii)

    def point_at(self, s: NDArray | float) -> NDArray:
        """Centreline point(s) at arc length ``s`` (mm): shape ``(..., 3)``."""
        s = np.asarray(s, dtype=np.float64)
        return np.stack([np.interp(s, self._arc_all, self._all[:, d]) for d in range(3)], axis=-1)

    def tangent_at(self, s: NDArray | float) -> NDArray:
        """Unit tangent(s) at arc length ``s``: the chord over +-0.5 mm (the polyline is fine)."""
        s = np.asarray(s, dtype=np.float64)
        return _unit(self.point_at(s + 0.5) - self.point_at(s - 0.5))

    def area_analytic(self, s: NDArray | float) -> NDArray:
        """The closed form of the normal section's area, ``pi r(s)^2`` (mm^2)."""
        return np.pi * self.radius_at(s) ** 2

    def volume_analytic(self) -> float:
        """``pi * integral r(s)^2 ds`` over the whole tube (mm^3; trapezoid rule on the samples)."""
        r2 = self.radii**2
        return float(np.pi * np.sum(0.5 * (r2[1:] + r2[:-1]) * np.diff(self.arc)))

    # ---------------------------------------------------------------------------------------
    # Membership
    # ---------------------------------------------------------------------------------------

    def nearest(self, p: NDArray, bound: float = np.inf) -> tuple[NDArray, NDArray]:
        """Arc length of the nearest centreline point (extensions included) and the distance.

        Points farther than ``bound`` from every sample get ``s = nan`` and distance ``inf``.
        """
        p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
        s = np.full(len(p), np.nan)
        dist = np.full(len(p), np.inf)
        _, idx = self._tree.query(p, distance_upper_bound=bound)
        hit = idx < len(self._all)
        if not np.any(hit):
            return s, dist
        q = p[hit]
        i = idx[hit]
        best_d = np.full(len(q), np.inf)
        best_s = np.zeros(len(q))
        # The foot lies on one of the two polyline segments at the nearest sample.
        for a in (i - 1, i):
            a = np.clip(a, 0, len(self._all) - 2)
            pa, pb = self._all[a], self._all[a + 1]
            ab = pb - pa
            t = np.clip(np.einsum("ij,ij->i", q - pa, ab) / np.einsum("ij,ij->i", ab, ab), 0, 1)
            foot = pa + t[:, None] * ab
            d = np.linalg.norm(q - foot, axis=1)
            better = d < best_d
            best_d[better] = d[better]
            sa, sb = self._arc_all[a], self._arc_all[a + 1]
            best_s[better] = (sa + t * (sb - sa))[better]
        s[hit] = best_s
        dist[hit] = best_d
        return s, dist

    def signed(self, p: NDArray, cap: float = np.inf) -> NDArray:
        """``max(rho - r(s*), -s*, s* - L)`` at points ``p`` (mm; negative inside), capped at ``cap``.

        Only points within ``r_max + cap`` of the centreline are resolved; the rest get ``cap``.
        """
        p = np.asarray(p, dtype=np.float64)
        shape = p.shape[:-1]
        s, rho = self.nearest(p.reshape(-1, 3), bound=self.r_max + cap)
        out = np.full(len(rho), cap, dtype=np.float64)
        ok = np.isfinite(rho)
        sv = s[ok]
        f = np.maximum(rho[ok] - self.radius_at(sv), np.maximum(-sv, sv - self.length))
        out[ok] = np.minimum(f, cap)
        return out.reshape(shape)

    def signed_grid(self, shape: Sequence[int], spacing: Sequence[float], cap: float) -> NDArray:
        """:meth:`signed` at every voxel centre ``(i sx, j sy, k sz)`` of a grid, capped at ``cap``."""
        sp = np.asarray(spacing, dtype=np.float64)
        F = np.full(tuple(int(n) for n in shape), cap, dtype=np.float64)
        # Only the bounding box of the tube (grown by r_max + cap) needs the nearest-point query.
        grow = self.r_max + cap
        lo = np.maximum(np.floor((self._all.min(axis=0) - grow) / sp).astype(int), 0)
        hi = np.minimum(np.ceil((self._all.max(axis=0) + grow) / sp).astype(int) + 1, F.shape)
        if np.any(hi <= lo):
            return F
        axes = [np.arange(lo[d], hi[d]) * sp[d] for d in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
        F[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = self.signed(grid, cap)
        return F

    def inside(self, p: NDArray, box: tuple[NDArray, NDArray] | None = None) -> NDArray[np.bool_]:
        """Membership of points ``p`` (``signed < 0``), and within ``box = (lo, hi)`` when given."""
        p = np.asarray(p, dtype=np.float64)
        ins = self.signed(p, cap=1.0) < 0
        if box is not None:
            lo, hi = (np.asarray(b, dtype=np.float64) for b in box)
            ins &= np.all((p >= lo) & (p <= hi), axis=-1)
        return ins

    # ---------------------------------------------------------------------------------------
    # Profile
    # ---------------------------------------------------------------------------------------

    def profile(self, s: NDArray | Sequence[float], box: tuple[NDArray, NDArray] | None = None,
                rays: int = PROFILE_RAYS) -> dict[str, NDArray]:
        """The tube's section in the plane normal to the centreline at arc lengths ``s``, measured.

        From the centreline point ``c(s)``, ``rays`` rays in the normal plane; each leaves the
        section once (it is star-shaped about ``c(s)``: a disk, or a disk cut by the box's faces)
        at a radius found by bisection on :meth:`inside`. Area = ``(1/2) sum rho^2 dtheta``;
        the diameter along a direction is ``rho(theta) + rho(theta + pi)``.

        Parameters
        ----------
        s : sequence of floats
            Arc lengths (mm) in ``[0, L]``.
        box : (lo, hi) of 3 floats each, optional
            Clip the section to this box (mm): the volume's extent, for a tube leaving it.
        rays : int
            Number of rays (even).

        Returns
        -------
        dict
            ``s``, ``center`` (n, 3), ``area`` (mm^2), ``equivalent_diameter`` (``2 sqrt(A/pi)``),
            ``min_diameter``, ``max_diameter`` (mm; the extremes over ``rays / 2`` directions of
            the diameter through the centreline point).
        """
        s = np.atleast_1d(np.asarray(s, dtype=np.float64))
        if rays < 8 or rays % 2:
            raise ValueError("rays must be an even number >= 8")
        c = self.point_at(s)
        t = self.tangent_at(s)
        helper = np.eye(3)[np.argmin(np.abs(t), axis=1)]
        u = _unit(np.cross(t, helper))
        v = np.cross(t, u)
        theta = np.arange(rays) * (2.0 * np.pi / rays)
        dirs = (np.cos(theta)[None, :, None] * u[:, None, :]
                + np.sin(theta)[None, :, None] * v[:, None, :])  # (n, rays, 3)
        lo = np.zeros((len(s), rays))
        hi = np.full((len(s), rays), 1.5 * self.r_max + 1.0)
        for _ in range(_BISECTIONS):
            mid = 0.5 * (lo + hi)
            ins = self.inside(c[:, None, :] + mid[..., None] * dirs, box)
            lo = np.where(ins, mid, lo)
            hi = np.where(ins, hi, mid)
        rho = 0.5 * (lo + hi)
        area = 0.5 * np.sum(rho**2, axis=1) * (2.0 * np.pi / rays)
        diam = rho[:, : rays // 2] + rho[:, rays // 2:]
        return {"s": s, "center": c, "area": area,
                "equivalent_diameter": 2.0 * np.sqrt(area / np.pi),
                "min_diameter": diam.min(axis=1), "max_diameter": diam.max(axis=1)}
