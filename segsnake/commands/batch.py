"""``segsnake batch RUNS.yaml``: run many segmentations from one YAML file, resumably.

The batch file's format and the guarantees (validation first, one process per case, results
appended and fsynced as cases finish, ``--resume``) are described in :mod:`segsnake.batch`.
"""

from __future__ import annotations

import argparse
import sys

from segsnake.commands import positive_int
from segsnake.commands.reporting import add_output_options, emit, progress_off, warn
from segsnake.errors import BatchError, ConfigError

HELP = "run many segmentations from a YAML file (local process pool or a Dask cluster)"

EPILOG = """\
The YAML file has 'cases:' (each with 'image:', optional 'name:', 'truth:' and 'truth_label:',
and any 'segment' option as an override), optional 'defaults:' (segment options for every case)
and 'output_dir:' (relative to the YAML file). Before any case runs, the file is validated and
every image, truth and prior it names must exist (the missing ones are listed with their line).
Results are appended to OUT/results.csv and OUT/results.jsonl as cases finish; each case's outputs
go to OUT/<case name>/.
--resume keeps the cases recorded 'ok' and runs all others again, failed ones included.
Exit codes: 0 all cases ok, 2 invalid batch file, 3 images, truths or priors missing,
5 results/outputs not writable, 6 some cases failed (see results.csv).
"""


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a number of seconds > 0, got {text}")
    return value


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    parser = subparsers.add_parser("batch", help=HELP, description=HELP, epilog=EPILOG,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", metavar="RUNS.yaml", help="batch file (defaults, cases, output_dir)")
    parser.add_argument("--workers", "-j", type=positive_int, default=None, metavar="N",
                        help="cases running at once on this machine (default: number of CPUs)")
    parser.add_argument("--scheduler", metavar="ADDRESS", default=None,
                        help="send the cases to a running dask.distributed scheduler "
                             "(e.g. tcp://10.0.0.5:8786) instead of local processes")
    parser.add_argument("--resume", action="store_true",
                        help="continue an earlier run: skip cases recorded ok, run the others")
    parser.add_argument("--overwrite", action="store_true",
                        help="start again over earlier results and case outputs")
    parser.add_argument("--out", metavar="DIR", default=None,
                        help="output directory (overrides output_dir in the YAML file)")
    parser.add_argument("--case-timeout", type=_positive_float, default=None, metavar="SECONDS",
                        help="stop a case that runs longer and record it as failed (local runs)")
    add_output_options(parser)
    # For plug-ins and tests: another case function, 'module:function' or 'file.py:function'.
    parser.add_argument("--runner", default=None, help=argparse.SUPPRESS)
    parser.set_defaults(func=run)
    return parser


def run(args: argparse.Namespace) -> int:
    from segsnake.batch import load_batch, run_batch
    from segsnake.parallel import threads

    threads()  # a bad SEGSNAKE_NUM_THREADS stops here, before any work

    if args.resume and args.overwrite:
        raise ConfigError("--resume and --overwrite contradict each other: pick one")
    if args.scheduler and args.case_timeout is not None:
        raise ConfigError("--case-timeout applies to local runs only, not with --scheduler")
    spec = load_batch(args.runs, output_dir=args.out)  # validates everything before any work
    report = run_batch(spec, workers=args.workers, scheduler=args.scheduler, resume=args.resume,
                       overwrite=args.overwrite, runner=args.runner,
                       case_timeout=args.case_timeout, quiet=progress_off(args),
                       on_warning=lambda case, text: warn("batch", [f"case {case}: {text}"]))
    counts = {"total": report.total, "ok": report.ok, "failed": report.failed,
              "skipped": report.skipped, "failed_cases": report.failed_cases,
              "output_dir": report.output_dir, "results_csv": report.results_csv,
              "results_jsonl": report.results_jsonl}
    ran = report.total - report.skipped
    skipped = f", {report.skipped} already done" if report.skipped else ""
    lines = [f"{report.total} cases: {report.ok} ok, {report.failed} failed ({ran} run{skipped}); "
             f"results in {report.results_csv}"]
    if report.failed:
        if progress_off(args):
            # (the progress lists each failed case with its message as it ends; without it,
            # they are listed here, before the error line)
            for name in report.failed_cases:
                sys.stderr.write(f"segsnake batch: case {name} failed: {report.errors[name]}\n")
        if not args.json:  # with --json the error object carries the counts instead
            emit(args, counts, lines)
        raise BatchError(f"{report.failed} of {report.total} cases failed "
                         f"(see {report.results_csv})", file=report.results_csv, details=counts)
    emit(args, counts, lines)
    return 0
