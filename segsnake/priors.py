"""Shape priors from affine projectors (Schmitter's thesis, ch. 2, secs. 3.7.3 and 5.4).

Inner products of spline surfaces are exact quadratic forms of their control points
(thesis eq. (2.21)): for two surfaces of the same kind and size with full control grids
``c1, c2 (M1, M2 + 3, 3)``,

    <sigma1, sigma2>_L2 = integral_0^1 integral_0^1 sigma1(u, v) . sigma2(u, v) du dv
                        = sum_d  vec(c1_d)^T (beta_u kron beta_v) vec(c2_d),

where ``beta_u[k, k'] = integral_0^1 b_k(u) b_k'(u) du`` (periodized ``phi_M1`` around) and
``beta_v[l, l'] = integral_0^1 b_l(v) b_l'(v) dv`` (``phi_{2 M2}`` for the sphere, Keys' kernel
for the cylinder) are the *Gram* (autocorrelation) matrices of the two 1D bases. The generators
are smooth inside each knot interval (``1, s, cos ws, sin ws`` pieces, or cubics), so
Gauss-Legendre quadrature split at the knots with :data:`GRAM_ORDER` nodes per interval is exact
to rounding (1e-16; measured, and checked against a 3x finer rule in the tests). Pulled back
through the model's constraint map ``A`` (free parameters -> full grid), the metric on the free
parameters is ``B = A^T (beta_u kron beta_v) A`` (one ``P x P`` matrix, the same for x, y, z).

The L2 inner product here is over the *parameter domain* ``(u, v) in [0, 1]^2`` (as in the
thesis), not over surface area; it is what makes every quantity below a fixed quadratic form.

Shape spaces of a reference ``sigma_ref`` (columns ``C`` in the stacked coordinates, 003 eq. (5.1)):

* ``affine``: ``A sigma_ref + b`` (12 dimensions);
* ``linear``: ``A sigma_ref`` (9, affine without translation);
* ``scaling``: ``s sigma_ref + b`` (4: isotropic scaling and translation; rotations do not form
  a linear space, so the ``rigid`` and ``similarity`` spaces, with rotations, have their own
  non-linear projector in :mod:`segsnake.procrustes`);
* ``translation``: ``sigma_ref + b`` (an affine, not linear, set: the prior measures
  ``sigma - sigma_ref`` against the 3 translations).

The L2-orthogonal projector is ``P = C (C^T beta C)^-1 C^T beta`` and the prior energy is
``gamma ||sigma - P sigma||^2 = gamma Gamma^T S Gamma`` with ``S = beta (I - P)`` (symmetric,
positive semi-definite), gradient ``2 gamma S Gamma``. ``S`` is computed without inverting
anything ill-conditioned: with ``B = L L^T`` (Cholesky; B is a Riesz-basis Gram matrix) and an
orthonormal basis ``Q`` of ``L^T C`` (SVD, which also copes with a degenerate, e.g. planar,
reference), ``S = B - (L Q)(L Q)^T``. For ``affine``, ``linear`` and ``translation`` the space is
a product over the coordinates (each coordinate of ``sigma`` is fitted by the same scalar
functions), so ``S`` is one ``P x P`` matrix applied to x, y and z; ``scaling`` couples the
coordinates and uses a ``3P x 3P`` matrix.

Stacked coordinates ("Gamma") follow the thesis: ``stack(params) = params.T.ravel()``, i.e. all
x, then all y, then all z, and the metric on them is ``kron(I_3, B)``.

Weights: :class:`AffinePrior` takes an absolute ``gamma`` (energy per mm^2 of mean squared
deviation over the parameter domain). ``segment --prior-weight W`` is relative
(:func:`relative_prior_weight`): ``gamma = W * area / (0.1 r)^2`` for the snake at the start of
each stage. The edge map is normalized to about one unit per mm^2 of detected surface (the image
energy of a snake on its edge is about minus its area), so ``W`` reads: "an RMS deviation from
the reference's shape space of 10 % of the snake's radius costs ``W`` times the image energy",
independent of the object's size and of the image's intensities.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp
from numpy.typing import NDArray

from segsnake.surfaces import CylinderModel, SphereModel, SplineSurface, gauss_legendre_grid

__all__ = [
    "SPACES",
    "GRAM_ORDER",
    "AffinePrior",
    "check_same_size",
    "gram_1d",
    "grid_gram",
    "param_gram",
    "inner_product",
    "l2_norm",
    "stack",
    "unstack",
    "shape_space_columns",
    "projector",
    "prior_matrix",
    "relative_prior_weight",
    "RELATIVE_DEVIATION",
    "model_radius",
]

SPACES = ("affine", "linear", "scaling", "translation")

#: The RMS deviation, as a fraction of the snake's radius, that costs ``W`` times the image
#: energy under a relative prior weight ``W`` (:func:`relative_prior_weight`).
RELATIVE_DEVIATION = 0.1

#: Gauss-Legendre nodes per knot interval of the Gram integrals (order 8 is already exact to
#: 1e-16 for M = 4..50; 10 leaves a margin).
GRAM_ORDER = 10

#: Spaces that act on each coordinate separately with the same scalar functions.
_SEPARABLE = ("affine", "linear", "translation")

_KINDS = {"sphere": SphereModel, "cylinder": CylinderModel}


# ---------------------------------------------------------------------------------------------
# Gram matrices
# ---------------------------------------------------------------------------------------------
def _template(kind: str, m1: int, m2: int) -> SplineSurface:
    if kind not in _KINDS:
        raise ValueError(f"unknown model kind {kind!r}")
    return _KINDS[kind].unit(m1, m2)


@lru_cache(maxsize=64)
def _gram_1d_cached(kind: str, m1: int, m2: int) -> tuple[NDArray, NDArray]:
    model = _template(kind, m1, m2)
    u, wu = gauss_legendre_grid(m1, GRAM_ORDER)
    v, wv = gauss_legendre_grid(m2, GRAM_ORDER)
    bu = model._basis_u(u, 0)
    bv = model._basis_v(v, 0)
    beta_u = bu.T @ (wu[:, None] * bu)
    beta_v = bv.T @ (wv[:, None] * bv)
    # Symmetric by construction up to rounding in the sums; make it exactly so.
    beta_u = 0.5 * (beta_u + beta_u.T)
    beta_v = 0.5 * (beta_v + beta_v.T)
    beta_u.setflags(write=False)
    beta_v.setflags(write=False)
    return beta_u, beta_v


def gram_1d(model: SplineSurface) -> tuple[NDArray, NDArray]:
    """Gram matrices of the 1D bases: ``beta_u (M1, M1)`` around and ``beta_v (L, L)`` along.

    ``beta_u[k, k'] = integral_0^1 phi_per(M1 u - k) phi_per(M1 u - k') du`` (circulant) and
    ``beta_v[l, l'] = integral_0^1 b(M2 v - l) b(M2 v - l') dv`` for ``l, l' = -1..M2+1``, with
    ``b = phi_{2 M2}`` (sphere) or Keys' kernel (cylinder). Read-only, cached per kind and size.
    """
    return _gram_1d_cached(model.kind, model.m1, model.m2)


def grid_gram(model: SplineSurface) -> sp.csr_matrix:
    """Gram matrix ``beta = beta_u kron beta_v`` of the full control grid (flattened k-major).

    ``<sigma1, sigma2>_L2 = sum_d c1[..., d].ravel() @ beta @ c2[..., d].ravel()`` with
    ``c = model.control_points()`` of shape ``(M1, M2 + 3, 3)``.
    """
    beta_u, beta_v = gram_1d(model)
    # Entries beyond the generators' support overlap are exact zeros of the quadrature.
    return sp.csr_matrix(sp.kron(sp.csr_matrix(beta_u), sp.csr_matrix(beta_v)))


@lru_cache(maxsize=64)
def _param_gram_cached(kind: str, m1: int, m2: int) -> tuple[NDArray, NDArray]:
    model = _template(kind, m1, m2)
    beta = grid_gram(model)
    A = model.constraint
    B = np.asarray((A.T @ (beta @ A)).todense())
    B = 0.5 * (B + B.T)
    L = la.cholesky(B, lower=True)
    B.setflags(write=False)
    L.setflags(write=False)
    return B, L


def param_gram(model: SplineSurface) -> NDArray:
    """Metric on the free parameters: ``B = A^T beta A`` (``P x P``, dense, read-only, cached).

    ``<sigma1, sigma2>_L2 = sum_d p1[:, d] @ B @ p2[:, d]`` for parameter arrays ``(P, 3)``.
    """
    return _param_gram_cached(model.kind, model.m1, model.m2)[0]


def _param_cholesky(model: SplineSurface) -> NDArray:
    return _param_gram_cached(model.kind, model.m1, model.m2)[1]


def inner_product(model: SplineSurface, params1: NDArray, params2: NDArray) -> float:
    """Exact ``<sigma1, sigma2>_L2`` over ``(u, v) in [0, 1]^2`` of two parameter arrays ``(P, 3)``."""
    B = param_gram(model)
    return float(np.sum(np.asarray(params1) * (B @ np.asarray(params2))))


def l2_norm(model: SplineSurface, params: NDArray) -> float:
    """Exact ``||sigma||_L2`` over the parameter domain."""
    return float(np.sqrt(max(inner_product(model, params, params), 0.0)))


def stack(params: NDArray) -> NDArray:
    """Stacked coordinates ``Gamma`` (all x, then y, then z) of a ``(P, 3)`` array."""
    return np.asarray(params).T.ravel()


def unstack(gamma: NDArray) -> NDArray:
    """Inverse of :func:`stack`: a ``(P, 3)`` array."""
    return np.asarray(gamma).reshape(3, -1).T


# ---------------------------------------------------------------------------------------------
# Shape spaces and projectors
# ---------------------------------------------------------------------------------------------
def _check_space(space: str) -> None:
    if space not in SPACES:
        raise ValueError(f"unknown shape space {space!r}; expected one of {', '.join(SPACES)}")


def _translation_column(model: SplineSurface) -> NDArray:
    # A translation moves every control point and leaves direction vectors (pole tangents) alone.
    return (~model.is_vector).astype(np.float64)


def shape_space_columns(reference: SplineSurface, space: str) -> NDArray:
    """Columns ``C (3P, d)`` spanning the shape space of ``reference``, in stacked coordinates.

    ``affine``: ``A sigma_ref + b`` (12 columns: reference coordinate e into output coordinate d,
    then the 3 translations); ``linear``: ``A sigma_ref`` (9); ``scaling``: ``sigma_ref`` and
    the 3 translations (4); ``translation``: the 3 translations (the set ``sigma_ref + b`` is
    affine: :class:`AffinePrior` measures ``sigma - sigma_ref`` against them).
    """
    _check_space(space)
    p = reference.params
    n = len(p)
    t = _translation_column(reference)
    cols = []
    if space in ("affine", "linear"):
        for d in range(3):
            for e in range(3):
                col = np.zeros((3, n))
                col[d] = p[:, e]
                cols.append(col.ravel())
    elif space == "scaling":
        cols.append(stack(p))
    if space != "linear":
        for d in range(3):
            col = np.zeros((3, n))
            col[d] = t
            cols.append(col.ravel())
    return np.column_stack(cols)


def _centred(reference: SplineSurface) -> NDArray:
    """Reference parameters minus their L2 centroid (control points only, not tangent vectors).

    Spans with a translation are unchanged by it, and a reference far from the origin
    (x ~ 100 + 10 cos) no longer has a column nearly parallel to the translation's.
    """
    p = reference.params
    t = _translation_column(reference)
    Bt = param_gram(reference) @ t
    centroid = (Bt @ p) / (Bt @ t)
    return p - t[:, None] * centroid[None, :]


def _scalar_columns(reference: SplineSurface, space: str) -> NDArray:
    """Scalar functions ``(P, d)`` that every coordinate is fitted with (separable spaces)."""
    t = _translation_column(reference)[:, None]
    if space == "affine":
        return np.hstack([_centred(reference), t])
    if space == "linear":
        return reference.params.copy()
    return t  # translation


def _orthonormal_range(Y: NDArray) -> NDArray:
    """Orthonormal basis of the column space of ``Y`` (rank-revealing, via the SVD)."""
    # Columns are rescaled first so that a reference far from the origin (x ~ 100 + 10 cos)
    # does not hide its shape behind the translation column in the rank decision.
    norms = np.linalg.norm(Y, axis=0)
    Y = Y[:, norms > 0] / norms[norms > 0]
    if Y.shape[1] == 0:
        return np.zeros((Y.shape[0], 0))
    U, s, _ = np.linalg.svd(Y, full_matrices=False)
    keep = s > 1e-10 * s[0]
    return U[:, keep]


def _factor(reference: SplineSurface, space: str) -> tuple[NDArray, bool]:
    """``Q``, an orthonormal basis of ``L^T C`` (``B = L L^T``), and whether it is per coordinate.

    The B-orthogonal projector is then ``P = L^-T Q Q^T L^T`` and ``S = B (I - P) =
    L (I - Q Q^T) L^T``. Separable spaces give ``Q (P, d)`` for one coordinate, ``scaling``
    gives ``Q (3P, 4)`` on stacked coordinates.
    """
    L = _param_cholesky(reference)
    if space in _SEPARABLE:
        return _orthonormal_range(L.T @ _scalar_columns(reference, space)), True
    # scaling: same span with the centred reference (better conditioned).
    C = shape_space_columns(reference.with_params(_centred(reference)), space)
    Lf = la.block_diag(L, L, L)
    return _orthonormal_range(Lf.T @ C), False


@lru_cache(maxsize=64)
def _factor_cached(kind: str, m1: int, m2: int, space: str, ref_bytes: bytes
                   ) -> tuple[NDArray, bool]:
    template = _template(kind, m1, m2)
    ref = template.with_params(np.frombuffer(ref_bytes, dtype=np.float64).reshape(-1, 3))
    Q, separable = _factor(ref, space)
    Q.setflags(write=False)
    return Q, separable


def _cached_factor(reference: SplineSurface, space: str) -> tuple[NDArray, bool]:
    _check_space(space)
    key = np.ascontiguousarray(reference.params, dtype=np.float64).tobytes()
    return _factor_cached(reference.kind, reference.m1, reference.m2, space, key)


def projector(reference: SplineSurface, space: str = "affine") -> NDArray:
    """L2-orthogonal projector ``P = C (C^T beta C)^-1 C^T beta`` on stacked parameters ``(3P, 3P)``.

    ``unstack(P @ stack(params))`` are the parameters of the best approximation of the surface
    by an element of the shape space of ``reference`` (for ``translation``: by a translation).
    Computed as ``L^-T Q Q^T L^T`` (triangular solves, no explicit inverse of a Gram matrix).
    """
    L = _param_cholesky(reference)
    Q, separable = _cached_factor(reference, space)
    if not separable:
        L = la.block_diag(L, L, L)
    P = la.solve_triangular(L.T, Q, lower=False) @ (Q.T @ L.T)
    return np.kron(np.eye(3), P) if separable else P


def prior_matrix(reference: SplineSurface, space: str = "affine") -> tuple[NDArray, bool]:
    """``S = beta (I - P)`` pulled back to the free parameters, and whether it is per coordinate.

    Separable spaces return ``S (P, P)`` with ``||sigma - P sigma||^2 = sum_d p_d^T S p_d``;
    ``scaling`` returns ``S (3P, 3P)`` acting on :func:`stack` ed parameters.
    (:class:`AffinePrior` evaluates the same form as ``||(I - Q Q^T) L^T p||^2``, which keeps
    full relative accuracy for shapes close to the space.)
    """
    L = _param_cholesky(reference)
    Q, separable = _cached_factor(reference, space)
    B = param_gram(reference)
    if not separable:
        L, B = la.block_diag(L, L, L), la.block_diag(B, B, B)
    W = L @ Q
    S = B - W @ W.T
    return 0.5 * (S + S.T), separable


# ---------------------------------------------------------------------------------------------
# The prior energy
# ---------------------------------------------------------------------------------------------
def check_same_size(model: SplineSurface, reference: SplineSurface, what: str = "the reference"
                    ) -> None:
    """ValueError unless ``reference`` has the snake's kind and control-point counts."""
    if (reference.kind, reference.m1, reference.m2) != (model.kind, model.m1, model.m2):
        raise ValueError(
            f"{what} ({reference.kind}, M1={reference.m1}, M2={reference.m2}) must have the "
            f"snake's kind and control-point counts ({model.kind}, M1={model.m1}, M2={model.m2})")


@dataclass
class AffinePrior:
    """``weight * ||sigma - P sigma||^2_L2``: distance to the shape space of a reference.

    An exact, fixed quadratic form on the free parameters (module docstring): one evaluation
    is two triangular ``P x P`` products and two thin ones (~30 us for a 9 x 9 sphere).

    Parameters
    ----------
    model : SplineSurface
        Kind and size of the snake.
    reference : SplineSurface
        Reference shape of the same kind and size.
    weight : float
        gamma, in energy per mm^2 of mean squared deviation over the parameter domain
        (see :func:`relative_prior_weight` for a scale-free choice).
    space : str
        One of :data:`SPACES`.
    order : int
        Unused (the Gram matrices are exact); kept for compatibility with the quadrature
        version.

    Raises
    ------
    ValueError
        Reference of another kind or size, or an unknown space.
    """

    model: SplineSurface
    reference: SplineSurface
    weight: float = 1.0
    space: str = "affine"
    order: int = 4

    def __post_init__(self) -> None:
        check_same_size(self.model, self.reference)
        self._Q, self._separable = _cached_factor(self.reference, self.space)
        self._L = _param_cholesky(self.reference)
        self._Lt = np.ascontiguousarray(self._L.T)
        # sigma_ref + b is an affine (not linear) set: measure sigma - sigma_ref against b.
        self._offset = self.reference.params.copy() if self.space == "translation" else None

    def distance2(self, params: NDArray) -> float:
        """``||sigma - P sigma||^2_L2`` (mm^2), without the weight."""
        return self._quadratic(params)[0]

    def value_and_grad(self, params: NDArray) -> tuple[float, NDArray]:
        """Energy and exact gradient ``2 gamma S Gamma`` with respect to the parameters ``(P, 3)``."""
        value, grad = self._quadratic(params)
        return self.weight * value, self.weight * grad

    def _quadratic(self, params: NDArray) -> tuple[float, NDArray]:
        # ||sigma - P sigma||^2 = Gamma^T S Gamma with S = L (I - Q Q^T) L^T, evaluated as the
        # squared norm of the whitened residual r = (I - Q Q^T) L^T Gamma: forming S Gamma and
        # then Gamma . S Gamma would lose the digits of a shape close to the space (1e-10 mm^2 of
        # rounding for a snake 1000 mm from the origin); r . r keeps them. Gradient 2 L r.
        q = np.asarray(params, dtype=np.float64)
        if self._offset is not None:
            q = q - self._offset
        Q = self._Q
        if self._separable:
            y = self._Lt @ q  # (P, 3): every coordinate in the same whitened basis
            r = y - Q @ (Q.T @ y)
            return float(np.einsum("pd,pd->", r, r)), 2.0 * (self._L @ r)
        y = (self._Lt @ q).T.ravel()  # stacked whitened coordinates
        r = y - Q @ (Q.T @ y)
        return float(r @ r), 2.0 * (self._L @ unstack(r))


def model_radius(model: SplineSurface) -> float:
    """Size of a snake in mm: equal-volume radius (sphere) or mean end-ring radius (cylinder)."""
    if model.kind == "cylinder":
        r0, r1 = model.end_rings(4 * model.m1)
        return float(0.5 * (np.linalg.norm(r0 - r0.mean(axis=0), axis=1).mean()
                            + np.linalg.norm(r1 - r1.mean(axis=0), axis=1).mean()))
    return float((3 * abs(model.volume(order=4)) / (4 * np.pi)) ** (1 / 3))


def relative_prior_weight(model: SplineSurface, weight: float) -> float:
    """Absolute gamma for a relative prior weight ``W`` (``segment --prior-weight``).

    ``gamma = W * area / (RELATIVE_DEVIATION * r)^2`` for the current snake (area in mm^2,
    ``r`` from :func:`model_radius`). The edge map is normalized to about one unit per mm^2 of
    detected surface, so the image energy of a snake lying on its edge is about minus its area;
    with this gamma an RMS deviation (over the parameter domain) from the reference's shape
    space of 10 % of the snake's radius costs ``W`` times that image energy, whatever the size of
    the object or the intensities of the image. ``W = 1`` holds a ball against a touching
    neighbour of the same intensity (tests/test_priors.py); ``0.1`` is mild.
    """
    r = max(model_radius(model), 1e-12)
    return float(weight) * model.area(order=4) / (RELATIVE_DEVIATION * r) ** 2
