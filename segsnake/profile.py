"""A tube's profile along its centerline, exact from a cylinder snake's spline (what a vessel or
airway study measures; VMTK's centerline sections).

For a :class:`~segsnake.surfaces.CylinderModel` ``sigma(u, v)`` (in mm: world mm for the outputs),
closed at its ends by planar caps through the end rings as its mask and volume are:

* a **section** at a point ``p`` with unit normal ``T`` is the cut of that closed tube by the
  plane ``(x - p) . T = 0`` around ``p``: the cut of the **stretch** of tube between the last
  ring behind the plane and the first ring ahead of it. A ring ``v = const`` of
  :data:`SECTION_BRACKETS` nodes per knot interval bounds a stretch if it lies wholly on one
  side of the plane (at every line ``u = const`` of the area's rule; an end ring lying in the
  plane bounds one too); between two neighbouring
  bounding rings on opposite sides every line ``u = const`` crosses the plane an odd number of
  times and the cut is closed. Of those stretches (and the open ones of the next item) the
  sample's is the one nearest to its own ``v``. Along a line the plane's distance is a cubic in
  ``v`` on each knot interval: cut at its turning points, every crossing is found, to rounding
  (safeguarded Newton). The section's **area** and **centroid** are its Green integrals in the
  plane (``A = 1/2 int (a db - b da)`` and the first moments, ``a, b`` its coordinates), by
  Stokes' theorem the integrals of ``J = (sigma_u x sigma_v) . T`` (the area form ``da ^ db``
  on the surface) and of ``a J, b J`` over the part of the stretch behind the plane, less the
  Green integrals along the bounding ring behind it: along each line a sum over its crossings
  of those integrals up to the crossing, exact by Gauss-Legendre (:data:`BAND_ORDER` nodes per
  knot interval along ``v``: polynomials there), then :data:`AREA_ORDER` nodes per knot
  interval around (1e-12 or better on the tests' cylinders; where the cut crosses a knot line
  along ``v`` the integrand around is only C1, and where a fold begins only continuous, so the
  rule converges more slowly there). The area counts the plane's region with the number of
  times the cut winds around it, as the mask's and the volume's integrals count a region the
  surface wraps twice or inside out: the simple ring's area where the cut is one ring. The
  **equivalent diameter** is ``2 sqrt(A / pi)``; the **minimum and maximum diameters** are the
  smallest and largest caliper widths of the cut: the width along :data:`CALIPER_DIRECTIONS`
  directions over 180 degrees (every degree), each from the crossings of
  :data:`CALIPER_SAMPLES` lines ``u = const`` per knot interval around; where each line crosses
  once, a curve in ``u`` whose extreme point of a direction and extreme direction are refined
  by a parabola through their neighbours (below 1e-7 of the diameter on circles and on ellipses
  of aspect 2 and 4, ``tests/test_profile.py``), else the samples' extremes (within ``(pi /
  m)^2 / 2`` of the width).
* **Where the plane leaves the tube.** If the sample's stretch reaches an end ring that
  crosses the plane (no ring between lies wholly on one side), the plane may leave the tube
  through that end's cap: near an end whose cap is not normal to the centerline (a tube leaving
  through an oblique face of the volume) the plane crosses the end ring twice, and the section
  is the lateral cut on the arc between those crossings (on each line ``u = const`` the
  crossing nearest to the sample's ``v``; Green's formula along it, Gauss-Legendre,
  :data:`AREA_ORDER` nodes per knot interval of the arc) closed by the chord between them (the
  cap's cut, exact for a planar cap): the section of the closed tube as its mask has it, and as
  a truth clipped to the volume has it. Such rows are **capped** (``TubeProfile.capped``; their
  calipers are the samples' extremes, as the corners would throw a parabola off). A capped cut
  that jumps from one piece of the surface to another between neighbouring ``u`` (a chord
  between neighbouring nodes more than twice the curve's ``|q'| du``), or that does not wind
  around its sample (a plane through the other leg of a bend near its end crosses that end ring
  too), is not a section. The two samples at the centerline's very ends lie on the caps: a cap
  not normal to the centerline cuts their plane through its middle (about half the section,
  jumping with the least tilt), so they are left out rather than reported. A sample whose
  plane has no section (its stretch is bounded by rings on the same side, it crosses the end
  ring other than twice, or no capped cut is a section) is **dropped** (its arc length is kept
  in ``TubeProfile.dropped_mm``). If no sample is left (a tube so short that every plane
  crosses both caps), the rows are the rings projected on the normal planes instead, flagged
  ``TubeProfile.projected``.
* **Where the plane cuts the tube more than once**: the other leg of an arch lies beyond a
  bounding ring and is no part of the section; inside the stretch, where the surface folds over
  itself (a pleat a segmentation leaves on the inner side of a tight bend, every line through it
  crossing the plane three times, on three sheets less than a millimetre apart), the fold's
  pieces count with their winding number (net once where the surface covers the tube three
  times), so the section changes continuously as the plane sweeps over the fold, and no choice
  between the sheets is made that rounding could flip. Both are flagged
  (``TubeProfile.crossed``).
* the **centerline** is the curve of the sections' centroids, found by iteration: start from
  the ring centroids ``c(v) = integral_0^1 sigma(u, v) du`` (exactly the Keys spline in ``v`` of
  each row's mean control point), then repeatedly cut sections normal to the current curve at
  stations every ``min(spacing, length / (4 M2))`` mm and fit a cubic spline by least squares to
  the centroids of the complete sections, at the stations' arc lengths, with the tube's own
  resolution along its length (``M2`` knot intervals over its length, knots at the stations'
  quantiles), until the curve that places the stations (below) moves by no more than
  :data:`CENTERLINE_TOL_MM` at them (at most :data:`CENTERLINE_ITERATIONS` passes; a pass that
  moves it more than the one before ends it, and the better curve is kept). Why not through
  every centroid: the centroids of sections through a fold move by tenths of a millimetre
  within a millimetre (0.25 mm per mm in the bend of issue 16's arch), and a spline through each
  station turned that into 26 degrees between neighbouring samples' normals, their sections
  into 397-482 mm^2 where the tube has 430, and the next pass diverged; the surface itself has
  no detail finer than its knots. A
  centroid more than half its section's radius from its station is not followed (a pinched or
  folded stretch). Beyond the first and last complete sections the curve goes straight on along
  its end tangents to the end caps' planes (a capped section's centroid is off the axis: the cap
  cut part of it). The next pass's stations follow the curve fitted without the sections within
  :data:`END_FIT_RADII` of their radius of the first or last complete one (a slightly tilted
  plane there reaches the cap or a taper, which pulls its centroid and would tilt the curve
  further at each pass); the curve kept, the pass's whose stations moved least, is fitted to
  them all. Why not the ring centroids: a ring's mean point is not its section's centroid where
  the rings tilt (into an oblique face, across a bend) or their points bunch on one side, and a
  ring projected on the plane normal to that curve is not the section; a section's centroid is
  on the axis of any straight tube and on a torus' centre circle. With fewer than
  :data:`MIN_FULL_STATIONS` complete sections the ring centroids are the centerline.
* the profile is sampled every ``spacing_mm`` of the centerline's arc length from its ``v = 0``
  end, plus the far end.

:func:`tube_profile` is the numerical core: a model in, arrays out, nothing read or written.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import CubicSpline, make_lsq_spline

from segsnake.basis import keys
from segsnake.surfaces import CylinderModel, gauss_legendre_grid, orthonormal_pair

__all__ = ["PROFILE_SPACING_MM", "PROFILE_COLUMNS", "TubeProfile", "ring_centroids",
           "even_rings", "tube_profile"]

#: Spacing of the profile's samples along the centerline (mm of arc length).
PROFILE_SPACING_MM = 1.0
#: Gauss-Legendre nodes per knot interval: along a curve for its arc length, around ``u`` for a
#: section's area and centroid (the integrands are smooth inside each knot interval).
ARC_ORDER = 8
AREA_ORDER = 16
#: Caliper widths: section points per knot interval around, directions over 180 degrees.
CALIPER_SAMPLES = 32
CALIPER_DIRECTIONS = 180
#: Rings ``v = const`` per knot interval that may bound a section's stretch of tube; nodes along
#: ``v`` on which a capped section's crossings are bracketed.
SECTION_BRACKETS = 8
#: Gauss-Legendre nodes per knot interval along ``v`` for a section's surface integrals (exact:
#: their integrands are polynomials of degree <= 8 in ``v`` there).
BAND_ORDER = 5
#: Newton steps (bisection when a step leaves the bracket) for a crossing, at most.
CROSSING_ITERATIONS = 60
#: The centerline's iteration: passes at most, the curve's shift at its stations (mm) that ends
#: it, and the Gauss-Legendre nodes per knot interval of its sections (centroids to ~1e-8 of the
#: radius).
CENTERLINE_ITERATIONS = 12
CENTERLINE_TOL_MM = 1e-3
CENTERLINE_ORDER = 8
#: Stations per knot interval along the tube, at least (short tubes), for the centerline.
STATIONS_PER_INTERVAL = 4
#: Lines ``u = const`` per knot interval around whose mean speed along ``v`` spaces a tube's
#: rings (:func:`even_rings`).
RING_SPEED_SAMPLES = 4
#: Complete sections needed for the sections' centerline (else the ring centroids).
MIN_FULL_STATIONS = 4
#: The complete sections within this many of their own radii of the first or last one do not
#: place the next pass's stations: those follow the curve fitted to the sections further in,
#: straight on beyond them. A plane tilted by a few degrees near an end reaches the cap or the
#: tapering stretch before it, which shifts its centroid and tilts the next pass's planes
#: further: the 1 mm arch phantom's curve turned 8 degrees off its leg within 2 mm of the face,
#: and its first row lost a fifth of its area to the cap (docs/benchmarks.md, session 25: at
#: 0.5, 1 and 2 radii its largest diameter error is 1.9, 1.5 and 3.0 %, 7.3 % without).
END_FIT_RADII = 1.0
#: The profile's columns (``profile.csv``'s header, ``snake.json``'s ``profile.columns``).
PROFILE_COLUMNS = ("arc_length_mm", "x_mm", "y_mm", "z_mm", "area_mm2", "equivalent_diameter_mm",
                   "min_diameter_mm", "max_diameter_mm")

_FULL, _CAPPED, _DROPPED = 0, 1, -1


@dataclass(frozen=True)
class TubeProfile:
    """The profile of a tube, one row per sample along its centerline.

    Attributes
    ----------
    arc_mm : ndarray (n,)
        Arc length from the ``v = 0`` end (mm).
    centerline : ndarray (n, 3)
        The sections' centerline (the model's coordinates, mm).
    tangent : ndarray (n, 3)
        Unit tangents of the centerline: the sections' normals.
    area : ndarray (n,)
        Cross-section area (mm^2).
    min_diameter, max_diameter : ndarray (n,)
        Smallest and largest caliper width of the cross-section (mm).
    length_mm : float
        The centerline's length.
    spacing_mm : float
        The sampling step along it.
    capped : ndarray (n,) of bool
        The section is closed by an end cap (its plane leaves the tube through an end ring).
    crossed : ndarray (n,) of bool
        The plane also cuts the tube elsewhere (the other leg of a bend), or a line ``u =
        const`` crosses the section more than once (a fold, counted with its winding number).
    dropped_mm : ndarray (k,)
        Arc lengths of the samples left out: no single section there.
    projected : bool
        No sample had a section (a tube so short that every plane crosses both end caps): the
        rows are the rings projected on the planes normal to the centerline instead.
    """

    arc_mm: NDArray
    centerline: NDArray
    tangent: NDArray
    area: NDArray
    min_diameter: NDArray
    max_diameter: NDArray
    length_mm: float
    spacing_mm: float
    capped: NDArray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    crossed: NDArray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    dropped_mm: NDArray = field(default_factory=lambda: np.zeros(0))
    projected: bool = False

    @property
    def equivalent_diameter(self) -> NDArray:
        """``2 sqrt(A / pi)``: the diameter of the circle of the same area (mm)."""
        return 2.0 * np.sqrt(self.area / np.pi)

    def rows(self) -> NDArray:
        """The table ``(n, 8)`` in the order of :data:`PROFILE_COLUMNS`."""
        return np.column_stack([self.arc_mm, self.centerline, self.area,
                                self.equivalent_diameter, self.min_diameter, self.max_diameter])

    def to_dict(self, decimals: int = 4) -> dict[str, Any]:
        """A compact JSON-able form: spacing, length, columns and rows (rounded to
        ``decimals``), and which rows are capped, which crossed, which arc lengths dropped."""
        return {"spacing_mm": self.spacing_mm, "length_mm": round(self.length_mm, decimals),
                "columns": list(PROFILE_COLUMNS),
                "rows": np.round(self.rows(), decimals).tolist(),
                "capped_rows": np.flatnonzero(self.capped).tolist(),
                "crossed_rows": np.flatnonzero(self.crossed).tolist(),
                "dropped_arc_mm": np.round(self.dropped_mm, decimals).tolist(),
                "projected_rings": self.projected}


def ring_centroids(model: CylinderModel, v: NDArray) -> tuple[NDArray, NDArray]:
    """Centroids ``c(v)`` of the rings ``sigma(., v)`` and their derivatives ``c'(v)``.

    Parameters
    ----------
    model : CylinderModel
    v : ndarray (n,)
        Parameters along the tube.

    Returns
    -------
    (ndarray (n, 3), ndarray (n, 3))
    """
    rows = model.control_points().mean(axis=0)  # (M2 + 3, 3): each row's mean control point
    gb = model.grid_basis([0.0], np.asarray(v, dtype=np.float64))
    return gb.Bv @ rows, gb.dBv @ rows


def even_rings(model: CylinderModel, n: int) -> NDArray:
    """The parameters ``v_0 = 0 < v_1 < ... < v_n = 1`` that cut the tube into ``n`` stretches
    of equal mean length along it: the arc length of ``v`` weighted by ``mean_u |sigma_v(u,
    v)|``, the mean speed of the lines ``u = const`` (the ring centroids' arc length on a tube
    of constant calibre; where it closes to a dome or widens, the lines' own length, so that
    rings are not spared where the calibre changes fast). Evenly spaced parameters if the tube
    has no length.

    Parameters
    ----------
    model : CylinderModel
    n : int
        Stretches, >= 1.

    Returns
    -------
    ndarray (n + 1,)
    """
    u = np.arange(RING_SPEED_SAMPLES * model.m1) / (RING_SPEED_SAMPLES * model.m1)

    def speed(v: NDArray) -> NDArray:
        return np.linalg.norm(model.evaluate(u, np.atleast_1d(v))[2], axis=-1).mean(axis=0)

    knots, table = _arc_along(model, speed)
    even = np.arange(n + 1) / n
    if not table[-1] > 0:
        return even
    v = np.maximum.accumulate(_parameters_at(speed, knots, table, table[-1] * even))
    v[0], v[-1] = 0.0, 1.0
    return v


def _ring_arc(model: CylinderModel) -> tuple[NDArray, NDArray, Speed]:
    """The knots along ``v``, the ring centroids' arc length at them, and its speed."""
    def speed(v: NDArray) -> NDArray:
        return np.linalg.norm(ring_centroids(model, v)[1], axis=-1)

    return (*_arc_along(model, speed), speed)


def _arc_along(model: CylinderModel, speed: Speed) -> tuple[NDArray, NDArray]:
    """The knots along ``v`` and the arc length of ``speed`` from ``v = 0`` at them."""
    knots = np.arange(model.m2 + 1) / model.m2
    return knots, _arc_table(speed, knots)


# --------------------------------------------------------------------------------------------
# Arc length of a curve given its speed
# --------------------------------------------------------------------------------------------

Speed = Callable[[NDArray], NDArray]


def _arc_table(speed: Speed, knots: NDArray) -> NDArray:
    """Arc length at ``knots`` (cumulative from the first): Gauss-Legendre per knot interval."""
    x, w = np.polynomial.legendre.leggauss(ARC_ORDER)
    half = np.diff(knots) / 2.0
    pts = knots[:-1, None] + half[:, None] * (x[None, :] + 1.0)
    per = half * (speed(pts.ravel()).reshape(pts.shape) @ w)
    return np.concatenate([[0.0], np.cumsum(per)])


def _arc_to(speed: Speed, knots: NDArray, table: NDArray, x: NDArray) -> NDArray:
    """Arc length at parameters ``x``: the table at the knot below plus the rest by
    Gauss-Legendre on ``[knot, x]`` (the integrand is smooth there)."""
    gx, gw = np.polynomial.legendre.leggauss(ARC_ORDER)
    b = np.clip(np.searchsorted(knots, x, side="right") - 1, 0, len(knots) - 2)
    lo = knots[b]
    half = (x - lo) / 2.0
    pts = lo[:, None] + half[:, None] * (gx[None, :] + 1.0)
    return table[b] + half * (speed(pts.ravel()).reshape(pts.shape) @ gw)


def _parameters_at(speed: Speed, knots: NDArray, table: NDArray, s: NDArray) -> NDArray:
    """The parameters at which the arc length is ``s`` (Newton from linear interpolation, to
    1e-10 mm)."""
    x = np.interp(s, table, knots)
    for _ in range(20):
        step = (_arc_to(speed, knots, table, x) - s) / np.maximum(speed(x), 1e-300)
        x = np.clip(x - step, knots[0], knots[-1])
        if np.max(np.abs(step * speed(x)), initial=0.0) < 1e-10:
            break
    return x


def _unit(x: NDArray) -> NDArray:
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-300)


def _refined_extreme(values: NDArray, axis: int, largest: bool) -> NDArray:
    """The largest (or smallest) of periodic samples along ``axis``: the vertex of the parabola
    through the extreme sample and its two neighbours."""
    v = np.moveaxis(values, axis, -1)
    v = v if largest else -v
    m = v.shape[-1]
    i = np.argmax(v, axis=-1)[..., None]
    a = np.take_along_axis(v, (i - 1) % m, axis=-1)[..., 0]
    b = np.take_along_axis(v, i, axis=-1)[..., 0]
    c = np.take_along_axis(v, (i + 1) % m, axis=-1)[..., 0]
    curv = a - 2.0 * b + c
    ok = np.abs(curv) > 1e-300
    delta = np.where(ok, np.clip(0.5 * (a - c) / np.where(ok, curv, 1.0), -1.0, 1.0), 0.0)
    top = b - 0.25 * (a - c) * delta
    return top if largest else -top


def _calipers(rings: NDArray, smooth: bool = True) -> tuple[NDArray, NDArray]:
    """Smallest and largest caliper widths of closed planar curves sampled as ``rings (n, m,
    2)``: the support values along :data:`CALIPER_DIRECTIONS` directions over 180 degrees.

    ``smooth``: the curves are smooth, so the extremes are refined by parabolas; a capped
    section has corners where its chord meets its arc, where a parabola would overshoot, so its
    extremes are the samples' (within about ``(pi / m)^2 / 2`` of the width)."""
    theta = np.pi * np.arange(CALIPER_DIRECTIONS) / CALIPER_DIRECTIONS
    d = np.stack([np.cos(theta), np.sin(theta)])  # (2, D)
    proj = rings @ d  # (n, m, D): each direction's support values along each ring
    if not smooth:
        width = proj.max(axis=1) - proj.min(axis=1)
        return width.min(axis=1), width.max(axis=1)
    width = _refined_extreme(proj, 1, True) - _refined_extreme(proj, 1, False)  # (n, D)
    # The width has period pi in theta: the D directions are periodic samples.
    return _refined_extreme(width, 1, False), _refined_extreme(width, 1, True)


# --------------------------------------------------------------------------------------------
# Planar sections of the spline surface
# --------------------------------------------------------------------------------------------


class _Surface:
    """A cylinder snake evaluated at scattered ``(u, v)``: the columns ``R(u) = sum_k
    phi_k(u) c[k, .]`` (the surface restricted to one ``u``, a Keys spline in ``v``) first, then
    ``v``. Scattered points, not a tensor grid, so not through ``grid_basis`` and its cache."""

    def __init__(self, model: CylinderModel) -> None:
        self.model = model
        self.C = model.control_points()  # (M1, L, 3)
        scale = float(np.ptp(self.C.reshape(-1, 3), axis=0).max()) or 1.0
        #: Plane distances below this are zero: a plane through an end ring crosses it there.
        self.zero = 1e-12 * scale
        self.vgrid = np.linspace(0.0, 1.0, SECTION_BRACKETS * model.m2 + 1)
        self.Bgrid = model._basis_v(self.vgrid, 0)  # (G, L)

    def columns(self, u: NDArray) -> tuple[NDArray, NDArray]:
        """``R(u)`` and ``R_u(u)``, each ``(len(u), L, 3)``."""
        m1, n_l = self.C.shape[:2]
        flat = self.C.reshape(m1, n_l * 3)
        uu = np.mod(u, 1.0)
        return ((self.model._basis_u(uu, 0) @ flat).reshape(-1, n_l, 3),
                (self.model._basis_u(uu, 1) @ flat).reshape(-1, n_l, 3))

    def at(self, R: NDArray, Ru: NDArray, v: NDArray, line: NDArray | None = None,
           l0: NDArray | None = None) -> tuple[NDArray, NDArray, NDArray]:
        """sigma, sigma_u, sigma_v at ``(u_i, v_i)`` from the columns of ``u_i`` (``R[i]``, or
        ``R[line[i]]``): the four Keys weights of each ``v`` (rows ``l0 - 1 .. l0 + 2`` of its
        knot interval ``l0``; given, for a ``v`` on the interval's upper knot)."""
        m2 = self.model.m2
        x = m2 * np.asarray(v, dtype=np.float64)
        if l0 is None:
            l0 = np.clip(np.floor(x).astype(int), 0, m2 - 1)
        cols = l0[:, None] + np.arange(4)[None, :]  # array index of l = l0 - 1 + j
        t = x[:, None] - (cols - 1)
        w, dw = keys(t), keys(t, 1) * m2
        rows = (np.arange(len(v)) if line is None else line)[:, None]
        Rn, Run = R[rows, cols], Ru[rows, cols]  # (n, 4, 3)
        return (np.einsum("nj,njd->nd", w, Rn), np.einsum("nj,njd->nd", w, Run),
                np.einsum("nj,njd->nd", dw, Rn))


def _cut(surf: _Surface, u: NDArray, p: NDArray, t: NDArray, v0: NDArray
         ) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray]:
    """Where the planes ``(x - p_i) . t_i = 0`` cut the surface along ``u = u[i, j]``.

    Returns ``v (n, nu)`` (NaN where the line ``u = const`` does not cross the plane within ``0
    <= v <= 1``), ``sigma, sigma_u, sigma_v`` there ``(n, nu, 3)``, and whether any ``u`` of a
    plane crosses it more than once (the crossing nearest to ``v0[i]`` is kept)."""
    n, nu = u.shape
    vg = surf.vgrid
    mid = 0.5 * (vg[:-1] + vg[1:])
    v_out = np.full((n, nu), np.nan)
    pts = np.full((n, nu, 3, 3), np.nan)
    many = np.zeros(n, dtype=bool)
    block = max(1, int(2_000_000 // (nu * len(vg))))
    for a in range(0, n, block):
        b = min(n, a + block)
        R, Ru = surf.columns(u[a:b].ravel())
        pp = np.repeat(p[a:b], nu, axis=0)
        tt = np.repeat(t[a:b], nu, axis=0)
        offset = np.einsum("nd,nd->n", pp, tt)
        f = np.einsum("nld,nd->nl", R, tt) @ surf.Bgrid.T - offset[:, None]  # (m, G)
        f[np.abs(f) <= surf.zero] = 0.0
        br = f[:, :-1] * f[:, 1:] <= 0.0
        starts = br & ~np.pad(br[:, :-1], ((0, 0), (1, 0)))  # separate crossings
        many[a:b] = (starts.sum(axis=1) > 1).reshape(b - a, nu).any(axis=1)
        near = np.where(br, np.abs(mid[None, :] - np.repeat(v0[a:b], nu)[:, None]), np.inf)
        j = np.argmin(near, axis=1)
        rows = np.flatnonzero(br[np.arange(len(j)), j])
        j = j[rows]
        lo, hi = vg[j], vg[j + 1]
        flo, fhi = f[rows, j], f[rows, j + 1]
        den = np.where(fhi == flo, 1.0, fhi - flo)
        v = np.where(flo == 0.0, lo, np.where(fhi == 0.0, hi, lo - flo * (hi - lo) / den))
        R, Ru, tr, off = R[rows], Ru[rows], tt[rows], offset[rows]
        for _ in range(CROSSING_ITERATIONS):
            s, _, s_v = surf.at(R, Ru, v)
            fv = np.einsum("nd,nd->n", s, tr) - off
            slope = np.einsum("nd,nd->n", s_v, tr)
            with np.errstate(divide="ignore", invalid="ignore"):
                newton = v - fv / slope
            # Done: on the plane to rounding, or a Newton step below 1e-14 (of v in [0, 1]).
            active = (np.abs(fv) > 1e-2 * surf.zero) & (hi - lo > 4e-16) & \
                ~(np.abs(newton - v) < 1e-14)
            if not active.any():
                break
            same = np.sign(fv) == np.sign(flo)
            lo = np.where(active & same, v, lo)
            flo = np.where(active & same, fv, flo)
            hi = np.where(active & ~same, v, hi)
            ok = np.isfinite(newton) & (newton > lo) & (newton < hi)
            v = np.where(active, np.where(ok, newton, 0.5 * (lo + hi)), v)
        flat_v = np.full(len(pp), np.nan)
        flat_v[rows] = v
        flat_pts = np.full((len(pp), 3, 3), np.nan)
        flat_pts[rows] = np.stack(surf.at(R, Ru, v), axis=1)
        v_out[a:b] = flat_v.reshape(b - a, nu)
        pts[a:b] = flat_pts.reshape(b - a, nu, 3, 3)
    return v_out, pts[:, :, 0], pts[:, :, 1], pts[:, :, 2], many


def _sign_changes(f: NDArray) -> list[int]:
    """Indices ``i`` of the periodic samples ``f`` after which the sign changes (zeros
    skipped: the change is counted at the last non-zero sample before it)."""
    nz = np.flatnonzero(f)
    if len(nz) == 0:
        return []
    sg = np.sign(f[nz])
    return [int(nz[i - 1]) for i in range(len(nz)) if sg[i] != sg[i - 1]]


def _cap_candidates(surf: _Surface, p: NDArray, t: NDArray, idx: NDArray
                    ) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """The ways the planes ``idx`` may be closed by a cap: for each end ring the plane crosses
    exactly twice, at ``u_1 < u_2``, both arcs ``[u_1, u_2]`` and ``[u_2, u_1 + 1]``.

    Returns the station, the end's ``v`` and the arc ``(u_a, u_b)`` of each candidate. The
    crossings are found on :data:`CALIPER_SAMPLES` ring points per knot interval, then to
    rounding by bisection on the exact ring."""
    model = surf.model
    k = CALIPER_SAMPLES * model.m1
    ud = np.arange(k) / k
    rings = model.evaluate(ud, [0.0, 1.0])[0]  # (k, 2, 3)
    f = np.einsum("ked,nd->nek", rings, t[idx]) - np.einsum("nd,nd->n", p[idx], t[idx])[:, None,
                                                                                          None]
    f[np.abs(f) <= surf.zero] = 0.0
    found = []  # (station, end, bracket start, bracket end) per crossing, in pairs
    for i, station in enumerate(idx):
        for e in (0, 1):
            changes = _sign_changes(f[i, e])
            if len(changes) != 2:
                continue
            for j in changes:
                nxt = np.flatnonzero(np.roll(f[i, e], -(j + 1)))[0] + j + 1  # next non-zero
                found.append((station, e, ud[j], nxt / k))  # nxt / k may pass 1: around
    if not found:
        return np.zeros(0, dtype=int), np.zeros(0), np.zeros(0), np.zeros(0)
    st, ends, lo, hi = (np.array(x) for x in zip(*found))
    pc, tc, ve = p[st], t[st], ends.astype(float)

    def g(u: NDArray) -> NDArray:
        return np.einsum("nd,nd->n", model(np.mod(u, 1.0), ve) - pc, tc)

    glo = g(lo)
    for _ in range(60):  # bisection: the crossings to rounding
        mid = 0.5 * (lo + hi)
        gm = g(mid)
        left = np.sign(gm) == np.sign(glo)
        lo, glo = np.where(left, mid, lo), np.where(left, gm, glo)
        hi = np.where(left, hi, mid)
    cross = np.sort(np.mod(0.5 * (lo + hi), 1.0).reshape(-1, 2), axis=1)
    st, ve = st[::2], ve[::2]
    return (np.concatenate([st, st]), np.concatenate([ve, ve]),
            np.concatenate([cross[:, 0], cross[:, 1]]),
            np.concatenate([cross[:, 1], cross[:, 0] + 1.0]))


def _arc_nodes(m1: int, ua: NDArray, ub: NDArray, order: int) -> tuple[NDArray, NDArray]:
    """Gauss-Legendre nodes and weights on ``[ua, ub]``, ``order`` per piece between the knots
    ``k / M1`` inside (pieces padded to ``M1 + 1`` per arc, empty ones weigh 0)."""
    x, w = np.polynomial.legendre.leggauss(order)
    n = len(ua)
    bounds = np.empty((n, m1 + 2))
    for i in range(n):
        knots = np.arange(np.floor(ua[i] * m1) + 1, np.ceil(ub[i] * m1)) / m1
        inside = np.concatenate([[ua[i]], knots, [ub[i]]])
        bounds[i] = np.concatenate([inside, np.full(m1 + 2 - len(inside), ub[i])])
    lo, half = bounds[:, :-1], np.diff(bounds, axis=1) / 2.0
    nodes = lo[..., None] + half[..., None] * (x + 1.0)
    return nodes.reshape(n, -1), (half[..., None] * w).reshape(n, -1)


def _green(rel: NDArray, dq: NDArray, w: NDArray, e1: NDArray, e2: NDArray
           ) -> tuple[NDArray, NDArray, NDArray]:
    """Signed area and first moments (in the plane's ``e1, e2``) of the curve's Green integrals:
    ``A = 1/2 int (a b' - b a')``, ``M_a = 1/2 int a^2 b'``, ``M_b = -1/2 int b^2 a'``."""
    a, b = np.einsum("nud,nd->nu", rel, e1), np.einsum("nud,nd->nu", rel, e2)
    da, db = np.einsum("nud,nd->nu", dq, e1), np.einsum("nud,nd->nu", dq, e2)
    return (0.5 * np.sum(w * (a * db - b * da), axis=1), 0.5 * np.sum(w * a * a * db, axis=1),
            -0.5 * np.sum(w * b * b * da, axis=1))


def _chord(P: NDArray, Q: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """The same integrals along the segments ``P -> Q`` (plane coordinates ``(n, 2)``), exact."""
    (pa, pb), (qa, qb) = P.T, Q.T
    return (0.5 * (pa * qb - pb * qa), 0.5 * (qb - pb) * (pa * pa + pa * qa + qa * qa) / 3.0,
            -0.5 * (qa - pa) * (pb * pb + pb * qb + qb * qb) / 3.0)


def _broken(s: NDArray, dq: NDArray, u: NDArray, tol: float) -> NDArray:
    """Whether a capped section's arc jumps between two pieces of the surface (a plane that cuts
    the tube more than once, where the crossing nearest to the sample's ``v`` is on one piece for
    some ``u`` and on another for the next): a chord between neighbouring nodes more than twice
    the length ``|q'| du`` the curve would have there."""
    with np.errstate(invalid="ignore"):
        chord = np.linalg.norm(np.diff(s, axis=1), axis=-1)
        speed = np.linalg.norm(dq, axis=-1)
        expect = 0.5 * (speed[:, 1:] + speed[:, :-1]) * np.diff(u, axis=1)
        return np.any(chord > 2.0 * expect + 1e3 * tol, axis=1)


# --------------------------------------------------------------------------------------------
# A section as the cut of the stretch of tube between two rings on either side of its plane
# --------------------------------------------------------------------------------------------

#: The Keys weights of the four control rows ``l0 - 1 .. l0 + 2`` of the knot interval ``l0``
#: as cubics in ``tau = M2 v - l0`` in [0, 1]: ``w_j(tau) = sum_k KEYS_POWER[j, k] tau^k``.
KEYS_POWER = np.array([[0.0, -0.5, 1.0, -0.5], [1.0, 0.0, -2.5, 1.5],
                       [0.0, 0.5, 2.0, -1.5], [0.0, 0.0, -0.5, 0.5]])


@dataclass
class _Bands:
    """Which stretch of the tube each station's section is cut from (see :func:`_bands`)."""

    full: NDArray      # a closed section: between the rings v = lo and v = hi
    lo: NDArray
    hi: NDArray
    side: NDArray      # the sign of (x - p) . t on the ring lo (the ring hi has the other)
    ends: NDArray      # (n, 2): not full, the open stretch reaches the v = 0 / v = 1 end ring
    crossed: NDArray   # the plane crosses more than one stretch of the tube

    def take(self, idx: NDArray) -> "_Bands":
        return _Bands(*(getattr(self, f.name)[idx] for f in fields(self)))


def _bands(surf: _Surface, R: NDArray, p: NDArray, t: NDArray, v0: NDArray) -> _Bands:
    """For each plane ``(x - p_i) . t_i = 0``, the stretch of tube its section is cut from.

    A ring ``v = const`` of the :attr:`_Surface.vgrid` nodes is **one-sided** if it lies wholly
    on one side of the plane (every line of ``R``, the columns ``(nu, L, 3)`` of the lines ``u =
    const``, more than the zero distance from it); an end ring lying in the plane (every line
    within it) bounds a stretch too. Between two neighbouring bounding rings of opposite sides
    the plane's cut is closed (every line crosses it an odd number of times): a **full**
    stretch. Between the end ring and the first bounding ring, where the end ring crosses the
    plane, the cut ends on the end ring: the stretch is **open** at that end (an end cap closes
    the section there). Between two bounding rings on the same side the cut is only pieces of
    surface poking through the plane (no section). The station's stretch is the full or open
    one nearest to ``v0[i]`` in ``v`` (the one holding it if any; a full one on a tie); an open
    one is given by the ends it reaches (both if no ring bounds).
    """
    n, vg = len(p), surf.vgrid
    g_n = len(vg)
    c = np.zeros((n, g_n), dtype=int)
    flat = np.zeros((n, g_n), dtype=bool)
    block = max(1, int(4_000_000 // (len(R) * g_n)))
    for a in range(0, n, block):
        b = min(n, a + block)
        rows = np.einsum("uld,nd->nul", R, t[a:b]) - np.einsum("nd,nd->n", p[a:b],
                                                               t[a:b])[:, None, None]
        f = (rows.reshape(-1, rows.shape[-1]) @ surf.Bgrid.T).reshape(b - a, len(R), g_n)
        fmin, fmax = f.min(axis=1), f.max(axis=1)
        c[a:b] = np.where(fmin > surf.zero, 1, np.where(fmax < -surf.zero, -1, 0))
        flat[a:b] = (fmin >= -surf.zero) & (fmax <= surf.zero)
    bound = c != 0
    bound[:, [0, -1]] |= flat[:, [0, -1]]  # an end ring in the plane
    k = np.arange(g_n)
    # The next bounding ring above each node (g_n: none) and its side.
    at = np.where(bound, k, g_n)
    nxt = np.concatenate([np.minimum.accumulate(at[:, :0:-1], axis=1)[:, ::-1],
                          np.full((n, 1), g_n)], axis=1)
    c_next = np.take_along_axis(c, np.minimum(nxt, g_n - 1), axis=1)
    pair = bound & (nxt < g_n)
    full = pair & ((c * c_next < 0) | ((c == 0) != (c_next == 0)))  # opposite, or a flat end
    crossing = (pair & ((nxt > k + 1) | (c * c_next < 0))).sum(axis=1)
    anyb = bound.any(axis=1)
    first = np.where(anyb, np.argmax(bound, axis=1), g_n - 1)
    last = np.where(anyb, g_n - 1 - np.argmax(bound[:, ::-1], axis=1), 0)
    open0, open1 = ~anyb | (first > 0), ~anyb | (last < g_n - 1)  # the end rings crossing
    crossing += open0.astype(int) + (open1 & anyb)
    # The stretch nearest to v0: how far v0 is from each (0 inside it).
    above = vg[np.minimum(nxt, g_n - 1)]
    dist = np.where(full, np.maximum(np.maximum(vg - v0[:, None], v0[:, None] - above), 0.0),
                    np.inf)
    best = np.argmin(dist, axis=1)
    rows = np.arange(n)
    d0 = np.where(open0, np.maximum(v0 - vg[first], 0.0), np.inf)
    d1 = np.where(open1, np.maximum(vg[last] - v0, 0.0), np.inf)
    is_full = dist[rows, best] <= np.minimum(d0, d1)  # a tie: the full one
    side = np.where(c[rows, best] != 0, c[rows, best], -c_next[rows, best])  # flat lo: far side
    ends = np.column_stack([open0 & (d0 <= d1), open1 & (d1 <= d0)]) & ~is_full[:, None]
    return _Bands(full=is_full, lo=np.where(is_full, vg[best], 0.0),
                  hi=np.where(is_full, above[rows, best], 0.0),
                  side=np.where(is_full, side, 1).astype(float), ends=ends, crossed=crossing > 1)


def _band_pairs(m2: int, lo: NDArray, hi: NDArray, nu: int
                ) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray]:
    """Every (station, line, knot interval) of the stretches ``[lo_i, hi_i]`` along ``nu``
    lines, in that order: station, line, interval ``l`` and its part ``[alpha, beta]`` in the
    stretch."""
    la = np.clip(np.floor(m2 * lo).astype(int), 0, m2 - 1)
    lb = np.maximum(np.clip(np.ceil(m2 * hi).astype(int) - 1, 0, m2 - 1), la)
    span = lb - la + 1
    count = span * nu
    st = np.repeat(np.arange(len(lo)), count)
    k = np.arange(len(st)) - np.repeat(np.cumsum(count) - count, count)
    line, l = k // span[st], la[st] + k % span[st]
    alpha = np.maximum(l / m2, lo[st])
    beta = np.maximum(np.minimum((l + 1) / m2, hi[st]), alpha)
    return st, line, l, alpha, beta


def _band_roots(surf: _Surface, R: NDArray, p: NDArray, t: NDArray, bands: _Bands
                ) -> tuple[tuple[NDArray, ...], tuple[NDArray, ...]]:
    """Every crossing of the lines (columns ``R (nu, L, 3)``) with each plane inside its full
    stretch, exactly: along a line the plane distance is a cubic on each knot interval, cut
    at its turning points into monotone pieces, each piece's sign change solved by safeguarded
    Newton to rounding (no pair of crossings is missed however close). A distance within the
    zero distance counts as on the far side from the ring ``lo``'s, but on the ring ``lo``
    itself (a line touching the plane crosses it twice at one point, or not at all).

    Returns the pairs of :func:`_band_pairs` and, per crossing, ``(pair, v, eps)``: ``eps`` is
    +1 where the line leaves the ring ``lo``'s side going up ``v``, -1 where it comes back."""
    m2 = surf.model.m2
    pairs = _band_pairs(m2, bands.lo, bands.hi, len(R))
    st, line, l, alpha, beta = pairs
    if not len(st):
        return pairs, (np.zeros(0, dtype=int), np.zeros(0), np.zeros(0))
    rows = np.einsum("uld,nd->nul", R, t) - np.einsum("nd,nd->n", p, t)[:, None, None]
    g = rows[st[:, None], line[:, None], l[:, None] + np.arange(4)[None, :]]  # (P, 4)
    c = g @ KEYS_POWER  # the cubic's coefficients in tau
    t_lo, t_hi = m2 * alpha - l, m2 * beta - l
    # Turning points: roots of c1 + 2 c2 tau + 3 c3 tau^2 inside (t_lo, t_hi).
    qa, qb, qc = 3.0 * c[:, 3], 2.0 * c[:, 2], c[:, 1]
    disc = qb * qb - 4.0 * qa * qc
    with np.errstate(divide="ignore", invalid="ignore"):
        q = -0.5 * (qb + np.copysign(np.sqrt(np.maximum(disc, 0.0)), qb))
        turns = np.stack([q / qa, qc / q], axis=1)
    turns[~(disc >= 0.0)] = np.nan
    inside = np.isfinite(turns) & (turns > t_lo[:, None]) & (turns < t_hi[:, None])
    nodes = np.sort(np.column_stack([t_lo, np.where(inside, turns, t_lo[:, None]), t_hi]),
                    axis=1)
    val = ((c[:, 3, None] * nodes + c[:, 2, None]) * nodes + c[:, 1, None]) * nodes + c[:, :1]
    val = np.where(nodes == 0.0, g[:, 1:2], np.where(nodes == 1.0, g[:, 2:3], val))
    val[np.abs(val) <= surf.zero] = 0.0
    side = bands.side[st][:, None]
    sgn = np.where(side * val > 0.0, side, -side)
    # The ring lo itself is on its side: a line that meets the plane there (within the zero
    # distance: an end ring in the plane, a plane touching the ring) crosses it at lo, or not.
    at_lo = (nodes == t_lo[:, None]) & (alpha == bands.lo[st])[:, None]
    sgn = np.where(at_lo, side, sgn)
    pi, k = np.nonzero(sgn[:, :-1] != sgn[:, 1:])
    lo, hi = nodes[pi, k], nodes[pi, k + 1]
    flo, fhi = val[pi, k], val[pi, k + 1]
    cc = c[pi]
    eps = np.where(sgn[pi, k] == side[pi, 0], 1.0, -1.0)
    den = np.where(fhi == flo, 1.0, fhi - flo)
    x = np.where(flo == 0.0, lo, np.where(fhi == 0.0, hi, lo - flo * (hi - lo) / den))
    fixed = (flo == 0.0) | (fhi == 0.0)
    for _ in range(CROSSING_ITERATIONS):
        fx = ((cc[:, 3] * x + cc[:, 2]) * x + cc[:, 1]) * x + cc[:, 0]
        slope = (3.0 * cc[:, 3] * x + 2.0 * cc[:, 2]) * x + cc[:, 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            newton = x - fx / slope
        active = ~fixed & (fx != 0.0) & (hi - lo > 4e-16) & ~(np.abs(newton - x) < 1e-15)
        if not active.any():
            break
        same = np.sign(fx) == np.sign(flo)
        lo, flo = np.where(active & same, x, lo), np.where(active & same, fx, flo)
        hi = np.where(active & ~same, x, hi)
        ok = np.isfinite(newton) & (newton > lo) & (newton < hi)
        x = np.where(active, np.where(ok, newton, 0.5 * (lo + hi)), x)
    return pairs, (pi, (l[pi] + x) / m2, eps)


def _form_integrals(m2: int, R: NDArray, Ru: NDArray, line: NDArray, l: NDArray, x0: NDArray,
                    x1: NDArray, p: NDArray, t: NDArray, e1: NDArray, e2: NDArray) -> NDArray:
    """The integrals ``(N, 3)`` over ``x0 <= v <= x1`` (inside the knot interval ``l``) along the
    lines ``line`` of the 2-forms ``J, a J, b J`` (``J = (sigma_u x sigma_v) . t``, ``a, b`` the
    plane coordinates of ``sigma - p``): over a part of the surface they integrate to the area
    and first moments of its projection on the plane. Gauss-Legendre, :data:`BAND_ORDER` nodes
    (exact: polynomials of degree <= 8 in ``v``)."""
    gx, gw = np.polynomial.legendre.leggauss(BAND_ORDER)
    half = 0.5 * (x1 - x0)
    tau = m2 * (x0[:, None] + half[:, None] * (gx[None, :] + 1.0)) - l[:, None]  # (N, q)
    one = np.ones_like(tau)
    w = np.stack([one, tau, tau * tau, tau * tau * tau], axis=-1) @ KEYS_POWER.T  # (N, q, 4)
    dw = m2 * (np.stack([0 * one, one, 2 * tau, 3 * tau * tau], axis=-1) @ KEYS_POWER.T)
    cols = l[:, None] + np.arange(4)[None, :]
    rows, rows_u = R[line[:, None], cols], Ru[line[:, None], cols]  # (N, 4, 3)
    s = np.einsum("nqj,njd->nqd", w, rows)
    jac = np.einsum("nqd,nd->nq", np.cross(np.einsum("nqj,njd->nqd", w, rows_u),
                                           np.einsum("nqj,njd->nqd", dw, rows)), t)
    rel = s - p[:, None, :]
    forms = np.stack([jac, np.einsum("nqd,nd->nq", rel, e1) * jac,
                      np.einsum("nqd,nd->nq", rel, e2) * jac], axis=-1)
    return half[:, None] * np.einsum("nqk,q->nk", forms, gw)


def _band_moments(surf: _Surface, R: NDArray, Ru: NDArray, w: NDArray, p: NDArray, t: NDArray,
                  bands: _Bands) -> tuple[NDArray, NDArray]:
    """The signed area and first moments ``(n, 3)`` of full sections on the lines with columns
    ``R, Ru`` and weights ``w`` around (see the module's notes), and whether some line crosses
    the section more than once.

    On the surface ``d(1/2 (a db - b da)) = da ^ db = J du dv``: by Stokes' theorem the Green
    integrals along the cut, oriented as the boundary of the part ``S`` of the stretch on the
    ring ``lo``'s side of the plane, are the integrals of ``J, a J, b J`` over ``S`` less the
    Green integrals along the ring ``lo``. Along each line the integral over ``S`` is ``sum_k
    eps_k F(v_k)`` over its crossings, ``F(v)`` the integral from ``lo`` to ``v``
    (Gauss-Legendre, :data:`BAND_ORDER` nodes per knot interval: exact, the forms are
    polynomials of degree <= 8 in ``v`` there). It changes continuously with the plane, also
    where crossings appear or merge in pairs (where the Green integrand along the cut itself is
    singular)."""
    m2, n, nu = surf.model.m2, len(p), len(R)
    e1, e2 = orthonormal_pair(t)
    moments = np.zeros((n, 3))
    many = np.zeros(n, dtype=bool)
    span = np.ceil(m2 * bands.hi) - np.floor(m2 * bands.lo) + 1  # knot intervals, at most
    block = max(1, int(200_000 // (nu * BAND_ORDER * max(float(span.max(initial=1)), 1.0))))
    for a in range(0, n, block):
        b = min(n, a + block)
        (st, line, l, alpha, beta), (pi, vr, eps) = _band_roots(surf, R, p[a:b], t[a:b],
                                                                 bands.take(slice(a, b)))
        sg = a + st

        def integral(x0: NDArray, x1: NDArray, pair: NDArray) -> NDArray:
            k = sg[pair]
            return _form_integrals(m2, R, Ru, line[pair], l[pair], x0, x1, p[k], t[k], e1[k],
                                   e2[k])

        whole = integral(alpha, beta, np.arange(len(st)))  # each pair's part of the stretch
        # F at the start of each pair: its line's earlier pairs (in order along v).
        first = np.concatenate([[True], (st[1:] != st[:-1]) | (line[1:] != line[:-1])])
        start = np.maximum.accumulate(np.where(first, np.arange(len(st)), 0))
        pos = np.arange(len(st)) - start
        before = np.zeros_like(whole)
        for j in range(int(pos.max(initial=0))):
            later = pos > j
            before[later] += whole[start[later] + j]
        f_at = before[pi] + integral(alpha[pi], vr, pi)
        np.add.at(moments, sg[pi], (w[line[pi]] * eps)[:, None] * f_at)
        per_line = np.add.reduceat(np.bincount(pi, minlength=len(st)), np.flatnonzero(first))
        many[sg[first][per_line > 1]] = True
    # Less the Green integrals along the ring lo.
    k = np.repeat(np.arange(n), nu)
    line = np.tile(np.arange(nu), n)
    vlo = bands.lo[k]
    s, su, _ = surf.at(R, Ru, vlo, line)
    ring = _green((s - p[k]).reshape(n, nu, 3), su.reshape(n, nu, 3), np.broadcast_to(w, (n, nu)),
                  e1, e2)
    return moments - np.stack(ring, axis=1), many


def _band_points(surf: _Surface, u: NDArray, p: NDArray, t: NDArray, bands: _Bands
                 ) -> tuple[NDArray, NDArray, NDArray]:
    """The full sections' points on the lines ``u``: ``(station, line, point)`` of every
    crossing, in order of station, line and ``v``."""
    m2 = surf.model.m2
    R, Ru = surf.columns(u)
    span = np.ceil(m2 * bands.hi) - np.floor(m2 * bands.lo) + 1  # knot intervals, at most
    block = max(1, int(500_000 // (len(u) * max(float(span.max(initial=1)), 1.0))))
    out = []
    for a in range(0, len(p), block):
        b = min(len(p), a + block)
        (st, line, l, _, _), (pi, vr, _) = _band_roots(surf, R, p[a:b], t[a:b],
                                                       bands.take(slice(a, b)))
        out.append((a + st[pi], line[pi], surf.at(R, Ru, vr, line[pi], l[pi])[0]))
    return (np.concatenate([o[0] for o in out]), np.concatenate([o[1] for o in out]),
            np.concatenate([o[2] for o in out]))


# --------------------------------------------------------------------------------------------
# The sections
# --------------------------------------------------------------------------------------------


@dataclass
class _Sections:
    status: NDArray
    area: NDArray
    centroid: NDArray
    crossed: NDArray
    min_diameter: NDArray
    max_diameter: NDArray


def _measure_capped(surf: _Surface, p: NDArray, t: NDArray, v0: NDArray, uu: NDArray,
                    ww: NDArray, cap: tuple[NDArray, NDArray, NDArray]
                    ) -> tuple[NDArray, NDArray, NDArray]:
    """Green's integrals ``(A, M_a, M_b)`` of the arcs of the cuts along ``uu`` (weights
    ``ww``) closed by the cap's chord, ``cap = (end, u_a, u_b)``; whether each arc is whole
    (every ``u`` crosses, no jump) and whether its plane cuts the tube elsewhere too."""
    e1, e2 = orthonormal_pair(t)
    v, s, s_u, s_v, many = _cut(surf, uu, p, t, v0)
    tt = t[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        dv = -np.sum(s_u * tt, axis=-1) / np.sum(s_v * tt, axis=-1)
    dq = s_u + s_v * dv[..., None]
    moments = np.stack(_green(s - p[:, None, :], dq, ww, e1, e2), axis=1)
    end, ua, ub = cap  # closed by the cap's chord from the arc's end back to its start
    plane = [np.stack([np.einsum("nd,nd->n", q - p, e1), np.einsum("nd,nd->n", q - p, e2)],
                      axis=1) for q in (surf.model(np.mod(ub, 1.0), end),
                                        surf.model(np.mod(ua, 1.0), end))]
    moments += np.stack(_chord(*plane), axis=1)
    whole = np.all(np.isfinite(v), axis=1) & np.all(np.isfinite(dv), axis=1)
    whole &= ~_broken(s, dq, uu, tol=surf.zero)
    return moments, whole & np.all(np.isfinite(moments), axis=1), many


def _sections(surf: _Surface, p: NDArray, t: NDArray, v0: NDArray, calipers: bool,
              order: int = AREA_ORDER) -> _Sections:
    """The sections by the planes through ``p`` normal to ``t`` (see the module's notes): the
    cut of the station's full stretch (:func:`_bands`) if it has one; else, if its stretch is
    open at an end, the first cap candidate (:func:`_cap_candidates`) of that end whose arc
    crosses the plane at every ``u`` without a jump; else dropped."""
    model = surf.model
    n = len(p)
    status = np.full(n, _DROPPED)
    end, ua, ub = np.zeros(n), np.zeros(n), np.zeros(n)
    u, w = gauss_legendre_grid(model.m1, order)
    R, Ru = surf.columns(u)
    bands = _bands(surf, R, p, t, v0)
    moments = np.full((n, 3), np.nan)
    crossed = bands.crossed.copy()
    full = np.flatnonzero(bands.full)
    if len(full):
        moments[full], many = _band_moments(surf, R, Ru, w, p[full], t[full], bands.take(full))
        crossed[full] |= many
        status[full] = _FULL
    st, ve, ca, cb = _cap_candidates(surf, p, t, np.flatnonzero(bands.ends.any(axis=1)))
    keep = bands.ends[st, ve.astype(int)]  # only the end the station's stretch is open at
    st, ve, ca, cb = st[keep], ve[keep], ca[keep], cb[keep]
    if len(st):
        # The arc's own ends (weight 0) too, so that a jump next to the cap is seen.
        nodes, weights = _arc_nodes(model.m1, ca, cb, order)
        uu = np.column_stack([ca, nodes, cb])
        ww = np.column_stack([np.zeros(len(st)), weights, np.zeros(len(st))])
        m_cap, ok, many = _measure_capped(surf, p[st], t[st], v0[st], uu, ww, (ve, ca, cb))
        for c in np.lexsort((np.abs(ve - v0[st]), st)):  # per station, the nearer end first
            i = st[c]
            if ok[c] and status[i] == _DROPPED:
                status[i], end[i], ua[i], ub[i] = _CAPPED, ve[c], ca[c], cb[c]
                moments[i], crossed[i] = m_cap[c], many[c]
    a_signed = moments[:, 0]
    status[(status != _DROPPED) & ~(np.abs(a_signed) > 0)] = _DROPPED
    ok = status != _DROPPED
    area = np.where(ok, np.abs(a_signed), np.nan)
    e1, e2 = orthonormal_pair(t)
    centroid = np.full((n, 3), np.nan)
    centroid[ok] = (p[ok] + (moments[ok, 1] / a_signed[ok])[:, None] * e1[ok]
                    + (moments[ok, 2] / a_signed[ok])[:, None] * e2[ok])
    dmin, dmax = np.full(n, np.nan), np.full(n, np.nan)
    if calipers:
        _section_calipers(surf, p, t, v0, bands, status, end, ua, ub, e1, e2, dmin, dmax)
    return _Sections(status, area, centroid, crossed & ok, dmin, dmax)


def _plane_calipers(rel: NDArray, e1: NDArray, e2: NDArray, smooth: bool
                    ) -> tuple[NDArray, NDArray]:
    """:func:`_calipers` of curves ``rel (n, m, 3)`` (points less the plane's origin) in their
    planes' ``e1, e2``, 64 curves at a time."""
    dmin, dmax = np.empty(len(rel)), np.empty(len(rel))
    for j in range(0, len(rel), 64):
        sl = slice(j, j + 64)
        plane = np.stack([np.einsum("nmd,nd->nm", rel[sl], e[sl]) for e in (e1, e2)], -1)
        dmin[sl], dmax[sl] = _calipers(plane, smooth=smooth)
    return dmin, dmax


def _section_calipers(surf: _Surface, p: NDArray, t: NDArray, v0: NDArray, bands: _Bands,
                      status: NDArray, end: NDArray, ua: NDArray, ub: NDArray, e1: NDArray,
                      e2: NDArray, dmin: NDArray, dmax: NDArray) -> None:
    """Caliper widths of the sections (in place): a full section's cut on
    :data:`CALIPER_SAMPLES` lines ``u = const`` per knot interval around (every crossing in its
    stretch: a curve in ``u`` where each line crosses once, else a point set, as a capped
    section's corners, its extremes the samples'); a capped one's lateral arc at as many points,
    then its chord."""
    model = surf.model
    k = CALIPER_SAMPLES * model.m1
    idx = np.flatnonzero(status == _FULL)
    if len(idx):
        sta, lin, pts = _band_points(surf, np.arange(k) / k, p[idx], t[idx], bands.take(idx))
        pts = pts - p[idx][sta]
        counts = np.bincount(sta * k + lin, minlength=len(idx) * k).reshape(len(idx), k)
        simple = (counts == 1).all(axis=1)
        if simple.any():  # a curve in u: the points in order of station and line
            g = idx[simple]
            one = simple[sta]
            dmin[g], dmax[g] = _plane_calipers(pts[one].reshape(-1, k, 3), e1[g], e2[g], True)
        rest = np.flatnonzero(~simple & (counts.sum(axis=1) > 0))
        if len(rest):  # every crossing, padded with each section's first one
            size = counts[rest].sum(axis=1)
            first = np.searchsorted(sta, rest)
            pad = np.repeat(pts[first][:, None, :], size.max(), axis=1)
            for r in range(len(rest)):
                pad[r, :size[r]] = pts[first[r]:first[r] + size[r]]
            g = idx[rest]
            dmin[g], dmax[g] = _plane_calipers(pad, e1[g], e2[g], False)
    idx = np.flatnonzero(status == _CAPPED)
    if not len(idx):
        return
    uu = ua[idx, None] + (ub - ua)[idx, None] * np.linspace(0.0, 1.0, k)[None, :]
    v, s, _, _, _ = _cut(surf, uu, p[idx], t[idx], v0[idx])
    frac = np.linspace(0.0, 1.0, CALIPER_SAMPLES + 1)[1:-1, None]
    qa, qb = s[:, 0], s[:, -1]  # the chord back from the arc's end to its start
    chord = qb[:, None, :] + frac[None] * (qa - qb)[:, None, :]
    rel = np.concatenate([s, chord], axis=1) - p[idx][:, None, :]
    # Whole, and around its station: a plane that also cuts the tube near an end (the other leg
    # of a bend) crosses that end ring too, but the cut closed there is not the section.
    with np.errstate(invalid="ignore"):
        turn = np.angle(np.einsum("nmd,nd->nm", rel, e1[idx])
                        + 1j * np.einsum("nmd,nd->nm", rel, e2[idx]))
        winding = np.sum(np.angle(np.exp(1j * np.diff(turn, axis=1, append=turn[:, :1]))),
                         axis=1) / (2.0 * np.pi)
    bad = ~np.all(np.isfinite(v), axis=1) | ~(np.abs(winding) > 0.5)
    status[idx[bad]] = _DROPPED
    good = idx[~bad]
    dmin[good], dmax[good] = _plane_calipers(rel[~bad], e1[good], e2[good], False)


# --------------------------------------------------------------------------------------------
# The centerline
# --------------------------------------------------------------------------------------------


def _cap_planes(model: CylinderModel) -> list[tuple[NDArray, NDArray]]:
    """Each end cap's plane: the end ring's centroid and unit vector area (zero if the ring
    has closed to a point)."""
    u, wu = gauss_legendre_grid(model.m1, AREA_ORDER)
    s, su, _ = model.evaluate(u, [0.0, 1.0])
    out = []
    for j in (0, 1):
        c = wu @ s[:, j]
        vec = 0.5 * (wu @ np.cross(s[:, j] - c, su[:, j]))
        size = np.linalg.norm(vec)
        out.append((c, vec / size if size > 0 else vec))
    return out


def _to_cap(point: NDArray, direction: NDArray, cap: tuple[NDArray, NDArray]) -> float:
    """How far along ``direction`` from ``point`` the cap's plane is (>= 0); the foot of the
    cap's centroid on that line when the line runs nearly along the cap (< 15 degrees)."""
    c, n = cap
    along = float(direction @ n)
    d = float((c - point) @ n) / along if abs(along) > 0.25 else float((c - point) @ direction)
    return max(d, 0.0)


class _Curve:
    """A centerline by arc length: straight from the head to the curve's start along its
    tangent there, a cubic spline through ``points`` (chord length, not-a-knot), or fitted to
    them by least squares at parameters ``x`` with ``intervals`` knot intervals (knots at the
    parameters' quantiles), straight on to the tail along its end tangent."""

    def __init__(self, points: NDArray, v: NDArray, caps: list[tuple[NDArray, NDArray]] | None,
                 x: NDArray | None = None, intervals: int | None = None) -> None:
        if x is None:
            keep = np.concatenate([[True],
                                   np.linalg.norm(np.diff(points, axis=0), axis=1) > 1e-12])
            points, v = points[keep], v[keep]
            x = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0),
                                                                 axis=1))])
        x = np.asarray(x, dtype=np.float64)
        breaks = x
        if intervals is not None and len(x) >= intervals + 3 + STATIONS_PER_INTERVAL:
            inner = np.quantile(x, np.arange(1, intervals) / intervals)
            self.spline = make_lsq_spline(x, points, np.r_[[x[0]] * 4, inner, [x[-1]] * 4], k=3)
            breaks = np.union1d(x, inner)
        else:
            self.spline = CubicSpline(x, points, bc_type="not-a-knot"
                                      if len(points) > 3 else "natural")
        self.knots = breaks
        self.table = _arc_table(self._speed, self.knots)
        self.t0 = _unit(self.spline(x[0], 1))
        self.t1 = _unit(self.spline(x[-1], 1))
        self.p0, self.p1 = self.spline(x[0]), self.spline(x[-1])
        self.head = _to_cap(self.p0, -self.t0, caps[0]) if caps else 0.0
        self.tail = _to_cap(self.p1, self.t1, caps[1]) if caps else 0.0
        self.inner = float(self.table[-1])
        self.length = self.head + self.inner + self.tail
        self.arc_v = (np.concatenate([[0.0], self.head + self.table[np.searchsorted(breaks, x)],
                                      [self.length]]), np.concatenate([[0.0], v, [1.0]]))
        if self.head == 0.0:
            self.arc_v = (self.arc_v[0][1:], self.arc_v[1][1:])
        if self.tail == 0.0:
            self.arc_v = (self.arc_v[0][:-1], self.arc_v[1][:-1])

    def _speed(self, x: NDArray) -> NDArray:
        return np.linalg.norm(self.spline(x, 1), axis=-1)

    def at(self, s: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        """Points, unit tangents and the tube's parameter ``v`` at arc lengths ``s``."""
        r = np.clip(s - self.head, 0.0, self.inner)
        x = _parameters_at(self._speed, self.knots, self.table, r)
        pts, tan = self.spline(x), _unit(self.spline(x, 1))
        before, after = s < self.head, s > self.head + self.inner
        pts[before] = self.p0 + (s[before] - self.head)[:, None] * self.t0
        tan[before] = self.t0
        pts[after] = self.p1 + (s[after] - self.head - self.inner)[:, None] * self.t1
        tan[after] = self.t1
        return pts, tan, np.interp(s, *self.arc_v)


def _samples(length: float, step: float) -> NDArray:
    """``0, step, 2 step, ...`` up to ``length``, and ``length``."""
    s = np.arange(int(np.floor(length / step + 1e-9)) + 1) * step
    if length - s[-1] > 1e-9 * max(length, 1.0):
        s = np.append(s, length)
    return s


def _centerline(surf: _Surface, spacing_mm: float) -> _Curve:
    """The sections' centerline (see the module's notes)."""
    model = surf.model
    knots, table, speed = _ring_arc(model)
    length = float(table[-1])
    step = min(spacing_mm, length / (STATIONS_PER_INTERVAL * model.m2))
    s = _samples(length, step)  # the stations' arc lengths
    v = _parameters_at(speed, knots, table, s)
    p, dp = ring_centroids(model, v)
    rings = _Curve(p, v, None)  # the fallback
    t = _unit(dp)
    caps = _cap_planes(model)
    best, best_shift = rings, np.inf
    for _ in range(CENTERLINE_ITERATIONS):
        sec = _sections(surf, p, t, v, calipers=False, order=CENTERLINE_ORDER)
        moved = np.linalg.norm(sec.centroid - p, axis=1)
        # A centroid more than half its section's radius from the station is not a small
        # correction of the curve but a section gone wrong (a pinched or folded stretch): it is
        # not followed.
        radius = np.sqrt(np.maximum(sec.area, 0.0) / np.pi)
        use = (sec.status == _FULL) & (moved < 0.5 * radius)
        if use.sum() < MIN_FULL_STATIONS:
            break

        def fit(keep: NDArray) -> _Curve:
            # (the tube's own resolution: M2 knot intervals over its length)
            span = s[keep][-1] - s[keep][0]
            return _Curve(sec.centroid[keep], v[keep], caps, x=s[keep],
                          intervals=max(1, int(np.ceil(model.m2 * span / s[-1] - 1e-9))))

        # The next pass's planes: normal to the curve fitted without the sections near an end
        # (straight on from those further in), whose planes, tilted a little, reach the cap or
        # a taper beyond, whose pull on their centroids would tilt them further at each pass.
        # That curve places the stations: how far it moved at them is the iteration's measure.
        first, last = s[use][0], s[use][-1]
        steer = use & (s >= first + END_FIT_RADII * radius) & (s <= last - END_FIT_RADII * radius)
        if steer.sum() < MIN_FULL_STATIONS:
            steer = use
        guide = fit(steer)
        shift = float(np.max(np.linalg.norm(guide.spline(s[steer]) - p[steer], axis=1)))
        if shift >= best_shift and best is not rings:
            break  # not converging: keep the best curve so far
        best, best_shift = (guide if steer is use else fit(use)), shift
        if shift <= CENTERLINE_TOL_MM:
            break
        s = _samples(guide.length, min(step, guide.length / (STATIONS_PER_INTERVAL * model.m2)))
        p, t, v = guide.at(s)
    return best


def _projected_rings(model: CylinderModel, curve: _Curve, s: NDArray, p: NDArray, t: NDArray,
                     v: NDArray, spacing_mm: float) -> TubeProfile:
    """The last resort when no sample has a section (a tube so short that every plane crosses
    both caps): each ring ``sigma(., v)`` projected on the plane normal to the centerline, its
    area by Green's formula there and its calipers; every row flagged ``projected``."""
    u, wu = gauss_legendre_grid(model.m1, AREA_ORDER)
    sig, sig_u, _ = model.evaluate(u, v)  # (nu, n, 3)
    vec = 0.5 * np.einsum("u,unk->nk", wu, np.cross(sig - p[None], sig_u))
    area = np.abs(np.einsum("nk,nk->n", vec, t))
    ud = np.arange(CALIPER_SAMPLES * model.m1) / (CALIPER_SAMPLES * model.m1)
    rel = np.swapaxes(model.evaluate(ud, v)[0], 0, 1) - p[:, None, :]  # (n, m, 3)
    e1, e2 = orthonormal_pair(t)
    dmin, dmax = _calipers(np.stack([np.einsum("nmk,nk->nm", rel, e) for e in (e1, e2)], -1))
    return TubeProfile(arc_mm=s, centerline=p, tangent=t, area=area, min_diameter=dmin,
                       max_diameter=dmax, length_mm=curve.length, spacing_mm=float(spacing_mm),
                       capped=np.zeros(len(s), dtype=bool), crossed=np.zeros(len(s), dtype=bool),
                       projected=True)


def tube_profile(model: CylinderModel, spacing_mm: float = PROFILE_SPACING_MM) -> TubeProfile:
    """The profile of a cylinder snake along its centerline (see the module's notes).

    Parameters
    ----------
    model : CylinderModel
        In millimetres (world mm for the outputs; an anisotropic scaling would distort it).
    spacing_mm : float
        Step along the centerline's arc length, > 0.

    Returns
    -------
    TubeProfile
        Samples at ``0, spacing_mm, 2 spacing_mm, ...`` from the ``v = 0`` end and at its
        ``v = 1`` end, less the dropped ones.
    """
    if model.kind != "cylinder":
        raise ValueError(f"a profile needs a cylinder snake, got a {model.kind}")
    if not spacing_mm > 0:
        raise ValueError(f"the profile's spacing must be > 0, got {spacing_mm}")
    surf = _Surface(model)
    curve = _centerline(surf, spacing_mm)
    s = _samples(curve.length, spacing_mm)
    p, t, v = curve.at(s)
    sec = _sections(surf, p, t, v, calipers=True)
    # (a cut no line crosses at the calipers' samples is no section: the plane of an end sample
    # that runs along its end ring, on an exiting tube, had an area of 15 against 78 mm^2 a
    # millimetre in, and no calipers)
    ok = (sec.status != _DROPPED) & np.isfinite(sec.min_diameter) & np.isfinite(sec.max_diameter)
    # The two end samples lie on the caps: a cap not normal to the centerline cuts their section
    # through its middle (about half of it, and a jump with the least tilt), so they are
    # dropped rather than reported.
    ends_ok = ok.copy()
    ends_ok[[0, -1]] &= sec.status[[0, -1]] != _CAPPED
    if ends_ok.any():  # (a tube shorter than a sample step keeps them: nothing else to show)
        ok = ends_ok
    if not ok.any():
        return _projected_rings(model, curve, s, p, t, v, spacing_mm)
    return TubeProfile(arc_mm=s[ok], centerline=p[ok], tangent=t[ok], area=sec.area[ok],
                       min_diameter=sec.min_diameter[ok], max_diameter=sec.max_diameter[ok],
                       length_mm=curve.length, spacing_mm=float(spacing_mm),
                       capped=sec.status[ok] == _CAPPED, crossed=sec.crossed[ok],
                       dropped_mm=s[~ok])
