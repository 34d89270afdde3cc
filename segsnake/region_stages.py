"""The region stages: a filled object, sphere or tube, from its click (docs/design.md, "The
region energy").

:func:`segment_region` reads the click's intensity model, grows the surface with the click's
band (the region stage), then puts it on the step with the two classes (the two-class rounds),
and refines it on finer control grids (:func:`finer_grids`); a tube that reaches a division of
its structure is held back there (:mod:`segsnake.branching`). Each stage is a
:class:`segsnake.stage.Run` stage in a window around the surface (:mod:`segsnake.window`).
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from segsnake.departure import departure
from segsnake.distance import distance_within
from segsnake.energy import FluxTerm
from segsnake.errors import NoBoundaryError, SegmentationError
from segsnake.pipeline import SegmentResult, restart_options, usable_restart
from segsnake.resample import interpolate_tube
from segsnake.stage import FOV_DENSITY, FOV_PAD, MAX_ORDER, REGULARIZATION, Run
from segsnake.surfaces import CylinderModel, SplineSurface, axial_rings, model_from_dict

__all__ = ["segment_region", "finer_grids", "polish", "tube_rings", "tube_ends"]


def segment_region(image, sp, config, model, progress, extra_energy, init_s,
                    params=None, on_boundary: bool = False,
                    init_record: dict | None = None) -> SegmentResult:
    """The region energy from the click (:mod:`segsnake.region`, docs/design.md).

    1. *Intensity model*: the robust Gaussian of the smoothed image in the click's core.
    2. *Region*: the surface minimizes the volume integral of ``w``, the click's Gaussian
       against a uniform outside: it fills what looks like the click and stops where the
       intensity leaves the click's band, a little inside a blurred step. A sphere grows in
       passes, each at most ``growth_mm`` beyond where the pass before stopped, so that it
       stops at the first boundary around the click.
    3. *Two classes*: the outside's mean is read just outside that surface, averaged along it;
       the same minimization with the inside's Gaussian against that local outside one (on the
       image as acquired: smoothing would move a curved step inwards) puts the surface at the
       midpoint intensity between the two, i.e. on the step (plus, with
       ``edge_length_mm``, the flux of ``grad I`` over the step's peak gradient).

    A tube that reaches a division of its structure (:mod:`segsnake.branching`, read after
    stage 2 and after each round but the last) is held back beyond it from then on.

    ``on_boundary`` (a saved result): stage 2 is skipped, the snake is already on the step.
    ``init_record``: that result's ``restart`` record (:func:`restart_options`; in its
    ``snake.json`` settings). When it was made on this image with these options for a snake of
    this size, the run rebuilds the energy the result's last stage ended in (the intensity
    model, the window, the last round's starting surface that placed the outside's shell, a
    tube's cuts at its divisions, the stage's reference surface and quadrature order) and runs
    only that stage, which checks
    stationarity before its first step: a result comes back unchanged. Otherwise (a hand-edited
    markups file, another size, image or options) the intensity model is read from the snake's
    core and the two-class rounds run from it.

    The last stage (the last round, or the finer grid kept, run to the interim tolerance and
    then on with the same functional: :func:`polish`) ends stationary
    (:func:`segsnake.optimize.stationarity`), and its record is returned in ``settings``.
    """
    from segsnake import region as rg
    from segsnake.branching import Cut, find_cuts
    from segsnake.rasterize import rasterize
    from segsnake.window import Window

    p = params or rg.RegionParams()
    # Lengths that must hold voxels, however large: the passes' band two of the finest voxels,
    # the shell's gap one (the outside is read beyond the partial-volume layer) and the shell
    # one more. (Measured on a ball of radius 9.6 voxels relabelled from 1 to 10 mm voxels: Dice
    # 0.987 at 1 mm; with the millimetre values alone 0.970, 0.930 and 0.924 at 2, 3 and 4 mm,
    # the outside read in the partial-volume layer, and from 5 mm no voxel in the shell (exit 4);
    # with these 0.987-0.990 at every size. The same at the benchmark's voxels, whose finest
    # axis is 1 mm or less.)
    growth_mm = max(p.growth_mm, 2 * min(sp))
    gap_mm = max(p.shell_gap_mm, min(sp))
    shell_mm = max(p.shell_mm, gap_mm + min(sp))
    report = progress or (lambda stage, frac: None)
    run = Run(config, sp, image.shape, extra_energy, p)
    init = model
    run.timings["init_s"] = init_s
    t0 = time.perf_counter()
    image_s = rg.smoothed(image, sp, p.smooth_mm)
    options = restart_options(image, sp, config, p)
    restart, restart_use = usable_restart(init_record, options, model) if on_boundary \
        else (None, None)
    # where a tube branches, beyond which it is held back (segsnake.branching), by end
    cuts: dict[int, Cut] = {}
    if restart is not None:
        window = Window(*(tuple(map(int, c)) for c in restart["window"]),
                        tuple(map(int, image.shape)), sp)
        intensity = rg.IntensityModel(**restart["intensity"])
        cuts = {int(end): Cut.from_dict(c) for end, c in restart["cuts"].items()}
    else:
        window = Window.around(model, image.shape, sp, p.window_mm)
        core = _click_core(window.model_in(model), window.shape, sp, p.core_fraction)
        intensity = rg.IntensityModel.from_samples(image_s[window.slices][core],
                                                   rg.image_range(image_s), p.min_sigma_fraction)
        del core
    run.timings["edge_map_s"] = time.perf_counter() - t0

    def stage(on, window, start, density, name, tol=None, stationary=False, resume=None,
              used=0, at_rest=True, reuse=False, inner=False):
        # One stage of the run ``on`` (the image's grid, or the growth passes' coarser one) in
        # a window of its grid around the surface; while its surface comes near a face of the
        # window (which holds it back from then on), on from there in a window around both
        # (segsnake.window). Returns the surface and the window it ended in; ``on.lookup`` is
        # that window's lookup, and ``on.last["window"]`` the window. ``reuse``: ``on.lookup``
        # is the window's, already built (a later stage of the same energy: the finer grids;
        # held only there, so that a grown window's is built after it is freed). ``inner``: the
        # surfaces, given and returned, are in their windows' coordinates. ``used``, ``at_rest``:
        # as :func:`segsnake.stage.run_stage`'s.
        margin = p.window_mm
        start = start if inner else window.model_in(start)
        lookup = on.lookup if reuse else None
        while True:
            if lookup is None:
                on.lookup = None  # (the last stage's: not needed while this one's is built)
                lookup = build_lookup(on, window, density)
            # (a surface that comes near a face of the window leaves the stage at once: its
            # further course would be the window's, not the image's)
            found = on.region(start, lookup, name, tol, stationary, resume,
                              leaves=lambda m, w=window: w.reaches(w.model_out(m), shell_mm),
                              used=used, at_rest=at_rest)
            on.last["window"] = window
            model = window.model_out(found)
            lookup = None
            if not window.reaches(model, shell_mm):
                return found if inner else model, window
            last = on.history[-1]
            last["window_grown"] = True
            old, margin = window, 2 * margin  # (a surface that grows far needs few windows)
            window = window.union(Window.around(model, window.full_shape, window.spacing,
                                                margin))
            start, resume = window.model_in(model), None
            if last.get("left"):
                # Up to here the window's energy was the whole volume's: the stage goes on from
                # this iterate with the same functional (reference surface, quadrature order).
                reference = window.model_from(on.last["reference"], old)
                resume = (reference, tuple(on.last["order"]))
                used += last["iterations"]
            else:  # (ended near a face it never came near while running: afresh)
                used = 0

    def build_lookup(on, window, density):
        # The lookup of ``density`` on the window: the density straight into the lookup's
        # array, +1 in its padding and beyond a tube's cuts.
        spent = []

        def write(values):
            t0 = time.perf_counter()
            values[...] = FOV_DENSITY
            inner = values[(slice(FOV_PAD, -FOV_PAD or None),) * 3]
            density(window, inner)
            for cut in cuts.values():
                cut.apply(inner, window.lo, window.spacing, FOV_DENSITY)
            spent.append(time.perf_counter() - t0)

        t0 = time.perf_counter()
        lookup = on.region_lookup(tuple(n + 2 * FOV_PAD for n in window.shape), write)
        on.timings["edge_map_s"] += sum(spent)
        on.timings["lookup_s"] += time.perf_counter() - t0 - sum(spent)
        return lookup

    def branching(model):
        # A tube that reached a division of its structure ends there (the first cut found at
        # an end stays: the rounds after it draw the tube back to it).
        if model.kind == "cylinder":
            for end, cut in find_cuts(model, image_s, sp, intensity, p.branch_fraction,
                                      p.cut_radii).items():
                cuts.setdefault(end, cut)

    def beyond(surface, win, max_mm):
        # The voxels inside the surface on the window's grid, and the distance (mm) of those
        # outside it up to max_mm (inf farther): both found in the box max_mm (and two voxels)
        # around the surface, beyond which nothing is inside and nothing that near (the window
        # is wider: the passes' windows follow their union, the rounds' the surface's moves).
        spacing = win.spacing
        box = win.within(Window.around(surface, win.full_shape, spacing,
                                       max_mm + 2 * max(spacing)))
        inside = np.zeros(win.shape, dtype=bool)
        distance = np.full(win.shape, np.inf, dtype=np.float32)
        part = box.slices_in(win)
        inside[part] = rasterize(box.model_in(surface), box.shape, spacing)
        distance[part] = distance_within(inside[part], spacing, max_mm)
        return inside, distance

    def grow(model, window):
        # The region stage in passes, each within growth_mm beyond its starting surface (a
        # sphere; a tube's start already spans its structure along the user's line). Returns
        # the surface and the window of the image's grid for the rounds.
        if model.kind != "sphere" or p.growth_mm <= 0:
            return stage(run, window, model,
                         lambda win, out: rg.region_density(image_s[win.slices], intensity, out),
                         "region", p.interim_tol)
        # The passes on a coarser grid where it still samples the start and the band finely
        # (RegionParams.coarse_fraction): they only bring the surface to the boundary, which
        # the rounds then place on the image's own grid.
        factors = rg.coarse_factors(_smallest_radius(model), sp, growth_mm, p.coarse_fraction)
        coarse = any(f > 1 for f in factors)
        on, win, grid_s = run, window, image_s
        if coarse:
            # (voxel i of the coarse grid is the image's voxel f i; the image's last f - 1
            # voxels along an axis may lie beyond the coarse grid's last, and count as beyond
            # the field of view for the passes: the rounds read them again)
            grid_s = image_s[tuple(slice(None, None, f) for f in factors)]
            on = run.on_grid(tuple(s * f for s, f in zip(sp, factors)), grid_s.shape)
            win = Window.around(model, grid_s.shape, on.sp, p.window_mm)
        # (each pass that goes on moves the surface out; it cannot cross the image more than
        # once: the count only bounds the time)
        passes = math.ceil(math.dist((0, 0, 0), np.multiply(image.shape, sp)) / growth_mm)
        for k in range(passes):
            start, before = model, abs(model.volume())

            def density(w, out, start=start):
                rg.region_density(grid_s[w.slices], intensity, out)
                out[~np.isfinite(beyond(start, w, growth_mm)[1])] = FOV_DENSITY

            model, win = stage(on, win, start, density, f"region, pass {k + 1}", p.interim_tol)
            on.history[-1]["volume_mm3"] = after = abs(model.volume())
            if coarse:
                on.history[-1]["voxel_mm"] = list(on.sp)
            if after < before * (1 + p.growth_stop):
                break
        if not coarse:
            return model, win
        run.take_counts(on)
        return model, Window.around(model, image.shape, sp, p.window_mm)

    # A tube's rings go evenly along it after the growth and before each later round (a
    # stage stretches what it grows); not a prior's, whose rings correspond to its reference's,
    # nor a saved or edited surface's, whose control points are the user's.
    respace = model.kind == "cylinder" and config.prior is None and not on_boundary
    report("region", 0.1)
    if not on_boundary:
        model, window = grow(model, window)
        if respace:
            # (now that the tube's calibre and ends are known: a ring a radius apart, unless M2
            # is given)
            model = interpolate_tube(model, tube_rings(model) if config.m2 is None else model.m2)
        branching(model)
    report("two classes", 0.5)

    # The farthest a point's gap reaches: blur_gaps widths of the widest blur its profile can
    # read.
    gap_cap = max(gap_mm, p.blur_gaps * rg.widest_step(p.blur_reach_mm))
    thick = shell_mm - gap_mm

    def inside_and_shell(surface, win, far=True):
        # The voxels inside the surface, the shell between shell_gap_mm and shell_mm outside
        # it where the outside is read, on the window's grid, and the distance outside it (up to
        # the farthest gap where ``far``, for read_beyond).
        inside, distance = beyond(surface, win,
                                  gap_cap + thick if far and p.blur_gaps > 0 else shell_mm)
        return inside, (distance > gap_mm) & (distance <= shell_mm), distance

    def read_beyond(shell, distance, win, gaps):
        # The shell the density reads: with ``gaps`` (the surface's area samples, their normals
        # and each one's gap, mm) as thick as the fixed one beyond each point's own gap, shared
        # at the resolution the outside's mean is shared at (or finer). (Where the surface lies
        # nearer a face of the window than its gap and shell, the part beyond the face is not
        # read: the outside's mean comes from the rest.)
        if gaps is None:
            return shell
        pts, unit, gap = gaps
        own = rg.along_normals(gap, (pts - win.origin_mm, unit), win.shape, sp, gap_cap + thick,
                               gap_mm, 0.5 * p.outside_smooth_mm, win.lo)
        return (distance > own) & (distance <= own + thick)

    def own_gaps(surface, polarity):
        # Each area sample's gap: beyond blur_gaps widths of its step's own blur (the width
        # measured on I_s less its smoothing), None where no point needs more than the gap.
        if p.blur_gaps <= 0:
            return None
        pts, unit, _ = surface.area_samples(4)
        width = rg.step_widths(image_s, (pts, unit), sp, polarity, p.blur_reach_mm,
                               p.step_spreads * intensity.sigma)
        blur = np.sqrt(np.maximum(width ** 2 - p.smooth_mm ** 2, 0.0))
        gap = np.clip(p.blur_gaps * blur, gap_mm, gap_cap)
        return (pts, unit, gap) if gap.max() > gap_mm else None

    last = p.two_class_rounds - 1
    final, record = None, None  # (the last stage's run.last, and its restart record)
    # (a restart: only the last round, its outside read around the surface the saved one read)
    for k in range(last if restart else 0, p.two_class_rounds + 1):
        # The outside, read beyond the current surface; after the last round it scores the
        # result (an inside that does not differ from its outside found no boundary).
        run.lookup = None  # (the last stage's lookup is done with)
        t0 = time.perf_counter()
        start, win = model, window
        if restart is not None and k == last:
            start = model_from_dict(restart["round_start"])
        sub = image_s[win.slices]
        # (after the last round only the fixed shell, which scores the result)
        inside, shell, distance = inside_and_shell(start, win, far=k < p.two_class_rounds)
        if not inside.any():
            raise SegmentationError("the surface encloses no voxel centre")
        if not shell.any():
            raise SegmentationError("the surface filled the whole image: no outside to compare")
        contrast, polarity = rg.step_contrast(sub, inside, shell)
        if contrast < p.min_separation * intensity.sigma:
            # (a click alone started from one tissue's ball: an object of several needs a radius)
            hint = ""
            if not on_boundary and model.kind == "sphere" and config.center is not None \
                    and config.radii is None:
                hint = " or give --radii (the click alone found one tissue's ball)"
            elif not on_boundary and model.kind == "cylinder" and config.centerline is None:
                # (a straight cylinder between two points of a bent tube lies mostly outside it)
                hint = " or give points along the tube (--centerline) if it bends"
            raise NoBoundaryError(
                f"no boundary found: inside and outside the surface differ by {contrast:.3g}, "
                f"{contrast / intensity.sigma:.2f} x the click's spread; check the "
                f"initialization{hint}")
        if config.polarity in ("bright", "dark"):
            polarity = 1 if config.polarity == "bright" else -1
        if k == p.two_class_rounds:
            separated = rg.class_separation(sub, inside, shell)
            run.timings["edge_map_s"] += time.perf_counter() - t0
            break
        gaps = own_gaps(start, polarity)
        read = read_beyond(shell, distance, win, gaps)
        del distance
        run.timings["edge_map_s"] += time.perf_counter() - t0

        def density(w_win, out, read=read, gaps=gaps):
            # The two classes with the outside read around the round's starting surface (in a
            # grown window, read again there), beyond each point's own blur.
            if w_win != win:
                _, shell, distance = inside_and_shell(start, w_win, far=gaps is not None)
                read = read_beyond(shell, distance, w_win, gaps)
                del shell, distance
            sub = image_s[w_win.slices]
            mu_out = rg.local_outside_mean(sub, read, sp, p.outside_smooth_mm)
            rg.two_class_blend(image[w_win.slices], sub, intensity, mu_out, out, p.pure_spreads)
            del mu_out
            if p.edge_length_mm > 0:
                out += rg.edge_density(image[w_win.slices], sp, polarity, contrast,
                                       p.edge_length_mm, p.edge_smooth_mm)

        del inside
        resume = None
        if restart is not None:
            resume = (model_from_dict(restart["reference"]), tuple(restart["order"]))
        # (the last round runs to the final tolerance in windows that follow it, stationary)
        model, window = stage(run, window, model, density, f"two classes, round {k + 1}",
                              None if k == last else p.interim_tol, stationary=k == last,
                              resume=resume)
        if k < last:
            del density, shell, read
            branching(model)
            if respace:
                model = interpolate_tube(model, model.m2)
            continue
        round_start = start
        # (a tube's rings along follow its calibre: its finer grids are finer around only; a
        # restart's record names the result's last stage, after which its schedule had ended)
        if restart is None and config.coarse_to_fine and config.m1 is None \
                and (config.m2 is None or model.kind == "cylinder"):
            base, built = window, True  # (the window the stages run in; run.lookup is its)

            def advance(start, name, tol=None, stationary=False, resume=None, used=0,
                        at_rest=True):
                # A stage of the last round's energy (its density) from ``start`` in windows
                # that follow it as the round's did, on from the current window's lookup;
                # ``resume``: the record of the stage whose functional it goes on with.
                # Surfaces in ``base``'s coordinates (the round's window).
                nonlocal window, built
                here = window
                if resume is not None:
                    resume = (here.model_from(resume["reference"], resume["window"]),
                              tuple(resume["order"]))
                # (a stage that fails may leave another window's lookup: the next builds anew)
                reuse, built = built, False
                found, window = stage(run, here, here.model_from(start, base), density, name,
                                      tol, stationary, resume, used, at_rest, reuse=reuse,
                                      inner=True)
                built = True
                return base.model_from(found, window)

            def image_energy(m, order):
                # the image energy of ``m`` (``base``'s coordinates) on the current lookup
                m = window.model_from(m, base)
                return FluxTerm(m, run.lookup, weight=1.0, order=order, closed=True).value(
                    m.params)

            model = base.model_out(finer_grids(run, base.model_in(model), p, advance,
                                               image_energy))
            window = run.last["window"]
        # The result's energy: its record (lookup from these, reference, order).
        final = run.last
    # The last pass of the loop rasterized the final surface (and checked it is not empty).
    mask = win.embed(inside)
    # (how deep the start's centre, the click, lies in the result: not for a saved surface)
    depth = rg.click_depth(inside, sp, _centre(init) - win.origin_mm) \
        if init.kind == "sphere" and not on_boundary else None
    del inside, shell, distance
    report("done", 1.0)
    on_step = rg.boundary_fraction(image_s, model, sp, polarity,
                                   p.step_spreads * intensity.sigma, p.step_depth_mm)
    beyond = rg.step_beyond(image_s, model, sp, polarity, p.step_depth_mm, p.step_reach_mm,
                            p.step_spreads * intensity.sigma)
    if final is not None:
        record = {**options, "intensity": intensity.to_dict(),
                  "window": [list(final["window"].lo), list(final["window"].hi)],
                  "round_start": round_start.to_dict(), "stage": final["stage"],
                  "cuts": {str(end): cut.to_dict() for end, cut in cuts.items()},
                  "reference": final["reference"].to_dict(), "order": final["order"]}
    else:  # (no two-class round: the region stage's result, no record)
        final = run.last
    settings = {"energy": "region", "intensity_model": intensity.to_dict(),
                "contrast": contrast, "separation": contrast / intensity.sigma,
                # (null for two constant classes: JSON has no infinity)
                "class_separation": separated if math.isfinite(separated) else None,
                "boundary_fraction": on_step, "step_beyond": beyond, "click_depth": depth,
                "window": [list(window.lo), list(window.hi)],
                "regularization": REGULARIZATION, "region_params": dataclasses.asdict(p),
                "restart": record}
    if on_boundary:
        settings["restart_record"] = restart_use
    if model.kind == "cylinder":
        settings["ends"] = tube_ends(model, image.shape, sp)
        from segsnake.profile import ring_centroids

        for end, cut in cuts.items():
            if cut.holds(ring_centroids(model, np.array([float(end)]))[0][0]):
                settings["ends"][end] = "branching"
    return SegmentResult(model, mask, final["energy"], run.iterations, run.history,
                         run.timings, "bright" if polarity > 0 else "dark", init, settings)


def finer_grids(run, model: SplineSurface, p, advance, image_energy) -> SplineSurface:
    """Coarse to fine: the last stage again on finer control grids (``p.finer_m``: M1 = M2 for a
    sphere, M1 around a tube, whose M2 stays the one its calibre chose), each started from the
    current surface: a sphere's first finer grid fitted with its poles on
    the surface's long axis (``p.long_axis_poles``,
    :func:`segsnake.resample.poles_on_long_axis`), every other from the exact L2 projection
    (:func:`segsnake.resample.resample`). A grid is kept while it refines the surface: the
    volume between it and the coarser surface farther than the coarser grid's control spacing
    stays within ``p.finer_departure`` of the coarser volume (:func:`segsnake.departure.departure`:
    detail comes back within a control spacing; a leak into a neighbour carries the surface
    farther). The first grid refused ends the schedule, as does
    a finer stage that fails (a collapse), and a kept grid after the first whose image energy
    gain over the grid before (recorded) is below ``p.finer_gain``: the next is not tried
    (docs/design.md, "Coarse to fine").

    ``model`` is the last round's stationary result. ``advance(start, name, tol=None,
    stationary=False, resume=None, used=0, at_rest=True)`` runs a stage of the last round's
    energy from ``start`` (in windows that follow it as the round's did) and returns its
    surface; ``image_energy(model, order)`` is a surface's image energy on the current window's
    lookup. Each grid runs to the interim tolerance (``p.interim_tol``): only the grid kept last
    is the result, which :func:`polish` takes on to the final tolerance, and the test is then
    asked again of the polished surface against the surface it refined (a leak that had begun
    goes on while it is polished): refused, the grid before is polished instead, down to the
    last round's surface. Returns the result; ``run.last`` is its stage's."""
    from segsnake.resample import poles_on_long_axis, resample

    def refines(finer: SplineSurface, coarser: SplineSurface) -> tuple[bool, dict]:
        moved = departure(coarser, finer, run.sp)
        volume = abs(coarser.volume(order=4))
        return moved <= p.finer_departure, {
            "departure": moved,
            "volume_change": (abs(finer.volume(order=4)) - volume) / max(volume, 1e-300)}

    tube = model.kind == "cylinder"
    # the grids kept: (surface, its stage's record, the surface it refines)
    kept: list[tuple[SplineSurface, dict, SplineSurface]] = []
    base = model, run.last
    for m in p.finer_m:
        if m <= (model.m1 if tube else min(model.m1, model.m2)):
            continue
        m2 = model.m2 if tube else m
        last, name = run.last, f"grid {m}x{m2}"
        # (a sphere's first finer grid: its poles move to the ends of the surface's long axis)
        start = poles_on_long_axis(model, m, m2) \
            if not tube and not kept and p.long_axis_poles else resample(model, m, m2)
        try:
            finer = advance(start, name, p.interim_tol)
        except SegmentationError as exc:
            # (a finer surface that collapsed through itself is no refinement either)
            run.history.append({"stage": name, "kept": False, "error": str(exc)})
            break
        # Both at twice the finer of the two stages' own orders, each checked against twice
        # itself when its stage ended (segsnake.stage.QUADRATURE_RTOL; at a stage's iteration
        # cap, the running tolerance): an order chosen from the finer grid's
        # intervals under-resolves the coarser surface's longer ones by as much as the gain
        # tested (a blob's 13 x 13 gained 0.7 % at order 8, 1.3 % at 16 to 48).
        order = tuple(min(2 * max(a, b), MAX_ORDER) for a, b in zip(last["order"],
                                                                     run.last["order"]))
        e, e_fine = image_energy(model, order), image_energy(finer, order)
        gain = (e - e_fine) / max(abs(e), 1e-300)
        keep, measures = refines(finer, model)
        run.history[-1].update(image_energy_gain=gain, **measures, kept=keep)
        if not keep:
            run.last = last  # (the result's energy stays the coarser stage's)
            break
        kept.append((finer, run.last, model))
        model = finer
        # (the first finer grid's gain is read against the last round's surface, which ran to
        # the final tolerance or its cap and on a noisy image ends in one of several minima:
        # only a gain between two finer grids, each at the interim tolerance, ends the schedule)
        if gain < p.finer_gain and len(kept) > 1:
            break
    while kept:
        finer, run.last, coarser = kept.pop()
        stages = len(run.history)
        polished = polish(run, finer, advance)
        keep, measures = refines(polished, coarser)
        if len(run.history) > stages:  # (a stage at its cap is not polished: kept as it was)
            run.history[-1].update(**measures, kept=keep)
        if keep:
            return polished
    model, run.last = base
    return model


def polish(run, model: SplineSurface, advance) -> SplineSurface:
    """The result's stage: ``model``, where the last stage (``run.last``) stopped at the interim
    tolerance, on from there with the same functional (its reference surface and quadrature
    order; ``advance`` as :func:`finer_grids`') to the ``tol`` option and stationarity
    (:func:`segsnake.optimize.stationarity`), its iterations counted against the stage's cap
    (the ``max_iter`` option: one stage, run in two tolerances). A restart from the result's
    record minimizes the same functional and comes back unchanged."""
    last = run.last
    if last["iterations"] >= run.config.max_iter:
        return model  # (the stage ended at its cap: there is nothing left to run)
    return advance(model, f"polish: {last['stage']}", stationary=True, resume=last,
                   at_rest=False, used=last["iterations"])


def _centre(model: SplineSurface) -> NDArray:
    """A sphere's centre (mm): the middle of its poles (of a start about a click, the click)."""
    return 0.5 * (model.pole("cN") + model.pole("cS"))


def _smallest_radius(model: SplineSurface) -> float:
    """A sphere's smallest distance (mm) from its :func:`_centre` to its surface, sampled 4
    times per knot interval (an ellipsoid's smallest semi-axis)."""
    from segsnake.window import surface_samples

    return float(np.linalg.norm(surface_samples(model) - _centre(model), axis=-1).min())


def _click_core(model: SplineSurface, shape, spacing, fraction: float) -> NDArray[np.bool_]:
    """The voxels of the initial surface shrunk by ``fraction`` (grown back towards the whole
    surface until it holds enough voxels for a spread): a sphere about its centre, a tube about
    its centerline (each ring about its own centre, so that a curved tube's core stays in it)."""
    from segsnake.rasterize import rasterize
    from segsnake.region import MIN_SAMPLES

    C = model.control_points()
    for f in (fraction, 0.5 * (1 + fraction), 1.0):
        if model.kind == "cylinder":  # every control point is free: the grid is the params
            rings = C.mean(axis=0, keepdims=True)
            shrunk = model.with_params((rings + f * (C - rings)).reshape(-1, 3))
        else:
            centre = C.reshape(-1, 3).mean(axis=0)
            shrunk = model.transformed(f * np.eye(3), (1 - f) * centre)
        core = rasterize(shrunk, shape, spacing)
        if core.sum() >= MIN_SAMPLES:
            break
    return core


def tube_rings(model: CylinderModel) -> int:
    """M2 for a tube (:func:`segsnake.surfaces.axial_rings`) from its centerline (the rings'
    mean points, at 4 samples per knot interval) and its mean distance from it."""
    from segsnake.profile import ring_centroids

    nu, v = 4 * model.m1, np.linspace(0.0, 1.0, 4 * model.m2 + 1)
    rings, _, _ = model.evaluate(np.arange(nu) / nu, v)  # (nu, nv, 3)
    centres = ring_centroids(model, v)[0]
    length = float(np.linalg.norm(np.diff(centres, axis=0), axis=1).sum())
    return axial_rings(length, float(np.linalg.norm(rings - centres, axis=2).mean()))


def tube_ends(model: CylinderModel, shape: Sequence[int], spacing: Sequence[float]) -> list[str]:
    """How each end of a tube (``v = 0``, then ``v = 1``) ended: ``"field of view"`` when its
    ring's mean point lies within the padding beyond the volume's faces (:data:`FOV_PAD` voxels)
    of a face, or outside, else ``"structure"`` (the image energy stopped it)."""
    from segsnake.profile import ring_centroids

    sp = np.asarray(spacing, dtype=float)
    far = (np.asarray(shape) - 1) * sp
    margin = FOV_PAD * sp
    return ["field of view" if np.any(c <= margin) or np.any(c >= far - margin) else "structure"
            for c in ring_centroids(model, np.array([0.0, 1.0]))[0]]
