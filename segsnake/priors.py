"""Shape-prior energies from affine projectors (Schmitter's thesis, secs. 3.7.3 and 5.4).

``E_prior = gamma * || sigma - P sigma ||^2_L2``, where ``P`` is the L2-orthogonal projector onto
the shape space of a reference surface: every image ``A sigma_ref + b`` of the reference under
the allowed transformations. With the unit sphere as reference and the affine space, the shape
space is every ellipsoid, so the prior pulls towards ellipsoids without pulling the surface
inwards or outwards; it also penalizes what the flux energy cannot see (folds, bunched control
points, drifting poles), which is why the pipeline uses it as the snake's internal energy.

Here the L2 inner product is evaluated by Gauss-Legendre quadrature on the model's knot grid
(exact to rounding for a high enough order, since the integrands are smooth on each knot
cell), and ``P`` is applied as a weighted least-squares fit of the reference's coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from segsnake.surfaces import SplineSurface

__all__ = ["SPACES", "AffinePrior", "shape_space_basis"]

SPACES = ("affine", "linear", "similarity", "translation")


def shape_space_basis(ref_points: NDArray, space: str) -> NDArray:
    """Columns spanning the shape space, per coordinate, at the quadrature nodes.

    Returns an array ``(n_nodes * 3, d)``: each column is one shape (stacked x, y, z samples).
    ``affine``: ``A sigma_ref + b`` (12 columns); ``linear``: ``A sigma_ref`` (9);
    ``similarity``: ``s sigma_ref + b`` (4: isotropic scaling and translation; rotations do not
    form a linear space, so this is the linear part of a similarity prior); ``translation``:
    the 3 translations only (the prior then measures ``sigma - sigma_ref`` against them, see
    :class:`AffinePrior`).
    """
    n = len(ref_points)
    cols = []
    if space in ("affine", "linear"):
        for d in range(3):  # output coordinate d gets reference coordinate e
            for e in range(3):
                col = np.zeros((n, 3))
                col[:, d] = ref_points[:, e]
                cols.append(col.ravel())
    elif space == "similarity":
        cols.append(ref_points.ravel())
    elif space != "translation":
        raise ValueError(f"unknown shape space {space!r}; expected one of {SPACES}")
    if space != "linear":
        for d in range(3):
            col = np.zeros((n, 3))
            col[:, d] = 1.0
            cols.append(col.ravel())
    return np.column_stack(cols)


@dataclass
class AffinePrior:
    """``weight * ||sigma - P sigma||^2`` over the model's parameter domain.

    Parameters
    ----------
    model : SplineSurface
        Kind and size of the snake (its quadrature grid is precomputed).
    reference : SplineSurface
        Reference shape of the same kind and size.
    weight : float
        gamma.
    space : str
        One of :data:`SPACES`.
    order : int
        Gauss-Legendre nodes per knot interval.
    """

    model: SplineSurface
    reference: SplineSurface
    weight: float = 1.0
    space: str = "affine"
    order: int = 4

    def __post_init__(self) -> None:
        if (self.reference.kind, self.reference.m1, self.reference.m2) != \
                (self.model.kind, self.model.m1, self.model.m2):
            raise ValueError("the reference must have the snake's kind and control-point counts")
        self.basis, w = self.model.quadrature(self.order)
        ref, _, _ = self.basis.evaluate(self.reference.control_points())
        self._w = np.repeat(w.ravel(), 3)  # per stacked coordinate
        X = shape_space_basis(ref.reshape(-1, 3), self.space)
        # Weighted least squares via QR of W^1/2 X: P y = X (X^T W X)^-1 X^T W y, stably.
        sw = np.sqrt(self._w)
        self._q, _ = np.linalg.qr(sw[:, None] * X)
        self._sw = sw
        # sigma_ref + b is an affine (not linear) set: measure sigma - sigma_ref against b.
        self._offset = ref.ravel() if self.space == "translation" else np.zeros(ref.size)

    def residual(self, sigma: NDArray) -> NDArray:
        """``W^1/2 (sigma - P sigma)`` for stacked samples ``sigma (n_nodes * 3,)``."""
        y = self._sw * (sigma - self._offset)
        return y - self._q @ (self._q.T @ y)

    def value_and_grad(self, params: NDArray) -> tuple[float, NDArray]:
        C = self.model.control_points(params)
        s, _, _ = self.basis.evaluate(C)
        r = self.residual(s.ravel())
        value = float(r @ r)
        # d/dsigma ||W^1/2 (I - P) sigma||^2 = 2 W^1/2 (I - P_w) W^1/2 ... = 2 sw * r (P_w is
        # orthogonal in the weighted space, so (I - Q Q^T) is symmetric and idempotent).
        g = (2.0 * self._sw * r).reshape(s.shape)
        zero = np.zeros_like(g)
        grad = self.model.grid_gradient_to_params(self.basis.adjoint(g, zero, zero))
        return self.weight * value, self.weight * grad
