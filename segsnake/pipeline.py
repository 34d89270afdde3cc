"""The segmentation pipeline: image -> initial snake -> stages -> snake and mask.

:func:`segment_volume` is the numerical core (arrays in, model and mask out, no files);
:func:`segsnake.runner.segment_file` wraps it with loading, validation and the outputs. It builds
the initial snake from the options (:func:`initial_model`: a click, a polyline along a tube, or
the image's largest object) and runs one of two sequences of stages:

- a filled object, sphere or tube (``energy: auto`` with ``feature: edge``): the region energy
  (:mod:`segsnake.region_stages`; docs/design.md, "The region energy");
- thin sheets (``feature: surface``) and ``energy: edge``: the edge stages
  (:mod:`segsnake.edge_stages`).

Each stage minimizes one energy (:mod:`segsnake.stage`). A saved result carries the record of
the energy its last stage ended in (:func:`restart_options`): a run from it on the same image
with the same options rebuilds that energy and comes back unchanged.
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

from segsnake.errors import ConfigError, SegmentationError
from segsnake.moments import mask_moments
from segsnake.parallel import one_blas_thread
from segsnake.surfaces import CylinderModel, SphereModel, SplineSurface, model_from_dict

__all__ = ["SegmentResult", "segment_volume", "initial_model", "auto_init", "region_energy",
           "perpendicular_spacing"]

Progress = Callable[[str, float], None]


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
        # (a cylinder's radius or axis that the sphere would ignore, deciding its start from the
        # click alone or the image: refused. Given beside a sphere's own radii or centre, as a
        # YAML base's or a batch's defaults may leave them, they are left alone.)
        if config.radius is not None and config.radii is None:
            raise ConfigError("radius is a cylinder's; a sphere takes radii, its three semi-axes "
                              "(for a ball of radius R: radii R R R)")
        if config.center is None and (config.axis_start is not None or
                                      config.axis_end is not None):
            raise ConfigError("axis_start and axis_end describe a cylinder's axis; a sphere "
                              "takes a center and radii")
        m1 = config.m1 or 9
        m2 = config.m2 or 9
        center = point(config.center, "--center")
        axes = None  # columns: the ellipsoid's semi-axes in mm of scaled index space
        if config.radii is not None:
            radii = lengths(config.radii, "--radii")
            if config.world and world_axes is not None:
                # Radii along the world axes: map them through the affine's inverse. (A grid
                # whose affine mirrors, as a LAS image's does, mirrors the axes too: the same
                # ellipsoid, parameterized inside out. One semi-axis reversed turns it back.)
                axes = np.diag(sp) @ world_axes @ np.diag(radii)
                if np.linalg.det(axes) < 0:
                    axes[:, 0] *= -1
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
        if image is not None and region_energy(config):
            # (the region energy's tube follows the cheapest path between the points through
            # the intensity around them: a bent vessel's start lies in it; docs/design.md)
            traced = _traced_tube(image, sp, a0, a1, r, config, region_params)
            if traced is not None:
                return traced
        return CylinderModel.from_axis(a0, a1, r, m1=config.m1 or 8, m2=config.m2 or 4)
    raise ConfigError(f"unknown shape {config.shape!r} (expected sphere or cylinder)")


def _traced_tube(image: NDArray, sp: NDArray, a0: NDArray, a1: NDArray, r: float, config,
                 region_params=None) -> CylinderModel | None:
    """The initial tube between two points for the region energy: along the cheapest path
    between them (:func:`segsnake.tube_path.traced_centerline`) through the image smoothed as the
    region energy reads it, in a box around the points (their distance beyond them on every
    side), the intensity model read within the start radius of either point
    (:func:`segsnake.tube_path.point_samples`). The path's points are ``TRACE_STEP_RADII`` radii
    apart (at least two voxels, at most ``AXIAL_RINGS_MAX`` intervals): a ring per point.

    Two points whose surroundings are not one tissue (medians more than
    :data:`segsnake.click.SHELL_SPREADS` pooled spreads apart: one of them off the tube) name no
    tube to trace, nor does a path too short for its rings: None, and the start is the straight
    cylinder between them, whose stages say what they find ("no boundary found" where it lies
    in the background)."""
    from segsnake import region as rg
    from segsnake.click import SHELL_SPREADS
    from segsnake.surfaces import AXIAL_RINGS_MAX
    from segsnake.tube_path import point_samples, traced_centerline

    p = region_params or rg.RegionParams()
    span = rg.image_range(image)  # (the whole image's: the spread's floor, as the stages read it)
    samples = [point_samples(image, sp, a, r, p.smooth_mm, rg.MIN_SAMPLES) for a in (a0, a1)]
    ends = [rg.IntensityModel.from_samples(x, span, p.min_sigma_fraction) for x in samples]
    if abs(ends[0].mu - ends[1].mu) > SHELL_SPREADS * math.sqrt(
            0.5 * (ends[0].sigma ** 2 + ends[1].sigma ** 2)):
        return None
    model = rg.IntensityModel.from_samples(np.concatenate(samples), span, p.min_sigma_fraction)
    margin = float(np.linalg.norm(a1 - a0))
    lo = np.maximum(np.floor((np.minimum(a0, a1) - margin) / sp), 0).astype(int)
    hi = np.minimum(np.ceil((np.maximum(a0, a1) + margin) / sp) + 1, image.shape).astype(int)
    origin = lo * sp
    image_s = rg.smoothed(image[tuple(slice(a, b) for a, b in zip(lo, hi))], sp, p.smooth_mm)
    step = max(TRACE_STEP_RADII * r, 2.0 * float(sp.max()))
    pts = traced_centerline(image_s, sp, a0 - origin, a1 - origin, model.mu, model.sigma, step,
                            AXIAL_RINGS_MAX + 1) + origin
    del image_s
    try:
        return CylinderModel.from_centerline(pts, r, m1=config.m1 or 8,
                                             m2=config.m2 or max(4, len(pts) - 1))
    except ValueError:  # (two stations at one point: a path shorter than its steps can hold)
        return None


#: Spacing of an end-point tube's traced centreline, in radii of the start (``--radius``): a ring
#: every two, so a bend of a few radii gets rings whether the radius given is the tube's or half
#: of it. Measured from the end points of bench_tubes' arch, S and exiting phantoms (half their
#: radius): 2 and 4 give the same (0.969-0.993 and 0.968-0.992), at 8 the thin S vessels and the
#: arch lose their bends (0.36-0.44, no boundary found); at the true radius 4 lost them too (S3
#: 0.56-0.67, the arch 0.71; 2: 0.96-0.995). docs/benchmarks.md, session 35.
TRACE_STEP_RADII = 2.0


def perpendicular_spacing(spacing: Sequence[float], axis: Sequence[float]) -> float:
    """Voxel size across a direction: how ``--radius`` in voxels converts to mm.

    ``sqrt(sum_i (1 - a_i^2) s_i^2 / 2)`` for the unit axis ``a``: the RMS of the spacing over the
    plane perpendicular to the axis (for an axis along k, ``sqrt((sx^2 + sy^2) / 2)``).
    """
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    s = np.asarray(spacing, dtype=np.float64)
    return float(np.sqrt(np.sum((1 - a * a) * s * s) / 2))


@one_blas_thread
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
        (:func:`segsnake.region_stages.segment_region`,
        :func:`segsnake.edge_stages.segment_edges`).
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
        from segsnake.region_stages import segment_region

        return segment_region(image, sp, config, model, progress, extra_energy, init_s,
                              region_params, on_boundary, init_record)
    # The edge stages' record: the edges discarded were chosen from the first run's initial
    # surface.
    from segsnake.edge_stages import segment_edges, with_record
    from segsnake.region import RegionParams

    options = restart_options(image, sp, config, region_params or RegionParams())
    record, record_use = usable_restart(init_record, options, model) if on_boundary \
        else (None, None)
    first = model if record is None else model_from_dict(record["initial"])
    res = segment_edges(image, sp, config, model, progress, extra_energy, init_s,
                        on_boundary=on_boundary, record=record, first=first)
    return with_record(res, options, first, on_boundary, record_use)


def region_energy(config) -> bool:
    """Does ``config`` segment with the region energy (:func:`segsnake.region_stages.segment_region`)?

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

#: Version of the ``restart`` record in a result's settings (:func:`restart_options`).
RESTART_FORMAT = 3  # (2: the edge stages' tubes closed, no frame; session 15; 3: cuts)


def restart_options(image: NDArray, spacing, config, params) -> dict[str, Any]:
    """What a saved result's restart record must agree with to be used: the image (its
    SHA-256, shape, dtype and voxel size) and the options that enter the energy (the region
    energy's or the edge stages'; of the region parameters, not those that only judge the
    result, :data:`segsnake.region.JUDGING_FIELDS`, nor those that only shape the growth
    passes a restart never runs, :data:`segsnake.region.PASS_FIELDS`), as JSON reads them back
    (a restart compares them with the record's)."""
    import hashlib
    import json

    from segsnake.region import JUDGING_FIELDS, PASS_FIELDS

    data = np.ascontiguousarray(image)
    options = {"format": RESTART_FORMAT,
               "image_sha256": hashlib.sha256(memoryview(data).cast("B")).hexdigest(),
               "image_shape": list(data.shape), "image_dtype": str(data.dtype),
               "spacing": [float(s) for s in spacing],
               "energy": config.energy, "feature": config.feature, "scale": config.scale,
               "threshold": config.threshold, "seed_point": config.seed_point,
               "polarity": config.polarity, "tol": config.tol, "max_iter": config.max_iter,
               "prior": config.prior, "prior_weight": config.prior_used()[0],
               "atlas": config.atlas, "structure": config.structure,
               "region_params": {k: v for k, v in dataclasses.asdict(params).items()
                                 if k not in JUDGING_FIELDS | PASS_FIELDS}}
    return json.loads(json.dumps(options))


def _agrees(saved: Any, value: Any) -> bool:
    """Does a record's entry agree with this run's? The region parameters on the fields this run
    compares (an older record also holds those that only judge a result or shape the passes)."""
    if isinstance(value, dict) and isinstance(saved, dict):
        return all(k in saved and saved[k] == v for k, v in value.items())
    return saved == value


def usable_restart(record, options: dict[str, Any], model: SplineSurface
                    ) -> tuple[dict | None, str]:
    """The record if it applies to a run from ``model`` with ``options``, and why (not)."""
    if not isinstance(record, dict):
        return None, ("not used: the snake has none (a markups file, a render output, or a "
                      "snake.json of an older segsnake)")
    differ = [k for k, v in options.items() if not _agrees(record.get(k), v)]
    if differ:
        return None, (f"not used: the record's {', '.join(differ)} "
                      f"{'differs' if len(differ) == 1 else 'differ'} from this run's")
    ref = record["reference"]
    if (ref["kind"], ref["m1"], ref["m2"]) != (model.kind, model.m1, model.m2):
        return None, "not used: the snake was resampled to another size"
    return record, "used"
