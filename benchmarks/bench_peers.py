"""Benchmark: segsnake against other tools on the same phantoms (design.md, "Peers to measure against").

Methods, all started from the phantom's suggested initialization (the same sphere/ellipsoid or
cylinder that segsnake gets, rasterized on the grid as the initial region):

``segsnake``
    :func:`segsnake.pipeline.segment_volume` with the options the issue-4 tests use: the default
    ``edge`` feature for filled objects, ``surface`` for the hollow cylinder, ``surface`` with
    ``polarity: dark`` for the T1 brain (its dark CSF sheet) and ``surface`` for the PD brain.
``skimage MCV``, ``skimage MGAC``, ``SimpleITK GAC``, ``Otsu + morphology``
    :mod:`peer_methods` (shared with ``bench_real.py``), which also gives their stopping rules;
    on the hollow cylinder MCV starts from skimage's checkerboard level set (the initial
    cylinder lies in the dark lumen, as dark as the outside: no two-phase start).

Every region result is post-processed alike: the connected component that contains the
initialization's centre (the largest if it does not), holes filled.

The hollow cylinder (open ends; truth = the region inside the wall's mid-surface) is a sheet,
not a filled object. Methods that return the bright phase (Otsu, MCV: its phase that is
brighter on average) give the wall; it is turned into the truth's definition by filling each
slice perpendicular to the cylinder's axis (holes = the lumen) and adding the wall voxels that
are closer to the lumen than to the outside (the inner half of the wall, i.e. up to the
mid-surface). MGAC and SimpleITK GAC grow a region from the initial cylinder inside the lumen;
it is reported as it comes (it stops at the inner face of the wall, about half a wall
thickness inside the mid-surface, and can leak through the open ends).

Parameters (:data:`PARAMS`) were chosen with ``--tune``: a small grid per method, mean Dice
over tuning volumes built with another seed (seed 1) than the reported ones (seed 0).

Usage::

    .venv/bin/python benchmarks/bench_peers.py                   # all families, markdown out
    .venv/bin/python benchmarks/bench_peers.py --families ball cylinder --json out.json
    .venv/bin/python benchmarks/bench_peers.py --tune             # the parameter sweep
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import statistics
import subprocess
import sys
import time
from typing import Any

import numpy as np
from scipy import ndimage
from machine import machine_info, machine_line, report  # noqa: E402 (benchmarks/ is on sys.path)
from peer_methods import (init_center, largest, mcv, mgac, otsu_morphology,  # noqa: E402
                          region_post, sitk_gac, unit)

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
if ROOT not in sys.path:  # run as a script from anywhere: import the checkout's segsnake
    sys.path.insert(0, ROOT)

METHODS = ("segsnake", "skimage MCV", "skimage MGAC", "SimpleITK GAC", "Otsu + morphology")

#: Method parameters (chosen with --tune on seed-1 volumes; see the module docstring).
PARAMS: dict[str, dict[str, Any]] = {
    "skimage MCV": {"smoothing": 1},
    "skimage MGAC": {"sigma": 1.0, "smoothing": 1, "threshold": "auto"},
    "SimpleITK GAC": {"sigma": 1.0, "curvature": 1.0, "advection": 1.0},
    "Otsu + morphology": {"sigma": 1.0},
}
#: Grids searched by --tune.
TUNE_GRID: dict[str, dict[str, list]] = {
    "skimage MCV": {"smoothing": [1, 2, 3]},
    "skimage MGAC": {"sigma": [1.0, 2.0], "smoothing": [1, 2], "threshold": ["auto", 0.5]},
    "SimpleITK GAC": {"sigma": [1.0, 2.0], "curvature": [0.5, 1.0, 2.0], "advection": [1.0]},
    "Otsu + morphology": {"sigma": [0.0, 1.0]},
}


# ------------------------------------------------------------------------------------------
# Volumes
# ------------------------------------------------------------------------------------------


def volumes(families: list[str]) -> list[dict]:
    """The benchmark volumes: name, family, phantom kind and options, segsnake options."""
    out = []
    for fam in ("ball", "ellipsoid", "blob"):
        if fam not in families:
            continue
        for noise, spacing in itertools.product((0.1, 0.3), ((1.0, 1.0, 1.0), (1.0, 1.0, 2.0))):
            sp = "1x1x2 mm" if spacing[2] == 2.0 else "1 mm"
            out.append({"name": f"{fam}, noise {noise:g}, {sp}", "family": fam, "kind": fam,
                        "options": {"noise": noise, "spacing": spacing}, "segsnake": {}})
    if "cylinder" in families:
        for std in (0.0, 50.0, 90.0):
            out.append({"name": f"hollow cylinder, std {std:g}", "family": "cylinder",
                        "kind": "hollow-cylinder", "options": {"std": std},
                        "segsnake": {"feature": "surface"}})
    if "brain" in families:
        for contrast, extra in (("t1", {"feature": "surface", "polarity": "dark"}),
                                ("pd", {"feature": "surface"})):
            out.append({"name": f"brain {contrast.upper()}, 2 mm", "family": "brain",
                        "kind": "brain",
                        "options": {"contrast": contrast, "noise": 0.03, "shape": (96, 112, 96),
                                    "spacing": (2.0, 2.0, 2.0)},
                        "segsnake": extra})
    return out


FAMILIES = ("ball", "ellipsoid", "blob", "cylinder", "brain")


# ------------------------------------------------------------------------------------------
# Methods
# ------------------------------------------------------------------------------------------


def _wall_to_region(wall: np.ndarray, axis: int, spacing) -> np.ndarray:
    """Wall mask of an open hollow cylinder -> region inside the wall's mid-surface.

    Fill per slice perpendicular to ``axis`` (a structuring element that connects only within
    the slice), then keep the wall voxels closer to the lumen than to the outside.
    """
    structure = np.zeros((3, 3, 3), bool)
    sl = [slice(None)] * 3
    sl[axis] = 1
    structure[tuple(sl)] = ndimage.generate_binary_structure(2, 1)
    filled = ndimage.binary_fill_holes(wall, structure=structure)
    lumen = filled & ~wall
    if not lumen.any():
        return lumen
    d_lumen = ndimage.distance_transform_edt(~lumen, sampling=spacing)
    d_out = ndimage.distance_transform_edt(filled, sampling=spacing)
    return lumen | (wall & filled & (d_lumen <= d_out))


def run_method(method: str, vol: dict, ph, init: np.ndarray, params: dict) -> tuple[np.ndarray, dict]:
    """Segment ``ph.image`` with one method; returns the mask and notes (iterations, stop)."""
    img = ph.image.astype(np.float32)
    sp = tuple(float(s) for s in ph.spacing)
    sheet = vol["family"] == "cylinder"
    center = init_center(init)
    axis = None
    if ph.init["shape"] == "cylinder":
        axis = int(np.argmax(np.abs(np.subtract(ph.init["axis_end"], ph.init["axis_start"]))))
    notes: dict[str, Any] = {}

    if method == "segsnake":
        from segsnake.config import SegmentConfig
        from segsnake.pipeline import segment_volume

        if ph.init["shape"] == "sphere":
            geometry = {"shape": "sphere", "center": ph.init["center"], "radii": ph.init["radii"]}
        else:
            geometry = dict(ph.init)
        res = segment_volume(img, sp, SegmentConfig.from_mapping({**vol["segsnake"], **geometry}))
        notes["iterations"] = res.iterations
        return res.mask, notes

    if method == "skimage MCV":
        from skimage.segmentation import checkerboard_level_set

        # A two-phase model needs a start whose two phases differ: the initial cylinder lies
        # in the dark lumen, as dark as the outside, so the sheet starts from skimage's
        # checkerboard (5 voxel squares) instead.
        start = checkerboard_level_set(img.shape, 5) if sheet else init
        u, notes = mcv(img, start, params)
        if sheet:
            # The bright phase is the wall (the initial region, in the lumen, is the dark one).
            u01 = unit(img)
            wall = u if u01[u].mean() > u01[~u].mean() else ~u
            return _wall_to_region(largest(wall), axis, sp), notes
        return region_post(u, center), notes

    if method == "skimage MGAC":
        u, notes = mgac(img, init, params)
        return region_post(u, center), notes

    if method == "SimpleITK GAC":
        mask, notes = sitk_gac(img, sp, init, params)
        return region_post(mask, center), notes

    if method == "Otsu + morphology":
        if sheet:
            from skimage.filters import threshold_otsu

            sm = ndimage.gaussian_filter(img, params["sigma"]) if params["sigma"] > 0 else img
            return _wall_to_region(largest(sm > threshold_otsu(sm)), axis, sp), notes
        return otsu_morphology(img, center, params), notes

    raise ValueError(f"unknown method {method!r}")


# ------------------------------------------------------------------------------------------
# Children and the report
# ------------------------------------------------------------------------------------------


def child_volume(vol: dict, methods: list[str], seed: int, params: dict) -> dict:
    """Build one phantom, run every method on it, return metrics and wall times."""
    from segsnake.metrics import evaluate_masks
    from segsnake.phantoms import make_phantom, rasterize_init

    ph = make_phantom(vol["kind"], seed=seed, **vol["options"])
    init = rasterize_init(ph.params["init_mm"], ph.image.shape, ph.spacing)
    out = {"volume": vol["name"], "family": vol["family"], "shape": list(ph.image.shape),
           "spacing": list(ph.spacing), "init": evaluate_masks(init, ph.truth, ph.spacing),
           "results": []}
    for method in methods:
        row: dict[str, Any] = {"method": method, "params": params.get(method, {})}
        t0 = time.perf_counter()
        try:
            mask, notes = run_method(method, vol, ph, init, params.get(method, {}))
        except Exception as exc:  # noqa: BLE001 - a failure is a result
            row.update(wall_s=time.perf_counter() - t0, error=f"{type(exc).__name__}: {exc}")
        else:
            row["wall_s"] = time.perf_counter() - t0
            row["notes"] = notes
            m = evaluate_masks(mask, ph.truth, ph.spacing)
            row["metrics"] = {k: m[k] for k in ("dice", "jaccard", "hausdorff95_mm", "assd_mm",
                                                "volume_difference_rel")}
        out["results"].append(row)
    return out


def _run_child(payload: dict) -> dict:
    proc = subprocess.run([sys.executable, os.path.abspath(__file__), "--child",
                           json.dumps(payload)], capture_output=True, text=True)
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["(no output)"]
        return {"volume": payload["vol"]["name"], "family": payload["vol"]["family"],
                "error": f"child exited {proc.returncode}: {tail[0]}", "results": []}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def machine() -> dict:
    """See :func:`machine.machine_info`."""
    return machine_info()


FAMILY_TITLES = {"ball": "Ball (64^3 at 1 mm, 64 x 64 x 32 at 1 x 1 x 2 mm)",
                 "ellipsoid": "Ellipsoid (64^3 at 1 mm, 64 x 64 x 32 at 1 x 1 x 2 mm)",
                 "blob": "Blob (64^3 at 1 mm, 64 x 64 x 32 at 1 x 1 x 2 mm)",
                 "cylinder": "Hollow cylinder (128^3, Table 7.2; truth: inside the mid-surface)",
                 "brain": "Brain (96 x 112 x 96 at 2 mm; truth: inside the pial surface)"}


def markdown(info: dict) -> str:
    lines = [machine_line(info["machine"]) + ".",
             f"Command: `{info['command']}` (total {info['total_s'] / 60:.1f} min).", ""]
    for fam in FAMILIES:
        rows = [v for v in info["volumes"] if v["family"] == fam]
        if not rows:
            continue
        lines.append(f"**{FAMILY_TITLES[fam]}**")
        lines.append("")
        lines.append("| volume | method | Dice | Jaccard | HD95 (mm) | ASSD (mm) | time (s) | notes |")
        lines.append("|---|---|---|---|---|---|---|---|")
        for v in rows:
            if v.get("error"):
                lines.append(f"| {v['volume']} | all | failed: {v['error']} | | | | | |")
            init = v.get("init")
            if init:
                lines.append(f"| {v['volume']} | (initialization) | {init['dice']:.3f} | "
                             f"{init['jaccard']:.3f} | {init['hausdorff95_mm']:.2f} | "
                             f"{init['assd_mm']:.2f} | | |")
            for r in v["results"]:
                if "error" in r:
                    lines.append(f"| {v['volume']} | {r['method']} | failed | | | | "
                                 f"{r['wall_s']:.2f} | {r['error'][:90]} |")
                    continue
                mt = r["metrics"]
                notes = r.get("notes") or {}
                note = ", ".join(f"{k} {notes[k]}" for k in ("iterations", "stop") if k in notes)
                best = max(x["metrics"]["dice"] for x in v["results"] if "metrics" in x)
                dice = f"**{mt['dice']:.3f}**" if mt["dice"] == best else f"{mt['dice']:.3f}"
                lines.append(f"| {v['volume']} | {r['method']} | {dice} | {mt['jaccard']:.3f} | "
                             f"{mt['hausdorff95_mm']:.2f} | {mt['assd_mm']:.2f} | "
                             f"{r['wall_s']:.2f} | {note} |")
        lines.append("")
    # Summary: mean Dice and total time per method and family.
    lines.append("Mean Dice / total seconds per family:")
    lines.append("")
    methods = [mm for mm in METHODS if any(r["method"] == mm for v in info["volumes"]
                                           for r in v["results"])]
    lines.append("| family | " + " | ".join(methods) + " |")
    lines.append("|---|" + "---|" * len(methods))
    for fam in FAMILIES:
        rows = [v for v in info["volumes"] if v["family"] == fam]
        if not rows:
            continue
        cells = []
        for mm in methods:
            rs = [r for v in rows for r in v["results"] if r["method"] == mm]
            dice = [r["metrics"]["dice"] if "metrics" in r else 0.0 for r in rs]
            cells.append(f"{statistics.mean(dice):.3f} / {sum(r['wall_s'] for r in rs):.1f}"
                         if rs else "-")
        lines.append(f"| {fam} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def tune(families: list[str]) -> int:
    """Grid search of each peer's parameters on seed-1 volumes; prints mean Dice per setting."""
    vols = [v for v in volumes(families)
            if "noise 0.1" not in v["name"] and "std 0" not in v["name"]]
    for method, grid in TUNE_GRID.items():
        keys = list(grid)
        scores = {}
        for values in itertools.product(*(grid[k] for k in keys)):
            p = dict(zip(keys, values))
            dice, secs = [], 0.0
            for vol in vols:
                res = _run_child({"vol": vol, "methods": [method], "seed": 1,
                                  "params": {method: p}})
                for r in res["results"]:
                    dice.append(r["metrics"]["dice"] if "metrics" in r else 0.0)
                    secs += r["wall_s"]
            scores[json.dumps(p)] = (statistics.mean(dice) if dice else 0.0, secs, dice)
            print(f"{method} {p}: mean Dice {scores[json.dumps(p)][0]:.4f} ({secs:.1f} s) "
                  f"{[round(d, 3) for d in dice]}", flush=True)
        best = max(scores, key=lambda k: scores[k][0])
        print(f"-> {method}: {best}", flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--families", nargs="+", choices=FAMILIES, default=list(FAMILIES))
    ap.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS))
    ap.add_argument("--seed", type=int, default=0, help="phantom seed (default 0)")
    ap.add_argument("--json", metavar="PATH", help="also write the raw numbers here")
    ap.add_argument("--tune", action="store_true", help="run the parameter sweep (seed 1)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.child:
        p = json.loads(args.child)
        print(json.dumps(child_volume(p["vol"], p["methods"], p["seed"], p["params"])))
        return 0
    if args.tune:
        return tune(args.families)

    t0 = time.perf_counter()
    exe = sys.executable
    info: dict[str, Any] = {"machine": machine(), "params": PARAMS,
                            "command": " ".join([os.path.relpath(exe, ROOT)
                                                 if exe.startswith(ROOT) else exe,
                                                 os.path.relpath(__file__, ROOT), *sys.argv[1:]]),
                            "volumes": []}
    for vol in volumes(args.families):
        res = _run_child({"vol": vol, "methods": args.methods, "seed": args.seed,
                          "params": PARAMS})
        info["volumes"].append(res)
        brief = ", ".join(f"{r['method']} {r['metrics']['dice']:.3f}/{r['wall_s']:.1f}s"
                          if "metrics" in r else f"{r['method']} failed"
                          for r in res["results"])
        print(f"[bench_peers] {vol['name']}: {res.get('error', brief)}", file=sys.stderr,
              flush=True)
    info["total_s"] = time.perf_counter() - t0
    return report(info, args.json, markdown)


if __name__ == "__main__":
    sys.exit(main())
