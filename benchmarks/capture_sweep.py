"""The sweep behind ``edge_stages.CAPTURE_CONTINUATION``: the fraction of its smoothing width at which
the edge stages' capture runs a second time (docs/design.md, "The edge stages").

    .venv/bin/python benchmarks/capture_sweep.py [--values 0.33 0.5 0.67 1] [--perturb 1e-12]

For each value the module constant is set in this process (a sweep of a constant, not an option
users have; 1 runs the capture again at the same width, which stops at once: no continuation),
and the ``tubes`` and ``table72`` suites of ``bench_robustness.py`` (hollow cylinders, the edge
stages) are segmented exactly and with every flux gradient perturbed by ``1 + EPS N(0, 1)``.
Prints, per value and suite, how many cases reach their goal exactly and perturbed, the least
score and the largest difference between the two.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_robustness import cases, perturbed_gradients, run_case  # noqa: E402
from segsnake import edge_stages  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--values", type=float, nargs="+", default=[0.33, 0.5, 0.67, 1.0])
    ap.add_argument("--perturb", type=float, default=1e-12)
    args = ap.parse_args()
    print("| continuation | suite | reach their goal | perturbed | least | largest difference |")
    print("|---|---|---|---|---|---|")
    for value in args.values:
        edge_stages.CAPTURE_CONTINUATION = value
        for suite in ("tubes", "table72"):
            exact, perturbed = [], []
            for case in cases(suite, []):
                exact.append(run_case(case)["score"])
                with perturbed_gradients(args.perturb, 0):
                    perturbed.append(run_case(case)["score"])
            goals = [case["goal"] for case in cases(suite, [])]
            ok = sum(s >= g for s, g in zip(exact, goals))
            ok_p = sum(s >= g for s, g in zip(perturbed, goals))
            diff = max(abs(a - b) for a, b in zip(exact, perturbed))
            print(f"| {value:g} | {suite} | {ok} of {len(goals)} | {ok_p} of {len(goals)} | "
                  f"{min(exact):.4f} | {diff:.4f} |", flush=True)


if __name__ == "__main__":
    main()
