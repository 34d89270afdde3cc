"""``segsnake morph A.json B.json --steps N --out DIR``: minimum-energy paths between two snakes.

The path of seed 000 (sec. 6.3) on the control points (:mod:`segsnake.morph`): ``--path plane``
(eq. (17), the default) or ``sphere`` (eq. (19), on the Hilbert sphere of centred, normalized
shapes), optionally after the unbiased affine alignment of the pair (``--align``). DIR receives,
for every step ``i``, ``step_i.json`` (the snake, a ``segsnake-model``) and ``step_i.vtp`` (its
mesh, in the snakes' coordinates: mm of scaled index space), and ``morph.csv`` with ``tau``, the
enclosed volume and the area of every step; with ``--like IMAGE`` also ``step_i.nii.gz``, the
step's mask on that image's grid (the snakes must be in its scaled index space, as ``segment``'s
and ``fit``'s of a mask on that grid are). All files are staged and moved in together.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil

from segsnake.commands import positive_int
from segsnake.commands.reporting import add_output_options, emit

HELP = "morph one snake into another along a minimum-energy path (plane or sphere)"


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    from segsnake.morph import PATHS

    parser = subparsers.add_parser("morph", help=HELP, description=HELP + ".")
    parser.add_argument("a", metavar="A.json", help="the start (tau = 0)")
    parser.add_argument("b", metavar="B.json", help="the end (tau = 1); same kind and M1, M2")
    parser.add_argument("--steps", type=positive_int, default=5,
                        help="shapes on the path, the two inputs included (default 5)")
    parser.add_argument("--out", required=True, metavar="DIR", help="output directory")
    parser.add_argument("--path", choices=PATHS, default="plane",
                        help="Hilbert plane (eq. 17) or Hilbert sphere (eq. 19); default plane")
    parser.add_argument("--align", action="store_true",
                        help="align both snakes to their unbiased affine reference first")
    parser.add_argument("--like", default=None, metavar="IMAGE",
                        help="also write each step's mask on this image's grid (step_i.nii.gz)")
    parser.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    add_output_options(parser)
    parser.set_defaults(func=run)
    return parser


def run(args: argparse.Namespace) -> int:
    from segsnake.saved_snake import read_model
    from segsnake.errors import ConfigError, InputError, OutputError
    from segsnake.measure import closed_area
    from segsnake.morph import morph
    from segsnake import outdir
    from segsnake.runner import _check_existing, _check_out_dir

    if args.steps < 2:
        raise ConfigError(f"--steps must be at least 2 (the two inputs), got {args.steps}")
    a, b = read_model(args.a), read_model(args.b)
    if (a.kind, a.m1, a.m2) != (b.kind, b.m1, b.m2):
        raise InputError(f"{args.b}: a {b.kind} with M1={b.m1}, M2={b.m2}; {args.a} is a {a.kind} "
                         f"with M1={a.m1}, M2={a.m2} (the control points must correspond)")
    width = max(3, len(str(args.steps - 1)))
    stems = [f"step_{i:0{width}d}" for i in range(args.steps)]
    kinds = (".json", ".vtp") + ((".nii.gz",) if args.like else ())
    names = tuple(s + k for s in stems for k in kinds) + ("morph.csv",)
    _check_out_dir(args.out, args.overwrite, [args.a, args.b, args.like], names)
    like = None
    if args.like:
        from segsnake.io import load_volume

        like = load_volume(args.like, bytes_per_voxel=None, one_of_several=False)
    try:
        taus, shapes = morph(a, b, args.steps, args.path, args.align)
    except ValueError as exc:
        raise InputError(f"{args.a}: {exc}") from None
    rows = [{"step": i, "tau": float(t), "volume_mm3": float(m.volume()),
             "area_mm2": closed_area(m)} for i, (t, m) in enumerate(zip(taus, shapes))]

    # Staged and committed as segment's outputs, under the output directory's lock.
    with outdir.locked(args.out):
        _check_existing(args.out, args.overwrite, names)
        stage = None
        try:
            stage = outdir.stage_dir(args.out)
            for stem, m in zip(stems, shapes):
                with open(os.path.join(stage, stem + ".json"), "w", encoding="utf-8") as fh:
                    json.dump(m.to_dict(), fh)
                m.to_mesh().save(os.path.join(stage, stem + ".vtp"))
                if like is not None:
                    from segsnake.io import save_mask
                    from segsnake.rasterize import rasterize

                    save_mask(rasterize(m, like.shape, like.spacing), like,
                              os.path.join(stage, stem + ".nii.gz"))
            with open(os.path.join(stage, "morph.csv"), "w", newline="", encoding="utf-8") as fh:
                writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
                writer.writeheader()
                writer.writerows(rows)
            outdir.commit(stage, args.out, args.overwrite, names)
        except OSError as exc:
            raise OutputError(f"{args.out}: cannot write ({exc.strerror or exc})") from None
        finally:
            if stage is not None:
                shutil.rmtree(stage, ignore_errors=True)
    record = {"out": args.out, "path": args.path, "aligned": args.align, "steps": rows}
    emit(args, record, [f"tau {r['tau']:.3f}: volume {r['volume_mm3']:.6g} mm^3, area "
                        f"{r['area_mm2']:.6g} mm^2" for r in rows]
         + [f"{args.steps} shapes ({args.path} path) written to {args.out}"])
    return 0
