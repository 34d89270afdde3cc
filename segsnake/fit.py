"""Least-squares fit of a deformable sphere to a parameterized surface (issue 19, item 1).

Two problems, both linear in the free parameters ``p`` (P x 3) of a :class:`SphereModel`:

* **A surface given as a function** ``f(u, v)`` (an analytic surface, or the piecewise-linear
  mesh surface of a :class:`segsnake.parameterize.SphericalMap`): the L2 projection over the
  parameter domain, ``min_p ||sigma_p - f||^2_L2``. Its normal equations are ``B p = A^T r`` with
  ``B = A^T beta A`` the *exact* Gram matrix of the model (:func:`segsnake.priors.grid_gram`,
  ``A`` the constraint map from free parameters to the control grid) and
  ``r[k, l] = integral b_k(u) b_l(v) f(u, v) du dv`` integrated with Gauss-Legendre nodes in every
  knot interval. ``B`` is sparse (generators of support 4), so the solve is a sparse Cholesky-
  type factorization even for thousands of control points. A surface the model reproduces (any
  ellipsoid) is returned exactly: the projection of an element of the space is itself, and the
  integrands are smooth inside the knot intervals, where Gauss-Legendre is exact to rounding.
* **Parameterized samples** ``x_i`` at ``(u_i, v_i)`` (a parameterized point cloud, seed 000
  sec. 6.2): discrete least squares ``min_p sum_i |x_i - sigma_p(u_i, v_i)|^2`` with the sparse
  design matrix, also exact for samples of a reproducible surface.

Errors are reported as seed 004 does: at the input samples, ``e_i = |x_i - sigma(u_i, v_i)|``,
RMS and maximum, in mm and in % of the diagonal of the samples' bounding box.
:func:`fit_until` raises M (with ``M1 = 2 M2``: u runs once around, v half-way) until an RMS
target is met.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

from segsnake.priors import grid_gram
from segsnake.surfaces import SphereModel, gauss_legendre_grid

if TYPE_CHECKING:  # the parameterization (scipy.interpolate) is imported when a mesh is fitted
    from segsnake.parameterize import SphericalMap

__all__ = ["DEFAULT_RMS_PERCENT", "FitResult", "fit_mesh", "fit_cloud", "FitError", "M2_SCHEDULE", "QUADRATURE_ORDER", "fit_function", "fit_samples",
           "fit_errors", "fit_until", "FitStep"]

#: Gauss-Legendre nodes per knot interval of the projection's right-hand side.
QUADRATURE_ORDER = 6

#: RMS target of ``segsnake fit`` without --m1/--m2 or --rms-target, in % of the diagonal.
DEFAULT_RMS_PERCENT = 0.5

#: The M2 values :func:`fit_until` tries in turn (M1 = 2 M2).
M2_SCHEDULE = (4, 6, 8, 12, 16, 24, 32, 40, 48)


@dataclass(frozen=True)
class FitError:
    """Fitting errors at the samples (seed 004's measures)."""

    rms: float
    max: float
    diagonal: float

    @property
    def rms_percent(self) -> float:
        """RMS error in % of the bounding-box diagonal."""
        return 100.0 * self.rms / self.diagonal

    @property
    def max_percent(self) -> float:
        """Maximal error in % of the bounding-box diagonal."""
        return 100.0 * self.max / self.diagonal


@dataclass
class FitStep:
    """One size tried by :func:`fit_until`."""

    m1: int
    m2: int
    n_params: int
    error: FitError
    model: SphereModel = field(repr=False)


def _template(m1: int, m2: int) -> SphereModel:
    return SphereModel.unit(m1, m2)


def _solve_gram(model: SphereModel, rhs: NDArray) -> NDArray:
    """``B^-1 rhs`` with the exact sparse Gram matrix ``B = A^T beta A`` of the free parameters."""
    A = model.constraint
    B = (A.T @ grid_gram(model) @ A).tocsc()
    return spla.splu(B).solve(np.ascontiguousarray(rhs))


def fit_function(f: Callable[[NDArray, NDArray], NDArray], m1: int, m2: int,
                 order: int = QUADRATURE_ORDER) -> SphereModel:
    """L2 projection of a surface ``f(u, v)`` on the sphere model with ``M1 x M2`` control points.

    Parameters
    ----------
    f : callable
        ``f(U, V)`` with arrays ``U, V`` of shape ``(nu, nv)`` returns points ``(nu, nv, 3)``.
    m1, m2 : int
        Control points around and along.
    order : int
        Gauss-Legendre nodes per knot interval for the right-hand side.

    Returns
    -------
    SphereModel
    """
    model = _template(m1, m2)
    u, wu = gauss_legendre_grid(m1, order)
    v, wv = gauss_legendre_grid(m2, order)
    U, V = np.meshgrid(u, v, indexing="ij")
    F = np.asarray(f(U, V), dtype=np.float64) * (wu[:, None] * wv[None, :])[..., None]
    bu = model._basis_u(u, 0)  # (nu, M1)
    bv = model._basis_v(v, 0)  # (nv, L)
    grid_rhs = np.einsum("uk,uvd,vl->kld", bu, F, bv, optimize=True)  # (M1, L, 3)
    rhs = model.constraint.T @ grid_rhs.reshape(-1, 3)
    return model.with_params(_solve_gram(model, rhs))


def _support(values: NDArray, width: int = 4) -> tuple[NDArray, NDArray]:
    """Column indices and values of the ``width`` largest entries of each row (the support)."""
    width = min(width, values.shape[1])
    idx = np.argpartition(-np.abs(values), width - 1, axis=1)[:, :width]
    return idx, np.take_along_axis(values, idx, axis=1)


def _design_matrix(model: SphereModel, u: NDArray, v: NDArray) -> sp.csr_matrix:
    """Sparse ``(n, P)`` matrix of ``sigma(u_i, v_i) = D p`` (generators of support 4)."""
    n_l = model.m2 + 3
    ku, au = _support(model._basis_u(u, 0))
    lv, av = _support(model._basis_v(v, 0))
    cols = (ku[:, :, None] * n_l + lv[:, None, :]).reshape(len(u), -1)
    vals = (au[:, :, None] * av[:, None, :]).reshape(len(u), -1)
    rows = np.repeat(np.arange(len(u)), cols.shape[1])
    grid = sp.csr_matrix((vals.ravel(), (rows, cols.ravel())), shape=(len(u), model.m1 * n_l))
    return (grid @ model.constraint).tocsr()


def fit_samples(points: NDArray, u: NDArray, v: NDArray, m1: int, m2: int) -> SphereModel:
    """Discrete least squares through parameterized samples (a parameterized point cloud).

    Raises
    ------
    ValueError
        Fewer samples than parameters, or samples that leave some parameters undetermined.
    """
    model = _template(m1, m2)
    points = np.asarray(points, dtype=np.float64)
    if len(points) < model.n_params:
        raise ValueError(f"{len(points)} samples cannot determine {model.n_params} control "
                         f"parameters (M1={m1}, M2={m2}); use fewer control points")
    D = _design_matrix(model, np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64))
    N = (D.T @ D).tocsc()
    try:
        params = spla.splu(N).solve(np.ascontiguousarray(D.T @ points))
    except RuntimeError:
        raise ValueError("the samples leave some control parameters undetermined "
                         "(no samples near some control points); use fewer control points") from None
    if not np.all(np.isfinite(params)):
        raise ValueError("the samples leave some control parameters undetermined")
    return model.with_params(params)


def fit_errors(model: SphereModel, points: NDArray, u: NDArray, v: NDArray) -> FitError:
    """RMS and maximal ``|x_i - sigma(u_i, v_i)|`` and the bounding-box diagonal of the samples."""
    points = np.asarray(points, dtype=np.float64)
    e = np.linalg.norm(points - model(u, v), axis=1)
    diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    return FitError(rms=float(np.sqrt(np.mean(e * e))), max=float(e.max()), diagonal=diagonal)


def fit_until(fit: Callable[[int, int], SphereModel], points: NDArray, u: NDArray, v: NDArray,
              rms_target: float, schedule: Sequence[int] = M2_SCHEDULE) -> list[FitStep]:
    """Fit with ``M2`` from ``schedule`` (``M1 = 2 M2``) until the RMS error is ``<= rms_target``.

    Parameters
    ----------
    fit : callable
        ``fit(m1, m2)`` returns a model (e.g. a closure over :func:`fit_function`).
    points, u, v : ndarray
        The samples the errors are measured at, with their parameters.
    rms_target : float
        RMS error to reach, in the points' units.
    schedule : sequence of int
        The M2 values to try, increasing.

    Returns
    -------
    list of FitStep
        Every size tried; the last one met the target, or is the largest of the schedule.
    """
    steps: list[FitStep] = []
    for m2 in schedule:
        m1 = 2 * m2
        model = fit(m1, m2)
        err = fit_errors(model, points, u, v)
        steps.append(FitStep(m1, m2, model.n_params, err, model))
        if err.rms <= rms_target:
            break
    return steps


@dataclass
class FitResult:
    """Every size tried, the RMS target, and the parameterization used (for meshes)."""

    steps: list[FitStep]
    rms_target: float | None
    spherical_map: "SphericalMap | None" = None

    @property
    def model(self) -> SphereModel:
        """The last (largest) fit."""
        return self.steps[-1].model

    @property
    def target_met(self) -> bool:
        """Whether the last fit reached the RMS target (True for a fixed size)."""
        return self.rms_target is None or self.steps[-1].error.rms <= self.rms_target


def _fit_sizes(fit: Callable[[int, int], SphereModel], pts: NDArray, u: NDArray, v: NDArray,
               m1: int | None, m2: int | None, rms_target: float | None,
               schedule: Sequence[int]) -> tuple[list[FitStep], float | None]:
    """A fixed size, or the schedule until the RMS target (default: a share of the diagonal)."""
    if m1 is not None and m2 is not None:
        model = fit(m1, m2)
        return [FitStep(m1, m2, model.n_params, fit_errors(model, pts, u, v), model)], None
    if rms_target is None:
        diagonal = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
        rms_target = DEFAULT_RMS_PERCENT / 100.0 * diagonal
    return fit_until(fit, pts, u, v, rms_target, schedule), rms_target


def fit_mesh(points: NDArray, faces: NDArray, *, m1: int | None = None, m2: int | None = None,
             rms_target: float | None = None, samples: NDArray | None = None,
             schedule: Sequence[int] = M2_SCHEDULE) -> FitResult:
    """Parameterize a closed genus-0 mesh over the sphere and fit the sphere model to it.

    Parameters
    ----------
    points, faces : ndarray
        The mesh (``(n, 3)`` vertices, ``(m, 3)`` triangles).
    m1, m2 : int, optional
        A fixed size; otherwise M2 runs through ``schedule`` (M1 = 2 M2) until ``rms_target``.
    rms_target : float, optional
        RMS error to reach (points' units); default :data:`DEFAULT_RMS_PERCENT` of the diagonal.
    samples : ndarray, optional
        Where the errors are measured (default the vertices); e.g. the point cloud a mesh was
        reconstructed from, parameterized by their closest mesh points.
    schedule : sequence of int
        The M2 values to try.

    Returns
    -------
    FitResult

    Raises
    ------
    segsnake.parameterize.TopologyError
        The mesh is not a closed genus-0 manifold.
    """
    from segsnake.parameterize import spherical_parameterization

    smap = spherical_parameterization(points, faces)
    if samples is None:
        pts, u, v = smap.points, smap.u, smap.v
    else:
        pts = np.asarray(samples, dtype=np.float64)
        u, v = smap.parameters_of(pts)

    def fit(a: int, b: int) -> SphereModel:
        return fit_function(smap.surface_at, a, b)

    steps, target = _fit_sizes(fit, pts, u, v, m1, m2, rms_target, schedule)
    return FitResult(steps, target, smap)


def fit_cloud(points: NDArray, u: NDArray, v: NDArray, *, m1: int | None = None,
              m2: int | None = None, rms_target: float | None = None,
              schedule: Sequence[int] = M2_SCHEDULE) -> FitResult:
    """Fit a parameterized point cloud (discrete least squares, :func:`fit_samples`).

    Sizes with more parameters than points are left out of ``schedule``.

    Raises
    ------
    ValueError
        Too few points for any size, or for the fixed one.
    """
    pts = np.asarray(points, dtype=np.float64)
    schedule = [m for m in schedule if _template(2 * m, m).n_params <= len(pts)]
    if m1 is None and not schedule:
        raise ValueError(f"{len(pts)} points are too few to fit any size")

    def fit(a: int, b: int) -> SphereModel:
        return fit_samples(pts, u, v, a, b)

    steps, target = _fit_sizes(fit, pts, u, v, m1, m2, rms_target, schedule)
    return FitResult(steps, target)
