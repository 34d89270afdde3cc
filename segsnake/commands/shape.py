"""``segsnake shape sphere|ellipsoid|cylinder --out REF.json``: write a reference snake.

The file is a saved model (``segsnake-model`` JSON) that ``segment --prior REF.json`` reads.
Positions and lengths are in mm of scaled index space (``p = (i*sx, j*sy, k*sz)``: a voxel index
times the image's spacing). Under the default ``--prior-space affine`` only the shape up to an
affine map matters, so any sphere means "stay close to some ellipsoid" and any straight
cylinder "close to some elliptic cylinder", whatever the units and position; the position,
size and orientation given here matter only for the ``similarity``, ``rigid``, ``scaling``,
``translation`` and ``linear`` spaces.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from segsnake.commands.reporting import add_output_options, emit
from segsnake.errors import ConfigError

HELP = "write a reference shape (sphere, ellipsoid, cylinder) for segment --prior"

_UNITS = ("coordinates and lengths in mm of scaled index space (voxel index x spacing); "
          "for the default affine prior only the shape up to an affine map matters")


def _vec3(p: argparse.ArgumentParser, flag: str, default, help: str, required: bool = False) -> None:
    p.add_argument(flag, nargs=3, type=float, metavar=("X", "Y", "Z"), default=default,
                   required=required, help=help)


def _common(p: argparse.ArgumentParser, m1: int, m2: int) -> None:
    p.add_argument("--m1", type=int, default=m1, help=f"control points around (default {m1})")
    p.add_argument("--m2", type=int, default=m2, help=f"control points along (default {m2})")
    p.add_argument("--out", required=True, metavar="REF.json", help="output file")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    add_output_options(p)


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    parser = subparsers.add_parser("shape", help=HELP, description=HELP + ". " + _UNITS + ".")
    kinds = parser.add_subparsers(dest="kind", metavar="KIND")
    kinds.required = True

    s = kinds.add_parser("sphere", help="a sphere (the affine prior: any ellipsoid)",
                         description="Sphere reference; " + _UNITS + ".")
    _vec3(s, "--center", [0.0, 0.0, 0.0], "centre (default 0 0 0)")
    s.add_argument("--radius", type=float, default=1.0, metavar="R", help="radius (default 1)")
    _common(s, 9, 9)

    e = kinds.add_parser("ellipsoid", help="an ellipsoid",
                         description="Ellipsoid reference R diag(radii) s + centre; " + _UNITS + ".")
    _vec3(e, "--center", [0.0, 0.0, 0.0], "centre (default 0 0 0)")
    e.add_argument("--radii", nargs=3, type=float, required=True, metavar=("RX", "RY", "RZ"),
                   help="semi-axes along the ellipsoid's own axes")
    e.add_argument("--rotation", nargs=3, type=float, default=None, metavar=("A", "B", "C"),
                   help="Euler angles in degrees ('xyz', as in segsnake phantom ellipsoid) "
                        "rotating the axes (default none)")
    _common(e, 9, 9)

    c = kinds.add_parser("cylinder", help="a straight circular cylinder",
                         description="Cylinder reference; " + _UNITS + ".")
    _vec3(c, "--axis-start", [0.0, 0.0, 0.0], "axis start point (default 0 0 0)")
    _vec3(c, "--axis-end", [0.0, 0.0, 1.0], "axis end point (default 0 0 1)")
    c.add_argument("--radius", type=float, default=1.0, metavar="R", help="radius (default 1)")
    _common(c, 8, 4)

    parser.set_defaults(func=run)
    return parser


def _check(cond: bool, message: str) -> None:
    if not cond:
        raise ConfigError(message)


def build_reference(args: argparse.Namespace):
    """The model described by the parsed options (ConfigError on invalid values)."""
    from segsnake.surfaces import CylinderModel, SphereModel

    from segsnake.config import M_MAX, M_MIN

    for flag, m in (("--m1", args.m1), ("--m2", args.m2)):
        # The bounds of segment's --m1/--m2: a reference must match the snake's size.
        _check(M_MIN <= m <= M_MAX, f"{flag} must be between {M_MIN} and {M_MAX}, got {m}")
    values = [v for name in ("center", "radii", "rotation", "axis_start", "axis_end", "radius")
              for v in np.atleast_1d(getattr(args, name, None) or 0.0)]
    _check(bool(np.all(np.isfinite(values))), "coordinates and lengths must be finite numbers")
    if args.kind == "sphere":
        _check(args.radius > 0, f"--radius must be positive, got {args.radius}")
        return SphereModel.ellipsoid(args.center, [args.radius] * 3, m1=args.m1, m2=args.m2)
    if args.kind == "ellipsoid":
        _check(all(r > 0 for r in args.radii), f"--radii must be positive, got {args.radii}")
        rotation = None
        if args.rotation is not None:
            from scipy.spatial.transform import Rotation

            rotation = Rotation.from_euler("xyz", args.rotation, degrees=True).as_matrix()
        return SphereModel.ellipsoid(args.center, args.radii, rotation, m1=args.m1, m2=args.m2)
    _check(args.radius > 0, f"--radius must be positive, got {args.radius}")
    _check(not np.allclose(args.axis_start, args.axis_end), "--axis-start and --axis-end coincide")
    return CylinderModel.from_axis(args.axis_start, args.axis_end, args.radius, m1=args.m1,
                                   m2=args.m2)


def run(args: argparse.Namespace) -> int:
    from segsnake.io import atomic_write

    model = build_reference(args)
    text = json.dumps(model.to_dict())

    def writer(tmp: str) -> None:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)

    atomic_write(args.out, writer, overwrite=args.overwrite)
    record = {"out": args.out, "reference": args.kind, "kind": model.kind, "m1": model.m1,
              "m2": model.m2}
    emit(args, record, [f"wrote {args.kind} reference ({model.kind} model, M1={model.m1}, "
                        f"M2={model.m2}) to {args.out}"])
    return 0
