"""The sweep behind ``RegionParams.crossing_weight``: the price, per mm^3, of the volume a region
stage's surface wraps other than once (docs/design.md, "No self-crossing").

    .venv/bin/python benchmarks/crossing_sweep.py [--values 0 0.5 1 2 4 8]

Each value is the ``crossing_weight`` of the run's :class:`segsnake.region.RegionParams` (a sweep
of a constant, not an option users have; 0 is no price and no refusal), and the cases below are
segmented in this process with the default options otherwise: the cases of the real-data
benchmark (``make bench-real-data``) whose results crossings moved (the hippocampus also with
perfect edges, where its surface folded through itself), the lung2 trachea from the benchmark's
third perturbed click (the tube whose planar end cap grazes its wall) and its perfect-edge
ceiling at 16 x 8, and the 1 mm aortic arch phantom of ``bench_tubes.py`` from its 5-point
centreline. Prints the Dice of each.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_real import clicks  # noqa: E402
from bench_tubes import cases as tube_cases  # noqa: E402
from segsnake.config import SegmentConfig  # noqa: E402
from segsnake.errors import SegmentationError  # noqa: E402
from segsnake.io import load_volume  # noqa: E402
from segsnake.metrics import dice  # noqa: E402
from segsnake.phantoms import make_phantom  # noqa: E402
from segsnake.pipeline import segment_volume  # noqa: E402
from segsnake.region import RegionParams  # noqa: E402

CASES = Path.home() / ".cache" / "segsnake" / "real" / "cases"


def runs(cases: dict) -> list[tuple[str, str, dict, bool]]:
    """(label, case name, initialization, perfect edges) of each run."""
    trachea = dict(cases["lung2-trachea"], truth=str(CASES / cases["lung2-trachea"]["truth"]))
    return [("thalamus R, click", "colin27-thalamus-r", cases["colin27-thalamus-r"]["init"], False),
            ("hippocampus R, click", "colin27-hippocampus-r",
             cases["colin27-hippocampus-r"]["init"], False),
            ("hippocampus R, perfect edges", "colin27-hippocampus-r",
             cases["colin27-hippocampus-r"]["init"], True),
            ("tumour, click", "lung2-tumour", cases["lung2-tumour"]["init"], False),
            ("trachea, perturbed click 3", "lung2-trachea", clicks(trachea, 3)[3][1], False),
            ("trachea, perfect edges 16x8", "lung2-trachea",
             {**cases["lung2-trachea"]["init"], "m1": 16, "m2": 8}, True)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--values", nargs="+", type=float,
                    default=[0.0, 0.5, 1.0, 2.0, 4.0, 8.0])
    opts = ap.parse_args()
    cases = {c["name"]: c for c in json.loads((CASES / "cases.json").read_text())}
    plan = runs(cases)
    volumes: dict[str, tuple] = {}
    arch = next(c for c in tube_cases() if c["id"] == "arch_1x1x1")
    ph = make_phantom(arch["kind"], seed=arch["seed"], **arch["options"])
    click = ph.params["geometry"]["click"]
    volumes["arch_1x1x1"] = (ph.image, ph.truth.astype(bool), ph.spacing)
    plan.append(("arch 1 mm, centreline", "arch_1x1x1",
                 {"shape": "cylinder", "centerline": [[*p, r] for p, r in
                                                      zip(click["points_voxels"],
                                                          click["radius_voxels"])]}, False))
    print("| crossing_weight | " + " | ".join(label for label, *_ in plan) + " |")
    print("|---" * (len(plan) + 1) + "|")
    for value in opts.values:
        params = RegionParams(crossing_weight=value)
        row = []
        for _, name, init, perfect in plan:
            if name not in volumes:
                case = cases[name]
                truth = load_volume(str(CASES / case["truth"]))
                volumes[name] = (load_volume(str(CASES / case["image"])).data,
                                 truth.data > 0, truth.spacing)
            image, truth, spacing = volumes[name]
            try:
                res = segment_volume(truth.astype(np.float32) if perfect else image, spacing,
                                     SegmentConfig.from_mapping(init), region_params=params)
                row.append(f"{dice(res.mask, truth):.3f}")
            except SegmentationError as exc:
                row.append(f"fail ({str(exc).split(':')[0]})")
        print(f"| {value:g} | " + " | ".join(row) + " |", flush=True)

if __name__ == "__main__":
    main()
