"""Benchmark: segsnake and the tools users run, on public scans, from the same clicks.

The cases (public scans, references and clicks; ``benchmarks/real/README.md``) are built by
``benchmarks/real/fetch.py`` (``make bench-real-data``). Every tool starts from the same
initialization: the case's click (a sphere at the reference's deepest point with half its depth
as radius; a tube's axis shortened by 15 % at each end with half its radius) and ``--clicks N``
seeded perturbations of it (:func:`segsnake.perturb.perturb_init`: centre moved up to half the
radius, radius x0.6-1.4, axis tilted up to 10 degrees; seeds 1..N).

Tools (settings in :data:`PEER_PARAMS`, the reasons in the README):

``segsnake``
    the ``segsnake segment`` command with default options and the click (``--center/--radii``
    or ``--shape cylinder --axis-start/--axis-end/--radius``), on the whole image.
``segsnake, no click``
    the brain only: ``segsnake segment`` with no initialization at all.
``segsnake, centre only``
    the sphere cases: ``segsnake segment --center`` with the click's centre (and each perturbed
    click's) and no radius: the sphere comes from the image around it
    (:func:`segsnake.click.click_radius`).
``segsnake, centreline``
    the tube cases: ``segsnake segment --centerline`` with 5 points along the click's axis
    (:func:`centerline_click`: the reference's centroids in 5 of its axial slices evenly
    spaced between the click's ends, each with the click's radius), and each perturbed click's
    (the same points moved as the perturbation moves the click's axis): issue 16's "from a
    5-point centerline".
``segsnake, perfect edges``
    the ceiling of model and optimizer: the same command on the reference mask itself as the
    image, with the click and its default options: the region energy chooses M (the issue's
    ceiling is "with the M schedule choosing the resolution by itself"), and that run is
    reported with its M. A cylinder also runs on the fixed control grids of :data:`CEILING_M`
    (the full run), listed in the row's label for comparison.
``BET``, ``ROBEX``
    the brain only, whole-head tools that take no click: ``benchmarks/real/brain_tools.py``
    runs each in a virtual environment of its own, with its default settings.
``skimage MCV``, ``skimage MGAC``, ``SimpleITK GAC``, ``SimpleITK confidence connected``
    :mod:`peer_methods` from the click's rasterized sphere or cylinder, in an ITK-SNAP-style
    region of interest: the reference's bounding box grown by :data:`ROI_MARGIN_MM` on each
    side (segsnake gets the whole image). Their parameters were tuned with ``--tune`` on the
    ``tuning`` case (Colin27's left thalamus, which no table reports) and then frozen.

Every tool runs as its own process: wall time (whole command: start-up, loading, writing) and
peak resident memory are that process's (``os.wait4``). Dice, HD95 and ASSD are
:func:`segsnake.metrics.evaluate_masks` against the reference on the case's grid.

Usage::

    .venv/bin/python benchmarks/bench_real.py                 # everything (make bench-real)
    .venv/bin/python benchmarks/bench_real.py --quick         # segsnake + ceiling, click only
    .venv/bin/python benchmarks/bench_real.py --cases lung2-tumour --tools segsnake
    .venv/bin/python benchmarks/bench_real.py --tune          # the peers' parameter sweep
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from typing import Any

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
for _p in (os.path.join(HERE, "real"), HERE, ROOT):
    if _p not in sys.path:
        sys.path.insert(0, _p)

from machine import machine_info, machine_line, report  # noqa: E402

#: The whole-head case: BET and ROBEX run on it, the generic region growers do not.
BRAIN_CASE = "colin27-brain"
SEGSNAKE = "segsnake"
NO_CLICK = "segsnake, no click"
CENTRE_ONLY = "segsnake, centre only"
CEILING = "segsnake, perfect edges"
CENTRELINE = "segsnake, centreline"
#: ``segment --atlas`` (benchmarks/atlas_start.py's folder) from the click: the label under it
#: names the structure; the cerebellum, a set of lobules, is named as its set (once: no click).
ATLAS = "segsnake, atlas"
ATLAS_NAMES = {"colin27-cerebellum": "suit"}
BRAIN_TOOLS = ("BET", "ROBEX")
PEERS = ("skimage MCV", "skimage MGAC", "SimpleITK GAC", "SimpleITK confidence connected")
TOOLS = (SEGSNAKE, NO_CLICK, CENTRE_ONLY, CENTRELINE, CEILING, ATLAS, *BRAIN_TOOLS, *PEERS)
OURS = (SEGSNAKE, NO_CLICK, CENTRE_ONLY, CENTRELINE, CEILING, ATLAS)
#: Points of the tube cases' centreline click (issue 16's "5-point centerline").
CENTRELINE_POINTS = 5

#: Peer parameters, chosen by ``--tune`` on the tuning case (mean Dice over its click and
#: perturbed clicks) and frozen; the sweep's numbers are in docs/benchmarks.md.
PEER_PARAMS: dict[str, dict[str, Any]] = {
    "skimage MCV": {"smoothing": 1},
    "skimage MGAC": {"sigma": 1.0, "smoothing": 1, "threshold": 0.5},
    "SimpleITK GAC": {"sigma": 1.0, "curvature": 1.0, "advection": 1.0},
    "SimpleITK confidence connected": {"multiplier": 1.5, "iterations": 4},
}
TUNE_GRID: dict[str, dict[str, list]] = {
    "skimage MCV": {"smoothing": [1, 2, 3]},
    "skimage MGAC": {"sigma": [1.0, 2.0], "smoothing": [1], "threshold": ["auto", 0.5]},
    "SimpleITK GAC": {"sigma": [1.0, 2.0], "curvature": [0.5, 1.0, 2.0], "advection": [1.0]},
    "SimpleITK confidence connected": {"multiplier": [1.5, 2.0, 2.5, 3.0], "iterations": [1, 4]},
}
#: The peers' region of interest: the reference's bounding box grown by this much (mm), as an
#: ITK-SNAP user draws a box around the structure before running its snake.
ROI_MARGIN_MM = 20.0
#: Control grids (m1, m2) the perfect-edge ceiling runs; the first, segsnake's default (None:
#: the M schedule chooses), is the one reported.
CEILING_M = {"sphere": [None], "cylinder": [None, (8, 4), (12, 6), (16, 8)]}
#: Seconds before a tool's process is stopped and its run recorded as failed.
TIMEOUT_S = 1800.0
METRICS = ("dice", "jaccard", "hausdorff95_mm", "assd_mm")


# ------------------------------------------------------------------------------------------
# Clicks and files
# ------------------------------------------------------------------------------------------


def _spacing(path: str) -> np.ndarray:
    import nibabel as nib

    return np.asarray(nib.load(path).header.get_zooms()[:3], dtype=float)


def _load(path: str) -> np.ndarray:
    import nibabel as nib

    return np.asanyarray(nib.load(path).dataobj)


def clicks(case: dict, n: int) -> list[tuple[str, dict]]:
    """The case's click and ``n`` seeded perturbations of it (seeds 1..n)."""
    from segsnake.perturb import perturb_init

    sp = _spacing(case["truth"])
    return [("click", case["init"])] + [(f"perturbed {k}", perturb_init(case["init"], sp, seed=k))
                                        for k in range(1, n + 1)]


def centerline_click(click: dict, start: dict, truth: np.ndarray, sp: np.ndarray) -> dict:
    """A tube case's :data:`CENTRELINE_POINTS`-point centreline for the cylinder ``start``.

    The points are the reference's centroids in axial slices (array axis 2, as the tube cases'
    references run) evenly spaced between the ends of the case's ``click``, each with the
    click's radius; for a perturbed ``start`` they are moved as it moves the click's axis (its
    middle's shift, the rotation taking one axis to the other) and given its radius.
    """
    from scipy import ndimage

    a0, a1 = (np.asarray(click[k], dtype=float) * sp for k in ("axis_start", "axis_end"))
    b0, b1 = (np.asarray(start[k], dtype=float) * sp for k in ("axis_start", "axis_end"))
    ks = np.rint(np.linspace(a0[2], a1[2], CENTRELINE_POINTS) / sp[2]).astype(int)
    points = np.array([[*ndimage.center_of_mass(truth[:, :, k]), k] for k in ks]) * sp
    u, w = (a1 - a0) / np.linalg.norm(a1 - a0), (b1 - b0) / np.linalg.norm(b1 - b0)
    axis, c = np.cross(u, w), float(u @ w)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + k + k @ k / (1.0 + c)  # (Rodrigues: u to w; the tilts are < 90 degrees)
    moved = (points - 0.5 * (a0 + a1)) @ rot.T + 0.5 * (b0 + b1)
    return {"shape": "cylinder", "centerline": [[*np.round(q / sp, 3).tolist(),
                                                 float(start["radius"])] for q in moved]}


def init_args(init: dict | None, centerline_csv: str | None = None) -> list[str]:
    """``segsnake segment`` flags for an initialization (none: the image decides; a centreline
    is read from ``centerline_csv``, where :func:`run_segsnake` wrote it)."""
    if init is None:
        return []
    if "centerline" in init:
        return ["--shape", "cylinder", "--centerline", centerline_csv]
    if init["shape"] == "sphere":  # (no radii: the click alone)
        return ["--center", *map(str, init["center"]),
                *(["--radii", *map(str, init["radii"])] if init.get("radii") else [])]
    return ["--shape", "cylinder", "--axis-start", *map(str, init["axis_start"]),
            "--axis-end", *map(str, init["axis_end"]), "--radius", str(init["radius"])]


def init_mask(init: dict, shape, spacing) -> np.ndarray:
    """The initialization rasterized on the grid (what the region-based peers start from)."""
    from segsnake.config import SegmentConfig
    from segsnake.pipeline import initial_model
    from segsnake.rasterize import rasterize

    model = initial_model(SegmentConfig.from_mapping(dict(init)), spacing, shape)
    return rasterize(model, shape, spacing)


def roi(truth: np.ndarray, spacing) -> tuple[slice, ...]:
    """The reference's bounding box grown by :data:`ROI_MARGIN_MM`, clipped to the grid."""
    idx = np.argwhere(truth)
    pad = np.ceil(ROI_MARGIN_MM / np.asarray(spacing)).astype(int)
    lo = np.maximum(idx.min(axis=0) - pad, 0)
    hi = np.minimum(idx.max(axis=0) + pad + 1, truth.shape)
    return tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))


# ------------------------------------------------------------------------------------------
# Running the tools
# ------------------------------------------------------------------------------------------


def _segsnake_exe() -> str:
    exe = os.path.join(os.path.dirname(sys.executable), "segsnake")
    return exe if os.path.exists(exe) else shutil.which("segsnake") or "segsnake"


def run_segsnake(image: str, init: dict | None, tmp: str, extra: list[str] | None = None) -> dict:
    """``segsnake segment`` on ``image``: measured run, exit code, warnings, mask path."""
    from brain_tools import run_measured

    out = os.path.join(tmp, "seg")
    shutil.rmtree(out, ignore_errors=True)
    csv_path = os.path.join(tmp, "centerline.csv")
    if init is not None and "centerline" in init:  # (the CSV --centerline reads)
        with open(csv_path, "w") as fh:
            fh.write("x,y,z,radius\n" + "".join(",".join(map(str, q)) + "\n"
                                                for q in init["centerline"]))
    cmd = [_segsnake_exe(), "segment", image, "--out", out, "--quiet", "--json", "--overwrite",
           *init_args(init, csv_path), *(extra or [])]
    res = run_measured(cmd, timeout_s=TIMEOUT_S)
    mask = os.path.join(out, "mask.nii.gz")
    res["mask"] = mask if res["returncode"] == 0 and os.path.exists(mask) else None
    res["warnings"] = []
    if res["mask"]:
        with open(os.path.join(out, "snake.json")) as fh:
            saved = json.load(fh)
        res["warnings"] = saved["summary"].get("warnings", [])
        res["notes"] = {k: saved["settings"].get(k) for k in ("edge_support", "separation")}
        res["notes"]["quality"] = saved["summary"].get("quality")
        res["m"] = [saved["model"]["m1"], saved["model"]["m2"]]
    return res


def child_peer(payload: dict) -> None:
    """In a child process: one peer on the ROI of one case from one initialization."""
    import peer_methods as pm

    img = _load(payload["image"]).astype(np.float32)
    truth = _load(payload["truth"]) != 0
    sp = _spacing(payload["truth"])
    box = roi(truth, sp)
    start = init_mask(payload["init"], img.shape, sp)[box]
    if not start.any():
        raise SystemExit("the initialization does not meet the region of interest")
    sub = np.ascontiguousarray(img[box])
    method, params = payload["method"], payload["params"]
    if method == "skimage MCV":
        u, notes = pm.mcv(sub, start, params)
    elif method == "skimage MGAC":
        u, notes = pm.mgac(sub, start, params)
    elif method == "SimpleITK GAC":
        u, notes = pm.sitk_gac(sub, sp, start, params)
    elif method == "SimpleITK confidence connected":
        u, notes = pm.confidence_connected(sub, start, params)
    else:
        raise SystemExit(f"unknown peer {method!r}")
    full = np.zeros(img.shape, bool)
    full[box] = pm.region_post(u, pm.init_center(start))
    np.save(payload["out"], np.packbits(full))
    with open(payload["out"] + ".json", "w") as fh:
        json.dump(notes, fh)


def run_peer(method: str, case: dict, init: dict, params: dict, tmp: str) -> dict:
    """One peer in its own process; returns the measured run and the mask (or None)."""
    from brain_tools import run_measured

    out = os.path.join(tmp, "peer.npy")
    for p in (out, out + ".json"):
        if os.path.exists(p):
            os.remove(p)
    payload = {"method": method, "params": params, "init": init, "image": case["image"],
               "truth": case["truth"], "out": out}
    res = run_measured([sys.executable, os.path.abspath(__file__), "--child", json.dumps(payload)],
                       timeout_s=TIMEOUT_S)
    if res["returncode"] == 0 and os.path.exists(out):
        res["mask_array"] = np.load(out)
        with open(out + ".json") as fh:
            res["notes"] = json.load(fh)
    return res


def _score(res: dict, truth: np.ndarray, sp, mask: np.ndarray | None) -> dict:
    """The row of one run: metrics (or the error), time, memory, exit code, warnings."""
    from segsnake.metrics import evaluate_masks

    row = {k: res.get(k) for k in ("wall_s", "peak_rss_mb", "returncode", "timed_out", "warnings",
                                   "notes")}
    if mask is None:
        tail = (res.get("error") or res.get("stderr_tail") or "").strip().splitlines()[-1:]
        row["error"] = (f"timed out after {TIMEOUT_S:g} s" if res.get("timed_out")
                        else tail[0] if tail else f"exit {res.get('returncode')}")
        return row
    m = evaluate_masks(mask, truth, sp)
    row.update({k: m[k] for k in METRICS})
    return row


def _mask_from(res: dict, shape) -> np.ndarray | None:
    if res.get("mask"):
        return _load(res["mask"]) != 0
    if res.get("mask_array") is not None:
        return np.unpackbits(res["mask_array"])[: int(np.prod(shape))].reshape(shape).astype(bool)
    return None


def run_case(case: dict, tools: list[str], n_clicks: int, quick: bool, qc_dir: str | None,
             params: dict, keep: str | None = None) -> dict:
    """Every tool on one case, from the click and its perturbations (``keep``: copy each
    segsnake run's output folder there)."""
    truth = _load(case["truth"]) != 0
    sp = _spacing(case["truth"])
    out: dict[str, Any] = {"case": case["name"], "structure": case["structure"],
                           "shape": list(truth.shape), "spacing": sp.tolist(),
                           "init": case["init"], "runs": []}
    starts = clicks(case, 0 if quick else n_clicks)
    atlas_dir = None  # (the atlas folder, checked and laid out once a case)
    if ATLAS in tools and case["name"].startswith("colin27-") and case["name"] != BRAIN_CASE:
        from atlas_start import atlas_folder

        atlas_dir = atlas_folder(_cache())
    tmp = tempfile.mkdtemp(prefix="segsnake-bench-real-")
    seg_click_mask = None
    try:
        def record(tool: str, label: str, init: dict | None, res: dict, **extra) -> np.ndarray | None:
            mask = _mask_from(res, truth.shape)
            row = {"tool": tool, "start": label, "init": init, **extra, **_score(res, truth, sp, mask)}
            out["runs"].append(row)
            if keep and res.get("mask"):  # the whole output folder, for a later look
                dest = os.path.join(keep, case["name"], f"{tool}-{label}".replace(" ", "_")
                                    .replace(",", "") + (f"-m{_grid(extra['m'])}" if "m" in extra else ""))
                shutil.rmtree(dest, ignore_errors=True)
                shutil.copytree(os.path.dirname(res["mask"]), dest)
            brief = f"{row['dice']:.3f}" if "dice" in row else f"failed ({row['error'][:60]})"
            print(f"[bench_real] {case['name']}: {tool} ({label}): {brief}, "
                  f"{row['wall_s']:.1f} s, {row['peak_rss_mb']:.0f} MB", file=sys.stderr, flush=True)
            return mask

        for label, init in starts:
            if SEGSNAKE in tools:
                mask = record(SEGSNAKE, label, init, run_segsnake(case["image"], init, tmp))
                if label == "click":
                    seg_click_mask = mask
            if CENTRE_ONLY in tools and init["shape"] == "sphere":
                centre = {"shape": "sphere", "center": init["center"]}
                record(CENTRE_ONLY, label, centre, run_segsnake(case["image"], centre, tmp))
            if atlas_dir is not None:
                named = ATLAS_NAMES.get(case["name"])
                if named is None or label == "click":  # (a named structure takes no click)
                    extra = ["--atlas", atlas_dir,
                             *(["--structure", named] if named else [])]
                    click = None if named else {"shape": "sphere", "center": init["center"]}
                    record(ATLAS, label, click, run_segsnake(case["image"], click, tmp, extra))
            if CENTRELINE in tools and init["shape"] == "cylinder":
                line = centerline_click(case["init"], init, truth, sp)
                record(CENTRELINE, label, line, run_segsnake(case["image"], line, tmp))
            # On the brain, users run BET and ROBEX; a generic region grower's region of
            # interest would be the whole 7 M-voxel head (15+ min a run for the morphological ones).
            for method in (m for m in PEERS if m in tools and case["name"] != BRAIN_CASE):
                record(method, label, init, run_peer(method, case, init, params[method], tmp))
        if NO_CLICK in tools and case["name"] == BRAIN_CASE:
            record(NO_CLICK, "none", None, run_segsnake(case["image"], None, tmp))
        if CEILING in tools:  # the reference itself (0/1 on the same grid) as the image
            grids = CEILING_M[case["init"]["shape"]][: 1 if quick else None]
            for grid in grids:
                res = run_segsnake(case["truth"], case["init"], tmp,
                                   None if grid is None else ["--m1", str(grid[0]),
                                                              "--m2", str(grid[1])])
                record(CEILING, "click", case["init"], res, m=res.get("m") or list(grid or ()))
        for tool in (t for t in BRAIN_TOOLS if t in tools and case["name"] == BRAIN_CASE):
            import brain_tools

            name = next(k for k in brain_tools.TOOLS if k.startswith(tool))
            mask_path = os.path.join(tmp, f"{tool}.nii.gz")
            res = brain_tools.run_tool(name, case["image"], mask_path, _cache(), TIMEOUT_S)
            res["mask"] = mask_path if res["returncode"] == 0 and os.path.exists(mask_path) else None
            record(tool, "none", None, res)
        if qc_dir and seg_click_mask is not None:
            os.makedirs(qc_dir, exist_ok=True)
            qc_picture(os.path.join(qc_dir, f"{case['name']}.png"), case, truth, sp, seg_click_mask)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def _brain_tool_settings(tools: list[str]) -> dict:
    """The pinned requirements and settings of the whole-head tools that will run."""
    if not any(t in tools for t in BRAIN_TOOLS):
        return {}
    import brain_tools

    return {name: {k: spec[k] for k in ("requirements", "settings", "argv")}
            for name, spec in brain_tools.TOOLS.items()}


def _cache() -> str:
    from fetch import cache_dir

    return cache_dir()


def qc_picture(path: str, case: dict, truth: np.ndarray, sp, seg: np.ndarray) -> None:
    """Three orthogonal slices through the click: reference (green), segsnake (red), click
    (yellow, dashed), drawn with the physical aspect ratio."""
    from matplotlib.figure import Figure

    image = _load(case["image"]).astype(np.float32)
    click = init_mask(case["init"], truth.shape, sp)
    centre = np.round(np.argwhere(click).mean(axis=0)).astype(int)
    from segsnake.qc import slice_panel

    fig = Figure(figsize=(12, 4.2), dpi=72)
    contours = [(truth, "lime", "solid", 1.0), (seg, "red", "solid", 1.0),
                (click, "yellow", "dashed", 1.0)]
    for panel, axis in enumerate((2, 1, 0)):
        slice_panel(fig.add_subplot(1, 3, panel + 1), image, sp, axis, int(centre[axis]), contours)
    fig.suptitle(f"{case['name']}: reference (green), segsnake from the click (red), "
                 f"click (yellow)", fontsize=10)
    fig.subplots_adjust(left=0.04, right=0.99, bottom=0.07, top=0.88, wspace=0.2)
    fig.savefig(path, format="png")


# ------------------------------------------------------------------------------------------
# Report
# ------------------------------------------------------------------------------------------


def _fmt(x: float | None, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def _grid(m: list[int]) -> str:
    """A control grid as ``M1xM2`` (``?`` for a run that failed before it had one)."""
    return "x".join(map(str, m)) or "?"


def summarize(runs: list[dict]) -> dict:
    """Click row, Dice over the perturbed clicks (a failed run counts as 0) and their failures."""
    click = next((r for r in runs if r["start"] in ("click", "none")), runs[0])
    pert = [r for r in runs if r["start"].startswith("perturbed")]
    return {"click": click, "perturbed": [r.get("dice", 0.0) for r in pert],
            "failed": sum("dice" not in r for r in pert)}


def markdown(info: dict) -> str:
    lines = [f"{machine_line(info['machine'])}; {info['date']}.",
             f"Command: `{info['command']}` (total {info['total_s'] / 60:.1f} min).", "",
             "| case | tool | Dice (click) | perturbed clicks: min / median / max Dice (n; a failed "
             "run counts 0) | "
             "HD95 (mm) | ASSD (mm) | time (s) | peak (MB) | exit, warnings |",
             "|---|---|---|---|---|---|---|---|---|"]
    for case in info["cases"]:
        tools = list(dict.fromkeys(r["tool"] for r in case["runs"]))
        for tool in tools:
            runs = [r for r in case["runs"] if r["tool"] == tool]
            if tool == CEILING:
                default = runs[0]  # (the M schedule's choice: CEILING_M's first)
                fixed = ", ".join(f"{_grid(r['m'])}: {_fmt(r.get('dice'), '.3f')}"
                                  for r in runs[1:])
                label = f"{tool} (M {_grid(default['m'])}" + \
                    (f"; fixed grids {fixed})" if fixed else ")")
                runs = [default]
            else:
                label = tool
            s = summarize(runs)
            c = s["click"]
            pert = s["perturbed"]
            spread = (f"{min(pert):.3f} / {statistics.median(pert):.3f} / {max(pert):.3f} "
                      f"({len(pert)}" + (f", {s['failed']} failed)" if s["failed"] else ")")
                      if pert else "")
            dice = _fmt(c.get("dice"), ".3f") if "error" not in c else f"failed: {c['error'][:70]}"
            flags = f"{c.get('returncode')}, " + (f"{len(c['warnings'])} warning(s)"
                                                  if c.get("warnings") else "none")
            lines.append(f"| {case['case']} | {label} | {dice} | {spread} | "
                         f"{_fmt(c.get('hausdorff95_mm'), '.1f')} | {_fmt(c.get('assd_mm'), '.2f')} | "
                         f"{_fmt(c.get('wall_s'), '.1f')} | {_fmt(c.get('peak_rss_mb'), '.0f')} | "
                         f"{flags if tool in OURS else ''} |")
    lines += ["", warning_coverage(info)]
    return "\n".join(lines)


def warning_coverage(info: dict) -> str:
    """Issue 15's test of the failure warning, over segsnake's runs from the benchmark's clicks
    (the click and the perturbed clicks of every case): how many of those below Dice 0.8 carry
    a warning, and how many of those above 0.9 do (none should)."""
    runs = [r for case in info["cases"] for r in case["runs"]
            if r["tool"] == SEGSNAKE and r.get("dice") is not None]
    low = [r for r in runs if r["dice"] < 0.8]
    high = [r for r in runs if r["dice"] > 0.9]
    return (f"The failure warning ({SEGSNAKE}, the clicks and perturbed clicks): on "
            f"{sum(bool(r.get('warnings')) for r in low)} of the {len(low)} results below Dice "
            f"0.8, on {sum(bool(r.get('warnings')) for r in high)} of the {len(high)} above 0.9.")


def tune(cases: list[dict], n_clicks: int, methods: list[str]) -> int:
    """Grid search of each peer's parameters on the tuning case(s): mean Dice over the clicks."""
    from segsnake.metrics import evaluate_masks

    tuning = [c for c in cases if c["role"] == "tuning"]
    for method in methods:
        grid = TUNE_GRID[method]
        keys = list(grid)
        scores = {}
        for values in itertools.product(*(grid[k] for k in keys)):
            p = dict(zip(keys, values))
            dice = []
            for case in tuning:
                truth = _load(case["truth"]) != 0
                sp = _spacing(case["truth"])
                tmp = tempfile.mkdtemp(prefix="segsnake-tune-")
                try:
                    for _, init in clicks(case, n_clicks):
                        mask = _mask_from(run_peer(method, case, init, p, tmp), truth.shape)
                        dice.append(evaluate_masks(mask, truth, sp)["dice"] if mask is not None else 0.0)
                finally:
                    shutil.rmtree(tmp, ignore_errors=True)
            scores[json.dumps(p)] = statistics.mean(dice)
            print(f"{method} {p}: mean Dice {scores[json.dumps(p)]:.4f} "
                  f"{[round(d, 3) for d in dice]}", flush=True)
        print(f"-> {method}: {max(scores, key=scores.get)}", flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    from fetch import load_cases

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="the click only, segsnake and its perfect-edge ceiling (default M)")
    ap.add_argument("--cases", nargs="+", help="case names (default: every benchmark case)")
    ap.add_argument("--tools", nargs="+", choices=TOOLS, help="tools (default: all)")
    ap.add_argument("--clicks", type=int, default=5, help="perturbed clicks per case (default 5)")
    ap.add_argument("--qc", metavar="DIR", default=None,
                    help="write a QC montage per case here (default: docs/real for a full run)")
    ap.add_argument("--json", metavar="PATH", help="also write the raw numbers here")
    ap.add_argument("--keep", metavar="DIR", help="keep every segsnake run's outputs here")
    ap.add_argument("--tune", action="store_true", help="the peers' parameter sweep")
    ap.add_argument("--report", nargs="+", metavar="JSON",
                    help="print the table of earlier runs' --json files (merged) and exit")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.report:
        print(markdown(merge(args.report)))
        return 0

    if args.child:
        child_peer(json.loads(args.child))
        return 0
    try:
        cases = load_cases()
    except FileNotFoundError as exc:
        print(f"bench_real: {exc}", file=sys.stderr)
        return 3
    if args.tune:
        return tune(cases, args.clicks, [t for t in (args.tools or PEERS) if t in PEERS])
    if args.cases:
        unknown = set(args.cases) - {c["name"] for c in cases}
        if unknown:
            print(f"bench_real: unknown case(s): {', '.join(sorted(unknown))}", file=sys.stderr)
            return 2
        cases = [c for c in cases if c["name"] in args.cases]
    else:
        cases = [c for c in cases if c["role"] == "benchmark"]
    tools = args.tools or ([SEGSNAKE, CEILING] if args.quick else list(TOOLS))
    qc = args.qc if args.qc is not None else (None if args.quick or args.cases
                                              else os.path.join(ROOT, "docs", "real"))
    t0 = time.perf_counter()
    exe = sys.executable
    info: dict[str, Any] = {
        "machine": machine_info(), "date": time.strftime("%Y-%m-%d"), "total_s": 0.0,
        "params": {**PEER_PARAMS, **_brain_tool_settings(tools)},
        "command": " ".join([os.path.relpath(exe, ROOT) if exe.startswith(ROOT) else exe,
                             os.path.relpath(__file__, ROOT), *(argv if argv is not None
                                                                else sys.argv[1:])]),
        "cases": []}
    for case in cases:
        info["cases"].append(run_case(case, tools, args.clicks, args.quick, qc, PEER_PARAMS,
                                     args.keep))
        info["total_s"] = time.perf_counter() - t0
        if args.json:  # after every case: a long run stopped half-way keeps what it measured
            with open(args.json, "w") as fh:
                json.dump(info, fh, indent=1)
    return report(info, args.json, markdown)


def merge(paths: list[str]) -> dict:
    """Runs of several ``--json`` files as one report: a later file's runs of a tool on a case
    replace an earlier file's; the header is the first file's, with every command and the
    summed run time (the runs may have overlapped: see the dates)."""
    infos = []
    for path in paths:
        with open(path) as fh:
            infos.append(json.load(fh))
    merged = dict(infos[0], cases=[], total_s=sum(i["total_s"] for i in infos),
                  command="` + `".join(i["command"] for i in infos),
                  params={k: v for i in infos for k, v in i["params"].items()})
    for info in infos:
        for case in info["cases"]:
            into = next((c for c in merged["cases"] if c["case"] == case["case"]), None)
            if into is None:
                merged["cases"].append(dict(case, runs=list(case["runs"])))
                continue
            tools = {r["tool"] for r in case["runs"]}
            into["runs"] = [r for r in into["runs"] if r["tool"] not in tools] + case["runs"]
    return merged


if __name__ == "__main__":
    sys.exit(main())
