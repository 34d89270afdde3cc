"""Snake energies with exact gradients over the free parameters of a surface model.

Every image term of segsnake is a *flux term*: by the divergence theorem,

    w * integral_V h dV = w * integral integral G(sigma(u, v)) n_x(u, v) du dv,

where ``G(x, y, z) = integral_{-inf}^{x} h(tau, y, z) dtau`` is a lookup volume pre-integrated
along x and ``n = orientation * (sigma_v x sigma_u)`` is the outward (unnormalized) normal
(Schmitter 2017 eq. (20); thesis eq. (7.25)). With ``h = div(grad f)`` the term is the flux of
``grad f`` through the surface; with ``h`` a likelihood ratio it is a region integral. The
quadrature is Gauss-Legendre with ``order`` nodes per knot interval in u and in v, and the
gradient below is the exact derivative of that discrete sum, chained through the basis matrices
and the model's constraint map (so it matches finite differences of the same discrete energy).

An energy is anything with ``value_and_grad(params) -> (float, ndarray like params)``; they add
up with :class:`SumEnergy`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Protocol, Sequence

import numpy as np
from numpy.typing import NDArray

from segsnake.surfaces import SplineSurface

try:
    from segsnake import _flux
except ImportError as exc:  # an install that skipped the build (no compiler), or a stale checkout
    raise ImportError("segsnake's compiled kernel segsnake/_flux.c is not built: reinstall "
                      "with `pip install -e .` (or `make install`), which needs a C compiler "
                      "and the Python headers") from exc

__all__ = ["Sampler", "Energy", "FluxTerm", "AxialTension", "SumEnergy", "flux_integrand_grads",
           "flux_value", "cap_nodes", "RingBarrier", "CrossingPenalty"]


class Sampler(Protocol):
    """A lookup volume: G and its gradient at points in scaled index space (mm)."""

    def sample(self, points: NDArray) -> tuple[NDArray, NDArray]:
        """Return ``G (N,)`` and ``grad G (N, 3)`` at ``points (N, 3)``."""


class Energy(Protocol):
    def value_and_grad(self, params: NDArray) -> tuple[float, NDArray]:
        """Energy and its gradient with respect to the model's free parameters ``(P, 3)``."""


def flux_value(G: NDArray, su: NDArray, sv: NDArray, weights: NDArray,
               orientation: int) -> tuple[float, NDArray]:
    """Discrete flux ``sum W G n_x`` and ``n_x = orientation * (y_v z_u - z_v y_u)`` (arrays on
    the quadrature grid ``(nu, nv[, 3])``): the value :func:`flux_integrand_grads` returns, to
    the last bit."""
    nx = float(orientation) * (sv[..., 1] * su[..., 2] - sv[..., 2] * su[..., 1])
    # (summed in C order whatever the inputs' layout, as flux_integrand_grads sums)
    return float(np.sum(np.ascontiguousarray(weights * G * nx))), nx


def flux_integrand_grads(G: NDArray, dG: NDArray, su: NDArray, sv: NDArray, weights: NDArray,
                         orientation: int) -> tuple[float, NDArray, NDArray, NDArray]:
    """Discrete flux ``sum W G n_x`` and its derivatives with respect to sigma, sigma_u, sigma_v.

    ``n_x = orientation * (y_v z_u - z_v y_u)``; all arrays are on the quadrature grid
    ``(nu, nv[, 3])``.
    """
    value, g_stack, g_v = _integrand_stacked(G, dG, su, sv, weights, orientation)
    return value, g_stack[0], g_stack[1], g_v


def _integrand_stacked(G: NDArray, dG: NDArray, su: NDArray, sv: NDArray, weights: NDArray,
                       orientation: int) -> tuple[float, NDArray, NDArray]:
    # flux_integrand_grads with the derivatives on sigma and sigma_u stacked in one array
    # (2, nu, nv, 3), as GridBasis.adjoint_stacked takes them. One compiled pass over the nodes
    # (segsnake/_flux.c), the same numbers as numpy's float64 products (inputs broadcast
    # together as numpy would); the sum is numpy's, in C order.
    grid = np.broadcast_shapes(np.shape(G), np.shape(weights), np.shape(dG)[:-1],
                               np.shape(su)[:-1], np.shape(sv)[:-1])

    def c(a, trailing=()):
        return np.ascontiguousarray(np.broadcast_to(a, grid + trailing), dtype=np.float64)

    term = np.empty(grid)
    g_stack = np.empty((2, *grid, 3))
    g_v = np.empty((*grid, 3))
    _flux.integrand(c(G), c(dG, (3,)), c(su, (3,)), c(sv, (3,)), c(weights),
                    float(orientation), term, g_stack[0], g_stack[1], g_v)
    return float(np.sum(term)), g_stack, g_v


@dataclass
class FluxTerm:
    """``weight * integral_V h dV`` through a lookup ``G`` (see the module docstring).

    For a cylinder, ``closed=False`` integrates only the lateral surface. That is the
    closed-surface flux only when the end caps are perpendicular to x, i.e. the cylinder's axis
    is perpendicular to x. ``closed=True`` (every stage of the pipeline) adds the two end caps,
    the planar fans ``tau(u, s) = c + s (sigma(u, e) - c)`` (``e`` = 0 and 1, ``c`` the ring's
    mean point) with which the volume, the mask and the mesh close the tube: the surface is then
    closed in any orientation, and the flux is the volume integral whatever the frame
    (docs/design.md, "Closed cylinders"). Each cap is a surface of the same control points,
    integrated with ``order_u`` nodes per knot interval around and :func:`cap_nodes` nodes
    across.

    Parameters
    ----------
    model : SplineSurface
        Fixes the kind and size; its basis matrices on the quadrature grid are precomputed once.
    sampler : Sampler
        Lookup volume of the pre-integrated field.
    weight : float
        Multiplier (negative to *maximize* the integral).
    order : int or (int, int)
        Gauss-Legendre nodes per knot interval (in u and v, or ``(order_u, order_v)``).
    closed : bool
        Cylinders: add the end caps (above). Ignored for spheres, which are closed.
    """

    model: SplineSurface
    sampler: Sampler
    weight: float = 1.0
    order: int | tuple[int, int] = 4
    closed: bool = False

    def __post_init__(self) -> None:
        self.basis, self.weights = self.model.quadrature(self.order)
        self.caps = _Caps(self.model, self.basis.u, self.weights.sum(axis=1)) \
            if self.closed and self.model.kind == "cylinder" else None

    def _on_nodes(self, params: NDArray) -> tuple[NDArray, ...]:
        # The control grid, the surface and its tangents on the quadrature nodes, and G and its
        # gradient there (nu, nv[, 3]).
        C = self.model.control_points(params)
        s, su, sv = self.basis.evaluate(C)
        G, dG = self.sampler.sample(s.reshape(-1, 3))
        return C, su, sv, G.reshape(s.shape[:2]), dG.reshape(s.shape)

    def value_and_grad(self, params: NDArray) -> tuple[float, NDArray]:
        C, su, sv, G, dG = self._on_nodes(params)
        value, g_stack, g_v = _integrand_stacked(G, dG, su, sv, self.weights,
                                                 self.model.orientation)
        grad_C = self.basis.adjoint_stacked(g_stack, g_v)
        if self.caps is not None:
            value += self.caps.flux(C, self.sampler, grad_C)
        grad = self.model.grid_gradient_to_params(grad_C)
        return self.weight * value, self.weight * grad

    def value(self, params: NDArray) -> float:
        """``value_and_grad(params)[0]``, the same number, without the gradient's products (a
        quadrature check needs the energy only)."""
        C, su, sv, G, _ = self._on_nodes(params)
        value = flux_value(G, su, sv, self.weights, self.model.orientation)[0]
        if self.caps is not None:
            value += self.caps.flux(C, self.sampler)
        return self.weight * value


def cap_nodes(m1: int, order_u: int) -> int:
    """Gauss-Legendre nodes across a cylinder's end cap (from the ring's mean point to the ring):
    the lateral surface's node density around (``order_u`` per interval ``2 pi r / M1``) over
    the cap's radius r."""
    return max(4, int(np.ceil(order_u * m1 / (2 * np.pi))))


class _Caps:
    """The flux through a cylinder's two planar fan caps and its gradient on the control grid.

    At each end ``e`` the ring is ``r(u) = sum_k R_k phi_k(u)`` with ``R = C psi(e)`` (the axial
    basis at ``v = e``), its mean point ``c = sum_i w_i r(u_i)`` (the u weights sum to 1), and
    the cap ``tau(u, s) = c + s (r(u) - c)``: ``tau_u = s r_u`` and ``tau_s = r - c``. The
    outward normal is ``o (tau_s x tau_u)`` with ``o`` the model's orientation at ``v = 0``
    and its opposite at ``v = 1`` (the rule of :meth:`CylinderModel.volume`).
    """

    def __init__(self, model: SplineSurface, u: NDArray, wu: NDArray) -> None:
        from segsnake.surfaces import gauss_legendre_grid

        self.Bu = model._basis_u(u, 0)  # (nu, M1)
        self.dBu = model._basis_u(u, 1)
        self.psi = model._basis_v(np.array([0.0, 1.0]), 0)  # (2, L)
        order_u = len(u) // model.m1
        self.s, ws = gauss_legendre_grid(1, cap_nodes(model.m1, order_u))
        self.wu = wu
        self.weights = wu[:, None] * ws[None, :]
        self.signs = (model.orientation, -model.orientation)

    def flux(self, C: NDArray, sampler: Sampler, grad_C: NDArray | None = None) -> float:
        """Both caps' flux ``sum W G n_x``; adds its gradient to ``grad_C (M1, L, 3)`` when
        given."""
        s = self.s[None, :, None]
        total = 0.0
        for psi, sign in zip(self.psi, self.signs):
            R = np.einsum("l,kld->kd", psi, C)
            ring, ring_u = self.Bu @ R, self.dBu @ R  # (nu, 3)
            c = self.wu @ ring
            radial = ring - c
            tau = c + s * radial[:, None, :]  # (nu, ns, 3)
            tau_u = s * ring_u[:, None, :]
            tau_s = np.broadcast_to(radial[:, None, :], tau.shape)
            G, dG = sampler.sample(tau.reshape(-1, 3))
            if grad_C is None:
                total += flux_value(G.reshape(tau.shape[:2]), tau_u, tau_s, self.weights,
                                    sign)[0]
                continue
            value, g, g_u, g_s = flux_integrand_grads(G.reshape(tau.shape[:2]),
                                                      dG.reshape(tau.shape), tau_u, tau_s,
                                                      self.weights, sign)
            total += value
            d_c = np.sum(g * (1 - s) - g_s, axis=(0, 1))
            d_ring = np.sum(g * s + g_s, axis=1) + self.wu[:, None] * d_c
            d_ring_u = np.sum(g_u * s, axis=1)
            grad_C += psi[None, :, None] * (self.Bu.T @ d_ring + self.dBu.T @ d_ring_u)[:, None, :]
        return total


@dataclass
class SumEnergy:
    """Sum of energies."""

    terms: Sequence[Energy]

    def value_and_grad(self, params: NDArray) -> tuple[float, NDArray]:
        total, grad = 0.0, np.zeros_like(params)
        for term in self.terms:
            v, g = term.value_and_grad(params)
            total += v
            grad += g
        return total, grad


@dataclass
class AxialTension:
    """``weight * |c1 - c0|`` (the part of it inside ``box``): a pull between the end rings'
    centres of a cylinder.

    ``c0`` and ``c1`` are the mean points of the rings ``sigma(u, 0)`` and ``sigma(u, 1)``
    (over u: the mean of the control grid's rows weighted by the axial basis at v = 0 and 1,
    since every periodic basis function has the same integral). Unlike the surface area, whose
    gradient is also a pressure of ``weight * (k1 + k2)`` on the whole lateral surface, this
    acts only along the axis: it pulls the ends in where no edge holds them, and leaves the
    radius to the image.

    ``box`` (lower and upper corner, mm): the field of view. Only the part of the segment
    ``c0 c1`` along which the end rings lie wholly inside it is pulled on: the box shrunk on
    each side by the end rings' half extent along that axis (of ``model``, the stage's
    reference surface). An end whose ring reaches past a face of the volume is where the image
    ends, not where no edge holds it: the tube goes on out until its ring has left the volume,
    and the mask ends on the face. Pulled on up to the face itself, an oblique tube's end
    stopped a few mm inside it, where the wall still inside no longer paid for the tension, at
    a place that moved with the optimizer's path. (The length inside the box also depends on
    the axis' direction: a clipped end is still pulled a little across the axis, towards the
    face's normal. A tube that runs along a face within a ring's reach of it is not pulled on
    at all, and the clipping follows the straight line between the centres, not a bent
    centreline.)
    """

    model: SplineSurface
    weight: float = 1.0
    box: tuple[NDArray, NDArray] | None = None

    def __post_init__(self) -> None:
        self.ends = self.model._basis_v(np.array([0.0, 1.0]), 0)  # (2, L)
        if self.box is not None:
            rings = self.model.end_rings(4 * self.model.m1)
            reach = np.max([np.abs(ring - ring.mean(axis=0)).max(axis=0) for ring in rings],
                           axis=0)
            # (the box the rings' centres must stay in; ``box`` itself is kept as given)
            self.inner = (np.asarray(self.box[0], float) + reach,
                          np.asarray(self.box[1], float) - reach)
        else:
            self.inner = None

    def value_and_grad(self, params: NDArray) -> tuple[float, NDArray]:
        C = self.model.control_points(params)
        rows = C.mean(axis=0)  # (L, 3)
        c0, c1 = self.ends @ rows
        length, (g0, g1) = _clipped_length(c0, c1, self.inner)
        # d length / d rows, through c0 = ends[0] @ rows and c1 = ends[1] @ rows
        g_rows = np.outer(self.ends[0], g0) + np.outer(self.ends[1], g1)
        grad_C = np.broadcast_to(g_rows[None] / self.model.m1, C.shape)
        return self.weight * length, self.weight * self.model.grid_gradient_to_params(grad_C)


def _clipped_length(c0: NDArray, c1: NDArray, box) -> tuple[float, tuple[NDArray, NDArray]]:
    """The length of the segment ``c0 c1`` inside the axis-aligned ``box`` (all of it when
    ``box`` is None) and its gradients with respect to ``c0`` and ``c1``.

    The segment ``c0 + t d`` (``d = c1 - c0``) lies in the box for ``t`` in ``[t0, t1]``: ``t0``
    the largest of 0 and its entries through the faces' planes, ``t1`` the smallest of 1 and
    its exits; the length is ``(t1 - t0) |d|``. A crossing ``t = (b - c0_k) / d_k`` moves with
    ``c0_k`` by ``(t - 1) / d_k`` and with ``c1_k`` by ``-t / d_k``."""
    d = c1 - c0
    norm = float(np.linalg.norm(d))
    e = d / max(norm, 1e-300)
    if box is None:
        return norm, (-e, e)
    lo, hi = box
    if np.any(lo > hi):  # (an empty box: rings wider than the volume along an axis)
        return 0.0, (np.zeros(3), np.zeros(3))
    t0, t1 = 0.0, 1.0
    k0 = k1 = None  # (the axis whose face sets t0 and t1; None: the segment's own end)
    for k in range(3):
        if abs(d[k]) < 1e-12 * max(norm, 1e-300):
            if c0[k] < lo[k] or c0[k] > hi[k]:
                return 0.0, (np.zeros(3), np.zeros(3))
            continue
        ta, tb = (lo[k] - c0[k]) / d[k], (hi[k] - c0[k]) / d[k]
        enter, leave = min(ta, tb), max(ta, tb)
        if enter > t0:
            t0, k0 = enter, k
        if leave < t1:
            t1, k1 = leave, k
    if t1 <= t0:
        return 0.0, (np.zeros(3), np.zeros(3))
    g0, g1 = -(t1 - t0) * e, (t1 - t0) * e
    for t, k, sign in ((t1, k1, 1.0), (t0, k0, -1.0)):
        if k is not None:
            g0[k] += sign * norm * (t - 1.0) / d[k]
            g1[k] += sign * norm * (-t) / d[k]
    return (t1 - t0) * norm, (g0, g1)


@dataclass
class RingBarrier:
    """A tube's rings may narrow but not close: ``weight * sum_j psi(a_j / a0_j)``.

    ``a_j`` is the signed area of the ring ``sigma(., v_j)`` along the tube's tangent,
    ``T . 1/2 integral sigma x sigma_u du`` with ``T`` the unit vector of ``integral sigma_v du``
    (rings at ``per_interval`` rows per knot interval, ends included), ``a0_j`` its value for
    ``start`` (rings that start at or below zero are left out), and
    ``psi(x) = (floor / x - 1)^2`` below ``floor``, 0 above: smooth, zero for any ring above
    ``floor`` of its start's area, and growing without bound as a ring closes. (A refusal of
    every step that shrinks a ring below a floor stalled whole stages when one end ring wanted
    to close: measured on a perturbed trachea click, 131 refused steps, Dice 0.18.)
    """

    model: SplineSurface
    start: NDArray
    weight: float = 1.0
    floor: float = 0.1
    per_interval: int = 3

    def __post_init__(self) -> None:
        nu = 4 * self.model.m1
        self.basis = self.model.grid_basis((np.arange(nu) + 0.5) / nu,
                                           np.linspace(0.0, 1.0, self.per_interval * self.model.m2 + 1))
        self.a0 = self.areas(self.start)[0]

    def areas(self, params: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray, tuple]:
        """``a (nv,)``, the area vectors ``A``, the unit tangents ``T``, ``|t|`` and the grid."""
        s, su, sv = self.basis.evaluate(self.model.control_points(params))
        A = 0.5 * np.cross(s, su).mean(axis=0)
        t = sv.mean(axis=0)
        tn = np.maximum(np.linalg.norm(t, axis=1), 1e-300)
        T = t / tn[:, None]
        return np.einsum("vd,vd->v", A, T), A, T, tn, (s, su)

    def value_and_grad(self, params: NDArray) -> tuple[float, NDArray]:
        a, A, T, tn, (s, su) = self.areas(params)
        ok = self.a0 > 0
        x = np.where(ok, a / np.where(ok, self.a0, 1.0), np.inf)
        active = x < self.floor
        if not np.any(active):
            return 0.0, np.zeros_like(params)
        if np.any(x[active] <= 0):
            return float("inf"), np.zeros_like(params)
        xa = np.where(active, x, self.floor)
        value = self.weight * float(np.sum(np.where(active, (self.floor / xa - 1) ** 2, 0.0)))
        # dE/da_j, then through a = T . A and T = t / |t|
        c = np.where(active, self.weight * 2 * (self.floor / xa - 1) * (-self.floor / xa ** 2)
                     / np.where(ok, self.a0, 1.0), 0.0)
        dA = c[:, None] * T  # (nv, 3)
        dt = c[:, None] * (A - a[:, None] * T) / tn[:, None]
        nu = s.shape[0]
        g_s = 0.5 / nu * np.cross(su, dA[None])
        g_su = 0.5 / nu * np.cross(dA[None], s)
        g_sv = np.broadcast_to(dt[None] / nu, s.shape)
        grad_C = self.basis.adjoint(g_s, g_su, np.ascontiguousarray(g_sv))
        return value, self.model.grid_gradient_to_params(grad_C)


@dataclass
class CrossingPenalty:
    """``weight * integral f(k) dx``, ``f(k) = |k - clip(k, 0, 1)|``, ``k`` the surface's winding
    number: the price of the volume a closed surface wraps other than 0 or 1 times
    (:class:`segsnake.rasterize.SelfCrossing`; 0 for an embedded surface).

    A flux or volume energy counts a region the surface wraps twice twice, and one it wraps
    inside out negatively: a density's volume integral can be lowered by passing one part of
    the surface through another (docs/design.md, "No self-crossing"). With ``weight`` at least the
    density's largest magnitude, no such crossing lowers the sum, and where one exists the
    gradient pushes the surface out of it.

    The gradient is the shape derivative of a volume integral: moving the surface outward by
    ``dn`` changes the winding number of the swept volume from ``k_out`` to ``k_out + 1``
    (``k_out`` just outside the surface), so ``d/dn = weight * (f(k_out + 1) - f(k_out))
    = weight * sign(k_out)`` per mm^2: ``weight * sum w sign(k_out) (dsigma/dp . n)`` on a
    Gauss-Legendre grid (``order`` nodes per knot interval). A cylinder's gradient is its
    lateral surface's (its planar caps, which only graze its wall, are left out). Where the
    surface is embedded, the term is 0 and costs one winding scan.
    """

    model: SplineSurface
    weight: float = 1.0
    order: int = 4

    @cached_property
    def _grid(self):
        # (built once a crossing appears: most stages never need it)
        return self.model.quadrature(self.order)

    def value_and_grad(self, params: NDArray) -> tuple[float, NDArray]:
        from segsnake.rasterize import SelfCrossing

        surface = self.model.with_params(params)
        crossing = SelfCrossing(surface)
        if crossing.volume == 0:
            return 0.0, np.zeros_like(params)
        basis, weights = self._grid
        s, su, sv = basis.evaluate(surface.control_points())
        n = self.model.orientation * np.cross(sv, su)
        k_out = crossing.outside_windings(s.reshape(-1, 3), n.reshape(-1, 3)).reshape(s.shape[:2])
        g = (weights * np.sign(k_out))[..., None] * n
        zero = np.zeros_like(g)
        grad_C = basis.adjoint(g, zero, zero)
        return self.weight * crossing.volume, \
            self.weight * self.model.grid_gradient_to_params(grad_C)
