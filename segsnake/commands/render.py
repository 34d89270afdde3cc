"""``segsnake render SNAKE --like IMAGE --out DIR``: a saved or hand-edited snake's outputs on a grid."""

from __future__ import annotations

import argparse
import os

from segsnake.commands import add_wait_option
from segsnake.commands.reporting import add_output_options, emit, warn

HELP = "rebuild mask, surface and QC picture of a saved snake (or edited points) on an image's grid"


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    parser = subparsers.add_parser("render", help=HELP, description=HELP + ".")
    parser.add_argument("snake", metavar="SNAKE.json|POINTS.mrk.json",
                        help="a snake.json written by segment or render, a fit of a mask, or "
                             "a markups file written by export-points (points may have been "
                             "moved in Slicer)")
    parser.add_argument("--like", required=True, metavar="IMAGE",
                        help="the image whose grid (shape, affine) the outputs are written on")
    parser.add_argument("--out", required=True, metavar="DIR", help="output directory")
    parser.add_argument("--mesh", default=None, metavar="NAME.stl",
                        help="also write the surface as NAME.stl, NAME.obj or NAME.ply")
    parser.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    add_wait_option(parser)
    add_output_options(parser)
    parser.set_defaults(func=run)
    return parser


def run(args: argparse.Namespace) -> int:
    from segsnake.config import SegmentConfig
    from segsnake.runner import render_file

    mesh = SegmentConfig().replace(mesh=args.mesh).mesh  # the same check as segment --mesh
    summary = render_file(args.snake, args.like, args.out, mesh=mesh, overwrite=args.overwrite,
                          wait=args.wait)
    warn("render", summary.get("warnings", []))
    names = " ".join(os.path.basename(p) for p in summary["outputs"].values())
    emit(args, summary, [f"rendered {summary['mask_voxels']} voxels "
                         f"({summary['volume_mm3']:.0f} mm^3) on the grid of {args.like}",
                         f"outputs in {args.out}: {names}"])
    return 0
