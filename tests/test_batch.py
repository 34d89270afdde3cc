"""`segsnake batch`: validation before work, one process per case, durable results, resume, Dask.

The batch mechanics are exercised with a fast, real stand-in runner (Otsu threshold of the image,
written as a mask, Dice against the truth) defined below; the real pipeline
(:func:`segsnake.runner.segment_file`) gets one end-to-end test.
"""

from __future__ import annotations

import csv
import fcntl
import importlib
import importlib.util
import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest

from segsnake.batch import (
    LOCK_NAME,
    RESULT_COLUMNS,
    load_batch,
    read_results,
    run_batch,
)
from segsnake.cli import main
from segsnake.config import SegmentConfig
from segsnake.errors import ConfigError, InputError, OutputError
from segsnake.progress import ProgressBar

HERE = Path(__file__).resolve()
RUNNER = f"{HERE}:otsu_runner"
VENV_BIN = Path(sys.executable).parent


# -- the stand-in runner (runs in the case processes) --------------------------------------------


def otsu_runner(case: dict) -> dict:
    """Segment by Otsu's threshold; behaves like the pipeline's contract (summary dict, errors).

    Case names steer failure modes: ``crash*`` dies by SIGSEGV, ``slow*`` sleeps first,
    ``hang*`` sleeps for a minute; ``warn*`` succeeds with a warning in its summary.
    """
    from skimage.filters import threshold_otsu

    name = case["name"]
    if name.startswith("crash"):
        os.kill(os.getpid(), signal.SIGSEGV)
    if name.startswith("slow"):
        time.sleep(0.3)
    if name.startswith("hang"):
        # (as the pipeline's runner does: outputs are written into a staging directory in the
        # case's directory, committed at the end)
        from segsnake.outdir import stage_dir

        Path(case["out_dir"]).mkdir(parents=True, exist_ok=True)
        (Path(stage_dir(case["out_dir"])) / "mask.nii.gz").write_bytes(b"half")
        time.sleep(60)
    img = nib.load(case["image"])
    data = np.asarray(img.dataobj, dtype=np.float32)
    cfg = SegmentConfig.from_mapping(case["config"])
    if cfg.center is not None and not all(0 <= c < n for c, n in zip(cfg.center, data.shape)):
        raise InputError(f"{case['image']}: initialization center {cfg.center} is outside the volume")
    mask = (data > threshold_otsu(data)).astype(np.uint8)
    out = Path(case["out_dir"]) / "mask.nii.gz"
    if out.exists() and not case["overwrite"]:
        raise OutputError(f"{out}: exists (use --overwrite)")
    tmp = out.with_name(".mask.tmp.nii.gz")
    nib.save(nib.Nifti1Image(mask, img.affine), tmp)
    os.replace(tmp, out)
    summary = {"timings": {"threshold_s": 0.0}, "iterations": int(cfg.m1 or 0),
               "outputs": {"mask": str(out)}, "pid": os.getpid(),
               "warnings": [f"{name} looks odd"] if name.startswith("warn") else []}
    if case["truth"]:
        truth = np.asarray(nib.load(case["truth"]).dataobj) > 0
        inter = np.count_nonzero(mask.astype(bool) & truth)
        a, b = np.count_nonzero(mask), np.count_nonzero(truth)
        summary["dice"] = 2 * inter / (a + b)
        summary["jaccard"] = inter / (a + b - inter)
    return summary


# -- fixtures -------------------------------------------------------------------------------------


def make_ball(path: Path, truth_path: Path, seed: int, radius: float = 5.0, n: int = 16) -> None:
    """A noisy bright ball on a dark background and its truth mask."""
    rng = np.random.default_rng(seed)
    i, j, k = np.indices((n, n, n))
    truth = ((i - n / 2) ** 2 + (j - n / 2) ** 2 + (k - n / 2) ** 2 <= radius**2).astype(np.uint8)
    image = (100.0 * truth + 10.0 + rng.normal(0.0, 18.0, truth.shape)).astype(np.float32)
    nib.save(nib.Nifti1Image(image, np.eye(4)), path)
    nib.save(nib.Nifti1Image(truth, np.eye(4)), truth_path)


@pytest.fixture(scope="module")
def images(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("images")
    for s in range(3):
        make_ball(d / f"ball{s}.nii.gz", d / f"ball{s}_truth.nii.gz", seed=s, radius=4.0 + s)
    raw = (d / "ball0.nii.gz").read_bytes()
    (d / "corrupt.nii.gz").write_bytes(raw[: len(raw) // 2])  # a truncated gzip
    return d


def batch_file(tmp_path: Path, images: Path, cases: list[str], defaults: str = "  m1: 8\n",
               output_dir: str = "out") -> Path:
    text = f"output_dir: {output_dir}\ndefaults:\n{defaults}cases:\n" + "".join(cases)
    path = tmp_path / "runs.yaml"
    path.write_text(text.replace("IMG", str(images)), encoding="utf-8")
    return path


def good(name: str, s: int, extra: str = "") -> str:
    return f"  - name: {name}\n    image: IMG/ball{s}.nii.gz\n    truth: IMG/ball{s}_truth.nii.gz\n{extra}"


def csv_rows(path: Path) -> list[dict]:
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def expected_dice(images: Path, s: int, tmp_path: Path) -> float:
    """What the runner computes for ball s, run here in-process."""
    out = tmp_path / f"direct{s}"
    out.mkdir()
    case = {"name": "direct", "image": str(images / f"ball{s}.nii.gz"),
            "truth": str(images / f"ball{s}_truth.nii.gz"), "out_dir": str(out),
            "config": SegmentConfig().to_dict(), "overwrite": False}
    return otsu_runner(case)["dice"]


# -- validation -----------------------------------------------------------------------------------


def test_load_batch_merges_defaults_overrides_and_paths(tmp_path, images):
    path = batch_file(tmp_path, images, [
        good("a", 0),
        "  - image: IMG/ball1.nii.gz\n    m1: 12\n    max-iter: 40\n    prior: ref.json\n",
    ], defaults="  m1: 8\n  scale: 1.5\n")
    (tmp_path / "ref.json").write_text("{}")  # only its existence is checked here
    spec = load_batch(path)
    assert spec.output_dir == str(tmp_path / "out")
    a, b = spec.cases
    assert (a.name, a.config.m1, a.config.scale, a.config.max_iter) == ("a", 8, 1.5, 300)
    assert a.truth == str(images / "ball0_truth.nii.gz")
    # name from the file name, per-case override wins, relative prior resolved against the YAML file
    assert (b.name, b.config.m1, b.config.scale, b.config.max_iter) == ("ball1", 12, 1.5, 40)
    assert b.truth is None and b.config.prior == str(tmp_path / "ref.json")
    assert load_batch(path, output_dir=tmp_path / "elsewhere").output_dir == str(tmp_path / "elsewhere")


@pytest.mark.parametrize("cases, defaults, where, fragment", [
    # a bad override: m1 below the basis minimum, at the case's line 9
    (["  - name: a\n    image: x.nii\n", "  - name: b\n    image: y.nii\n    m1: 2\n"], "  m1: 8\n",
     "9:5", "m1: must be >= 4, got 2"),
    # an unknown option in a case, with a suggestion
    (["  - name: a\n    image: x.nii\n    radi: [1, 2, 3]\n"], "", "6:5",
     "unknown option 'radi' (did you mean 'radii'?)"),
    # a bad default is reported once, at the defaults line
    (["  - name: a\n    image: x.nii\n"], "  shape: sphre\n", "3:3", "did you mean 'sphere'?"),
    # duplicate case names
    (["  - name: a\n    image: x.nii\n", "  - name: a\n    image: y.nii\n"], "", "6:5",
     "duplicate case name 'a' (first used at line 4)"),
    # a case without an image
    (["  - name: a\n    truth: t.nii\n"], "", "4:5", "case 1: 'image:' must be a file path"),
    # a name that cannot be a directory
    (["  - name: ../up\n    image: x.nii\n"], "", "4:5", "case name '../up': must be 1-128 letters"),
])
def test_validation_errors_point_at_the_line_and_nothing_runs(tmp_path, capsys, cases, defaults,
                                                               where, fragment):
    path = batch_file(tmp_path, tmp_path, cases, defaults=defaults)
    assert main(["batch", str(path), "--runner", RUNNER]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"segsnake batch: error: {path}:{where}: ") and fragment in err
    assert len(err.splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_missing_inputs_are_listed_with_their_lines_before_anything_runs(tmp_path, images,
                                                                         capsys):
    """Issue 17: a batch whose files were never made stops at once, every missing one listed."""
    path = batch_file(tmp_path, images, [
        good("a", 0),                                                        # lines 6-8: all there
        "  - name: b\n    image: IMG/nope.nii.gz\n",                          # line 10: image
        good("c", 1).replace("ball1_truth", "nothing"),                      # line 13: truth
        "  - name: d\n    image: IMG/ball2.nii.gz\n    prior: ref2.json\n",   # line 16: prior
    ], defaults="  m1: 8\n  prior: ref.json\n")                            # line 4: shared prior
    before = sorted(tmp_path.iterdir())
    assert main(["batch", str(path), "--runner", RUNNER]) == 3
    out, err = capsys.readouterr()
    assert out == ""
    assert err.splitlines() == [
        f"segsnake batch: error: {path}: 4 input files of the batch cannot be read "
        "(nothing was run):",
        f"  {path}:4:3: prior {tmp_path / 'ref.json'}: no such file",   # once for its 3 cases
        f"  {path}:10:5: image {images / 'nope.nii.gz'}: no such file",
        f"  {path}:13:5: truth {images / 'nothing.nii.gz'}: no such file",
        f"  {path}:16:5: prior {tmp_path / 'ref2.json'}: no such file",
    ]
    assert sorted(tmp_path.iterdir()) == before  # no output directory, nothing ran

    assert main(["batch", str(path), "--runner", RUNNER, "--json"]) == 3
    record = json.loads(capsys.readouterr().out)
    assert (record["status"], record["code"], record["file"]) == ("error", 3, str(path))
    assert [(m["line"], m["role"], m["case"]) for m in record["missing"]] == [
        (4, "prior", "a"), (10, "image", "b"), (13, "truth", "c"), (16, "prior", "d")]
    # all there: validation passes (the YAML's own errors come first and keep exit 2)
    (tmp_path / "ref.json").write_text("{}")
    (tmp_path / "ref2.json").write_text("{}")
    ok = batch_file(tmp_path, images, [good("a", 0), good("c", 1)], defaults="  m1: 8\n")
    assert [c.name for c in load_batch(ok).cases] == ["a", "c"]
    bad = batch_file(tmp_path, images, ["  - name: b\n    image: IMG/nope.nii.gz\n    m1: 2\n"])
    with pytest.raises(ConfigError, match=":7:5: m1: must be >= 4"):
        load_batch(bad)


def test_truth_label_is_a_case_key_checked_with_its_line(tmp_path, images):
    path = batch_file(tmp_path, images, [good("a", 0, "    truth_label: 1\n")])
    case = load_batch(path).cases[0]
    assert case.truth_label == 1 and case.to_job(tmp_path)["truth_label"] == 1
    for extra, where, fragment in (
            ("    truth_label: one\n", "8:5", "truth_label: must be an integer"),
            ("    truth_label: 2.5\n", "8:5", "truth_label: must be an integer")):
        path = batch_file(tmp_path, images, [good("a", 0, extra)])
        with pytest.raises(ConfigError, match=f"runs.yaml:{where}: {fragment}"):
            load_batch(path)
    path = batch_file(tmp_path, images, ["  - name: a\n    image: IMG/ball0.nii.gz\n"
                                         "    truth_label: 3\n"])
    with pytest.raises(ConfigError, match=r"runs.yaml:7:5: truth_label needs a 'truth:'"):
        load_batch(path)
    path = batch_file(tmp_path, images, [good("a", 0)], defaults="  truth_label: 3\n")
    with pytest.raises(ConfigError, match=r"runs.yaml:3:3: 'truth_label' belongs to a case"):
        load_batch(path)


def test_all_problems_are_counted_and_top_level_keys_checked(tmp_path):
    path = tmp_path / "runs.yaml"
    path.write_text("outptu_dir: o\ncases:\n  - {image: a.nii, m1: 1}\n  - {image: b.nii, tol: 0}\n")
    with pytest.raises(ConfigError) as info:
        load_batch(path)
    assert str(info.value) == (f"{path}:1:1: unknown key 'outptu_dir' (did you mean 'output_dir'?) "
                               "(a batch file has output_dir, defaults, cases) (and 2 more problems)")
    path.write_text("cases:\n  - {image: a/image.nii, tol: 0}\n  - {image: b/image.nii}\n")
    with pytest.raises(ConfigError) as info:
        load_batch(path)
    assert str(info.value) == (f"{path}:2:26: tol: must be > 0, got 0 (and 1 more problem)")
    path.write_text("cases:\n  - {image: a/image.nii}\n  - {image: b/image.nii}\n")
    with pytest.raises(ConfigError, match=r":3:6: duplicate case name 'image' \(first used at line 2; "
                                          r"give the cases a 'name:'\)$"):
        load_batch(path)
    path.write_text("defaults: {m1: 8}\n")
    with pytest.raises(ConfigError, match="no cases: add a 'cases:' list"):
        load_batch(path)


# -- running --------------------------------------------------------------------------------------


def test_broken_cases_are_recorded_and_the_rest_is_done(tmp_path, images, capsys):
    path = batch_file(tmp_path, images, [
        good("good0", 0),
        "  - name: missing\n    image: IMG/nope.nii.gz\n",
        "  - name: corrupt\n    image: IMG/corrupt.nii.gz\n",
        good("outside", 1, "    center: [40, 3, 3]\n"),  # valid option, wrong for this image
        good("crash", 1),
        good("good1", 1),
        good("nothruth", 2).replace("ball2_truth", "ball9_truth"),
        good("good2", 2, "    m1: 12\n"),
    ])
    # Files missing when the cases run (removed since validation, or not seen by a Dask worker)
    # are those cases' failures: here they are missing from the start, so validation, which
    # would refuse the batch (test_missing_inputs_are_listed...), is told not to look.
    report = run_batch(load_batch(path, check_files=False), runner=RUNNER, workers=2)
    results_csv = tmp_path / "out" / "results.csv"
    assert (report.total, report.ok, report.failed) == (8, 3, 5)
    assert sorted(report.failed_cases) == ["corrupt", "crash", "missing", "nothruth", "outside"]

    records = {r["case"]: r for r in read_results(tmp_path / "out" / "results.jsonl")}
    rows = {r["case"]: r for r in csv_rows(results_csv)}
    assert sorted(records) == sorted(rows) == sorted(
        ["good0", "missing", "corrupt", "outside", "crash", "good1", "nothruth", "good2"])
    for s in range(3):
        r = records[f"good{s}"]
        assert r["status"] == "ok" and r["exit_code"] == 0 and r["error"] is None
        assert r["dice"] == pytest.approx(expected_dice(images, s, tmp_path), abs=1e-12)
        assert 0.85 < r["dice"] < 1.0 and r["jaccard"] == pytest.approx(r["dice"] / (2 - r["dice"]))
        assert float(rows[f"good{s}"]["dice"]) == r["dice"]  # CSV holds the exact value
        assert (tmp_path / "out" / f"good{s}" / "mask.nii.gz").is_file()
    assert records["good2"]["iterations"] == 12 and records["good0"]["iterations"] == 8
    assert records["missing"]["error"] == f"{images / 'nope.nii.gz'}: image file not found"
    assert (records["missing"]["error_type"], records["missing"]["exit_code"]) == ("InputError", 3)
    assert records["nothruth"]["error"] == f"{images / 'ball9_truth.nii.gz'}: truth file not found"
    assert records["corrupt"]["status"] == "failed" and records["corrupt"]["error"]
    assert records["outside"]["error"].endswith("initialization center [40.0, 3.0, 3.0] is outside "
                                                "the volume")
    assert records["outside"]["exit_code"] == 3
    assert records["crash"]["error"] == "case process was killed by SIGSEGV"
    assert records["crash"]["error_type"] == "CaseCrash"
    for r in records.values():
        assert "\n" not in (r["error"] or "")
    assert list(csv_rows(results_csv)[0]) == list(RESULT_COLUMNS)


def test_failed_cases_exit_6_with_the_counts_and_warnings_reach_stderr(tmp_path, images, capsys):
    path = batch_file(tmp_path, images, [
        good("good0", 0), "  - name: corrupt\n    image: IMG/corrupt.nii.gz\n", good("warn1", 1)])
    assert main(["batch", str(path), "--runner", RUNNER, "--workers", "2"]) == 6
    out, err = capsys.readouterr()
    results_csv = tmp_path / "out" / "results.csv"
    assert out == f"3 cases: 2 ok, 1 failed (3 run); results in {results_csv}\n"
    assert "segsnake batch: warning: case warn1: warn1 looks odd\n" in err
    assert err.splitlines()[-1] == f"segsnake batch: error: 1 of 3 cases failed (see {results_csv})"
    assert main(["batch", str(path), "--runner", RUNNER, "--overwrite", "--json"]) == 6
    out, err = capsys.readouterr()
    record = json.loads(out)  # one object: the error, with the counts
    assert (record["code"], record["total"], record["ok"], record["failed_cases"]) == \
        (6, 3, 2, ["corrupt"])
    assert record["file"] == str(results_csv) and "warn1 looks odd" in err
    assert main(["batch", str(path), "--runner", RUNNER, "--overwrite", "--quiet"]) == 6
    out, err = capsys.readouterr()
    assert out == "" and "warn1 looks odd" in err  # warnings even with --quiet
    # ... and each failed case with its message (the progress, which lists them, is off)
    assert err.splitlines()[-2].startswith("segsnake batch: case corrupt failed: ")


def test_sigkill_midway_then_resume_records_every_case_exactly_once(tmp_path, images):
    names = [f"slow{i}" for i in range(6)]
    path = batch_file(tmp_path, images, [good(n, i % 3) for i, n in enumerate(names)])
    jsonl = tmp_path / "out" / "results.jsonl"
    script = VENV_BIN / "segsnake"
    command = [str(script)] if script.is_file() else [sys.executable, "-m", "segsnake.cli"]
    proc = subprocess.Popen([*command, "batch", str(path), "--workers", "1",
                             "--runner", RUNNER, "--quiet"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and proc.poll() is None:
        if jsonl.exists() and jsonl.read_bytes().count(b"\n") >= 1:
            break
        time.sleep(0.01)
    assert proc.poll() is None, proc.stderr.read().decode()
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    proc.stderr.close()
    masks_at_kill = sorted((tmp_path / "out").glob("*/mask.nii.gz"))
    before = read_results(jsonl)
    assert 1 <= len(before) < len(names)
    time.sleep(0.6)  # longer than a case: an orphaned case would finish and write its mask now
    assert sorted((tmp_path / "out").glob("*/mask.nii.gz")) == masks_at_kill

    assert main(["batch", str(path), "--resume", "--runner", RUNNER, "-j", "2", "-q"]) == 0
    after = read_results(jsonl)
    rows = csv_rows(tmp_path / "out" / "results.csv")
    assert sorted(r["case"] for r in after) == sorted(r["case"] for r in rows) == sorted(names)
    assert all(r["status"] == "ok" for r in after)
    # the cases done before the kill were kept, not run again
    kept = {r["case"]: r for r in after}
    for r in before:
        assert kept[r["case"]] == r
    # running again with --resume does nothing and changes nothing
    text = jsonl.read_text()
    assert main(["batch", str(path), "--resume", "--runner", RUNNER, "-q"]) == 0
    assert jsonl.read_text() == text


def test_resume_skips_ok_reruns_failed_and_drops_a_torn_line(tmp_path, images):
    path = batch_file(tmp_path, images, [good("a", 0), good("b", 1), good("c", 2)])
    out = tmp_path / "out"
    out.mkdir()
    ok_a = {"case": "a", "status": "ok", "dice": 0.5, "exit_code": 0}
    failed_b = {"case": "b", "status": "failed", "error": "transient", "exit_code": 4}
    old = {"case": "gone", "status": "ok", "dice": 0.1}  # a case since removed from the file
    (out / "results.jsonl").write_text(
        "".join(json.dumps(r) + "\n" for r in (ok_a, failed_b, old, ok_a)) + '{"case": "c", "sta')
    report = run_batch(load_batch(path), resume=True, runner=RUNNER, workers=2)
    assert (report.total, report.ok, report.failed, report.skipped) == (3, 3, 0, 1)
    records = read_results(out / "results.jsonl")
    by_case = {r["case"]: r for r in records}
    assert len(records) == 4 and sorted(by_case) == ["a", "b", "c", "gone"]
    assert by_case["a"] == ok_a and by_case["gone"] == old  # kept as they were
    assert by_case["b"]["status"] == by_case["c"]["status"] == "ok"
    assert [r["case"] for r in csv_rows(out / "results.csv")] == [r["case"] for r in records]


def test_existing_results_need_resume_or_overwrite(tmp_path, images, capsys):
    path = batch_file(tmp_path, images, [good("a", 0)])
    assert main(["batch", str(path), "--runner", RUNNER, "-q"]) == 0
    first = read_results(tmp_path / "out" / "results.jsonl")
    assert main(["batch", str(path), "--runner", RUNNER, "-q"]) == 5
    assert "results.jsonl already exists: use --resume" in capsys.readouterr().err
    assert read_results(tmp_path / "out" / "results.jsonl") == first  # untouched
    assert main(["batch", str(path), "--runner", RUNNER, "-q", "--overwrite"]) == 0
    again = read_results(tmp_path / "out" / "results.jsonl")
    assert len(again) == 1 and again[0]["dice"] == first[0]["dice"]
    assert again[0]["summary"]["pid"] != first[0]["summary"]["pid"]  # really ran again
    assert main(["batch", str(path), "--resume", "--overwrite"]) == 2
    capsys.readouterr()
    # A bad thread count in the environment stops before the earlier results are touched.
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SEGSNAKE_NUM_THREADS", "0")
        assert main(["batch", str(path), "--runner", RUNNER, "-q", "--overwrite"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("segsnake batch: error: ") and "SEGSNAKE_NUM_THREADS" in err
    assert read_results(tmp_path / "out" / "results.jsonl") == again


def test_a_second_batch_on_the_same_directory_is_refused(tmp_path, images):
    path = batch_file(tmp_path, images, [good("a", 0)])
    (tmp_path / "out").mkdir()
    fd = os.open(tmp_path / "out" / LOCK_NAME, os.O_RDWR | os.O_CREAT)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        with pytest.raises(OutputError, match="another segsnake batch is writing here"):
            run_batch(load_batch(path), runner=RUNNER)
    finally:
        os.close(fd)
    assert run_batch(load_batch(path), runner=RUNNER).all_ok


def test_case_timeout_kills_only_that_case(tmp_path, images):
    path = batch_file(tmp_path, images, [good("hang", 0), good("a", 1)])
    t0 = time.monotonic()
    report = run_batch(load_batch(path), runner=RUNNER, workers=2, case_timeout=1.0)
    assert time.monotonic() - t0 < 20
    assert (report.ok, report.failed_cases) == (1, ["hang"])
    rec = {r["case"]: r for r in read_results(report.results_jsonl)}["hang"]
    assert (rec["error"], rec["error_type"], rec["exit_code"]) == \
        ("timed out after 1 s", "CaseTimeout", 4)
    # what the killed case had begun to write went with it: no staging files, no empty directory
    assert not (tmp_path / "out" / "hang").exists()


def test_dask_local_cluster_gives_the_same_results_as_the_pool(tmp_path, images):
    distributed = pytest.importorskip("distributed")
    cases = [good("a", 0), good("b", 1, "    m1: 5\n"), good("c", 2),
             "  - name: missing\n    image: IMG/nope.nii.gz\n", good("outside", 0, "    center: [-1, 2, 2]\n")]
    pool_spec = load_batch(batch_file(tmp_path, images, cases), output_dir=tmp_path / "pool",
                           check_files=False)  # "missing" fails at run time, on either executor
    pool = run_batch(pool_spec, runner=RUNNER, workers=2)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False,
                                  dashboard_address=None) as cluster:
        dask_spec = load_batch(batch_file(tmp_path, images, cases), output_dir=tmp_path / "dask",
                               check_files=False)
        via_dask = run_batch(dask_spec, runner=RUNNER, scheduler=cluster.scheduler_address)
    assert (pool.ok, pool.failed) == (via_dask.ok, via_dask.failed) == (3, 2)

    def essence(report):
        keys = ("status", "dice", "jaccard", "iterations", "error", "error_type", "exit_code")
        return {r["case"]: {k: r.get(k) for k in keys} for r in read_results(report.results_jsonl)}

    assert essence(pool) == essence(via_dask)
    assert essence(pool)["b"]["iterations"] == 5
    assert (tmp_path / "dask" / "a" / "mask.nii.gz").is_file()


def test_unreachable_scheduler_is_a_config_error(tmp_path, images):
    pytest.importorskip("distributed")
    path = batch_file(tmp_path, images, [good("a", 0)])
    with pytest.raises(ConfigError, match="cannot connect to the Dask scheduler at tcp://127.0.0.1:9"):
        run_batch(load_batch(path), runner=RUNNER, scheduler="tcp://127.0.0.1:9", connect_timeout=1)


def test_progress_bar_draws_on_a_terminal_and_logs_otherwise():
    class Tty(io.StringIO):
        def isatty(self):
            return True

    tty = Tty()
    with ProgressBar(4, label="cases", initial=1, stream=tty, width=8) as bar:
        bar.update(1, "a ok")
        bar.message("b FAILED: boom")
        bar.update(2, "c ok")
    text = tty.getvalue()
    assert "\r[##------] 1/4 cases" in text and "[####----] 2/4 cases" in text
    assert "\r\033[Kb FAILED: boom\n" in text and "[########] 4/4 cases" in text and text.endswith("\n")
    log = io.StringIO()
    bar = ProgressBar(2, stream=log)
    bar.update(1, "a ok")
    assert log.getvalue() == "[1/2] a ok\n"
    quiet = io.StringIO()
    ProgressBar(2, stream=quiet, quiet=True).update(1, "x")
    assert quiet.getvalue() == ""


def test_shipped_configs_are_valid_and_match_the_synthetic_sets():
    root = HERE.parent.parent
    # check_files=False: the volumes exist only after `make data`
    specs = {name: load_batch(root / "configs" / f"{name}.yaml", check_files=False)
             for name in ("brain-sweep", "cylinder-table", "blobs")}
    assert {k: len(v.cases) for k, v in specs.items()} == {"brain-sweep": 30, "cylinder-table": 6,
                                                           "blobs": 20}
    assert specs["cylinder-table"].cases[0].config.shape == "cylinder"
    assert all(c.config.m1 == c.config.m2 == 9 for c in specs["brain-sweep"].cases)  # as in 003
    make_sets = root / "data_synthetic" / "make_sets.py"
    if not make_sets.is_file():
        pytest.skip("data_synthetic/make_sets.py not there")
    spec = importlib.util.spec_from_file_location("_make_sets_for_test", make_sets)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    sets = module.load_sets()
    for config, set_name in (("brain-sweep", "brain-sweep"), ("cylinder-table", "cylinder-table-7-2"),
                             ("blobs", "organ-blobs")):
        names = [name for name, _, _ in module.expand(sets[set_name])]
        cases = specs[config].cases
        assert [c.name for c in cases] == names
        base = root / "out" / "synthetic" / set_name
        assert [c.image for c in cases] == [str(base / n / "image.nii.gz") for n in names]
        assert [c.truth for c in cases] == [str(base / n / "truth.nii.gz") for n in names]


def test_end_to_end_with_the_real_pipeline(tmp_path):
    """Two small ball phantoms through `segsnake phantom` and the real segment pipeline."""
    from conftest import perturbed_init  # here: case processes import this file as the runner

    for module, name in (("segsnake.runner", "segment_file"), ("segsnake.phantoms", None)):
        if importlib.util.find_spec(module) is None:
            pytest.skip(f"{module} not written yet")
        if name and not hasattr(importlib.import_module(module), name):
            pytest.skip(f"{module}.{name} not written yet")
    cases = ""
    for s, start in enumerate((24, 25)):
        assert main(["phantom", "ball", "--out", str(tmp_path / f"ph{s}"), "--seed", str(s)]) == 0
        # the phantom's suggested start, perturbed (issue 14)
        init = perturbed_init(json.loads((tmp_path / f"ph{s}" / "phantom.json").read_text()), start)
        truth = f"ph{s}/truth.nii.gz"
        if s == 1:  # ph1's truth is a label map: the ball is label 5, a corner cube label 9
            img = nib.load(tmp_path / truth)
            labels = np.asarray(img.dataobj).astype(np.int16) * 5
            labels[:8, :8, :8] = 9
            nib.save(nib.Nifti1Image(labels, img.affine), tmp_path / "ph1" / "labels.nii.gz")
            truth = "ph1/labels.nii.gz\n    truth_label: 5"
        cases += (f"  - name: ph{s}\n    image: ph{s}/image.nii.gz\n    truth: {truth}\n"
                  f"    center: {init['center']}\n    radii: {init['radii']}\n")
    (tmp_path / "runs.yaml").write_text(f"output_dir: out\ndefaults:\n  shape: sphere\ncases:\n{cases}")
    assert main(["batch", str(tmp_path / "runs.yaml"), "-j", "2", "-q"]) == 0
    records = read_results(tmp_path / "out" / "results.jsonl")
    assert sorted(r["case"] for r in records) == ["ph0", "ph1"]
    rows = {r["case"]: r for r in csv_rows(tmp_path / "out" / "results.csv")}
    assert [r["truth_label"] for r in sorted(records, key=lambda r: r["case"])] == [None, 5]
    for r in records:
        assert r["status"] == "ok" and r["dice"] > 0.95, r  # ph1: against label 5 only
        assert r["summary"]["warnings"] == []
        assert r["hd95_mm"] == r["summary"]["hausdorff95_mm"] and 0 <= r["hd95_mm"] < 2.0
        assert float(rows[r["case"]]["dice"]) == r["dice"] and rows[r["case"]]["assd_mm"]
        assert r["timings"]["total_s"] > 0 and Path(r["outputs"]["mask"]).is_file()
