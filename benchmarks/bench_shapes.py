"""Benchmark: shape modelling (issue 19): fit convergence, real structures, measures.

Usage::

    .venv/bin/python benchmarks/bench_shapes.py [--json out.json] [--skip-brain]

Prints the markdown of docs/benchmarks.md's section "Shape modelling (issue 19)". Needs the
cached Colin27 masks (``make bench-real-data``) for the real-structure tables.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
from machine import machine_info, machine_line, report  # noqa: E402 (benchmarks/ on sys.path)

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "real"))

from segsnake.fit import M2_SCHEDULE, fit_errors, fit_function, fit_mesh  # noqa: E402
from segsnake.mask_mesh import mask_surface  # noqa: E402
from segsnake.measure import closed_area  # noqa: E402
from segsnake.parameterize import spherical_parameterization, to_sphere  # noqa: E402
from segsnake.surfaces import SphereModel  # noqa: E402

STRUCTURES = ("brain", "thalamus_r", "caudate_l", "hippocampus_r")


def lobed(u, v):
    """Lobed blob: 1 + 0.3 sin(3 pi v) cos(4 pi u) times the unit sphere, scaled (30, 20, 15)."""
    r = 1 + 0.3 * np.sin(3 * np.pi * v) * np.cos(4 * np.pi * u)
    return to_sphere(u, v) * r[..., None] * np.array([30.0, 20.0, 15.0])


def analytic() -> dict:
    """Errors of the L2 projection against M on analytic surfaces (and a lobed mesh)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    u, v = rng.random(20000), rng.random(20000)
    rot = Rotation.from_euler("xyz", [20, 30, 40], degrees=True).as_matrix()
    ell = SphereModel.ellipsoid((10, -5, 100), (7, 4, 2), rot)
    # The lobed blob also as a mesh, parameterized like any mesh (its own (u, v) forgotten).
    mesh = SphereModel.unit(40, 40).to_mesh(240, 120)
    faces = np.asarray(mesh.faces).reshape(-1, 4)[:, 1:]
    p = np.asarray(mesh.points)
    theta, phi = np.arccos(np.clip(p[:, 2], -1, 1)), np.arctan2(p[:, 1], p[:, 0])
    lobed_pts = lobed(np.mod(phi / (2 * np.pi), 1), theta / np.pi)
    smap = spherical_parameterization(lobed_pts, faces)
    rows = []
    for m2 in M2_SCHEDULE[:7]:
        row = {"m1": 2 * m2, "m2": m2, "n_params": SphereModel.unit(2 * m2, m2).n_params}
        for name, f, pts, uu, vv in (("ellipsoid", ell, ell(u, v), u, v),
                                     ("lobed", lobed, lobed(u, v), u, v),
                                     ("lobed_mesh", smap.surface_at, lobed_pts, smap.u, smap.v)):
            t0 = time.perf_counter()
            model = fit_function(f, 2 * m2, m2)
            err = fit_errors(model, pts, uu, vv)
            row[name] = {"rms_percent": err.rms_percent, "max_percent": err.max_percent,
                         "max_mm": err.max, "seconds": time.perf_counter() - t0}
        rows.append(row)
    return {"rows": rows, "lobed_mesh_vertices": len(lobed_pts),
            "lobed_mesh_flipped": smap.flipped_fraction()}


def real(names) -> dict:
    """Every structure's mask -> genus-0 mesh -> fits for every M2 of the schedule."""
    import nibabel as nib
    import pyvista as pv
    from fetch import cache_dir
    from scipy.spatial import cKDTree
    from skimage.measure import marching_cubes

    out = {}
    for name in names:
        path = os.path.join(cache_dir(), "cases", f"colin27_{name}.nii.gz")
        img = nib.load(path)
        mask = np.asarray(img.dataobj) > 0
        spacing = tuple(float(z) for z in img.header.get_zooms()[:3])
        t0 = time.perf_counter()
        surf = mask_surface(mask, spacing)
        t_mesh = time.perf_counter() - t0
        t0 = time.perf_counter()
        res = fit_mesh(surf.points, surf.faces, rms_target=0.0)  # every size of the schedule
        t_fit = time.perf_counter() - t0
        cells = np.hstack([np.full((len(surf.faces), 1), 3), surf.faces]).ravel()
        mesh = pv.PolyData(surf.points, cells)
        binary, _, _, _ = marching_cubes(np.pad(mask, 1).astype(np.float32), 0.5, spacing=spacing)
        binary -= np.asarray(spacing)
        steps = []
        for s in res.steps:
            dense = s.model.to_mesh(12 * s.model.m1, 12 * s.model.m2)
            d = cKDTree(np.asarray(dense.points)).query(binary)[0]
            steps.append({"m1": s.m1, "m2": s.m2, "n_params": s.n_params,
                          "rms_percent": s.error.rms_percent, "max_percent": s.error.max_percent,
                          "rms_mm": s.error.rms, "max_mm": s.error.max,
                          "volume_mm3": s.model.volume(), "area_mm2": closed_area(s.model),
                          "mask_boundary_rms_mm": float(np.sqrt(np.mean(d * d)))})
        out[name] = {"vertices": len(surf.points), "smoothing_voxels": surf.sigma_voxels,
                     "mask_to_surface_rms_mm": surf.distance_to_mask_rms,
                     "mask_to_surface_max_mm": surf.distance_to_mask_max,
                     "flipped": res.spherical_map.flipped_fraction(),
                     "diagonal_mm": res.steps[0].error.diagonal,
                     "mask_volume_mm3": float(mask.sum() * np.prod(spacing)),
                     "mesh_volume_mm3": float(abs(mesh.volume)), "mesh_area_mm2": float(mesh.area),
                     "mesh_s": t_mesh, "fit_all_sizes_s": t_fit, "steps": steps}
    return out


def morph_demo(names=("thalamus_r", "hippocampus_r"), m1: int = 24, m2: int = 12,
               steps: int = 9) -> dict:
    """Plane and sphere paths between two fitted real structures; ellipsoid plane-path check."""
    import nibabel as nib
    from fetch import cache_dir

    from segsnake.morph import morph

    r1 = np.linalg.qr(np.random.default_rng(3).normal(size=(3, 3)))[0]
    e1 = SphereModel.ellipsoid((0, 0, 0), (3, 4, 5), m1=m1, m2=m2)
    e2 = SphereModel.ellipsoid((10, 2, 0), (6, 2, 3), r1, m1=m1, m2=m2)
    taus, plane = morph(e1, e2, steps, "plane")
    affine_err = max(float(np.max(np.abs(s.params - SphereModel.unit(m1, m2).transformed(
        (1 - t) * np.diag([3.0, 4, 5]) + t * r1 @ np.diag([6.0, 2, 3]),
        t * np.array([10.0, 2, 0])).params))) for t, s in zip(taus, plane))
    out = {"ellipsoid_plane_vs_affine_max": affine_err}
    fitted = []
    for name in names:
        img = nib.load(os.path.join(cache_dir(), "cases", f"colin27_{name}.nii.gz"))
        surf = mask_surface(np.asarray(img.dataobj) > 0,
                            tuple(float(z) for z in img.header.get_zooms()[:3]))
        fitted.append(fit_mesh(surf.points, surf.faces, m1=m1, m2=m2).model)
    for path in ("plane", "sphere"):
        for align in (False, True):
            taus, shapes = morph(fitted[0], fitted[1], steps, path, align)
            out[f"{path}{'_aligned' if align else ''}"] = {
                "tau": taus.tolist(), "volume_mm3": [s.volume() for s in shapes],
                "area_mm2": [closed_area(s) for s in shapes],
                "ends_exact": bool(np.array_equal(shapes[0].params, fitted[0].params)
                                   and np.array_equal(shapes[-1].params, fitted[1].params))}
    out["names"] = list(names)
    return out


# -- priors with modes: a phantom with a gap in its boundary ---------------------------------
GAP_M = 8
GAP_CENTRE = np.array([32.0, 32.0, 32.0])
GAP_RADII = np.array([13.0, 10.0, 9.0])
GAP_SD = np.array([1.0, 0.7, 0.5])  # standard deviations of the three deformations
GAP_TEST = np.array([2.0, 1.2, 0.0])  # the test shape: 2 and 1.7 standard deviations
GAP_DEG = 35.0


def _gap_deformations() -> list[np.ndarray]:
    """Three non-affine displacement fields of the control points: pear, square, three lobes."""
    unit = SphereModel.unit(GAP_M, GAP_M)
    n = np.where(unit.is_vector[:, None], 0.0, unit.params)
    z, ang = n[:, 2], np.arctan2(n[:, 1], n[:, 0])
    rxy = np.hypot(n[:, 0], n[:, 1])
    fields = [z * (1 - z**2) * 2.6, np.cos(2 * ang) * rxy**2, np.cos(3 * ang) * rxy**3]
    return [f[:, None] * n * GAP_RADII * 0.25 for f in fields]


def _gap_image(model, seed: int, gap: bool):
    """Blurred, noisy phantom; with ``gap`` the boundary inside a cone around +x is replaced by a
    gentle ramp blended in over the cone's rim (no edge there)."""
    from scipy import ndimage as ndi

    from segsnake.rasterize import rasterize

    truth = rasterize(model, (64, 64, 64), (1.0, 1.0, 1.0))
    img = ndi.gaussian_filter(truth.astype(np.float32), 1.0)
    idx = np.indices(img.shape).astype(float) - GAP_CENTRE[:, None, None, None]
    rr = np.maximum(np.sqrt((idx**2).sum(0)), 1e-9)
    angle = np.degrees(np.arccos(np.clip(idx[0] / rr, -1, 1)))
    if gap:
        w = np.clip((GAP_DEG + 10 - angle) / 20.0, 0.0, 1.0)
        img = (1 - w) * img + w * np.clip((25.0 - rr) / 20.0, 0.0, 1.0)
    img = img + 0.1 * np.random.default_rng(seed).normal(size=img.shape)
    return truth, img.astype(np.float32), angle < GAP_DEG


def prior_gap(workdir: str, weights=(1.0, 0.3)) -> dict:
    """10 perturbed phantoms segmented -> shape model -> a gapped test phantom, prior by prior."""
    import contextlib
    import io
    import json

    import nibabel as nib

    from segsnake.cli import main as cli

    base = SphereModel.ellipsoid(GAP_CENTRE, GAP_RADII, m1=GAP_M, m2=GAP_M)
    fields = _gap_deformations()

    def shape(a):
        return base.with_params(base.params + sum(a[k] * fields[k] for k in range(3)))

    def segment(name, img, truth, *extra):
        paths = [os.path.join(workdir, f"{name}{s}.nii.gz") for s in ("", "_truth")]
        nib.save(nib.Nifti1Image(img, np.eye(4)), paths[0])
        nib.save(nib.Nifti1Image(truth.astype(np.uint8), np.eye(4)), paths[1])
        out = os.path.join(workdir, "seg_" + name)
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            code = cli(["segment", paths[0], "--out", out, "--truth", paths[1], "--center", "32",
                        "32", "32", "--radii", "6", "6", "6", "--m1", str(GAP_M), "--m2",
                        str(GAP_M), "--overwrite", "--json", *extra])
        if code:
            raise RuntimeError(f"segment {name} failed with {code}")
        rec = json.loads(buf.getvalue().strip().splitlines()[-1])
        return rec, nib.load(os.path.join(out, "mask.nii.gz")).get_fdata() > 0

    rng = np.random.default_rng(0)
    train = []
    for i in range(10):
        truth, img, _ = _gap_image(shape(rng.normal(size=3) * GAP_SD), 10 + i, gap=False)
        rec, _ = segment(f"train{i}", img, truth)
        train.append({"dice": rec["dice"], "snake": os.path.join(workdir, f"seg_train{i}",
                                                                 "snake.json")})
    from segsnake.shapes import load_shape_model

    models, variances = {}, {}
    for align in ("affine", "similarity", "rigid"):
        models[align] = os.path.join(workdir, f"model_{align}.json")
        with contextlib.redirect_stdout(io.StringIO()):
            cli(["shape-model", *[t["snake"] for t in train], "--out", models[align],
                 "--align", align, "--overwrite"])
        variances[align] = load_shape_model(models[align]).variances.tolist()
    truth, img, cone = _gap_image(shape(GAP_TEST), 99, gap=True)

    def dice(a, b):
        return float(2 * (a & b).sum() / max(a.sum() + b.sum(), 1))

    runs = []
    settings = [("none", None, None, [])]
    for w in weights:
        settings += [("affine", w, "affine", [])]
        settings += [(f"affine + {k} modes", w, "affine", ["--prior-modes", str(k)])
                     for k in (1, 2, 3, 5)]
        for sp in ("similarity", "rigid"):
            settings += [(sp, w, sp, ["--prior-space", sp])]
            settings += [(f"{sp} + {k} modes", w, sp, ["--prior-space", sp, "--prior-modes", str(k)])
                         for k in (1, 3)]
    for name, w, align, extra in settings:
        args = [] if w is None else ["--prior", models[align], "--prior-weight", str(w), *extra]
        rec, mask = segment("test", img, truth, *args)
        runs.append({"prior": name, "weight": w, "model": align, "dice": rec["dice"],
                     "assd_mm": rec["assd_mm"], "hd95_mm": rec["hausdorff95_mm"],
                     "gap_dice": dice(mask & cone, truth & cone),
                     "rest_dice": dice(mask & ~cone, truth & ~cone)})
    return {"train_dice": [t["dice"] for t in train], "variances_mm2": variances, "runs": runs}


def _prior_lines(info: dict) -> list[str]:
    """Markdown of the prior experiment."""
    g = info.get("prior_gap")
    if not g:
        return []
    lines = ["", "### A prior with modes on a phantom with a gap in its boundary", "",
             f"Ten phantoms (ellipsoid radii {GAP_RADII.tolist()} mm with three non-affine "
             f"deformations of standard deviations {GAP_SD.tolist()}, blurred, noise 0.1) "
             f"segmented without a prior (Dice {min(g['train_dice']):.3f} to "
             f"{max(g['train_dice']):.3f}), their snakes into `segsnake shape-model` with "
             "`--align affine` (the affine rows' model; variances "
             f"{', '.join(f'{v:.3g}' for v in g['variances_mm2']['affine'][:4])} mm^2, ...), "
             "`similarity` (variances "
             f"{', '.join(f'{v:.3g}' for v in g['variances_mm2']['similarity'][:4])}, ...) and "
             "`rigid` (the rows of those spaces use the model aligned the same way). "
             f"Test phantom: coefficients {GAP_TEST.tolist()} (2 and 1.7 standard "
             f"deviations), and inside a {GAP_DEG:.0f} degree cone around +x the boundary is "
             "replaced by a gentle ramp (no edge). `segment --prior MODEL.json` with the "
             "options below; gap Dice: inside the cone, rest: outside it.", "",
             "| prior | --prior-weight | Dice | ASSD (mm) | HD95 (mm) | gap Dice | rest Dice |",
             "|---|---|---|---|---|---|---|"]
    for r in g["runs"]:
        w = "-" if r["weight"] is None else f"{r['weight']:g}"
        lines.append(f"| {r['prior']} | {w} | {r['dice']:.4f} | {r['assd_mm']:.3f} | "
                     f"{r['hd95_mm']:.2f} | {r['gap_dice']:.4f} | {r['rest_dice']:.4f} |")
    return lines


def _morph_lines(info: dict) -> list[str]:
    """Markdown of the morph demonstration."""
    m = info.get("morph")
    if not m:
        return []
    a, b = m["names"]
    lines = ["", f"### Morph: {a} into {b} (both fitted at 24 x 12)", "",
             f"Plane path between two ellipsoids against the affine interpolation of their maps: "
             f"max parameter difference {m['ellipsoid_plane_vs_affine_max']:.1e} mm. Volumes "
             "(mm^3) along the paths (`segsnake.morph.morph`, 9 steps; aligned: after the "
             "unbiased affine alignment of the pair, so tau = 0 and 1 are the aligned inputs):",
             "", "| tau | " + " | ".join(k for k in ("plane", "plane_aligned", "sphere",
                                                     "sphere_aligned")) + " |",
             "|---|---|---|---|---|"]
    for i, t in enumerate(m["plane"]["tau"]):
        lines.append(f"| {t:.3f} | " + " | ".join(
            f"{m[k]['volume_mm3'][i]:.0f}" for k in ("plane", "plane_aligned", "sphere",
                                                      "sphere_aligned")) + " |")
    exact = all(m[k]["ends_exact"] for k in ("plane", "sphere"))
    lines += ["", f"Unaligned paths end exactly on the inputs: {exact}."]
    return lines


def markdown(info: dict) -> str:
    lines = []
    a = info.get("analytic")
    if a is None:
        lines += _prior_lines(info)
        lines += ["", machine_line(info["machine"])]
        return "\n".join(lines)
    lines += ["### Fit convergence on analytic surfaces", "",
             "L2 projection with the exact Gram matrix (`segsnake.fit.fit_function`), errors at "
             "20000 random parameter points, in % of the bounding-box diagonal (RMS / max). "
             "`lobed mesh`: the lobed blob as a "
             f"{a['lobed_mesh_vertices']}-vertex mesh, parameterized by `segsnake.parameterize` "
             f"(its own (u, v) unknown to the fit; flipped triangles {a['lobed_mesh_flipped']:.1e}), "
             "errors at its vertices.", "",
             "| M1 x M2 | params | ellipsoid max (mm) | lobed RMS % | lobed max % | lobed mesh RMS % "
             "| lobed mesh max % |", "|---|---|---|---|---|---|---|"]
    for r in a["rows"]:
        lines.append(f"| {r['m1']} x {r['m2']} | {r['n_params']} | {r['ellipsoid']['max_mm']:.1e} | "
                     f"{r['lobed']['rms_percent']:.4f} | {r['lobed']['max_percent']:.4f} | "
                     f"{r['lobed_mesh']['rms_percent']:.3f} | {r['lobed_mesh']['max_percent']:.3f} |")
    if info.get("real"):
        real_ = info["real"]
        names = list(real_)
        lines += ["", "### Real structures (Colin27 masks, marching cubes, genus-0 repaired)", "",
                  "| structure | vertices | smoothing (voxels) | mask boundary to mesh RMS / max (mm) "
                  "| flipped triangles | diagonal (mm) | mesh + all fits (s) |",
                  "|---|---|---|---|---|---|---|"]
        for n in names:
            r = real_[n]
            lines.append(f"| {n} | {r['vertices']} | {r['smoothing_voxels']} | "
                         f"{r['mask_to_surface_rms_mm']:.2f} / {r['mask_to_surface_max_mm']:.1f} | "
                         f"{r['flipped']:.1e} | {r['diagonal_mm']:.1f} | "
                         f"{r['mesh_s']:.1f} + {r['fit_all_sizes_s']:.1f} |")
        lines += ["", "RMS % / max % of the bounding-box diagonal at the mesh vertices, against "
                  "the number of control points (M1 = 2 M2; params = M1 (M2 - 1) + 6 control "
                  "points and pole tangents, x 3 coordinates):", "",
                  "| M1 x M2 | params | " + " | ".join(names) + " |",
                  "|---|---|" + "---|" * len(names)]
        for i, s in enumerate(real_[names[0]]["steps"]):
            cells = [f"{real_[n]['steps'][i]['rms_percent']:.3f} / "
                     f"{real_[n]['steps'][i]['max_percent']:.3f}" for n in names]
            lines.append(f"| {s['m1']} x {s['m2']} | {s['n_params']} | " + " | ".join(cells) + " |")
        lines.append("| seed 004 (quartic spherical DCB-spline, brain) | see text | 0.090 / 0.493 "
                     + "| " * (len(names) - 1) + "|")
        lines += ["", "Measures against the mask at M2 = 24 (volume and area of the spline, "
                  "`segsnake.measure`; the mesh is the repaired marching-cubes surface that was "
                  "fitted; mask boundary RMS: from the binary mask's marching-cubes vertices to "
                  "the fitted spline):", "",
                  "| structure | mask volume (mm^3) | mesh volume | spline volume | mesh area (mm^2) "
                  "| spline area | mask boundary to spline RMS (mm) |", "|---|---|---|---|---|---|---|"]
        for n in names:
            r = real_[n]
            s = next(x for x in r["steps"] if x["m2"] == 24)
            lines.append(f"| {n} | {r['mask_volume_mm3']:.0f} | {r['mesh_volume_mm3']:.0f} | "
                         f"{s['volume_mm3']:.0f} | {r['mesh_area_mm2']:.0f} | {s['area_mm2']:.0f} | "
                         f"{s['mask_boundary_rms_mm']:.2f} |")
    lines += _morph_lines(info)
    lines += _prior_lines(info)
    lines += ["", machine_line(info["machine"])]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write the raw numbers here")
    ap.add_argument("--skip-brain", action="store_true", help="leave out the brain (slowest)")
    ap.add_argument("--only-priors", action="store_true", help="only the prior experiment")
    args = ap.parse_args(argv)
    import tempfile

    info = {"machine": machine_info()}
    with tempfile.TemporaryDirectory(prefix="bench-shapes-") as tmp:
        info["prior_gap"] = prior_gap(tmp)
    if args.only_priors:
        return report(info, args.json, markdown)
    info["analytic"] = analytic()
    try:
        info["morph"] = morph_demo()
    except FileNotFoundError as exc:
        print(f"morph demonstration skipped: {exc}", file=sys.stderr)
    names = [n for n in STRUCTURES if not (args.skip_brain and n == "brain")]
    try:
        info["real"] = real(names)
    except FileNotFoundError as exc:
        print(f"real structures skipped: {exc}", file=sys.stderr)
    return report(info, args.json, markdown)


if __name__ == "__main__":
    sys.exit(main())
