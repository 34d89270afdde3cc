"""Benchmark: edge map + lookup volume on a 181 x 217 x 181 float32 volume (issue 3).

Goal: under 4 s and under 2 GB peak memory on the 2-core reference machine.

The volume is a brain-like phantom generated here with a fixed seed (1 mm voxels): an
ellipsoidal head (scalp, dark skull, CSF) around a folded "brain" with a grey/white contrast,
a smooth bias field and Gaussian noise. Each mode runs in its own child process so that its
peak resident memory (``ru_maxrss``) is its own; the increase over the resident size just
before the measured work is reported too (the phantom itself is 28 MB).

Usage::

    .venv/bin/python benchmarks/bench_features.py            # both modes, markdown table
    .venv/bin/python benchmarks/bench_features.py --json     # machine-readable
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np
from machine import machine_info  # noqa: E402 (benchmarks/ is on sys.path)

SHAPE = (181, 217, 181)
SPACING = (1.0, 1.0, 1.0)


def phantom(seed: int = 0) -> np.ndarray:
    """Brain-like float32 phantom (values ~0..1, noise std 0.03)."""
    rng = np.random.default_rng(seed)
    c = (np.asarray(SHAPE) - 1) / 2.0
    x = (np.arange(SHAPE[0], dtype=np.float32) - c[0])[:, None, None]
    y = (np.arange(SHAPE[1], dtype=np.float32) - c[1])[None, :, None]
    z = (np.arange(SHAPE[2], dtype=np.float32) - c[2])[None, None, :]
    # normalised ellipsoidal radius of the head (1 on its surface)
    rho = np.sqrt((x / 80.0) ** 2 + (y / 100.0) ** 2 + (z / 82.0) ** 2)
    r_mm = rho * 85.0  # roughly mm
    img = np.zeros(SHAPE, np.float32)
    img[r_mm < 85.0] = 0.75  # scalp
    img[r_mm < 80.0] = 0.08  # skull
    img[r_mm < 74.0] = 0.25  # CSF
    # folded brain: the radius of the grey-matter surface is modulated by a few harmonics
    az = np.arctan2(y, x)
    el = np.arctan2(z, np.sqrt(x * x + y * y))
    fold = 2.0 * np.sin(7 * az) * np.cos(5 * el) + 1.5 * np.sin(11 * el + 3 * az)
    img[r_mm < 71.0 + fold] = 0.55  # grey matter
    img[r_mm < 62.0 + 1.5 * fold] = 0.80  # white matter
    bias = 1.0 + 0.1 * (x / 90.0) - 0.08 * (z / 90.0) ** 2
    img *= bias.astype(np.float32)
    img += rng.normal(0.0, 0.03, SHAPE).astype(np.float32)
    return img


def _rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def run_one(mode: str, scale_mm: float) -> dict:
    from segsnake.features import edge_map
    from segsnake.lookup import Lookup

    img = phantom()
    base = _rss_mb()
    t0 = time.perf_counter()
    em = edge_map(img, SPACING, mode=mode, scale_mm=scale_mm)
    t1 = time.perf_counter()
    lk = Lookup.from_field(em.f, SPACING)
    t2 = time.perf_counter()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    # 10^4 points on an ellipsoid through the brain surface, the snake's typical query
    uu, vv = np.meshgrid(np.linspace(0, 2 * np.pi, 100, endpoint=False),
                         np.linspace(0.02, np.pi - 0.02, 100), indexing="ij")
    d = np.stack([70 * np.cos(uu) * np.sin(vv), 88 * np.sin(uu) * np.sin(vv), 70 * np.cos(vv)], -1)
    pts = d.reshape(-1, 3) + (np.asarray(SHAPE) - 1) / 2.0
    lk.sample(pts)
    best = np.inf
    for _ in range(20):
        s0 = time.perf_counter()
        lk.sample(pts)
        best = min(best, time.perf_counter() - s0)
    return {
        "mode": mode,
        "scale_mm": scale_mm,
        "edge_map_s": t1 - t0,
        "lookup_s": t2 - t1,
        "total_s": t2 - t0,
        "peak_rss_mb": peak,
        "rss_before_mb": base,
        "peak_increase_mb": peak - base,
        "edge_voxels": int(em.mask.sum()),
        "levels": [float(v) for v in em.levels] if em.levels else None,
        "sample_1e4_ms": best * 1e3,
    }


def machine() -> dict:
    """See :func:`machine.machine_info`."""
    return machine_info()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mode", choices=["edge", "surface"], help="run one mode in this process")
    ap.add_argument("--scale", type=float, default=1.5, help="detector scale in mm (default 1.5)")
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    args = ap.parse_args(argv)
    if args.mode:
        print(json.dumps(run_one(args.mode, args.scale)))
        return 0
    results = []
    for mode in ("edge", "surface"):
        out = subprocess.run([sys.executable, __file__, "--mode", mode, "--scale", str(args.scale)],
                             check=True, capture_output=True, text=True)
        results.append(json.loads(out.stdout.strip().splitlines()[-1]))
    info = {"machine": machine(), "shape": SHAPE, "results": results}
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    m = info["machine"]
    print(f"machine: {m['nproc']} cores, {m['cpu']}, Python {m['python']}, numpy {m['numpy']}, "
          f"scipy {m['scipy']}")
    print("| mode | scale | edge map (s) | lookup (s) | total (s) | peak RSS (MB) | "
          "increase (MB) | edge voxels | sample 1e4 pts (ms) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in results:
        print(f"| {r['mode']} | {r['scale_mm']:g} mm | {r['edge_map_s']:.2f} | "
              f"{r['lookup_s']:.2f} | {r['total_s']:.2f} | {r['peak_rss_mb']:.0f} | "
              f"{r['peak_increase_mb']:.0f} | {r['edge_voxels']} | {r['sample_1e4_ms']:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
