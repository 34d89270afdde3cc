"""Rigid and similarity shape priors: exact projectors with rotations (issue 19, item 4).

The thesis' transformation classes (Table 3.1) include the rigid maps ``R sigma + b`` and the
similarities ``s R sigma + b`` (``R`` a rotation, ``s > 0``). Rotations do not form a linear
space, so unlike the affine spaces of :mod:`segsnake.priors` these shape spaces have no linear
projector; the projection is the L2 Procrustes problem

    P sigma = argmin_{s, R, b} || sigma - (s R sigma_ref + b) ||_L2 ,

solved exactly with the exact Gram matrix ``B`` of the free parameters (thesis eq. (2.21)):

* ``b`` matches the L2 centroids: ``g = (t^T B p) / (t^T B t)`` with ``t`` the translation column
  (1 for control points, 0 for the pole tangent vectors, which rotate and scale but do not move);
* with the centred parameters ``p_c`` and ``r_c``, the cross-covariance ``M = p_c^T B r_c``
  (3 x 3, exact L2 inner products of the coordinates) has the SVD ``U S V^T``; the best rotation is
  ``R = U D V^T`` with ``D = diag(1, 1, det(U V^T))`` (Kabsch: no reflection);
* ``s = 1`` (rigid) or ``s = tr(D S) / ||r_c||^2`` (similarity, clamped at 0).

The energy is ``gamma ||sigma - P sigma||^2``. Its gradient is exactly ``2 gamma B (p - P p)``: the
distance is a minimum over (s, R, b), and at a unique minimizer the derivative of the minimum is the
partial derivative at the minimizer (Danskin's theorem), where ``d/dp ||p - q||^2 = 2 B (p - q)``.
The minimizer is unique unless ``M`` has a repeated smallest singular value with the wrong sign,
a measure-zero set (tests/test_procrustes.py checks the gradient against central differences and
``P P = P``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from segsnake.priors import check_same_size, param_gram
from segsnake.shapes import _centre  # noqa: PLC2701 (same package: the L2 centroid)
from segsnake.surfaces import SplineSurface

__all__ = ["ROTATION_SPACES", "procrustes_fit", "procrustes_project", "ProcrustesPrior"]

ROTATION_SPACES = ("rigid", "similarity")


def procrustes_fit(model: SplineSurface, params: NDArray, reference: NDArray, space: str
                   ) -> tuple[float, NDArray, NDArray]:
    """``(s, R, b)`` minimizing ``||sigma_params - (s R sigma_reference + b)||_L2``.

    Parameters
    ----------
    model : SplineSurface
        Kind and size (the metric and which rows are vectors).
    params, reference : ndarray (P, 3)
        Parameters of the snake and of the reference.
    space : {"rigid", "similarity"}

    Returns
    -------
    s : float
        1 for ``rigid``.
    R : ndarray (3, 3)
        A rotation (determinant +1).
    b : ndarray (3,)
    """
    if space not in ROTATION_SPACES:
        raise ValueError(f"unknown rotation space {space!r}; expected one of {ROTATION_SPACES}")
    B = param_gram(model)
    pc, gp = _centre(model, np.asarray(params, dtype=np.float64))
    rc, gr = _centre(model, np.asarray(reference, dtype=np.float64))
    M = pc.T @ (B @ rc)
    U, S, Vt = np.linalg.svd(M)
    D = np.ones(3)
    D[2] = np.sign(np.linalg.det(U @ Vt)) or 1.0
    R = (U * D) @ Vt
    if space == "rigid":
        s = 1.0
    else:
        norm2 = float(np.sum(rc * (B @ rc)))
        s = max(float(np.sum(D * S)) / norm2, 0.0) if norm2 > 0 else 0.0
    b = gp - s * (R @ gr)
    return s, R, b


def procrustes_project(model: SplineSurface, params: NDArray, reference: NDArray, space: str
                       ) -> NDArray:
    """Parameters of ``P sigma = s R sigma_ref + b``, the closest rigid/similar image of the reference."""
    s, R, b = procrustes_fit(model, params, reference, space)
    t = (~model.is_vector).astype(np.float64)
    return s * np.asarray(reference) @ R.T + t[:, None] * b[None, :]


@dataclass
class ProcrustesPrior:
    """``weight * ||sigma - P sigma||^2_L2`` for the rigid or similarity images of a reference.

    The same interface as :class:`segsnake.priors.AffinePrior` (``distance2``,
    ``value_and_grad``), so a snake's energy takes either.
    """

    model: SplineSurface
    reference: SplineSurface
    weight: float = 1.0
    space: str = "similarity"

    def __post_init__(self) -> None:
        check_same_size(self.model, self.reference)
        if self.space not in ROTATION_SPACES:
            raise ValueError(f"unknown rotation space {self.space!r}; expected one of "
                             f"{', '.join(ROTATION_SPACES)}")
        self._B = param_gram(self.model)

    def project(self, params: NDArray) -> NDArray:
        """Parameters of ``P sigma``."""
        return procrustes_project(self.model, params, self.reference.params, self.space)

    def _residual(self, params: NDArray) -> tuple[float, NDArray]:
        p = np.asarray(params, dtype=np.float64)
        d = p - self.project(p)
        Bd = self._B @ d
        return float(np.sum(d * Bd)), Bd

    def distance2(self, params: NDArray) -> float:
        """``||sigma - P sigma||^2_L2`` (mm^2), without the weight."""
        return self._residual(params)[0]

    def value_and_grad(self, params: NDArray) -> tuple[float, NDArray]:
        """Energy and exact gradient ``2 gamma B (p - P p)`` (Danskin) with respect to ``(P, 3)``."""
        d2, Bd = self._residual(params)
        return self.weight * d2, 2.0 * self.weight * Bd
