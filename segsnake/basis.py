"""Spline generators: the exponential interpolator phi_M, its periodization, and Keys' kernel.

``phi_M`` (Schmitter et al. 2017, SIGGRAPH Asia eq. (1); design.md) is the interpolating
generator of the deformable sphere: support (-2, 2), ``phi(0) = 1``, ``phi(+-1) = 0``, C1 with a
bounded second derivative, and it reproduces ``1``, ``cos(2 pi t / M)`` and ``sin(2 pi t / M)``
exactly. Its closed form divides two quantities that both vanish like ``M**-4`` as M grows, so it
is evaluated in extended precision (``numpy.longdouble``) and rounded to float64 once; basis
matrices are precomputed, so that cost is paid once per model, not per energy evaluation.

Keys' cubic convolution kernel (a = -1/2) is the axial generator of the cylinder: interpolating,
C1, support (-2, 2), reproduces polynomials up to degree 2.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["phi", "phi_periodic", "keys", "phi_prime_at_one"]

_LD = np.longdouble


def _piece_coefficients(M: int) -> tuple[NDArray, NDArray]:
    """Coefficients (A, B, C, D) of the two pieces of phi_M in span{1, s, cos(w s), sin(w s)}.

    Outer piece, 1 <= t < 2 with s = t - 2: eq. (1) of the SIGGRAPH Asia paper, which the text
    extraction kept intact (it vanishes with its derivative at t = 2 and at t = 1).
    Inner piece, 0 <= t < 1 with s = t: the extraction of that branch is garbled (it gives
    phi(0) != 1), so it is derived here from what defines it: phi(0) = 1, phi'(0) = 0 (phi is even
    and C1), phi(1) = 0, and phi'(1) equal to the outer piece's slope (C1). The reproduction of
    1, cos and sin is then checked by the tests, not assumed.
    """
    pi = _LD(np.pi)
    Ml = _LD(M)
    w = 2 * pi / Ml
    sw, cw = np.sin(w), np.cos(w)
    sh2 = np.sin(pi / Ml) ** 2
    # (cos w - 1)(-M sin w + pi cos w + pi) with cos w - 1 = -2 sin^2(w/2) (no cancellation there).
    den = (-2 * np.sin(w / 2) ** 2) * (-Ml * sw + pi * cw + pi)
    k = Ml * sw - 2 * pi
    outer = np.array([k / (4 * den), -pi * sh2 / den, -k / (4 * den), sh2 * Ml / (2 * den)])
    # Slope of the outer piece at t = 1, i.e. s = -1.
    g = outer[1] + w * (outer[2] * np.sin(w) + outer[3] * np.cos(w))
    # Inner piece: a + b s + c cos(ws) + d sin(ws) with a = 1 - c, b = -w d and
    #   c (cos w - 1) + d (sin w - w) = -1,   -c w sin w + d w (cos w - 1) = g.
    m11, m12 = cw - 1, sw - w
    m21, m22 = -w * sw, w * (cw - 1)
    det = m11 * m22 - m12 * m21
    c = (-m22 - m12 * g) / det
    d = (m11 * g + m21) / det
    inner = np.array([1 - c, -w * d, c, d])
    return inner, outer


_COEFF_CACHE: dict[int, tuple[NDArray, NDArray]] = {}


def _eval_piece(coef: NDArray, s: NDArray, w, deriv: int) -> NDArray:
    A, B, C, D = coef
    if deriv == 0:
        return A + B * s + C * np.cos(w * s) + D * np.sin(w * s)
    if deriv == 1:
        return B + w * (D * np.cos(w * s) - C * np.sin(w * s))
    return -w * w * (C * np.cos(w * s) + D * np.sin(w * s))


def _phi_pieces(t: NDArray, M: int, deriv: int) -> NDArray:
    """phi_M(t) (or a derivative) for t >= 0, in extended precision."""
    if M not in _COEFF_CACHE:
        _COEFF_CACHE[M] = _piece_coefficients(M)
    inner_c, outer_c = _COEFF_CACHE[M]
    w = 2 * _LD(np.pi) / _LD(M)
    out = np.zeros(t.shape, dtype=_LD)
    inner = t < 1
    out[inner] = _eval_piece(inner_c, t[inner], w, deriv)
    outer = (t >= 1) & (t < 2)
    out[outer] = _eval_piece(outer_c, t[outer] - 2, w, deriv)
    return out


def phi(t: ArrayLike, M: int, deriv: int = 0) -> NDArray[np.float64]:
    """Evaluate the interpolating exponential generator phi_M or its derivative.

    Parameters
    ----------
    t : array_like
        Arguments (any shape).
    M : int
        Number of control points per period of the reproduced sinusoid (``M >= 3``).
    deriv : {0, 1, 2}
        Order of the derivative with respect to ``t``.

    Returns
    -------
    ndarray of float64
        Values with the shape of ``t``; zero outside the support ``(-2, 2)``.
    """
    if deriv not in (0, 1, 2):
        raise ValueError("deriv must be 0, 1 or 2")
    if M < 3:
        raise ValueError(f"phi_M needs M >= 3, got {M}")
    t = np.asarray(t, dtype=_LD)
    a = np.abs(t)
    vals = _phi_pieces(a, M, deriv)
    if deriv == 1:  # phi is even, so its first derivative is odd
        vals = np.sign(t) * vals
    return vals.astype(np.float64)


def phi_periodic(t: ArrayLike, M: int, period: int, deriv: int = 0) -> NDArray[np.float64]:
    """Periodized generator ``sum_n phi_M(t - n * period)``.

    With ``period >= 4`` at most one term is non-zero, so the argument is wrapped into
    ``[-period/2, period/2)`` and evaluated once.
    """
    if period < 4:
        raise ValueError(f"periodic basis needs at least 4 control points, got {period}")
    t = np.asarray(t, dtype=np.float64)
    wrapped = np.mod(t + period / 2.0, period) - period / 2.0
    return phi(wrapped, M, deriv)


def phi_prime_at_one(M: int) -> float:
    """``phi_M'(1)``, the constant of the pole smoothness conditions (000 eqs. (11), (12))."""
    return float(phi(np.array([1.0]), M, deriv=1)[0])


def keys(t: ArrayLike, deriv: int = 0, a: float = -0.5) -> NDArray[np.float64]:
    """Keys' cubic convolution kernel (``a = -1/2``) or its first or second derivative.

    The second derivative is piecewise linear with jumps at integers (the kernel is C1).
    """
    t = np.asarray(t, dtype=np.float64)
    x = np.abs(t)
    inner = x <= 1
    outer = (x > 1) & (x < 2)
    out = np.zeros_like(x)
    if deriv == 0:
        out[inner] = ((a + 2) * x[inner] - (a + 3)) * x[inner] ** 2 + 1
        xo = x[outer]
        out[outer] = ((a * xo - 5 * a) * xo + 8 * a) * xo - 4 * a
    elif deriv == 1:
        xi = x[inner]
        out[inner] = (3 * (a + 2) * xi - 2 * (a + 3)) * xi
        xo = x[outer]
        out[outer] = (3 * a * xo - 10 * a) * xo + 8 * a
        out = np.sign(t) * out
    elif deriv == 2:
        out[inner] = 6 * (a + 2) * x[inner] - 2 * (a + 3)
        out[outer] = 6 * a * x[outer] - 10 * a
    else:
        raise ValueError("deriv must be 0, 1 or 2")
    return out
