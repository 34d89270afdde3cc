"""``segsnake demo``: make a phantom, segment it, print what was found.

Writes ``DIR/phantom/{image,truth}.nii.gz, phantom.json`` and ``DIR/segmentation/`` (the outputs of
``segsnake segment``), DIR being a new temporary directory unless ``--out`` is given. Existing
outputs there are refused before anything is written, unless ``--overwrite``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile

HELP = "segment a built-in noisy phantom and report Dice against its truth"


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    parser = subparsers.add_parser("demo", help=HELP, description=HELP)
    parser.add_argument("--out", default=None, metavar="DIR",
                        help="where to put the phantom and the outputs (default: a new temp dir)")
    parser.add_argument("--kind", default="blob", choices=("ball", "ellipsoid", "blob"),
                        help="phantom kind (default blob)")
    parser.add_argument("--seed", type=int, default=0, help="phantom seed (default 0)")
    parser.add_argument("--noise", type=float, default=0.2,
                        help="noise std as a fraction of the contrast (default 0.2)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the outputs of an earlier demo in --out")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)
    return parser


def _fmt(value, spec: str) -> str:
    return "n/a" if value is None else format(value, spec)


def run(args: argparse.Namespace) -> int:
    from segsnake.commands import phantom as phantom_cmd
    from segsnake.commands.segment import progress_reporter
    from segsnake.config import SegmentConfig
    from segsnake.errors import OutputError
    from segsnake.phantoms import make_phantom
    from segsnake.runner import OUTPUT_NAMES, segment_file

    if args.out is None:
        try:
            out = tempfile.mkdtemp(prefix="segsnake-demo-")
        except OSError as exc:
            raise OutputError(f"{tempfile.gettempdir()}: cannot create a temporary directory "
                              f"({exc.strerror or exc}); choose one with --out DIR") from None
    else:
        out = args.out
    phantom_dir = os.path.join(out, "phantom")
    seg_dir = os.path.join(out, "segmentation")
    if not args.overwrite:  # refuse before writing anything, not after the phantom
        for path in [os.path.join(phantom_dir, n) for n in phantom_cmd.OUTPUT_NAMES] + \
                    [os.path.join(seg_dir, n) for n in OUTPUT_NAMES]:
            if os.path.lexists(path):
                raise OutputError(f"{path}: already exists; use --overwrite to replace it")

    ph = make_phantom(args.kind, seed=args.seed, noise=args.noise)
    phantom_cmd.write_phantom(ph, phantom_dir, overwrite=args.overwrite)
    print(f"phantom: {args.kind}, {ph.image.shape[0]}x{ph.image.shape[1]}x{ph.image.shape[2]} voxels, "
          f"noise {100 * args.noise:.0f} % of the contrast, seed {args.seed}")
    print(f"initial sphere: centre {ph.init['center']}, radii {ph.init['radii']} (voxels)")
    sys.stdout.flush()  # before the progress bar on stderr
    config = SegmentConfig.from_mapping(dict(ph.init), source="phantom init")
    progress, bar = progress_reporter(args.quiet)
    try:
        summary = segment_file(os.path.join(phantom_dir, "image.nii.gz"), seg_dir, config,
                               truth_path=os.path.join(phantom_dir, "truth.nii.gz"),
                               overwrite=args.overwrite, progress=progress)
    finally:
        bar.close()
    print(f"segmented in {summary['timings']['total_s']:.1f} s: Dice {_fmt(summary['dice'], '.4f')}, "
          f"Jaccard {_fmt(summary['jaccard'], '.4f')}, "
          f"HD95 {_fmt(summary['hausdorff95_mm'], '.2f')} mm, "
          f"ASSD {_fmt(summary['assd_mm'], '.2f')} mm")
    print(f"outputs: {seg_dir}/mask.nii.gz surface.vtp snake.json qc.png")
    return 0
