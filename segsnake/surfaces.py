"""Parametric spline surfaces: the deformable sphere and the open cylinder.

Both are tensor products ``sigma(u, v) = sum_k sum_l c[k, l] b1_k(u) b2_l(v)`` on
``(u, v) in [0, 1]^2`` with ``k = 0..M1-1`` (periodic around) and ``l = -1..M2+1`` (along):

* sphere (Schmitter et al. 2017, eq. (7)): ``b1 = phi_{M1,per}(M1 u - k)``,
  ``b2 = phi_{2 M2}(M2 v - l)``, with closed poles (``c[k, 0] = cN``, ``c[k, M2] = cS``) and smooth
  poles (eqs. (11), (12)) imposed by a fixed sparse linear map from the *free parameters*
  (interior rows, the two poles, four tangent vectors) to the full control grid;
* cylinder (Schmitter's thesis, sec. 7.3): the same periodic ``b1`` around and Keys' cubic
  convolution kernel along the axis; every control point is free and the ends are open.

The optimizer only ever sees the free parameters, so every shape it can reach is closed and
smooth at the poles. Parameters are stored as a ``(P, 3)`` array together with a boolean
``is_vector`` mask: tangent vectors transform under an affine map without the translation.

Orientation: each model class has an ``orientation`` sign so that the outward normal is
``n = orientation * (sigma_v x sigma_u)``. With the papers' parameterizations the sphere's
``sigma_u x sigma_v`` points inward (v runs from the north pole down), so its orientation is +1;
the cylinder ``(cos 2pi u, sin 2pi u, v)`` has ``sigma_u x sigma_v`` outward, so its orientation
is -1. Normals, volumes, flux signs and mesh face order all go through this one sign. An affine
map with negative determinant reverses it; :meth:`SplineSurface.reversed` restores it.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from functools import cached_property, lru_cache
from typing import Any, Callable, Sequence

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray

from segsnake.basis import keys, phi, phi_periodic, phi_prime_at_one

__all__ = [
    "SplineSurface",
    "SphereModel",
    "CylinderModel",
    "GridBasis",
    "gauss_legendre_grid",
    "load_model",
    "axial_rings",
]

FORMAT_VERSION = 1
#: Grids whose basis matrices a model keeps (:meth:`SplineSurface.grid_basis`).
BASIS_CACHE_SIZE = 32


@dataclass(frozen=True)
class GridBasis:
    """Basis matrices of a model on a tensor grid ``u (nu,) x v (nv,)``.

    ``sigma = Bu @ C @ Bv.T`` per coordinate, ``sigma_u = dBu @ C @ Bv.T``,
    ``sigma_v = Bu @ C @ dBv.T``. The matrices are sparse (four non-zeros a row).
    """

    u: NDArray
    v: NDArray
    Bu: sp.csr_matrix
    dBu: sp.csr_matrix
    Bv: sp.csr_matrix
    dBv: sp.csr_matrix

    def __post_init__(self) -> None:
        # Stacked once, so that evaluate and adjoint are five sparse products on all three
        # coordinates at once (were fifteen: 0.3-0.5 ms an energy evaluation).
        stack_u = sp.vstack([self.Bu, self.dBu]).tocsr()  # (2 nu, M1): [Bu; dBu]
        stack_v = sp.vstack([self.Bv, self.dBv]).tocsr()  # (2 nv, L): [Bv; dBv]
        object.__setattr__(self, "_stack_u", stack_u)
        object.__setattr__(self, "_stack_v", stack_v)
        object.__setattr__(self, "_stack_u_t", stack_u.T.tocsr())
        object.__setattr__(self, "_stack_v_t", stack_v.T.tocsr())
        object.__setattr__(self, "_bu_t", self.Bu.T.tocsr())

    def evaluate(self, C: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        """sigma, sigma_u, sigma_v, each ``(nu, nv, 3)`` and C-contiguous, from a full grid
        ``C (M1, L, 3)``."""
        m1, n_l, _ = C.shape
        nu, nv = self.Bu.shape[0], self.Bv.shape[0]
        # [Bv; dBv] C per coordinate: (2, nv, M1, 3), then [Bu; dBu] times Bv C (sigma and
        # sigma_u in one contiguous block each) and Bu times dBv C (sigma_v).
        P = (self._stack_v @ C.transpose(1, 0, 2).reshape(n_l, m1 * 3)).reshape(2, nv, m1, 3)
        along = P[0].transpose(1, 0, 2).reshape(m1, nv * 3)
        Q = (self._stack_u @ along).reshape(2, nu, nv, 3)
        sv = (self.Bu @ P[1].transpose(1, 0, 2).reshape(m1, nv * 3)).reshape(nu, nv, 3)
        return Q[0], Q[1], sv

    def positions(self, C: NDArray) -> NDArray:
        """sigma alone, ``(nu, nv, 3)``: the same products as :meth:`evaluate`'s first block
        (the same numbers), without the derivatives' three quarters of the memory (a mask's
        mesh of a brain-sized 17 x 17 surface: 19 MB instead of 75 MB)."""
        m1, n_l, _ = C.shape
        nu, nv = self.Bu.shape[0], self.Bv.shape[0]
        P = self.Bv @ C.transpose(1, 0, 2).reshape(n_l, m1 * 3)  # (nv, M1 * 3)
        P = P.reshape(nv, m1, 3).transpose(1, 0, 2).reshape(m1, nv * 3)
        return (self.Bu @ P).reshape(nu, nv, 3)

    def adjoint(self, g: NDArray, g_u: NDArray, g_v: NDArray) -> NDArray:
        """Gradient on the full grid ``(M1, L, 3)`` from gradients on sigma, sigma_u, sigma_v.

        The transpose of :meth:`evaluate`: ``dE/dC = Bu^T g Bv + dBu^T g_u Bv + Bu^T g_v dBv``.
        """
        return self.adjoint_stacked(np.stack([g, g_u]), g_v)

    def adjoint_stacked(self, g_stack: NDArray, g_v: NDArray) -> NDArray:
        """:meth:`adjoint` with the gradients on sigma and sigma_u stacked, ``(2, nu, nv, 3)``."""
        nu, nv = self.Bu.shape[0], self.Bv.shape[0]
        m1, n_l = self.Bu.shape[1], self.Bv.shape[1]
        left = np.empty((m1, 2, nv, 3))
        left[:, 0] = (self._stack_u_t @ g_stack.reshape(2 * nu, nv * 3)).reshape(m1, nv, 3)
        left[:, 1] = (self._bu_t @ g_v.reshape(nu, nv * 3)).reshape(m1, nv, 3)
        out = self._stack_v_t @ left.transpose(1, 2, 0, 3).reshape(2 * nv, m1 * 3)  # (L, M1*3)
        return out.reshape(n_l, m1, 3).transpose(1, 0, 2)


@lru_cache(maxsize=256)
def gauss_legendre_grid(n_intervals: int, order: int) -> tuple[NDArray, NDArray]:
    """Gauss-Legendre nodes and weights on [0, 1], ``order`` nodes per knot interval
    (read-only arrays, kept: the volume check of every trial step asks for the same grid, and
    ``leggauss`` took a quarter of a millisecond each time).

    The integrands of the flux, volume and area are smooth inside each knot interval and only C0
    or C1 across knots, so splitting at the knots is what makes Gauss-Legendre converge fast.
    """
    x, w = np.polynomial.legendre.leggauss(order)
    h = 1.0 / n_intervals
    starts = np.arange(n_intervals) * h
    nodes = (starts[:, None] + (x[None, :] + 1) * h / 2).ravel()
    weights = np.tile(w * h / 2, n_intervals)
    nodes.flags.writeable = weights.flags.writeable = False
    return nodes, weights


def _csr(values: NDArray) -> sp.csr_matrix:
    values = np.where(np.abs(values) < 1e-300, 0.0, values)
    return sp.csr_matrix(values)


class SplineSurface:
    """Common machinery of the tensor-product spline surfaces.

    Subclasses define the generators (:meth:`_basis_u`, :meth:`_basis_v`), the constraint map
    from free parameters to the full grid, and the mesh topology.

    Attributes
    ----------
    m1, m2 : int
        Control points around (periodic) and along the surface.
    params : ndarray, shape (P, 3)
        Free parameters (control points and, for the sphere, pole tangent vectors).
    """

    kind: str = "surface"
    orientation: int = 1

    def __init__(self, m1: int, m2: int, params: ArrayLike) -> None:
        self.m1 = int(m1)
        self.m2 = int(m2)
        self._check_sizes()
        params = np.array(params, dtype=np.float64)
        if params.shape != (self.n_params, 3):
            raise ValueError(f"{self.kind} with M1={m1}, M2={m2} takes {self.n_params} x 3 parameters, "
                             f"got {params.shape}")
        self.params = params

    # -- subclass interface -------------------------------------------------------------------
    def _check_sizes(self) -> None:
        if self.m1 < 4:
            raise ValueError(f"M1 must be >= 4 (the periodic basis needs it), got {self.m1}")

    @property
    def n_params(self) -> int:
        raise NotImplementedError

    @property
    def is_vector(self) -> NDArray[np.bool_]:
        """Which parameter rows are direction vectors (no translation under affine maps)."""
        return np.zeros(self.n_params, dtype=bool)

    def _constraint_matrix(self) -> sp.csr_matrix:
        raise NotImplementedError

    def _basis_v(self, v: NDArray, deriv: int) -> NDArray:
        raise NotImplementedError

    # -- basis --------------------------------------------------------------------------------
    @property
    def l_index(self) -> NDArray[np.int_]:
        """Indices l of the control grid's second axis: -1 .. M2+1."""
        return np.arange(-1, self.m2 + 2)

    def _basis_u(self, u: NDArray, deriv: int) -> NDArray:
        k = np.arange(self.m1)
        t = self.m1 * np.asarray(u, dtype=np.float64)[:, None] - k[None, :]
        return phi_periodic(t, self.m1, self.m1, deriv) * self.m1**deriv

    def grid_basis(self, u: ArrayLike, v: ArrayLike) -> GridBasis:
        """The sparse basis matrices of this model on the grid ``u x v``.

        They depend on the grid and the model's kind and size only, so they are kept (the last
        :data:`BASIS_CACHE_SIZE` grids) and shared with every model :meth:`with_params` makes
        from this one: the fold and volume checks evaluate the same grids at every step
        (measured: 25,000 sparse matrices built in one 5 s tube run)."""
        u = np.atleast_1d(np.asarray(u, dtype=np.float64))
        v = np.atleast_1d(np.asarray(v, dtype=np.float64))
        cache = self.__dict__.setdefault("_basis_cache", {})
        key = (u.tobytes(), v.tobytes())
        basis = cache.get(key)
        if basis is None:
            basis = GridBasis(u, v, _csr(self._basis_u(u, 0)), _csr(self._basis_u(u, 1)),
                              _csr(self._basis_v(v, 0)), _csr(self._basis_v(v, 1)))
            if len(cache) >= BASIS_CACHE_SIZE:
                cache.pop(next(iter(cache)))
            cache[key] = basis
        return basis

    @cached_property
    def constraint(self) -> sp.csr_matrix:
        """Sparse map ``(M1 * L, P)`` from free parameters to the flattened full grid."""
        return self._constraint_matrix()

    # -- control points -----------------------------------------------------------------------
    def control_points(self, params: NDArray | None = None) -> NDArray:
        """Full control grid ``c[k, l]``, shape ``(M1, M2 + 3, 3)``; ``l`` runs from -1."""
        p = self.params if params is None else params
        return (self.constraint @ p).reshape(self.m1, self.m2 + 3, 3)

    def grid_gradient_to_params(self, grad_C: NDArray) -> NDArray:
        """Chain a gradient on the full grid ``(M1, L, 3)`` to the free parameters ``(P, 3)``."""
        return self.constraint.T @ grad_C.reshape(-1, 3)

    def with_params(self, params: ArrayLike) -> "SplineSurface":
        """A model of the same kind and size with other parameters (shares cached matrices)."""
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        new.params = np.array(params, dtype=np.float64).reshape(self.n_params, 3)
        return new

    # -- evaluation ---------------------------------------------------------------------------
    def evaluate(self, u: ArrayLike, v: ArrayLike) -> tuple[NDArray, NDArray, NDArray]:
        """sigma, sigma_u, sigma_v on the tensor grid ``u x v``, each of shape ``(nu, nv, 3)``."""
        return self.grid_basis(u, v).evaluate(self.control_points())

    def positions(self, u: ArrayLike, v: ArrayLike) -> NDArray:
        """sigma alone on the tensor grid ``u x v``, ``(nu, nv, 3)`` (as :meth:`evaluate`)."""
        return self.grid_basis(u, v).positions(self.control_points())

    def __call__(self, u: ArrayLike, v: ArrayLike) -> NDArray:
        """sigma at matching points ``(u[i], v[i])`` (not a grid); shape ``(..., 3)``."""
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        shape = np.broadcast_shapes(u.shape, v.shape)
        uu, vv = np.broadcast_to(u, shape).ravel(), np.broadcast_to(v, shape).ravel()
        bu = self._basis_u(uu, 0)  # (N, M1)
        bv = self._basis_v(vv, 0)  # (N, L)
        C = self.control_points()
        out = np.einsum("nk,nl,kld->nd", bu, bv, C)
        return out.reshape(shape + (3,))

    def normals(self, u: ArrayLike, v: ArrayLike, unit: bool = True) -> NDArray:
        """Outward normals on the grid ``u x v`` (unit length by default)."""
        _, su, sv = self.evaluate(u, v)
        n = self.orientation * np.cross(sv, su)
        if unit:
            n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
        return n

    def quadrature(self, order: int | tuple[int, int] = 6) -> tuple[GridBasis, NDArray]:
        """Gauss-Legendre grid basis and 2D weights ``(nu, nv)``.

        ``order`` nodes per knot interval, or ``(order_u, order_v)`` for each direction.
        """
        order_u, order_v = (order, order) if np.isscalar(order) else order
        u, wu = gauss_legendre_grid(self.m1, int(order_u))
        v, wv = gauss_legendre_grid(self.m2, int(order_v))
        return self.grid_basis(u, v), wu[:, None] * wv[None, :]

    def area_samples(self, order: int = 4) -> tuple[NDArray, NDArray, NDArray]:
        """Gauss-Legendre nodes on the surface: points ``(N, 3)``, outward unit normals
        ``(N, 3)`` and area weights ``(N,)``, so that ``sum(weights * f(points))`` is the
        surface integral of ``f``."""
        gb, w = self.quadrature(order)
        s, su, sv = gb.evaluate(self.control_points())
        n = self.orientation * np.cross(sv, su)
        norm = np.linalg.norm(n, axis=-1)
        unit = n / np.maximum(norm, 1e-300)[..., None]
        return s.reshape(-1, 3), unit.reshape(-1, 3), (w * norm).ravel()

    def volume(self, order: int = 8) -> float:
        """Signed enclosed volume ``1/3 integral sigma . n du dv`` (positive when outward).

        For the open cylinder this is the volume of the cone from the origin over the lateral
        surface; :meth:`CylinderModel.volume` adds the planar end caps.
        """
        gb, w = self.quadrature(order)
        s, su, sv = gb.evaluate(self.control_points())
        flux = np.sum(w * np.einsum("uvd,uvd->uv", s, np.cross(sv, su)))
        return float(self.orientation * flux / 3.0)

    def area(self, order: int = 8) -> float:
        """Surface area ``integral |sigma_u x sigma_v| du dv`` (Gauss-Legendre per knot interval)."""
        gb, w = self.quadrature(order)
        _, su, sv = gb.evaluate(self.control_points())
        return float(np.sum(w * np.linalg.norm(np.cross(sv, su), axis=-1)))

    # -- affine maps --------------------------------------------------------------------------
    def transformed(self, A: ArrayLike, b: ArrayLike = (0.0, 0.0, 0.0)) -> "SplineSurface":
        """The model of ``A sigma + b``: control points ``A c + b``, tangent vectors ``A T``."""
        A = np.asarray(A, dtype=np.float64).reshape(3, 3)
        b = np.asarray(b, dtype=np.float64).reshape(3)
        new = self.params @ A.T + (~self.is_vector)[:, None] * b[None, :]
        return self.with_params(new)

    def reversed(self) -> "SplineSurface":
        """The same surface traversed with u -> -u, which flips the normal orientation."""
        raise NotImplementedError

    # -- meshes -------------------------------------------------------------------------------
    def triangles(self, samples_u: int | None = None, samples_v: int | None = None,
                  **kwargs: Any) -> tuple[NDArray, NDArray]:
        """The mesh of :meth:`to_mesh` as arrays: points ``(n, 3)`` and outward-oriented
        triangles ``(f, 3)`` (vertex ids), without VTK."""
        raise NotImplementedError

    def to_mesh(self, samples_u: int | None = None, samples_v: int | None = None, **kwargs: Any):
        """Triangle mesh (``pyvista.PolyData``) with outward-oriented faces
        (:meth:`triangles`)."""
        import pyvista as pv

        points, tris = self.triangles(samples_u, samples_v, **kwargs)
        faces = np.hstack([np.full((len(tris), 1), 3), tris]).astype(np.int64).ravel()
        return pv.PolyData(np.ascontiguousarray(points), faces)

    @staticmethod
    def _grid_faces(nu: int, rows: int, offset: int = 0, tail: Sequence[NDArray] = ()) -> NDArray:
        """Quads of a u-periodic vertex grid (rows of nu vertices), split into outward triangles.

        Vertex (i, j) (u index i, row j) has id offset + j * nu + i. With u increasing along i
        and v along j, the outward normal is sigma_v x sigma_u, so (i, j), (i, j+1), (i+1, j)
        is counter-clockwise seen from outside. The faces of ``tail`` (the caps) follow them in
        the same array (appended, the mesh would be copied once more).
        """
        i = np.arange(nu)
        ip = (i + 1) % nu
        row = offset + nu * np.arange(max(rows - 1, 0))[:, None]
        a, b = row + i, row + ip  # (c = b + nu, d = a + nu)
        # per row: its nu triangles (a, d, b), then its nu triangles (b, d, c); written in
        # place (stacked, the pieces held 3 x the result: 110 MB for a 17 x 17 brain's mask mesh)
        grid = 2 * nu * len(row)
        faces = np.empty((grid + sum(map(len, tail)), 3), dtype=np.int64)
        if len(tail):
            faces[grid:] = np.concatenate(tail)
        out = faces[:grid].reshape(len(row), 2, nu, 3)
        out[:, 0, :, 0] = a
        out[:, 0, :, 1] = a + nu
        out[:, 0, :, 2] = b
        out[:, 1, :, 0] = b
        out[:, 1, :, 1] = a + nu
        out[:, 1, :, 2] = b + nu
        return faces

    @staticmethod
    def _cap_faces(nu: int, first_apex: int, first_row: int, last_apex: int,
                   last_row: int) -> list[NDArray]:
        """Fans closing the first and last vertex rows, ordered like :meth:`_grid_faces`.

        (apex, i, i+1) at the v = 0 end has normal (r_i - apex) x (r_i+1 - r_i) ~ sigma_v x
        sigma_u; the v = 1 end runs the other way round.
        """
        i = np.arange(nu)
        ip = (i + 1) % nu
        return [np.stack([np.full(nu, first_apex), first_row + i, first_row + ip], axis=1),
                np.stack([np.full(nu, last_apex), last_row + ip, last_row + i], axis=1)]

    def _outward(self, points: NDArray, tris: NDArray) -> tuple[NDArray, NDArray]:
        if self.orientation < 0:  # faces were built sigma_v x sigma_u-outward
            tris = tris[:, ::-1]
        return points, tris

    # -- serialization ------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """JSON-able description; :func:`load_model` inverts it exactly."""
        return {
            "format": "segsnake-model",
            "version": FORMAT_VERSION,
            "kind": self.kind,
            "m1": self.m1,
            "m2": self.m2,
            "units": "mm (scaled index space: p = (i*sx, j*sy, k*sz))",
            "params": self.params.tolist(),
            "params_is_vector": self.is_vector.tolist(),
            "control_points": self.control_points().tolist(),
        }

    def save(self, path: str | os.PathLike) -> None:
        """Write :meth:`to_dict` as JSON (floats round-trip exactly through ``repr``)."""
        with open(path, "w", encoding="utf-8") as fh:
            json.dump(self.to_dict(), fh)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(m1={self.m1}, m2={self.m2})"


# ---------------------------------------------------------------------------------------------
class SphereModel(SplineSurface):
    """Closed, smooth deformable sphere (Schmitter, Garcia-Amorena, Unser 2017).

    Free parameters, in order: the interior rows ``c[k, l]`` for ``l = 1..M2-1`` (row-major in
    k then l... stored as k-major ``k * (M2 - 1) + (l - 1)``), then ``cN``, ``cS``, ``T1N``,
    ``T2N``, ``T1S``, ``T2S``.
    """

    kind = "sphere"

    def _check_sizes(self) -> None:
        super()._check_sizes()
        if self.m2 < 2:
            raise ValueError(f"M2 must be >= 2 for a sphere, got {self.m2}")

    @property
    def n_params(self) -> int:
        return self.m1 * (self.m2 - 1) + 6

    @property
    def is_vector(self) -> NDArray[np.bool_]:
        flags = np.zeros(self.n_params, dtype=bool)
        flags[-4:] = True
        return flags

    @property
    def _idx(self) -> dict[str, int]:
        base = self.m1 * (self.m2 - 1)
        return {"cN": base, "cS": base + 1, "T1N": base + 2, "T2N": base + 3,
                "T1S": base + 4, "T2S": base + 5}

    def _basis_v(self, v: NDArray, deriv: int) -> NDArray:
        t = self.m2 * np.asarray(v, dtype=np.float64)[:, None] - self.l_index[None, :]
        return phi(t, 2 * self.m2, deriv) * self.m2**deriv

    def _constraint_matrix(self) -> sp.csr_matrix:
        m1, m2 = self.m1, self.m2
        L = m2 + 3
        idx = self._idx
        theta = 2 * np.pi * np.arange(m1) / m1
        scale = 1.0 / (m2 * phi_prime_at_one(2 * m2))
        rows, cols, vals = [], [], []

        def put(k: int, l: int, col: int, val: float) -> None:
            rows.append(k * L + (l + 1))
            cols.append(col)
            vals.append(val)

        for k in range(m1):
            for l in range(1, m2):
                put(k, l, k * (m2 - 1) + (l - 1), 1.0)
            put(k, 0, idx["cN"], 1.0)
            put(k, m2, idx["cS"], 1.0)
            # eq. (11): c[k,-1] = c[k,1] + (T1N cos + T2N sin) / (M2 phi'_{2M2}(1))
            put(k, -1, k * (m2 - 1), 1.0)
            put(k, -1, idx["T1N"], np.cos(theta[k]) * scale)
            put(k, -1, idx["T2N"], np.sin(theta[k]) * scale)
            # eq. (12): c[k,M2+1] = c[k,M2-1] - (T1S cos + T2S sin) / (M2 phi'_{2M2}(1))
            put(k, m2 + 1, k * (m2 - 1) + (m2 - 2), 1.0)
            put(k, m2 + 1, idx["T1S"], -np.cos(theta[k]) * scale)
            put(k, m2 + 1, idx["T2S"], -np.sin(theta[k]) * scale)
        return sp.csr_matrix((vals, (rows, cols)), shape=(m1 * L, self.n_params))

    def reversed(self) -> "SphereModel":
        """u -> -u: rows k -> -k mod M1; tangents T2 change sign (sin(-x) = -sin x)."""
        order = (-np.arange(self.m1)) % self.m1
        interior = self.interior()[order]
        p = {n: self.pole(n) for n in ("cN", "cS", "T1N", "T2N", "T1S", "T2S")}
        return SphereModel.from_parts(interior, p["cN"], p["cS"], p["T1N"], -p["T2N"],
                                      p["T1S"], -p["T2S"])

    # -- named parameters ---------------------------------------------------------------------
    def interior(self) -> NDArray:
        """Interior control points ``c[k, l]``, ``l = 1..M2-1``, shape ``(M1, M2-1, 3)``."""
        return self.params[: self.m1 * (self.m2 - 1)].reshape(self.m1, self.m2 - 1, 3)

    def pole(self, name: str) -> NDArray:
        """One of ``cN``, ``cS``, ``T1N``, ``T2N``, ``T1S``, ``T2S``."""
        return self.params[self._idx[name]]

    # -- constructors -------------------------------------------------------------------------
    @classmethod
    def from_parts(cls, interior: ArrayLike, cN: ArrayLike, cS: ArrayLike, T1N: ArrayLike,
                   T2N: ArrayLike, T1S: ArrayLike, T2S: ArrayLike) -> "SphereModel":
        """Assemble a sphere from its interior rows ``(M1, M2-1, 3)``, poles and tangents."""
        interior = np.asarray(interior, dtype=np.float64)
        m1, m2m1, _ = interior.shape
        params = np.vstack([interior.reshape(-1, 3), cN, cS, T1N, T2N, T1S, T2S])
        return cls(m1, m2m1 + 1, params)

    @classmethod
    def unit(cls, m1: int = 9, m2: int = 9) -> "SphereModel":
        """The exact unit sphere ``(cos 2pi u sin pi v, sin 2pi u sin pi v, cos pi v)``.

        The pole tangents that make it exact are ``T1N = (pi, 0, 0)``, ``T2N = (0, pi, 0)``,
        ``T1S = (-pi, 0, 0)``, ``T2S = (0, -pi, 0)`` (``sigma_v`` at the poles); the papers'
        "natural choice" (1, 0, 0) leaves out that scale (design.md).
        """
        k = np.arange(m1)[:, None]
        l = np.arange(1, m2)[None, :]
        a, b = 2 * np.pi * k / m1, np.pi * l / m2
        interior = np.stack(np.broadcast_arrays(np.cos(a) * np.sin(b), np.sin(a) * np.sin(b),
                                                np.cos(b)), axis=-1)
        pi = np.pi
        return cls.from_parts(interior, (0, 0, 1), (0, 0, -1), (pi, 0, 0), (0, pi, 0),
                              (-pi, 0, 0), (0, -pi, 0))

    @classmethod
    def ellipsoid(cls, center: ArrayLike = (0, 0, 0), radii: ArrayLike = (1, 1, 1),
                  rotation: ArrayLike | None = None, m1: int = 9, m2: int = 9) -> "SphereModel":
        """Exact ellipsoid ``R diag(radii) s + center`` (``s`` the unit sphere).

        ``rotation`` is a 3x3 matrix whose columns are the ellipsoid's axes (identity default).
        """
        R = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
        A = R @ np.diag(np.asarray(radii, dtype=np.float64))
        return cls.unit(m1, m2).transformed(A, center)

    @classmethod
    def from_points(cls, points: ArrayLike, north: ArrayLike, south: ArrayLike) -> "SphereModel":
        """Interpolate a parameterized point grid (000 sec. 6.2).

        Parameters
        ----------
        points : array_like, shape (M1, M2-1, 3)
            Samples ``p[k, l] = sigma(k/M1, l/M2)`` for ``l = 1..M2-1``.
        north, south : array_like, shape (3,)
            The pole samples ``sigma(., 0)`` and ``sigma(., 1)``.

        Notes
        -----
        The pole tangents are estimated from the first ring of latitude next to each pole
        (000 sec. 7.1.2): the first Fourier harmonic of the ring around the pole, projected onto
        the plane that best fits the ring and scaled by ``pi / sin(pi / M2)``. That scale makes the
        estimate exact for any sphere or ellipsoid (an affine image of the unit sphere, whose ring
        is ``cN + sin(pi/M2) (cos, sin, 0) + ...``), so such shapes are reproduced exactly.
        """
        points = np.asarray(points, dtype=np.float64)
        m1, m2m1, _ = points.shape
        m2 = m2m1 + 1
        north = np.asarray(north, dtype=np.float64)
        south = np.asarray(south, dtype=np.float64)
        T1N, T2N = _ring_tangents(points[:, 0] - north, m2)
        T1S, T2S = _ring_tangents(points[:, -1] - south, m2)
        return cls.from_parts(points, north, south, T1N, T2N, -T1S, -T2S)

    # -- meshes -------------------------------------------------------------------------------
    def triangles(self, samples_u: int | None = None, samples_v: int | None = None,
                  **kwargs: Any) -> tuple[NDArray, NDArray]:
        """Closed, manifold triangle mesh with both poles as single vertices.

        Parameters
        ----------
        samples_u, samples_v : int, optional
            Vertices around and intervals along; default 8 per control interval.
        """
        nu = samples_u or 8 * self.m1
        nv = samples_v or 8 * self.m2
        u = np.arange(nu) / nu
        v = np.arange(1, nv) / nv
        n_ring = nu * (nv - 1)
        pts = np.empty((n_ring + 2, 3))
        # row j = v index (filled in place: a brain's mask mesh has 780 000 vertices)
        pts[:n_ring].reshape(nv - 1, nu, 3)[...] = np.transpose(self.positions(u, v), (1, 0, 2))
        pts[n_ring], pts[n_ring + 1] = self.pole("cN"), self.pole("cS")
        caps = self._cap_faces(nu, n_ring, 0, n_ring + 1, (nv - 2) * nu)
        return self._outward(pts, self._grid_faces(nu, nv - 1, tail=caps))


def _ring_tangents(ring: NDArray, m2: int) -> tuple[NDArray, NDArray]:
    """Tangent vectors at a pole from the ring of latitude next to it (relative positions)."""
    m1 = len(ring)
    theta = 2 * np.pi * np.arange(m1) / m1
    scale = np.pi / np.sin(np.pi / m2)
    t1 = scale * 2.0 / m1 * (np.cos(theta) @ ring)
    t2 = scale * 2.0 / m1 * (np.sin(theta) @ ring)
    # Project onto the plane that best fits the ring (through its centroid): the two leading
    # principal directions. For a planar ring (any ellipsoid) this changes nothing.
    centred = ring - ring.mean(axis=0)
    _, svals, vt = np.linalg.svd(centred, full_matrices=False)
    if svals[1] > 1e-12 * max(svals[0], 1e-300):
        normal = vt[2]
        t1 = t1 - (t1 @ normal) * normal
        t2 = t2 - (t2 @ normal) * normal
    return t1, t2


# ---------------------------------------------------------------------------------------------
class CylinderModel(SplineSurface):
    """Open deformable cylinder (Schmitter's thesis, sec. 7.3).

    Periodic ``phi_{M1}`` around, Keys' cubic convolution kernel along the axis. All
    ``M1 x (M2 + 3)`` control points are free (``l = -1..M2+1``, k-major). The ends are open;
    the mask and the volume close them with planar caps through the end rings ``sigma(., 0)``
    and ``sigma(., 1)`` (each cap is the fan from the ring's centroid).
    """

    kind = "cylinder"
    orientation = -1

    def _check_sizes(self) -> None:
        super()._check_sizes()
        if self.m2 < 1:
            raise ValueError(f"M2 must be >= 1 for a cylinder, got {self.m2}")

    @property
    def n_params(self) -> int:
        return self.m1 * (self.m2 + 3)

    def _basis_v(self, v: NDArray, deriv: int) -> NDArray:
        t = self.m2 * np.asarray(v, dtype=np.float64)[:, None] - self.l_index[None, :]
        return keys(t, deriv) * self.m2**deriv

    def _constraint_matrix(self) -> sp.csr_matrix:
        return sp.identity(self.n_params, format="csr")

    # -- constructors -------------------------------------------------------------------------
    @classmethod
    def unit(cls, m1: int = 8, m2: int = 4) -> "CylinderModel":
        """Exact cylinder of radius 1 along z from 0 to 1: ``c[k,l] = (cos 2pi k/M1, sin, l/M2)``."""
        k = np.arange(m1)[:, None]
        l = np.arange(-1, m2 + 2)[None, :]
        a = 2 * np.pi * k / m1
        c = np.stack(np.broadcast_arrays(np.cos(a), np.sin(a), l / m2), axis=-1)
        return cls(m1, m2, c.reshape(-1, 3))

    @classmethod
    def from_axis(cls, start: ArrayLike, end: ArrayLike, radius: float, m1: int = 8,
                  m2: int = 4) -> "CylinderModel":
        """Straight cylinder of the given radius between two axis end points."""
        start = np.asarray(start, dtype=np.float64)
        end = np.asarray(end, dtype=np.float64)
        axis = end - start
        length = np.linalg.norm(axis)
        if length <= 0:
            raise ValueError("cylinder axis end points coincide")
        e3 = axis / length
        e1, e2 = orthonormal_pair(e3)
        A = np.column_stack([radius * e1, radius * e2, axis])
        return cls.unit(m1, m2).transformed(A, start)

    @classmethod
    def from_centerline(cls, points: ArrayLike, radii: ArrayLike | float, m1: int = 8,
                        m2: int | None = None) -> "CylinderModel":
        """Tube along a curved centerline (a polyline) with a radius per polyline point.

        Parameters
        ----------
        points : array_like, shape (N, 3)
            N >= 2 points along the tube, in order, no two consecutive ones equal.
        radii : array_like, shape (N,), or float
            The tube's radius at each point (or one for all), > 0.
        m1 : int
            Control points around.
        m2 : int, optional
            Control intervals along; default :func:`axial_rings` of the curve's length and mean
            radius (about one ring per diameter).

        Returns
        -------
        CylinderModel
            Ring ``l`` (``l = 0..M2``) is the circle of the interpolated radius around the point
            at arc length ``l / M2`` of the curve, in the plane normal to its tangent, so
            ``sigma(., l / M2)`` passes through it (the splines interpolate). The curve is the
            cubic spline through the points (chord-length parameter, not-a-knot ends; the
            straight segment for two points), which keeps a few clicks along an arch on the arch
            instead of cutting its corners. Rings ``-1`` and ``M2 + 1`` continue the end
            tangents by one ring spacing, radii extrapolated linearly (so a straight or conical
            tube is reproduced exactly). The rings' frames are rotation-minimizing (double
            reflection, Wang et al. 2008), so the tube does not twist.

        Raises
        ------
        ValueError
            Fewer than 2 points, non-finite values, two consecutive equal points, radii <= 0.
        """
        from scipy.interpolate import CubicSpline

        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2:
            raise ValueError("centerline must be an (N >= 2, 3) array")
        r = np.broadcast_to(np.asarray(radii, dtype=np.float64), (len(pts),)).copy()
        if not (np.all(np.isfinite(pts)) and np.all(np.isfinite(r))):
            raise ValueError("centerline points and radii must be finite")
        if np.any(r <= 0):
            raise ValueError(f"centerline radii must be > 0, got {float(r.min()):g}")
        chord = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        if np.any(chord <= 0):
            k = int(np.argmax(chord <= 0))
            raise ValueError(f"centerline points {k + 1} and {k + 2} coincide")
        t = np.concatenate([[0.0], np.cumsum(chord)])
        if len(pts) == 2:
            curve = CubicSpline(t, pts, bc_type=((1, (pts[1] - pts[0]) / t[1]),
                                                 (1, (pts[1] - pts[0]) / t[1])))
        else:
            curve = CubicSpline(t, pts, bc_type="not-a-knot")
        # Arc length of the spline against its parameter, on a fine grid (32 per segment).
        tt = np.concatenate([np.linspace(t[i], t[i + 1], 33)[:-1] for i in range(len(t) - 1)]
                            + [t[-1:]])
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(curve(tt), axis=0),
                                                              axis=1))])
        length = float(arc[-1])
        if m2 is None:
            m2 = axial_rings(length, float(np.mean(r)))
        h = length / m2
        t_ring = np.interp(np.arange(m2 + 1) * h, arc, tt)
        centers = curve(t_ring)
        tangents = curve(t_ring, 1)
        tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
        rad = np.interp(t_ring, t, r)
        # Rings -1 and M2+1: one spacing beyond the ends along the end tangents.
        rad_ends = [rad[0] - (rad[1] - rad[0]), rad[-1] + (rad[-1] - rad[-2])]
        rad = np.concatenate([[max(rad_ends[0], 0.5 * rad[0])], rad,
                              [max(rad_ends[1], 0.5 * rad[-1])]])
        centers = np.vstack([centers[0] - h * tangents[0], centers, centers[-1] + h * tangents[-1]])
        tangents = np.vstack([tangents[:1], tangents, tangents[-1:]])
        f1 = [orthonormal_pair(tangents[0])[0]]
        for j in range(1, len(centers)):  # double reflection (rotation-minimizing frames)
            v1 = centers[j] - centers[j - 1]
            c1 = v1 @ v1
            r_l = f1[-1] - (2.0 / c1) * (v1 @ f1[-1]) * v1
            t_l = tangents[j - 1] - (2.0 / c1) * (v1 @ tangents[j - 1]) * v1
            v2 = tangents[j] - t_l
            c2 = v2 @ v2
            nxt = r_l - (2.0 / c2) * (v2 @ r_l) * v2 if c2 > 1e-300 else r_l
            nxt = nxt - (nxt @ tangents[j]) * tangents[j]  # rounding only
            f1.append(nxt / np.linalg.norm(nxt))
        theta = 2 * np.pi * np.arange(m1) / m1
        c = np.empty((m1, m2 + 3, 3))
        for j in range(m2 + 3):
            e1 = f1[j]
            e2 = np.cross(tangents[j], e1)  # (e1, e2, tangent) right-handed: outward normals
            c[:, j] = centers[j] + rad[j] * (np.cos(theta)[:, None] * e1
                                             + np.sin(theta)[:, None] * e2)
        return cls(m1, m2, c.reshape(-1, 3))

    def reversed(self) -> "CylinderModel":
        """u -> -u: rows k -> -k mod M1."""
        order = (-np.arange(self.m1)) % self.m1
        grid = self.params.reshape(self.m1, self.m2 + 3, 3)[order]
        return self.with_params(grid.reshape(-1, 3))

    # -- geometry -----------------------------------------------------------------------------
    def end_rings(self, samples_u: int) -> tuple[NDArray, NDArray]:
        """The rings ``sigma(u, 0)`` and ``sigma(u, 1)`` at ``samples_u`` points each."""
        u = np.arange(samples_u) / samples_u
        s, _, _ = self.evaluate(u, [0.0, 1.0])
        return s[:, 0], s[:, 1]

    def axis_and_radius(self) -> tuple[NDArray, NDArray, float]:
        """Centre of the ``v = 0`` end ring, the vector to the ``v = 1`` ring's centre, and the
        ``v = 0`` ring's mean radius."""
        r0, r1 = self.end_rings(4 * self.m1)
        c0 = r0.mean(axis=0)
        return c0, r1.mean(axis=0) - c0, float(np.linalg.norm(r0 - c0, axis=1).mean())

    def volume(self, order: int = 8) -> float:
        """Volume closed by planar caps through the end rings.

        By the divergence theorem each planar cap adds ``1/3 (c . n) A``; its vector area
        ``1/2 integral (sigma - c) x sigma_u du`` is integrated with the same Gauss-Legendre rule
        as the lateral part, so the result is exact to quadrature precision for any cap whose
        ring is planar (``c`` is the ring's mean point, which lies in that plane).
        """
        lateral = super().volume(order)
        u, wu = gauss_legendre_grid(self.m1, order)
        s, su, _ = self.evaluate(u, [0.0, 1.0])
        cap = 0.0
        for j, sign in ((0, -1.0), (1, 1.0)):
            ring, d_ring = s[:, j], su[:, j]
            c = wu @ ring  # mean point of the ring (weights sum to 1)
            vec = 0.5 * (wu @ np.cross(ring - c, d_ring))
            # vec follows increasing u; on an outward cylinder (orientation -1) it points along
            # +sigma_v, and the outward cap normal is -sigma_v at v = 0, +sigma_v at v = 1.
            cap += sign * -self.orientation * (c @ vec) / 3.0
        return lateral + cap

    def triangles(self, samples_u: int | None = None, samples_v: int | None = None,
                  caps: bool = True, **kwargs: Any) -> tuple[NDArray, NDArray]:
        """Triangle mesh of the lateral surface, closed by planar end caps when ``caps``."""
        nu = samples_u or 8 * self.m1
        nv = samples_v or 8 * self.m2
        u = np.arange(nu) / nu
        v = np.linspace(0.0, 1.0, nv + 1)
        n0 = nu * (nv + 1)
        pts = np.empty((n0 + 2 * caps, 3))
        pts[:n0].reshape(nv + 1, nu, 3)[...] = np.transpose(self.positions(u, v), (1, 0, 2))
        ends = self._cap_faces(nu, n0, 0, n0 + 1, nv * nu) if caps else []
        if caps:
            pts[n0], pts[n0 + 1] = pts[:nu].mean(axis=0), pts[nv * nu:n0].mean(axis=0)
        return self._outward(pts, self._grid_faces(nu, nv + 1, tail=ends))


#: Bounds of the axial control-interval count M2 chosen from a tube's length
#: (:func:`axial_rings`): at least 4 (the cylinder's default M2 and the smallest --m2 the options
#: take), at most 32 (a tube longer than 32 diameters gets rings more than a diameter apart;
#: --m2 gives more).
AXIAL_RINGS_MIN = 4
AXIAL_RINGS_MAX = 32
#: Control rings per diameter of a tube's length: two, so that a change of calibre or of
#: direction over one diameter is sampled at its Nyquist rate (measured on the lung2 trachea,
#: M2 = 6, 8, 10, 12, 16 from the start: Dice 0.814, 0.853, 0.859, 0.868, 0.861; one ring per
#: diameter chose 6).
RINGS_PER_DIAMETER = 2.0


def axial_rings(length: float, mean_radius: float) -> int:
    """M2 for a tube: :data:`RINGS_PER_DIAMETER` control rings per diameter along it.

    ``clip(round(RINGS_PER_DIAMETER * length / (2 * mean_radius)), AXIAL_RINGS_MIN,
    AXIAL_RINGS_MAX)``.

    Parameters
    ----------
    length : float
        The tube's centerline length (mm).
    mean_radius : float
        Its mean radius (mm), > 0.

    Returns
    -------
    int
    """
    if not (math.isfinite(length) and math.isfinite(mean_radius) and mean_radius > 0):
        raise ValueError(f"a tube needs a finite length and a radius > 0, got {length:g}, "
                         f"{mean_radius:g}")
    rings = round(RINGS_PER_DIAMETER * length / (2.0 * mean_radius))
    return int(min(max(rings, AXIAL_RINGS_MIN), AXIAL_RINGS_MAX))


def orthonormal_pair(e3: NDArray) -> tuple[NDArray, NDArray]:
    """Two unit vectors completing the unit ``e3`` (``(3,)`` or ``(n, 3)``) to right-handed
    orthonormal frames (e1, e2, e3)."""
    e3 = np.asarray(e3, dtype=np.float64)
    helper = np.where(np.abs(e3[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    e1 = np.cross(helper, e3)
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    return e1, np.cross(e3, e1)


_KINDS: dict[str, Callable[..., SplineSurface]] = {"sphere": SphereModel, "cylinder": CylinderModel}


def model_from_dict(d: dict[str, Any]) -> SplineSurface:
    """Rebuild a model from :meth:`SplineSurface.to_dict` output."""
    if d.get("format") != "segsnake-model":
        raise ValueError("not a segsnake model (missing 'format: segsnake-model')")
    kind = d.get("kind")
    if kind not in _KINDS:
        raise ValueError(f"unknown model kind {kind!r}; expected one of {sorted(_KINDS)}")
    return _KINDS[kind](int(d["m1"]), int(d["m2"]), np.asarray(d["params"], dtype=np.float64))


def load_model(path: str | os.PathLike) -> SplineSurface:
    """Load a model saved with :meth:`SplineSurface.save` (or a ``snake.json`` with a ``model``)."""
    with open(path, encoding="utf-8") as fh:
        d = json.load(fh)
    if "model" in d and isinstance(d["model"], dict):
        d = d["model"]
    return model_from_dict(d)
