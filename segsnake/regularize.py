"""The snake's internal energy: bending of the deviation from the nearest affine reference shape.

``E = w * sum_q W_q ( h_u^4 |r_uu|^2 + 2 h_u^2 h_v^2 |r_uv|^2 + h_v^4 |r_vv|^2 )`` with
``r = sigma - P sigma`` the residual after the L2 best affine fit of a reference (the unit sphere
for a sphere snake, the unit cylinder for a cylinder snake) and ``h = 1 / M`` the knot spacing.

* Any affine image of the reference (every ellipsoid, every elliptic cylinder) costs nothing,
  so unlike a membrane or thin-plate energy it exerts no shrinking force on a round object.
* A crease or a fold is a large second derivative of the residual over one knot interval: it
  costs a lot, which is what keeps the flux energies (that a folded surface can lower) honest.
* The fit is a linear map of the parameters and the reference's images act on each coordinate
  separately, so ``E = w * sum_d p_d^T K p_d`` with one fixed ``K (P x P)`` per model size:
  an evaluation is a single small matrix product, the gradient ``2 w K p``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from segsnake.surfaces import CylinderModel, SphereModel, SplineSurface, gauss_legendre_grid

__all__ = ["BendingRegularizer", "bending_matrix"]

_CACHE: dict[tuple[str, int, int, int, bool], NDArray] = {}


def _reference(model: SplineSurface) -> SplineSurface:
    if model.kind == "cylinder":
        return CylinderModel.unit(model.m1, model.m2)
    return SphereModel.unit(model.m1, model.m2)


def bending_matrix(model: SplineSurface, order: int = 4, tube: bool = False) -> NDArray:
    """The matrix ``K`` of the module docstring for the model's kind and size (cached).

    ``tube`` (cylinders): the tube's own bending instead of the deviation from the nearest
    straight elliptic cylinder, which pulls a curved vessel straight: each ring's deviation
    from an ellipse bends as above, and the rings' ellipses (the centerline and the axes) pay
    ``sum_l |third difference along l|^2 / (M1 M2)`` over the control rows, zero for a straight
    elliptic cylinder and small for a tube that bends or turns its axes at a steady rate (an
    arch), large for a kink.
    """
    tube = tube and model.kind == "cylinder"  # (a sphere has no rings: the same matrix)
    key = (model.kind, model.m1, model.m2, order, tube)
    if key in _CACHE:
        return _CACHE[key]
    u, wu = gauss_legendre_grid(model.m1, order)
    v, wv = gauss_legendre_grid(model.m2, order)
    A = model.constraint  # (M1 * L, P), sparse

    def gram(ku: int, kv: int) -> NDArray:
        # sum_q W_q s_q s_q^T over the samples s_q (rows of (Bu ⊗ Bv) A) of sigma's (ku, kv)
        # derivative, per coordinate: A^T (Bu^T Wu Bu ⊗ Bv^T Wv Bv) A, the tensor product's
        # Gram factors (a 37 x 37 grid's samples held 230 MB; the factors hold kilobytes).
        bu, bv = model._basis_u(u, ku), model._basis_v(v, kv)
        grid = np.kron((bu * wu[:, None]).T @ bu, (bv * wv[:, None]).T @ bv)
        return np.asarray((A.T @ (A.T @ grid).T).T)

    hu, hv = 1.0 / model.m1, 1.0 / model.m2
    # The weighted second-derivative samples' Gram matrix, one derivative at a time.
    G = sum((c * c) * gram(ku, kv)
            for (ku, kv), c in (((2, 0), hu * hu), ((1, 1), np.sqrt(2.0) * hu * hv),
                                ((0, 2), hv * hv)))
    if tube:
        # Each control ring's part beyond its best ellipse bends like the surface above; the
        # ellipses themselves (centre and axes, row by row) only pay for third differences
        # along the tube (see :func:`_ellipse_projector`).
        ellipses = _ellipse_projector(model.m1, model.m2 + 3)
        R = np.eye(A.shape[1]) - ellipses
        T = np.kron(np.eye(model.m1), np.diff(np.eye(model.m2 + 3), n=3, axis=0)) @ ellipses
        K = R.T @ G @ R + T.T @ T / (model.m1 * model.m2)
    else:
        ref = _reference(model)
        # The weighted least-squares affine fit of the samples: the fitted affine image of the
        # reference has parameters basis @ fit, ``basis`` (P, 4) the reference's parameters and
        # the translation (points get it, vectors do not), and
        # fit = (basis^T M basis)^-1 basis^T M with M the samples' Gram matrix.
        basis = np.column_stack([ref.params, (~ref.is_vector).astype(float)])
        M = gram(0, 0)
        fit = np.linalg.solve(basis.T @ M @ basis, basis.T @ M)  # (4, P)
        R = np.eye(A.shape[1]) - basis @ fit  # residual parameters, (P, P)
        K = R.T @ G @ R
    K = 0.5 * (K + K.T)
    _CACHE[key] = K
    return K


def _ellipse_projector(m1: int, n_rows: int) -> NDArray:
    """Orthogonal projection of a cylinder's control grid (k-major, ``m1 x n_rows``) onto grids
    whose every row ``c[., l]`` is ``centre_l + a_l cos(2 pi k / m1) + b_l sin(2 pi k / m1)``:
    rings that are exact ellipses (phi_M reproduces {1, cos, sin}). Per coordinate."""
    theta = 2 * np.pi * np.arange(m1) / m1
    F = np.column_stack([np.ones(m1), np.cos(theta), np.sin(theta)])
    return np.kron(F @ np.linalg.solve(F.T @ F, F.T), np.eye(n_rows))


@dataclass
class BendingRegularizer:
    """``weight * sum_d p_d^T K p_d`` (see the module docstring); ``value_and_grad(params)``."""

    model: SplineSurface
    weight: float = 1.0
    tube: bool = False

    def __post_init__(self) -> None:
        self.K = bending_matrix(self.model, tube=self.tube)

    def value_and_grad(self, params: NDArray) -> tuple[float, NDArray]:
        Kp = self.K @ params
        return self.weight * float(np.sum(params * Kp)), 2.0 * self.weight * Kp
