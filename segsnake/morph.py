"""Minimum-energy paths between two snakes (seed 000, secs. 6.2-6.3, eqs. (15)-(19)).

Both paths act on the free parameters alone: the surface is linear in them, so a path of
parameters is the same path of surfaces, and every intermediate shape is closed and smooth at
the poles. ``tau = 0`` gives the first snake ``A`` and ``tau = 1`` the second ``B`` exactly; other
``tau`` extrapolate.

**Hilbert plane** (eqs. (15)-(17)). In the extracted text, eq. (15) reads
``F(tau, sigma) = tau ||sigma1 - sigma||^2 + (1 - tau) ||sigma2 - sigma||^2`` (the squares
were lost to the line breaks) and eq. (16) integrates over ``R x R`` where the parameter domain
is ``[0, 1]^2``. Its minimizer is ``tau sigma1 + (1 - tau) sigma2`` (eq. (17)): the gradient
``2 B (tau (p - p1) + (1 - tau)(p - p2))`` vanishes there and the Gram matrix ``B`` is positive
definite. So in eq. (17) ``tau = 0`` gives ``sigma2``, while in eq. (18) ``Gamma(0) = sigma1``:
the two conventions are opposite. Here ``A`` is always the start: the plane path is
``p(tau) = (1 - tau) p_A + tau p_B`` (tests/test_morph.py checks it against the numerical
minimizer of eq. (15) with the exact Gram matrix).

**Hilbert sphere** (eqs. (18), (19)). ``Gamma(tau) = [sin(theta (1 - tau)) s1 + sin(theta tau) s2]
/ sin theta`` with ``theta = arccos <s1, s2>`` is the great circle only for *unit* shapes
``s = sigma / ||sigma||`` (the text says so in words, the formula assumes it). The L2 norm
depends on where a shape is: two snakes 100 mm from the origin would be nearly parallel whatever
their shapes, so each snake is first split into its L2 centroid and the centred shape; the centred
shapes are normalized, joined by the great circle, scaled back with the linearly interpolated
norms ``(1 - tau) |A| + tau |B|`` and moved to the linearly interpolated centroid. The tests check
that ``Gamma`` stays on the unit sphere, moves at the constant angular speed ``theta`` and ends on
the inputs.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from segsnake.priors import inner_product
from segsnake.shapes import _centre  # noqa: PLC2701 (same package: the L2 centroid)
from segsnake.surfaces import SplineSurface

__all__ = ["PATHS", "plane_path", "sphere_path", "great_circle", "l2_centre", "morph"]

PATHS = ("plane", "sphere")


def _check_pair(a: SplineSurface, b: SplineSurface) -> None:
    if (a.kind, a.m1, a.m2) != (b.kind, b.m1, b.m2):
        raise ValueError(f"cannot morph a {a.kind} with M1={a.m1}, M2={a.m2} into a {b.kind} with "
                         f"M1={b.m1}, M2={b.m2}: the control points must correspond")


def l2_centre(model: SplineSurface) -> tuple[NDArray, NDArray]:
    """``(centred parameters, L2 centroid)``: the mean of sigma over the parameter domain."""
    return _centre(model, model.params)


def plane_path(a: SplineSurface, b: SplineSurface, taus: Sequence[float]) -> list[SplineSurface]:
    """Shortest path in the Hilbert plane: ``p(tau) = (1 - tau) p_A + tau p_B`` (eq. (17))."""
    _check_pair(a, b)
    return [a.with_params((1.0 - t) * a.params + t * b.params) for t in taus]


def great_circle(model: SplineSurface, s1: NDArray, s2: NDArray, tau: float) -> NDArray:
    """Eq. (18)/(19) on unit-norm parameters ``s1, s2``: the point at ``tau`` of the great circle.

    ``Gamma(0) = s1``, ``Gamma(1) = s2``; for (nearly) parallel shapes the chord is used.
    """
    c = np.clip(inner_product(model, s1, s2), -1.0, 1.0)
    theta = float(np.arccos(c))
    if theta < 1e-8:
        return (1.0 - tau) * s1 + tau * s2
    return (np.sin(theta * (1.0 - tau)) * s1 + np.sin(theta * tau) * s2) / np.sin(theta)


def sphere_path(a: SplineSurface, b: SplineSurface, taus: Sequence[float]) -> list[SplineSurface]:
    """Great circle on the Hilbert sphere between the centred, normalized snakes (module doc).

    Raises
    ------
    ValueError
        A snake with zero size (all control points at one place).
    """
    _check_pair(a, b)
    t = (~a.is_vector).astype(np.float64)
    (ca, ga), (cb, gb) = l2_centre(a), l2_centre(b)
    na = np.sqrt(max(inner_product(a, ca, ca), 0.0))
    nb = np.sqrt(max(inner_product(b, cb, cb), 0.0))
    if na <= 0 or nb <= 0:
        raise ValueError("a snake of zero size has no direction on the Hilbert sphere")
    out = []
    for tau in taus:
        if tau == 0.0:
            out.append(a.with_params(a.params))  # exactly the inputs at the ends
            continue
        if tau == 1.0:
            out.append(b.with_params(b.params))
            continue
        s = great_circle(a, ca / na, cb / nb, tau)
        scale = (1.0 - tau) * na + tau * nb
        centroid = (1.0 - tau) * ga + tau * gb
        out.append(a.with_params(scale * s + t[:, None] * centroid[None, :]))
    return out


def morph(a: SplineSurface, b: SplineSurface, steps: int, path: str = "plane",
          align: bool = False) -> tuple[NDArray, list[SplineSurface]]:
    """``steps`` shapes at ``tau = 0, 1/(steps-1), ..., 1`` from ``a`` to ``b``.

    Parameters
    ----------
    a, b : SplineSurface
        Snakes of the same kind and size (their control points correspond).
    steps : int
        Number of shapes, >= 2 (the inputs included).
    path : {"plane", "sphere"}
        Eq. (17) or eq. (19).
    align : bool
        Replace both snakes by their best affine images of the unbiased reference of the pair
        first (:func:`segsnake.shapes.unbiased_reference`), so that the path changes shape, not
        pose or size.

    Returns
    -------
    taus : ndarray
    shapes : list of SplineSurface
    """
    if path not in PATHS:
        raise ValueError(f"unknown path {path!r}; expected one of {', '.join(PATHS)}")
    if steps < 2:
        raise ValueError(f"a path needs at least 2 steps, got {steps}")
    _check_pair(a, b)
    if align:
        from segsnake.shapes import align_to_reference, unbiased_reference

        reference, _ = unbiased_reference([a, b])
        (a, b), _, _ = align_to_reference([a, b], reference)
    taus = np.linspace(0.0, 1.0, steps)
    shapes = (plane_path if path == "plane" else sphere_path)(a, b, taus)
    return taus, shapes
