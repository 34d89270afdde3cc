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

With the ``rigid`` and ``similarity`` spaces the transformed shape is ``s R (mean + sum c_k xi_k)
+ b`` (:class:`RotationModePrior`): the minimum is no longer a quadratic form, and it is found by
alternating the exact Procrustes fit of ``(s, R, b)`` (:mod:`segsnake.procrustes`) with the exact
ridge solve for ``c`` in the pulled-back frame ``R^T (sigma - b) / s``, until the energy stops
decreasing (each step cannot increase it). At the minimizer the gradient is
``2 gamma B (p - P p)`` with ``P p`` the fitted shape (Danskin), as for the rotation priors.
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

__all__ = ["ModePrior", "RotationModePrior", "residual_variance", "build_prior"]

#: Alternations of :class:`RotationModePrior` at most, and the relative energy change that stops them.
ALTERNATIONS = 200
ALTERNATION_TOL = 1e-13


def _check(model: SplineSurface, shape_model: ShapeModel, space: str, spaces, n_modes: int,
           least: int) -> None:
    """ValueError for a shape model of another size, a space not in ``spaces``, or K out of range."""
    check_same_size(model, shape_model.mean, "the shape model")
    if space not in spaces:
        raise ValueError(f"unknown shape space {space!r} for this prior; expected one of "
                         f"{', '.join(spaces)}")
    n_avail = len(shape_model.variances)
    if not least <= n_modes <= n_avail:
        raise ValueError(f"--prior-modes {n_modes}: the shape model has {n_avail} modes")


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
        _check(self.model, self.shape_model, self.space, SPACES, self.n_modes, 0)
        mean = self.shape_model.mean
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


@dataclass
class RotationModePrior:
    """Distance to ``{s R (mean + sum_k c_k xi_k) + b}`` with a PPCA penalty on ``c`` (module doc).

    Parameters are those of :class:`ModePrior`, with ``space`` ``rigid`` or ``similarity``.
    """

    model: SplineSurface
    shape_model: ShapeModel
    weight: float = 1.0
    space: str = "similarity"
    n_modes: int = 1

    def __post_init__(self) -> None:
        from segsnake.priors import param_gram
        from segsnake.procrustes import ROTATION_SPACES

        _check(self.model, self.shape_model, self.space, ROTATION_SPACES, self.n_modes, 1)
        mean = self.shape_model.mean
        K = self.n_modes
        self._B = param_gram(mean)
        self._modes = np.asarray(self.shape_model.modes[:K])  # (K, P, 3)
        # Gram of the modes in the L2 metric and the ridge: rho^2 / lambda_k.
        self._XtX = np.einsum("kpd,pq,lqd->kl", self._modes, self._B, self._modes)
        rho2 = residual_variance(self.shape_model.variances, K)
        self._ridge = np.diag(rho2 / np.maximum(self.shape_model.variances[:K], 1e-300))
        self._t = (~mean.is_vector).astype(np.float64)

    def fit(self, params: NDArray) -> tuple[NDArray, NDArray, float]:
        """``(P p, c, energy bracket)`` at the alternating minimum."""
        from segsnake.procrustes import procrustes_fit

        p = np.asarray(params, dtype=np.float64)
        mean = self.shape_model.mean.params
        c = np.zeros(self.n_modes)
        last = np.inf
        for _ in range(ALTERNATIONS):
            shape = mean + np.einsum("k,kpd->pd", c, self._modes)
            s, R, b = procrustes_fit(self.model, p, shape, self.space)
            fitted = s * shape @ R.T + self._t[:, None] * b[None, :]
            d = p - fitted
            value = float(np.sum(d * (self._B @ d))) + float(c @ self._ridge @ c)
            if last - value <= ALTERNATION_TOL * max(value, 1e-300):
                break
            last = value
            if s <= 0:
                break
            # pulled back: y = R^T (p - b) / s; minimize s^2 ||y - mean - Xi c||^2 + c W c
            y = ((p - self._t[:, None] * b[None, :]) @ R) / s
            rhs = s * s * np.einsum("kpd,pq,qd->k", self._modes, self._B, y - mean)
            c = np.linalg.solve(s * s * self._XtX + self._ridge, rhs)
        shape = mean + np.einsum("k,kpd->pd", c, self._modes)
        s, R, b = procrustes_fit(self.model, p, shape, self.space)
        fitted = s * shape @ R.T + self._t[:, None] * b[None, :]
        d = p - fitted
        return fitted, c, float(np.sum(d * (self._B @ d))) + float(c @ self._ridge @ c)

    def distance2(self, params: NDArray) -> float:
        """The bracket of the energy (mm^2), without the weight."""
        return self.fit(params)[2]

    def value_and_grad(self, params: NDArray) -> tuple[float, NDArray]:
        """Energy and gradient ``2 gamma B (p - P p)`` at the alternating minimum (Danskin)."""
        fitted, _, value = self.fit(params)
        grad = 2.0 * (self._B @ (np.asarray(params, dtype=np.float64) - fitted))
        return self.weight * value, self.weight * grad


def build_prior(model: SplineSurface, reference: SplineSurface, weight: float, space: str,
                shape_model: ShapeModel | None = None, n_modes: int = 0):
    """The prior energy ``segment --prior`` adds, for one snake.

    ``rigid`` and ``similarity``: :class:`segsnake.procrustes.ProcrustesPrior` of the reference;
    with ``n_modes > 0`` (a shape model): :class:`ModePrior` of its mean and first modes; else
    :class:`segsnake.priors.AffinePrior` of the reference; both (a rotation space with modes):
    :class:`RotationModePrior`.

    Raises
    ------
    ValueError
        Modes without a shape model, more modes than the model has, a size mismatch.
    """
    from segsnake.priors import AffinePrior
    from segsnake.procrustes import ROTATION_SPACES, ProcrustesPrior

    if n_modes and shape_model is None:
        raise ValueError("--prior-modes needs a shape model (segsnake shape-model MODEL.json) "
                         "as --prior")
    if space in ROTATION_SPACES:
        if n_modes:
            return RotationModePrior(model, shape_model, weight=weight, space=space,
                                     n_modes=n_modes)
        return ProcrustesPrior(model, reference, weight=weight, space=space)
    if n_modes:
        return ModePrior(model, shape_model, weight=weight, space=space, n_modes=n_modes)
    return AffinePrior(model, reference, weight=weight, space=space)
