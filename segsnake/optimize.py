"""Quasi-Newton minimization of a snake energy over the model's free parameters.

L-BFGS-B (scipy) on the exact gradient, with convergence on the relative energy change and on
the step size, an iteration cap, a progress callback, and guards that turn numerical trouble
into :class:`segsnake.errors.SegmentationError` instead of a hang or a garbage surface: a NaN or
infinite energy or gradient, a surface that leaves the volume, one that collapses (its volume
falls below a fraction of the initial one or turns inside out).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize

from segsnake.energy import Energy
from segsnake.errors import SegmentationError
from segsnake.surfaces import SplineSurface

__all__ = ["OptimizeResult", "minimize_energy"]


@dataclass
class OptimizeResult:
    """Outcome of :func:`minimize_energy`."""

    model: SplineSurface
    energy: float
    iterations: int
    evaluations: int
    converged: bool
    message: str
    history: list[float] = field(default_factory=list)


class _Stop(Exception):
    pass


def minimize_energy(model: SplineSurface, energy: Energy, *, max_iter: int = 300,
                    tol: float = 1e-5, step_tol_mm: float = 1e-3,
                    bounds_mm: NDArray | None = None,
                    callback: Callable[[int, float], None] | None = None,
                    min_volume_fraction: float = 0.02,
                    max_displacement_mm: float | None = None) -> OptimizeResult:
    """Minimize ``energy`` starting from ``model``.

    Parameters
    ----------
    model : SplineSurface
        Initial surface; its kind and size are kept.
    energy : Energy
        Object with ``value_and_grad(params)``.
    max_iter : int
        Cap on quasi-Newton iterations.
    tol : float
        Stop when the relative energy change of an iteration falls below ``tol``.
    step_tol_mm : float
        Stop when no control point moved more than this in an iteration.
    bounds_mm : ndarray (3,), optional
        Extent of the volume in mm; a control point farther than one extent outside it means
        the snake escaped (SegmentationError).
    callback : callable(iteration, energy), optional
        Progress report after each iteration.
    min_volume_fraction : float
        A volume below this fraction of the initial one counts as a collapse.
    max_displacement_mm : float, optional
        Trust band: box bounds of +- this many mm on every control point around its start (and
        +- pi times it on tangent vectors, whose length scales like pi times a radius). The
        flux through a surface is computed by the divergence theorem, which counts a region
        enclosed twice twice; without a band, a quasi-Newton step can fold the surface through
        itself and "gain" energy that way.
    """
    shape = model.params.shape
    x0 = model.params.ravel().copy()
    v0 = abs(model.volume(order=4))
    history: list[float] = []
    state = {"x": x0.copy(), "f": None, "nit": 0, "nfev": 0, "reason": ""}

    def fun(x: NDArray) -> tuple[float, NDArray]:
        state["nfev"] += 1
        value, grad = energy.value_and_grad(x.reshape(shape))
        if not np.isfinite(value) or not np.all(np.isfinite(grad)):
            raise SegmentationError("energy or gradient became NaN/Inf during optimization "
                                    f"(iteration {state['nit']})")
        return float(value), grad.ravel()

    def on_iter(xk: NDArray) -> None:
        state["nit"] += 1
        f, _ = energy.value_and_grad(xk.reshape(shape))
        prev = history[-1] if history else None
        history.append(float(f))
        step = np.abs(xk - state["x"]).max()
        state["x"] = xk.copy()
        if callback is not None:
            callback(state["nit"], float(f))
        if prev is not None and abs(prev - f) <= tol * max(abs(prev), abs(f), 1e-12):
            state["reason"] = "relative energy change below tol"
            raise _Stop
        if step < step_tol_mm:
            state["reason"] = "step below step_tol_mm"
            raise _Stop

    f0, _ = fun(x0)
    history.append(f0)
    converged = True
    try:
        bounds = None
        if max_displacement_mm is not None:
            band = np.where(model.is_vector, np.pi, 1.0)[:, None] * max_displacement_mm
            band = np.broadcast_to(band, shape).ravel()
            bounds = list(zip(x0 - band, x0 + band))
        res = minimize(fun, x0, jac=True, method="L-BFGS-B", callback=on_iter, bounds=bounds,
                       options={"maxiter": max_iter, "maxcor": 20, "ftol": 0.0, "gtol": 1e-12})
        x_final = res.x
        message = str(res.message)
        converged = bool(res.success) and state["nit"] < max_iter
        if state["nit"] >= max_iter:
            message = f"iteration cap ({max_iter}) reached"
    except _Stop:
        x_final = state["x"]
        message = state["reason"]
    final = model.with_params(x_final.reshape(shape))
    _check_surface(final, v0, bounds_mm, min_volume_fraction)
    f_final, _ = energy.value_and_grad(final.params)
    return OptimizeResult(final, float(f_final), state["nit"], state["nfev"], converged, message,
                          history)


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
