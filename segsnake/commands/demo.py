"""``segsnake demo``: make a phantom, segment it, print what was found.

With ``--out DIR`` it writes ``DIR/phantom/{image,truth}.nii.gz, phantom.json`` and
``DIR/segmentation/`` (the outputs of ``segsnake segment``) and keeps them; existing outputs there
are refused before anything is written, unless ``--overwrite``. Without ``--out`` it works in a new
temporary directory and removes it at the end, whatever the outcome: a demo run to see that the
install works must not leave a folder behind each time.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import sys
import tempfile
from typing import Iterator

from segsnake.commands.reporting import add_output_options, emit, progress_off, warn

HELP = "segment a built-in noisy phantom and report Dice against its truth"


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    parser = subparsers.add_parser("demo", help=HELP, description=HELP)
    parser.add_argument("--out", default=None, metavar="DIR",
                        help="keep the phantom and the outputs in DIR (default: work in a "
                             "temporary directory, removed at the end)")
    parser.add_argument("--kind", default="blob", choices=("ball", "ellipsoid", "blob"),
                        help="phantom kind (default blob)")
    parser.add_argument("--seed", type=int, default=0, help="phantom seed (default 0)")
    parser.add_argument("--noise", type=float, default=0.2,
                        help="noise std as a fraction of the contrast (default 0.2)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the outputs of an earlier demo in --out")
    add_output_options(parser)
    parser.set_defaults(func=run)
    return parser


def _fmt(value, spec: str) -> str:
    return "n/a" if value is None else format(value, spec)


@contextlib.contextmanager
def _work_dir(out: str | None) -> Iterator[str]:
    """``out`` itself, or a temporary directory removed on the way out (also on Ctrl-C)."""
    from segsnake.errors import OutputError

    if out is not None:
        yield out
        return
    try:
        tmp = tempfile.mkdtemp(prefix="segsnake-demo-")
    except OSError as exc:
        raise OutputError(f"{tempfile.gettempdir()}: cannot create a temporary directory "
                          f"({exc.strerror or exc}); choose one with --out DIR") from None
    try:
        yield tmp
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def run(args: argparse.Namespace) -> int:
    from segsnake.commands import phantom as phantom_cmd
    from segsnake.commands.segment import progress_reporter
    from segsnake.config import SegmentConfig
    from segsnake.errors import OutputError
    from segsnake.phantoms import make_phantom
    from segsnake.runner import OUTPUT_NAMES, segment_file

    if args.out is not None and not args.overwrite:  # refuse before writing anything
        for path in [os.path.join(args.out, "phantom", n) for n in phantom_cmd.OUTPUT_NAMES] + \
                    [os.path.join(args.out, "segmentation", n) for n in OUTPUT_NAMES]:
            if os.path.lexists(path):
                raise OutputError(f"{path}: already exists; use --overwrite to replace it")

    ph = make_phantom(args.kind, seed=args.seed, noise=args.noise)
    shape = "x".join(str(n) for n in ph.image.shape)
    intro = [f"phantom: {args.kind}, {shape} voxels, noise {100 * args.noise:.0f} % of the "
             f"contrast, seed {args.seed}",
             f"initial sphere: centre {ph.init['center']}, radii {ph.init['radii']} (voxels)"]
    if not progress_off(args):  # now, before the progress bar on stderr
        sys.stdout.write("\n".join(intro) + "\n")
        sys.stdout.flush()
    config = SegmentConfig.from_mapping(dict(ph.init), source="phantom init")
    with _work_dir(args.out) as out:
        phantom_dir = os.path.join(out, "phantom")
        seg_dir = os.path.join(out, "segmentation")
        phantom_cmd.write_phantom(ph, phantom_dir, overwrite=args.overwrite)
        progress, bar = progress_reporter(progress_off(args))
        try:
            summary = segment_file(os.path.join(phantom_dir, "image.nii.gz"), seg_dir, config,
                                   truth_path=os.path.join(phantom_dir, "truth.nii.gz"),
                                   overwrite=args.overwrite, progress=progress)
        finally:
            bar.close()
    warn("demo", summary.get("warnings", []))
    kept = args.out is not None
    result = (f"segmented in {summary['timings']['total_s']:.1f} s: "
              f"Dice {_fmt(summary['dice'], '.4f')}, Jaccard {_fmt(summary['jaccard'], '.4f')}, "
              f"HD95 {_fmt(summary['hausdorff95_mm'], '.2f')} mm, "
              f"ASSD {_fmt(summary['assd_mm'], '.2f')} mm")
    names = " ".join(os.path.basename(p) for p in summary["outputs"].values())
    outputs = (f"outputs: {seg_dir}/{names}" if kept else
               "outputs: not kept (segsnake demo --out DIR keeps the phantom and the segmentation)")
    if not kept:  # the files named there are gone
        summary = {k: v for k, v in summary.items() if k != "outputs"}
    record = {"kind": args.kind, "shape": list(ph.image.shape), "noise": args.noise,
              "seed": args.seed, "init": ph.init, "summary": summary,
              "out": os.path.abspath(args.out) if kept else None}
    emit(args, record, [result, outputs])
    return 0
