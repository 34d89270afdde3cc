"""Run the segsnake command line with every flux gradient perturbed by ``1 + EPS * N(0, 1)``.

The gradient perturbation of ``bench_robustness.py --perturb`` for benchmarks that call the
command line (``bench_tubes.py --perturb``)::

    .venv/bin/python benchmarks/perturbed_cli.py EPS SEED segment IMAGE --out DIR ...

Exits with :data:`UNSUPPORTED` (and a one-line message) when the installed segsnake has no
``energy.FluxTerm`` to perturb; otherwise with the command's own exit status.
"""

from __future__ import annotations

import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

#: Exit status when this segsnake's energy cannot be perturbed this way.
UNSUPPORTED = 97


def main(argv: list[str]) -> int:
    if len(argv) < 3:
        print("usage: perturbed_cli.py EPS SEED SEGSNAKE-ARGS...", file=sys.stderr)
        return 2
    eps, seed = float(argv[0]), int(argv[1])
    from segsnake import energy
    from segsnake.cli import main as segsnake_main

    if not hasattr(getattr(energy, "FluxTerm", None), "value_and_grad"):
        print("perturbed_cli: this segsnake has no energy.FluxTerm.value_and_grad to perturb",
              file=sys.stderr)
        return UNSUPPORTED
    from bench_robustness import perturbed_gradients

    with perturbed_gradients(eps, seed):
        return int(segsnake_main(argv[2:]) or 0)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
