"""``segsnake export-points SNAKE.json --out POINTS.mrk.json``: a snake's control points for 3D Slicer."""

from __future__ import annotations

import argparse
import json

from segsnake.commands.reporting import add_output_options, emit

HELP = "write a snake's control points as a 3D Slicer markups file (world coordinates)"


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "export-points", help=HELP, description=HELP + ". Move the points in Slicer, save, and "
        "rebuild the snake with 'segsnake render POINTS.mrk.json --like IMAGE --out DIR' or "
        "refine it with 'segsnake segment IMAGE --init POINTS.mrk.json'.")
    parser.add_argument("snake", metavar="SNAKE.json",
                        help="a snake.json written by segment or render, a fit of a mask (or "
                             "a markups file written by export-points)")
    parser.add_argument("--out", required=True, metavar="POINTS.mrk.json",
                        help="the markups file to write")
    parser.add_argument("--coordinate-system", choices=("LPS", "RAS"), default="LPS",
                        help="the file's coordinateSystem (default LPS, as Slicer saves)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing file")
    add_output_options(parser)
    parser.set_defaults(func=run)
    return parser


def run(args: argparse.Namespace) -> int:
    from segsnake.io import atomic_write, check_not_input
    from segsnake.saved_snake import load_snake, snake_markups

    check_not_input(args.out, args.snake)
    world = load_snake(args.snake)
    doc = snake_markups(world, system=args.coordinate_system,
                        name=f"segsnake {world.kind} {world.m1}x{world.m2}")
    text = json.dumps(doc, indent=1)

    def writer(tmp: str) -> None:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)

    atomic_write(args.out, writer, overwrite=args.overwrite)
    n = len(doc["markups"][0]["controlPoints"])
    record = {"out": args.out, "kind": world.kind, "m1": world.m1, "m2": world.m2,
              "points": n, "coordinate_system": args.coordinate_system}
    emit(args, record, [f"wrote {n} control points of a {world.kind} snake (M1={world.m1}, "
                        f"M2={world.m2}) to {args.out} ({args.coordinate_system} mm)"])
    return 0
