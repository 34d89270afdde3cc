"""Run many segmentations from one YAML file, locally or on a Dask cluster, without losing results.

A batch file looks like::

    output_dir: ../out/brain-sweep      # relative to this file; --out overrides it
    defaults:                           # any `segsnake segment` option (SegmentConfig keys)
      shape: sphere
      m1: 9
    cases:
      - name: t1-n3-rf20                # optional: defaults to the image's file name
        image: ../data/t1_n3_rf20.nii.gz
        truth: ../data/truth.nii.gz     # optional: adds dice/jaccard/hd95_mm/assd_mm
        truth_label: 17                 # optional: the truth is a label map, compare with label 17
        scale: 1.5                      # per-case override of any option

Guarantees, in the order they matter to someone running hundreds of scans:

* The whole file is validated before anything runs (every case's merged options, duplicate names);
  errors point at ``FILE:LINE:COL``. Then every image, truth and prior it names must exist: the
  missing ones are all listed, each with its line, and nothing runs
  (:mod:`segsnake.batch_inputs`). A corrupt image is that case's failure, recorded, and the rest
  go on.
* Each case runs in its own process (one fresh process per case), so a crash, a segfault or the
  out-of-memory killer in one case takes only that case down.
* ``results.jsonl`` (the source of truth) and ``results.csv`` in the output directory get one
  record per finished case, appended, flushed and fsynced immediately: a killed run loses only
  the cases still running.
* ``--resume`` keeps the cases already recorded ``ok``, runs every other case again (failed ones
  included: a failure may have been transient, and a deterministic one fails again quickly), and
  rewrites both files first so that each case appears exactly once.
* ``--scheduler ADDRESS`` sends the same case function to an existing ``dask.distributed``
  cluster instead of the local process pool.

Each case's outputs go to ``output_dir/<case name>/``. The function that runs one case is
:func:`run_case` (which calls :func:`segsnake.runner.segment_file`); another can be named with
``runner="package.module:function"`` or ``"/path/to/file.py:function"``: it receives the case dict
(``name``, ``image``, ``truth``, ``truth_label``, ``out_dir``, ``config``, ``overwrite``) and
returns a JSON-able summary dict.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import datetime as _dt
import hashlib
import importlib
import importlib.util
import io
import json
import multiprocessing as mp
import multiprocessing.connection
import os
import re
import signal
import socket
import sys
import tempfile
import threading
import time
import traceback
from collections import deque
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

from segsnake.allocator import return_freed_memory
from segsnake.config import (
    LineDict,
    LineList,
    PATH_KEYS,
    SegmentConfig,
    load_yaml,
    locate,
    resolve_config_paths,
    suggest,
)
from segsnake import cancel
from segsnake.errors import ConfigError, InputError, OutputError, SegsnakeError
from segsnake.outdir import fsync_dir, make_dirs, recover, remove_empty_dirs, try_lock
from segsnake.jsonable import jsonable as _jsonable
from segsnake.parallel import set_threads, threads as parallel_threads

__all__ = [
    "BatchCase",
    "BatchSpec",
    "BatchReport",
    "load_batch",
    "run_batch",
    "run_case",
    "execute_case",
    "tidy_case_dirs",
    "read_results",
    "RESULT_COLUMNS",
    "DEFAULT_RUNNER",
]

DEFAULT_RUNNER = "segsnake.batch:run_case"
RESULTS_JSONL = "results.jsonl"
RESULTS_CSV = "results.csv"
LOCK_NAME = ".segsnake-batch.lock"

TOP_KEYS = ("output_dir", "defaults", "cases")
CASE_KEYS = ("name", "image", "truth", "truth_label")
METRIC_KEYS = ("dice", "jaccard", "hd95_mm", "assd_mm", "volume_difference_rel")
# Result column -> the summary keys it is read from, first found wins (segsnake.metrics names the
# 95th-percentile Hausdorff distance "hausdorff95_mm").
_SUMMARY_ALIASES = {"hd95_mm": ("hd95_mm", "hausdorff95_mm")}
RESULT_COLUMNS = (
    "case", "status", *METRIC_KEYS, "iterations", "energy", "time_s", "exit_code", "error_type",
    "error", "image", "truth", "truth_label", "out_dir", "host", "finished", "timings",
)
# A case name becomes a directory name: one safe path component.
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._+-]{0,127}$")
_MAX_ERROR_CHARS = 500


# --------------------------------------------------------------------------------------------------
# The batch file
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class BatchCase:
    """One validated case: absolute paths and the fully merged options."""

    name: str
    image: str
    truth: str | None
    config: SegmentConfig
    line: int | None = None
    truth_label: int | None = None
    # "FILE:LINE:COL" where each input file (image, truth, prior) is written, for messages.
    where: dict[str, str] = dataclasses.field(default_factory=dict, compare=False)

    def to_job(self, output_dir: str | os.PathLike[str], *, overwrite: bool = False) -> dict[str, Any]:
        """The picklable dict a runner receives."""
        return {
            "name": self.name,
            "image": self.image,
            "truth": self.truth,
            "truth_label": self.truth_label,
            "out_dir": str(Path(output_dir) / self.name),
            "config": self.config.to_dict(),
            "overwrite": bool(overwrite),
        }


@dataclasses.dataclass(frozen=True)
class BatchSpec:
    """A validated batch file."""

    path: str
    output_dir: str
    cases: tuple[BatchCase, ...]


def _stem(path: str) -> str:
    name = Path(path).name
    for suffix in (".nii.gz", ".nii", ".gz", ".mha", ".mhd", ".nrrd"):
        if name.lower().endswith(suffix):
            return name[: -len(suffix)]
    return Path(name).stem or name


def _normalise_keys(d: LineDict) -> LineDict:
    """Copy of ``d`` with ``-`` read as ``_`` in keys, keeping positions (``max-iter`` = ``max_iter``)."""
    out = LineDict()
    out.mark = d.mark
    for key, value in d.items():
        k = key.replace("-", "_") if isinstance(key, str) else key
        out[k] = value
        out.key_marks[k] = d.key_marks.get(key, d.mark)  # type: ignore[assignment]
    return out


def load_batch(path: str | os.PathLike[str], *, output_dir: str | os.PathLike[str] | None = None,
               check_files: bool = True) -> BatchSpec:
    """Read and validate a batch YAML file completely, before anything runs.

    Parameters
    ----------
    path : str or path-like
        The batch file. Relative paths inside it are relative to its directory.
    output_dir : str or path-like, optional
        Overrides the file's ``output_dir`` (relative to the current directory). Without either,
        results go to ``<file stem>-results`` beside the file.
    check_files : bool
        Also require every image, truth and prior to exist and be readable, as seen from this
        machine (:func:`segsnake.batch_inputs.check_inputs`).

    Returns
    -------
    BatchSpec

    Raises
    ------
    ConfigError
        Syntax error, unknown key (with a suggestion), wrong type or range, duplicate case name,
        no cases. The message names ``FILE:LINE:COL`` of the first problem and counts the others.
    InputError
        A valid file whose images, truths or priors are missing (``check_files``): every one is
        listed with its ``FILE:LINE:COL``.
    """
    p = Path(path)
    src = str(p)
    data = load_yaml(p)
    base = p.resolve().parent
    errors: list[str] = []

    if data is None:
        raise ConfigError(f"{src}: empty batch file (expected 'cases:' and optionally 'defaults:', "
                          "'output_dir:')")
    if not isinstance(data, LineDict):
        raise ConfigError(f"{locate(src, data)}: a batch file must be a mapping with 'cases:', "
                          "'defaults:' and 'output_dir:'")
    for key in data:
        if key not in TOP_KEYS:
            errors.append(f"{locate(src, data, key)}: unknown key {key!r}{suggest(key, TOP_KEYS)} "
                          f"(a batch file has {', '.join(TOP_KEYS)})")

    # output_dir
    out: Path
    if output_dir is not None:
        out = Path(output_dir).expanduser().resolve()
    elif data.get("output_dir") is not None:
        value = data["output_dir"]
        if not isinstance(value, str) or not value:
            errors.append(f"{locate(src, data, 'output_dir')}: output_dir: must be a directory path")
            out = base / f"{_stem(src)}-results"
        else:
            out = (base / Path(value).expanduser()).resolve()
    else:
        out = base / f"{_stem(src)}-results"

    # defaults
    defaults = data.get("defaults")
    if defaults is None:
        defaults = LineDict()
    elif not isinstance(defaults, LineDict):
        errors.append(f"{locate(src, data, 'defaults')}: defaults: must be a mapping of "
                      "segment options")
        defaults = LineDict()
    else:
        defaults = _normalise_keys(defaults)
        for key in list(defaults):
            if key in CASE_KEYS:
                errors.append(f"{locate(src, defaults, key)}: {key!r} belongs to a case, "
                              "not to defaults")
                del defaults[key]
        try:  # on its own first, so an error there is reported once, at its line
            SegmentConfig.from_mapping(defaults, source=src)
        except ConfigError as exc:
            errors.append(str(exc))
            defaults = LineDict()

    # cases
    cases_raw = data.get("cases")
    cases: list[BatchCase] = []
    if cases_raw is None or (isinstance(cases_raw, list) and not cases_raw):
        errors.append(f"{locate(src, data, 'cases') if 'cases' in data else src}: "
                      "no cases: add a 'cases:' list")
        cases_raw = []
    elif not isinstance(cases_raw, LineList):
        errors.append(f"{locate(src, data, 'cases')}: cases: must be a list ('- image: ...' items)")
        cases_raw = []

    first_line: dict[str, int] = {}
    valid_case_keys = CASE_KEYS + SegmentConfig.keys()
    for index, raw in enumerate(cases_raw):
        where_case = locate(src, cases_raw, index)
        if not isinstance(raw, LineDict):
            errors.append(f"{where_case}: case {index + 1}: must be a mapping with at least 'image:'")
            continue
        raw = _normalise_keys(raw)
        bad = False
        for key in raw:
            if key not in valid_case_keys:
                errors.append(f"{locate(src, raw, key)}: unknown option {key!r}"
                              f"{suggest(key, valid_case_keys)}")
                bad = True
        image = raw.get("image")
        if not isinstance(image, str) or not image:
            where = locate(src, raw, "image") if "image" in raw else where_case
            errors.append(f"{where}: case {index + 1}: 'image:' must be a file path")
            bad = True
        truth = raw.get("truth")
        if truth is not None and (not isinstance(truth, str) or not truth):
            errors.append(f"{locate(src, raw, 'truth')}: truth: must be a file path or null")
            bad = True
        truth_label = raw.get("truth_label")
        if truth_label is not None:
            where_label = locate(src, raw, "truth_label")
            if isinstance(truth_label, bool) or not isinstance(truth_label, int):
                errors.append(f"{where_label}: truth_label: must be an integer (a label of the "
                              f"truth's label map), got {truth_label!r}")
                bad = True
            elif truth is None:
                errors.append(f"{where_label}: truth_label needs a 'truth:' (the label map it "
                              "selects from)")
                bad = True
        name = raw.get("name")
        name_key = "name" if "name" in raw else "image"
        if name is None and isinstance(image, str) and image:
            name = _stem(image)
        where_name = locate(src, raw, name_key)
        name_line = raw.key_marks.get(name_key, raw.mark or (0, 0))[0]
        if isinstance(name, (int, float)) and not isinstance(name, bool):
            name = str(name)
        if not isinstance(name, str) or not _NAME_RE.match(name):
            if name is not None or not bad:
                errors.append(f"{where_name}: case name {name!r}: must be 1-128 letters, digits, "
                              "'.', '_', '+' or '-' (it becomes a directory name)")
            bad = True
        elif name in first_line:
            hint = "" if name_key == "name" else "; give the cases a 'name:'"
            errors.append(f"{where_name}: duplicate case name {name!r} "
                          f"(first used at line {first_line[name]}{hint})")
            bad = True
        else:
            first_line[name] = name_line
        # Merge: defaults first, then the case's own options; positions come along so an error
        # names the line the offending value was written on.
        merged = LineDict()
        merged.mark = raw.mark
        for source_map in (defaults, raw):
            for key, value in source_map.items():
                if key in CASE_KEYS or key not in SegmentConfig.keys():
                    continue
                merged[key] = value
                merged.key_marks[key] = source_map.key_marks.get(key, source_map.mark)
        try:
            config = SegmentConfig.from_mapping(merged, source=src)
        except ConfigError as exc:
            errors.append(str(exc))
            continue
        if bad:
            continue
        config = resolve_config_paths(config, base)
        where = {"image": locate(src, raw, "image")}
        if truth:
            where["truth"] = locate(src, raw, "truth")
        for key in PATH_KEYS:  # the files among the options
            if isinstance(getattr(config, key), str):
                where[key] = locate(src, merged, key)
        cases.append(BatchCase(
            name=name,
            image=os.path.abspath(base / Path(image).expanduser()),
            truth=os.path.abspath(base / Path(truth).expanduser()) if truth else None,
            config=config,
            line=raw.mark[0] if raw.mark else None,
            truth_label=truth_label,
            where=where,
        ))

    if errors:
        # One line: the first problem in file order, and how many more there are.
        position = re.compile(re.escape(src) + r":(\d+):(\d+): ")

        def order(message: str) -> tuple[int, int]:
            m = position.match(message)
            return (int(m.group(1)), int(m.group(2))) if m else (1 << 30, 0)

        unique = sorted(dict.fromkeys(errors), key=order)
        more = f" (and {len(unique) - 1} more problem{'s' if len(unique) > 2 else ''})" \
            if len(unique) > 1 else ""
        raise ConfigError(unique[0] + more)
    spec = BatchSpec(path=str(p.resolve()), output_dir=str(out), cases=tuple(cases))
    if check_files:
        from segsnake.batch_inputs import check_inputs

        check_inputs(spec, source=src)
    return spec


# --------------------------------------------------------------------------------------------------
# Running one case (in its own process, or on a Dask worker)
# --------------------------------------------------------------------------------------------------


def run_case(case: dict[str, Any]) -> dict[str, Any]:
    """The default runner: segment one case with :func:`segsnake.runner.segment_file`.

    Parameters
    ----------
    case : dict
        ``name``, ``image``, ``truth`` (or None), ``truth_label`` (or None), ``out_dir``,
        ``config`` (a :meth:`SegmentConfig.to_dict`), ``overwrite``.

    Returns
    -------
    dict
        The pipeline's JSON-able summary.
    """
    from segsnake.runner import segment_file  # lazily: a light import for the parent process

    config = SegmentConfig.from_mapping(case["config"], source=f"case {case['name']}")
    return segment_file(case["image"], case["out_dir"], config, truth_path=case.get("truth"),
                        truth_label=case.get("truth_label"), truth_label_option="truth_label: N",
                        overwrite=bool(case.get("overwrite", False)))


def resolve_runner(spec: str | Callable[..., Any]) -> Callable[[dict[str, Any]], dict[str, Any]]:
    """Import a runner named ``"package.module:function"`` or ``"/path/file.py:function"``."""
    if callable(spec):
        return spec  # type: ignore[return-value]
    if not isinstance(spec, str) or ":" not in spec:
        raise ConfigError(f"runner {spec!r}: expected 'module:function' or 'file.py:function'")
    module_name, _, func_name = spec.rpartition(":")
    if module_name.endswith(".py") or os.sep in module_name:
        path = os.path.abspath(module_name)
        # A stable private module name per file, so the module is imported once per process.
        private = "_segsnake_runner_" + hashlib.sha1(path.encode()).hexdigest()[:12]
        module = sys.modules.get(private)
        if module is None:
            if not os.path.isfile(path):
                raise ConfigError(f"runner {spec!r}: file not found: {path}")
            file_spec = importlib.util.spec_from_file_location(private, path)
            if file_spec is None or file_spec.loader is None:
                raise ConfigError(f"runner {spec!r}: cannot import {path}")
            module = importlib.util.module_from_spec(file_spec)
            sys.modules[private] = module
            try:
                file_spec.loader.exec_module(module)
            except BaseException:
                sys.modules.pop(private, None)
                raise
    else:
        try:
            module = importlib.import_module(module_name)
        except ImportError as exc:
            raise ConfigError(f"runner {spec!r}: cannot import {module_name}: {exc}") from None
    func = getattr(module, func_name, None)
    if not callable(func):
        raise ConfigError(f"runner {spec!r}: {module_name} has no function {func_name!r}")
    return func


def _runner_spec(runner: str | Callable[..., Any] | None) -> str:
    """A string that names the runner in any process (functions are named by module:qualname)."""
    if runner is None:
        return DEFAULT_RUNNER
    if isinstance(runner, str):
        return runner
    module = getattr(runner, "__module__", None)
    qualname = getattr(runner, "__qualname__", "")
    if not module or "<" in qualname or "." in qualname:
        raise ConfigError(f"runner {runner!r} must be a top-level function (importable by name)")
    if module == "__main__":
        path = getattr(sys.modules["__main__"], "__file__", None)
        if not path:
            raise ConfigError("a runner defined in an interactive __main__ cannot be imported by "
                              "worker processes; put it in a module")
        return f"{os.path.abspath(path)}:{qualname}"
    return f"{module}:{qualname}"


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _one_line(text: str) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= _MAX_ERROR_CHARS else text[: _MAX_ERROR_CHARS - 3] + "..."


def _base_record(case: dict[str, Any]) -> dict[str, Any]:
    return {
        "case": case["name"],
        "status": None,
        "image": case.get("image"),
        "truth": case.get("truth"),
        "truth_label": case.get("truth_label"),
        "out_dir": case.get("out_dir"),
        "host": socket.gethostname(),
    }


def failure_record(case: dict[str, Any], exc: BaseException | str, *, time_s: float | None = None,
                   exit_code: int | None = None, error_type: str | None = None) -> dict[str, Any]:
    """The result record of a failed case: message (one line), error type and its exit code."""
    record = _base_record(case)
    if isinstance(exc, BaseException):
        message = str(exc) or type(exc).__name__
        if isinstance(exc, MemoryError):
            message = f"out of memory {message}".strip() if str(exc) else "out of memory"
        etype = type(exc).__name__
        code = exc.exit_code if isinstance(exc, SegsnakeError) else (3 if isinstance(exc, MemoryError) else 1)
        if not isinstance(exc, SegsnakeError) and not isinstance(exc, MemoryError):
            # An unexpected exception: say what and where, in one line (the traceback's last frame).
            tb = traceback.extract_tb(exc.__traceback__)
            where = f" at {Path(tb[-1].filename).name}:{tb[-1].lineno}" if tb else ""
            message = f"{etype}: {message}{where}"
    else:
        message, etype, code = str(exc), "Error", 1
    record.update(
        status="failed",
        error=_one_line(message),
        error_type=error_type or etype,
        exit_code=exit_code if exit_code is not None else code,
        time_s=None if time_s is None else round(time_s, 3),
        finished=_now(),
    )
    return record


def _ok_record(case: dict[str, Any], summary: Any, time_s: float) -> dict[str, Any]:
    record = _base_record(case)
    summary = _jsonable(summary) if summary is not None else {}
    if not isinstance(summary, dict):
        summary = {"result": summary}
    record.update(status="ok", error=None, error_type=None, exit_code=0)
    for key in (*METRIC_KEYS, "iterations", "energy"):
        for source in _SUMMARY_ALIASES.get(key, (key,)):
            if source in summary:
                record[key] = summary[source]
                break
    record["time_s"] = round(time_s, 3)
    if isinstance(summary.get("timings"), dict):
        record["timings"] = summary["timings"]
    if "outputs" in summary:
        record["outputs"] = summary["outputs"]
    record["summary"] = summary
    record["finished"] = _now()
    return record


def execute_case(runner: str, case: dict[str, Any], sys_path: list[str] | None = None
                 ) -> dict[str, Any]:
    """Run one case and return its result record; never raises (a failure is a record).

    This is the function that crosses process boundaries (process pool child, Dask worker), so it
    takes only picklable arguments: the runner's import name, the case dict and, optionally, the
    parent's ``sys.path`` (appended where missing so a runner found by the parent is found here).
    """
    start = time.perf_counter()
    created: list[str] = []
    try:
        if sys_path:
            for entry in sys_path:
                if entry not in sys.path:
                    sys.path.append(entry)
        # Checked again here: a file removed since validation, or one a Dask worker does not see,
        # is this case's failure, not the batch's.
        for role in ("image", "truth"):
            path = case.get(role)
            if path is not None and not os.path.exists(path):
                raise InputError(f"{path}: {role} file not found")
        if case.get("out_dir"):
            try:
                created = make_dirs(case["out_dir"])
            except OutputError as exc:
                raise OutputError(f"{case['out_dir']}: cannot create the case directory: "
                                  f"{str(exc).split(': ', 1)[-1]}") from None
        func = resolve_runner(runner)
        summary = func(case)
        return _ok_record(case, summary, time.perf_counter() - start)
    except (Exception, SystemExit) as exc:  # noqa: BLE001 - every failure becomes a record
        if isinstance(exc, SystemExit):
            exc = RuntimeError(f"the case called exit({exc.code})")
        return failure_record(case, exc, time_s=time.perf_counter() - start)
    finally:
        # A failed (or interrupted) case leaves no empty case directory behind.
        remove_empty_dirs(created)


def _die_with_batch(alive: multiprocessing.connection.Connection) -> None:
    """End this case process as soon as the batch process is gone (killed, crashed).

    ``alive`` is the read end of a pipe whose only write end stays in the batch process, so it
    reads EOF exactly when that process dies. (PR_SET_PDEATHSIG would not do: a forkserver child's
    parent is the fork server, which itself stays up while any of its children runs.) Otherwise a
    killed batch would leave orphans writing outputs while ``--resume`` redoes the same cases.
    """

    def watch() -> None:
        try:
            alive.recv_bytes()  # never sent: returns only by EOF (or error) when the batch died
        except (EOFError, OSError):
            pass
        except BaseException:  # noqa: BLE001 - never let the watchdog itself kill the case
            return
        os.kill(os.getpid(), signal.SIGKILL)

    threading.Thread(target=watch, name="segsnake-batch-watchdog", daemon=True).start()


def _child_main(runner: str, case: dict[str, Any], sys_path: list[str],
                conn: multiprocessing.connection.Connection,
                alive: multiprocessing.connection.Connection, threads: int) -> None:
    """Entry point of the one process that runs one case (with ``threads`` threads)."""
    # Ctrl-C in a terminal reaches every process of the group: the case unwinds (its staging
    # files removed) and ends with 130 in silence; the batch reports the interruption once. (An
    # interrupt before the handler is installed, or while the record is sent, would otherwise
    # leave multiprocessing's "Process segsnake-case-NAME:" and a traceback on stderr: measured
    # once in 50 interrupted batches.)
    try:
        _die_with_batch(alive)
        set_threads(threads)
        return_freed_memory()  # (as the segsnake program does: segsnake.allocator)
        cancel.install()
        record = execute_case(runner, case, sys_path)
        with contextlib.suppress(Exception):
            conn.send(record)
        with contextlib.suppress(Exception):
            conn.close()
    except KeyboardInterrupt:
        cancel.exit_now(cancel.EXIT_INTERRUPTED)


# --------------------------------------------------------------------------------------------------
# Results files
# --------------------------------------------------------------------------------------------------


def read_results(path: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """Records of a ``results.jsonl``, skipping a line a killed run left half-written."""
    records = []
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            for line in fh:
                line = line.strip()
                if not line:
                    continue
                try:
                    record = json.loads(line)
                except json.JSONDecodeError:
                    continue
                if isinstance(record, dict) and isinstance(record.get("case"), str):
                    records.append(record)
    except FileNotFoundError:
        return []
    return records


def _csv_row(record: dict[str, Any]) -> list[str]:
    row = []
    for col in RESULT_COLUMNS:
        value = record.get(col)
        if value is None:
            row.append("")
        elif isinstance(value, (dict, list)):
            row.append(json.dumps(value, sort_keys=True, separators=(",", ":")))
        elif isinstance(value, float):
            row.append(repr(value))
        else:
            row.append(str(value))
    return row


def _write_atomic(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    fsync_dir(path.parent)


class ResultsWriter:
    """Appends one record per finished case to ``results.jsonl`` and ``results.csv``, durably.

    The JSON-lines file is written first and is the source of truth; the CSV is the spreadsheet
    view, regenerated from it on ``--resume``.
    """

    def __init__(self, out_dir: str | os.PathLike[str]) -> None:
        self.dir = Path(out_dir)
        self.jsonl = self.dir / RESULTS_JSONL
        self.csv = self.dir / RESULTS_CSV
        self._jfh: io.TextIOWrapper | None = None
        self._cfh: io.TextIOWrapper | None = None

    def reset(self, records: Iterable[dict[str, Any]]) -> None:
        """Replace both files (atomically) with ``records``."""
        records = list(records)
        lines = "".join(json.dumps(r, sort_keys=True, allow_nan=False) + "\n" for r in records)
        buf = io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        writer.writerow(RESULT_COLUMNS)
        for r in records:
            writer.writerow(_csv_row(r))
        _write_atomic(self.jsonl, lines)
        _write_atomic(self.csv, buf.getvalue())

    def open(self) -> None:
        """Open both files for appending (a header goes into a new or empty CSV)."""
        self._jfh = open(self.jsonl, "a", encoding="utf-8")
        self._cfh = open(self.csv, "a", encoding="utf-8", newline="")
        if self._cfh.tell() == 0:
            csv.writer(self._cfh, lineterminator="\n").writerow(RESULT_COLUMNS)
            self._sync(self._cfh)
        fsync_dir(self.dir)

    @staticmethod
    def _sync(fh: io.TextIOWrapper) -> None:
        fh.flush()
        os.fsync(fh.fileno())

    def append(self, record: dict[str, Any]) -> None:
        """Write one record to both files and push it to the disk before returning."""
        if self._jfh is None or self._cfh is None:
            self.open()
        assert self._jfh is not None and self._cfh is not None
        try:
            self._jfh.write(json.dumps(record, sort_keys=True, allow_nan=False) + "\n")
            self._sync(self._jfh)
            csv.writer(self._cfh, lineterminator="\n").writerow(_csv_row(record))
            self._sync(self._cfh)
        except OSError as exc:
            raise OutputError(f"{self.dir}: cannot write results: {exc.strerror or exc}") from None

    def close(self) -> None:
        for fh in (self._jfh, self._cfh):
            if fh is not None:
                with contextlib.suppress(OSError):
                    fh.close()
        self._jfh = self._cfh = None


@contextlib.contextmanager
def _locked(out_dir: Path) -> Iterator[None]:
    """Refuse a second batch writing the same output directory at the same time."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX: no lock
        yield
        return
    fd = os.open(out_dir / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise OutputError(f"{out_dir}: another segsnake batch is writing here right now") from None
        yield
    finally:
        os.close(fd)  # closing releases the lock (and the kernel releases it if we are killed)


# --------------------------------------------------------------------------------------------------
# Executors
# --------------------------------------------------------------------------------------------------


def _mp_context(runner: str) -> mp.context.BaseContext:
    """``forkserver`` where available: a clean, thread-safe fork of a small server that has the
    heavy modules preloaded (each case then starts in milliseconds); ``spawn`` otherwise."""
    if "forkserver" not in mp.get_all_start_methods():
        return mp.get_context("spawn")
    ctx = mp.get_context("forkserver")
    preload = ["numpy", "scipy.ndimage", "nibabel", "segsnake.errors", "segsnake.config",
               "segsnake.batch"]
    # The runner's modules too (the pipeline pulls in the heavy imaging stack), but only those that
    # import cleanly here: the server skips ImportError, yet any other exception would kill it.
    module_name = runner.rpartition(":")[0]
    if runner == DEFAULT_RUNNER:
        candidates = ["segsnake.io", "segsnake.metrics", "segsnake.pipeline", "segsnake.stage",
                      "segsnake.region_stages", "segsnake.edge_stages", "segsnake.runner"]
    elif module_name and not module_name.endswith(".py") and os.sep not in module_name:
        candidates = [module_name]
    else:
        candidates = []
    for name in candidates:
        try:
            importlib.import_module(name)
            preload.append(name)
        except Exception:  # noqa: BLE001 - each case will then report the problem itself
            pass
    # Only effective before the server first starts (it is one per parent process).
    ctx.set_forkserver_preload(preload)
    # The server (and the resource tracker) ignore SIGINT only once they have imported: a Ctrl-C
    # to the process group before would print their traceback. So they start with SIGINT ignored
    # (an ignored signal stays ignored through fork and exec; the cases the server forks install
    # their own handlers in _child_main). Meanwhile SIGINT is also blocked here, so that a Ctrl-C
    # in that moment stays pending (Linux never discards a blocked signal) and reaches this
    # process once its handler is back.
    if threading.current_thread() is threading.main_thread():
        from multiprocessing import forkserver

        old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        old_handler = signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            forkserver.ensure_running()
        finally:
            signal.signal(signal.SIGINT, old_handler)
            signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)
    return ctx


@dataclasses.dataclass
class _Running:
    proc: Any
    conn: multiprocessing.connection.Connection
    case: dict[str, Any]
    started: float
    record: dict[str, Any] | None = None
    conn_open: bool = True


def _describe_exit(code: int | None) -> str:
    if code is None:
        return "did not exit"
    if code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        hint = " (out of memory?)" if -code == signal.SIGKILL else ""
        return f"was killed by {name}{hint}"
    return f"exited with code {code}"


# Seconds the running cases get to unwind after the batch is interrupted, before SIGKILL: within
# the grace of segsnake.cancel, so that the batch itself still ends within it.
_STOP_S = 0.4


def _stop(running: list["_Running"]) -> None:
    """End the running case processes: SIGTERM, up to :data:`_STOP_S` s, then SIGKILL."""
    for r in running:
        with contextlib.suppress(Exception):
            r.proc.terminate()
    deadline = time.monotonic() + _STOP_S
    for r in running:
        with contextlib.suppress(Exception):
            r.proc.join(max(0.0, deadline - time.monotonic()))
    for r in running:
        with contextlib.suppress(Exception):
            if r.proc.is_alive():
                r.proc.kill()
                r.proc.join(5)


def _run_local(jobs: list[dict[str, Any]], runner: str, workers: int, timeout: float | None,
               on_record: Callable[[dict[str, Any]], None]) -> None:
    """One fresh process per case, at most ``workers`` at a time, sharing the CPUs."""
    ctx = _mp_context(runner)
    threads = max(1, parallel_threads() // max(1, min(workers, len(jobs))))
    pending = deque(jobs)
    running: list[_Running] = []
    sys_path = list(sys.path)
    # Children read EOF on alive_r when this process dies; alive_w never leaves this process.
    alive_r, alive_w = ctx.Pipe(duplex=False)

    def stop_all() -> None:
        # the running cases taken down and tidied (the batch interrupted, or ended by the
        # watchdog of segsnake.cancel, which skips this function's finally)
        _stop(running)
        for r in running:
            _tidy(r.case)

    try:
        with cancel.cleanup_on_exit(stop_all):
            _run_cases(ctx, pending, running, workers, timeout, runner, sys_path, alive_r,
                       threads, on_record)
    finally:
        # Interrupted (Ctrl-C) or failing to write results: take the running cases down with us,
        # first asking them (SIGTERM: each removes its staging files), then by force.
        stop_all()
        alive_r.close()
        alive_w.close()


def _run_cases(ctx, pending: deque, running: list["_Running"], workers: int,
               timeout: float | None, runner: str, sys_path: list[str], alive_r, threads: int,
               on_record: Callable[[dict[str, Any]], None]) -> None:
    """:func:`_run_local`'s loop: ``running`` is updated in place (its caller stops what is
    left in it)."""
    while pending or running:
        while pending and len(running) < workers:
            job = pending.popleft()
            recv, send = ctx.Pipe(duplex=False)
            proc = ctx.Process(target=_child_main, args=(runner, job, sys_path, send, alive_r,
                                                            threads),
                               name=f"segsnake-case-{job['name']}")
            proc.start()
            send.close()  # the child holds the only write end: EOF means it is gone
            running.append(_Running(proc, recv, job, time.monotonic()))
        waitables: list[Any] = []
        for r in running:
            waitables.append(r.proc.sentinel)
            if r.conn_open:
                waitables.append(r.conn)
        wait_s = None
        if timeout is not None:
            now = time.monotonic()
            wait_s = max(0.0, min(r.started + timeout - now for r in running))
        ready = set(multiprocessing.connection.wait(waitables, timeout=wait_s))
        still: list[_Running] = []
        for r in running:
            if r.conn_open and r.conn in ready:
                try:
                    r.record = r.conn.recv()
                except (EOFError, OSError):
                    pass
                r.conn_open = False
            elapsed = time.monotonic() - r.started
            if r.record is not None and r.proc.sentinel not in ready:
                # The child sent its record and is on its way out; don't wait on a straggler.
                r.proc.join(10)
                if r.proc.is_alive():
                    r.proc.kill()
                    r.proc.join()
                ready.add(r.proc.sentinel)
            if r.proc.sentinel in ready:
                r.proc.join()
                if r.record is None and r.conn_open:
                    with contextlib.suppress(EOFError, OSError):
                        if r.conn.poll():
                            r.record = r.conn.recv()
                if r.record is None:
                    _tidy(r.case)
                    r.record = failure_record(
                        r.case, f"case process {_describe_exit(r.proc.exitcode)}",
                        time_s=elapsed, error_type="CaseCrash", exit_code=1)
            elif timeout is not None and elapsed >= timeout and r.record is None:
                r.proc.kill()
                r.proc.join()
                _tidy(r.case)
                r.record = failure_record(r.case, f"timed out after {timeout:g} s",
                                          time_s=elapsed, error_type="CaseTimeout",
                                          exit_code=4)  # (no result: not a bug)
            else:
                still.append(r)
                continue
            with contextlib.suppress(OSError):
                r.conn.close()
            on_record(r.record)
        running[:] = still


def _tidy(case: dict[str, Any]) -> None:
    """What a case process that was killed (a timeout, the batch interrupted, a crash) left in its
    directory: removed now (:func:`tidy_case_dirs`), not by the next run on the directory. Its
    staging files and an empty case directory go; a commit it was making is completed or undone."""
    with contextlib.suppress(OSError):
        out = Path(case["out_dir"])
        tidy_case_dirs(out.parent, [out.name])


def _run_dask(jobs: list[dict[str, Any]], runner: str, address: str,
              on_record: Callable[[dict[str, Any]], None], connect_timeout: float = 30.0) -> None:
    """The same :func:`execute_case` on an existing ``dask.distributed`` cluster.

    Dask's workers give the isolation (a worker that dies is replaced and its task retried up to
    the cluster's ``allowed-failures``; then the case is recorded as failed).
    """
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise ConfigError("--scheduler needs dask.distributed: pip install 'segsnake[dask]'") from None
    try:
        client = Client(address, timeout=f"{connect_timeout}s", set_as_default=False)
    except (OSError, TimeoutError, ValueError) as exc:
        raise ConfigError(f"cannot connect to the Dask scheduler at {address}: {_one_line(exc)}") from None
    try:
        sys_path = list(sys.path)
        futures = {}
        for job in jobs:
            fut = client.submit(execute_case, runner, job, sys_path, pure=False,
                                key=f"segsnake-case-{job['name']}-{os.urandom(4).hex()}")
            futures[fut] = job
        for fut in as_completed(list(futures), loop=client.loop):
            job = futures[fut]
            try:
                record = fut.result()
            except Exception as exc:  # noqa: BLE001 - a lost worker (KilledWorker), cancelled...
                record = failure_record(job, exc, error_type=type(exc).__name__, exit_code=1)
            on_record(record)
    finally:
        with contextlib.suppress(Exception):
            client.close()


# --------------------------------------------------------------------------------------------------
# The batch
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class BatchReport:
    """What a batch run did: counts, failed case names, where the results are."""

    total: int
    ok: int
    failed: int
    skipped: int
    failed_cases: list[str]
    output_dir: str
    results_csv: str
    results_jsonl: str
    #: each failed case's message (this run's), by name
    errors: dict[str, str] = dataclasses.field(default_factory=dict)

    @property
    def all_ok(self) -> bool:
        return self.failed == 0


def _previous(records: list[dict[str, Any]], names: set[str]) -> tuple[list[dict[str, Any]], set[str]]:
    """Records to keep on resume (one per case) and the names of cases already done."""
    last_ok: dict[str, dict[str, Any]] = {}
    last_any: dict[str, dict[str, Any]] = {}
    for r in records:
        last_any[r["case"]] = r
        if r.get("status") == "ok":
            last_ok[r["case"]] = r
    keep: dict[str, dict[str, Any]] = {}
    for r in records:  # first-seen order
        name = r["case"]
        if name in keep:
            continue
        if name in last_ok:
            keep[name] = last_ok[name]
        elif name not in names:
            keep[name] = last_any[name]  # a case no longer in the file: keep its record, untouched
    done = {n for n in last_ok if n in names}
    return list(keep.values()), done


def tidy_case_dirs(out: str | os.PathLike[str], names: Iterable[str]) -> None:
    """What killed runs left in the case directories ``out/NAME``: commits completed or undone
    and staging directories removed (:func:`segsnake.outdir.recover`), empty case directories
    removed. A directory another process holds (a segment run on it) is left alone."""
    for name in names:
        d = Path(out) / name
        if not d.is_dir():
            continue
        lock = try_lock(str(d))
        if lock is None:
            continue
        try:
            recover(str(d))
            lock.created = [str(d)]
        finally:
            lock.release(remove_if_empty=True)


def run_batch(spec: BatchSpec | str | os.PathLike[str], *, workers: int | None = None,
              scheduler: str | None = None, resume: bool = False, overwrite: bool = False,
              runner: str | Callable[..., Any] | None = None, case_timeout: float | None = None,
              quiet: bool = True, progress_stream: Any = None, connect_timeout: float = 30.0,
              on_warning: Callable[[str, str], None] | None = None) -> BatchReport:
    """Run every case of a batch and record each result as it finishes.

    Parameters
    ----------
    spec : BatchSpec or path
        A validated spec (:func:`load_batch`) or the YAML file to validate.
    workers : int, optional
        Cases running at once in the local pool (default: the CPUs this process may use, or
        SEGSNAKE_NUM_THREADS, at most the number of cases); they share those CPUs' threads.
    scheduler : str, optional
        Address of a running ``dask.distributed`` scheduler; replaces the local pool.
    resume : bool
        Keep cases already recorded ``ok``; run all others (failed ones again).
    overwrite : bool
        Start over when results exist, and let cases replace their earlier outputs.
    runner : str or function, optional
        The case function (default :func:`run_case`), as ``"module:function"``,
        ``"/path/file.py:function"`` or a top-level function.
    case_timeout : float, optional
        Seconds after which a case is killed and recorded as failed (local pool only).
    quiet : bool
        No progress display.
    progress_stream : text stream, optional
        Where progress goes (default stderr).
    connect_timeout : float
        Seconds to wait for the Dask scheduler to answer.
    on_warning : callable(case name, warning), optional
        Called with each warning of a finished case (its summary's ``warnings``: NaN voxels
        filled, a truth that looks like a label map), as the case finishes; they are also in
        ``results.jsonl``.

    Returns
    -------
    BatchReport

    Raises
    ------
    ConfigError
        Invalid batch file, bad worker count or runner, unreachable scheduler.
    OutputError
        Output directory not writable, results present without ``resume``/``overwrite``,
        another batch writing the same directory.
    """
    from segsnake.progress import ProgressBar

    if not isinstance(spec, BatchSpec):
        spec = load_batch(spec)
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise ConfigError(f"--workers must be an integer >= 1, got {workers!r}")
    if case_timeout is not None and not case_timeout > 0:
        raise ConfigError(f"--case-timeout must be > 0 seconds, got {case_timeout!r}")
    runner_name = _runner_spec(runner)
    if runner_name != DEFAULT_RUNNER and scheduler is None:
        resolve_runner(runner_name)  # fail now, once, rather than once per case

    out = Path(spec.output_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise OutputError(f"{out}: output_dir exists and is not a directory") from None
    except OSError as exc:
        raise OutputError(f"{out}: cannot create output_dir: {exc.strerror or exc}") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise OutputError(f"{out}: output_dir is not writable")

    names = {c.name for c in spec.cases}
    writer = ResultsWriter(out)
    with _locked(out):
        existing = [p for p in (writer.jsonl, writer.csv) if p.exists() and p.stat().st_size > 0]
        done: set[str] = set()
        if resume:
            kept, done = _previous(read_results(writer.jsonl), names)
            writer.reset(kept)  # each case once: failed/partial records of re-run cases go
        elif existing and not overwrite:
            raise OutputError(f"{existing[0]} already exists: use --resume to continue that run "
                              "or --overwrite to start again")
        else:
            writer.reset([])

        tidy_case_dirs(out, [c.name for c in spec.cases])
        todo = [c for c in spec.cases if c.name not in done]
        # Re-run cases may have complete outputs from a run killed before it recorded them.
        jobs = [c.to_job(out, overwrite=overwrite or resume) for c in todo]
        n_workers = workers or max(1, min(len(jobs), parallel_threads()))
        failed: list[str] = []
        errors: dict[str, str] = {}
        counts = {"ok": 0}
        bar = ProgressBar(len(spec.cases), label="cases", initial=len(done), quiet=quiet,
                          stream=progress_stream)

        def on_record(record: dict[str, Any]) -> None:
            record = _jsonable(record)
            writer.append(record)
            summary = record.get("summary")
            case_warnings = summary.get("warnings") if isinstance(summary, dict) else None
            if on_warning is not None and isinstance(case_warnings, list):
                for text in case_warnings:
                    bar.clear_line()
                    on_warning(record["case"], str(text))
            if record.get("status") == "ok":
                counts["ok"] += 1
                note = f"{record['case']} ok"
                if isinstance(record.get("dice"), (int, float)):
                    note += f" dice {record['dice']:.4f}"
                bar.update(1, note)
            else:
                failed.append(record["case"])
                errors[record["case"]] = str(record.get("error"))
                if bar.mode == "bar":  # the message above the bar, the bar stays short
                    bar.message(f"{record['case']} FAILED: {record.get('error')}")
                    bar.update(1, f"{record['case']} FAILED")
                else:
                    bar.update(1, f"{record['case']} FAILED: {record.get('error')}")

        writer.open()
        try:
            if jobs:
                if scheduler:
                    _run_dask(jobs, runner_name, scheduler, on_record, connect_timeout)
                else:
                    _run_local(jobs, runner_name, n_workers, case_timeout, on_record)
        finally:
            writer.close()
            bar.close()

    return BatchReport(
        total=len(spec.cases), ok=counts["ok"] + len(done), failed=len(failed), skipped=len(done),
        failed_cases=failed, errors=errors, output_dir=str(out), results_csv=str(writer.csv),
        results_jsonl=str(writer.jsonl),
    )
