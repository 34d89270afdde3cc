"""Score kept trachea masks against the benchmark's reference taken at other air thresholds.

The lung2 trachea reference is the air below :data:`cases.AIR_HU` (-950 HU) inside the body,
tracked slice by slice (:func:`cases.trachea_reference`). This script builds the same reference
at other thresholds, on the benchmark reference's own slices, and prints the Dice of every kept
``mask.nii.gz`` of the ``lung2-trachea`` case under ``DIR`` (``bench_real.py --keep DIR``)
against each: where the result's surface lies between the lumen's core and the wall's half
maximum.

Usage::

    .venv/bin/python benchmarks/real/trachea_thresholds.py DIR [--thresholds -950 -800 -600 -500]
"""

from __future__ import annotations

import argparse
import glob
import os
import sys

import nibabel as nib
import numpy as np

sys.path[:0] = [os.path.dirname(__file__), os.path.dirname(os.path.dirname(__file__))]
import cases  # noqa: E402  (benchmarks/real, with benchmarks/ on the path as it expects)
from fetch import load_cases  # noqa: E402

from segsnake.metrics import dice  # noqa: E402


#: The benchmark case whose kept masks are scored (bench_real.py keeps them under its name).
CASE = "lung2-trachea"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("keep", help="a bench_real.py --keep directory")
    ap.add_argument("--thresholds", type=float, nargs="+", default=[-950.0, -800.0, -600.0, -500.0])
    args = ap.parse_args(argv)
    case = next(c for c in load_cases() if c["name"] == CASE)  # (its files, as fetch.py built)
    ct = nib.load(case["image"]).get_fdata()
    reference = nib.load(case["truth"]).get_fdata() > 0
    on_slices = np.zeros(ct.shape[2], bool)
    on_slices[np.unique(np.nonzero(reference)[2])] = True
    refs = {}
    for hu in args.thresholds:
        mask, _ = cases.trachea_reference(ct, air_hu=hu)
        mask[:, :, ~on_slices] = False
        refs[hu] = mask
    print("| references | " + " | ".join(f"{a:g} / {b:g}: {dice(refs[a], refs[b]):.3f}"
                                         for a in refs for b in refs if a < b) + " |")
    print("| run | " + " | ".join(f"< {hu:g} HU" for hu in refs) + " | volume / reference's |")
    print("|---" * (len(refs) + 2) + "|")
    for path in sorted(glob.glob(os.path.join(args.keep, "**", "mask.nii.gz"), recursive=True)):
        if CASE not in os.path.abspath(path).split(os.sep):
            continue  # (a whole --keep folder holds the other cases' masks too)
        seg = nib.load(path).get_fdata() > 0
        run = os.path.relpath(os.path.dirname(path), args.keep)
        ratios = " / ".join(f"{seg.sum() / refs[hu].sum():.3f}" for hu in refs)
        print(f"| {run} | " + " | ".join(f"{dice(seg, m):.3f}" for m in refs.values())
              + f" | {ratios} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
