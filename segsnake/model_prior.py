"""Shape priors that use what a shape model learned: its mean and first K modes (issue 19, item 4).

A :class:`segsnake.shapes.ShapeModel` (``segsnake shape-model``) holds the mean of an aligned
training set and its principal modes ``xi_k`` (unit L2 norm) with variances ``lambda_k`` (mm^2).
With ``K`` modes the prior measures how far a snake is from the linear span of the transformed
mean plus the modes, and how far along the modes it went, in the spirit of probabilistic PCA
(thesis ch. 5; Tipping and Bishop 1999):

    E(sigma) = gamma * min_{theta, c} ( ||sigma - T_theta(mean) - sum_k c_k xi_k||^2
                                         + rho^2 sum_k c_k^2 / lambda_k ),

with ``T_theta`` ranging over the linear shape space of the mean (``affine``, ``linear``,
``scaling`` or ``translation``, :mod:`segsnake.priors`). ``rho^2`` is the mean variance of the
modes left out (PPCA's noise level; the smallest variance when all are used), so one standard
deviation along a kept mode costs what a typical left-out variation costs; a residual outside the
span costs ``gamma ||r||^2`` exactly as in :class:`segsnake.priors.AffinePrior` (the same
relative weight applies). The modes enter untransformed: they describe variation in the pose of
the model's mean, and the energy stays an exact convex quadratic form of the free parameters.

Minimizing over ``theta`` and ``c`` in closed form (Cholesky-whitened coordinates ``y = L^T Gamma``,
``Q`` an orthonormal basis of the whitened space columns, ``X = (I - Q Q^T) L^T Xi``,
``y' = (I - Q Q^T) y``): ``c* = (X^T X + W)^-1 X^T y'`` with ``W = diag(rho^2 / lambda_k)`` and

    E = gamma * y'^T (I - X (X^T X + W)^-1 X^T) y',      grad = 2 gamma L (I - Q Q^T) H y',

``H`` the bracket. With ``K = 0`` it is :class:`AffinePrior`'s energy for the mean as reference.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as la
from numpy.typing import NDArray

from segsnake.priors import _orthonormal_range, _param_cholesky  # noqa: PLC2701 (shared factor)
from segsnake.priors import SPACES, check_same_size, shape_space_columns, stack, unstack
from segsnake.shapes import ShapeModel
from segsnake.surfaces import SplineSurface

__all__ = ["ModePrior", "residual_variance", "build_prior"]


def residual_variance(variances: NDArray, n_modes: int) -> float:
    """``rho^2``: mean variance of the modes beyond ``n_modes`` (the smallest if none is left)."""
    variances = np.asarray(variances, dtype=np.float64)
    rest = variances[n_modes:]
    return float(rest.mean()) if len(rest) else float(variances[-1])


@dataclass
class ModePrior:
    """Distance to the linear shape space of a shape model's mean plus its first K modes.

    Parameters
    ----------
    model : SplineSurface
        Kind and size of the snake.
    shape_model : ShapeModel
        Mean, modes and variances (same kind and size).
    weight : float
        gamma (energy per mm^2 of residual), as for :class:`AffinePrior`.
    space : str
        A linear space of :data:`segsnake.priors.SPACES` applied to the mean.
    n_modes : int
        K, at most the number of modes of the model.
    """

    model: SplineSurface
    shape_model: ShapeModel
    weight: float = 1.0
    space: str = "affine"
    n_modes: int = 0

    def __post_init__(self) -> None:
        mean = self.shape_model.mean
        check_same_size(self.model, mean, "the shape model")
        if self.space not in SPACES:
            raise ValueError(f"unknown shape space {self.space!r} for a mode prior; expected one "
                             f"of {', '.join(SPACES)}")
        n_avail = len(self.shape_model.variances)
        if not 0 <= self.n_modes <= n_avail:
            raise ValueError(f"--prior-modes {self.n_modes}: the shape model has {n_avail} modes")
        L = _param_cholesky(mean)
        self._Lf = la.block_diag(L, L, L)
        self._offset = stack(mean.params) if self.space == "translation" else 0.0
        Q = _orthonormal_range(self._Lf.T @ shape_space_columns(mean, self.space))
        self._Q = Q
        K = self.n_modes
        if K:
            Xi = np.column_stack([stack(m) for m in self.shape_model.modes[:K]])
            X = self._Lf.T @ Xi
            X = X - Q @ (Q.T @ X)
            rho2 = residual_variance(self.shape_model.variances, K)
            W = np.diag(rho2 / np.maximum(self.shape_model.variances[:K], 1e-300))
            self._X = X
            self._G = la.cho_factor(X.T @ X + W)
        else:
            self._X = None

    def coefficients(self, params: NDArray) -> NDArray:
        """The minimizing mode coefficients ``c*`` (mm along the unit modes)."""
        y = self._whitened(params)
        if self._X is None:
            return np.zeros(0)
        return la.cho_solve(self._G, self._X.T @ y)

    def _whitened(self, params: NDArray) -> NDArray:
        y = self._Lf.T @ (stack(np.asarray(params, dtype=np.float64)) - self._offset)
        return y - self._Q @ (self._Q.T @ y)

    def distance2(self, params: NDArray) -> float:
        """The bracket of the energy (mm^2), without the weight."""
        return self._value(self._whitened(params))[0]

    def _value(self, y: NDArray) -> tuple[float, NDArray]:
        # H y' = y' - X c*; E = y' . H y' (H symmetric, and y' is already off the space).
        Hy = y if self._X is None else y - self._X @ la.cho_solve(self._G, self._X.T @ y)
        return float(y @ Hy), Hy

    def value_and_grad(self, params: NDArray) -> tuple[float, NDArray]:
        """Energy and exact gradient with respect to the parameters ``(P, 3)``."""
        y = self._whitened(params)
        value, Hy = self._value(y)
        Hy = Hy - self._Q @ (self._Q.T @ Hy)
        grad = 2.0 * (self._Lf @ Hy)
        return self.weight * value, self.weight * unstack(grad)


def build_prior(model: SplineSurface, reference: SplineSurface, weight: float, space: str,
                shape_model: ShapeModel | None = None, n_modes: int = 0):
    """The prior energy ``segment --prior`` adds, for one snake.

    ``rigid`` and ``similarity``: :class:`segsnake.procrustes.ProcrustesPrior` of the reference;
    with ``n_modes > 0`` (a shape model): :class:`ModePrior` of its mean and first modes; else
    :class:`segsnake.priors.AffinePrior` of the reference.

    Raises
    ------
    ValueError
        Modes without a shape model, modes with a rotation space, a size mismatch.
    """
    from segsnake.priors import AffinePrior
    from segsnake.procrustes import ROTATION_SPACES, ProcrustesPrior

    if n_modes and shape_model is None:
        raise ValueError("--prior-modes needs a shape model (segsnake shape-model MODEL.json) "
                         "as --prior")
    if space in ROTATION_SPACES:
        if n_modes:
            raise ValueError(f"--prior-modes works with the linear spaces ({', '.join(SPACES)}), "
                             f"not with {space}")
        return ProcrustesPrior(model, reference, weight=weight, space=space)
    if n_modes:
        return ModePrior(model, shape_model, weight=weight, space=space, n_modes=n_modes)
    return AffinePrior(model, reference, weight=weight, space=space)
