"""``segsnake shape-model SNAKES... --out MODEL.json``: a shape space learned from saved snakes.

Each SNAKE is a saved model: a ``snake.json`` from ``segsnake segment``, a ``segsnake shape``
reference, or any ``segsnake-model`` JSON; all must have the same kind. Snakes of different
control-point counts (coarse to fine ends each segmentation on the grid its image supports) are
resampled to the largest counts among them by the exact L2 projection.
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
                        help="saved snakes of one kind (at least two); snakes of other sizes are "
                             "resampled to the largest M1 and M2 among them (the exact L2 "
                             "projection, as --init resamples)")
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
        if m.kind != first.kind:
            raise InputError(f"{path}: a {m.kind}; {args.snakes[0]} is a {first.kind} (all snakes "
                             f"must be of one kind)")
    # (coarse to fine ends on 9 x 9 to 37 x 37 as each image allows: one size for all)
    models, moved = _one_size(models)
    first = models[0]
    sm = build_shape_model(models, sources=list(args.snakes), align=args.align)
    sm.save(args.out, overwrite=args.overwrite)
    summary = {
        "out": args.out,
        "kind": first.kind, "m1": first.m1, "m2": first.m2, "n_shapes": len(models),
        "align": args.align,
        "resampled": [p for p, d in zip(args.snakes, moved) if d is not None],
        "resampled_max_move_mm": max((d for d in moved if d is not None), default=None),
        "max_residual_mm": float(np.max(sm.residuals)),
        "agreement": sm.agreement.tolist(),
        "variances_mm2": sm.variances.tolist(),
        "explained": sm.explained.tolist(),
    }
    first_mode = (f"; mode 1 explains {100 * sm.explained[0]:.1f} % of the variance"
                  if len(sm.variances) else "; no variation left after alignment")
    resampled = "" if not summary["resampled"] else (
        f", {len(summary['resampled'])} of them resampled to that size (surface points moved "
        f"{summary['resampled_max_move_mm']:.2g} mm at most)")
    emit(args, summary, [
        f"shape model of {len(models)} {first.kind} snakes (M1={first.m1}, M2={first.m2}"
        f"{resampled}): "
        f"alignment residuals up to {summary['max_residual_mm']:.3g} mm, "
        f"{len(sm.variances)} modes{first_mode}; written to {args.out}"])
    return 0


def _one_size(models: list) -> tuple[list, list[float | None]]:
    """The snakes at the largest M1 and M2 among them: those of another size replaced by their
    L2 projection onto that spline space (:func:`segsnake.resample.resample`, which keeps the
    parameterization: a point keeps its (u, v), so correspondences survive), and for each, how
    far its surface points moved (mm, on a grid of 8 samples per interval of the finer size; None
    for a snake kept as it was)."""
    from segsnake.resample import resample

    m1, m2 = max(m.m1 for m in models), max(m.m2 for m in models)
    u = (np.arange(8 * m1) + 0.5) / (8 * m1)
    v = np.linspace(0.0, 1.0, 8 * m2 + 1)
    out, moved = [], []
    for m in models:
        if (m.m1, m.m2) == (m1, m2):
            out.append(m)
            moved.append(None)
            continue
        r = resample(m, m1, m2)
        out.append(r)
        moved.append(float(np.linalg.norm(r.positions(u, v) - m.positions(u, v),
                                          axis=-1).max()))
    return out, moved
