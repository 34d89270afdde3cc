"""How much a real-anatomy result moves when its click moves by a tiny amount (issue 15: a
result that flips with rounding is a design fault).

    .venv/bin/python benchmarks/click_sensitivity.py [--cases colin27-hippocampus-r ...]
        [--shifts 0 1e-9 1e-6 1e-3] [--m1 8 --m2 4] [--perfect-edges]

For each case of the real-data benchmark (``make bench-real-data``), the benchmark's click is
moved by each shift (voxels, along the first array axis; a cylinder: its axis start) and the
structure segmented with the default options (``segment_volume``, in this process); prints the
Dice with the reference and the mask's voxel count. ``--perfect-edges`` uses the reference mask
as the image (the benchmark's ceiling).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from segsnake.config import SegmentConfig  # noqa: E402
from segsnake.errors import SegmentationError  # noqa: E402
from segsnake.io import load_volume  # noqa: E402
from segsnake.metrics import dice  # noqa: E402
from segsnake.pipeline import segment_volume  # noqa: E402

CASES = Path.home() / ".cache" / "segsnake" / "real" / "cases"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="+", default=["colin27-hippocampus-r", "colin27-thalamus-r"])
    ap.add_argument("--shifts", nargs="+", type=float, default=[0.0, 1e-9, 1e-6, 1e-3])
    ap.add_argument("--m1", type=int)
    ap.add_argument("--m2", type=int)
    ap.add_argument("--perfect-edges", action="store_true")
    opts = ap.parse_args()
    cases = {c["name"]: c for c in json.loads((CASES / "cases.json").read_text())}
    print("| case | shift (voxels) | Dice | voxels |")
    print("|---|---|---|---|")
    for name in opts.cases:
        case = cases[name]
        truth = load_volume(str(CASES / case["truth"])).data > 0
        image = truth.astype(np.float32) if opts.perfect_edges else \
            load_volume(str(CASES / case["image"])).data
        spacing = load_volume(str(CASES / case["truth"])).spacing
        for shift in opts.shifts:
            init = dict(case["init"])
            key = "center" if init["shape"] == "sphere" else "axis_start"
            init[key] = [init[key][0] + shift, *init[key][1:]]
            if opts.m1:
                init.update(m1=opts.m1, m2=opts.m2)
            try:
                res = segment_volume(image, spacing, SegmentConfig.from_mapping(init))
                print(f"| {name} | {shift:g} | {dice(res.mask, truth):.3f} | {int(res.mask.sum())} |",
                      flush=True)
            except SegmentationError as exc:
                print(f"| {name} | {shift:g} | failed: {str(exc)[:50]} | |", flush=True)


if __name__ == "__main__":
    main()
