"""The segmentation pipeline: image -> edge map -> lookups -> snake -> mask.

:func:`segment_volume` is the numerical core (arrays in, model and mask out, no files);
:func:`segsnake.runner.segment_file` wraps it with loading, validation and the outputs.

A filled object, sphere or tube (``energy: auto`` with ``feature: edge``), is segmented with the
region energy (:func:`_segment_region`; docs/design.md, "The region energy"). The edge stages
below serve thin sheets (``feature: surface``) and ``energy: edge``.

How the edge stages get the surface onto the boundary (design.md, "Where the minimum sits"):

1. *Edges.* The detector's edge map (``features.edge_map``), minus what cannot be the boundary:
   edges enclosed by the initial surface (the start lies inside the object, so they are internal
   structures), and in sheet mode sheets that do not face the snake's centre (sulci, septa).
2. *Capture.* The flux of ``grad(-d)``, ``d`` the distance to the remaining edges: the surface
   is pulled out towards its nearest edges from any distance, whatever the object's thickness.
   Its minimum lies about two smoothing widths inside the edge.
3. *Refinement.* The region integral of ``n_out . grad f`` (``f`` the smooth edge map, ``n_out``
   the detected normal oriented outward: down the step for a bright object, up it for a dark
   one, away from the centre for a sheet). Its first variation on the surface is
   ``n_out . grad f``, which vanishes exactly on the ridge of ``f``: no inward bias, and an edge
   of the wrong polarity repels.
4. *Inner face* (sheet mode with a polarity): for an object enclosed by a sheet (a brain in its
   CSF), capture and refinement again on the steps just inside the sheet.

Every stage minimizes its image term plus the internal energy (:mod:`segsnake.regularize`),
plus, in the edge stages, an axial pull on a cylinder's ends, and the user's shape prior, with
the step-limited L-BFGS of :mod:`segsnake.optimize` (the edge stages refuse steps that fold the surface; the
region stages price the volume it wraps twice).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from segsnake.distance import distance_to, distance_within
from segsnake.moments import mask_moments
from segsnake.energy import AxialTension, CrossingPenalty, FluxTerm, RingBarrier, SumEnergy
from segsnake.errors import ConfigError, SegmentationError
from segsnake.optimize import MIN_VOLUME_FRACTION, minimize_energy
from segsnake.parallel import gaussian_filter, pieces, thread_map
from segsnake.regularize import BendingRegularizer
from segsnake.surfaces import CylinderModel, SphereModel, SplineSurface, axial_rings, \
    model_from_dict

__all__ = ["SegmentResult", "segment_volume", "initial_model", "auto_init"]

Progress = Callable[[str, float], None]

#: Weight of the internal energy (see :func:`_stage_energy`), relative to the image energy
#: (measured: 0.5 keeps more of a lobed blob's detail at 1 x 1 x 2 mm, Dice 0.978 against
#: 0.970, but lets the noise-free Table 7.2 cylinder fold off its wall, 0.64).
REGULARIZATION = 1.0
#: Sheet mode with a polarity: the inner face is searched this deep inside the sheet's mid-surface
#: (mm; at least 3 detector scales). A brain's CSF and skull together are 5-10 mm thick.
INNER_FACE_DEPTH_MM = 10.0
#: ... after a refinement of the sheet stopped at this relative energy change per iteration.
INNER_FACE_SHEET_TOL = 1e-4
#: Below this mean edge strength under the final surface the segmentation is a failure.
MIN_EDGE_SUPPORT = 0.15
#: A-priori quadrature: nodes this many feature widths apart (see :func:`quadrature_order`),
#: or CAPTURE_NODE_SPACING in the capture stage (see :meth:`_Run.capture`; the inner face's
#: capture starts a few mm from its edges and takes INNER_CAPTURE_NODE_SPACING: measured on the
#: T1 brain, 1.9 s -> 0.8 s, same Dice), ...
NODE_SPACING = 4.0
CAPTURE_NODE_SPACING = 0.75
INNER_CAPTURE_NODE_SPACING = 2.0
#: ... at most this many per knot interval ...
MAX_ORDER = 48
#: ... refined until the image energy agrees with twice the order to this relative error.
QUADRATURE_RTOL = 2e-3
#: ... and while it runs, every this many iterations (see :class:`_QuadratureCheck`).
#: A moving surface crosses features that a converged one lies along: the running check only
#: catches gross under-resolution (measured: 0.2-1 % while a blob's refinement runs).
QUADRATURE_CHECK_EVERY = 25
QUADRATURE_RTOL_RUNNING = 2e-2
#: The capture runs again at this fraction of its smoothing width (:meth:`_Run.capture`): at
#: 1.5 mm it stops about 4 mm inside a hollow tube's mid-surface, where the refinement's ridge
#: term is flat and its tension shortened the tube instead (docs/benchmarks.md, session 15: the
#: sweep, which is not flat, and held-out tubes).
CAPTURE_CONTINUATION = 0.5
#: The region energy's density beyond the field of view (voxels of padding, and the density
#: there: +1, what the region densities give far outside an object, whose inside is negative).
#: Space the image does not show is not the object: a tube that leaves the volume ends on its
#: face, instead of following the face's density continued outwards (:mod:`segsnake.lookup`).
FOV_PAD = 2
FOV_DENSITY = 1.0
#: Tension of cylinder snakes per mm^2 of lateral surface, in units of the edge map's peak,
#: applied as a pull along the axis (see :func:`_stage_energy`).
CYLINDER_TENSION = 0.2


@dataclass
class SegmentResult:
    """What :func:`segment_volume` found."""

    model: SplineSurface
    mask: NDArray[np.bool_]
    energy: float
    iterations: int
    history: list[dict[str, Any]]
    timings: dict[str, float]
    polarity: str
    init_model: SplineSurface
    settings: dict[str, Any] = field(default_factory=dict)


def auto_init(image: NDArray, spacing: Sequence[float],
              polarity: str = "auto") -> tuple[NDArray, NDArray]:
    """Rough centre and half-size radii (both in voxel indices) of the largest object.

    Otsu's threshold of the image, the largest connected component on the object's side of it
    (bright, dark, or for ``auto`` the larger of the two that does not touch the volume's
    border), its centroid, and the radii of the ellipsoid with the same second moments, halved
    (so the initial sphere lies inside the object, as in thesis sec. 7.2.2/7.2.3).
    """
    from skimage.filters import threshold_otsu

    ok = np.isfinite(image)
    finite = image.ravel() if ok.all() else image[ok]  # (a view when nothing is missing)
    del ok
    if finite.size == 0 or finite.min() == finite.max():
        raise SegmentationError("cannot estimate an initial sphere: the image is constant")
    level = threshold_otsu(finite)
    sides = {"bright": image > level, "dark": image <= level}
    candidates = []
    for name, side in sides.items():
        if polarity in ("bright", "dark") and name != polarity:
            continue
        labels, n = ndimage.label(side)
        if n == 0:
            continue
        sizes = np.bincount(labels.ravel())[1:]
        comp = labels == (np.argmax(sizes) + 1)
        border = any(comp.take(0, axis=a).any() or comp.take(-1, axis=a).any() for a in range(3))
        candidates.append((border, -int(sizes.max()), name == "dark", comp))
    if not candidates:
        raise SegmentationError("cannot estimate an initial sphere: no object after Otsu")
    comp = min(candidates, key=lambda c: c[:3])[3]  # off the border first, then the largest
    center, cov = mask_moments(comp, spacing)
    sp = np.asarray(spacing, dtype=np.float64)
    # A solid ellipsoid of semi-axis a has variance a^2 / 5 along it.
    radii_mm = np.sqrt(np.maximum(np.linalg.eigvalsh(cov), 0.0) * 5.0)
    r = 0.5 * float(np.exp(np.mean(np.log(np.maximum(radii_mm, sp.min())))))
    return center, np.full(3, r) / sp


def _voxel_index(config, p: Sequence[float],
                index_from_world: Callable[[NDArray], NDArray] | None) -> NDArray:
    """A position of the ``segment`` options as voxel indices (it is in world mm with
    ``config.world``, which needs ``index_from_world``)."""
    q = np.asarray(p, dtype=np.float64)
    if not config.world:
        return q
    if index_from_world is None:
        raise ConfigError("--world needs an image with an affine")
    return index_from_world(q[None])[0]


def initial_model(config, spacing: Sequence[float], shape: Sequence[int],
                  index_from_world: Callable[[NDArray], NDArray] | None = None,
                  image: NDArray | None = None, region_params=None) -> SplineSurface:
    """Initial snake (in mm, scaled index space) from the ``segment`` options.

    Positions and radii are voxel indices along the array axes, or world millimetres with
    ``config.world``: then ``index_from_world`` converts points, sphere radii are lengths along
    the world axes (mapped through the inverse affine, so a rotated grid gets a rotated
    ellipsoid) and a cylinder radius is a length in mm. A sphere without radii: for the region
    energy with a centre, the largest ball about it that looks like one tissue
    (:func:`segsnake.click.click_radius`, read as ``region_params`` read the click); otherwise
    half the size of the image's largest object (:func:`auto_init`).
    """
    sp = np.asarray(spacing, dtype=np.float64)
    world_axes = None
    if config.world and index_from_world is not None:
        origin = index_from_world(np.zeros((1, 3)))[0]
        world_axes = index_from_world(np.eye(3)) - origin  # rows: index change per world unit
        world_axes = world_axes.T  # columns: the world axes in index units
    ext = (np.asarray(shape) - 1) * sp

    def point(p: Sequence[float] | None, name: str) -> NDArray | None:
        if p is None:
            return None
        mm = _voxel_index(config, p, index_from_world) * sp
        if np.any(mm < -0.5 * sp) or np.any(mm > ext + 0.5 * sp):
            raise ConfigError(f"{name} {list(map(float, p))} lies outside the volume "
                              f"(shape {tuple(int(n) for n in shape)})")
        return mm

    def lengths(r: Sequence[float], name: str) -> NDArray:
        r = np.asarray(r, dtype=np.float64)
        if np.any(~np.isfinite(r)) or np.any(r <= 0):
            raise ConfigError(f"{name} must be positive, got {list(map(float, np.atleast_1d(r)))}")
        return r if config.world else r * sp

    if config.shape == "sphere":
        m1 = config.m1 or 9
        m2 = config.m2 or 9
        center = point(config.center, "--center")
        axes = None  # columns: the ellipsoid's semi-axes in mm of scaled index space
        if config.radii is not None:
            radii = lengths(config.radii, "--radii")
            if config.world and world_axes is not None:
                # Radii along the world axes: map them through the affine's inverse.
                axes = np.diag(sp) @ world_axes @ np.diag(radii)
            else:
                axes = np.diag(radii)
        if center is None or config.radii is None:
            if image is None:
                raise ConfigError("sphere initialization needs --center and --radii")
            if center is not None and region_energy(config):
                # A click alone: the largest ball of its tissue. (The edge stages read no
                # intensity model from it; they keep the object's size.)
                from segsnake.click import click_radius
                from segsnake.region import RegionParams

                p = region_params or RegionParams()
                axes = click_radius(image, sp, center, smooth_mm=p.smooth_mm,
                                    core_fraction=p.core_fraction,
                                    min_sigma_fraction=p.min_sigma_fraction) * np.eye(3)
            else:  # the largest object: a sphere inside it
                c_idx, r_idx = auto_init(image, sp, config.polarity)
                center = c_idx * sp if center is None else center
                if axes is None:
                    axes = np.diag(r_idx * sp)
        return SphereModel.unit(m1, m2).transformed(axes, center)
    if config.shape == "cylinder":
        if config.centerline is not None:  # issue 16: a tube along a polyline
            from segsnake.centerline import centerline_model

            return centerline_model(config, sp, shape, index_from_world)
        if config.axis_start is None or config.axis_end is None or config.radius is None:
            raise ConfigError("cylinder initialization needs --axis-start, --axis-end and --radius")
        a0 = point(config.axis_start, "--axis-start")
        a1 = point(config.axis_end, "--axis-end")
        if np.allclose(a0, a1):
            raise ConfigError("--axis-start and --axis-end coincide")
        r = float(lengths([config.radius], "--radius")[0])
        if not config.world:  # lengths() scaled it per axis; a radius goes across the axis
            r = float(config.radius) * perpendicular_spacing(sp, a1 - a0)
        return CylinderModel.from_axis(a0, a1, r, m1=config.m1 or 8, m2=config.m2 or 4)
    raise ConfigError(f"unknown shape {config.shape!r} (expected sphere or cylinder)")


def perpendicular_spacing(spacing: Sequence[float], axis: Sequence[float]) -> float:
    """Voxel size across a direction: how ``--radius`` in voxels converts to mm.

    ``sqrt(sum_i (1 - a_i^2) s_i^2 / 2)`` for the unit axis ``a``: the RMS of the spacing over the
    plane perpendicular to the axis (for an axis along k, ``sqrt((sx^2 + sy^2) / 2)``).
    """
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    s = np.asarray(spacing, dtype=np.float64)
    return float(np.sqrt(np.sum((1 - a * a) * s * s) / 2))


def _center_and_axis(model: SplineSurface) -> tuple[NDArray, NDArray | None]:
    """The centre of a sphere snake; for a cylinder its axis as (start point, end - start)."""
    if model.kind == "cylinder":
        return model.axis_and_radius()[:2]
    return model.control_points().reshape(-1, 3).mean(axis=0), None


def _radial_cosine(normals: NDArray, spacing: Sequence[float], center: NDArray,
                   axis: NDArray | None) -> NDArray:
    """``n . r`` per voxel (float32), ``r`` the unit vector pointing away from a centre, or from
    the nearest point of an axis segment.

    For a cylinder, ``center`` is the axis start and ``axis`` runs to its end: inside the
    segment's slab ``r`` is radial, beyond an end it points away from that end's centre (so the
    ends of a tube are pushed along it). Computed in slabs of planes in threads: the whole
    field as float64 arrays took 0.25 s on a 128^3 tube.
    """
    shape = normals.shape[:3]
    sp = [float(s) for s in spacing]
    c = [float(x) for x in center]
    length = float(np.linalg.norm(axis)) if axis is not None else 0.0
    a = [float(x) / max(length, 1e-12) for x in axis] if axis is not None else None
    out = np.empty(shape, dtype=np.float32)
    ys = (np.arange(shape[1], dtype=np.float32) * sp[1] - c[1])[None, :, None]
    zs = (np.arange(shape[2], dtype=np.float32) * sp[2] - c[2])[None, None, :]

    def slab(sl: slice) -> None:
        xs = (np.arange(sl.start, sl.stop, dtype=np.float32) * sp[0] - c[0])[:, None, None]
        d = [xs, ys, zs]
        if a is not None:
            along = np.clip(xs * a[0] + ys * a[1] + zs * a[2], 0.0, length)
            d = [di - along * ai for di, ai in zip(d, a)]
        n = normals[sl]
        norm = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) + 1e-6
        out[sl] = (n[..., 0] * d[0] + n[..., 1] * d[1] + n[..., 2] * d[2]) / norm

    thread_map(slab, pieces(shape[0], 16))
    return out


def _polarity(model: SplineSurface, gradient: NDArray, spacing: Sequence[float]) -> int:
    """+1 when the object is brighter than its surroundings along the current surface."""
    u = np.linspace(0, 1, 4 * model.m1, endpoint=False)
    v = np.linspace(0.05, 0.95, 4 * model.m2)
    pts = model.evaluate(u, v)[0].reshape(-1, 3)
    n = model.normals(u, v).reshape(-1, 3)
    idx = np.round(pts / np.asarray(spacing)).astype(int)
    idx = np.clip(idx, 0, np.asarray(gradient.shape[:3]) - 1)
    g = gradient[idx[:, 0], idx[:, 1], idx[:, 2]]
    return 1 if float(np.sum(g * n)) <= 0 else -1


def segment_volume(image: NDArray, spacing: Sequence[float], config, *,
                   index_from_world: Callable[[NDArray], NDArray] | None = None,
                   progress: Progress | None = None, extra_energy=None,
                   region_params=None,
                   init_model: SplineSurface | None = None,
                   init_record: dict | None = None) -> SegmentResult:
    """Segment one structure in ``image`` with the options of ``config`` (a SegmentConfig).

    Parameters
    ----------
    image : ndarray (nx, ny, nz)
        Intensities (float).
    spacing : (sx, sy, sz)
        Voxel size in mm.
    config : SegmentConfig
        The ``segment`` options.
    index_from_world : callable, optional
        World mm -> voxel index conversion (for ``config.world``).
    progress : callable(stage, fraction), optional
        Progress reports in [0, 1].
    extra_energy : callable(model) -> Energy, optional
        Added to every stage (the shape prior plugs in here).
    region_params : segsnake.region.RegionParams, optional
        The region energy's constants (default ``RegionParams()``).
    init_model : SplineSurface, optional
        Start from this snake (mm of scaled index space; a saved result, ``segment --init``)
        instead of :func:`initial_model`. It is taken to lie on the boundary already: the
        stages that only bring a rough start onto it are skipped (region energy: the first
        region stage, which grows a click; edge stages: the discard of edges enclosed by the
        initial surface, and the first capture), so that a saved result is refined where it
        is rather than pulled elsewhere.
    init_record : dict, optional
        The saved result's ``restart`` record (its ``snake.json`` settings), with ``init_model``:
        a run from a result on the same image with the same options then reproduces it
        (:func:`_segment_region`, :func:`_segment`).
    """
    sp = tuple(float(s) for s in spacing)
    t0 = time.perf_counter()
    # (issue 17, --init) A saved snake replaces the initial shape and skips the rough start.
    on_boundary = init_model is not None
    model = init_model if on_boundary else \
        initial_model(config, sp, image.shape, index_from_world, image, region_params)
    init_s = time.perf_counter() - t0
    if config.seed_point is not None:
        # The seed point is a position like the others: world mm with --world. (It may lie
        # outside the volume: it picks the edge component nearest to it.)
        seed = _voxel_index(config, config.seed_point, index_from_world)
        config = config.replace(seed_point=[float(x) for x in seed])
    if region_energy(config):
        return _segment_region(image, sp, config, model, progress, extra_energy, init_s,
                               region_params, on_boundary, init_record)
    # The edge stages' record: the edges discarded were chosen from the first run's initial
    # surface.
    from segsnake.region import RegionParams

    options = _restart_options(image, sp, config, region_params or RegionParams())
    record, record_use = _usable_restart(init_record, options, model) if on_boundary \
        else (None, None)
    first = model if record is None else model_from_dict(record["initial"])
    res = _segment(image, sp, config, model, progress, extra_energy, init_s,
                   on_boundary=on_boundary, record=record, first=first)
    return _with_record(res, options, first, on_boundary, record_use)


def _with_record(res: SegmentResult, options: dict[str, Any], first: SplineSurface,
                 on_boundary: bool, record_use: str | None) -> SegmentResult:
    """An edge-stage result with its restart record completed: the options, and the initial
    surface its discards came from."""
    res.settings["restart"] = {**options, "initial": first.to_dict(),
                               **res.settings["restart"]}
    if on_boundary:
        res.settings["restart_record"] = record_use
    return res


def region_energy(config) -> bool:
    """Does ``config`` segment with the region energy (:func:`_segment_region`)?

    ``energy: auto`` chooses it for a filled object (``feature: edge``): a sphere, or a
    cylinder closed by its end caps (:class:`FluxTerm`); a thin sheet (``feature: surface``)
    and a ``seed_point`` (which picks one of the edge map's surfaces) keep the edge stages
    (docs/design.md).
    """
    if config.energy == "auto":
        return config.feature == "edge" and config.seed_point is None
    if config.energy == "region" and config.feature != "edge":
        raise ConfigError("energy: region segments a filled object (feature: edge)")
    return config.energy == "region"


def _segment_region(image, sp, config, model, progress, extra_energy, init_s,
                    params=None, on_boundary: bool = False,
                    init_record: dict | None = None) -> SegmentResult:
    """The region energy from the click (:mod:`segsnake.region`, docs/design.md).

    1. *Intensity model*: the robust Gaussian of the smoothed image in the click's core.
    2. *Region*: the surface minimizes the volume integral of ``w``, the click's Gaussian
       against a uniform outside: it fills what looks like the click and stops where the
       intensity leaves the click's band, a little inside a blurred step.
    3. *Two classes*: the outside's mean is read just outside that surface, averaged along it;
       the same minimization with the inside's Gaussian against that local outside one (on the
       image as acquired: smoothing would move a curved step inwards) puts the surface at the
       midpoint intensity between the two, i.e. on the step (plus, with
       ``edge_length_mm``, the flux of ``grad I`` over the step's peak gradient).

    A tube that reaches a division of its structure (:mod:`segsnake.branching`, read after
    stage 2 and after each round but the last) is held back beyond it from then on.

    ``on_boundary`` (a saved result): stage 2 is skipped, the snake is already on the step.
    ``init_record``: that result's ``restart`` record (:func:`_restart_options`; in its
    ``snake.json`` settings). When it was made on this image with these options for a snake of
    this size, the run rebuilds the energy the result's last stage ended in (the intensity
    model, the window, the last round's starting surface that placed the outside's shell, a
    tube's cuts at its divisions, the stage's reference surface and quadrature order) and runs
    only that stage, which checks
    stationarity before its first step: a result comes back unchanged. Otherwise (a hand-edited
    markups file, another size, image or options) the intensity model is read from the snake's
    core and the two-class rounds run from it.

    The last stage (the last round, or the finer grid kept) ends stationary
    (:func:`segsnake.optimize.stationarity`), and its record is returned in ``settings``.
    """
    from segsnake import region as rg
    from segsnake.branching import Cut, find_cuts
    from segsnake.rasterize import rasterize
    from segsnake.window import Window

    p = params or rg.RegionParams()
    report = progress or (lambda stage, frac: None)
    run = _Run(config, sp, image.shape, extra_energy, p)
    init = model
    run.timings["init_s"] = init_s
    t0 = time.perf_counter()
    image_s = rg.smoothed(image, sp, p.smooth_mm)
    options = _restart_options(image, sp, config, p)
    restart, restart_use = _usable_restart(init_record, options, model) if on_boundary \
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

    def stage(start, density, name, tol=None, stationary=False, resume=None):
        # One stage in a window around the surface; while its surface comes near a face of the
        # window (which holds it back from then on), on from there in a window around both
        # (segsnake.window).
        nonlocal window
        margin, used = p.window_mm, 0
        while True:
            run.lookup = None  # (the last stage's: not needed while this one's is built)

            spent = []

            def write(values, window=window):
                # the density straight into the lookup's array, +1 in its padding
                t0 = time.perf_counter()
                values[...] = FOV_DENSITY
                inner = values[(slice(FOV_PAD, -FOV_PAD or None),) * 3]
                density(window, inner)
                for cut in cuts.values():
                    cut.apply(inner, window.lo, sp, FOV_DENSITY)
                spent.append(time.perf_counter() - t0)

            t0 = time.perf_counter()
            lookup = run.region_lookup(tuple(n + 2 * FOV_PAD for n in window.shape), write)
            run.timings["edge_map_s"] += sum(spent)
            run.timings["lookup_s"] += time.perf_counter() - t0 - sum(spent)
            # (a surface that comes near a face of the window leaves the stage at once: its
            # further course would be the window's, not the image's)
            model = window.model_out(run.region(
                window.model_in(start), lookup, name, tol, stationary, resume,
                leaves=lambda m, w=window: w.reaches(w.model_out(m), p.shell_mm), used=used))
            del lookup
            if not window.reaches(model, p.shell_mm):
                return model
            last = run.history[-1]
            last["window_grown"] = True
            old, margin = window, 2 * margin  # (a surface that grows far needs few windows)
            window = window.union(Window.around(model, image.shape, sp, margin))
            resume = None
            if last.get("left"):
                # Up to here the window's energy was the whole volume's: the stage goes on from
                # this iterate with the same functional (reference surface, quadrature order).
                reference = window.model_in(old.model_out(run.last["reference"]))
                start, resume = model, (reference, tuple(run.last["order"]))
                used += last["iterations"]
            else:  # (ended near a face it never came near while running: afresh)
                used = 0

    def branching(model):
        # A tube that reached a division of its structure ends there (the first cut found at
        # an end stays: the rounds after it draw the tube back to it).
        if model.kind == "cylinder":
            for end, cut in find_cuts(model, image_s, sp, intensity, p.branch_fraction,
                                      p.cut_radii).items():
                cuts.setdefault(end, cut)

    report("region", 0.1)
    if not on_boundary:
        model = stage(model, lambda win, out: rg.region_density(image_s[win.slices], intensity,
                                                                out),
                      "region", p.interim_tol)
        if model.kind == "cylinder" and config.m2 is None:
            # Now that the tube's calibre is known: rings a radius apart along it.
            from segsnake.resample import interpolate_tube

            m2 = tube_rings(model)
            if m2 != model.m2:
                model = interpolate_tube(model, m2)
        branching(model)
    report("two classes", 0.5)

    def inside_and_shell(surface, win):
        # The voxels inside the surface, and the shell between shell_gap_mm and shell_mm
        # outside it where the outside is read, on the window's grid.
        inside = rasterize(win.model_in(surface), win.shape, sp)
        shell = distance_within(inside, sp, p.shell_mm)
        return inside, (shell > p.shell_gap_mm) & (shell <= p.shell_mm)

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
        inside, shell = inside_and_shell(start, win)
        if not inside.any():
            raise SegmentationError("the surface encloses no voxel centre")
        if not shell.any():
            raise SegmentationError("the surface filled the whole image: no outside to compare")
        contrast, polarity = rg.step_contrast(sub, inside, shell)
        if contrast < p.min_separation * intensity.sigma:
            # (a click alone started from one tissue's ball: an object of several needs a radius)
            hint = " or give --radii (the click alone found one tissue's ball)" \
                if config.center is not None and config.radii is None and not on_boundary \
                and model.kind == "sphere" else ""
            raise SegmentationError(
                f"no boundary found: inside and outside the surface differ by {contrast:.3g}, "
                f"{contrast / intensity.sigma:.2f} x the click's spread; check the "
                f"initialization{hint}")
        if config.polarity in ("bright", "dark"):
            polarity = 1 if config.polarity == "bright" else -1
        if k == p.two_class_rounds:
            separated = rg.class_separation(sub, inside, shell)
            run.timings["edge_map_s"] += time.perf_counter() - t0
            break
        run.timings["edge_map_s"] += time.perf_counter() - t0

        def density(w_win, out, shell=shell):
            # The two classes with the outside read around the round's starting surface (in a
            # grown window, read again there).
            if w_win != win:
                shell = inside_and_shell(start, w_win)[1]
            sub = image_s[w_win.slices]
            mu_out = rg.local_outside_mean(sub, shell, sp, p.outside_smooth_mm)
            rg.two_class_blend(image[w_win.slices], sub, intensity, mu_out, out)
            del mu_out
            if p.edge_length_mm > 0:
                out += rg.edge_density(image[w_win.slices], sp, polarity, contrast,
                                       p.edge_length_mm, p.edge_smooth_mm)

        del inside
        resume = None
        if restart is not None:
            resume = (model_from_dict(restart["reference"]), tuple(restart["order"]))
        model = stage(model, density, f"two classes, round {k + 1}",
                      None if k == last else p.interim_tol, stationary=k == last, resume=resume)
        del density, shell
        if k == last:
            # The result's energy: its record (lookup from these, reference, order).
            final, round_start, final_window = run.last, start, window
        else:
            branching(model)
        # (a tube's rings along follow its calibre: its finer grids are finer around only)
        if k == last and config.coarse_to_fine and config.m1 is None \
                and (config.m2 is None or model.kind == "cylinder"):
            finer, kept = _finer_grids(run, window.model_in(model), p)
            model, final = window.model_out(finer), kept or final
    # The last pass of the loop rasterized the final surface (and checked it is not empty).
    mask = win.embed(inside)
    del inside, shell
    report("done", 1.0)
    on_step = rg.boundary_fraction(image_s, model, sp, polarity,
                                   p.step_spreads * intensity.sigma, p.step_depth_mm)
    if final is not None:
        record = {**options, "intensity": intensity.to_dict(),
                  "window": [list(final_window.lo), list(final_window.hi)],
                  "round_start": round_start.to_dict(), "stage": final["stage"],
                  "cuts": {str(end): cut.to_dict() for end, cut in cuts.items()},
                  "reference": final["reference"].to_dict(), "order": final["order"]}
    else:  # (no two-class round: the region stage's result, no record)
        final = run.last
    settings = {"energy": "region", "intensity_model": intensity.to_dict(),
                "contrast": contrast, "separation": contrast / intensity.sigma,
                # (null for two constant classes: JSON has no infinity)
                "class_separation": separated if math.isfinite(separated) else None,
                "boundary_fraction": on_step, "window": [list(window.lo), list(window.hi)],
                "regularization": REGULARIZATION, "region_params": dataclasses.asdict(p),
                "restart": record}
    if on_boundary:
        settings["restart_record"] = restart_use
    if model.kind == "cylinder":
        settings["ends"] = tube_ends(model, image.shape, sp)
        from segsnake.profile import ring_centroids

        for end, cut in cuts.items():
            # (an end that had crept far past the division before it was seen may stay there)
            c = ring_centroids(model, np.array([float(end)]))[0][0]
            if abs(np.dot(c - cut.centre, cut.normal)) <= cut.radius / p.cut_radii:
                settings["ends"][end] = "branching"
    return SegmentResult(model, mask, final["energy"], run.iterations, run.history,
                         run.timings, "bright" if polarity > 0 else "dark", init, settings)


#: Version of the ``restart`` record in a result's settings (:func:`_restart_options`).
RESTART_FORMAT = 3  # (2: the edge stages' tubes closed, no frame; session 15; 3: cuts)


def _restart_options(image: NDArray, spacing, config, params) -> dict[str, Any]:
    """What a saved result's restart record must agree with to be used: the image (its
    SHA-256, shape, dtype and voxel size) and the options that enter the energy (the region
    energy's or the edge stages'), as JSON reads them back (a restart compares them with the
    record's)."""
    import hashlib
    import json

    data = np.ascontiguousarray(image)
    options = {"format": RESTART_FORMAT,
               "image_sha256": hashlib.sha256(memoryview(data).cast("B")).hexdigest(),
               "image_shape": list(data.shape), "image_dtype": str(data.dtype),
               "spacing": [float(s) for s in spacing],
               "energy": config.energy, "feature": config.feature, "scale": config.scale,
               "threshold": config.threshold, "seed_point": config.seed_point,
               "polarity": config.polarity, "tol": config.tol, "max_iter": config.max_iter,
               "prior": config.prior, "prior_weight": config.prior_weight,
               "region_params": dataclasses.asdict(params)}
    return json.loads(json.dumps(options))


def _usable_restart(record, options: dict[str, Any], model: SplineSurface
                    ) -> tuple[dict | None, str]:
    """The record if it applies to a run from ``model`` with ``options``, and why (not)."""
    if not isinstance(record, dict):
        return None, ("not used: the snake has none (a markups file, a render output, or a "
                      "snake.json of an older segsnake)")
    differ = [k for k, v in options.items() if record.get(k) != v]
    if differ:
        return None, (f"not used: the record's {', '.join(differ)} "
                      f"{'differs' if len(differ) == 1 else 'differ'} from this run's")
    ref = record["reference"]
    if (ref["kind"], ref["m1"], ref["m2"]) != (model.kind, model.m1, model.m2):
        return None, "not used: the snake was resampled to another size"
    return record, "used"


def _finer_grids(run, model: SplineSurface, p) -> tuple[SplineSurface, dict | None]:
    """Coarse to fine: the last stage again on finer control grids (``p.finer_m``: M1 = M2 for a
    sphere, M1 around a tube, whose M2 stays the one its calibre chose), each started
    from the exact L2 projection of the current surface (:mod:`segsnake.resample`), kept while
    it refines the surface: it lowers the image energy (where it fits just as well, the two
    surfaces nearly agree, so the choice does not flip the result), and the volume it encloses
    stays within ``p.finer_volume`` of the coarser surface's (detail comes back as bulges and
    necks whose volumes nearly cancel; a leak into a neighbour or a fold through itself moves
    the whole volume). The first grid refused ends the schedule, as does a finer stage that
    fails (a collapse). Returns the surface and the ``run.last`` of the finer stage kept (None
    if none)."""
    from segsnake.resample import resample

    lookup, kept = run.lookup, None

    def image_energy(m: SplineSurface, order: int) -> float:
        flux = FluxTerm(m, lookup, weight=1.0, order=order, closed=True)
        return flux.value_and_grad(m.params)[0]

    tube = model.kind == "cylinder"
    for m in p.finer_m:
        if m <= (model.m1 if tube else min(model.m1, model.m2)):
            continue
        m2 = model.m2 if tube else m
        last, name = run.last, f"grid {m}x{m2}"
        try:
            finer = run.region(resample(model, m, m2), lookup, name, stationary=True)
        except SegmentationError as exc:
            # (a finer surface that collapsed through itself is no refinement either)
            run.history.append({"stage": name, "kept": False, "error": str(exc)})
            break
        # both on the finer grid's nodes: intervals of the coarser one's size or less
        order = min(2 * quadrature_order(float(longest_intervals(finer).max()),
                                         p.edge_smooth_mm), MAX_ORDER)
        e, e_fine = image_energy(model, order), image_energy(finer, order)
        gain = (e - e_fine) / max(abs(e), 1e-300)
        volume = abs(model.volume(order=4))
        change = (finer.volume(order=4) - volume) / max(volume, 1e-300)
        keep = bool(gain > 0.0 and abs(change) <= p.finer_volume)
        run.history[-1].update(image_energy_gain=gain, volume_change=change, kept=keep)
        if not keep:
            run.last = last  # (the result's energy stays the coarser stage's)
            break
        model, kept = finer, run.last
    return model, kept


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


def _default_scale(spacing: Sequence[float]) -> float:
    """The detector scale without ``--scale``: 1.5 voxels of the largest size, at least 1 mm."""
    return max(1.0, 1.5 * max(spacing))


def _final_mask(model: SplineSurface, shape, spacing) -> NDArray[np.bool_]:
    from segsnake.rasterize import rasterize

    mask = rasterize(model, shape, spacing)
    if not mask.any():
        raise SegmentationError("the final surface encloses no voxel centre")
    return mask


def _segment(image, sp, config, model, progress, extra_energy, init_s,
             on_boundary: bool = False, record: dict | None = None,
             first: SplineSurface | None = None) -> SegmentResult:
    """:func:`segment_volume` from the initial snake on, with the edge stages (``on_boundary``:
    the snake is a saved result, no enclosed-edge discard and no first capture).

    ``record`` (with ``on_boundary``): the saved result's restart record, usable here. Then the
    edges are discarded as the first run did, from its initial surface ``first``; the
    refinement's normals are oriented (and an automatic polarity decided) on its recorded
    starting surface, an inner face's band placed around its recorded sheet; the stages before
    the last are skipped, and the last runs on its recorded reference and order: a stationary
    result comes back unchanged (:func:`_run_stage`). The last stage ends stationary, and what
    it needs is returned in ``settings["restart"]``."""
    from segsnake.features import auto_levels, edge_map, hysteresis_threshold
    from segsnake.rasterize import rasterize

    shape = image.shape
    report = progress or (lambda stage, frac: None)
    run = _Run(config, sp, shape, extra_energy)
    init = model
    run.timings["init_s"] = init_s

    t0 = time.perf_counter()
    scale = config.scale if config.scale is not None else _default_scale(sp)
    seed = None if config.seed_point is None else np.asarray(config.seed_point, dtype=float)
    sheet = config.feature == "surface"
    # Thin dark sheets (the CSF around a brain in T1) are thin bright sheets of -image.
    dark_sheet = sheet and config.polarity == "dark"
    em = edge_map(-image if dark_sheet else image, sp, mode=config.feature, scale_mm=scale,
                  threshold=config.threshold, seed=seed)
    # The initial surface lies inside the object (that is the contract of an initialization):
    # edges it encloses are internal structures (ventricles, vessels), never the boundary.
    # (A saved result encloses its own boundary's edges: nothing is discarded for it, unless
    # its record gives the first run's initial surface.)
    first = model if first is None else first
    if not on_boundary or record is not None:
        inside_init = rasterize(first, shape, sp)
        _discard(em, ~ndimage.binary_dilation(inside_init) if inside_init.any() else None)
    if sheet:
        # A sheet around the object faces its centre (thesis sec. 7.2.2: keep the voxels whose
        # normal points to the centre); sheets that run radially (sulci, septa) are not it.
        _discard(em, np.abs(_radial_cosine(em.normals, sp, *_center_and_axis(first))) >= 0.5)
    run.timings["edge_map_s"] = time.perf_counter() - t0
    report("edge map", 0.15)

    if not on_boundary:
        model = run.capture(model, em.mask, em.smooth_mm)
    report("snake", 0.5)
    # (the surface the refinement starts from orients its normals)
    start = model if record is None else model_from_dict(record["refine_start"])
    if sheet:
        out = np.sign(_radial_cosine(em.normals, sp, *_center_and_axis(start)))[..., None] \
            * em.normals
        polarity = "sheet"
    elif config.polarity in ("auto", "bright", "dark"):
        pol = _polarity(start, em.gradient, sp) if config.polarity == "auto" else \
            (1 if config.polarity == "bright" else -1)
        polarity = "bright" if pol > 0 else "dark"
        out = -pol * em.normals  # normals point to the brighter side
    else:
        out = np.sign(_radial_cosine(em.normals, sp, *_center_and_axis(start)))[..., None] \
            * em.normals
        polarity = "none"
    inner_face = sheet and config.polarity in ("bright", "dark")
    resume = None if record is None else \
        (model_from_dict(record["reference"]), tuple(record["order"]))
    if record is None or not inner_face:
        # Before an inner face, the sheet only has to be found well enough to place the band
        # inside it: the capture's tolerance (measured on the T1 brain: its last three stages
        # took 345 iterations, now 242; same Dice).
        model = run.refine(model, em, out, min(em.smooth_mm, scale),
                           tol=INNER_FACE_SHEET_TOL if inner_face else None,
                           stationary=not inner_face, resume=None if inner_face else resume)
    support = edge_support(model, em.f, sp)
    sheet_model = model if record is None or not inner_face else \
        model_from_dict(record["sheet"])

    if inner_face:
        # An object enclosed by a sheet (a brain in its CSF) ends at the sheet's inner face:
        # the step from the object to the sheet, just inside the sheet's mid-surface. For a
        # dark sheet the inside is brighter than the sheet, for a bright one darker.
        report("inner face", 0.75)
        t0 = time.perf_counter()
        # Every step that survives non-maximum suppression, thresholded among the candidates
        # of the band only: the inner face can be far weaker than the sheet's outer face.
        inside = rasterize(sheet_model, shape, sp)
        depth = distance_to(~inside, sp)
        band = inside & (depth <= max(INNER_FACE_DEPTH_MM, 3 * scale))
        del depth
        # The sheet's pass already smoothed this image (or its negative) at this scale, and
        # Gaussian filtering commutes exactly with the sign: its derivatives are reused.
        sign = np.float32(-1.0 if dark_sheet else 1.0)
        derivs = {(0, 0, 0): sign * em.image_smooth}
        derivs.update({o: sign * em.gradient[..., d]
                       for d, o in enumerate([(1, 0, 0), (0, 1, 0), (0, 0, 1)])})
        face = edge_map(image, sp, mode="edge", scale_mm=scale, threshold=None, region=band,
                        _derivs=derivs)
        del derivs
        pol = 1 if config.polarity == "dark" else -1  # +1: the object is brighter than the sheet
        # steps that face the sheet
        band &= -pol * _radial_cosine(face.normals, sp, *_center_and_axis(sheet_model)) >= 0.5
        low, high = auto_levels(face.response[face.mask & band])
        _discard(face, band & hysteresis_threshold(np.where(band, face.response, -1.0), low, high))
        run.timings["edge_map_s"] += time.perf_counter() - t0
        if record is None:
            model = run.capture(model, face.mask, face.smooth_mm, INNER_CAPTURE_NODE_SPACING)
        model = run.refine(model, face, -pol * face.normals, min(face.smooth_mm, scale),
                           stationary=True, resume=resume)
        support = edge_support(model, face.f, sp)
        polarity = f"inner face of a {config.polarity} sheet"

    if support < MIN_EDGE_SUPPORT:
        raise SegmentationError(
            f"no boundary found: the final surface lies on almost no detected edge (mean edge "
            f"strength {support:.2f}, expected about 1); check the initialization or --scale")
    t0 = time.perf_counter()
    mask = _final_mask(model, shape, sp)
    run.timings["mask_s"] = time.perf_counter() - t0
    report("done", 1.0)
    settings = {"edge_support": support, "scale_mm": scale, "smooth_mm": em.smooth_mm,
                "regularization": REGULARIZATION,
                "levels": None if em.levels is None else list(map(float, em.levels)),
                "edge_voxels": int(em.mask.sum()),
                "restart": {"refine_start": start.to_dict(),
                            "sheet": sheet_model.to_dict() if inner_face else None,
                            "stage": run.last["stage"],
                            "reference": run.last["reference"].to_dict(),
                            "order": run.last["order"]}}
    return SegmentResult(model, mask, run.history[-1]["energy"], run.iterations, run.history,
                         run.timings, polarity, init, settings)


def _discard(em, keep: NDArray | None) -> None:
    """Keep only the edges where ``keep`` is True, in the mask and in the smooth map f."""
    if keep is None:
        return
    em.mask &= keep
    em.f *= gaussian_filter(keep, [em.smooth_mm / x for x in em.spacing])


class _Run:
    """The stages of one segmentation, with their history and timings."""

    def __init__(self, config, spacing, shape, extra_energy, region_params=None) -> None:
        self.config, self.sp, self.extra = config, spacing, extra_energy
        self.region_params = region_params
        self.bounds = (np.asarray(shape) - 1) * np.asarray(spacing)
        self.history: list[dict[str, Any]] = []
        self.iterations = 0
        self.timings: dict[str, float] = {"lookup_s": 0.0, "optimize_s": 0.0}
        self.last: dict[str, Any] | None = None  # the last stage's energy and functional

    def _stage(self, name, model, lookup, band, feature_mm, tol=None, node_spacing=None,
               weight=-1.0, region=False, stationary=False, resume=None, leaves=None, used=0):
        model, res = _run_stage(model, lookup, weight, self.config, self.bounds, self.extra, band,
                                feature_mm, tol, node_spacing, region, stationary, resume,
                                leaves, used,
                                self.region_params.crossing_weight if region else 0.0)
        self.timings["optimize_s"] += res["time_s"]
        self.iterations += res["iterations"]
        # What defines the energy this stage ended in (its lookup is self.lookup), for the
        # restart record of the stage that gives the result.
        reference, order = res.pop("functional")
        self.last = {"stage": name, "energy": res["energy"], "reference": reference,
                     "order": [int(o) for o in order]}
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
               stationary: bool = False, resume=None, leaves=None, used: int = 0):
        """Minimize the volume integral of a density (:mod:`segsnake.region`) given by its
        :meth:`region_lookup` (the model in the window's coordinates); ``self.lookup`` keeps
        the lookup. ``stationary``, ``resume``, ``leaves``, ``used``: see :func:`_run_stage`."""
        self.lookup = lookup
        p = self.region_params
        return self._stage(name, model, lookup, p.step_mm, p.edge_smooth_mm, tol, weight=1.0,
                           region=True, stationary=stationary, resume=resume, leaves=leaves,
                           used=used)

    def _edge_lookup(self, field: NDArray, divergence_of_gradient: bool) -> "_Shifted":
        """An edge stage's lookup (:meth:`segsnake.lookup.Lookup.from_field`): its density is
        zero on :data:`FOV_PAD` voxels around the grid (no edge is known beyond the field of
        view), sampled in the grid's coordinates."""
        from segsnake.lookup import Lookup

        return _Shifted(Lookup.from_field(field, self.sp, pad=FOV_PAD,
                                          divergence_of_gradient=divergence_of_gradient),
                        FOV_PAD * np.asarray(self.sp))

    def capture(self, model, edges: NDArray, smooth_mm: float,
                node_spacing: float = CAPTURE_NODE_SPACING):
        """The flux of ``grad(-d)``, d the distance to the edges (smoothed to be differentiable).

        Inside an object, ``grad(-d)`` points to the nearest edge, so the flux pulls the surface
        out towards the edges from any distance, whatever the object's thickness (a wide Gaussian
        ridge collapses snakes in objects thinner than its width). The pull is the curvature of
        the distance's level sets: strong in front of round edges, weak in front of large flat
        walls. Its minimum lies about two smoothing widths inside the edge: so it runs again at
        :data:`CAPTURE_CONTINUATION` times its width from where it stopped (continuation in
        scale), which ends within the refinement's reach. (A region integral of ``r .
        grad(-d)``, r radial, pulls with unit strength in front of flat walls too, but turns
        negative in the concave necks of lobed shapes and folds them.)

        Beyond the field of view ``lap(-d)`` is zero (:data:`FOV_PAD`; no edge is known there):
        a tube that leaves the volume feels nothing past the face, and its tension ends it there.
        """
        if not edges.any():
            raise SegmentationError("no edges found outside the initial surface")
        t0 = time.perf_counter()
        dist = distance_to(edges, self.sp)
        self.timings["lookup_s"] += time.perf_counter() - t0
        first = max(smooth_mm, 1.5)
        widths = (first, CAPTURE_CONTINUATION * first)
        for k, sigma in enumerate(widths):
            t0 = time.perf_counter()
            # -d, filtered in place (the last pass takes dist itself)
            f_d = np.negative(dist, out=None if k < len(widths) - 1 else dist)
            f_d = gaussian_filter(f_d, [sigma / x for x in self.sp], mode="nearest", copy=False)
            lookup = self._edge_lookup(f_d, divergence_of_gradient=True)
            del f_d
            self.timings["lookup_s"] += time.perf_counter() - t0
            # -d varies on the scale of sigma only near edges and medial axes: nodes 2 sigma
            # apart. The capture surface crosses the features of -d on its way out, so its
            # a-priori quadrature is fine from the start: a coarse first round can run into a
            # spurious minimum that the finer rounds do not leave (measured on the PD brain:
            # -28311 against -51907, Dice 0.53).
            model = self._stage(f"capture (edge distance, sigma={sigma:.2f}mm)", model, lookup,
                                sigma, 2 * sigma, tol=1e-4, node_spacing=node_spacing)
            del lookup
        return model

    def refine(self, model, em, out: NDArray, feature_mm: float, tol: float | None = None,
               stationary: bool = False, resume=None):
        """The region integral of n_out . grad f, n_out the detected normal oriented outward.

        Its first variation is n_out . grad f on the surface, which vanishes exactly on the
        ridge of f. (The flux of f n_out would add f div(n_out) = 2 H f, and its optimum would
        sit 2 s^2 H outside the ridge: +15 % volume on a 10 mm ball.)
        """
        t0 = time.perf_counter()
        along = sum(out[..., d] * np.gradient(em.f, h, axis=d) for d, h in enumerate(self.sp))
        lookup = self._edge_lookup(along.astype(np.float32), divergence_of_gradient=False)
        del along
        self.timings["lookup_s"] += time.perf_counter() - t0
        return self._stage("refine", model, lookup, em.smooth_mm, feature_mm, tol=tol,
                           stationary=stationary, resume=resume)


def edge_support(model: SplineSurface, f: NDArray, spacing: Sequence[float]) -> float:
    """Area-weighted mean of the edge map over the surface (about 1 on a detected boundary).

    The edge map is an area density that peaks at about 1 on every detected surface, so this is
    the fraction of the snake that found an edge; a snake that ended in empty space or in
    noise has almost none.
    """
    pts, _, area = model.area_samples(4)
    values = ndimage.map_coordinates(f, (pts / np.asarray(spacing)).T, order=1, mode="constant",
                                     cval=0.0)
    return float(np.sum(area * values) / max(np.sum(area), 1e-300))


def _model_radius(model: SplineSurface) -> float:
    if model.kind == "cylinder":
        return model.axis_and_radius()[2]
    return float((3 * abs(model.volume(order=4)) / (4 * math.pi)) ** (1 / 3))


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

    This is only the starting order: :func:`_run_stage` checks the converged energy against twice
    the order and refines when they disagree. The integrand varies on the scale of the lookup's
    features only where the surface crosses them; a surface lying along a ridge sees it vary on
    the scale of its own geometry, so the a-priori order is deliberately coarse.
    """
    spacing = NODE_SPACING if spacing is None else spacing
    return int(np.clip(np.ceil(interval_mm / (spacing * feature_mm)), 4, MAX_ORDER))


def _run_stage(model, lookup, weight, config, bounds, extra_energy, band, feature_mm, tol=None,
               node_spacing=None, region=False, stationary=False, resume=None, leaves=None,
               used=0, crossing_weight=0.0):
    """Minimize one stage's energy, re-choosing the quadrature until it is trustworthy.

    A stage runs in rounds (at most 8). Each round picks the quadrature order for intervals up to
    1.5 times the current longest one and refuses steps beyond that; a round that ends at that
    limit is followed by another. A round that converged is then checked: the image energy at
    twice the order must agree to ``QUADRATURE_RTOL``, else the next round runs at the finer
    order. The check matters: an under-resolved quadrature is not just inaccurate, the optimizer
    *exploits* it (it grows a spike whose few nodes all sit on favourable values; measured: order
    4 gave -104695 where order 16 gives -92674 on a noisy ball). So every
    ``QUADRATURE_CHECK_EVERY`` iterations the running round is checked too, with the looser
    ``QUADRATURE_RTOL_RUNNING``, and a failure ends it (:class:`_QuadratureCheck`). A stage
    stopped by the iteration cap is checked too, with the running tolerance (it is still
    moving); ``quadrature_resolved`` in its history says whether the last check agreed
    (``segment`` warns when not).

    ``region``: the lookup integrates a volume density (:mod:`segsnake.region`), which moves the
    surface far from its start: no step is refused for its normals (:class:`_Admissible`), the
    bending is weighted for a volume energy, and the volume the surface wraps other than once
    is priced at ``crossing_weight`` per mm^3 (:func:`_stage_energy`).

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
    for _ in range(8):
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
        energy = _stage_energy(reference, lookup, weight, order, extra_energy, region,
                               crossing_weight)
        check = _QuadratureCheck(energy.terms[0], fine, checks, model.params)
        admissible = _Admissible(reference, max_interval, follow=region)
        res = minimize_energy(model, energy, max_iter=max(max_iter - iterations, 1),
                              tol=tol, bounds_mm=bounds, max_step_mm=band,
                              admissible=admissible,
                              callback=leaving(check.during),
                              stationary_tol=tol if resumed and stationary else None)
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
                              admissible=_Admissible(reference, max_interval, follow=region),
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


class _QuadratureCheck:
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
        coarse_e = self.coarse.value_and_grad(params)[0]
        fine_e = self._fine_term.value_and_grad(params)[0]
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


class _Admissible:
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


def _stage_energy(model, lookup, weight, order, extra_energy, region=False,
                  crossing_weight=0.0) -> SumEnergy:
    """The stage's energy; its first term is the image's :class:`FluxTerm`. A region stage's
    prices the volume its surface wraps other than once at ``crossing_weight`` per mm^3
    (:class:`CrossingPenalty`)."""
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
        # Past the end of a sheet (a hollow tube's open end) or the field of view the edge
        # map is empty: the caps feel no flux there, and without tension the ends drift on.
        # Tension makes a tube's length without edge support cost a fraction of what
        # surface on an edge gains (the edge map peaks at about 1 per mm^2): CYLINDER_TENSION
        # per mm^2 of lateral surface, as a pull along the axis only. (Surface tension, the
        # area, also presses on the whole lateral surface with CYLINDER_TENSION / radius, which
        # held tubes whose capture ended 4-5 mm inside the wall out of the refinement's reach:
        # measured when this was introduced: a tube along (1, 1, 0), Jaccard 0.32 -> 0.969.)
        perimeter = 2 * math.pi * r
        terms.append(AxialTension(model, weight=CYLINDER_TENSION * perimeter))
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
