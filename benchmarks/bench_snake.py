"""Benchmark: flux energy evaluation and ``segment_volume`` wall time (issue 4).

Goals (issue 4, thesis 003 for the paper's figures):

- one energy + gradient evaluation of :class:`segsnake.energy.FluxTerm` for a 9 x 9 sphere on a
  181 x 217 x 181 lookup: under 2 ms (median of 200 calls), at quadrature order 4 (the paper's
  setting) and at the orders the pipeline actually uses (read from ``history[i]
  ["quadrature_order"]`` of the runs below);
- ``segment_volume`` on the 181 x 217 x 181 brain phantom (T1 with a dark CSF sheet, PD; the
  options of configs/brain-sweep.yaml): under 10 s (the paper: 70 s), with the Dice index;
- ``segment_volume`` on the 128^3 hollow cylinder (std 50): under 2 s (the paper: 4 s), with the
  Jaccard index of the region inside the wall's mid-surface;
- a 64^3 blob (noise 20 % of contrast, default ``edge`` feature) for scale.

Every case runs in a fresh child process (imports, phantom and caches are the child's own),
``--repeats`` times (default 3); the median wall time of ``segment_volume`` is reported with its
``timings`` breakdown (median over repeats) and the stages of the last repeat. The modules
``segment_volume`` imports on first use are imported before the clock starts; one more run per
case is the whole ``segsnake segment`` command on the phantom written as NIfTI, timed from process
start to exit (imports, loading and the four outputs included). One more child per case runs
``segment_volume`` under cProfile (slower by the profiler's overhead) for the top functions.

Usage::

    .venv/bin/python benchmarks/bench_snake.py                 # everything, markdown to stdout
    .venv/bin/python benchmarks/bench_snake.py --cases blob hollow-cylinder --repeats 1
    .venv/bin/python benchmarks/bench_snake.py --json out.json # also the raw numbers
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from typing import Any

import numpy as np
from machine import machine_info, report  # noqa: E402 (benchmarks/ is on sys.path)

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
if ROOT not in sys.path:  # run as a script from anywhere: import the checkout's segsnake
    sys.path.insert(0, ROOT)

#: name -> phantom kind and options, config builder name (+ extra options), goal s, paper s.
#: The brains use the detector scale of configs/brain-sweep.yaml (3 mm, the CSF sheet's width;
#: at the default 1.5 mm the sheet detector prefers the thinner sulcal CSF).
CASES: dict[str, dict[str, Any]] = {
    "brain-t1": {"kind": "brain", "options": {"contrast": "t1", "noise": 0.03},
                 "config": "sheet-dark", "extra": {"scale": 3.0}, "metric": "dice",
                 "goal_s": 10.0, "paper_s": 70.0},
    "brain-pd": {"kind": "brain", "options": {"contrast": "pd", "noise": 0.03},
                 "config": "sheet", "extra": {"scale": 3.0}, "metric": "dice",
                 "goal_s": 10.0, "paper_s": 70.0},
    "hollow-cylinder": {"kind": "hollow-cylinder", "options": {"std": 50.0},
                        "config": "sheet", "metric": "jaccard", "goal_s": 2.0, "paper_s": 4.0},
    "blob": {"kind": "blob", "options": {"noise": 0.2},
             "config": "edge", "metric": "dice", "goal_s": None, "paper_s": None},
}

#: The lookup of the energy benchmark: BrainWeb's grid.
ENERGY_SHAPE = (181, 217, 181)


def case_config(name: str, init: dict) -> dict:
    """The ``segment`` options of a case, with the phantom's suggested initialization."""
    how = CASES[name]["config"]
    if init["shape"] == "sphere":
        geometry = {"shape": "sphere", "center": init["center"], "radii": init["radii"]}
    else:
        geometry = dict(init)
    extra = CASES[name].get("extra", {})
    if how == "sheet-dark":
        return {"feature": "surface", "polarity": "dark", **extra, **geometry}
    if how == "sheet":
        return {"feature": "surface", **extra, **geometry}
    return {**extra, **geometry}


def machine() -> dict:
    """See :func:`machine.machine_info`."""
    return machine_info()


# ------------------------------------------------------------------------------------------
# Children
# ------------------------------------------------------------------------------------------


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def child_case(name: str, profile_top: int = 0) -> dict:
    """Build the case's phantom, segment it once, return timings, stages and metrics."""
    from segsnake.config import SegmentConfig
    from segsnake.metrics import evaluate_masks
    from segsnake.phantoms import make_phantom
    from segsnake.pipeline import segment_volume

    _import_pipeline_modules()
    case = CASES[name]
    t0 = time.perf_counter()
    ph = make_phantom(case["kind"], seed=0, **case["options"])
    phantom_s = time.perf_counter() - t0
    options = case_config(name, ph.init)
    config = SegmentConfig.from_mapping(options)
    out: dict[str, Any] = {"case": name, "shape": list(ph.image.shape),
                           "spacing": list(ph.spacing), "config": options,
                           "phantom_s": phantom_s}
    prof = None
    if profile_top:
        import cProfile

        prof = cProfile.Profile()
    t0 = time.perf_counter()
    try:
        if prof is not None:
            prof.enable()
        try:
            res = segment_volume(ph.image, ph.spacing, config)
        finally:
            if prof is not None:
                prof.disable()
    except Exception as exc:  # noqa: BLE001 - a failed run is a result too
        out.update(wall_s=time.perf_counter() - t0, error=f"{type(exc).__name__}: {exc}")
    else:
        out["wall_s"] = time.perf_counter() - t0
        out["timings"] = dict(res.timings)
        out["iterations"] = res.iterations
        out["polarity"] = res.polarity
        out["m"] = [res.model.m1, res.model.m2]
        out["stages"] = [{k: h.get(k) for k in ("stage", "iterations", "evaluations",
                                                  "quadrature_order", "time_s", "converged",
                                                  "message")} for h in res.history]
        for s in out["stages"]:
            s["quadrature_order"] = list(np.atleast_1d(s["quadrature_order"]).tolist())
        m = evaluate_masks(res.mask, ph.truth, ph.spacing)
        out["metrics"] = {k: m[k] for k in ("dice", "jaccard", "hausdorff95_mm", "assd_mm")}
    out["peak_rss_mb"] = _peak_rss_mb()
    if prof is not None:
        out["profile"] = _profile_rows(prof, profile_top)
    return out


def _import_pipeline_modules() -> None:
    """Import what ``segment_volume`` imports on first use (VTK, ITK, scikit-image: about 0.5 s).

    Those imports are paid once per process, by every ``segsnake`` command; the CLI rows of the
    report (:func:`child_cli`) include them, the ``segment_volume`` rows do not.
    """
    import pyvista  # noqa: F401
    import SimpleITK  # noqa: F401
    import skimage.filters  # noqa: F401

    import segsnake.distance  # noqa: F401
    import segsnake.features  # noqa: F401
    import segsnake.rasterize  # noqa: F401


def cli_args(options: dict) -> list[str]:
    """``segsnake segment`` flags for a case's options."""
    args = []
    for key, value in options.items():
        flag = "--" + key.replace("_", "-")
        if isinstance(value, (list, tuple)):
            args += [flag, *map(str, value)]
        else:
            args += [flag, str(value)]
    return args


def child_cli(name: str) -> dict:
    """``segsnake segment`` end to end on the case's phantom written as NIfTI: the wall time of
    the whole process (interpreter start, imports, loading, segmentation, the four outputs)."""
    import tempfile

    from segsnake.commands.phantom import write_phantom
    from segsnake.phantoms import make_phantom

    case = CASES[name]
    ph = make_phantom(case["kind"], seed=0, **case["options"])
    exe = os.path.join(os.path.dirname(sys.executable), "segsnake")
    with tempfile.TemporaryDirectory() as tmp:
        write_phantom(ph, tmp)
        cmd = [exe, "segment", os.path.join(tmp, "image.nii.gz"), "--out",
               os.path.join(tmp, "out"), "--truth", os.path.join(tmp, "truth.nii.gz"), "--json",
               *cli_args(case_config(name, ph.init))]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.perf_counter() - t0
    if proc.returncode != 0:
        return {"case": name, "error": (proc.stderr.strip().splitlines() or ["?"])[-1]}
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    return {"case": name, "wall_s": wall, "timings": summary["timings"],
            "dice": summary.get("dice"), "jaccard": summary.get("jaccard")}


def _profile_rows(prof, top: int) -> list[dict]:
    """Top functions by own time, with their cumulative time and call counts."""
    import pstats

    st = pstats.Stats(prof)
    rows = []
    for (filename, line, func), (cc, nc, tt, ct, _callers) in st.stats.items():
        short = filename
        for marker in ("/site-packages/", "/lib/python3"):
            if marker in short:
                short = short.split(marker, 1)[1]
                break
        if short.startswith(ROOT):
            short = os.path.relpath(short, ROOT)
        name = func if short == "~" else f"{short}:{line}({func})"
        rows.append({"function": name, "calls": nc, "tottime_s": tt, "cumtime_s": ct,
                     "own_code": short.startswith("segsnake/")})
    by_own = sorted(rows, key=lambda r: r["tottime_s"], reverse=True)[:top]
    # segsnake's own functions by cumulative time: which stage/step the time is spent under.
    by_cum = sorted((r for r in rows if r["own_code"]), key=lambda r: r["cumtime_s"],
                    reverse=True)[:top]
    return {"own": by_own, "cumulative": by_cum}


def _median_ms(fn, calls: int) -> dict:
    times = []
    for _ in range(calls):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    times = np.asarray(times) * 1e3
    return {"median_ms": float(np.median(times)), "p10_ms": float(np.percentile(times, 10)),
            "p90_ms": float(np.percentile(times, 90))}


def child_energy(orders: list[tuple[int, int]], calls: int) -> dict:
    """Median time of FluxTerm.value_and_grad for a 9 x 9 sphere on a brain-sized lookup.

    The lookup is the one the pipeline builds for the T1 brain phantom (edge map of the dark
    CSF sheet, ``surface`` mode, scale 1.5 mm); the sphere is the ellipsoid through the brain's
    hull (twice the phantom's initial radii), i.e. where the refinement evaluates it. Parameters
    alternate between two slightly different shapes so that nothing can be reused between calls.
    """
    from segsnake.energy import FluxTerm, flux_integrand_grads
    from segsnake.features import edge_map
    from segsnake.lookup import Lookup
    from segsnake.phantoms import make_phantom
    from segsnake.surfaces import SphereModel

    ph = make_phantom("brain", seed=0, contrast="t1", noise=0.03)
    assert ph.image.shape == ENERGY_SHAPE
    sp = ph.spacing
    em = edge_map(-ph.image, sp, mode="surface", scale_mm=1.5)
    lookup = Lookup.from_field(em.f, sp)
    del em
    center = np.asarray(ph.init["center"]) * sp
    radii = 2.0 * np.asarray(ph.init["radii"]) * sp
    model = SphereModel.ellipsoid(center, radii, m1=9, m2=9)
    rng = np.random.default_rng(0)
    params = [model.params, model.params + rng.normal(0.0, 0.3, model.params.shape)]
    results = []
    for order in [(4, 4)] + [tuple(o) for o in orders if tuple(o) != (4, 4)]:
        term = FluxTerm(model, lookup, weight=-1.0, order=order)
        k = [0]

        def call() -> None:
            term.value_and_grad(params[k[0] % 2])
            k[0] += 1

        for _ in range(5):
            call()
        row = {"order": list(order), "points": int(term.weights.size), **_median_ms(call, calls)}
        # Where one call goes: the same steps as FluxTerm.value_and_grad, timed one by one.
        C = model.control_points(params[0])
        s, su, sv = term.basis.evaluate(C)
        G, dG = lookup.sample(s.reshape(-1, 3))
        G, dG = G.reshape(s.shape[:2]), dG.reshape(s.shape)
        _, g, gu, gv = flux_integrand_grads(G, dG, su, sv, term.weights, model.orientation)
        gC = term.basis.adjoint(g, gu, gv)
        n = max(calls // 4, 20)
        row["parts_ms"] = {
            "control_points": _median_ms(lambda: model.control_points(params[0]), n)["median_ms"],
            "basis.evaluate": _median_ms(lambda: term.basis.evaluate(C), n)["median_ms"],
            "lookup.sample": _median_ms(lambda: lookup.sample(s.reshape(-1, 3)), n)["median_ms"],
            "integrand": _median_ms(lambda: flux_integrand_grads(G, dG, su, sv, term.weights,
                                                                 model.orientation), n)["median_ms"],
            "basis.adjoint": _median_ms(lambda: term.basis.adjoint(g, gu, gv), n)["median_ms"],
            "to_params": _median_ms(lambda: model.grid_gradient_to_params(gC), n)["median_ms"],
        }
        results.append(row)
    return {"shape": list(ENERGY_SHAPE), "m": [9, 9], "calls": calls, "results": results}


def _run_child(args: list[str]) -> dict:
    proc = subprocess.run([sys.executable, os.path.abspath(__file__), *args],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["(no output)"]
        return {"error": f"child {' '.join(args)} exited {proc.returncode}: {tail[0]}"}
    return json.loads(proc.stdout.strip().splitlines()[-1])


# ------------------------------------------------------------------------------------------
# Report
# ------------------------------------------------------------------------------------------


def _fmt(v: Any, digits: int = 3) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def summarize(name: str, runs: list[dict]) -> dict:
    """Median wall time and timings over repeats; stages of the last successful repeat."""
    ok = [r for r in runs if "error" not in r]
    summary: dict[str, Any] = {"case": name, "repeats": len(runs), "ok": len(ok),
                               "walls_s": [r.get("wall_s") for r in runs]}
    if not ok:
        summary["error"] = runs[-1].get("error", "no run")
        return summary
    summary["wall_s"] = statistics.median(r["wall_s"] for r in ok)
    keys = sorted({k for r in ok for k in r["timings"]})
    summary["timings"] = {k: statistics.median(r["timings"].get(k, 0.0) for r in ok) for k in keys}
    last = ok[-1]
    for k in ("shape", "spacing", "config", "metrics", "stages", "iterations", "polarity", "m",
              "peak_rss_mb", "phantom_s"):
        summary[k] = last.get(k)
    if len(ok) < len(runs):
        summary["error"] = next(r["error"] for r in runs if "error" in r)
    return summary


def markdown(info: dict) -> str:
    lines = []
    m = info["machine"]
    lines.append(f"Machine: {m['nproc']} cores (affinity {m['affinity']}), {m['cpu']}, Python "
                 f"{m['python']}, numpy {m['numpy']}, scipy {m['scipy']}; segsnake at "
                 f"{m.get('commit', '?')}"
                 + (f" with local changes in {', '.join(m['segsnake_modified'])}"
                    if m.get("segsnake_modified") else "") + ".")
    lines.append(f"Command: `{info['command']}`")
    lines.append("")
    if info.get("energy"):
        e = info["energy"]
        lines.append(f"One `FluxTerm.value_and_grad` (9 x 9 sphere, lookup "
                     f"{' x '.join(map(str, e['shape']))}, median of {e['calls']} calls; goal < 2 ms):")
        lines.append("")
        lines.append("| order (u, v) | points | median (ms) | p10-p90 (ms) | control pts | "
                     "basis.evaluate | lookup.sample | integrand | basis.adjoint | to params |")
        lines.append("|---|---|---|---|---|---|---|---|---|---|")
        for r in e["results"]:
            p = r["parts_ms"]
            lines.append(
                f"| {r['order'][0]}, {r['order'][1]} | {r['points']} | {r['median_ms']:.2f} | "
                f"{r['p10_ms']:.2f}-{r['p90_ms']:.2f} | {p['control_points']:.3f} | "
                f"{p['basis.evaluate']:.3f} | {p['lookup.sample']:.3f} | {p['integrand']:.3f} | "
                f"{p['basis.adjoint']:.3f} | {p['to_params']:.3f} |")
        lines.append("")
    lines.append(f"`segment_volume` (median of {info['repeats']} fresh processes; seconds):")
    lines.append("")
    lines.append("| case | grid | goal (paper) | wall | init | edge map | lookups | optimize | "
                 "mask | Dice | Jaccard | HD95 (mm) | ASSD (mm) | iterations | runs |")
    lines.append("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for s in info["cases"]:
        c = CASES[s["case"]]
        goal = "-" if c["goal_s"] is None else f"< {c['goal_s']:g} ({c['paper_s']:g})"
        if "wall_s" not in s:
            lines.append(f"| {s['case']} | | {goal} | failed: {s['error']} |" + " |" * 11)
            continue
        t, mt = s["timings"], s["metrics"]
        lines.append(
            f"| {s['case']} | {'x'.join(map(str, s['shape']))} | {goal} | **{s['wall_s']:.2f}** | "
            f"{t.get('init_s', 0):.2f} | {t.get('edge_map_s', 0):.2f} | {t.get('lookup_s', 0):.2f} | "
            f"{t.get('optimize_s', 0):.2f} | {t.get('mask_s', 0):.2f} | {mt['dice']:.3f} | "
            f"{mt['jaccard']:.3f} | {mt['hausdorff95_mm']:.2f} | {mt['assd_mm']:.2f} | "
            f"{s['iterations']} | {s['ok']}/{s['repeats']} "
            f"({', '.join(_fmt(w, 1) for w in s['walls_s'])}) |")
    lines.append("")
    if info.get("cli"):
        lines.append("`segsnake segment IMAGE --out DIR --truth MASK --json` end to end (one run per "
                     "case; the process's wall time from start to exit, and its summary's "
                     "timings: loading, `segment_volume`, writing the four outputs):")
        lines.append("")
        lines.append("| case | process wall (s) | inside segment_file (s) | load | segment_volume | "
                     "write | Dice | Jaccard |")
        lines.append("|---|---|---|---|---|---|---|---|")
        for c in info["cli"]:
            if "wall_s" not in c:
                lines.append(f"| {c.get('case', '?')} | failed: {c.get('error')} | | | | | | |")
                continue
            t = c["timings"]
            inner = sum(v for k, v in t.items() if k not in ("load_s", "write_s", "total_s"))
            lines.append(f"| {c['case']} | **{c['wall_s']:.2f}** | {t['total_s']:.2f} | "
                         f"{t['load_s']:.2f} | {inner:.2f} | {t['write_s']:.2f} | "
                         f"{_fmt(c['dice'])} | {_fmt(c['jaccard'])} |")
        lines.append("")
    lines.append("Stages (last repeat): iterations / energy evaluations, quadrature order, seconds, "
                 "ms per evaluation:")
    lines.append("")
    lines.append("| case | stage | iterations | evaluations | order (u, v) | time (s) | ms / eval |")
    lines.append("|---|---|---|---|---|---|---|")
    for s in info["cases"]:
        for st in s.get("stages") or []:
            per = 1e3 * st["time_s"] / max(st["evaluations"] or 1, 1)
            lines.append(f"| {s['case']} | {st['stage']} | {st['iterations']} | "
                         f"{st['evaluations']} | {', '.join(map(str, st['quadrature_order']))} | "
                         f"{st['time_s']:.2f} | {per:.1f} |")
    if info.get("profiles"):
        lines.append("")
        for name, prof in info["profiles"].items():
            if "profile" not in prof:
                continue
            for key, title in (("own", "top functions by own time"),
                               ("cumulative", "segsnake functions by cumulative time")):
                lines.append(f"cProfile, {name} (wall {prof['wall_s']:.2f} s under the "
                             f"profiler), {title}:")
                lines.append("")
                lines.append("| function | calls | own (s) | cumulative (s) |")
                lines.append("|---|---|---|---|")
                for r in prof["profile"][key]:
                    lines.append(f"| `{r['function']}` | {r['calls']} | {r['tottime_s']:.2f} | "
                                 f"{r['cumtime_s']:.2f} |")
                lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", choices=list(CASES), default=list(CASES),
                    help="which segment_volume cases (default all)")
    ap.add_argument("--repeats", type=int, default=3, help="fresh processes per case (default 3)")
    ap.add_argument("--calls", type=int, default=200, help="energy calls per order (default 200)")
    ap.add_argument("--profile-top", type=int, default=12,
                    help="functions listed per cProfile run (0: no profiling)")
    ap.add_argument("--no-energy", action="store_true", help="skip the energy benchmark")
    ap.add_argument("--no-cli", action="store_true",
                    help="skip the end-to-end `segsnake segment` runs")
    ap.add_argument("--json", metavar="PATH", help="also write the raw numbers here")
    # Internal: one measurement in this process, JSON on stdout.
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--orders", default="", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.child and args.child.startswith("cli:"):
        print(json.dumps(child_cli(args.child[4:])))
        return 0
    if args.child == "energy":
        orders = [tuple(int(x) for x in o.split("x")) for o in args.orders.split(",") if o]
        print(json.dumps(child_energy(orders, args.calls)))
        return 0
    if args.child:
        print(json.dumps(child_case(args.child, args.profile_top)))
        return 0

    info: dict[str, Any] = {"machine": machine(), "repeats": args.repeats,
                            "command": " ".join([os.path.relpath(sys.executable, ROOT)
                                                 if sys.executable.startswith(ROOT)
                                                 else sys.executable,
                                                 os.path.relpath(__file__, ROOT), *sys.argv[1:]])}
    cases = []
    for name in args.cases:
        runs = []
        for r in range(args.repeats):
            runs.append(_run_child(["--child", name, "--profile-top", "0"]))
            print(f"[bench_snake] {name} run {r + 1}/{args.repeats}: "
                  f"{_fmt(runs[-1].get('wall_s'), 2)} s {runs[-1].get('error', '')}",
                  file=sys.stderr, flush=True)
        cases.append(summarize(name, runs))
    info["cases"] = cases
    if not args.no_cli:
        info["cli"] = []
        for name in args.cases:
            info["cli"].append(_run_child(["--child", f"cli:{name}"]))
            print(f"[bench_snake] {name} CLI: {_fmt(info['cli'][-1].get('wall_s'), 2)} s "
                  f"{info['cli'][-1].get('error', '')}", file=sys.stderr, flush=True)
    if args.profile_top > 0:
        info["profiles"] = {}
        for name in args.cases:
            info["profiles"][name] = _run_child(["--child", name, "--profile-top",
                                                 str(args.profile_top)])
            print(f"[bench_snake] {name} profiled", file=sys.stderr, flush=True)
    if not args.no_energy:
        orders = sorted({tuple(st["quadrature_order"]) for s in cases for st in s.get("stages") or []
                         if len(st["quadrature_order"]) == 2})
        # The energy benchmark is about the sphere: orders of the cylinder run are for an 8 x 4
        # cylinder, still informative as point counts on a 9 x 9 sphere.
        info["energy"] = _run_child(["--child", "energy", "--calls", str(args.calls),
                                     "--orders", ",".join(f"{u}x{v}" for u, v in orders)])
        print("[bench_snake] energy done", file=sys.stderr, flush=True)
        if "error" in info["energy"]:
            print(f"[bench_snake] energy: {info['energy']['error']}", file=sys.stderr)
            info["energy"] = None
    return report(info, args.json, markdown)


if __name__ == "__main__":
    sys.exit(main())
