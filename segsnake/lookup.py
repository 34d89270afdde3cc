"""The pre-integrated lookup volume that turns the flux energy into a surface integral.

For a closed surface S with outward normal, the divergence theorem with the
field ``(G, 0, 0)`` gives

    flux of grad f through S = volume integral of lap f inside S
                             = surface integral over S of G dy^dz,

where ``G(x, y, z) = integral_{-inf}^{x} lap f(tau, y, z) dtau`` (design.md,
"The energy"). Since the x-integral of ``f_xx`` is ``f_x``, G is built as

    G = f_x + cumulative integral along x of (f_yy + f_zz),

in mm units (x is the first array axis, spacing ``(sx, sy, sz)`` in mm), so
that ``dG/dx = lap f`` in mm^-2 and the theorem holds in mm. The same
machinery gives the flux of any vector field v
(:meth:`Lookup.from_vector_field`, ``G = v_x + cumint(dv_y/dy + dv_z/dz)``) and
the volume integral of a scalar field (``divergence_of_gradient=False``:
``G = cumint(f)``).

Discretisation (fourth order everywhere, so that G is accurate to a few 1e-4
relative on fields a few voxels wide):

- derivatives: five-point central differences (``-1, 8, 0, -8, 1 / 12 h`` and
  ``-1, 16, -30, 16, -1 / 12 h^2``), edge-replicated within two voxels of
  the border;
- the cumulative x-integral: trapezoid rule plus the Euler-Maclaurin end
  correction ``-h^2/12 (g'(x_i) - g'(x_0))``; the integral starts at the first
  plane (``G = f_x`` there: nothing is assumed before the volume);
- interpolation: one cubic B-spline interpolant of the G samples
  (``scipy.ndimage.spline_filter``, mirror boundary), evaluated by a compiled
  4x4x4 tensor product (``segsnake/_sampling.c``) that returns the value and
  its exact gradient, so the energy and its gradient come from one C2
  function. (scipy's ``map_coordinates`` gives the value only; four of its
  calls, or the same contraction in numpy, measured 5-8x slower.)

Outside the volume: coordinates are clamped to the grid box
``[0, (n - 1) s]`` per axis. The mirror-boundary spline has zero slope
across every face, so the continuation is C1 everywhere. Beyond the +x face G
is the total x-integral and beyond the -x face G is its value on the first
plane, both with ``dG/dx = 0``: outside the box ``div grad f`` is taken to be
0 along x, which is what keeps the divergence theorem meaningful for a surface
that pokes out through an x face. Beyond a y or z face the face values are
continued (``dG/dy`` or ``dG/dz = 0``). For every surface the flux is
exactly the volume integral of ``dG/dx`` of this continued function.
``Lookup.from_field(..., pad=n)`` instead puts the grid in a box ``n`` voxels
larger on every side where the density is zero (sampled at points shifted by
``n`` voxels): a surface beyond the grid then holds no density at all.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np
from scipy import ndimage

try:
    from segsnake import _sampling
except ImportError as exc:  # an install that skipped the build (no compiler), or a stale checkout
    raise ImportError("segsnake's compiled kernel segsnake/_sampling.c is not built: reinstall "
                      "with `pip install -e .` (or `make install`), which needs a C compiler "
                      "and the Python headers") from exc
from segsnake.parallel import pieces, slabs, spline_filter, thread_map

__all__ = ["Lookup"]

_D1 = np.array([1.0, -8.0, 0.0, 8.0, -1.0]) / 12.0  # correlate1d weights, first derivative
_D2 = np.array([-1.0, 16.0, -30.0, 16.0, -1.0]) / 12.0  # second derivative
_PAD = 2
_BLOCK = 4096  # points per block in Lookup.sample, at most (measured best of 2048-8192)


def _mirror_index(m: np.ndarray, n: int) -> np.ndarray:
    """scipy.ndimage 'mirror' extension: ... 2 1 | 0 1 2 ... n-1 | n-2 n-3 ..."""
    if n == 1:
        return np.zeros_like(m)
    period = 2 * (n - 1)
    m = np.mod(m, period)
    return np.where(m > n - 1, period - m, m)


def _check_spacing(spacing: Sequence[float]) -> tuple[float, float, float]:
    sp = tuple(float(s) for s in spacing)
    if len(sp) != 3 or not all(np.isfinite(s) and s > 0 for s in sp):
        raise ValueError(f"spacing must be 3 positive finite numbers, got {spacing!r}")
    return sp  # type: ignore[return-value]


def _deriv(a: np.ndarray, axis: int, h: float, order: int) -> np.ndarray:
    w = _D1 / h if order == 1 else _D2 / (h * h)
    return ndimage.correlate1d(a, w, axis=axis, mode="nearest", output=np.float64)


def _cumint_x(g: np.ndarray, h: float, out: np.ndarray | None = None) -> np.ndarray:
    """4th-order cumulative integral along axis 0 from the first plane (float64, or into ``out``
    if given, float64 or float32, which may be ``g`` itself), in threads over slabs cut across
    another axis, each written straight into the result."""
    if out is None:
        out = np.empty_like(g, dtype=np.float64)
    thread_map(lambda sl: _cumint_x_slab(g[sl], h, out[sl]), slabs(g.shape, 0))
    return out


def _cumint_x_slab(g: np.ndarray, h: float, out: np.ndarray) -> None:
    """Plane by plane, summed in float64 whatever ``g``'s and ``out``'s types (one rounding per
    value), with no full-size temporary.
    ``out`` may be ``g``: the planes still to be read are kept before they are overwritten."""
    n = g.shape[0]
    kept: dict[int, np.ndarray] = {}

    def plane(i: int) -> np.ndarray:
        return kept[i] if i in kept else np.array(g[i], dtype=np.float64)

    def keep(i: int) -> None:  # plane i is about to be overwritten; planes i-2.. are read later
        kept[i] = plane(i)
        kept.pop(i - 3, None)

    # Euler-Maclaurin end correction with a second-order derivative of g (np.gradient's
    # formulas, edge_order 2).
    def deriv(i: int) -> np.ndarray:
        if i == 0:
            return (-1.5 / h) * plane(0) + (2.0 / h) * plane(1) + (-0.5 / h) * plane(2)
        if i == n - 1:
            return (0.5 / h) * plane(n - 3) + (-2.0 / h) * plane(n - 2) + (1.5 / h) * plane(n - 1)
        return (plane(i + 1) - plane(i - 1)) / (2.0 * h)

    d0 = deriv(0) if n >= 3 else None
    scale = h * h / 12.0
    keep(0)
    out[0] = 0.0
    total = np.zeros(g.shape[1:])
    for i in range(1, n):
        total += plane(i) + plane(i - 1)
        value = total * (0.5 * h)  # the trapezoid rule
        if d0 is not None:
            value -= (deriv(i) - d0) * scale
        keep(i)
        out[i] = value


class Lookup:
    """Cubic B-spline lookup volume ``G`` with exact value-and-gradient sampling.

    Build it with :meth:`from_field` or :meth:`from_vector_field`; sample it with
    :meth:`sample`. Points are in scaled index space (mm): voxel ``(i, j, k)``
    is at ``(i sx, j sy, k sz)``.

    Attributes
    ----------
    shape : tuple of int
        Grid shape.
    spacing : tuple of float
        Voxel size in mm.
    coef : ndarray, float64
        Spline coefficients, mirror-padded by 2 on every side (C order).
    """

    def __init__(self, values: np.ndarray, spacing: Sequence[float]) -> None:
        """Wrap grid samples of G (any real array, shape (nx, ny, nz)) in the interpolant."""
        values = np.asarray(values)
        if values.ndim != 3:
            raise ValueError(f"lookup values must be 3D, got shape {values.shape}")
        self._build(values.shape, spacing, lambda inner: inner.__setitem__(Ellipsis, values))

    def _build(self, shape: Sequence[int], spacing: Sequence[float],
               fill: Callable[[np.ndarray], None], dtype=np.float64) -> None:
        """The interpolant of the samples ``fill`` writes into the coefficients' inner block
        (of ``dtype``): the samples are filtered where they lie, so no second full-size array
        is held (measured at 256^3: a lookup's build peaked at 512 MB, 8 x the float32 field)."""
        self.shape = tuple(int(s) for s in shape)
        self.spacing = _check_spacing(spacing)
        if np.dtype(dtype) not in (np.dtype(np.float64), np.dtype(np.float32)):
            raise ValueError(f"lookup coefficients are float64 or float32, not {np.dtype(dtype)}")
        # The coefficients are computed inside the padded array, whose borders are then
        # mirrored axis by axis (corners included); an axis of one sample is left as it is.
        self.coef = np.empty(tuple(n + 2 * _PAD for n in self.shape), dtype=dtype)
        inner = self.coef[tuple(slice(_PAD, n + _PAD) for n in self.shape)]
        fill(inner)
        if not np.all(np.isfinite(inner)):
            raise ValueError("lookup values contain NaN or Inf")
        spline_filter(inner, out=inner)
        for axis, n in enumerate(self.shape):
            for pads in (np.arange(-_PAD, 0), np.arange(n, n + _PAD)):
                sl = [slice(None)] * 3
                sl[axis] = pads + _PAD
                self.coef[tuple(sl)] = np.take(self.coef, _mirror_index(pads, n) + _PAD,
                                               axis=axis)
        self._flat = self.coef.reshape(-1)
        self._pshape = tuple(int(s) for s in self.coef.shape)

    # ---------------------------------------------------------------- builders
    @classmethod
    def from_field(
        cls, f: np.ndarray, spacing: Sequence[float], *, divergence_of_gradient: bool = True,
        pad: int = 0,
    ) -> "Lookup":
        """Lookup for the flux of ``grad f`` (or the volume integral of ``f``).

        Parameters
        ----------
        f : ndarray, shape (nx, ny, nz)
            Scalar field (the edge map).
        spacing : sequence of 3 float
            Voxel size in mm.
        divergence_of_gradient : bool
            True (default): ``G = f_x + cumint(f_yy + f_zz)``, so the surface
            integral of ``G dy^dz`` is the flux of ``grad f`` (``dG/dx = lap f``).
            False: ``G = cumint(f)``, so it is the volume integral of ``f``.
        pad : int
            The lookup of a grid grown by this many voxels on every side, where the density
            (``lap f``, or ``f``) is zero: sample it at points shifted by ``pad`` voxels. With
            the density given outright, ``G = cumint(lap f)`` (its x part is the integral of
            ``f_xx``, not ``f_x`` itself).
        """
        sp = _check_spacing(spacing)
        f = np.asarray(f)
        if f.ndim != 3:
            raise ValueError(f"field must be 3D, got shape {f.shape}")
        if pad:
            # The density written straight into the padded coefficients' array (no padded copy).
            def write(values: np.ndarray) -> None:
                values[...] = 0.0
                inner = values[(slice(pad, -pad),) * 3]
                if not divergence_of_gradient:
                    inner[...] = f
                    return
                for d in range(3):
                    inner += _deriv(f, d, sp[d], 2)

            return cls.volume_integral(tuple(n + 2 * pad for n in f.shape), sp, write)
        if divergence_of_gradient:
            base, integrand, f_zz = thread_map(lambda job: _deriv(f, *job),
                                               [(0, sp[0], 1), (1, sp[1], 2), (2, sp[2], 2)])
            integrand += f_zz
            del f_zz
        else:
            base = None
            integrand = f  # read as it is: the integral is accumulated in float64
        return cls._from_parts(base, integrand, sp)

    @classmethod
    def volume_integral(cls, shape: Sequence[int], spacing: Sequence[float],
                        write: Callable[[np.ndarray], None], dtype=np.float64) -> "Lookup":
        """Lookup for the volume integral of a density that ``write`` puts, in place, into the
        array of ``shape`` it is given (``G = cumint(w)``, like :meth:`from_field` with
        ``divergence_of_gradient=False``): the density is written where the coefficients will
        be, so it never exists as a second volume (issue 18).

        ``dtype`` (float64 or float32) is the coefficients' (and the written density's) type.
        float32 halves the lookup's memory; the integral is summed in float64 plane by plane and
        rounded once, so ``G`` is exact to a relative 6e-8 of its largest value (sampling is in
        float64 either way).
        """
        sp = _check_spacing(spacing)

        def fill(inner: np.ndarray) -> None:
            write(inner)
            _cumint_x(inner, sp[0], out=inner)

        obj = cls.__new__(cls)
        obj._build(shape, sp, fill, dtype)
        return obj

    @classmethod
    def from_vector_field(
        cls, vx: np.ndarray, vy: np.ndarray, vz: np.ndarray, spacing: Sequence[float],
    ) -> "Lookup":
        """Lookup for the flux of a vector field ``v`` (e.g. the smoothed image gradient).

        ``G = v_x + cumint(dv_y/dy + dv_z/dz)``, so ``dG/dx = div v`` and the
        surface integral of ``G dy^dz`` is the flux of ``v``.
        """
        sp = _check_spacing(spacing)
        vx, vy, vz = (np.asarray(v) for v in (vx, vy, vz))
        if not (vx.shape == vy.shape == vz.shape) or vx.ndim != 3:
            raise ValueError("vx, vy, vz must be 3D arrays of one shape")
        integrand = _deriv(vy, 1, sp[1], 1)
        integrand += _deriv(vz, 2, sp[2], 1)
        return cls._from_parts(vx.astype(np.float64), integrand, sp)

    @classmethod
    def _from_parts(cls, base: np.ndarray | None, integrand: np.ndarray,
                    spacing: tuple[float, float, float]) -> "Lookup":
        def fill(inner: np.ndarray) -> None:
            _cumint_x(integrand, spacing[0], out=inner)
            if base is not None:
                inner += base

        obj = cls.__new__(cls)
        obj._build(integrand.shape, spacing, fill)
        return obj

    # ---------------------------------------------------------------- sampling
    def sample(self, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """G and its exact gradient at continuous points.

        Parameters
        ----------
        points_mm : array_like, shape (N, 3) (or (3,))
            Points in scaled index space (mm).

        Returns
        -------
        G : ndarray, shape (N,)
        dG : ndarray, shape (N, 3)
            ``(dG/dx, dG/dy, dG/dz)`` per mm; ``dG/dx`` is ``lap f`` (or
            ``div v``) of the interpolant. A component is 0 along an axis on
            which the point lies outside the grid box (clamped). A point with a NaN or
            infinite coordinate gets NaN.
        """
        p = np.asarray(points_mm, dtype=np.float64)
        single = p.ndim == 1
        p = np.ascontiguousarray(p.reshape(-1, 3))
        g = np.empty(len(p))
        grad = np.empty((len(p), 3))
        # The kernel releases the GIL: equal blocks of points run in parallel threads, this one
        # among them (a block takes well under a millisecond; a pool thread that has slept
        # since the last call wakes late: docs/benchmarks.md, sessions 22 and 23).

        def block(sl: slice) -> None:
            _sampling.sample(self._flat, self._pshape, self.shape, self.spacing, p[sl],
                             g[sl], grad[sl])

        thread_map(block, pieces(len(p), _BLOCK), join=True)
        if single:
            return g[0], grad[0]
        return g, grad

    def __call__(self, points_mm: np.ndarray) -> np.ndarray:
        """G only (same as ``sample(points_mm)[0]``)."""
        return self.sample(points_mm)[0]

    @property
    def extent_mm(self) -> np.ndarray:
        """Upper corner of the grid box in mm (the lower one is the origin)."""
        return (np.asarray(self.shape) - 1) * np.asarray(self.spacing)
