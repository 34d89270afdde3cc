"""The sweep behind ``RegionParams.max_step_beyond`` and ``step_reach_mm``: the failure warning for
a result that stopped short of a stronger step beyond it (docs/design.md, "When it failed").

    .venv/bin/python benchmarks/bench_real.py --tools segsnake "segsnake, centre only" \\
        "segsnake, centreline" "segsnake, perfect edges" "segsnake, no click" --keep KEEP
    .venv/bin/python benchmarks/step_beyond_sweep.py KEEP [--reach 4 6 8] [--most 1.5 2 3]

For every region-energy result kept by ``bench_real.py --keep`` (its ``snake.json`` and mask),
:func:`segsnake.region.step_beyond` is computed again at each reach (the image smoothed and the
step measured as the run did, from its recorded parameters and intensity model), with the
result's Dice against its case's reference. Prints one row per result, then for each reach and
threshold how many results below Dice 0.8 and above 0.9 it would warn about.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
for _p in (HERE / "real", HERE.parent):
    sys.path.insert(0, str(_p))

from fetch import load_cases  # noqa: E402
from segsnake.io import load_volume  # noqa: E402
from segsnake.metrics import dice  # noqa: E402
from segsnake.region import smoothed, step_beyond  # noqa: E402
from segsnake.surfaces import load_model  # noqa: E402


def results(keep: str, reaches: list[float]) -> list[dict]:
    """Each kept region-energy result: case, run, Dice and ``step_beyond`` at each reach."""
    truths = {c["name"]: c["truth"] for c in load_cases()}
    image_s, read = None, None
    rows = []
    for path in sorted(glob.glob(os.path.join(keep, "*", "*", "snake.json"))):
        out = os.path.dirname(path)
        case = os.path.basename(os.path.dirname(out))
        with open(path) as fh:
            doc = json.load(fh)
        settings = doc["settings"]
        if "intensity_model" not in settings:  # (the edge stages: no region quality)
            continue
        params = settings["region_params"]
        key = (doc["summary"]["image"], params["smooth_mm"])
        if key != read:  # (the runs of one image come together: one smoothed image at a time)
            volume = load_volume(key[0])
            spacing = np.asarray(volume.spacing, dtype=np.float64)
            image_s, read = smoothed(volume.data.astype(np.float32), spacing, key[1]), key
        polarity = 1 if doc["summary"]["polarity"] == "bright" else -1
        floor = params["step_spreads"] * settings["intensity_model"]["sigma"]
        model = load_model(path)
        mask = load_volume(os.path.join(out, "mask.nii.gz")).data > 0
        truth = load_volume(truths[case]).data > 0
        rows.append({"case": case, "run": os.path.basename(out), "dice": float(dice(mask, truth)),
                     "step_beyond": [step_beyond(image_s, model, spacing, polarity,
                                                 params["step_depth_mm"], r, floor)
                                     for r in reaches]})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("keep", help="a bench_real.py --keep directory")
    ap.add_argument("--reach", type=float, nargs="+", default=[4.0, 6.0, 8.0])
    ap.add_argument("--most", type=float, nargs="+", default=[1.5, 2.0, 3.0])
    args = ap.parse_args()
    rows = results(args.keep, args.reach)
    print("| case | run | Dice | " + " | ".join(f"step beyond, {r:g} mm" for r in args.reach)
          + " |")
    print("|---|---|---|" + "---|" * len(args.reach))
    for row in rows:
        print(f"| {row['case']} | {row['run']} | {row['dice']:.3f} | "
              + " | ".join(f"{v:.2f}" for v in row["step_beyond"]) + " |")
    low = [r for r in rows if r["dice"] < 0.8]
    high = [r for r in rows if r["dice"] > 0.9]
    print()
    for i, reach in enumerate(args.reach):
        for most in args.most:
            n_low = sum(r["step_beyond"][i] > most for r in low)
            n_high = sum(r["step_beyond"][i] > most for r in high)
            print(f"reach {reach:g} mm, above {most:g}: warns {n_low} of {len(low)} below Dice "
                  f"0.8, {n_high} of {len(high)} above 0.9")
    values = [v for r in rows for v in r["step_beyond"]]
    if values:
        print(f"step_beyond over every result and reach: {min(values):.2f}-{max(values):.2f}")


if __name__ == "__main__":
    main()
