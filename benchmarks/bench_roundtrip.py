"""The edit round trip (issue 17, item 6), measured: export-points -> render, --init, resampled --init.

For each phantom: segment it from its suggested start, then

* ``render`` of ``export-points`` of the result: voxels that differ from the result's mask, and
  the largest distance between the two world surfaces (sampled on a 64 x 65 (u, v) grid);
* ``segment --init`` of the result, and ``--init`` of that run: Dice with the run it started
  from, relative energy difference, largest distance between the two surfaces (each sampled on
  a 128 x 129 (u, v) grid against the other's fine mesh, both ways), iterations;
* ``--init`` resampled to other M1 x M2: Dice with the result;
* the Dice of the result, the --init run and the resampled run with the phantom's truth.

Usage: ``python benchmarks/bench_roundtrip.py [--json FILE]`` (about two minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import nibabel as nib
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from machine import machine_info, machine_line, report  # noqa: E402

from segsnake.cli import main  # noqa: E402
from segsnake.commands.phantom import write_phantom  # noqa: E402
from segsnake.metrics import evaluate_masks  # noqa: E402
from segsnake.phantoms import make_phantom  # noqa: E402
from segsnake.saved_snake import load_snake  # noqa: E402

CASES = [
    # name, phantom kind, options, extra segment flags, resampled size
    ("blob (README)", "blob", {"seed": 1, "noise": 0.2}, [], (12, 12)),
    ("ball, rotated 1x1x1.3 grid (tests)", "ball",
     {"seed": 3, "shape": (28, 28, 22), "spacing": (1.0, 1.0, 1.3), "noise": 0.1,
      "grid_rotation": (15.0, -10.0, 25.0)}, [], (12, 12)),
    ("ellipsoid", "ellipsoid", {"seed": 2, "noise": 0.1}, [], (7, 7)),
    ("hollow cylinder (README)", "hollow-cylinder", {"seed": 0, "std": 30},
     ["--feature", "surface"], (12, 6)),
    ("T1 brain, inner face of the CSF", "brain", {"seed": 0},
     ["--feature", "surface", "--polarity", "dark", "--scale", "3"], (12, 12)),
]


def _init_flags(init: dict) -> list[str]:
    keys = ("center", "radii", "axis_start", "axis_end", "radius")
    out = ["--shape", init.get("shape", "sphere")]
    for k in keys:
        if init.get(k) is not None:
            v = init[k]
            out += ["--" + k.replace("_", "-"), *map(str, v if isinstance(v, list) else [v])]
    return out


def _mask(d: Path) -> np.ndarray:
    return np.asarray(nib.load(str(d / "mask.nii.gz")).dataobj) > 0


def _surface(d: Path, n: int = 64) -> np.ndarray:
    world = load_snake(str(d / "snake.json"))
    return world.evaluate(np.arange(n) / n, np.linspace(0.0, 1.0, n + 1))[0]


def _distance(a: Path, b: Path, n: int = 128) -> float:
    """Largest distance (mm) from either world surface to the other's fine mesh (symmetric)."""
    import pyvista as pv

    out = 0.0
    for p, q in ((a, b), (b, a)):
        points = pv.PolyData(_surface(p, n).reshape(-1, 3))
        mesh = load_snake(str(q / "snake.json")).to_mesh(8 * n, 8 * n)
        dist = points.compute_implicit_distance(mesh)["implicit_distance"]
        out = max(out, float(np.abs(dist).max()))
    return out


def _summary(d: Path) -> dict:
    return json.loads((d / "snake.json").read_text())["summary"]


def _segment(args: list[str]) -> float:
    t0 = time.perf_counter()
    if main(["segment", *map(str, args), "--quiet"]) != 0:
        raise RuntimeError(f"segment {args} failed")
    return time.perf_counter() - t0


def compare(a: Path, b: Path) -> dict:
    """Run ``a`` against the run ``b`` it started from."""
    ea, eb = _summary(a)["energy"], _summary(b)["energy"]
    return {"dice": evaluate_masks(_mask(a), _mask(b), (1, 1, 1))["dice"],
            "voxels_changed": int(np.sum(_mask(a) != _mask(b))),
            "energy_rel": abs(ea - eb) / abs(eb),
            "max_distance_mm": _distance(a, b),
            "iterations": _summary(a)["iterations"]}


def run_case(name, kind, options, flags, size, root: Path) -> dict:
    ph = make_phantom(kind, **options)
    d = root / kind
    write_phantom(ph, d)
    image = d / "image.nii.gz"
    seg, rendered, points = d / "seg", d / "rendered", d / "points.mrk.json"
    t_seg = _segment([image, "--out", seg, *_init_flags(ph.init), *flags])
    assert main(["export-points", str(seg / "snake.json"), "--out", str(points), "-q"]) == 0
    t0 = time.perf_counter()
    assert main(["render", str(points), "--like", str(image), "--out", str(rendered), "-q"]) == 0
    t_render = time.perf_counter() - t0
    row = {"case": name, "voxels": int(_mask(seg).sum()), "segment_s": t_seg, "render_s": t_render,
           "render_voxels_changed": int(np.sum(_mask(rendered) != _mask(seg))),
           "render_max_dev_mm": float(np.abs(_surface(rendered) - _surface(seg)).max())}
    t_init = _segment([image, "--out", d / "init", "--init", seg / "snake.json", *flags])
    _segment([image, "--out", d / "init2", "--init", d / "init" / "snake.json", *flags])
    _segment([image, "--out", d / "resampled", "--init", seg / "snake.json", "--m1", size[0],
              "--m2", size[1], *flags])
    row.update({"init_s": t_init, "init": compare(d / "init", seg),
                "init_of_init": compare(d / "init2", d / "init"),
                "resampled_size": list(size), "resampled": compare(d / "resampled", seg)})
    truth = np.asarray(nib.load(str(d / "truth.nii.gz")).dataobj) > 0
    row["truth_dice"] = {run: evaluate_masks(_mask(d / run), truth, (1, 1, 1))["dice"]
                         for run in ("seg", "init", "resampled")}
    return row


def markdown(info: dict) -> str:
    lines = ["| case | voxels | render: voxels changed, max dev (mm) | --init: Dice, voxels, rel. energy, "
             "max distance (mm), iterations | --init of --init: Dice, rel. energy | resampled: M, Dice | "
             "Dice with the truth: result, --init, resampled |",
             "|---|---:|---|---|---|---|---|"]
    for r in info["rows"]:
        i, ii, rs = r["init"], r["init_of_init"], r["resampled"]
        lines.append(
            f"| {r['case']} | {r['voxels']} | {r['render_voxels_changed']}, "
            f"{r['render_max_dev_mm']:.1e} | {i['dice']:.4f}, {i['voxels_changed']}, "
            f"{i['energy_rel']:.1e}, {i['max_distance_mm']:.3f}, {i['iterations']} | "
            f"{ii['dice']:.4f}, {ii['energy_rel']:.1e} | "
            f"{rs_size(r)}, {rs['dice']:.4f} | "
            + ", ".join(f"{r['truth_dice'][k]:.4f}" for k in ("seg", "init", "resampled")) + " |")
    return "\n".join(lines + ["", machine_line(info["machine"])])


def rs_size(r: dict) -> str:
    return f"{r['resampled_size'][0]}x{r['resampled_size'][1]}"


def cli() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", default=None, help="also write the raw numbers here")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="segsnake-roundtrip-") as tmp:
        rows = [run_case(*case, Path(tmp)) for case in CASES]
    return report({"machine": machine_info(), "rows": rows}, args.json, markdown)


if __name__ == "__main__":
    sys.exit(cli())
