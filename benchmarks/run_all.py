"""Run every ``benchmarks/bench_*.py`` script in turn (``make bench``).

Each script runs in its own process with this interpreter and prints its own markdown report;
this runner prints a header per script, passes nothing on, and exits non-zero when any script
failed. Benchmarks are run by hand (they take minutes), never by the test suite.

Usage::

    .venv/bin/python benchmarks/run_all.py                 # every bench_*.py, sorted by name
    .venv/bin/python benchmarks/run_all.py snake peers     # only bench_snake.py, bench_peers.py
    .venv/bin/python benchmarks/run_all.py --list
"""

from __future__ import annotations

import argparse
import glob
import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))


def scripts() -> list[str]:
    """The benchmark scripts, sorted by file name."""
    return sorted(glob.glob(os.path.join(HERE, "bench_*.py")))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="*",
                    help="run only these (bench_NAME.py; default: all)")
    ap.add_argument("--list", action="store_true", help="list the scripts and exit")
    args = ap.parse_args(argv)
    found = scripts()
    by_name = {os.path.basename(p)[len("bench_"):-len(".py")]: p for p in found}
    if args.list:
        print("\n".join(by_name))
        return 0
    unknown = [n for n in args.names if n not in by_name]
    if unknown:
        print(f"run_all: unknown benchmark(s) {', '.join(unknown)} "
              f"(available: {', '.join(by_name)})", file=sys.stderr)
        return 2
    chosen = [by_name[n] for n in args.names] if args.names else found
    failed = []
    t_all = time.perf_counter()
    for path in chosen:
        name = os.path.basename(path)
        print(f"\n## {name}\n", flush=True)
        t0 = time.perf_counter()
        rc = subprocess.run([sys.executable, path]).returncode
        print(f"\n({name}: exit {rc}, {time.perf_counter() - t0:.0f} s)", flush=True)
        if rc != 0:
            failed.append(name)
    print(f"\nAll benchmarks: {time.perf_counter() - t_all:.0f} s"
          + (f"; failed: {', '.join(failed)}" if failed else ""), flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
