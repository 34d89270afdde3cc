"""The sweep behind a tube's branching constants (:mod:`segsnake.branching`; ``RegionParams``'
``branch_fraction`` and ``cut_radii``): Y-shaped phantoms clicked in their trunk, and the real
benchmark's trachea (``make bench-real-data``), whose carina is such a division.

A Y (:func:`y_tube`) is a trunk along the third axis dividing into two branches that leave the
volume through its bottom face; the reference is the Y above its first axial slice of two
components, as the benchmark's trachea is cut above the carina. Each row: the Dice of every Y
(seeds 0-3 at 1 mm voxels, then seeds 0-1 at 0.6 x 0.6 x 2.5 mm) and of the trachea's click and
perturbed clicks, and of two tubes that do not divide (the S6 vessels of
``bench_tubes.py``, whose noisy ends must not be cut); the defaults first.

Usage::

    .venv/bin/python benchmarks/branch_sweep.py [--no-real] [--settings 0.15,2 0.4,2]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Sequence

import numpy as np
from scipy import ndimage

HERE = Path(__file__).resolve().parent
for _p in (HERE / "real", HERE, HERE.parent):
    sys.path.insert(0, str(_p))

from segsnake.config import SegmentConfig  # noqa: E402
from segsnake.metrics import dice  # noqa: E402
from segsnake.pipeline import segment_volume  # noqa: E402
from segsnake.region import RegionParams  # noqa: E402

#: (branch_fraction, cut_radii), the defaults first.
SETTINGS = ((RegionParams.branch_fraction, RegionParams.cut_radii), (0.1, 2.0), (0.5, 2.0),
            (0.25, 1.5), (0.25, 3.0))
#: The Y's field of view (mm) and its trunk's radius (mm); the branches' are 0.7-0.85 of it.
FOV_MM, TRUNK_RADIUS = (64.0, 48.0, 72.0), 6.0


def _capsules(shape: Sequence[int], spacing: Sequence[float], segments) -> np.ndarray:
    """Voxels whose centre is within ``r`` of a segment ``(a, b, r)`` (mm)."""
    sp = np.asarray(spacing, dtype=float)
    idx = np.indices(shape).reshape(3, -1).T * sp
    inside = np.zeros(len(idx), bool)
    for a, b, r in segments:
        a, b = np.asarray(a, float), np.asarray(b, float)
        t = np.clip((idx - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1)
        inside |= np.linalg.norm(idx - (a + t[:, None] * (b - a)), axis=1) <= r
    return inside.reshape(tuple(shape))


def y_tube(seed: int = 0, spacing: Sequence[float] = (1.0, 1.0, 1.0), noise: float = 0.1
           ) -> tuple[np.ndarray, np.ndarray, dict, list]:
    """A Y-shaped tube: image (100 on 20, Gaussian noise of ``noise`` x the contrast), the
    reference (the Y above its first axial slice of two components, from the top), a cylinder
    click in the trunk (voxel indices) and the Y's three capsules ``(a, b, radius)`` in mm (the
    trunk, then the branches).

    The trunk (radius 6 mm) runs down the third axis from the top face to its division at 40 %
    of the height; the branches leave it at 20-40 degrees on either side (the seed draws each
    angle and radius) and through the bottom face.
    """
    rng = np.random.default_rng(seed)
    sp = np.asarray(spacing, dtype=float)
    shape = tuple(int(round(f / s)) for f, s in zip(FOV_MM, sp))
    fork = np.array([FOV_MM[0] / 2, FOV_MM[1] / 2, 0.4 * FOV_MM[2]])
    segments = [(fork + [0, 0, FOV_MM[2]], fork, TRUNK_RADIUS)]
    for side in (-1, 1):
        angle = np.radians(rng.uniform(20, 40))
        down = fork[2] + 10  # (past the bottom face)
        end = fork + down * np.array([side * np.tan(angle), 0, -1])
        segments.append((fork, end, TRUNK_RADIUS * rng.uniform(0.7, 0.85)))
    y = _capsules(shape, sp, segments)
    image = np.where(y, 100.0, 20.0) + rng.normal(0, noise * 80.0, shape)
    k = next(k for k in range(shape[2] - 1, -1, -1) if ndimage.label(y[:, :, k])[1] > 1)
    reference = y & (np.indices(shape)[2] > k)
    # the click: the trunk's middle 60 % (of the part above the division), half its radius
    top, bottom = FOV_MM[2], fork[2]
    click = {"shape": "cylinder", "radius": 0.5 * TRUNK_RADIUS / sp[0],
             "axis_start": (np.r_[fork[:2], top - 0.2 * (top - bottom)] / sp).tolist(),
             "axis_end": (np.r_[fork[:2], bottom + 0.2 * (top - bottom)] / sp).tolist()}
    return image.astype(np.float32), reference, click, segments


def u_tube(gap: float = 16.0, seed: int = 0, radius: float = 5.0
           ) -> tuple[np.ndarray, dict]:
    """A U-shaped tube of two legs ``gap`` mm apart (1 mm voxels, 100 on 20, noise 8): the left
    leg leaves through the bottom face, the right one divides 34 mm up into two branches of 0.8 x
    its radius. Returns the image and a 5-point centerline click from the left leg over the bend
    into the right one (voxel indices, radius 2.5 mm)."""
    rng = np.random.default_rng(seed)
    shape = (64, 56, 80)
    xl, xr, top, fork_z = 32 - gap / 2, 32 + gap / 2, 56.0, 34.0
    segments = [((xl, 28, -10.0), (xl, 28, top), radius), ((xr, 28, fork_z), (xr, 28, top), radius)]
    bend = np.linspace(0, np.pi, 40)
    arc = np.stack([32 - gap / 2 * np.cos(bend), np.full_like(bend, 28.0),
                    top + gap / 2 * np.sin(bend)], 1)
    segments += [(a, b, radius) for a, b in zip(arc[:-1], arc[1:])]
    fork = np.array([xr, 28, fork_z])
    for side in (-1, 1):
        segments.append((fork, fork + 40 * np.array([0, side * np.tan(np.radians(35)), -1]),
                         0.8 * radius))
    u = _capsules(shape, (1, 1, 1), segments)
    image = np.where(u, 100.0, 20.0) + rng.normal(0, 8, shape)
    points = [[xl, 28, 20.0], [xl, 28, 50.0], [32, 28, top + gap / 2], [xr, 28, 50.0],
              [xr, 28, fork_z + 8]]
    return image.astype(np.float32), {"shape": "cylinder",
                                      "centerline": [p + [2.5] for p in points]}


def _phantoms() -> list[tuple[str, np.ndarray, np.ndarray, dict, tuple]]:
    out = []
    for seed in range(4):
        out.append((f"Y {seed}, 1 mm", *y_tube(seed)[:3], (1.0, 1.0, 1.0)))
    for seed in range(2):
        sp = (0.6, 0.6, 2.5)
        out.append((f"Y {seed}, 0.6 x 0.6 x 2.5 mm", *y_tube(seed, sp)[:3], sp))
    # tubes that do not divide, whose noisy tapering ends hold specks: bench_tubes.py's S6
    # vessels from their 5-point centreline (SNR -1 dB)
    from bench_tubes import cases
    from segsnake.phantoms import make_phantom

    for case in cases():
        if case["id"].startswith("s6"):
            ph = make_phantom(case["kind"], seed=case["seed"], **case["options"])
            click = ph.params["geometry"]["click"]
            rows = [list(p) + [r] for p, r in zip(click["points_voxels"], click["radius_voxels"])]
            out.append((case["id"].replace("_", ", ").replace("x", " x ") + " mm, centreline",
                        np.asarray(ph.image, np.float32), ph.truth,
                        {"shape": "cylinder", "centerline": rows}, tuple(ph.spacing)))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--no-real", action="store_true", help="the phantoms only")
    ap.add_argument("--settings", nargs="+", metavar="FRACTION,RADII",
                    help="these (branch_fraction, cut_radii) instead of SETTINGS")
    args = ap.parse_args()
    settings = [tuple(map(float, x.split(","))) for x in args.settings] if args.settings \
        else SETTINGS
    runs = _phantoms()
    if not args.no_real:
        from bench_real import clicks
        from fetch import load_cases
        from segsnake.io import load_volume

        case = next(c for c in load_cases() if c["name"] == "lung2-trachea")
        ct = load_volume(case["image"])
        truth = np.asarray(load_volume(case["truth"]).data) > 0
        image = np.asarray(ct.data, dtype=np.float32)
        for label, init in clicks(case, 5):
            runs.append((f"trachea, {label}", image, truth, init, tuple(ct.spacing)))
    print("| branch_fraction, cut_radii | " + " | ".join(r[0] for r in runs) + " | time (s) |")
    print("|---" * (len(runs) + 2) + "|")
    for fraction, radii in settings:
        params = RegionParams(branch_fraction=fraction, cut_radii=radii)
        t0, cells = time.perf_counter(), []
        for _, image, ref, click, sp in runs:
            res = segment_volume(image, sp, SegmentConfig.from_mapping(click),
                                 region_params=params)
            cells.append(f"{dice(res.mask, ref):.3f}")
        print(f"| {fraction:g}, {radii:g} | " + " | ".join(cells)
              + f" | {time.perf_counter() - t0:.0f} |", flush=True)


if __name__ == "__main__":
    main()
