"""``segsnake shape-model SNAKES... --out MODEL.json``: a shape space learned from saved snakes.

Each SNAKE is a saved model: a ``snake.json`` from ``segsnake segment``, a ``segsnake shape``
reference, or any ``segsnake-model`` JSON; all must have the same kind and control-point counts.
MODEL.json holds the unbiased affine-aligned reference (thesis ch. 5, Proposition 5) under
``model`` (so ``segment --prior MODEL.json`` uses it), the aligned examples with their affine
maps and residuals, and the functional PCA of the aligned set (mean, unit-L2 modes, variances
in mm^2). See :mod:`segsnake.shapes`.
"""

from __future__ import annotations

import argparse

import numpy as np

from segsnake.commands.reporting import add_output_options, emit
from segsnake.errors import ConfigError, InputError

HELP = "learn a shape model (aligned reference + functional PCA) from saved snakes"


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    from segsnake.shapes import ALIGNMENTS

    parser = subparsers.add_parser("shape-model", help=HELP, description=HELP + ".")
    parser.add_argument("snakes", nargs="+", metavar="SNAKE.json",
                        help="saved snakes of one kind and size (at least two)")
    parser.add_argument("--out", required=True, metavar="MODEL.json", help="output file")
    parser.add_argument("--align", choices=ALIGNMENTS, default=ALIGNMENTS[0],
                        help="unbiased affine alignment (default), or generalized Procrustes with "
                             "rotations (+ isotropic scaling): its modes keep the anisotropic "
                             "variation, for a rigid or similarity prior with --prior-modes")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output")
    add_output_options(parser)
    parser.set_defaults(func=run)
    return parser


def run(args: argparse.Namespace) -> int:
    from segsnake.io import check_not_input
    from segsnake.saved_snake import read_model
    from segsnake.shapes import build_shape_model

    if len(args.snakes) < 2:
        raise ConfigError(f"shape-model needs at least two snakes, got {len(args.snakes)}")
    check_not_input(args.out, *args.snakes)
    models = [read_model(p) for p in args.snakes]
    first = models[0]
    for path, m in zip(args.snakes, models):
        if (m.kind, m.m1, m.m2) != (first.kind, first.m1, first.m2):
            raise InputError(f"{path}: a {m.kind} with M1={m.m1}, M2={m.m2}; {args.snakes[0]} is a "
                             f"{first.kind} with M1={first.m1}, M2={first.m2} (all snakes must match)")
    sm = build_shape_model(models, sources=list(args.snakes), align=args.align)
    sm.save(args.out, overwrite=args.overwrite)
    summary = {
        "out": args.out,
        "kind": first.kind, "m1": first.m1, "m2": first.m2, "n_shapes": len(models),
        "align": args.align,
        "max_residual_mm": float(np.max(sm.residuals)),
        "agreement": sm.agreement.tolist(),
        "variances_mm2": sm.variances.tolist(),
        "explained": sm.explained.tolist(),
    }
    first_mode = (f"; mode 1 explains {100 * sm.explained[0]:.1f} % of the variance"
                  if len(sm.variances) else "; no variation left after alignment")
    emit(args, summary, [
        f"shape model of {len(models)} {first.kind} snakes (M1={first.m1}, M2={first.m2}): "
        f"alignment residuals up to {summary['max_residual_mm']:.3g} mm, "
        f"{len(sm.variances)} modes{first_mode}; written to {args.out}"])
    return 0
