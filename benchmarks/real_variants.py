"""How the real-anatomy results move when a constant of the region energy or a ``segment``
option changes: the sweeps behind the constants (the project's rule: a constant comes with a
measured sweep), and the "tried and not kept" numbers of docs/benchmarks.md.

    .venv/bin/python benchmarks/real_variants.py [--cases colin27-brain lung2-trachea ...]
        [--clicks 5] [--param finer_m='(13, 17, 21)'] [--option max_iter=1000]
        [--perfect-edges]

For each case of the real-data benchmark (``make bench-real-data``), the benchmark's click and
its ``--clicks`` perturbed clicks (:func:`bench_real.clicks`) are segmented in this process
(``segment_volume``) with the defaults changed by ``--param``
(:class:`segsnake.region.RegionParams` fields) and ``--option`` (``segment`` options, as a
config file names them); each value is a Python literal. Prints one row per case: the Dice of
every start ("fail" for a run that found no boundary), the control grid's M1 where it is not
the default schedule's last (``[9]``: coarse to fine kept no finer grid; a tube's ``[8]``), and
the wall time. ``--perfect-edges`` uses the reference mask as the image (the benchmark's
ceiling), click only.
"""

from __future__ import annotations

import argparse
import ast
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
for _p in (HERE / "real", HERE, HERE.parent):
    sys.path.insert(0, str(_p))

from bench_real import clicks  # noqa: E402
from fetch import load_cases  # noqa: E402
from segsnake.config import SegmentConfig  # noqa: E402
from segsnake.errors import SegmentationError  # noqa: E402
from segsnake.io import load_volume  # noqa: E402
from segsnake.metrics import dice  # noqa: E402
from segsnake.pipeline import segment_volume  # noqa: E402
from segsnake.region import RegionParams  # noqa: E402


def _pairs(items: list[str]) -> dict:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"real_variants: expected key=value, got {item!r}")
        out[key] = ast.literal_eval(value)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="+", help="case names (default: every benchmark case)")
    ap.add_argument("--clicks", type=int, default=5, help="perturbed clicks per case")
    ap.add_argument("--param", nargs="*", default=[], metavar="KEY=VALUE")
    ap.add_argument("--option", nargs="*", default=[], metavar="KEY=VALUE")
    ap.add_argument("--perfect-edges", action="store_true")
    args = ap.parse_args()
    params, options = RegionParams(**_pairs(args.param)), _pairs(args.option)
    cases = [c for c in load_cases()
             if c["role"] == "benchmark" and (not args.cases or c["name"] in args.cases)]
    print(f"RegionParams changes: {_pairs(args.param)}; options: {options}"
          f"{'; perfect edges' if args.perfect_edges else ''}")
    images = {}
    for case in cases:
        truth_volume = load_volume(case["truth"])
        truth = np.asarray(truth_volume.data) > 0
        spacing = np.asarray(truth_volume.spacing, dtype=float)
        if args.perfect_edges:
            image = truth.astype(np.float32)
        else:
            if case["image"] not in images:
                images[case["image"]] = np.asarray(load_volume(case["image"]).data,
                                                   dtype=np.float32)
            image = images[case["image"]]
        cells, t0 = [], time.perf_counter()
        for _, init in clicks(case, 0 if args.perfect_edges else args.clicks):
            config = SegmentConfig.from_mapping({**init, **options})
            try:
                res = segment_volume(image, spacing, config, region_params=params)
            except SegmentationError:
                cells.append("fail")
                continue
            # (M1: a sphere's grid, a tube's points around; both end at finer_m's last)
            grid = "" if res.model.m1 == max(params.finer_m or (res.model.m1,)) \
                else f"[{res.model.m1}]"
            cells.append(f"{dice(res.mask, truth):.3f}{grid}")
        print(f"{case['name']:24s} {' '.join(cells)}  ({time.perf_counter() - t0:.0f} s)",
              flush=True)


if __name__ == "__main__":
    main()
