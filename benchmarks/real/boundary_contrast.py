"""How much do a result's inside and outside differ across its surface? (a failure detector's raw data)

For every segsnake output folder kept by ``bench_real.py --keep DIR`` (``DIR/<case>/<run>/``), the
saved surface is laid on the case's *real* image (also for the perfect-edge runs, whose surface then
stands for "a near-correct result") and sampled at ``d`` mm inside and outside along its normals,
in the image smoothed at the run's detector scale:

- ``frac+``: the area fraction where the step inside - outside has the sign of its median;
- ``d'``: that median step over the robust spread of the samples (1.4826 MAD, inside and outside
  pooled in quadrature): a separation in units of the intensity variation along the surface.

Usage::

    .venv/bin/python benchmarks/bench_real.py --quick --keep /tmp/keep --json /tmp/quick.json
    .venv/bin/python benchmarks/real/boundary_contrast.py /tmp/keep /tmp/quick.json
"""

from __future__ import annotations

import glob
import json
import os
import sys

import numpy as np
from scipy import ndimage

HERE = os.path.dirname(os.path.abspath(__file__))
for _p in (HERE, os.path.dirname(HERE), os.path.dirname(os.path.dirname(HERE))):
    if _p not in sys.path:
        sys.path.insert(0, _p)


def contrast(model, smooth: np.ndarray, spacing: np.ndarray, d: float) -> tuple[float, float]:
    """(frac+, d') of ``model`` on the smoothed image at ``d`` mm either side (module docstring)."""
    gb, w = model.quadrature(6)
    s, su, sv = gb.evaluate(model.control_points())
    n = np.cross(sv, su) * model.orientation  # outward
    area = (w * np.linalg.norm(n, axis=-1)).ravel()
    n = (n / np.linalg.norm(n, axis=-1, keepdims=True)).reshape(-1, 3)
    s = s.reshape(-1, 3)

    def sample(p: np.ndarray) -> np.ndarray:
        return ndimage.map_coordinates(smooth, (p / spacing).T, order=1, mode="nearest")

    inside, outside = sample(s - d * n), sample(s + d * n)
    step = inside - outside
    step = step * np.sign(np.median(step))
    frac = float(area[step > 0].sum() / area.sum())

    def mad(x: np.ndarray) -> float:
        return 1.4826 * float(np.median(np.abs(x - np.median(x))))

    spread = np.sqrt((mad(inside) ** 2 + mad(outside) ** 2) / 2)
    return frac, float(np.median(step) / max(spread, 1e-12))


def main(argv: list[str]) -> int:
    from fetch import load_cases

    from segsnake.io import load_volume
    from segsnake.surfaces import model_from_dict

    keep, results = argv[0], argv[1] if len(argv) > 1 else None
    dice: dict[tuple[str, str], float] = {}
    if results:
        with open(results) as fh:
            for case in json.load(fh)["cases"]:
                for r in case["runs"]:
                    dice.setdefault((case["case"], r["tool"]), r.get("dice", 0.0))
    cases = {c["name"]: c for c in load_cases()}
    images: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    print("| case | run | Dice | d (mm) | frac+ | d' |")
    print("|---|---|---|---|---|---|")
    for path in sorted(glob.glob(os.path.join(keep, "*", "*", "snake.json"))):
        run_dir = os.path.dirname(path)
        name, run = os.path.basename(os.path.dirname(run_dir)), os.path.basename(run_dir)
        with open(path) as fh:
            saved = json.load(fh)
        image = cases[name]["image"]
        if image not in images:
            vol = load_volume(image)
            images[image] = (vol.data.astype(np.float32), np.asarray(vol.spacing))
        data, sp = images[image]
        scale = float(saved["settings"]["scale_mm"])
        smooth = ndimage.gaussian_filter(data, scale / sp)
        tool = "segsnake, perfect edges" if "perfect" in run else "segsnake"
        model = model_from_dict(saved["model"])
        for d in (scale, 2 * scale):
            frac, dprime = contrast(model, smooth, sp, d)
            print(f"| {name} | {run} | {dice.get((name, tool), float('nan')):.3f} | {d:.1f} | "
                  f"{frac:.2f} | {dprime:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
