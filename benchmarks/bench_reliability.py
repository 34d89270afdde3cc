"""Reliability measurements of issue 18: how fast a signal ends a run, two runs on one --out.

    .venv/bin/python benchmarks/bench_reliability.py [--instants 20] [--seed 18] [--json out.json]

1. Signal latency: ``segment`` on the blob phantom (64^3, and 128^3) at the default ``--scale`` and
   at the largest one allowed (a quarter of the image's extent), SIGINT or SIGTERM at seeded
   random instants of the run: exit code, "interrupted" line, no traceback, and the time from the
   signal to the process's end; also the run's length without a signal.
2. Two concurrent runs on one ``--out`` (with and without ``--overwrite`` on an existing set):
   exit codes, how long the second took to be refused, and whether one complete set is left.

Everything runs in a temporary directory; the numbers are printed as a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SEGSNAKE = [sys.executable, "-m", "segsnake.cli"]


def run(args: list[str]) -> tuple[int, str, float]:
    t0 = time.monotonic()
    proc = subprocess.run(SEGSNAKE + args, capture_output=True, text=True)
    return proc.returncode, proc.stderr, time.monotonic() - t0


def kill_at(args: list[str], instant: float, sig: int) -> dict:
    proc = subprocess.Popen(SEGSNAKE + args, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    time.sleep(instant)
    t0 = time.monotonic()
    proc.send_signal(sig)
    _, err = proc.communicate()
    return {"instant_s": instant, "signal": signal.Signals(sig).name, "code": proc.returncode,
            "latency_s": time.monotonic() - t0, "traceback": "Traceback" in err,
            "line": err.strip()}


def latency(work: Path, image: Path, scale: float | None, instants: int, seed: int) -> dict:
    base = [str(image), "--quiet", "--overwrite"] + (["--scale", f"{scale:g}"] if scale else [])
    code, err, full = run(["segment", *base[:1], "--out", str(work / "full"), *base[1:]])
    assert code == 0, err
    rng = random.Random(seed)
    rows = []
    for i in range(instants):
        sig = (signal.SIGINT, signal.SIGTERM)[i % 2]
        rows.append(kill_at(["segment", *base[:1], "--out", str(work / "killed"), *base[1:]],
                            rng.uniform(0.15, full), sig))
    killed = [r for r in rows if r["code"] != 0]
    lat = [r["latency_s"] for r in killed]
    return {"image": image.parent.name, "scale": scale, "run_s": full, "instants": instants,
            "interrupted": len(killed),
            "codes": sorted({r["code"] for r in rows}),
            "tracebacks": sum(r["traceback"] for r in rows),
            "latency_median_s": statistics.median(lat) if lat else None,
            "latency_max_s": max(lat) if lat else None,
            "left_behind": sorted(os.listdir(work / "killed")) if (work / "killed").exists() else []}


def concurrent(work: Path, image: Path, overwrite: bool) -> dict:
    out = work / ("conc-ow" if overwrite else "conc")
    extra = ["--overwrite"] if overwrite else []
    if overwrite:
        assert run(["segment", str(image), "--out", str(out), "--quiet"])[0] == 0
    first = subprocess.Popen(SEGSNAKE + ["segment", str(image), "--out", str(out), "--quiet",
                                         "--m1", "8", "--m2", "8", *extra],
                             stderr=subprocess.PIPE, text=True)
    time.sleep(1.0)  # the first holds the lock by now (it takes it before reading its image)
    code2, err2, t2 = run(["segment", str(image), "--out", str(out), "--quiet", *extra])
    _, err1 = first.communicate()
    names = sorted(os.listdir(out))
    snake = json.loads((out / "snake.json").read_text())
    return {"overwrite": overwrite, "first_code": first.returncode, "second_code": code2,
            "second_s": t2, "second_line": err2.strip(), "files": names,
            "set_of_first": snake["settings"]["m1"] == 8}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--instants", type=int, default=20)
    ap.add_argument("--seed", type=int, default=18)
    ap.add_argument("--json")
    args = ap.parse_args()
    from machine import machine_info

    print(json.dumps(machine_info()), flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        images = {}
        for n in (64, 128):
            d = work / f"blob{n}"
            code, err, _ = run(["phantom", "blob", "--out", str(d), "--seed", "1", "--noise", "0.2",
                                "--shape", str(n), str(n), str(n), "--quiet"])
            assert code == 0, err
            images[n] = d / "image.nii.gz"
        results = {"latency": [], "concurrent": []}
        for n, image in images.items():
            for scale in (None, n / 4):
                r = latency(work, image, scale, args.instants, args.seed)
                results["latency"].append(r)
                print(json.dumps(r), flush=True)
        for ow in (False, True):
            r = concurrent(work, images[64], ow)
            results["concurrent"].append(r)
            print(json.dumps(r), flush=True)
    print("\n| image | --scale (mm) | run (s) | signals | interrupted | exit codes | tracebacks "
          "| latency median / max (s) | left in --out |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in results["latency"]:
        print(f"| {r['image']} | {r['scale'] or 'default'} | {r['run_s']:.1f} | {r['instants']} | "
              f"{r['interrupted']} | {', '.join(map(str, r['codes']))} | {r['tracebacks']} | "
              f"{r['latency_median_s']:.3f} / {r['latency_max_s']:.3f} | "
              f"{' '.join(r['left_behind']) or 'nothing'} |")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
