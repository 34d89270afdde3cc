"""One stage of a segmentation: the minimization of one energy over a lookup.

:class:`Run` holds the stages of one segmentation (their history, timings and the energy the
last one ended in); :func:`run_stage` minimizes a stage's energy (:func:`stage_energy`: the
image's :class:`segsnake.energy.FluxTerm` plus the internal energy, a tube's barriers, the
price of self-crossing or a cylinder's tension, and a shape prior) with the step-limited L-BFGS
of :mod:`segsnake.optimize`, its quadrature chosen a priori and checked against twice its order
(:class:`QuadratureCheck`), its steps filtered by :class:`Admissible`. The region stages
(:mod:`segsnake.region_stages`) and the edge stages (:mod:`segsnake.edge_stages`) are sequences
of such stages (docs/design.md).
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from segsnake.energy import AxialTension, CrossingPenalty, FluxTerm, RingBarrier, SumEnergy
from segsnake.optimize import MIN_VOLUME_FRACTION, minimize_energy
from segsnake.regularize import BendingRegularizer
from segsnake.surfaces import SplineSurface

__all__ = ["Run", "run_stage", "stage_energy", "Admissible", "QuadratureCheck",
           "quadrature_order", "longest_intervals", "REGULARIZATION", "FOV_PAD", "FOV_DENSITY"]

#: Weight of the internal energy (see :func:`stage_energy`), relative to the image energy
#: (measured: 0.5 keeps more of a lobed blob's detail at 1 x 1 x 2 mm, Dice 0.978 against
#: 0.970, but lets the noise-free Table 7.2 cylinder fold off its wall, 0.64).
REGULARIZATION = 1.0
#: A-priori quadrature: nodes this many feature widths apart (see :func:`quadrature_order`;
#: the edge stages' captures take their own, :mod:`segsnake.edge_stages`), ...
NODE_SPACING = 4.0
#: ... at most this many per knot interval ...
MAX_ORDER = 48
#: ... refined until the image energy agrees with twice the order to this relative error.
QUADRATURE_RTOL = 2e-3
#: ... and while it runs, every this many iterations (see :class:`QuadratureCheck`).
#: A moving surface crosses features that a converged one lies along: the running check only
#: catches gross under-resolution (measured: 0.2-1 % while a blob's refinement runs).
QUADRATURE_CHECK_EVERY = 25
QUADRATURE_RTOL_RUNNING = 2e-2
#: The region energy's density beyond the field of view (voxels of padding, and the density
#: there: +1, what the region densities give far outside an object, whose inside is negative).
#: Space the image does not show is not the object: a tube that leaves the volume ends on its
#: face, instead of following the face's density continued outwards (:mod:`segsnake.lookup`).
FOV_PAD = 2
FOV_DENSITY = 1.0
#: Tension of cylinder snakes per mm^2 of lateral surface, in units of the edge map's peak,
#: applied as a pull along the axis (see :func:`stage_energy`).
CYLINDER_TENSION = 0.2


class Run:
    """The stages of one segmentation, with their history and timings."""

    def __init__(self, config, spacing, shape, extra_energy, region_params=None) -> None:
        self.config, self.sp, self.extra = config, spacing, extra_energy
        self.region_params = region_params
        self.bounds = (np.asarray(shape) - 1) * np.asarray(spacing)
        self.history: list[dict[str, Any]] = []
        self.iterations = 0
        self.timings: dict[str, float] = {"lookup_s": 0.0, "optimize_s": 0.0}
        self.last: dict[str, Any] | None = None  # the last stage's energy and functional

    def on_grid(self, spacing: Sequence[float], shape: Sequence[int]) -> "Run":
        """The same segmentation's stages on another grid of the same space (voxel size
        ``spacing`` mm, array ``shape``): they go into this run's history and timings;
        :meth:`take_counts` adds their iterations to this run's and takes their last stage."""
        other = copy.copy(self)
        other.sp = tuple(spacing)
        other.bounds = (np.asarray(shape) - 1) * np.asarray(spacing)
        other.iterations, other.lookup = 0, None
        return other

    def take_counts(self, other: "Run") -> None:
        """The iterations and last stage of a run :meth:`on_grid` made from this one (its last
        stage's energy is on the other grid's lookup, which this run does not keep)."""
        self.iterations += other.iterations
        self.last = other.last

    def _stage(self, name, model, lookup, band, feature_mm, tol=None, node_spacing=None,
               weight=-1.0, region=False, stationary=False, resume=None, leaves=None, used=0,
               at_rest=True):
        model, res = run_stage(model, lookup, weight, self.config, self.bounds, self.extra, band,
                                feature_mm, tol, node_spacing, region, stationary, resume,
                                leaves, used,
                                self.region_params.crossing_weight if region else 0.0, at_rest)
        self.timings["optimize_s"] += res["time_s"]
        self.iterations += res["iterations"]
        # What defines the energy this stage ended in (its lookup is self.lookup), for the
        # restart record of the stage that gives the result.
        reference, order = res.pop("functional")
        self.last = {"stage": name, "energy": res["energy"], "reference": reference,
                     "order": [int(o) for o in order], "iterations": used + res["iterations"]}
        self.history.append({"stage": name, **res})
        return model

    def region_lookup(self, shape: Sequence[int], write: Callable[[NDArray], None]) -> "_Shifted":
        """The lookup of a region density on a window padded by :data:`FOV_PAD` voxels (array
        ``shape``), which ``write`` puts in place (:meth:`segsnake.lookup.Lookup.volume_integral`),
        in the window's coordinates."""
        from segsnake.lookup import Lookup

        # float32 coefficients: half the memory. |G| is at most the window's length (|w| <= 1),
        # so their rounding is below 1e-5 mm^3 per mm^2 of surface; the results change at that
        # level (docs/benchmarks.md, "Memory").
        return _Shifted(Lookup.volume_integral(shape, self.sp, write, dtype=np.float32),
                        FOV_PAD * np.asarray(self.sp))

    def region(self, model, lookup: "_Shifted", name: str, tol: float | None = None,
               stationary: bool = False, resume=None, leaves=None, used: int = 0,
               at_rest: bool = True):
        """Minimize the volume integral of a density (:mod:`segsnake.region`) given by its
        :meth:`region_lookup` (the model in the window's coordinates); ``self.lookup`` keeps
        the lookup. ``stationary``, ``resume``, ``leaves``, ``used``, ``at_rest``: see
        :func:`run_stage`."""
        self.lookup = lookup
        p = self.region_params
        return self._stage(name, model, lookup, p.step_mm, p.edge_smooth_mm, tol, weight=1.0,
                           region=True, stationary=stationary, resume=resume, leaves=leaves,
                           used=used, at_rest=at_rest)

    def field_lookup(self, field: NDArray, divergence_of_gradient: bool) -> "_Shifted":
        """An edge stage's lookup (:meth:`segsnake.lookup.Lookup.from_field`): its density is
        zero on :data:`FOV_PAD` voxels around the grid (no edge is known beyond the field of
        view), sampled in the grid's coordinates."""
        from segsnake.lookup import Lookup

        return _Shifted(Lookup.from_field(field, self.sp, pad=FOV_PAD,
                                          divergence_of_gradient=divergence_of_gradient),
                        FOV_PAD * np.asarray(self.sp))



def _model_radius(model: SplineSurface) -> float:
    if model.kind == "cylinder":
        return model.axis_and_radius()[2]
    return float((3 * abs(model.volume(order=4)) / (4 * math.pi)) ** (1 / 3))


def _volume_per_area(model: SplineSurface, radius: float) -> float:
    """Volume per mm^2 of boundary of the model's kind at its radius r: r / 3 for a sphere,
    r / 2 for a tube (the scale of a volume energy relative to a surface one)."""
    return radius / (2 if model.kind == "cylinder" else 3)


def longest_intervals(model: SplineSurface, params: NDArray | None = None) -> NDArray:
    """Longest distances between neighbouring control points around (u) and along (v), mm."""
    C = model.control_points(params)
    around = max(np.linalg.norm(np.diff(C, axis=0), axis=-1).max(),
                 np.linalg.norm(C[0] - C[-1], axis=-1).max())
    along = np.linalg.norm(np.diff(C, axis=1), axis=-1).max()
    return np.array([around, along])


def quadrature_order(interval_mm: float, feature_mm: float, spacing: float | None = None) -> int:
    """A-priori Gauss-Legendre nodes per knot interval: nodes about ``NODE_SPACING * feature_mm``
    apart on intervals up to ``interval_mm`` (at least 4, at most ``MAX_ORDER``).

    This is only the starting order: :func:`run_stage` checks the converged energy against twice
    the order and refines when they disagree. The integrand varies on the scale of the lookup's
    features only where the surface crosses them; a surface lying along a ridge sees it vary on
    the scale of its own geometry, so the a-priori order is deliberately coarse.
    """
    spacing = NODE_SPACING if spacing is None else spacing
    return int(np.clip(np.ceil(interval_mm / (spacing * feature_mm)), 4, MAX_ORDER))


def run_stage(model, lookup, weight, config, bounds, extra_energy, band, feature_mm, tol=None,
               node_spacing=None, region=False, stationary=False, resume=None, leaves=None,
               used=0, crossing_weight=0.0, at_rest=True):
    """Minimize one stage's energy, re-choosing the quadrature until it is trustworthy.

    A stage runs in rounds, as many as its iteration cap allows. Each round picks the quadrature
    order for intervals up to 1.5 times the current longest one and refuses steps beyond that; a
    round that ends at that limit is followed by another (a surface that grows far needs several:
    a thin tube grows around and along at once, and each growth takes its own rounds). A round
    that converged is then checked: the image energy at twice the order must agree to
    ``QUADRATURE_RTOL``, else the next round runs at the finer order. The check matters: an
    under-resolved quadrature is not just inaccurate, the optimizer *exploits* it (it grows a
    spike whose few nodes all sit on favourable values; measured: order 4 gave -104695 where
    order 16 gives -92674 on a noisy ball). So every
    ``QUADRATURE_CHECK_EVERY`` iterations the running round is checked too, with the looser
    ``QUADRATURE_RTOL_RUNNING``, and a failure ends it (:class:`QuadratureCheck`). A stage
    stopped by the iteration cap is checked too, with the running tolerance (it is still
    moving); ``quadrature_resolved`` in its history says whether the last check agreed
    (``segment`` warns when not).

    ``region``: the lookup integrates a volume density (:mod:`segsnake.region`), which moves the
    surface far from its start: no step is refused for its normals (:class:`Admissible`), the
    bending is weighted for a volume energy, and the volume the surface wraps other than once
    is priced at ``crossing_weight`` per mm^3 (:func:`stage_energy`).

    A round's energy is defined by the lookup, the round's *reference* surface (its start, which
    sets the regularization weights, the ring barrier and the longest allowed intervals) and its
    quadrature order; the last round's are returned as ``functional``. ``resume`` (such a pair,
    from a saved result's restart record) makes the first round use them instead of deriving
    them from ``model``: the stage then minimizes exactly the energy the saved one ended in.
    ``stationary``: the stage ends stationary to its tolerance
    (:func:`segsnake.optimize.stationarity`): when the last round ended by the relative-change
    rule before that, it goes on with the same energy (a *polish*, at most
    :data:`segsnake.optimize.POLISH_ITER` iterations past that rule and within the stage's
    iteration cap; the rounds before it run as without). The polish, like a resumed round,
    checks stationarity before its first step: a restart from the result takes none.
    ``at_rest=False`` (with ``resume``): the surface is where the same energy stopped at a looser
    tolerance, not at rest: the resumed round runs the relative-change rule at ``tol`` first
    (the first-order test would pass it at once: a 1e-3 mm move gains little anywhere near a
    minimum), then the polish.
    ``leaves(surface)``: the stage ends at the first accepted iterate for which it is True
    (``left`` in the record; no check, no polish): the caller goes on elsewhere. ``used``: the
    iterations the stage already took there (they count against ``config.max_iter``).
    """
    t0 = time.perf_counter()
    iterations, evaluations, history, checks = 0, 0, [], []
    left = False

    def leaving(callback):
        if leaves is None:
            return callback

        def during(iteration: int, energy: float, params: NDArray) -> bool:
            nonlocal left
            left = leaves(model.with_params(params))
            return left or callback(iteration, energy, params)

        return during

    floor = np.array([4, 4])
    resolved = False
    tol = tol or max(config.tol, 1e-5)
    max_iter = config.max_iter - used
    while True:  # (each round that goes on took a step, or raised its order to MAX_ORDER)
        reference, resumed = model, resume is not None
        if resumed:
            reference, order = resume
            max_interval = 1.5 * longest_intervals(reference)
            resume = None
        else:
            max_interval = 1.5 * longest_intervals(model)
            order = tuple(int(max(quadrature_order(length, feature_mm, node_spacing), lo))
                          for length, lo in zip(max_interval, floor))
        fine = tuple(min(2 * o, MAX_ORDER) for o in order)
        energy = stage_energy(reference, lookup, weight, order, extra_energy, region,
                               crossing_weight, bounds)
        check = QuadratureCheck(energy.terms[0], fine, checks, model.params)
        admissible = Admissible(reference, max_interval, follow=region)
        res = minimize_energy(model, energy, max_iter=max(max_iter - iterations, 1),
                              tol=tol, bounds_mm=bounds, max_step_mm=band,
                              admissible=admissible,
                              callback=leaving(check.during),
                              stationary_tol=tol if resumed and stationary and at_rest
                              else None)
        model, final_energy = res.model, res.energy
        iterations += res.iterations
        evaluations += res.evaluations
        history += res.history
        capped = iterations >= max_iter
        if left:
            break
        if check.failed:
            # Caught while running: on at the finer order, if iterations are left, from the
            # last shape whose energy was trusted. (Going on from the exploited shape, a tube
            # along (1, 0.3, 1) whose first refinement round was 530 % off after 25 iterations
            # ended at Jaccard 0.97 or 0.17, as rounding of 1e-13 in the basis products went.)
            model = model.with_params(check.trusted)
            final_energy = energy.value_and_grad(model.params)[0]
            if capped:
                break
            floor = np.array(fine)
            continue
        if not capped and np.any(longest_intervals(model) >= 0.9 * max_interval):
            continue
        if fine == order:
            resolved = True
            break
        # A stage the cap stopped is still moving: it gets the running check's tolerance (one
        # stopped at its convergence tolerance at 0.18 % or 0.21 % off, against 0.2 %, as the
        # rounding of an unrelated change went: the warning flipped with it).
        resolved = check(model.params, "capped" if capped else "converged")
        if resolved or capped:
            break
        floor = np.array(fine)
    polish = None
    if stationary and not capped and not check.failed and not left:
        # The polish: the last round's energy again, from its end, until it is stationary.
        res = minimize_energy(model, energy, max_iter=max_iter - iterations, tol=tol,
                              bounds_mm=bounds, max_step_mm=band,
                              admissible=Admissible(reference, max_interval, follow=region),
                              stationary_tol=tol)
        model, final_energy, polish = res.model, res.energy, res.iterations
        iterations += res.iterations
        evaluations += res.evaluations
        history += res.history
    return model, {"polish_iterations": polish, "energy": final_energy,
                   "iterations": iterations, "quadrature_order": order,
                   "quadrature_checks": checks, "quadrature_resolved": resolved,
                   "volume_mm3": model.volume(order=4),
                   "evaluations": evaluations, "converged": res.converged,
                   "message": res.message, "stationarity": res.stationarity, "history": history,
                   "time_s": time.perf_counter() - t0, "functional": (reference, order),
                   **({"left": True} if left else {})}


class QuadratureCheck:
    """Does the image energy at ``order`` agree with the one at ``fine``?

    Called at the end of a round (tolerance ``QUADRATURE_RTOL``), and every
    ``QUADRATURE_CHECK_EVERY`` iterations while it runs (:meth:`during`, the optimizer's
    callback, tolerance ``QUADRATURE_RTOL_RUNNING``, which stops the round at the first
    disagreement): an optimizer that exploits a coarse quadrature does so progressively, and
    caught late the finer round starts far from the boundary with few iterations left
    (measured: a tube along (1, 0.3, 1) ran 220 iterations into a shape whose order-8 energy
    was off by 410 %, Jaccard 0.46; checked every 25 iterations, 0.95). Each check is appended
    to ``checks``. ``trusted`` holds the parameters of the last running check that agreed (the
    round's start before any): after a failure the stage goes on from there, not from the shape
    the coarse rule was exploited into.
    """

    def __init__(self, coarse: FluxTerm, fine: tuple[int, int], checks: list,
                 start: NDArray) -> None:
        self.coarse, self.fine, self.checks = coarse, fine, checks
        self.order = coarse.order
        self._fine_term: FluxTerm | None = None  # built on the first check (its basis costs)
        self.failed = False
        self.trusted = start.copy()

    def __call__(self, params: NDArray, when: str = "converged") -> bool:
        if self._fine_term is None:
            c = self.coarse
            self._fine_term = FluxTerm(c.model, c.sampler, weight=c.weight, order=self.fine,
                                       closed=c.closed)
        coarse_e = self.coarse.value(params)
        fine_e = self._fine_term.value(params)
        error = abs(fine_e - coarse_e) / max(abs(fine_e), 1e-300)
        self.checks.append({"order": list(self.order), "relative_error": error, "when": when})
        return error <= (QUADRATURE_RTOL if when == "converged" else QUADRATURE_RTOL_RUNNING)

    def during(self, iteration: int, energy: float, params: NDArray) -> bool:
        if self.fine == self.order or iteration % QUADRATURE_CHECK_EVERY:
            return False
        self.failed = not self(params, "running")
        if not self.failed:
            self.trusted = params.copy()
        return self.failed


class Admissible:
    """Which steps a stage may take: quadrature still resolved, and no fold.

    The flux through a surface is computed by the divergence theorem, which counts a region
    that the surface wraps twice twice: every flux energy can be lowered by a surface that
    folds through itself, and a quasi-Newton step will find that. A fold starts as a place
    where the surface turns over, i.e. where its normal reverses; so a step is refused if any
    normal on a grid turned by more than 90 degrees since the start of the stage (a stage
    moves the surface by a few ridge widths, far less than would turn a normal over). The two
    knot intervals next to each pole are left out: there the grid's normal also depends on the
    pole tangents, whose joint rotation in the tangent plane is a harmless reparameterization.
    (With only the first interval left out, one grid normal in the second turning over froze
    whole refinements: a ball and an ellipsoid phantom of 48 stopped at Dice 0.90 and 0.84, and
    changes of 1e-13 in the gradient decided which phantoms did. Left out, they converge to
    surfaces with every normal within 40 degrees of radial.)

    ``follow``: for a stage that moves the surface far (the region energy grows a click into a
    whole brain), no normal is compared: its lobes legitimately turn normals by more than 90
    degrees (measured on the Colin27 brain, the start's check stopped the growth at a tenth of
    the volume), and a fold there is priced instead of refused: such a stage's energy prices
    the volume the surface wraps other than once (:class:`segsnake.energy.CrossingPenalty`,
    whose gradient also undoes a crossing; a refusal only kept one from growing). (Its
    normals were compared with the last accepted iterate's until the price came: without that
    test, every result of the real-data benchmark's brain, tumour and perfect-edge rows and all
    48 sphere phantoms are the same to the third decimal, docs/benchmarks.md session 14.) It
    still refuses a step that shrinks the volume below :data:`MIN_VOLUME_FRACTION` of the
    start's (a surface that collapses through itself wraps nothing twice).

    A tube's rings are checked too (any stage): each ring's signed area vector
    ``1/2 integral sigma x sigma_u du`` must point along the tube (its component along the
    centerline's tangent ``integral sigma_v du`` positive) and keep at least
    :data:`MIN_VOLUME_FRACTION` of that component at the start (or the start's, if lower). A
    ring that tilts over or flattens turns the tube inside out there, and step by step no
    normal need turn by 90 degrees (measured: a curved tube in the region stages inverted half
    its rings, which a volume density rewards with minus the volume they wrap over the
    background).
    """

    def __init__(self, start: SplineSurface, max_interval: NDArray, per_interval: int = 3,
                 follow: bool = False) -> None:
        self.start = start
        self.max_interval = max_interval
        self.min_volume = MIN_VOLUME_FRACTION * abs(start.volume(order=4)) if follow else None
        self.n0 = None
        if not follow:
            u = (np.arange(per_interval * start.m1) + 0.5) / (per_interval * start.m1)
            # Two intervals at each pole (one when M2 = 4: two would leave no row to check).
            skip = per_interval * min(2, (start.m2 - 1) // 2) if start.kind == "sphere" else 0
            rows = np.arange(skip, per_interval * start.m2 - skip)
            v = (rows + 0.5) / (per_interval * start.m2)
            self.basis = start.grid_basis(u, v)
            self.n0 = self._normals(start.params)
        self.rings = None
        if start.kind == "cylinder":
            # The rings' signed areas, as the region stages' barrier measures them.
            self.rings = RingBarrier(start, start.params, per_interval=per_interval)
            # (a ring that starts at or below zero may only grow; in the region stages the
            # energy's RingBarrier keeps the others from closing)
            a0 = self.rings.a0
            self.min_area = np.minimum(MIN_VOLUME_FRACTION * a0, a0) if not follow else \
                np.minimum(0.0, a0)

    def _normals(self, params: NDArray) -> NDArray:
        _, su, sv = self.basis.evaluate(self.start.control_points(params))
        return np.cross(sv, su)

    def __call__(self, params: NDArray) -> bool:
        if np.any(longest_intervals(self.start, params) > self.max_interval):
            return False
        if self.min_volume is not None and \
                self.start.with_params(params).volume(order=4) < self.min_volume:
            return False
        if self.rings is not None and np.any(self.rings.areas(params)[0] < self.min_area):
            return False
        return self.n0 is None or \
            bool(np.all(np.einsum("uvd,uvd->uv", self._normals(params), self.n0) > 0))


def stage_energy(model, lookup, weight, order, extra_energy, region=False,
                  crossing_weight=0.0, bounds=None) -> SumEnergy:
    """The stage's energy; its first term is the image's :class:`FluxTerm`. A region stage's
    prices the volume its surface wraps other than once at ``crossing_weight`` per mm^3
    (:class:`CrossingPenalty`). ``bounds``: the field of view's upper corner (mm; the lower is
    the origin), where an edge stage's tube lets go of its tension."""
    flux = FluxTerm(model, lookup, weight=weight, order=order, closed=True)
    terms = [flux]
    # (measured once: the terms' weights all scale with them)
    area, r = abs(model.area(order=4)), _model_radius(model)
    per_area = _volume_per_area(model, r)
    if REGULARIZATION > 0:
        # Internal energy: bending of the deviation from the nearest ellipsoid (elliptic
        # cylinder), scaled so that a deviation of the size of the surface's radius costs about
        # REGULARIZATION times the image energy of the surface lying on its edges, which is
        # about its area (every image term here is normalized to about 1 per mm^2 of edge). Not
        # the stage's starting energy: a refinement that starts off the ridge has almost none,
        # and each round re-weighted the bending by a different amount (measured: T1 brain
        # n7_rf40, Dice 0.906 -> 0.960 with the area).
        # A volume density's energy on its boundary is about the volume: r / 3 per mm^2 of a
        # sphere, r / 2 of a tube.
        scale = per_area if region else 1.0
        terms.append(BendingRegularizer(model, weight=REGULARIZATION * scale * area / r ** 2,
                                        tube=region))
    if region and crossing_weight > 0:
        terms.append(CrossingPenalty(model, weight=crossing_weight))
    if model.kind == "cylinder" and region:
        # A ring may narrow but not close: the barrier costs a ring at a twentieth of its
        # start's area about as much as the volume of its slab of the tube.
        rings = RingBarrier.per_interval * model.m2 + 1  # the rows it measures
        slab = per_area * area / rings
        terms.append(RingBarrier(model, model.params, weight=slab))
    if model.kind == "cylinder" and not region:
        # Past the end of a sheet (a hollow tube's open end) the edge map is empty: the caps
        # feel no flux there, and without tension the ends drift on.
        # Tension makes a tube's length without edge support cost a fraction of what
        # surface on an edge gains (the edge map peaks at about 1 per mm^2): CYLINDER_TENSION
        # per mm^2 of lateral surface, as a pull along the axis only. (Surface tension, the
        # area, also presses on the whole lateral surface with CYLINDER_TENSION / radius, which
        # held tubes whose capture ended 4-5 mm inside the wall out of the refinement's reach:
        # measured when this was introduced: a tube along (1, 1, 0), Jaccard 0.32 -> 0.969.)
        # Where an end ring reaches past a face of the volume the tension lets go
        # (AxialTension's box): an end there is where the image ends, and the mask ends on the
        # face.
        perimeter = 2 * math.pi * r
        box = None if bounds is None else (np.zeros(3), np.asarray(bounds, dtype=float))
        terms.append(AxialTension(model, weight=CYLINDER_TENSION * perimeter, box=box))
    if extra_energy is not None:
        # The prior's weight is relative to the image energy, scaled like the bending.
        terms.append(_Scaled(extra_energy(model), per_area) if region
                     else extra_energy(model))
    return SumEnergy(terms)


@dataclass
class _Shifted:
    """A lookup built on a grid padded by ``offset`` mm on every side, sampled in the
    coordinates of the unpadded grid."""

    lookup: Any
    offset: NDArray

    def sample(self, points: NDArray) -> tuple[NDArray, NDArray]:
        return self.lookup.sample(np.asarray(points) + self.offset)


@dataclass
class _Scaled:
    """``factor`` times an energy."""

    energy: Any
    factor: float

    def value_and_grad(self, params: NDArray) -> tuple[float, NDArray]:
        value, grad = self.energy.value_and_grad(params)
        return self.factor * value, self.factor * grad
