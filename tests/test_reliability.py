"""Reliability under signals, crashes and concurrency (issue 18).

* Cancellation: the thread pool stops at a request; a signal inside a commit is deferred.
* One commit per run: the output directory's lock, the journal rolled forward by the next run,
  stale staging directories removed; a run killed at every step of the commit leaves the old or
  the new set once recovered.
* Fault injection: ``segment`` and ``batch`` killed (SIGINT, SIGTERM, SIGKILL) at seeded random
  instants: documented exit code, no traceback, a complete old or new set, the next run (or
  ``--resume``) succeeds. A handful of instants here; 50 each with ``-m slow``.
* Bounds and messages: ``--scale`` beyond the image, ``--out`` equal to the input, a short
  ``.raw``, NIfTI datatype 1, a memory limit below the estimate.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import random
import signal
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest

from segsnake import cancel, outdir, parallel
from segsnake.batch import tidy_case_dirs
from segsnake.cli import main
from segsnake.errors import InputError, OutputError
from segsnake.io import ADDRESS_SPACE_OVERHEAD, _cgroup_limit_bytes, check_memory

NAMES = ("mask.nii.gz", "surface.vtp", "snake.json", "qc.png")
SEGSNAKE = [sys.executable, "-m", "segsnake.cli"]


# -- helpers ----------------------------------------------------------------------------------------


def make_ball(path: Path, seed: int, n: int = 24, radius: float = 6.0) -> None:
    """A noisy bright ball (a quick segmentation: about a second)."""
    rng = np.random.default_rng(seed)
    i, j, k = np.indices((n, n, n))
    truth = ((i - n / 2) ** 2 + (j - n / 2) ** 2 + (k - n / 2) ** 2 <= radius**2)
    image = (100.0 * truth + 10.0 + rng.normal(0.0, 15.0, truth.shape)).astype(np.float32)
    nib.save(nib.Nifti1Image(image, np.eye(4)), path)


def snapshot(d: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(d.iterdir())} if d.exists() else {}


def hidden(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir() if p.name.startswith(".")) if d.exists() else []


def complete_set(d: Path) -> bool:
    """All four outputs, from one run: the mask's voxel count is the one snake.json records."""
    if sorted(p.name for p in d.iterdir() if not p.name.startswith(".")) != sorted(NAMES):
        return False
    summary = json.loads((d / "snake.json").read_text())["summary"]
    return int(np.asarray(nib.load(d / "mask.nii.gz").dataobj).sum()) == summary["mask_voxels"]


def recovered(d: Path) -> None:
    """What the next run does first: take the lock and recover."""
    if d.exists():
        with outdir.locked(str(d)):
            pass


def one_line(err: str) -> None:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err and "Exception ignored" not in err


@pytest.fixture(scope="module")
def ball(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("ball")
    make_ball(d / "ball.nii.gz", seed=0)
    return d / "ball.nii.gz"


# -- cancellation -----------------------------------------------------------------------------------


def test_thread_map_stops_at_a_cancel_request():
    """Pieces after the request never start, in every thread, and the caller gets the
    interrupt."""
    done: list[int] = []

    def piece(i: int) -> int:
        if i == 3:
            cancel.request()
        done.append(i)
        return i

    parallel.set_threads(2)
    try:
        with pytest.raises(KeyboardInterrupt):
            parallel.thread_map(piece, range(200))
    finally:
        parallel.set_threads(None)
        cancel.reset()
    assert 3 in done and len(done) < 10  # at most the pieces already running finish
    assert parallel.thread_map(lambda i: i * i, range(5)) == [0, 1, 4, 9, 16]


def test_a_signal_inside_a_commit_is_raised_after_it():
    """SIGINT during the commit: every file is moved, then KeyboardInterrupt."""
    old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    cancel.install(grace=None)
    try:
        steps: list[str] = []
        with pytest.raises(KeyboardInterrupt):
            with cancel.deferred():
                for i in range(3):
                    if i == 1:
                        os.kill(os.getpid(), signal.SIGINT)
                        time.sleep(0.05)  # the handler runs here: it must not raise
                    steps.append(f"step {i}")
        assert steps == ["step 0", "step 1", "step 2"]
        with pytest.raises(KeyboardInterrupt):  # requested before: the block does not start
            with cancel.deferred():
                steps.append("not run")
        assert steps[-1] == "step 2"
    finally:
        cancel.reset()
        for s, h in old.items():
            signal.signal(s, h)


def test_a_run_the_watchdog_ends_leaves_no_directory_of_its_own(tmp_path):
    """The watchdog ends a run whose main thread does not unwind (an interrupt during an import
    is left to it) without the ``finally`` blocks: the output directory the run created, and its
    staging directory, go anyway (measured before: an empty directory in 2 of 30 interrupts in
    the first 0.1 s)."""
    out = tmp_path / "new" / "out"
    code = (
        "import os, signal, time\n"
        "from segsnake import cancel, outdir\n"
        "cancel.install(grace=0.2)\n"
        f"with outdir.locked({str(out)!r}):\n"
        f"    open(os.path.join(outdir.stage_dir({str(out)!r}), 'mask.nii.gz'), 'w').close()\n"
        "    try:\n"
        "        os.kill(os.getpid(), signal.SIGINT)\n"
        "        time.sleep(1)\n"
        "    except KeyboardInterrupt:\n"
        "        pass  # (swallowed, as inside an import: the watchdog ends the process)\n"
        "    time.sleep(5)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 130, proc.stderr
    assert not (tmp_path / "new").exists()


class _RaisesInDel:
    """An object whose destructor raises (where the handler's interrupt can land: nibabel's
    ArrayProxy.__del__ in a batch case, measured once in about 40 interrupts)."""

    def __del__(self) -> None:
        raise KeyboardInterrupt


def test_an_interrupt_inside_a_destructor_is_not_printed(capsys):
    """Python prints an exception raised in a destructor ("Exception ignored in ...", a traceback)
    and goes on: an interrupt is raised again at the next check, and is not printed."""
    old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    old_hook = sys.unraisablehook
    cancel.install(grace=None)
    try:
        cancel.request()
        obj = _RaisesInDel()
        del obj
        assert capsys.readouterr().err == ""
        with pytest.raises(KeyboardInterrupt):
            cancel.check()
        cancel.reset()  # (no interrupt requested: Python's own report)
        obj = _RaisesInDel()
        del obj
        assert "Exception ignored" in capsys.readouterr().err
    finally:
        cancel.reset()
        sys.unraisablehook = old_hook
        for s, h in old.items():
            signal.signal(s, h)


# -- the lock, the journal, recovery ------------------------------------------------------------------


def test_a_second_run_on_a_locked_directory_is_refused_at_once(ball, tmp_path, capsys):
    out = tmp_path / "out"
    with outdir.locked(str(out)):
        t0 = time.monotonic()
        rc = main(["segment", str(ball), "--out", str(out), "--quiet"])
        took = time.monotonic() - t0
    err = capsys.readouterr().err
    assert rc == OutputError.exit_code and took < 1.0
    one_line(err)
    assert "another segsnake run is writing into this output directory" in err and "--wait" in err
    assert not out.exists()  # the first run created it and failed: removed on release


def test_wait_waits_for_the_other_run(ball, tmp_path, capsys):
    out = tmp_path / "out"
    lock = outdir._acquire(str(out), wait=False)
    threading.Timer(0.5, lock.release).start()
    t0 = time.monotonic()
    rc = main(["segment", str(ball), "--out", str(out), "--quiet", "--wait"])
    assert rc == 0 and time.monotonic() - t0 >= 0.5, capsys.readouterr().err
    assert complete_set(out) and hidden(out) == []


def _holds_flock(pid: int) -> bool:
    """Whether process ``pid`` holds a flock (``/proc/locks``)."""
    with open("/proc/locks", encoding="utf-8") as fh:
        return any(ln.split()[1] == "FLOCK" and ln.split()[4] == str(pid) for ln in fh
                   if len(ln.split()) > 4)


@pytest.mark.parametrize("overwrite", [pytest.param(False, marks=pytest.mark.slow), True])
def test_two_concurrent_runs_one_set_the_other_refused_before_it_computes(ball, tmp_path,
                                                                          overwrite):
    """Run A holds --out; run B on it is refused at once (exit 5), with or without --overwrite,
    and A leaves its complete set."""
    out = tmp_path / "out"
    extra = ["--overwrite"] if overwrite else []
    if overwrite:  # an earlier complete set, replaced by A
        assert main(["segment", str(ball), "--out", str(out), "--quiet"]) == 0
    a = subprocess.Popen([*SEGSNAKE, "segment", str(ball), "--out", str(out), "--quiet",
                          "--m1", "8", "--m2", "8", *extra], stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 30
    while not _holds_flock(a.pid):
        assert a.poll() is None and time.monotonic() < deadline
        time.sleep(0.01)
    b = subprocess.run([*SEGSNAKE, "segment", str(ball), "--out", str(out), "--quiet", *extra],
                       capture_output=True, text=True, timeout=60)
    _, err_a = a.communicate(timeout=60)
    assert a.returncode == 0, err_a
    assert b.returncode == 5
    one_line(b.stderr)
    assert "another segsnake run is writing into this output directory" in b.stderr
    assert complete_set(out) and hidden(out) == []
    assert json.loads((out / "snake.json").read_text())["settings"]["m1"] == 8


def _stage(out: Path, tag: bytes) -> Path:
    stage = Path(outdir.stage_dir(str(out)))
    for name in NAMES:
        (stage / name).write_bytes(tag + name.encode())
    return stage


def test_recovery_rolls_a_journal_forward_and_removes_stale_stages(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    for name in NAMES:
        (out / name).write_bytes(b"old" + name.encode())
    committed = _stage(out, b"new")
    # Killed after the journal and two renames: the next run finishes the commit.
    (out / outdir.JOURNAL).write_text(json.dumps({"stage": committed.name, "names": list(NAMES)}))
    for name in NAMES[:2]:
        os.replace(committed / name, out / name)
    stale = _stage(out, b"dead")  # killed before its journal: undone
    (out / ".segsnake-XXXXabcd").mkdir()  # a staging directory of segsnake before the lock
    done = outdir.recover(str(out))
    assert done["rolled_forward"] == list(NAMES[2:])
    assert sorted(done["removed"]) == sorted([committed.name, stale.name, ".segsnake-XXXXabcd"])
    assert snapshot(out) == {n: b"new" + n.encode() for n in NAMES}


def test_a_commit_removes_an_earlier_output_the_new_set_lacks(tmp_path):
    """A sphere's result over a cylinder's (issue 16): the old profile.csv goes in the same
    commit, and a commit killed after its journal removes it when rolled forward."""
    for kill in (False, True):
        out = tmp_path / f"out{int(kill)}"
        out.mkdir()
        for name in NAMES + ("profile.csv",):
            (out / name).write_bytes(b"old" + name.encode())
        stage = _stage(out, b"new")
        if kill:  # the journal written, nothing renamed yet
            (out / outdir.JOURNAL).write_text(json.dumps(
                {"stage": stage.name, "names": list(NAMES), "remove": ["profile.csv"]}))
            recovered(out)
        else:
            outdir.commit(str(stage), str(out), True, NAMES, remove=("profile.csv",))
            recovered(out)  # the staging directory (the runner removes its own)
        assert snapshot(out) == {n: b"new" + n.encode() for n in NAMES}
    # Without overwrite nothing is removed (the run would have been refused before).
    out = tmp_path / "kept"
    out.mkdir()
    (out / "profile.csv").write_bytes(b"old")
    outdir.commit(str(_stage(out, b"new")), str(out), False, NAMES, remove=("profile.csv",))
    recovered(out)
    assert snapshot(out)["profile.csv"] == b"old" and len(snapshot(out)) == 5


def _commit_and_stop(out: str, stage: str, stop_at: str, sig: int) -> None:
    cancel.install(grace=None)

    def step(name: str) -> None:
        if name == stop_at:
            os.kill(os.getpid(), sig)
            time.sleep(0.05)

    try:
        outdir.commit(stage, out, True, NAMES, on_step=step)
    except KeyboardInterrupt:
        os._exit(130)
    os._exit(0)


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGINT, signal.SIGTERM])
def test_a_kill_at_every_step_of_the_commit_leaves_the_old_or_the_new_set(tmp_path, sig):
    """SIGKILL after the journal and after each rename: rolled forward by the next run.
    SIGINT/SIGTERM: deferred to the end of the commit (exit 130, the new set complete)."""
    ctx = mp.get_context("fork")
    for k, stop_at in enumerate(("journal",) + NAMES + ("done",)):
        out = tmp_path / f"out{k}"
        out.mkdir()
        for name in NAMES:
            (out / name).write_bytes(b"old" + name.encode())
        stage = _stage(out, b"new")
        proc = ctx.Process(target=_commit_and_stop, args=(str(out), str(stage), stop_at, sig))
        proc.start()
        proc.join(10)
        assert proc.exitcode == (-signal.SIGKILL if sig == signal.SIGKILL else 130)
        recovered(out)
        assert snapshot(out) == {n: b"new" + n.encode() for n in NAMES}, stop_at


# -- bounds and messages ---------------------------------------------------------------------------


def _run(args: list[str], capsys) -> tuple[int, str]:
    rc = main(args)
    return rc, capsys.readouterr().err


def test_scale_beyond_the_image_is_refused(ball, tmp_path, capsys):
    before = ball.read_bytes()
    rc, err = _run(["segment", str(ball), "--out", str(tmp_path / "o"), "--scale", "1e6"], capsys)
    assert rc == 2
    one_line(err)
    # 24 voxels of 1 mm: at most 0.25 x 24 = 6 mm
    assert "--scale 1e+06 mm is larger than the image allows (6 mm" in err
    rc, err = _run(["segment", str(ball), "--out", str(tmp_path / "o"), "--radii", "30", "5", "5"],
                   capsys)
    assert rc == 2 and "--radii 30 voxels is larger than the image (longest extent 24 voxels)" in err
    assert ball.read_bytes() == before and not (tmp_path / "o").exists()


def test_out_equal_to_the_input_says_so(ball, tmp_path, capsys):
    rc, err = _run(["segment", str(ball), "--out", str(ball)], capsys)
    assert rc == 5
    one_line(err)
    assert "--out is the input file itself" in err and f"--out {ball.parent / 'ball-seg'}" in err


def test_short_raw_of_an_mhd_names_the_data_file(tmp_path, capsys):
    import SimpleITK as sitk

    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((20, 20, 20), np.float32)),
                    str(tmp_path / "m.mhd"))
    with open(tmp_path / "m.raw", "r+b") as fh:
        fh.truncate(1000)
    rc, err = _run(["segment", str(tmp_path / "m.mhd"), "--out", str(tmp_path / "o")], capsys)
    assert rc == 3
    one_line(err)
    assert f"data file {tmp_path / 'm.raw'} holds 1000 bytes but the header needs 32000" in err
    (tmp_path / "m.raw").unlink()
    rc, err = _run(["segment", str(tmp_path / "m.mhd"), "--out", str(tmp_path / "o")], capsys)
    assert rc == 3 and "(ElementDataFile) does not exist" in err
    assert not (tmp_path / "o").exists()


def test_nifti_datatype_1_says_what_to_do(tmp_path, capsys):
    path = tmp_path / "bit.nii"
    nib.save(nib.Nifti1Image(np.zeros((8, 8, 8), np.uint8), np.eye(4)), path)
    raw = bytearray(path.read_bytes())
    struct.pack_into("<hh", raw, 70, 1, 1)  # datatype DT_BINARY, bitpix 1
    path.write_bytes(bytes(raw))
    rc, err = _run(["segment", str(path), "--out", str(tmp_path / "o")], capsys)
    assert rc == 3
    one_line(err)
    assert "NIfTI datatype 1 (1 bit per voxel) cannot be read; save the image as uint8" in err
    assert path.read_bytes() == bytes(raw) and not (tmp_path / "o").exists()


def test_memory_limits_name_file_estimate_and_limit(tmp_path):
    with pytest.raises(InputError, match=r"big.nii: a 256x256x256 volume needs about 2.5 GB of "
                                         r"memory, more than the memory given \(1.0 GB\)"):
        check_memory((256, 256, 256), 160.0, what="big.nii", total_bytes=1 << 30)
    # cgroup v2: the group's own limit, or a smaller one of an ancestor; "max" is no limit
    v2 = tmp_path / "v2"
    (v2 / "jobs" / "run1").mkdir(parents=True)
    (tmp_path / "cg2").write_text("0::/jobs/run1\n")
    (v2 / "jobs" / "run1" / "memory.max").write_text("3221225472\n")
    assert _cgroup_limit_bytes(str(v2), str(tmp_path / "cg2")) == 3 << 30
    (v2 / "jobs" / "memory.max").write_text("2147483648\n")
    assert _cgroup_limit_bytes(str(v2), str(tmp_path / "cg2")) == 2 << 30
    for f in (v2 / "jobs" / "memory.max", v2 / "jobs" / "run1" / "memory.max"):
        f.write_text("max\n")
    assert _cgroup_limit_bytes(str(v2), str(tmp_path / "cg2")) == 0
    # cgroup v1: the memory controller's hierarchy; its "no limit" is a huge number
    v1 = tmp_path / "v1" / "memory" / "grp"
    v1.mkdir(parents=True)
    (tmp_path / "cg1").write_text("4:memory:/grp\n1:cpu:/\n")
    (v1 / "memory.limit_in_bytes").write_text("1073741824\n")
    (v1.parent / "memory.limit_in_bytes").write_text("9223372036854771712\n")
    assert _cgroup_limit_bytes(str(tmp_path / "v1"), str(tmp_path / "cg1")) == 1 << 30


def _under_address_space(headroom_mb: int, imports: str, body: str
                         ) -> subprocess.CompletedProcess:
    """Run ``body`` in a fresh interpreter, after ``imports``, with RLIMIT_AS set to what it
    then uses, the overhead and ``headroom_mb`` MB."""
    code = ("import resource\n" + imports +
            "used = [int(l.split()[1]) * 1024 for l in open('/proc/self/status') "
            "if l.startswith('VmSize:')][0]\n"
            f"lim = used + {ADDRESS_SPACE_OVERHEAD} + {headroom_mb} * 2**20\n"
            "resource.setrlimit(resource.RLIMIT_AS, (lim, lim))\n" + body)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)


def test_ulimit_v_below_the_estimate_is_refused_up_front():
    """RLIMIT_AS set to what this process uses + the overhead + 100 MB: 256^3 (2.5 GB) is
    refused, naming ulimit -v."""
    proc = _under_address_space(100, "from segsnake.io import check_memory\n",
                                "check_memory((64, 64, 64), 160.0, what='small.nii')\n"
                                "check_memory((256, 256, 256), 160.0, what='big.nii')\n")
    assert proc.returncode == 1
    assert "InputError: big.nii: a 256x256x256 volume needs about 2.5 GB of memory, more than " \
           "the address space left under ulimit -v (" in proc.stderr


def test_a_control_grid_too_large_for_memory_is_refused_up_front():
    """--m1 200 --m2 200 once took the machine's memory (the optimizer's dense metric, 61 GB):
    M1 = M2 = 60 (545 MB) is refused under ulimit -v with 300 MB left, 20 x 20 (8 MB) is not."""
    proc = _under_address_space(300, (
        "import types\n"
        "from segsnake.config import SegmentConfig\n"
        "from segsnake.runner import check_sizes\n"), (
        "image = types.SimpleNamespace(path='a.nii', shape=(64, 64, 64), spacing=(1.0, 1.0, 1.0))\n"
        "check_sizes(SegmentConfig(m1=20, m2=20), image)\n"
        "check_sizes(SegmentConfig(m1=60, m2=60), image)\n"))
    assert proc.returncode == 1
    assert "ConfigError: a.nii: --m1 60 --m2 60 needs about 545.1 MB of memory for the snake's " \
           "3780 control points, more than the address space left under ulimit -v (" \
           in proc.stderr, proc.stderr


def test_a_saved_snake_too_large_for_memory_is_refused_up_front():
    """A saved snake given with --init brings its own grid: M1 = M2 = 60 (545 MB) is refused
    under ulimit -v with 300 MB left, as --m1 60 --m2 60 is; resampled to 20 x 20 it is not."""
    proc = _under_address_space(300, (
        "import types\n"
        "import numpy as np\n"
        "from segsnake.config import SegmentConfig\n"
        "from segsnake.runner import _start_from\n"
        "from segsnake.surfaces import SphereModel\n"), (
        "image = types.SimpleNamespace(path='a.nii', shape=(64, 64, 64), spacing=(1.0, 1.0, 1.0),\n"
        "                              affine=np.eye(4))\n"
        "saved = SphereModel.unit(60, 60).transformed(10 * np.eye(3), [32.0, 32.0, 32.0])\n"
        "model, _ = _start_from(saved, SegmentConfig(init='s.json', m1=20, m2=20), image)\n"
        "assert (model.m1, model.m2) == (20, 20)\n"
        "_start_from(saved, SegmentConfig(init='s.json'), image)\n"))
    assert proc.returncode == 1
    assert "ConfigError: s.json: the saved snake's 60 x 60 control grid needs about 545.1 MB of " \
           "memory for the snake's 3780 control points, more than the address space left under " \
           "ulimit -v (" in proc.stderr, proc.stderr


# -- fault injection -------------------------------------------------------------------------------

SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGKILL)
# The interpreter's start and the import of segsnake.cli (about 0.06 s measured) come before
# segsnake's handlers: a signal then ends the process as the signal does (README).
STARTUP_S = 0.15


def _kill_segment(image: Path, out: Path, instant: float, sig: int, m1: int) -> tuple[int, float]:
    """One ``segment`` killed at ``instant`` s: checks exit code, stderr, the set after recovery."""
    had_old = out.exists() and complete_set(out)
    old = snapshot(out) if had_old else None
    args = [*SEGSNAKE, "segment", str(image), "--out", str(out), "--quiet", "--m1", str(m1),
            "--m2", str(m1)] + (["--overwrite"] if had_old else [])
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(instant)
    t0 = time.monotonic()
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    took = time.monotonic() - t0
    assert "Traceback" not in err and "Exception ignored" not in err, err
    if proc.returncode == 0:  # finished before the signal
        assert err == ""
    elif sig == signal.SIGKILL:
        assert proc.returncode == -signal.SIGKILL
    else:
        assert proc.returncode == 130 and err.strip().endswith("interrupted"), err
        assert took < 1.0, took
    recovered(out)
    if out.exists() and os.listdir(out):
        assert complete_set(out)
        assert hidden(out) == []
        if old is not None and snapshot(out) != old:
            assert proc.returncode in (0, 130, -signal.SIGKILL)  # the new set, complete
    else:
        assert old is None  # nothing was there: nothing (or an empty directory) is left
    return proc.returncode, took


def _summary(rows: list[tuple[int, float]]) -> str:
    """Exit codes with their counts, and the largest signal-to-exit time of SIGINT/SIGTERM."""
    codes = {c: sum(1 for r in rows if r[0] == c) for c in sorted({r[0] for r in rows})}
    lat = [t for c, t in rows if c == 130]
    return f"exit codes {codes}; SIGINT/SIGTERM to exit: max {max(lat, default=0):.3f} s"


def _fault_injection_segment(tmp_path: Path, image: Path, count: int, seed: int,
                             every_next_run: bool) -> list[tuple[int, float]]:
    rng = random.Random(seed)
    out = tmp_path / "seg"
    # The instants cover one whole run (its length measured here, on this machine and load),
    # and a little beyond: the commit is its last moment.
    run_s = 2.0  # about a run of the quick test on the 2-core machine
    if every_next_run:
        t0 = time.monotonic()
        # (at the killed runs' fixed size: without --m1/--m2 coarse to fine runs longer)
        subprocess.run([*SEGSNAKE, "segment", str(image), "--out", str(tmp_path / "timed"),
                        "--quiet", "--m1", "9", "--m2", "9"], check=True, timeout=120)
        run_s = time.monotonic() - t0
    rows = []
    for i in range(count):
        instant = rng.uniform(STARTUP_S, 1.05 * run_s)
        rows.append(_kill_segment(image, out, instant, SIGNALS[i % 3], m1=8 + i % 2))
        if every_next_run or i == count - 1:
            extra = ["--overwrite"] if out.exists() and complete_set(out) else []
            proc = subprocess.run([*SEGSNAKE, "segment", str(image), "--out", str(out),
                                   "--quiet", *extra], capture_output=True, text=True, timeout=60)
            assert proc.returncode == 0, proc.stderr
            assert complete_set(out) and hidden(out) == []
    return rows


def test_fault_injection_segment_quick(ball, tmp_path):
    _fault_injection_segment(tmp_path, ball, count=3, seed=18, every_next_run=False)


@pytest.mark.slow
def test_fault_injection_segment_50(ball, tmp_path):
    rows = _fault_injection_segment(tmp_path, ball, count=50, seed=1818, every_next_run=True)
    print(f"\nsegment, 50 instants: {_summary(rows)}")
    assert sum(1 for code, _ in rows if code != 0) >= 35  # most instants land inside the run


def _batch(tmp_path: Path, n_cases: int) -> Path:
    d = tmp_path / "imgs"
    d.mkdir(exist_ok=True)
    cases = ""
    for s in range(n_cases):
        make_ball(d / f"b{s}.nii.gz", seed=s, n=20, radius=5.0 + (s % 3) * 0.5)
        cases += f"  - name: c{s}\n    image: {d / f'b{s}.nii.gz'}\n"
    path = tmp_path / "runs.yaml"
    path.write_text(f"output_dir: {tmp_path / 'out'}\ndefaults:\n  m1: 8\ncases:\n{cases}")
    return path


def _kill_batch(yaml: Path, out: Path, instant: float, sig: int, resume: bool
                ) -> tuple[int, float]:
    args = [*SEGSNAKE, "batch", str(yaml), "--workers", "2", "--quiet"] + \
        (["--resume"] if resume else ["--overwrite"])
    # A new session: SIGINT goes to the whole group, as Ctrl-C in a terminal does.
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    time.sleep(instant)
    t0 = time.monotonic()
    if sig == signal.SIGINT:
        os.killpg(proc.pid, sig)
    else:
        proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    took = time.monotonic() - t0
    assert "Traceback" not in err and "Exception ignored" not in err, err
    if proc.returncode == 0:
        assert err == ""
    elif sig == signal.SIGKILL:
        assert proc.returncode == -signal.SIGKILL
    else:
        assert proc.returncode == 130 and err.strip() == "segsnake batch: interrupted", err
        assert took < 1.0, took
    time.sleep(0.3)  # the cases of a SIGKILLed batch end by themselves (their watchdog)
    return proc.returncode, took


def _check_batch_done(yaml: Path, out: Path, n_cases: int) -> None:
    proc = subprocess.run([*SEGSNAKE, "batch", str(yaml), "--resume", "--quiet"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    records = [json.loads(ln) for ln in (out / "results.jsonl").read_text().splitlines()]
    assert sorted(r["case"] for r in records) == [f"c{s}" for s in range(n_cases)]
    assert all(r["status"] == "ok" for r in records)
    for s in range(n_cases):
        assert complete_set(out / f"c{s}") and hidden(out / f"c{s}") == []


def _fault_injection_batch(tmp_path: Path, count: int, seed: int, every_next_run: bool,
                           n_cases: int = 4) -> list[tuple[int, float]]:
    yaml = _batch(tmp_path, n_cases)
    out = tmp_path / "out"
    rng = random.Random(seed)
    run_s = 4.0  # about a batch of the quick test
    if every_next_run:  # a whole batch, to draw the instants over (and a little beyond)
        t0 = time.monotonic()
        subprocess.run([*SEGSNAKE, "batch", str(yaml), "--workers", "2", "--quiet"], check=True,
                       timeout=300, capture_output=True)
        run_s = time.monotonic() - t0
    rows = []
    for i in range(count):
        # --overwrite runs every case again; --resume continues the killed run (only when that
        # was not completed by the check run).
        resume = not every_next_run and i % 2 == 1
        rows.append(_kill_batch(yaml, out, rng.uniform(STARTUP_S, 1.05 * run_s), SIGNALS[i % 3],
                                resume=resume))
        # Every case directory: a complete set or nothing, never an empty directory, once the
        # next run recovered it (the batch does that for every case before it runs any).
        if out.exists():
            tidy_case_dirs(out, [f"c{s}" for s in range(n_cases)])
            for d in out.iterdir():
                if d.is_dir():
                    assert complete_set(d) and hidden(d) == [], d
        if every_next_run or i == count - 1:
            _check_batch_done(yaml, out, n_cases)
    return rows


def test_fault_injection_batch_quick(tmp_path):
    # One instant, SIGINT to the process group (Ctrl-C in a terminal); the 50 of the slow test
    # cycle through SIGINT, SIGTERM and SIGKILL.
    _fault_injection_batch(tmp_path, count=1, seed=18, every_next_run=False, n_cases=3)


@pytest.mark.slow
def test_fault_injection_batch_50(tmp_path):
    rows = _fault_injection_batch(tmp_path, count=50, seed=1818, every_next_run=True)
    print(f"\nbatch, 50 instants: {_summary(rows)}")
    assert sum(1 for code, _ in rows if code != 0) >= 35


def test_the_up_front_memory_estimate_follows_the_energy():
    # The region energy works in a window around the surface (23 B/voxel measured at worst);
    # the edge stages build full-volume edge maps (92 B/voxel measured).
    from segsnake.config import SegmentConfig
    from segsnake.io import PIPELINE_BYTES_PER_VOXEL, REGION_BYTES_PER_VOXEL
    from segsnake.runner import _bytes_per_voxel

    assert _bytes_per_voxel(SegmentConfig()) == REGION_BYTES_PER_VOXEL == 32.0
    assert _bytes_per_voxel(SegmentConfig().replace(shape="cylinder")) == REGION_BYTES_PER_VOXEL
    assert _bytes_per_voxel(SegmentConfig().replace(feature="surface")) == PIPELINE_BYTES_PER_VOXEL
