"""The sweep behind :mod:`segsnake.click`'s constants: a click alone on the real benchmark.

Every sphere case of the real-data benchmark (``make bench-real-data``) from its click's centre
alone: the radius :func:`segsnake.click.click_radius` gives at each setting, and the Dice of the
region energy's segmentation from that sphere (``segment --center`` without ``--radii``;
"fail" is "no boundary found", exit 4). The defaults first.

Usage::

    .venv/bin/python benchmarks/click_sweep.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
for _p in (HERE / "real", HERE, HERE.parent):
    sys.path.insert(0, str(_p))

from fetch import load_cases  # noqa: E402
from segsnake import click  # noqa: E402
from segsnake.config import SegmentConfig  # noqa: E402
from segsnake.errors import SegmentationError  # noqa: E402
from segsnake.io import load_volume  # noqa: E402
from segsnake.metrics import dice  # noqa: E402
from segsnake.pipeline import segment_volume  # noqa: E402

#: (spread_growth, shell_spreads), the defaults first.
SETTINGS = ((click.SPREAD_GROWTH, click.SHELL_SPREADS), (1.25, 2.0), (2.0, 2.0), (1.5, 1.5),
            (1.5, 3.0))


def main() -> None:
    cases = [c for c in load_cases()
             if c["role"] == "benchmark" and c["init"]["shape"] == "sphere"]
    images: dict[str, np.ndarray] = {}
    print("| spread_growth, shell_spreads | " + " | ".join(c["name"] for c in cases) + " |")
    print("|---" * (len(cases) + 1) + "|")
    for growth, spreads in SETTINGS:
        row = []
        for case in cases:
            truth_volume = load_volume(case["truth"])
            truth = np.asarray(truth_volume.data) > 0
            sp = tuple(float(s) for s in truth_volume.spacing)
            if case["image"] not in images:
                images[case["image"]] = np.asarray(load_volume(case["image"]).data,
                                                   dtype=np.float32)
            image = images[case["image"]]
            centre = np.asarray(case["init"]["center"], dtype=np.float64)
            r = click.click_radius(image, sp, centre * sp, spread_growth=growth,
                                   shell_spreads=spreads)
            config = SegmentConfig(center=tuple(centre), radii=tuple(r / np.asarray(sp)))
            try:
                mask = segment_volume(image, sp, config).mask
                row.append(f"{dice(mask, truth):.3f} (r {r:.1f} mm)")
            except SegmentationError:
                row.append(f"fail (r {r:.1f} mm)")
        print(f"| {growth}, {spreads} | " + " | ".join(row) + " |", flush=True)

if __name__ == "__main__":
    main()
