"""``segsnake segment IMAGE --out DIR``: segment one structure with a sphere or cylinder snake."""

from __future__ import annotations

import argparse
import os

from segsnake.commands import add_wait_option, positive_int
from segsnake.config import ENERGIES
from segsnake.commands.reporting import add_output_options, emit, progress_off, warn

HELP = "segment one structure in a 3D image with a spline snake"


def _vec3(parser: argparse.ArgumentParser, flag: str, meta: tuple[str, str, str], help: str) -> None:
    parser.add_argument(flag, nargs=3, type=float, metavar=meta, default=None, help=help)


def _position(parser: argparse.ArgumentParser, flag: str, help: str) -> None:
    # Three numbers or one file: argparse cannot say "3 or 1", so take any count and let
    # _position_value check it (a usage error, exit 2).
    parser.add_argument(flag, nargs="+", metavar=("I|FILE.mrk.json", "J K"), default=None,
                        help=help + "; or a 3D Slicer markups file (.mrk.json, LPS or RAS)")


def _position_value(flag: str, values: list[str] | None) -> list[float] | str | None:
    """A position flag's values as three numbers or a markups file's path."""
    from segsnake.errors import ConfigError

    if values is None:
        return None
    if len(values) == 1:
        return values[0]
    try:
        numbers = [float(v) for v in values]
    except ValueError:
        numbers = None
    if numbers is None or len(numbers) != 3:
        raise ConfigError(f"{flag} takes three numbers (I J K, or world mm with --world) or one "
                          f"markups file, got {' '.join(values)!r}")
    return numbers


def add_segment_options(parser: argparse.ArgumentParser) -> None:
    """The options shared by ``segment`` and (as YAML keys) by ``batch`` cases."""
    from segsnake.config import PRIOR_SPACES

    g = parser.add_argument_group("initialization (voxel indices along the array axes, or world mm "
                                  "with --world)")
    g.add_argument("--shape", choices=("sphere", "cylinder"), default=None,
                   help="snake topology (default sphere)")
    _position(g, "--center", "sphere centre (default: estimated from the image)")
    _vec3(g, "--radii", ("RI", "RJ", "RK"), "sphere radii (default: with --center and the "
          "region energy, the largest ball about the click that looks like one tissue; "
          "otherwise half the largest object's size)")
    _position(g, "--axis-start", "cylinder axis start point, implying --shape cylinder (a "
                                 "markups file with two points: start and end)")
    _position(g, "--axis-end", "cylinder axis end point")
    g.add_argument("--radius", type=float, default=None,
                   help="cylinder radius (voxels across the axis, or mm with --world)")
    g.add_argument("--centerline", default=None, metavar="FILE",
                   help="a cylinder along a polyline of points along the tube: FILE.csv (header "
                        "x,y,z[,radius]), FILE.json ({\"points\": [[x, y, z], ...], "
                        "\"radii\": ...}) or a 3D Slicer curve FILE.mrk.json (world mm, radii "
                        "from --radius); implies --shape cylinder; M2 about one ring per "
                        "diameter unless --m2")
    g.add_argument("--world", action="store_true", default=None,
                   help="positions and radii are in the image's world millimetres")
    g.add_argument("--init", default=None, metavar="SNAKE.json",
                   help="start from a saved snake instead of a new sphere or cylinder: a "
                        "snake.json, a fit of a mask (segsnake fit MASK), or a markups file "
                        "written by export-points (perhaps edited in Slicer); placed by world "
                        "coordinates, resampled to --m1/--m2 when given; the rough-start stages "
                        "are skipped")
    g.add_argument("--atlas", default=None, metavar="DIR",
                   help="start from an atlas' structure: the image is registered (affine) to "
                        "the atlas' DIR/template.nii.gz, the structure carried onto it and "
                        "fitted; the fit is the start and the shape prior (--prior-weight, "
                        "--prior-space). DIR holds label images NAME.nii.gz with NAME.csv "
                        "(value,name). benchmarks/atlas_start.py builds one from PyPI packages")
    g.add_argument("--structure", default=None, metavar="NAME",
                   help="with --atlas: the structure, as SET:LABEL, LABEL (a name or value) or "
                        "SET (all its labels as one object); default the label under --center")
    m = parser.add_argument_group("model and features")
    m.add_argument("--m1", type=int, default=None, help="control points around (default 9 sphere, 8 cylinder)")
    m.add_argument("--m2", type=int, default=None,
                   help="control points along (default 9 sphere, 4 cylinder; with --centerline "
                        "about one per diameter, 4 to 32)")
    m.add_argument("--scale", type=float, default=None, metavar="MM",
                   help="detector scale in mm (default 1.5 x the largest voxel size)")
    m.add_argument("--feature", choices=("edge", "surface"), default=None,
                   help="edge: boundary of a filled object (default); surface: a thin sheet "
                        "(a tube wall, a membrane, the CSF around a brain)")
    m.add_argument("--polarity", choices=("auto", "bright", "dark", "none"), default=None,
                   help="edge mode: the object is brighter (bright) or darker (dark) than its "
                        "surroundings, auto detects it, none ignores it. surface mode: auto/none fit "
                        "the mid-surface of a bright sheet; bright/dark take the inner face of a "
                        "bright/dark sheet that encloses the object")
    m.add_argument("--energy", choices=ENERGIES, default=None,
                   help="region: the click's intensities against the rest of the image, then "
                        "the step (a sphere around a filled object; auto's choice there); edge: "
                        "the edge-map stages (auto's choice for cylinders and --feature surface)")
    m.add_argument("--coarse-to-fine", action=argparse.BooleanOptionalAction, default=None,
                   help="region energy: a sphere without --m1/--m2 tries 13 x 13, 17 x 17, "
                        "... up to 37 x 37 after 9 x 9 (the first with its poles on the "
                        "surface's long axis); a tube without --m1 as many control points "
                        "around after 8; each kept while it moves the surface by less than "
                        "the coarser grid's control spacing (finer detail, not a leak: under "
                        "2 %% of the volume may lie farther), the second finer grid always "
                        "tried and the next while the last one lowered the energy by 1 %% or "
                        "more (on by default, "
                        "--no-coarse-to-fine keeps the first grid)")
    m.add_argument("--threshold", default=None, help="edge threshold: auto (default) or a number")
    _position(m, "--seed-point", "keep only the detected surface nearest this voxel")
    m.add_argument("--max-iter", type=int, default=None, help="iteration cap per stage (default 300)")
    m.add_argument("--volume", type=int, default=None, metavar="N", help="which volume of a 4D image")
    m.add_argument("--nan", choices=("refuse", "fill"), default=None,
                   help="NaN/Inf voxels: refuse the image (default) or fill with its minimum")
    o = parser.add_argument_group("outputs")
    o.add_argument("--mesh", default=None, metavar="NAME.stl",
                   help="also write the surface as NAME.stl, NAME.obj or NAME.ply (by the "
                        "extension; world mm, like surface.vtp) in the output directory")
    p = parser.add_argument_group("shape prior")
    p.add_argument("--prior", default=None, metavar="REF.json", help="reference snake (a saved model)")
    p.add_argument("--prior-weight", type=float, default=None, metavar="W",
                   help="prior strength relative to the image energy: an RMS deviation from the "
                        "reference's shape space of 10%% of the snake's radius costs W times the "
                        "image energy (1 strong, 0.1 mild; default 1 with --prior, 5 with "
                        "--atlas, 0 = off)")
    p.add_argument("--prior-space", choices=PRIOR_SPACES, default=None,
                   help="transformations the prior ignores: affine (the default with "
                        "--prior), linear, similarity (rotation, scaling, translation; the "
                        "default with --atlas), rigid (rotation, translation), scaling "
                        "(scaling, translation), translation")
    p.add_argument("--prior-modes", type=int, default=None, metavar="K",
                   help="with a shape-model prior (segsnake shape-model MODEL.json): also allow its "
                        "first K modes of variation, penalized by their variances (default 0); "
                        "with --prior-space rigid or similarity, build the model with the same "
                        "shape-model --align")


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    parser = subparsers.add_parser("segment", help=HELP, description=HELP)
    parser.add_argument("image", metavar="IMAGE", help="NIfTI (.nii, .nii.gz) or NRRD/MHA volume, or a DICOM series "
                        "directory")
    parser.add_argument("--out", required=True, metavar="DIR", help="output directory")
    parser.add_argument("--truth", default=None, metavar="MASK",
                        help="truth mask on the image grid: report Dice, Jaccard, distances")
    parser.add_argument("--truth-label", type=int, default=None, metavar="N",
                        help="the truth is a label map (an atlas): compare with its voxels of "
                             "value N only (default: every non-zero voxel)")
    parser.add_argument("--config", default=None, metavar="FILE.yaml",
                        help="options from a YAML file (flags given here override it)")
    parser.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    add_wait_option(parser)
    add_output_options(parser)
    parser.add_argument("--threads", type=positive_int, default=None, metavar="N",
                        help="threads for the array work (default: $SEGSNAKE_NUM_THREADS, "
                             "else every CPU this process may use)")
    add_segment_options(parser)
    parser.set_defaults(func=run)
    return parser


OPTION_KEYS = ("shape", "center", "radii", "axis_start", "axis_end", "radius", "centerline",
               "world", "m1", "m2",
               "scale", "feature", "polarity", "energy", "coarse_to_fine", "threshold",
               "seed_point", "max_iter", "volume", "nan", "prior", "prior_weight", "prior_space",
               "prior_modes", "mesh", "init", "atlas", "structure")


def config_from_args(args: argparse.Namespace):
    """SegmentConfig from defaults < ``--config`` YAML < command-line flags."""
    from segsnake.config import POSITION_KEYS, SegmentConfig, load_segment_config

    base = load_segment_config(args.config) if args.config else SegmentConfig()
    overrides = {k: getattr(args, k) for k in OPTION_KEYS}
    for key in POSITION_KEYS:
        overrides[key] = _position_value("--" + key.replace("_", "-"), overrides[key])
    if overrides["threshold"] is not None and overrides["threshold"] != "auto":
        try:
            overrides["threshold"] = float(overrides["threshold"])
        except ValueError:
            from segsnake.errors import ConfigError

            raise ConfigError(f"--threshold must be 'auto' or a number, got {args.threshold!r}") from None
    return base.replace(**overrides)


def progress_reporter(quiet: bool):
    """A ``progress(stage, fraction)`` callback drawing a 0-100 % bar on stderr, and the bar.

    Call ``bar.close()`` when done (also on failure) so that later output starts on a new line.
    """
    from segsnake.progress import ProgressBar

    bar = ProgressBar(100, label="%", quiet=quiet, mode="auto")
    done = [0]

    def progress(stage: str, fraction: float) -> None:
        target = int(round(100 * fraction))
        if target > done[0]:
            bar.update(target - done[0], note=stage)
            done[0] = target

    return progress, bar


def run(args: argparse.Namespace) -> int:
    from segsnake.errors import ConfigError
    from segsnake.parallel import set_threads, threads
    from segsnake.runner import segment_file

    if args.threads is not None:
        set_threads(args.threads)
    threads()  # a bad SEGSNAKE_NUM_THREADS stops here, before any work

    config = config_from_args(args)
    if config.init is not None and args.shape is not None:
        # The saved snake is a sphere or a cylinder already: a --shape would be silently ignored.
        raise ConfigError(f"--shape does not apply with --init (the snake in {config.init} "
                          f"keeps its kind)")
    if args.truth_label is not None and args.truth is None:
        raise ConfigError("--truth-label needs --truth (the label map it selects from)")
    progress, bar = progress_reporter(progress_off(args))
    try:
        summary = segment_file(args.image, args.out, config, truth_path=args.truth,
                               truth_label=args.truth_label, truth_label_option="--truth-label N",
                               overwrite=args.overwrite, wait=args.wait,
                               progress=progress)
    finally:
        bar.close()
    # Warnings (e.g. NaN voxels filled) always reach stderr, even with --quiet or --json: they
    # say the result was computed on a changed image. They are also in the summary.
    warn("segment", summary.get("warnings", []))
    line = (f"segmented {summary['mask_voxels']} voxels ({summary['volume_mm3']:.0f} mm^3) in "
            f"{summary['timings']['total_s']:.1f} s")
    if summary.get("dice") is not None:
        line += f"; Dice {summary['dice']:.4f}, Jaccard {summary['jaccard']:.4f}"
    names = " ".join(os.path.basename(p) for p in summary["outputs"].values())
    emit(args, summary, [line, f"outputs in {args.out}: {names}"])
    return 0
