"""``segsnake fit INPUT --out SNAKE.json``: a deformable sphere fitted to a mask, mesh or cloud.

INPUT is recognized by its name:

* a binary mask (``.nii``, ``.nii.gz``, ``.mha``, ``.mhd``, ``.nrrd``, ``.nhdr``; non-zero voxels,
  or ``--label N``): its boundary becomes a closed genus-0 mesh in mm of scaled index space
  (voxel index times spacing, the units of ``snake.json``; :mod:`segsnake.mask_mesh`); the
  output then carries the mask's grid (``affine``, ``spacing_mm``), which places the fitted
  snake in the world, so that ``segment --init``, ``render`` and ``export-points`` take it as
  they take a ``snake.json`` (a rough mask, an atlas' structure or an earlier scan's
  segmentation, refined on an image);
* a point cloud (``.npy``, ``.txt``, ``.csv``, ``.xyz``, ``.pts``): three columns ``x y z`` are
  meshed with pyvista's surface reconstruction and the errors are measured at the points; five
  columns ``x y z u v`` are a *parameterized* cloud (seed 000 sec. 6.2) fitted directly;
* anything else: a closed genus-0 triangle mesh in any format pyvista reads (STL, OBJ, PLY, VTK,
  VTP, ...).

Meshes are parameterized over the sphere with a harmonic (mean-value) map to the disk and an
area-matched latitude (:mod:`segsnake.parameterize`; no star shape needed), then the L2
projection with the exact Gram matrix fits the control points (:mod:`segsnake.fit`). With
``--m1``/``--m2`` the size is fixed; otherwise M2 = 4, 6, 8, 12, ... (M1 = 2 M2) until the RMS
error reaches ``--rms-target`` mm (default 0.5 % of the bounding-box diagonal). Errors are
reported as seed 004 does: RMS and maximum of ``|x_i - sigma(u_i, v_i)|`` over the samples, in mm
and in % of the samples' bounding-box diagonal.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import warnings

import numpy as np

from segsnake.commands import positive_int
from segsnake.commands.reporting import add_output_options, emit, warn

HELP = "fit a deformable sphere to a mask, a closed genus-0 mesh or a point cloud"

MASK_SUFFIXES = (".nii", ".nii.gz", ".mha", ".mhd", ".nrrd", ".nhdr")
CLOUD_SUFFIXES = (".npy", ".txt", ".csv", ".xyz", ".pts")
#: A hole in the surface reconstructed from a point cloud is closed when it is at most this many
#: point spacings (sqrt(area / points)) across (pyvista's ``fill_holes`` size): the
#: reconstruction's own cut where the surface touches the bounds of its sample volume, not a gap
#: in the cloud. Measured (300-2000 random points, five seeds each): every such cut of a sphere's
#: clouds (4-8 edges at an extreme point, in 13 of its 20) is closed at 1, 2 and 3 spacings; a
#: sphere of radius 10 with a cap of radius 7 cut off stays open at 1-3 in all 20 clouds (at 5 in
#: 16, at 8 in 10).
HOLE_SPACINGS = 3.0


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    from segsnake.fit import DEFAULT_RMS_PERCENT

    parser = subparsers.add_parser("fit", help=HELP, description=HELP + ".")
    parser.add_argument("input", metavar="INPUT", help="mask (NIfTI, ...), mesh, or point cloud")
    parser.add_argument("--out", required=True, metavar="SNAKE.json", help="output file")
    parser.add_argument("--m1", type=positive_int, default=None, help="fixed control points around")
    parser.add_argument("--m2", type=positive_int, default=None, help="fixed control points along")
    parser.add_argument("--rms-target", type=float, default=None, metavar="MM",
                        help=f"raise M until the RMS error is at most MM (default "
                             f"{DEFAULT_RMS_PERCENT} %% of the bounding-box diagonal)")
    parser.add_argument("--label", type=int, default=None,
                        help="for a label map: fit this label (default: every non-zero voxel)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output")
    add_output_options(parser)
    parser.set_defaults(func=run)
    return parser


def _has_suffix(path: str, suffixes: tuple[str, ...]) -> bool:
    return path.lower().endswith(suffixes)


def _read_cloud(path: str) -> np.ndarray:
    from segsnake.errors import InputError

    try:
        if path.lower().endswith(".npy"):
            data = np.load(path, allow_pickle=False)
        else:
            delimiter = "," if path.lower().endswith(".csv") else None
            try:
                data = np.loadtxt(path, delimiter=delimiter, ndmin=2)
            except ValueError:  # a header line
                data = np.loadtxt(path, delimiter=delimiter, ndmin=2, skiprows=1)
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not a readable point cloud ({str(exc).splitlines()[0]})") from None
    data = np.asarray(data, dtype=np.float64)
    if data.ndim != 2 or data.shape[1] not in (3, 5):
        raise InputError(f"{path}: a point cloud needs 3 columns (x y z) or 5 (x y z u v), "
                         f"got shape {data.shape}")
    if not np.all(np.isfinite(data)):
        raise InputError(f"{path}: the point cloud has NaN or infinite values")
    return data


def _polydata_arrays(mesh) -> tuple[np.ndarray, np.ndarray]:
    import pyvista as pv

    if not isinstance(mesh, pv.PolyData):
        mesh = mesh.extract_surface(algorithm="dataset_surface")
    mesh = mesh.triangulate().clean()
    faces = np.asarray(mesh.faces).reshape(-1, 4)[:, 1:]
    return np.asarray(mesh.points, dtype=np.float64), faces.astype(np.int64)


def _read_mesh(path: str) -> tuple[np.ndarray, np.ndarray]:
    import pyvista as pv

    from segsnake.errors import InputError

    # VTK's readers report a file they cannot read on the terminal (its log, Python's logging,
    # a warning: about twenty lines) and return an empty mesh: silenced here, said in one line.
    logging.disable(logging.CRITICAL)
    try:
        with warnings.catch_warnings(record=True) as caught, pv.vtk_verbosity("off"):
            warnings.simplefilter("always")
            mesh = pv.read(path)
    except Exception as exc:  # noqa: BLE001 - pyvista/VTK raise many kinds for unreadable files
        raise InputError(f"{path}: not a mesh pyvista can read ({str(exc).splitlines()[0]})") from None
    finally:
        logging.disable(logging.NOTSET)
    if mesh.n_points == 0:
        why = "the reader failed" if caught else "it is empty"
        raise InputError(f"{path}: not a mesh pyvista can read ({why})")
    points, faces = _polydata_arrays(mesh)
    if len(faces) == 0:
        raise InputError(f"{path}: the mesh has no triangles")
    return points, faces


def _mask(path: str, label: int | None):
    from segsnake.errors import InputError
    from segsnake.io import load_volume

    volume = load_volume(path, bytes_per_voxel=None, one_of_several=False)
    mask = volume.data == label if label is not None else volume.data != 0
    if not mask.any():
        what = f"label {label}" if label is not None else "non-zero voxel"
        raise InputError(f"{path}: the mask has no {what}")
    return mask, volume.spacing, volume.affine


def _step_rows(steps) -> list[dict]:
    return [{"m1": s.m1, "m2": s.m2, "n_params": s.n_params, "rms_mm": s.error.rms,
             "max_mm": s.error.max, "rms_percent": s.error.rms_percent,
             "max_percent": s.error.max_percent} for s in steps]


def run(args: argparse.Namespace) -> int:
    from segsnake.errors import ConfigError, InputError
    from segsnake.fit import fit_cloud, fit_mesh
    from segsnake.io import atomic_write, check_not_input
    from segsnake.parameterize import TopologyError

    if (args.m1 is None) != (args.m2 is None):
        raise ConfigError("--m1 and --m2 go together (or give neither and let M grow)")
    if args.m1 is not None and args.rms_target is not None:
        raise ConfigError("--rms-target and a fixed --m1/--m2 are exclusive")
    if args.m1 is not None and (args.m1 < 4 or args.m2 < 2):
        raise ConfigError(f"a sphere needs --m1 >= 4 and --m2 >= 2, got {args.m1} and {args.m2}")
    if args.rms_target is not None and not args.rms_target > 0:
        raise ConfigError(f"--rms-target must be positive, got {args.rms_target}")
    if not os.path.exists(args.input):
        raise InputError(f"{args.input}: no such file")
    check_not_input(args.out, args.input)
    if os.path.exists(args.out) and not args.overwrite:
        from segsnake.errors import OutputError

        raise OutputError(f"{args.out}: exists (use --overwrite to replace it)")

    info: dict = {"input": args.input}
    grid: dict = {}  # (a mask's: where its scaled index space lies in the world)
    try:
        if _has_suffix(args.input, MASK_SUFFIXES) or os.path.isdir(args.input):
            from segsnake.mask_mesh import mask_surface

            mask, spacing, affine = _mask(args.input, args.label)
            grid = {"affine": np.asarray(affine, dtype=np.float64).tolist(),
                    "spacing_mm": [float(x) for x in spacing]}
            surf = mask_surface(mask, spacing)
            info.update(input_kind="mask", smoothing_voxels=surf.sigma_voxels,
                        mask_to_surface_rms_mm=surf.distance_to_mask_rms,
                        mask_to_surface_max_mm=surf.distance_to_mask_max)
            result = fit_mesh(surf.points, surf.faces, m1=args.m1, m2=args.m2,
                              rms_target=args.rms_target)
        elif _has_suffix(args.input, CLOUD_SUFFIXES):
            cloud = _read_cloud(args.input)
            if cloud.shape[1] == 5:
                info.update(input_kind="parameterized point cloud")
                if np.any((cloud[:, 4] < 0) | (cloud[:, 4] > 1)):
                    raise InputError(f"{args.input}: the v column must lie in [0, 1]")
                result = fit_cloud(cloud[:, :3], np.mod(cloud[:, 3], 1.0), cloud[:, 4],
                                   m1=args.m1, m2=args.m2, rms_target=args.rms_target)
            else:
                import pyvista as pv

                info.update(input_kind="point cloud (meshed by pyvista reconstruct_surface)")
                surface = pv.PolyData(cloud).reconstruct_surface().triangulate().clean()
                if surface.n_open_edges:
                    # (HOLE_SPACINGS: the reconstruction's cut at its bounds is closed, a gap in
                    # the cloud is refused below)
                    spacing = math.sqrt(surface.area / len(cloud))
                    surface = surface.fill_holes(HOLE_SPACINGS * spacing).clean()
                points, faces = _polydata_arrays(surface)
                try:
                    result = fit_mesh(points, faces, m1=args.m1, m2=args.m2,
                                      rms_target=args.rms_target, samples=cloud)
                except TopologyError as exc:
                    raise InputError(f"{args.input}: the surface reconstructed from its "
                                     f"{len(cloud)} points: {exc}") from None
        else:
            info.update(input_kind="mesh")
            points, faces = _read_mesh(args.input)
            result = fit_mesh(points, faces, m1=args.m1, m2=args.m2, rms_target=args.rms_target)
    except TopologyError as exc:
        raise InputError(f"{args.input}: {exc}") from None
    except ValueError as exc:
        raise InputError(f"{args.input}: {str(exc).splitlines()[0]}") from None

    smap = result.spherical_map
    if smap is not None:
        info.update(parameterization="mean-value harmonic map to the disk, area-matched latitude",
                    vertices=len(smap.points), flipped_triangles=smap.flipped_fraction())
    model = result.model
    last = result.steps[-1]
    info.update(m1=model.m1, m2=model.m2, n_params=model.n_params, rms_mm=last.error.rms,
                max_mm=last.error.max, rms_percent=last.error.rms_percent,
                max_percent=last.error.max_percent, diagonal_mm=last.error.diagonal,
                rms_target_mm=result.rms_target, target_met=result.target_met,
                steps=_step_rows(result.steps))
    text = json.dumps({"format": "segsnake-fit", "version": 1, "model": model.to_dict(),
                       **grid, "fit": info})

    def writer(tmp: str) -> None:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)

    atomic_write(args.out, writer, overwrite=args.overwrite)
    if not result.target_met:
        warn("fit", [f"the RMS target {result.rms_target:.4g} mm was not reached with the largest "
                     f"size tried (M1={model.m1}, M2={model.m2}: {last.error.rms:.4g} mm)"])
    lines = [f"{'M1':>4} {'M2':>4} {'params':>7} {'RMS %':>8} {'max %':>8}"]
    lines += [f"{s.m1:>4} {s.m2:>4} {s.n_params:>7} {s.error.rms_percent:>8.3f} "
              f"{s.error.max_percent:>8.3f}" for s in result.steps]
    lines.append(f"fitted {info['input_kind']} {args.input}: M1={model.m1}, M2={model.m2}, RMS "
                 f"{last.error.rms:.4g} mm ({last.error.rms_percent:.3f} % of the "
                 f"{last.error.diagonal:.4g} mm diagonal), max {last.error.max:.4g} mm; "
                 f"written to {args.out}")
    emit(args, {"out": args.out, **info}, lines)
    return 0

