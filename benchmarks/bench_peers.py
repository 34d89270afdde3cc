"""Benchmark: segsnake against other tools on the same phantoms (design.md, "Peers to measure against").

Methods, all started from the phantom's suggested initialization (the same sphere/ellipsoid or
cylinder that segsnake gets, rasterized on the grid as the initial region):

``segsnake``
    :func:`segsnake.pipeline.segment_volume` with the options the issue-4 tests use: the default
    ``edge`` feature for filled objects, ``surface`` for the hollow cylinder, ``surface`` with
    ``polarity: dark`` for the T1 brain (its dark CSF sheet) and ``surface`` for the PD brain.
``skimage MCV``
    ``skimage.segmentation.morphological_chan_vese`` (3D) on the image rescaled to [0, 1]
    (1st-99th percentile), ``lambda1 = lambda2 = 1``, ``smoothing`` from :data:`PARAMS`; on the
    hollow cylinder it starts from skimage's checkerboard level set (the initial cylinder lies in
    the dark lumen, as dark as the outside: no two-phase start).
``skimage MGAC``
    ``morphological_geodesic_active_contour`` on ``inverse_gaussian_gradient(image01, alpha=100,
    sigma)``, ``balloon=1`` (expand), ``sigma``, ``smoothing`` and ``threshold`` (skimage's
    ``"auto"``, the 40th percentile of the edge-stopping image, or a number) from :data:`PARAMS`.
``SimpleITK GAC``
    ``GeodesicActiveContourLevelSetImageFilter`` (propagation 1, curvature and advection from
    :data:`PARAMS`) on the speed image ``Sigmoid(GradientMagnitudeRecursiveGaussian(image,
    sigma))`` with the ITK Software Guide's ``alpha = -(K1 - K2) / 6``, ``beta = (K1 + K2) / 2``:
    K1 (edge level) is Otsu's threshold of the gradient magnitude, K2 (inside level) its median
    over the initial region. Initial level set: signed distance of the initial region (mm,
    negative inside). Voxel spacing is respected (the morphological snakes work in voxel units).
``Otsu + morphology``
    Gaussian pre-smoothing (``sigma`` voxels), ``threshold_otsu``, binary opening, the connected
    component containing the initialization's centre (the largest one if the centre is not in
    the foreground), binary closing and hole filling (6-connectivity, a 3x3x3 cross as the
    structuring element).

Iterations (none of these has a documented stopping rule that works on noisy data):

- morphological snakes run until the level set repeats one of its last 8 states (their
  evolution is deterministic, so it then cycles forever; on noisy data they end in a 2- or
  4-cycle that flips a few hundred voxels) or a cap of :data:`MORPH_CAP` iterations;
- the SimpleITK filter runs in chunks of :data:`ITK_CHUNK` iterations, each restarted from the
  signed distance of the previous result, until the region changes by less than 0.2 % of its
  volume between chunks (its RMS change stays around 0.05 on noisy data, far above any
  useful ``MaximumRMSError``) or :data:`ITK_CAP` iterations.

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
from typing import Any, Callable

import numpy as np
from scipy import ndimage
from machine import machine_info, report  # noqa: E402 (benchmarks/ is on sys.path)

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
MORPH_CAP = 300
ITK_CHUNK = 50
ITK_CAP = 400


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


class _Cycle(Exception):
    """Raised from the morphological snakes' callback to stop them once they cycle."""


def _run_morph(fn: Callable, *args: Any, **kwargs: Any) -> tuple[np.ndarray, int, str]:
    """Run a morphological snake until its level set repeats a recent state, or MORPH_CAP."""
    recent: list[bytes] = []
    state = {"n": 0, "u": None}

    def callback(u: np.ndarray) -> None:
        state["n"] += 1
        key = np.packbits(u.astype(bool)).tobytes()
        if key in recent:
            state["u"] = u.astype(bool)
            raise _Cycle
        recent.append(key)
        del recent[:-8]

    try:
        u = fn(*args, num_iter=MORPH_CAP, iter_callback=callback, **kwargs)
        return u.astype(bool), state["n"], "cap"
    except _Cycle:
        return state["u"], state["n"], "cycle"


def _unit(image: np.ndarray) -> np.ndarray:
    lo, hi = np.percentile(image, [1, 99])
    return np.clip((image - lo) / max(hi - lo, 1e-12), 0.0, 1.0).astype(np.float32)


def _component(mask: np.ndarray, center: tuple[int, ...]) -> np.ndarray:
    """The connected component containing ``center`` (the largest one if it is background)."""
    lab, n = ndimage.label(mask)
    if n == 0:
        return mask
    k = lab[center]
    if k == 0:
        k = int(np.argmax(np.bincount(lab.ravel())[1:])) + 1
    return lab == k


def _largest(mask: np.ndarray) -> np.ndarray:
    lab, n = ndimage.label(mask)
    if n == 0:
        return mask
    return lab == int(np.argmax(np.bincount(lab.ravel())[1:])) + 1


def _region_post(mask: np.ndarray, center: tuple[int, ...]) -> np.ndarray:
    return ndimage.binary_fill_holes(_component(mask, center))


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
    center = tuple(int(round(c)) for c in np.argwhere(init).mean(axis=0))
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
        from skimage.segmentation import checkerboard_level_set, morphological_chan_vese

        u01 = _unit(img)
        # A two-phase model needs a start whose two phases differ: the initial cylinder lies
        # in the dark lumen, as dark as the outside, so the sheet starts from skimage's
        # checkerboard (5 voxel squares) instead.
        start = checkerboard_level_set(img.shape, 5) if sheet else init
        u, n, stop = _run_morph(morphological_chan_vese, u01, init_level_set=start,
                                smoothing=params["smoothing"], lambda1=1, lambda2=1)
        notes.update(iterations=n, stop=stop)
        if sheet:
            # The bright phase is the wall (the initial region, in the lumen, is the dark one).
            wall = u if u01[u].mean() > u01[~u].mean() else ~u
            return _wall_to_region(_largest(wall), axis, sp), notes
        return _region_post(u, center), notes

    if method == "skimage MGAC":
        from skimage.segmentation import (inverse_gaussian_gradient,
                                          morphological_geodesic_active_contour)

        g = inverse_gaussian_gradient(_unit(img), alpha=100.0, sigma=params["sigma"])
        u, n, stop = _run_morph(morphological_geodesic_active_contour, g, init_level_set=init,
                                smoothing=params["smoothing"], threshold=params["threshold"],
                                balloon=1)
        notes.update(iterations=n, stop=stop)
        return _region_post(u, center), notes

    if method == "SimpleITK GAC":
        import SimpleITK as sitk
        from skimage.filters import threshold_otsu

        # SimpleITK's axes are the numpy axes reversed; so is the spacing.
        im = sitk.GetImageFromArray(img)
        im.SetSpacing(sp[::-1])
        gm = sitk.GradientMagnitudeRecursiveGaussian(im, float(params["sigma"]))
        garr = sitk.GetArrayViewFromImage(gm)
        k1 = float(threshold_otsu(garr))
        k2 = float(np.median(garr[init]))
        speed = sitk.Sigmoid(gm, -(k1 - k2) / 6.0, (k1 + k2) / 2.0, 1.0, 0.0)
        notes["K1, K2"] = [round(k1, 3), round(k2, 3)]
        mask, done, stop = init, 0, "cap"
        while done < ITK_CAP:
            m = sitk.GetImageFromArray(mask.astype(np.uint8))
            m.CopyInformation(im)
            ls = sitk.SignedMaurerDistanceMap(m, insideIsPositive=False, squaredDistance=False,
                                              useImageSpacing=True)
            f = sitk.GeodesicActiveContourLevelSetImageFilter()
            f.SetPropagationScaling(1.0)
            f.SetCurvatureScaling(float(params["curvature"]))
            f.SetAdvectionScaling(float(params["advection"]))
            f.SetMaximumRMSError(0.01)
            f.SetNumberOfIterations(ITK_CHUNK)
            new = sitk.GetArrayFromImage(f.Execute(ls, speed)) < 0
            done += int(f.GetElapsedIterations())
            change = np.count_nonzero(new ^ mask) / max(np.count_nonzero(new), 1)
            mask = new
            if change < 0.002 or f.GetElapsedIterations() < ITK_CHUNK:
                stop = "converged"
                break
        notes.update(iterations=done, stop=stop)
        return _region_post(mask, center), notes

    if method == "Otsu + morphology":
        from skimage.filters import threshold_otsu

        sm = ndimage.gaussian_filter(img, params["sigma"]) if params["sigma"] > 0 else img
        fg = sm > threshold_otsu(sm)
        cross = ndimage.generate_binary_structure(3, 1)
        if sheet:
            return _wall_to_region(_largest(fg), axis, sp), notes
        fg = ndimage.binary_opening(fg, cross)
        fg = _component(fg, center)
        fg = ndimage.binary_closing(fg, cross, border_value=0)
        return ndimage.binary_fill_holes(fg), notes

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
    m = info["machine"]
    lines = [f"Machine: {m['nproc']} cores, {m['cpu']}, Python {m['python']}, numpy {m['numpy']}, "
             f"scipy {m['scipy']}, scikit-image {m['skimage']}, SimpleITK {m['SimpleITK']} "
             f"({m['itk_threads']} ITK threads); segsnake at {m.get('commit', '?')}"
             + (f" with local changes in {', '.join(m['segsnake_modified'])}"
                if m.get("segsnake_modified") else "") + ".",
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
