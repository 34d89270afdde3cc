"""Quasi-Newton minimization of a snake energy over the model's free parameters.

L-BFGS on the exact gradient with a cap on how far a control point moves per iteration, with
convergence on the relative energy change and on
the step size, optionally on first-order stationarity (:func:`stationarity`, checked before
the first step too, so that a minimization started at its own end takes no step), an iteration
cap, a progress callback, and guards that turn numerical trouble
into :class:`segsnake.errors.SegmentationError` instead of a hang or a garbage surface: a NaN or
infinite energy or gradient, a surface that leaves the volume, one that collapses (its volume
falls below a fraction of the initial one or turns inside out).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import cho_factor, cho_solve
from segsnake import cancel
from segsnake.energy import Energy
from segsnake.errors import SegmentationError
from segsnake.surfaces import SplineSurface

__all__ = ["OptimizeResult", "minimize_energy", "stationarity", "surface_metric"]


@dataclass
class OptimizeResult:
    """Outcome of :func:`minimize_energy`."""

    model: SplineSurface
    energy: float
    #: Steps taken (an iteration whose line search found no admissible decrease is not one).
    iterations: int
    evaluations: int
    converged: bool
    message: str
    history: list[float] = field(default_factory=list)
    #: :func:`stationarity` at the end (None unless ``stationary_tol`` was given).
    stationarity: float | None = None


#: A surface whose volume falls below this fraction of its start's collapsed (the end check of
#: :func:`minimize_energy`; the region stages refuse such steps, ``stage.Admissible``).
MIN_VOLUME_FRACTION = 0.02

#: With ``stationary_tol``: iterations a minimization may go on after the relative-change or step
#: rule said it converged, waiting for :func:`stationarity` to fall below the tolerance.
POLISH_ITER = 50

def minimize_energy(model: SplineSurface, energy: Energy, *, max_iter: int = 300,
                    tol: float = 1e-5, step_tol_mm: float = 1e-3,
                    max_step_mm: float = 1.0, memory: int = 10,
                    metric: NDArray | None = None,
                    admissible: Callable[[NDArray], bool] | None = None,
                    bounds_mm: NDArray | None = None,
                    callback: Callable[[int, float, NDArray], bool | None] | None = None,
                    min_volume_fraction: float = MIN_VOLUME_FRACTION,
                    window: int = 5,
                    stationary_tol: float | None = None) -> OptimizeResult:
    """Minimize ``energy`` starting from ``model`` with step-limited L-BFGS.

    Parameters
    ----------
    model : SplineSurface
        Initial surface; its kind and size are kept.
    energy : Energy
        Object with ``value_and_grad(params)``.
    max_iter : int
        Cap on quasi-Newton iterations.
    tol : float
        Stop when the energy decreased by less than ``tol`` (relative) per iteration over the
        last ``window`` iterations.
    step_tol_mm : float
        Stop when the surface moved less than this in the last ``window`` iterations together.
    max_step_mm : float
        No point of the surface moves more than this in one iteration (measured on a grid of
        four samples per knot interval). The flux is computed through the
        divergence theorem, which counts a region enclosed twice twice and flips sign for an
        inside-out surface; an unlimited quasi-Newton step can jump straight into such a
        shape. Capping the step makes the iteration follow the gradient flow of the surface,
        which keeps it embedded, while the L-BFGS direction still gives fast convergence.
    memory : int
        Number of L-BFGS correction pairs.
    metric : ndarray (P, P), optional
        Symmetric positive definite metric on the parameters (default: :func:`surface_metric`
        of the initial model): steepest descent becomes the L2 gradient flow of the surface,
        so every part of it (a pole cap as much as the equator) moves at the speed the energy
        asks for, whatever its parameterization.
    admissible : callable(params) -> bool, optional
        A step to parameters for which this is False is shortened like one that does not
        decrease the energy (the pipeline uses it to keep the quadrature resolved).
    bounds_mm : ndarray (3,), optional
        Extent of the volume in mm; a control point farther than one extent outside it means
        the snake escaped (SegmentationError).
    callback : callable(iteration, energy, params), optional
        Called after each iteration; when it returns True the minimization stops there
        (message "stopped by callback", not converged).
    min_volume_fraction : float
        A volume below this fraction of the initial one counts as a collapse.
    window : int
        Number of iterations over which the energy change is measured (see ``tol``).
    stationary_tol : float, optional
        Also stop when :func:`stationarity` (the relative first-order decrease of a
        ``step_tol_mm`` move along the L2 gradient flow) is at most this, checked before the
        first step too: a minimization started where one of the same energy ended stationary
        takes no step (``segment --init`` of a result reproduces it exactly). The relative-change
        and step rules then do not end the minimization before it is stationary, unless
        :data:`POLISH_ITER` more iterations did not get there (the message then says "not
        stationary"). For a start that is the end of *another* energy (a stage's next
        quadrature round) leave it off: the test is first-order, and such a start may pass it
        while the new energy still has more to give than the relative-change rule would leave.
    """
    if window < 1:
        raise ValueError(f"window must be at least 1, got {window}")
    sampler = _DisplacementOperator(model)
    v0 = abs(model.volume(order=4))
    nfev = 0

    def fun(x: NDArray) -> tuple[float, NDArray]:
        nonlocal nfev
        nfev += 1
        value, grad = energy.value_and_grad(x)
        if not np.isfinite(value) or not np.all(np.isfinite(grad)):
            raise SegmentationError("energy or gradient became NaN/Inf during optimization "
                                    f"(evaluation {nfev})")
        return float(value), grad

    def displacement(d: NDArray) -> float:
        return float(np.max(np.linalg.norm(sampler @ d, axis=1)))

    if metric is None:
        metric = surface_metric(model)
    chol = cho_factor(metric)

    def precondition(v: NDArray) -> NDArray:
        # (both finite: cho_factor checked the metric, and every vector solved for is built from
        # gradients fun checked; scipy's check of them on every call cost a third of the solve
        # at 29 x 29)
        return cho_solve(chol, v, check_finite=False)

    x = model.params.copy()
    f, g = fun(x)
    history = [f]
    s_list: list[NDArray] = []
    y_list: list[NDArray] = []
    converged, message, it = False, f"iteration cap ({max_iter}) reached", 0
    steps: list[float] = []
    station: float | None = None
    slow_since: int | None = None  # iteration at which the change or step rule first held

    def stationary() -> bool:
        nonlocal station
        station = stationarity(model.with_params(x), f, g, step_tol_mm, sampler)
        return station <= stationary_tol

    if stationary_tol is not None and stationary():
        max_iter = 0  # stationary where it starts: no step
        converged, message = True, "stationary (first-order decrease below tol)"
    for it in range(1, max_iter + 1):
        cancel.check()  # a signal stops the run between iterations (segsnake.cancel)
        d = -_two_loop(g, s_list, y_list, precondition)
        slope = float(np.sum(g * d))
        if slope >= 0:  # not a descent direction: restart from (preconditioned) steepest descent
            s_list.clear()
            y_list.clear()
            d = -precondition(g)
            slope = float(np.sum(g * d))
        if slope == 0.0:
            converged, message = True, "zero gradient"
            break
        found = _line_search(fun, x, f, d, slope, bool(s_list), max_step_mm, displacement,
                             admissible)
        if found is None and s_list:
            # The quasi-Newton direction only leads to refused shapes (a fold): forget the
            # curvature pairs and follow the plain L2 gradient flow from here.
            s_list.clear()
            y_list.clear()
            d = -precondition(g)
            slope = float(np.sum(g * d))
            found = _line_search(fun, x, f, d, slope, False, max_step_mm, displacement,
                                 admissible)
        if found is None:
            # (an iteration that found no step took none: a restart from a surface at rest
            # among refused shapes counts no iteration, as one from a stationary surface)
            it -= 1
            converged, message = True, "no further admissible decrease"
            break
        x_new, f_new, g_new = found
        s, y = x_new - x, g_new - g
        if float(np.sum(s * y)) > 1e-12 * float(np.sqrt(np.sum(s * s) * np.sum(y * y))):
            s_list.append(s)
            y_list.append(y)
            if len(s_list) > memory:
                s_list.pop(0)
                y_list.pop(0)
        step = displacement(s)
        x, f, g = x_new, f_new, g_new
        history.append(f)
        if callback is not None and callback(it, f, x):
            message = "stopped by callback"
            break
        # The decrease over the last few iterations, not one: a single small step (after an
        # overshoot, or one shortened to stay admissible) says nothing about convergence.
        steps.append(step)
        rule = None
        if it >= window and history[-window - 1] - f <= window * tol * max(abs(f), 1e-12):
            rule = "relative energy change below tol"
        elif it >= window and sum(steps[-window:]) < step_tol_mm:
            rule = "steps below step_tol_mm"
        if stationary_tol is not None and (rule is not None or slow_since is not None):
            # Slow, but is it stationary? Go on (a while) until it is.
            slow_since = it if slow_since is None else slow_since
            if stationary():
                converged, message = True, "stationary (first-order decrease below tol)"
                break
            if it - slow_since < POLISH_ITER:
                continue
            rule = rule or "polish cap reached"
            converged, message = True, f"{rule} (not stationary)"
            break
        if rule is not None:
            converged, message = True, rule
            break
    final = model.with_params(x)
    _check_surface(final, v0, bounds_mm, min_volume_fraction)
    if stationary_tol is not None:
        stationary()  # (at the end, whatever stopped it)
    return OptimizeResult(final, f, it, nfev, converged, message, history, station)


def stationarity(model: SplineSurface, energy: float, grad: NDArray, step_mm: float,
                 sampler: _DisplacementOperator | None = None) -> float:
    """How far from stationary ``model`` is: the first-order decrease of the energy, relative to
    ``|energy|``, when the surface moves by ``step_mm`` (its largest point displacement) along
    the steepest descent of the L2 gradient flow at this surface.

    The direction is ``-M^-1 g`` with ``M`` the :func:`surface_metric` of ``model`` itself, so
    the number depends only on the energy and the surface, not on how the minimization got
    there (no curvature pairs, no starting metric): a restart from the same surface with the
    same energy computes the same value before its first step.

    Parameters
    ----------
    model : SplineSurface
        The surface (its parameters are the point ``grad`` was taken at).
    energy : float
        The energy there.
    grad : ndarray
        Its gradient with respect to ``model.params``.
    step_mm : float
        The move the decrease is predicted for (the optimizer's ``step_tol_mm``: a move it would
        count as standing still).
    sampler : _DisplacementOperator, optional
        The model's :class:`_DisplacementOperator` (built when not given).
    """
    if sampler is None:
        sampler = _DisplacementOperator(model)
    d = cho_solve(cho_factor(surface_metric(model)), grad)
    move = float(np.max(np.linalg.norm(sampler @ d, axis=1)))
    if move == 0.0:
        return 0.0
    return step_mm * float(np.sum(grad * d)) / move / max(abs(energy), 1e-300)


def _line_search(fun, x, f, d, slope, have_curvature, max_step_mm, displacement, admissible):
    """Armijo backtracking along d, capped in surface displacement; None if nothing works."""
    move = displacement(d)
    if not have_curvature:
        # No curvature information yet (first step, or the energy is concave along the path,
        # as it is while a surface is pulled towards an edge): the direction carries no step
        # length, so try the largest allowed one; Armijo shortens it.
        t = max_step_mm / move if move > 0 else 1.0
    else:
        t = min(1.0, max_step_mm / move) if move > 0 else 1.0
    for _ in range(30):
        x_new = x + t * d
        if admissible is None or admissible(x_new):
            f_new, g_new = fun(x_new)
            if f_new <= f + 1e-4 * t * slope:
                return x_new, f_new, g_new
        t *= 0.5
    return None


class _DisplacementOperator:
    """The map from a parameter change ``(P, 3)`` to the surface's displacements on a grid of
    ``per_interval`` samples per knot interval (``op @ d``, ``(n_samples, 3)``): the constraint
    map, then the tensor basis one direction at a time (:meth:`GridBasis.positions`, sparse).
    (The dense ``n_samples x P`` matrix cost O(samples x P) per product: 6 of the 27 s of a
    thin tube's run at 17 x 30 control points.)"""

    def __init__(self, model: SplineSurface, per_interval: int = 4) -> None:
        u = (np.arange(per_interval * model.m1) + 0.5) / (per_interval * model.m1)
        v = np.linspace(0.0, 1.0, per_interval * model.m2 + 1)
        self._basis = model.grid_basis(u, v)
        self._constraint = model.constraint
        self._grid = (self._basis.Bu.shape[1], self._basis.Bv.shape[1], 3)

    def __matmul__(self, d: NDArray) -> NDArray:
        grid = (self._constraint @ d).reshape(self._grid)
        return self._basis.positions(grid).reshape(-1, 3)


def surface_metric(model: SplineSurface, order: int = 4, ridge: float = 1e-6) -> NDArray:
    """Area-weighted mass matrix of the model's basis, pulled back to the free parameters.

    ``M = A^T (sum_q W_q |n_q| b_q b_q^T) A`` with ``b_q`` the tensor basis at quadrature node q,
    ``|n_q|`` the area element of the current surface and ``A`` the constraint map, so that
    ``d^T M d`` is the squared L2 norm (over the surface) of the displacement ``d``. A tiny
    ridge keeps it positive definite where a basis function has (numerically) no area.
    """
    gb, w = model.quadrature(order)
    _, su, sv = gb.evaluate(model.control_points())
    area = w * np.linalg.norm(np.cross(sv, su), axis=-1)  # (nu, nv)
    Bu = gb.Bu.toarray()  # (nu, M1)
    Bv = gb.Bv.toarray()  # (nv, L)
    # sum_{u,v} a(u,v) Bu[u,k] Bv[v,l] Bu[u,k'] Bv[v,l'] without forming the Kronecker product.
    M_C = np.einsum("uv,uk,vl,um,vn->klmn", area, Bu, Bv, Bu, Bv, optimize=True)
    n = Bu.shape[1] * Bv.shape[1]
    M_C = M_C.reshape(n, n)
    A = model.constraint
    M = np.asarray((A.T @ (A.T @ M_C).T).T)
    M = 0.5 * (M + M.T)
    M += ridge * np.trace(M) / len(M) * np.eye(len(M))
    return M


def _two_loop(g: NDArray, s_list: list[NDArray], y_list: list[NDArray],
              precondition: Callable[[NDArray], NDArray]) -> NDArray:
    """L-BFGS two-loop recursion with a preconditioned initial Hessian (approximates H^-1 g)."""
    q = g.copy()
    alphas = []
    for s, y in zip(reversed(s_list), reversed(y_list)):
        rho = 1.0 / float(np.sum(y * s))
        a = rho * float(np.sum(s * q))
        alphas.append((rho, a))
        q -= a * y
    r = precondition(q)
    if s_list:
        s, y = s_list[-1], y_list[-1]
        r *= float(np.sum(s * y)) / float(np.sum(y * precondition(y)))
    q = r
    for (s, y), (rho, a) in zip(zip(s_list, y_list), reversed(alphas)):
        b = rho * float(np.sum(y * q))
        q += (a - b) * s
    return q


def _check_surface(model: SplineSurface, v0: float, bounds_mm: NDArray | None,
                   min_fraction: float) -> None:
    vol = model.volume(order=4)
    if not np.isfinite(vol):
        raise SegmentationError("the snake degenerated (non-finite volume)")
    if vol <= min_fraction * v0:
        raise SegmentationError(f"the snake collapsed or turned inside out (volume {vol:.3g} mm^3, "
                                f"initial {v0:.3g} mm^3)")
    if bounds_mm is not None:
        pts = model.control_points().reshape(-1, 3)
        ext = np.asarray(bounds_mm, dtype=float)
        if np.any(pts < -ext) or np.any(pts > 2 * ext):
            raise SegmentationError("the snake left the volume (control points far outside the image)")
