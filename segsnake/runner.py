"""One segmentation from files to files: the I/O edge around :func:`segsnake.pipeline.segment_volume`.

``segment_file`` refuses bad outputs (an existing output without ``overwrite``, an output that is an
input, an unwritable directory) *before* any work, loads and validates the image, segments, and
writes ``mask.nii.gz``, ``surface.vtp``, ``snake.json`` and ``qc.png`` (and the surface as STL, OBJ or
PLY when the ``mesh`` option names a file).

All the outputs are first written into a staging directory inside the output directory and moved
into place only when all of them are complete; if a move fails, the ones already moved are taken
back and the earlier outputs restored. So a failed or interrupted run leaves no partial file, never
a mix of old and new outputs, and (when it created the output directory) no empty directory.

``render_file`` writes the same outputs for a saved snake (``snake.json`` or the markups file of
``export-points``) placed on another image's grid, through the same checks and staging; and
``segment_file`` with the ``init`` option starts from a saved snake instead of a new sphere or
cylinder.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from typing import Any, Callable

import numpy as np

from segsnake import __version__, outdir
from segsnake.allocator import trim
from segsnake.errors import ConfigError, InputError, NoBoundaryError, OutputError, \
    SegmentationError
from segsnake.centerline_files import read_centerline, resolve_centerline
from segsnake.markups import resolve_markups
from segsnake.meshes import write_mesh, write_surface
from segsnake.parallel import one_blas_thread
from segsnake.qc import click_index, write_qc_picture
from segsnake.saved_snake import image_from_world, load_snake, load_snake_and_record, \
    read_model, read_prior, world_from_image

__all__ = ["OUTPUT_NAMES", "MAX_SCALE_FRACTION", "output_names", "check_sizes",
           "check_grid_memory", "segment_file", "render_file", "result_warnings"]

OUTPUT_NAMES = ("mask.nii.gz", "surface.vtp", "snake.json", "qc.png")
# A cylinder's tube profile along its centerline (segsnake.profile), written with the others.
PROFILE_NAME = "profile.csv"
# The largest --scale, as a fraction of the image's longest extent in mm: the Gaussian filters then
# stay within a few times the volume (bounded time), and a scale near the whole image is
# already far outside any sensible use (the detector's scale is about a boundary's thickness).
MAX_SCALE_FRACTION = 0.25
#: Peak bytes of the optimizer per squared control point (the snake's dense L2 metric on its
#: parameters, :func:`segsnake.optimize.surface_metric`: the control grid's mass matrix, the
#: metric, its factor and the products' temporaries): measured 4.4 at M1 = M2 = 60 and 4.7 at 80
#: (peak memory above the run's without them), times 8 bytes a double.
METRIC_BYTES_PER_POINT2 = 5 * 8
COORDINATES = ("model control points in mm of scaled index space (i*sx, j*sy, k*sz); surface.vtp "
               "in world coordinates (the image affine)")


def output_names(config) -> tuple[str, ...]:
    """The files a run writes: the four :data:`OUTPUT_NAMES`, the ``mesh`` option's file, and a
    new cylinder's :data:`PROFILE_NAME` (a start from a saved snake adds it once the snake's
    kind is known)."""
    return _names(config.mesh, config.shape == "cylinder" and config.init is None)


def _names(mesh: str | None, profile: bool = False) -> tuple[str, ...]:
    return OUTPUT_NAMES + ((mesh,) if mesh is not None else ()) + \
        ((PROFILE_NAME,) if profile else ())


def _outputs(out_dir: str, names: tuple[str, ...], mesh: str | None) -> dict[str, str]:
    """The summary's ``outputs``: absolute paths by kind (mask, surface, snake, qc, mesh,
    profile)."""
    return {("mesh" if name == mesh else name.split(".")[0]):
            os.path.abspath(os.path.join(out_dir, name)) for name in names}


def _add_profile(out_dir: str, overwrite: bool, names: tuple[str, ...], inputs: list
                 ) -> tuple[str, ...]:
    """``names`` with the profile, checked as the others were before the run (a saved snake
    turned out to be a cylinder)."""
    from segsnake.io import check_not_input

    if PROFILE_NAME in names:
        return names
    check_not_input(os.path.join(out_dir, PROFILE_NAME), *inputs)
    _check_existing(out_dir, overwrite, (PROFILE_NAME,))
    return names + (PROFILE_NAME,)


def _profile(model, volume):
    """The tube profile of a cylinder snake (mm of the volume's scaled index space) in world mm,
    or None for a sphere."""
    if model.kind != "cylinder":
        return None
    from segsnake.profile import tube_profile

    return tube_profile(world_from_image(model, volume.affine, volume.spacing))


def _profile_summary(profile) -> dict[str, Any]:
    """The summary's few numbers of a profile (the whole table is in snake.json and the CSV)."""
    d = profile.equivalent_diameter
    return {"length_mm": round(profile.length_mm, 4),
            "equivalent_diameter_mm": {"min": float(d.min()), "median": float(np.median(d)),
                                       "max": float(d.max())}}


def _existing_ancestor(path: str) -> str:
    """The nearest existing directory at or above ``path`` (what ``makedirs`` would write in)."""
    d = os.path.abspath(path)
    while not os.path.lexists(d):
        parent = os.path.dirname(d)
        if parent == d:
            break
        d = parent
    return d


def _check_out_dir(out_dir: str, overwrite: bool, inputs: list[str | None],
                   names: tuple[str, ...]) -> None:
    """Refuse, before any work, every output problem that can be seen in advance.

    Nothing is created here: a run that fails later (bad input, failed segmentation) leaves no
    empty output directory behind.
    """
    from segsnake.io import check_not_input

    if os.path.lexists(out_dir) and not os.path.isdir(out_dir):
        for given in inputs:
            if given is not None and os.path.lexists(given) and os.path.samefile(given, out_dir):
                raise OutputError(f"{out_dir}: --out is the input file itself; --out takes a "
                                  f"directory for the outputs (a new one is created), e.g. "
                                  f"--out {_suggest_dir(out_dir)}")
        raise OutputError(f"{out_dir}: exists and is a file, not a directory; --out takes a "
                          f"directory for the outputs: give another name")
    for name in names:
        path = os.path.join(out_dir, name)
        check_not_input(path, *inputs)
    _check_existing(out_dir, overwrite, names)
    base = _existing_ancestor(out_dir)
    if not os.path.isdir(base):
        raise OutputError(f"{out_dir}: cannot create the output directory ({base} is not a directory)")
    # os.access sees read-only mounts and permissions (root bypasses the latter; the write itself
    # then still fails cleanly, see _write_outputs).
    if not os.access(base, os.W_OK | os.X_OK):
        what = "output directory is not writable" if base == os.path.abspath(out_dir) else \
            f"cannot create the output directory ({base} is not writable)"
        raise OutputError(f"{out_dir}: {what}")


def _suggest_dir(path: str) -> str:
    """``scan.nii.gz`` -> ``scan-seg``: a directory name next to an input file."""
    base = os.path.basename(path)
    for ext in (".nii.gz", ".nii", ".mhd", ".mha", ".nrrd", ".nhdr"):
        if base.lower().endswith(ext):
            base = base[: -len(ext)]
            break
    return os.path.join(os.path.dirname(path), (base or "out") + "-seg")


def _check_existing(out_dir: str, overwrite: bool, names: tuple[str, ...]) -> None:
    """Refuse outputs that exist already, unless ``overwrite``."""
    if overwrite:
        return
    for name in names:
        path = os.path.join(out_dir, name)
        if os.path.lexists(path):
            raise OutputError(f"{path}: already exists; use --overwrite to replace it")


def check_sizes(config, volume) -> None:
    """Refuse size-like options that do not fit the image (exit 2): ``scale`` larger than
    :data:`MAX_SCALE_FRACTION` of the image's longest extent (the filters' cost grows with it,
    and a detector wider than the image finds nothing), and ``radii``/``radius`` larger than the
    image's longest extent.

    Raises
    ------
    ConfigError
        An option out of its bound; the message names the image, the bound and the extent.
    """
    sp = np.asarray(volume.spacing, dtype=float)
    extent_mm = float(np.max(np.asarray(volume.shape) * sp))
    if config.scale is not None:
        limit = MAX_SCALE_FRACTION * extent_mm
        if config.scale > limit:
            raise ConfigError(f"{volume.path}: --scale {config.scale:g} mm is larger than the image "
                              f"allows ({limit:g} mm, {MAX_SCALE_FRACTION:g} x its longest extent "
                              f"of {extent_mm:g} mm); use --scale {limit:g} or less (about the "
                              f"thickness of the boundary you segment)")
    if config.m1 is not None or config.m2 is not None:
        # (without them coarse to fine stays at the schedule's grids, a few MB)
        m1, m2 = config.m1 or 9, config.m2 or 9
        check_grid_memory(m1, m2, f"{volume.path}: --m1 {m1} --m2 {m2}",
                          "give a smaller M, or none (coarse to fine then chooses it)")
    # radii/radius are voxels, or mm with world: compare with the extent in the same unit.
    extent = extent_mm if config.world else float(np.max(volume.shape))
    unit = "mm" if config.world else "voxels"
    lengths = [("--radii", r) for r in (config.radii or [])]
    if config.radius is not None:
        lengths.append(("--radius", config.radius))
    for flag, value in lengths:
        if value > extent:
            raise ConfigError(f"{volume.path}: {flag} {value:g} {unit} is larger than the image "
                              f"(longest extent {extent:g} {unit}); give a size inside the image")


def check_grid_memory(m1: int, m2: int, what: str, advice: str) -> None:
    """Refuse (exit 2) a control grid whose optimizer would need more memory than the process
    may use (:data:`METRIC_BYTES_PER_POINT2` per squared control point); ``what`` starts the
    message (the file and what asked for the grid), ``advice`` ends it."""
    from segsnake.io import beyond_memory, fmt_bytes

    need = METRIC_BYTES_PER_POINT2 * (m1 * (m2 + 3)) ** 2
    beyond = beyond_memory(need)
    if beyond is not None:
        raise ConfigError(f"{what} needs about {fmt_bytes(need)} of memory for the snake's "
                          f"{m1 * (m2 + 3)} control points, {beyond}; {advice}")


def _with_image_name(exc: Exception, image_path: str) -> None:
    """Prefix a core error's message with the image it is about (the core does not know files).

    The exception is changed in place and re-raised by the caller with a bare ``raise``, so its
    type (the exit code) and its traceback (``--debug``) stay those of the core.
    """
    msg = str(exc)
    if not msg.startswith(image_path):
        exc.args = (f"{image_path}: {msg}",)


# (BLAS in one thread from the start: a saved snake resampled to another size before
# segment_volume runs changed with the number of BLAS threads too, by 2.5e-12 mm)
@one_blas_thread
def segment_file(image_path: str, out_dir: str, config, *, truth_path: str | None = None,
                 truth_label: int | None = None, truth_label_option: str = "a truth label",
                 overwrite: bool = False, wait: bool = False,
                 progress: Callable[[str, float], None] | None = None) -> dict[str, Any]:
    """Segment ``image_path`` with ``config`` and write the outputs into ``out_dir``.

    The output directory is locked before any work (:func:`segsnake.outdir.locked`): what a
    killed run left there is completed or removed first, and a second run on the same directory
    is refused at once (or waits, ``wait``).

    Parameters
    ----------
    image_path : str
        NIfTI (or any SimpleITK-readable) volume, or a directory holding one DICOM series.
    out_dir : str
        Output directory (created if missing, only when the outputs are written).
    config : SegmentConfig
        The ``segment`` options.
    truth_path : str, optional
        A truth mask on the image's grid: Dice, Jaccard and surface distances are added.
    truth_label : int, optional
        The truth is a label map: compare with its voxels equal to ``truth_label`` only (default:
        every non-zero voxel, with a warning when the truth holds more than two values).
    truth_label_option : str
        How the caller's user gives ``truth_label`` (a flag, a YAML key), named by that warning.
    overwrite : bool
        Replace existing outputs.
    wait : bool
        Wait for another run holding the output directory instead of refusing (exit 5).
    progress : callable(stage, fraction), optional

    Returns
    -------
    dict
        JSON-able summary (also stored in ``snake.json`` under ``summary``).

    Raises
    ------
    InputError
        The image or truth cannot be read or is not usable (exit 3).
    ConfigError
        Options that do not fit this image, e.g. an initialization outside it (exit 2).
    SegmentationError
        No edges, or the snake collapsed, escaped or diverged (exit 4); nothing is written.
    OutputError
        Existing outputs without ``overwrite``, an output that is an input, an unwritable
        directory or a failed write (exit 5); earlier outputs are left as they were.
    """
    t_start = time.perf_counter()
    image_path = os.fspath(image_path)
    out_dir = os.fspath(out_dir)
    truth_path = None if truth_path is None else os.fspath(truth_path)
    names = output_names(config)
    _check_out_dir(out_dir, overwrite, _inputs(image_path, truth_path, config), names)
    if config.atlas is not None and os.path.isdir(config.atlas) and \
            _within(os.path.abspath(out_dir), os.path.realpath(config.atlas)):
        # (its mask.nii.gz would become a label set without names, and the atlas unreadable)
        raise OutputError(f"{out_dir}: --out lies in the atlas folder {config.atlas}; give "
                          f"another directory")
    with outdir.locked(out_dir, wait=wait):
        _check_existing(out_dir, overwrite, names)  # again: a run that held the lock wrote them?
        return _segment_locked(image_path, out_dir, config, truth_path, truth_label,
                               truth_label_option, overwrite, progress, names, t_start)


def _within(path: str, folder: str) -> bool:
    """Is ``path`` (absolute) ``folder`` or inside it, links resolved?"""
    path = os.path.realpath(path)
    return path == folder or path.startswith(folder.rstrip(os.sep) + os.sep)


def _inputs(image_path, truth_path, config) -> list[str | None]:
    """The files a ``segment`` run reads (no output may be one of them)."""
    centerline = config.centerline if isinstance(config.centerline, str) else None
    return [image_path, truth_path, config.prior, config.init, centerline]


def _segment_locked(image_path, out_dir, config, truth_path, truth_label, truth_label_option,
                    overwrite, progress, names, t_start) -> dict[str, Any]:
    """:func:`segment_file` once the output directory is locked."""
    from segsnake.io import load_volume
    from segsnake.measure import closed_area
    from segsnake.pipeline import segment_volume

    t0 = time.perf_counter()
    # A bad --init, --centerline or --atlas is refused before the image is read.
    saved, saved_record = load_snake_and_record(config.init) if config.init is not None \
        else (None, None)
    atlas = _read_atlas(config)
    if saved is not None and saved.kind == "cylinder":
        names = _add_profile(out_dir, overwrite, names, _inputs(image_path, truth_path, config))
    centerline_file = config.centerline if isinstance(config.centerline, str) else None
    centerline = read_centerline(centerline_file) if centerline_file is not None else None
    volume = load_volume(image_path, volume_index=config.volume, nan=config.nan,
                         bytes_per_voxel=_bytes_per_voxel(config))
    check_sizes(config, volume)
    truth = None
    truth_warnings: list[str] = []
    if truth_path is not None:
        truth, truth_warnings = _load_truth(truth_path, volume, truth_label, truth_label_option)
    load_s = time.perf_counter() - t0
    # Markups files given as positions become numbers here: converting them needs the affine.
    config = resolve_markups(config, volume.world_to_index)
    config = resolve_centerline(config, centerline, volume.world_to_index, volume.spacing,
                                volume.shape)
    init_model = init_record = None
    if saved is not None:
        init_model, config = _start_from(saved, config, volume)
        init_record = saved_record

    extra = None
    atlas_record = None
    atlas_s = None
    weight, space = config.prior_used()
    if atlas is not None:
        t0 = time.perf_counter()
        init_model, atlas_record = _atlas_start(config, volume, atlas)
        atlas_s = time.perf_counter() - t0
        config = config.replace(m1=init_model.m1, m2=init_model.m2)
        if weight > 0:  # (the atlas' shape is the prior too)
            extra = _prior_energy(config, init_model, source=f"{config.atlas} (atlas)")
    if config.prior is not None and weight > 0:
        reference = read_prior(config.prior, volume.affine, volume.spacing)
        extra = _prior_energy(config, reference)
        config = _sized_like_prior(config, reference)
    try:
        result = segment_volume(volume.data, volume.spacing, config,
                                index_from_world=volume.world_to_index, progress=progress,
                                extra_energy=extra, init_model=init_model,
                                init_record=init_record)
    except NoBoundaryError as exc:
        if atlas_record is None:
            _with_image_name(exc, image_path)
            raise
        # The image does not separate the atlas' structure from its surroundings (a nucleus
        # between a darker and a brighter neighbour): the registered atlas shape is the result,
        # and says so.
        result = _unrefined(init_model, volume, exc)
    except (ConfigError, SegmentationError) as exc:
        _with_image_name(exc, image_path)
        raise
    except MemoryError:
        from segsnake.io import fmt_bytes, memory_limit_bytes

        limit, source = memory_limit_bytes()
        need = float(np.prod(volume.shape)) * _bytes_per_voxel(config)
        raise InputError(f"{image_path}: out of memory while segmenting its "
                         f"{'x'.join(map(str, volume.shape))} voxels (estimate "
                         f"{fmt_bytes(need)}, {source or 'the limit'} {fmt_bytes(limit)}); "
                         f"crop the image to the structure or resample it to larger voxels "
                         f"first") from None
    timings = {"load_s": load_s, **({"atlas_s": atlas_s} if atlas_s is not None else {}),
               **result.timings}
    summary: dict[str, Any] = {
        "image": os.path.abspath(image_path),
        "shape": list(volume.shape),
        "spacing_mm": list(volume.spacing),
        "volume_mm3": float(result.model.volume()),
        "area_mm2": closed_area(result.model),
        "mask_voxels": int(result.mask.sum()),
        "energy": result.energy,
        "iterations": result.iterations,
        "polarity": result.polarity,
        "warnings": list(volume.warnings) + truth_warnings + _atlas_warnings(atlas_record)
        + result_warnings(result),
    }
    quality = {k: result.settings[k] for k in ("separation", "class_separation",
                                                "boundary_fraction", "step_beyond",
                                                "click_depth")
               if k in result.settings}
    if quality:
        summary["quality"] = quality
    if truth is not None:
        from segsnake.metrics import evaluate_masks  # (here: only a run with a truth uses it)

        summary["truth_label"] = truth_label
        metrics = evaluate_masks(result.mask, truth, volume.spacing)
        summary.update({k: (float(v) if np.isfinite(v) else None) for k, v in metrics.items()})
    t0 = time.perf_counter()
    profile = _profile(result.model, volume)
    if profile is not None:
        summary["profile"] = _profile_summary(profile)
    settings = {**config.to_dict(), **result.settings}
    if extra is not None:  # (the prior's weight and space as used, given or by its kind)
        settings["prior_weight"], settings["prior_space"] = weight, space
    if atlas_record is not None:
        settings["atlas_start"] = atlas_record
    if centerline_file is not None:
        settings["centerline_file"] = os.path.abspath(centerline_file)
    snake = {
        "format": "segsnake-result",
        "version": __version__,
        "summary": summary,
        "model": result.model.to_dict(),
        "initial_model": result.init_model.to_dict(),
        "coordinates": COORDINATES,
        "affine": np.asarray(volume.affine).tolist(),
        "settings": settings,
        "energy_history": result.history,
        "timings": timings,
    }
    if profile is not None:
        snake["profile"] = profile.to_dict()
    # (the writers' libraries load into the pages the segmentation's temporaries left free)
    trim()
    _write_outputs(out_dir, volume, result.mask, result.model, snake, overwrite, names,
                   init_model=result.init_model, mesh=config.mesh, truth=truth,
                   click=click_index(config, volume), profile=profile)
    timings["write_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_start
    summary["timings"] = timings
    summary["outputs"] = _outputs(out_dir, names, config.mesh)
    return summary


def _start_from(saved, config, volume):
    """The ``init`` option's saved snake (world mm) on this image, at the requested size.

    Returns the initial model (mm of this image's scaled index space; resampled by the exact L2
    projection, :func:`segsnake.resample.resample`, when ``m1``/``m2`` ask for another size) and
    the config with ``shape``, ``m1`` and ``m2`` those of the model, as ``snake.json`` records them.
    """
    from segsnake.resample import resample

    model = image_from_world(saved, volume.affine, volume.spacing)
    m1, m2 = config.m1 or model.m1, config.m2 or model.m2
    if config.m1 is None or config.m2 is None:  # (both given: check_sizes checked them)
        check_grid_memory(m1, m2, f"{config.init}: the saved snake's {m1} x {m2} control grid",
                          "give --m1 and --m2 to resample it to a smaller grid")
    if (m1, m2) != (model.m1, model.m2):
        model = resample(model, m1, m2)
    sp = np.asarray(volume.spacing)
    centre = model.control_points().reshape(-1, 3).mean(axis=0) / sp
    if np.any(centre < -0.5) or np.any(centre > np.asarray(volume.shape) - 0.5):
        raise ConfigError(f"{config.init}: the saved snake lies outside {volume.path} (its centre "
                          f"at voxel {[round(float(x), 1) for x in centre]}, shape "
                          f"{tuple(volume.shape)}): a snake of another image?")
    return model, config.replace(shape=model.kind, m1=m1, m2=m2)


def render_file(snake_path: str, image_path: str, out_dir: str, *, mesh: str | None = None,
                overwrite: bool = False, wait: bool = False) -> dict[str, Any]:
    """Rebuild the outputs of a saved snake on an image's grid (``segsnake render``).

    Parameters
    ----------
    snake_path : str
        A ``snake.json`` (``segment`` or ``render`` output) or a markups file written by
        ``export-points`` (perhaps with points moved in 3D Slicer).
    image_path : str
        The image whose grid the mask is written on (``--like``); its affine places the snake's
        world coordinates. Its voxels are only drawn in ``qc.png``.
    out_dir : str
        Output directory: ``mask.nii.gz``, ``surface.vtp``, ``snake.json`` (the snake on this grid,
        as ``segment`` writes it, without the run's history) and ``qc.png``, staged and committed
        as ``segment`` does.
    mesh : str, optional
        Also the surface as this STL/OBJ/PLY file name.
    overwrite : bool
        Replace existing outputs.
    wait : bool
        Wait for another run holding the output directory instead of refusing (exit 5).

    Returns
    -------
    dict
        JSON-able summary (also in ``snake.json``).

    Raises
    ------
    InputError
        An unreadable snake or image, or a snake that encloses no voxel centre of the image
        (exit 3).
    OutputError
        As for :func:`segment_file` (exit 5).
    """
    t_start = time.perf_counter()
    snake_path, image_path, out_dir = (os.fspath(p) for p in (snake_path, image_path, out_dir))
    names = _names(mesh)
    _check_out_dir(out_dir, overwrite, [snake_path, image_path], names)
    with outdir.locked(out_dir, wait=wait):
        _check_existing(out_dir, overwrite, names)
        return _render_locked(snake_path, image_path, out_dir, mesh, overwrite, names, t_start)


def _render_locked(snake_path, image_path, out_dir, mesh, overwrite, names, t_start
                   ) -> dict[str, Any]:
    """:func:`render_file` once the output directory is locked."""
    from segsnake.io import load_volume
    from segsnake.rasterize import rasterize

    world = load_snake(snake_path)
    # Only the grid is needed: NaN voxels do not stop a render (they are reported).
    volume = load_volume(image_path, nan="fill", one_of_several=False)
    model = image_from_world(world, volume.affine, volume.spacing)
    mask = rasterize(model, volume.shape, volume.spacing)
    if not mask.any():
        raise InputError(f"{snake_path}: the snake encloses no voxel centre of {image_path} "
                         f"(a snake of another image?)")
    profile = _profile(model, volume)
    if profile is not None:
        names = _add_profile(out_dir, overwrite, names, [snake_path, image_path])
    summary: dict[str, Any] = {
        "image": os.path.abspath(image_path),
        "snake": os.path.abspath(snake_path),
        "shape": list(volume.shape),
        "spacing_mm": list(volume.spacing),
        "volume_mm3": float(model.volume()),
        "mask_voxels": int(mask.sum()),
        "warnings": list(volume.warnings),
    }
    if profile is not None:
        summary["profile"] = _profile_summary(profile)
    timings = {"render_s": time.perf_counter() - t_start}
    snake = {"format": "segsnake-result", "version": __version__, "summary": summary,
             "model": model.to_dict(), "rendered_from": os.path.abspath(snake_path),
             "coordinates": COORDINATES, "affine": np.asarray(volume.affine).tolist(),
             "timings": timings}
    if profile is not None:
        snake["profile"] = profile.to_dict()
    _write_outputs(out_dir, volume, mask, model, snake, overwrite, names, mesh=mesh,
                   profile=profile)
    timings["total_s"] = time.perf_counter() - t_start
    summary["timings"] = timings
    summary["outputs"] = _outputs(out_dir, names, mesh)
    return summary


def result_warnings(result) -> list[str]:
    """What a segmentation's own record says may be wrong with it: a stage whose quadrature was
    not resolved (not one that left its window, nor a finer grid that coarse to fine refused:
    neither surface is the result), and (the region energy) an inside and outside that overlap
    in intensity (:func:`segsnake.region.class_separation` below the region parameters'
    ``min_class_separation``), and a result that grew away from its click
    (:func:`segsnake.region.click_depth` below ``min_click_depth``), and one that stopped short
    of a stronger step just beyond it (:func:`segsnake.region.step_beyond` above
    ``max_step_beyond``)."""
    out = [f"stage {i + 1} ({h['stage']}) ended with a quadrature that does not agree with twice "
           f"its order (iteration or round cap reached): the surface may be less accurate"
           for i, h in enumerate(result.history)
           if not h.get("quadrature_resolved", True) and not h.get("left") and h.get("kept", True)]
    # (a quality score beyond its region parameter's bound, below a least or above a most, and
    # what that says of the result; the text may name any region parameter)
    scores = {
        ("class_separation", "min_class_separation", -1):
            "the intensities inside the result and just outside it overlap (their medians differ "
            "by {value:.2f} of their spread, below {bound:g}): its boundary is weak or it leaked "
            "into its surroundings; check it (a shape prior may hold it)",
        ("click_depth", "min_click_depth", -1):
            "the result grew away from its start's centre (the click, or the centre estimated "
            "without one): that point lies at {value:.2f} of the result's greatest depth, below "
            "{bound:g}, near its surface; it may have run on into a neighbouring structure of "
            "like intensity; check it",
        ("step_beyond", "max_step_beyond", 1):
            "the result stopped short of a stronger boundary: on half its surface a step "
            "{value:.1f} times the one it sits on lies within {step_reach_mm:g} mm beyond it "
            "(above {bound:g}); the object may reach farther (an inside brighter in its middle "
            "than at its rim); check it, or give --radii that reach its rim, or try --energy edge"}
    params = result.settings.get("region_params", {})
    for (key, param, side), text in scores.items():
        value, bound = result.settings.get(key), params.get(param)
        if value is not None and bound is not None and side * (value - bound) > 0:
            out.append(text.format(**params, value=value, bound=bound))
    if "unrefined" in result.settings:
        out.append(result.settings["unrefined"])
    return out


def _load_truth(path: str, volume, label: int | None, truth_label_option: str
                ) -> tuple[np.ndarray, list[str]]:
    """The truth's foreground on the image's grid (one label of a label map) and its warnings."""
    from segsnake.io import load_volume
    from segsnake.labels import truth_mask

    truth = load_volume(path, bytes_per_voxel=None, one_of_several=False)
    if truth.shape != volume.shape or not np.allclose(truth.affine, volume.affine, atol=1e-4):
        raise InputError(f"{path}: truth mask is not on the grid of {volume.path} "
                         f"(shape {truth.shape} vs {volume.shape} or a different affine)")
    return truth_mask(truth.data, label, path, truth_label_option)


def _bytes_per_voxel(config) -> float:
    """The up-front memory estimate per voxel of the run ``config`` asks for."""
    from segsnake.io import PIPELINE_BYTES_PER_VOXEL, REGION_BYTES_PER_VOXEL
    from segsnake.pipeline import region_energy

    return REGION_BYTES_PER_VOXEL if region_energy(config) else PIPELINE_BYTES_PER_VOXEL


def _sized_like_prior(config, reference):
    """A snake given neither ``m1`` nor ``m2`` takes the size of its prior ``reference``: the
    prior is defined on that spline space (so coarse to fine, which would leave it, does not
    run); :func:`_prior_energy` checked the rest."""
    if config.m1 is not None or config.m2 is not None:
        return config
    return config.replace(m1=reference.m1, m2=reference.m2)


def _read_atlas(config):
    """``--atlas``'s folder, read (:func:`segsnake.atlas.read_atlas`) and its ``--structure``
    checked (a damaged label set refused before the image is read), or None without one."""
    if config.atlas is None:
        return None
    from segsnake.atlas import find_structure, read_atlas

    atlas = read_atlas(config.atlas)
    if config.structure is not None:  # (its name, and its label set's voxels, read now)
        find_structure(atlas, config.structure).label_set.labels
    return atlas


def _atlas_start(config, volume, atlas):
    """``--atlas``: the atlas' structure on the image, fitted (:func:`segsnake.atlas.atlas_start`),
    as the initial model (mm of the image's scaled index space), and its record."""
    from segsnake.atlas import atlas_start
    from segsnake.registration import RegistrationError, grid_problem

    problem = grid_problem(volume.affine)
    if problem is not None:
        raise InputError(f"{volume.path}: {problem}")
    click = None
    if config.center is not None:
        click = np.asarray(config.center, dtype=np.float64)
        if not config.world:
            click = volume.index_to_world(click)
    try:
        return atlas_start(volume.data, volume.affine, volume.spacing, atlas, config.structure,
                           click, m1=config.m1, m2=config.m2)
    except RegistrationError as exc:
        raise SegmentationError(f"{volume.path}: no map to the atlas' template "
                                f"({config.atlas}): {exc}") from None


#: The share of an atlas structure's voxels outside its largest piece from which a run warns
#: that the snake (one closed surface) left them out: below it they move a Dice by less than
#: 0.01 (the stray voxels a trilinear placement leaves at a thin part, as the Colin27 right
#: thalamus' two voxels, 0.01 %).
PIECES_WARNING_FRACTION = 0.01


def _atlas_warnings(record) -> list[str]:
    """What the atlas start says may be wrong: a structure that landed in several pieces, of
    which the snake (one closed surface) took the largest."""
    if record is None or record["dropped_fraction"] < PIECES_WARNING_FRACTION:
        return []
    return [f"the atlas' {record['structure']} lands on the image in {record['pieces']} pieces; "
            f"the snake, one closed surface, follows the largest ({record['dropped_fraction']:.0%} "
            f"of its voxels lie in the others): name one structure if it holds several"]


def _unrefined(model, volume, reason: Exception):
    """The atlas' structure as registered, as a result: what ``--atlas`` returns where the image
    holds no boundary for the segmentation to refine it on (:class:`NoBoundaryError`)."""
    from segsnake.pipeline import SegmentResult
    from segsnake.rasterize import rasterize

    why = str(reason).split(";")[0]
    warning = (f"the image does not separate the atlas' structure from its surroundings ({why}): "
               f"the result is the atlas' structure as registered, not refined on the image; "
               f"check it")
    # (no energy was minimized: None, which JSON writes as null)
    return SegmentResult(model, rasterize(model, volume.shape, volume.spacing), None, 0,
                         [], {}, "none", model, {"unrefined": warning})


def _prior_energy(config, reference=None, source=None):
    """The ``--prior`` energy for :func:`segment_volume`'s ``extra_energy`` (a factory per stage).

    REF is any saved model: ``segsnake shape`` output, a previous ``snake.json`` or a
    ``segsnake shape-model`` MODEL.json (its reference is stored under ``model``). The weight is
    relative (:func:`segsnake.priors.relative_prior_weight`): an RMS deviation from the
    reference's shape space of 10 % of the snake's radius costs ``--prior-weight`` times the
    image energy. ``reference``: the prior file's model in the image's scaled index space, as
    the run reads it (:func:`segsnake.saved_snake.read_prior`); without it, the file's model as
    stored (:func:`segsnake.saved_snake.read_model`). ``source``: the prior's name in messages
    (default the prior file). Its weight and space are :meth:`SegmentConfig.prior_used`'s.
    """
    from segsnake.priors import relative_prior_weight

    path = source or config.prior
    weight, space = config.prior_used()
    if reference is None:
        reference = read_model(path, "prior file")

    def mismatch(kind, m1, m2) -> InputError:
        sizes = ", ".join(f"{n}={v}" for n, v in (("M1", m1), ("M2", m2)) if v is not None)
        snake = f"a {kind}" + (f" with {sizes}" if sizes else "")
        return InputError(f"{path}: the prior is a {reference.kind} with M1={reference.m1}, "
                          f"M2={reference.m2} but the snake is {snake}; segment with --shape "
                          f"{reference.kind} --m1 {reference.m1} --m2 {reference.m2} or use a "
                          f"matching reference")

    # Refuse what the options already contradict before any image work; the sizes the pipeline
    # picks by default are checked when the snake exists (first stage).
    if reference.kind != config.shape or \
            (config.m1 is not None and config.m1 != reference.m1) or \
            (config.m2 is not None and config.m2 != reference.m2):
        raise mismatch(config.shape, config.m1, config.m2)

    shape_model = None
    if config.prior_modes:
        from segsnake.shapes import load_shape_model

        try:
            shape_model = load_shape_model(path)
        except (OSError, ValueError, KeyError, TypeError, json.JSONDecodeError) as exc:
            msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise InputError(f"{path}: --prior-modes needs a shape model from segsnake "
                             f"shape-model ({msg})") from None
    try:  # options that contradict the prior file: refused before any image work
        from segsnake.model_prior import build_prior

        build_prior(reference, reference, 1.0, space, shape_model, config.prior_modes)
    except ValueError as exc:
        raise InputError(f"{path}: {exc}") from None

    def make(model):
        from segsnake.model_prior import build_prior

        if (reference.kind, reference.m1, reference.m2) != (model.kind, model.m1, model.m2):
            raise mismatch(model.kind, model.m1, model.m2)
        try:
            return build_prior(model, reference, relative_prior_weight(model, weight),
                               space, shape_model, config.prior_modes)
        except ValueError as exc:
            raise InputError(f"{path}: {exc}") from None

    return make


def _write_outputs(out_dir: str, volume, mask, model, snake: dict[str, Any], overwrite: bool,
                   names: tuple[str, ...], *, init_model=None, mesh: str | None = None,
                   truth=None, click=None, profile=None) -> None:
    """Write every output into a staging directory, then move them into place together.

    ``mask`` and ``model`` (mm of the volume's scaled index space) give ``mask.nii.gz``,
    ``surface.vtp`` and ``mesh``; ``snake`` is the content of ``snake.json``; ``qc.png`` draws
    the model, ``init_model`` (dashed), ``truth``, ``click`` and a cylinder's ``profile``
    (:class:`segsnake.profile.TubeProfile`, also written as ``profile.csv``).

    The caller holds the directory's lock (:func:`segsnake.outdir.locked`). Every failure (disk
    full, read-only directory, Ctrl-C) leaves the output directory as it was: the staging
    directory is removed, outputs already moved are taken back and earlier outputs restored
    (:func:`segsnake.outdir.commit`; a kill is completed by the next run's recovery).
    """
    from segsnake.io import save_mask

    stage = None
    current = out_dir
    try:
        stage = outdir.stage_dir(out_dir)
        try:
            current = os.path.join(out_dir, "mask.nii.gz")
            try:
                save_mask(mask, volume, os.path.join(stage, "mask.nii.gz"))
            except OutputError as exc:  # name the real output, not the staging file
                reason = str(exc).split(": ", 1)[-1]
                raise OutputError(f"{current}: {reason}") from None
            # (the picture before the meshes: matplotlib's and VTK's libraries are not both
            # loaded while the picture's arrays are alive, issue 18)
            current = os.path.join(out_dir, "qc.png")
            write_qc_picture(os.path.join(stage, "qc.png"), volume.data, volume.spacing, mask,
                             model, init_model, affine=volume.affine, truth=truth, click=click,
                             profile=profile)
            current = os.path.join(out_dir, "surface.vtp")
            write_surface(os.path.join(stage, "surface.vtp"), model, volume)
            if mesh is not None:
                current = os.path.join(out_dir, mesh)
                write_mesh(os.path.join(stage, mesh), model, volume)
            current = os.path.join(out_dir, "snake.json")
            text = json.dumps(snake, indent=1, default=_json_default)
            with open(os.path.join(stage, "snake.json"), "w", encoding="utf-8") as fh:
                fh.write(text)
            if profile is not None:
                current = os.path.join(out_dir, PROFILE_NAME)
                _write_profile(os.path.join(stage, PROFILE_NAME), profile)
            current = out_dir
            # A new set without a profile (a sphere) replaces an earlier cylinder's profile too,
            # and one without the earlier set's mesh (or with another) its mesh.
            outdir.commit(stage, out_dir, overwrite, names,
                          remove=(PROFILE_NAME, *_earlier_mesh(out_dir, mesh)))
        except OSError as exc:
            raise OutputError(f"{current}: cannot write ({exc.strerror or exc})") from None
    finally:
        if stage is not None:
            shutil.rmtree(stage, ignore_errors=True)


def _earlier_mesh(out_dir: str, mesh: str | None) -> tuple[str, ...]:
    """The mesh file of the set already in ``out_dir`` (its ``snake.json``'s ``settings.mesh``),
    unless it is ``mesh``, the new set's: an output of the set the new one replaces."""
    from segsnake.meshes import mesh_suffix

    try:
        with open(os.path.join(out_dir, "snake.json"), encoding="utf-8") as fh:
            earlier = json.load(fh).get("settings", {}).get("mesh")
    except (OSError, ValueError, AttributeError):
        return ()
    if not isinstance(earlier, str) or earlier == mesh or os.path.basename(earlier) != earlier \
            or mesh_suffix(earlier) is None:
        return ()
    return (earlier,)


def _write_profile(path: str, profile) -> None:
    """``profile.csv``: a header (:data:`segsnake.profile.PROFILE_COLUMNS`), one row per sample
    (mm, mm^2; 4 decimals)."""
    from segsnake.profile import PROFILE_COLUMNS

    with open(path, "w", encoding="utf-8") as fh:
        fh.write(",".join(PROFILE_COLUMNS) + "\n")
        for row in profile.rows():
            fh.write(",".join(f"{x:.4f}" for x in row) + "\n")


def _json_default(obj: Any) -> Any:
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
