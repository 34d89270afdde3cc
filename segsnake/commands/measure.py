"""``segsnake measure SNAKE.json [--json|--csv]``: exact measurements of a saved snake.

Volume, area, centroid, principal axes and lengths, maximal diameter, sphericity, and mean and
Gaussian curvature statistics, all from the spline's exact derivatives (:mod:`segsnake.measure`).
SNAKE is a ``snake.json`` from ``segment``, a ``shape`` reference, a ``fit`` output or any
``segsnake-model`` JSON. Lengths are in the model's units: mm of scaled index space for snakes
(voxel index times spacing), so the axes' directions are along the image's index axes.
"""

from __future__ import annotations

import argparse
import csv
import sys

from segsnake.commands.reporting import add_output_options, emit

HELP = "measure a saved snake: volume, area, axes, diameter, sphericity, curvature"


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    parser = subparsers.add_parser("measure", help=HELP, description=HELP + ".")
    parser.add_argument("snake", metavar="SNAKE.json", help="a saved snake or model")
    parser.add_argument("--csv", action="store_true",
                        help="print 'quantity,value' rows on stdout instead of text")
    add_output_options(parser)
    parser.set_defaults(func=run)
    return parser


def flat_rows(record: dict, prefix: str = "") -> list[tuple[str, object]]:
    """``(name, value)`` pairs of a nested record: ``mean_curvature.max``, ``centroid.0``."""
    rows: list[tuple[str, object]] = []
    for key, value in record.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            rows += flat_rows(value, name + ".")
        elif isinstance(value, (list, tuple)):
            rows += flat_rows({str(i): v for i, v in enumerate(value)}, name + ".")
        else:
            rows.append((name, value))
    return rows


def run(args: argparse.Namespace) -> int:
    from segsnake.saved_snake import read_model
    from segsnake.errors import ConfigError
    from segsnake.measure import measure

    if args.csv and args.json:
        raise ConfigError("--csv and --json are exclusive")
    model = read_model(args.snake)
    record = {"snake": args.snake, **measure(model).to_dict()}
    if args.csv:
        if not args.quiet:
            writer = csv.writer(sys.stdout, lineterminator="\n")
            writer.writerow(["quantity", "value"])
            writer.writerows((k, repr(v) if isinstance(v, float) else v)
                             for k, v in flat_rows(record))
        return 0
    H, K = record["mean_curvature"], record["gaussian_curvature"]
    lines = [
        f"{args.snake}: {model.kind}, M1={model.m1}, M2={model.m2}",
        f"volume {record['volume']:.6g} mm^3, area {record['area']:.6g} mm^2, "
        f"sphericity {record['sphericity']:.4f}",
        "centroid " + " ".join(f"{c:.4g}" for c in record["centroid"]) + " mm",
        "principal lengths " + " ".join(f"{c:.4g}" for c in record["principal_lengths"])
        + f" mm, maximal diameter {record['max_diameter']:.4g} mm",
        f"mean curvature {H['mean']:.4g} (min {H['min']:.4g}, max {H['max']:.4g}) 1/mm; "
        f"Gaussian curvature integral {K['integral']:.6g} (4 pi = 12.5664 when closed and smooth)",
    ]
    emit(args, record, lines)
    return 0
