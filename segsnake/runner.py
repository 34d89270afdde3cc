"""One segmentation from files to files: the I/O edge around :func:`segsnake.pipeline.segment_volume`.

``segment_file`` loads and validates the image, refuses outputs that exist (without
``overwrite``) *before* any work, segments, and writes ``mask.nii.gz``, ``surface.vtp``,
``snake.json`` and ``qc.png``. Outputs are first written into a staging directory inside the
output directory and moved into place only when all of them are complete, so a failed run
leaves no partial file and earlier outputs untouched.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from typing import Any, Callable

import numpy as np

from segsnake import __version__
from segsnake.errors import InputError, OutputError

__all__ = ["OUTPUT_NAMES", "segment_file", "write_qc_picture"]

OUTPUT_NAMES = ("mask.nii.gz", "surface.vtp", "snake.json", "qc.png")


def _prepare_out_dir(out_dir: str, overwrite: bool, inputs: list[str | None]) -> None:
    from segsnake.io import check_not_input

    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise OutputError(f"{out_dir}: exists and is not a directory")
    for name in OUTPUT_NAMES:
        path = os.path.join(out_dir, name)
        check_not_input(path, *inputs)
        if os.path.lexists(path) and not overwrite:
            raise OutputError(f"{path}: already exists; use --overwrite to replace it")
    try:
        os.makedirs(out_dir, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{out_dir}: cannot create the output directory ({exc.strerror})") from None
    if not os.access(out_dir, os.W_OK | os.X_OK):
        raise OutputError(f"{out_dir}: output directory is not writable")


def segment_file(image_path: str, out_dir: str, config, *, truth_path: str | None = None,
                 overwrite: bool = False,
                 progress: Callable[[str, float], None] | None = None) -> dict[str, Any]:
    """Segment ``image_path`` with ``config`` and write the outputs into ``out_dir``.

    Parameters
    ----------
    image_path : str
        NIfTI (or any SimpleITK-readable) volume.
    out_dir : str
        Output directory (created if missing).
    config : SegmentConfig
        The ``segment`` options.
    truth_path : str, optional
        A truth mask on the image's grid: Dice, Jaccard and surface distances are added.
    overwrite : bool
        Replace existing outputs.
    progress : callable(stage, fraction), optional

    Returns
    -------
    dict
        JSON-able summary (also stored in ``snake.json`` under ``summary``).
    """
    from segsnake.io import check_memory, load_volume  # noqa: F401 (check_memory via load_volume)
    from segsnake.metrics import evaluate_masks
    from segsnake.pipeline import segment_volume

    t_start = time.perf_counter()
    image_path = os.fspath(image_path)
    out_dir = os.fspath(out_dir)
    _prepare_out_dir(out_dir, overwrite, [image_path, truth_path, config.prior])
    t0 = time.perf_counter()
    volume = load_volume(image_path, volume_index=config.volume, nan=config.nan)
    truth = None
    if truth_path is not None:
        truth = _load_truth(truth_path, volume)
    load_s = time.perf_counter() - t0

    extra = None
    if config.prior is not None and config.prior_weight > 0:
        extra = _prior_energy(config)
    result = segment_volume(volume.data, volume.spacing, config,
                            index_from_world=volume.world_to_index, progress=progress,
                            extra_energy=extra)
    timings = {"load_s": load_s, **result.timings}
    summary: dict[str, Any] = {
        "image": os.path.abspath(image_path),
        "shape": list(volume.shape),
        "spacing_mm": list(volume.spacing),
        "volume_mm3": float(result.model.volume()),
        "mask_voxels": int(result.mask.sum()),
        "energy": result.energy,
        "iterations": result.iterations,
        "polarity": result.polarity,
        "warnings": list(volume.warnings),
    }
    if truth is not None:
        metrics = evaluate_masks(result.mask, truth, volume.spacing)
        summary.update({k: (float(v) if np.isfinite(v) else None) for k, v in metrics.items()})
    t0 = time.perf_counter()
    _write_outputs(out_dir, volume, result, config, summary, timings, overwrite)
    timings["write_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_start
    summary["timings"] = timings
    summary["outputs"] = {name.split(".")[0]: os.path.abspath(os.path.join(out_dir, name))
                          for name in OUTPUT_NAMES}
    return summary


def _load_truth(path: str, volume) -> np.ndarray:
    from segsnake.io import load_volume

    truth = load_volume(path, bytes_per_voxel=None)
    if truth.shape != volume.shape or not np.allclose(truth.affine, volume.affine, atol=1e-4):
        raise InputError(f"{path}: truth mask is not on the grid of {volume.path} "
                         f"(shape {truth.shape} vs {volume.shape} or a different affine)")
    return truth.data > 0.5


def _prior_energy(config):
    from segsnake.priors import AffinePrior
    from segsnake.surfaces import load_model

    try:
        reference = load_model(config.prior)
    except (OSError, ValueError, KeyError, json.JSONDecodeError) as exc:
        raise InputError(f"{config.prior}: not a readable segsnake model ({exc})") from None

    def make(model):
        if (reference.kind, reference.m1, reference.m2) != (model.kind, model.m1, model.m2):
            raise InputError(f"{config.prior}: prior is a {reference.kind} with M1={reference.m1}, "
                             f"M2={reference.m2}; the snake is a {model.kind} with M1={model.m1}, "
                             f"M2={model.m2}")
        return AffinePrior(model, reference, weight=config.prior_weight, space=config.prior_space)

    return make


def _write_outputs(out_dir, volume, result, config, summary, timings, overwrite) -> None:
    """Write every output into a staging directory, then move them into place together."""
    from segsnake.io import save_mask
    from segsnake.rasterize import mesh_for_mask

    stage = tempfile.mkdtemp(prefix=".segsnake-", dir=out_dir)
    try:
        save_mask(result.mask, volume, os.path.join(stage, "mask.nii.gz"))
        mesh = mesh_for_mask(result.model, volume.spacing)
        index = np.asarray(mesh.points) / np.asarray(volume.spacing)
        mesh.points = volume.index_to_world(index)
        mesh.save(os.path.join(stage, "surface.vtp"))
        snake = {
            "format": "segsnake-result",
            "version": __version__,
            "summary": summary,
            "model": result.model.to_dict(),
            "initial_model": result.init_model.to_dict(),
            "coordinates": "model control points in mm of scaled index space (i*sx, j*sy, k*sz); "
                           "surface.vtp in world coordinates (the image affine)",
            "affine": np.asarray(volume.affine).tolist(),
            "settings": {**config.to_dict(), **result.settings},
            "energy_history": result.history,
            "timings": timings,
        }
        with open(os.path.join(stage, "snake.json"), "w", encoding="utf-8") as fh:
            json.dump(snake, fh, indent=1, default=_json_default)
        write_qc_picture(os.path.join(stage, "qc.png"), volume.data, volume.spacing, result.mask,
                         result.model, result.init_model)
        for name in OUTPUT_NAMES:
            final = os.path.join(out_dir, name)
            if os.path.lexists(final) and not overwrite:
                raise OutputError(f"{final}: already exists; use --overwrite to replace it")
        for name in OUTPUT_NAMES:
            os.replace(os.path.join(stage, name), os.path.join(out_dir, name))
    except OSError as exc:
        raise OutputError(f"{out_dir}: writing the outputs failed ({exc.strerror or exc})") from None
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def _json_default(obj: Any) -> Any:
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def write_qc_picture(path: str, image: np.ndarray, spacing, mask: np.ndarray, model,
                     init_model=None) -> None:
    """Three orthogonal slices through the object with the contour, and a 3D view.

    Slices pass through the mask's centroid and are drawn with the physical aspect ratio
    (anisotropic voxels are not stretched); the final contour is red, the initial one dashed.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from segsnake.rasterize import rasterize

    sp = np.asarray(spacing, dtype=float)
    idx = np.argwhere(mask)
    centre = np.round(idx.mean(axis=0)).astype(int) if len(idx) else np.array(mask.shape) // 2
    init_mask = rasterize(init_model, mask.shape, spacing) if init_model is not None else None
    lo, hi = np.percentile(image, [1, 99.5])
    fig = plt.figure(figsize=(13, 3.6), dpi=90)
    names = ("i (x)", "j (y)", "k (z)")
    for panel, axis in enumerate((2, 1, 0)):
        ax = fig.add_subplot(1, 4, panel + 1)
        sl = [slice(None)] * 3
        sl[axis] = int(centre[axis])
        other = [d for d in range(3) if d != axis]
        extent = (0, mask.shape[other[0]] * sp[other[0]], 0, mask.shape[other[1]] * sp[other[1]])
        ax.imshow(image[tuple(sl)].T, cmap="gray", origin="lower", vmin=lo, vmax=hi, extent=extent,
                  interpolation="nearest")
        xs = (np.arange(mask.shape[other[0]]) + 0.5) * sp[other[0]]
        ys = (np.arange(mask.shape[other[1]]) + 0.5) * sp[other[1]]
        if init_mask is not None and init_mask[tuple(sl)].any():
            ax.contour(xs, ys, init_mask[tuple(sl)].T.astype(float), [0.5], colors="yellow",
                       linestyles="dashed", linewidths=0.8)
        if mask[tuple(sl)].any():
            ax.contour(xs, ys, mask[tuple(sl)].T.astype(float), [0.5], colors="red", linewidths=1.0)
        ax.set_title(f"{names[axis]} = {centre[axis]}", fontsize=9)
        ax.set_xlabel(f"{names[other[0]]} mm", fontsize=8)
        ax.set_ylabel(f"{names[other[1]]} mm", fontsize=8)
        ax.tick_params(labelsize=7)
    ax3 = fig.add_subplot(1, 4, 4, projection="3d")
    mesh = model.to_mesh(4 * model.m1, 4 * model.m2)
    faces = np.asarray(mesh.faces).reshape(-1, 4)[:, 1:]
    pts = np.asarray(mesh.points)
    ax3.plot_trisurf(pts[:, 0], pts[:, 1], faces, pts[:, 2], color="tomato", alpha=0.8,
                     linewidth=0.1, edgecolor="k")
    ax3.set_box_aspect(np.ptp(pts, axis=0) + 1e-9)
    ax3.set_title("surface (mm)", fontsize=9)
    ax3.tick_params(labelsize=6)
    fig.tight_layout()
    fig.savefig(path, format="png")
    plt.close(fig)
