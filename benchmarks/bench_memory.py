"""Peak memory of ``segsnake segment`` against the input's float32 size (issue 18), and the sweep
of the allocator's mmap threshold (segsnake/allocator.py).

    .venv/bin/python benchmarks/bench_memory.py [--cases colin27 ball256 ball512]
        [--thresholds default dynamic 4 8 16 32] [--repeats 1]

Each run is a fresh process (``segsnake segment ... -q``): its peak resident set size (the
kernel's ``ru_maxrss`` of the child), wall time, user and system CPU time and minor page faults.
``default`` is the program as shipped; ``dynamic`` leaves glibc's adaptive threshold; a number is
a fixed threshold in MiB. Cases:

- ``colin27``: the real-anatomy benchmark's T1 head (181 x 217 x 181, needs
  ``make bench-real-data``), the brain with no click;
- ``ball256``: ``segsnake phantom ball --shape 256 256 256`` (a ball filling most of the
  volume), from the phantom's own initial sphere;
- ``ball512``: a 512^3 volume with a 12 mm ball in it (needs about 1.5 GB).

Prints a Markdown table; "x input" is the peak over the input's float32 size.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REAL = Path.home() / ".cache" / "segsnake" / "real" / "cases"
RUN = """
import sys
from segsnake.allocator import return_freed_memory
mode = sys.argv[1]
if mode not in ("default", "dynamic"):
    assert return_freed_memory(int(float(mode) * 2**20))
from segsnake.cli import main
sys.exit(main(sys.argv[2:], exit_process=mode == "default"))
"""


BALL512 = """
import sys, numpy as np, nibabel as nib
n = 512
g = np.indices((n, n, n), dtype=np.float32)
r = np.sqrt(sum((g[a] - 300.0) ** 2 for a in range(3)))
del g
image = np.where(r < 12.0, 1.0, 0.0).astype(np.float32)
image += np.random.default_rng(512).normal(0, 0.1, image.shape).astype(np.float32)
nib.save(nib.Nifti1Image(image, np.eye(4)), sys.argv[1])
"""


def make_case(name: str, tmp: Path) -> tuple[list[str], tuple[int, int, int]]:
    """The ``segment`` arguments of a case and its grid shape."""
    if name == "colin27":
        image = REAL / "colin27_t1.nii.gz"
        if not image.exists():
            raise SystemExit(f"{image} missing: run `make bench-real-data` first")
        return [str(image)], (181, 217, 181)
    if name == "ball256":
        out = tmp / "ball256"
        subprocess.run([sys.executable, "-m", "segsnake.cli", "phantom", "ball", "--shape", "256",
                        "256", "256", "--out", str(out), "-q"], check=True)
        init = json.loads((out / "phantom.json").read_text())["init"]
        return [str(out / "image.nii.gz"), "--center", *map(str, init["center"]), "--radii",
                *map(str, init["radii"])], (256, 256, 256)
    if name == "ball512":
        # (made in a child process: a child's peak counts the parent's resident memory at its
        # start, which the image's temporaries would inflate)
        path = tmp / "ball512.nii.gz"
        subprocess.run([sys.executable, "-c", BALL512, str(path)], check=True)
        return [str(path), "--center", "300", "300", "300", "--radii", "6", "6", "6"], (512,) * 3
    raise SystemExit(f"unknown case {name}")


def measure(args: list[str], mode: str, out: Path) -> dict:
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-c", RUN, mode, "segment", *args, "--out", str(out),
                             "--overwrite", "-q"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - t0
    err = proc.stderr.read().decode()
    proc.stdout.close()
    proc.stderr.close()
    if proc.returncode != 0:
        raise SystemExit(f"segment failed ({mode}): {err.strip()[-300:]}")
    return {"peak_mb": usage.ru_maxrss / 1024, "wall_s": wall, "user_s": usage.ru_utime,
            "sys_s": usage.ru_stime, "faults": usage.ru_minflt}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="+", default=["colin27", "ball256"])
    ap.add_argument("--thresholds", nargs="+", default=["default", "dynamic", "4", "8", "16", "32"])
    ap.add_argument("--repeats", type=int, default=1)
    opts = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="segsnake-bench-memory-") as tmp:
        tmp = Path(tmp)
        print("| case | input (float32) | threshold | peak RSS | x input | wall | user | sys "
              "| minor faults |")
        print("|---|---|---|---|---|---|---|---|---|")
        for case in opts.cases:
            args, shape = make_case(case, tmp)
            size_mb = 4 * float(np.prod(shape)) / 2**20
            for mode in opts.thresholds:
                for _ in range(opts.repeats):
                    m = measure(args, mode, tmp / "out")
                    label = mode if mode in ("default", "dynamic") else f"{mode} MiB"
                    print(f"| {case} {'x'.join(map(str, shape))} | {size_mb:.1f} MB | {label} "
                          f"| {m['peak_mb']:.0f} MB | {m['peak_mb'] / size_mb:.1f} "
                          f"| {m['wall_s']:.1f} s | {m['user_s']:.1f} s | {m['sys_s']:.2f} s "
                          f"| {m['faults']} |", flush=True)


if __name__ == "__main__":
    main()
