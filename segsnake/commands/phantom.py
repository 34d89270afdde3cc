"""``segsnake phantom KIND --out DIR``: write a synthetic volume with its truth.

Writes ``DIR/image.nii.gz`` (float32), ``DIR/truth.nii.gz`` (uint8 0/1) and ``DIR/phantom.json``
(kind, seed, spacing, parameters and a suggested ``segment`` initialisation). Nothing is written
when any of the three exists and ``--overwrite`` is not given.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from segsnake.commands.reporting import add_output_options, emit
from segsnake.errors import ConfigError, OutputError
from segsnake.io import Volume, atomic_write, save_mask, save_volume
from segsnake.phantoms import PHANTOMS, Phantom, make_phantom, phantom_options

HELP = "write a synthetic volume with known truth (image, truth mask, phantom.json)"

OUTPUT_NAMES = ("image.nii.gz", "truth.nii.gz", "phantom.json")
#: Peak bytes per voxel of making a phantom (measured: 133 over the five kinds at 160^3).
PHANTOM_BYTES_PER_VOXEL = 140

# Command-line flag (argparse dest) -> phantom keyword option.
_FLAG_OPTIONS = {
    "shape": "shape",
    "spacing": "spacing",
    "noise": "noise",
    "rician": "rician",
    "bias": "bias",
    "blur": "blur",
    "contrast": "contrast",
    "std": "std",
    "grid_rotation": "grid_rotation",
}


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "phantom", help=HELP, description=HELP,
        epilog="kinds: " + ", ".join(PHANTOMS) + ". Options a kind does not take are refused.",
    )
    parser.add_argument("kind", metavar="KIND", help="phantom kind: " + ", ".join(PHANTOMS))
    parser.add_argument("--out", required=True, metavar="DIR", help="output directory")
    parser.add_argument("--seed", type=int, default=0, metavar="S", help="random seed (default 0)")
    parser.add_argument("--shape", type=int, nargs=3, metavar=("NX", "NY", "NZ"),
                        help="grid shape (default: the kind's field of view / spacing)")
    parser.add_argument("--spacing", type=float, nargs=3, metavar=("SX", "SY", "SZ"),
                        help="voxel size in mm (default 1 1 1)")
    parser.add_argument("--noise", type=float, metavar="F",
                        help="noise std as a fraction of the contrast (brain: of the brightest "
                             "tissue), e.g. 0.03")
    parser.add_argument("--rician", action="store_true", default=None,
                        help="Rician (magnitude) noise instead of Gaussian")
    parser.add_argument("--bias", type=float, metavar="F",
                        help="multiplicative bias field range, e.g. 0.2 for 20 %%")
    parser.add_argument("--blur", type=float, metavar="MM", help="Gaussian blur sigma in mm")
    parser.add_argument("--contrast", choices=("t1", "pd"), help="brain contrast")
    parser.add_argument("--std", type=float, metavar="S",
                        help="hollow-cylinder noise std in 8-bit units (Table 7.2: 0..90)")
    parser.add_argument("--grid-rotation", type=float, nargs=3, metavar=("AX", "AY", "AZ"),
                        help="oblique acquisition grid: Euler angles in degrees (xyz), written "
                             "into the affine only")
    parser.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    add_output_options(parser)
    parser.set_defaults(func=run)
    return parser


def phantom_record(ph: Phantom) -> dict[str, Any]:
    """The content of ``phantom.json``: kind, seed, spacing, affine, init and all parameters."""
    return {
        "kind": ph.params["kind"],
        "seed": ph.params["seed"],
        "shape": ph.params["shape"],
        "spacing": list(ph.spacing),
        "affine": np.asarray(ph.affine).tolist(),
        "init": ph.init,
        "params": ph.params,
    }


def write_phantom(ph: Phantom, out_dir: str | Path, overwrite: bool = False) -> list[Path]:
    """Write a phantom's image, truth and JSON record into ``out_dir`` (created if missing).

    Parameters
    ----------
    ph : Phantom
        What to write.
    out_dir : path
        Destination directory.
    overwrite : bool
        Replace existing files; otherwise any existing output stops the write before anything
        is written.

    Returns
    -------
    list of Path
        The three files written.

    Raises
    ------
    OutputError
        An output exists without ``overwrite``, or the directory/files cannot be written.
    """
    out = Path(out_dir)
    paths = [out / n for n in OUTPUT_NAMES]
    if not overwrite:
        existing = [str(p) for p in paths if p.exists()]
        if existing:
            raise OutputError(f"{existing[0]}: exists (use --overwrite to replace it)")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{out}: cannot create directory ({exc.strerror or exc})") from None
    ref = Volume(data=ph.image, spacing=ph.spacing, affine=ph.affine, path=None, header=None)
    save_volume(ph.image, ref, paths[0], overwrite=overwrite)
    save_mask(ph.truth, ref, paths[1], overwrite=overwrite)
    text = json.dumps(phantom_record(ph), indent=2, allow_nan=False) + "\n"
    atomic_write(paths[2], lambda tmp: Path(tmp).write_text(text, encoding="utf-8"),
                 overwrite=overwrite)
    return paths


def run(args: argparse.Namespace) -> int:
    kind = args.kind.replace("_", "-").lower()
    if kind not in PHANTOMS:
        raise ConfigError(f"unknown phantom kind {args.kind!r} (kinds: {', '.join(PHANTOMS)})")
    accepted = set(phantom_options(kind))
    options: dict[str, Any] = {}
    for dest, opt in _FLAG_OPTIONS.items():
        value = getattr(args, dest, None)
        if value is None:
            continue
        if opt not in accepted:
            flag = "--" + dest
            raise ConfigError(f"{flag} does not apply to phantom {kind!r}")
        options[opt] = value
    if args.seed < 0:
        raise ConfigError(f"--seed must be >= 0, got {args.seed}")
    if "shape" in options:
        from segsnake.io import beyond_memory, fmt_bytes

        need = PHANTOM_BYTES_PER_VOXEL * float(np.prod(np.asarray(options["shape"], dtype=float)))
        beyond = beyond_memory(need)
        if beyond is not None:
            raise ConfigError(f"--shape {' '.join(map(str, options['shape']))}: the phantom needs "
                              f"about {fmt_bytes(need)} of memory, {beyond}; give a smaller shape")
    ph = make_phantom(kind, seed=args.seed, **options)
    paths = write_phantom(ph, args.out, overwrite=args.overwrite)
    record = {"kind": kind, "outputs": [str(p) for p in paths], "init": ph.init}
    emit(args, record, [f"wrote {', '.join(str(p) for p in paths)}"])
    return 0
