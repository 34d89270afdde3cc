"""What every command prints and how every run ends (issue 17, item 3).

``--version``; ``--quiet`` and ``--json`` meaning the same on every command; a JSON error object on
stdout with ``--json`` when a run fails (usage errors included); no traceback and a documented
exit code when stdout is closed early (``| head``) or anything unexpected happens; ``segsnake
demo`` leaves no temporary directory behind.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import segsnake
from segsnake.cli import EXIT_CLOSED_PIPE, build_parser, main
from segsnake.commands.phantom import write_phantom
from segsnake.errors import InputError, message_location
from segsnake.phantoms import make_phantom

SEGSNAKE = [sys.executable, "-m", "segsnake.cli"]


@pytest.fixture(scope="module")
def ball(tmp_path_factory) -> Path:
    """A small noisy ball phantom (24^3) written by ``write_phantom``: image, truth, phantom.json."""
    d = tmp_path_factory.mktemp("ball")
    write_phantom(make_phantom("ball", seed=3, shape=(24, 24, 24), noise=0.1), d)
    return d


def run(argv, capsys) -> tuple[int, str, str]:
    rc = main([str(a) for a in argv])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


# ------------------------------------------------------------------------------------ --version
def test_version(capsys):
    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0
    assert capsys.readouterr().out == f"segsnake {segsnake.__version__}\n"


def test_one_command_imports_only_its_module():
    # `segsnake segment` does not pay for the phantom and fit commands' numerical modules; the
    # parser of every command still lists them all (`segsnake --help`).
    code = ("import sys; from segsnake.cli import build_parser, COMMANDS; "
            "p = build_parser('segment'); "
            "print('segsnake.phantoms' in sys.modules, 'segsnake.fit' in sys.modules); "
            "sub = [a for a in build_parser()._actions if hasattr(a, 'choices') and a.choices]; "
            "print(sorted(sub[0].choices) == sorted(COMMANDS))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == ["False", "False", "True"]


# ------------------------------------------------------------------------ --quiet and --json
def test_every_command_takes_quiet_and_json():
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, command in sub.choices.items():
        parsers = [command]
        nested = [a for a in command._actions if isinstance(a, argparse._SubParsersAction)]
        if nested:  # `shape sphere|ellipsoid|cylinder`
            parsers = list(nested[0].choices.values())
        for p in parsers:
            flags = {s for a in p._actions for s in a.option_strings}
            assert {"--quiet", "-q", "--json"} <= flags, (name, p.prog)


def test_quiet_prints_nothing_and_json_one_object(ball, tmp_path, capsys):
    image, truth = ball / "image.nii.gz", ball / "truth.nii.gz"
    commands = {
        "phantom": ["phantom", "ball", "--shape", "16", "16", "16", "--out"],
        "shape": ["shape", "ellipsoid", "--radii", "3", "4", "5", "--out"],
        "evaluate": ["evaluate", truth, truth],
    }
    for name, argv in commands.items():
        needs_out = argv[-1] == "--out"
        for mode in ("--quiet", "--json", None):
            out = [tmp_path / f"{name}{mode}"] if needs_out else []
            if name == "shape" and out:
                out = [tmp_path / f"{name}{mode}.json"]
            rc, stdout, err = run([*argv, *out, *([mode] if mode else [])], capsys)
            assert rc == 0 and err == "", (name, mode, err)
            if mode == "--quiet":
                assert stdout == "", name
            elif mode == "--json":
                lines = stdout.splitlines()
                assert len(lines) == 1 and json.loads(lines[0])["status"] == "ok", name
            else:
                assert stdout and not stdout.startswith("{"), name
    record = json.loads(run(["evaluate", truth, truth, "--json"], capsys)[1])
    assert record["dice"] == 1.0 and record["label"] is None and record["warnings"] == []


# -------------------------------------------------------------------------- JSON error object
def test_json_error_object_on_failure(ball, tmp_path, capsys):
    missing = tmp_path / "missing.nii.gz"
    rc, stdout, err = run(["evaluate", ball / "truth.nii.gz", missing, "--json"], capsys)
    assert rc == 3
    record = json.loads(stdout)
    assert record == {"status": "error", "command": "evaluate", "code": 3, "error": "InputError",
                      "message": f"{missing}: no such file", "file": str(missing), "line": None}
    assert err == f"segsnake evaluate: error: {missing}: no such file\n"  # stderr as without --json

    # a usage error argparse finds, and a configuration error in a YAML file (with its line)
    rc, stdout, err = run(["segment", "--json", "--m1"], capsys)
    record = json.loads(stdout)
    assert rc == 2 and (record["code"], record["command"], record["error"]) == (2, "segment",
                                                                              "UsageError")
    assert "--m1" in record["message"] and "Traceback" not in err and len(err.splitlines()) == 1
    config = tmp_path / "bad.yaml"
    config.write_text("shape: sphere\nm1: 2\n")
    rc, stdout, _ = run(["segment", ball / "image.nii.gz", "--out", tmp_path / "o", "--config",
                         config, "--json"], capsys)
    record = json.loads(stdout)
    assert rc == 2 and (record["file"], record["line"]) == (str(config), 2)
    assert not (tmp_path / "o").exists()
    # without --json, stdout stays empty on failure
    rc, stdout, _ = run(["evaluate", ball / "truth.nii.gz", missing], capsys)
    assert rc == 3 and stdout == ""


def test_message_location():
    assert message_location("a/b.yaml:12:5: unknown option") == ("a/b.yaml", 12)
    assert message_location("scan.nii.gz: no such file") == ("scan.nii.gz", None)
    assert message_location("--resume and --overwrite contradict each other: pick one") == \
        (None, None)
    assert message_location("cannot connect to the Dask scheduler at tcp://h:9: refused") == \
        (None, None)
    assert InputError("x", file="f.nii").file == "f.nii"


# -------------------------------------------------------------------- no traceback, any path
def test_closed_stdout_ends_quietly_with_141(ball, tmp_path):
    """`segsnake evaluate A B | head -1` (issue 17): the reader goes away before the output."""
    truth = str(ball / "truth.nii.gz")
    for argv in (["evaluate", truth, truth], ["evaluate", truth, truth, "--json"], ["--help"]):
        proc = subprocess.Popen([*SEGSNAKE, *argv], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE)
        proc.stdout.close()  # nobody reads: every write to stdout fails with EPIPE
        err = proc.stderr.read().decode()
        proc.wait(timeout=120)
        assert err == "", (argv, err)  # no traceback, no "Exception ignored"
        # (argparse's --help swallows the failed write itself and exits 0)
        assert proc.returncode == (0 if argv == ["--help"] else EXIT_CLOSED_PIPE), (argv, err)


def test_unexpected_error_is_one_line_without_traceback(capsys):
    """A bug in a command (here a parser whose command raises) is exit 1 and one line."""
    parser = argparse.ArgumentParser(prog="segsnake")
    parser.add_argument("--debug", action="store_true")
    sub = parser.add_subparsers(dest="command")
    broken = sub.add_parser("broken")
    broken.add_argument("--json", action="store_true")

    def fail(args):
        raise KeyError("surprise")

    broken.set_defaults(func=fail)
    rc = main(["broken"], parser=parser)
    out, err = capsys.readouterr()
    assert rc == 1 and out == ""
    assert err == ("segsnake broken: error: unexpected error: KeyError: 'surprise' (a bug: run "
                   "with --debug for the traceback and please report it)\n")
    rc = main(["broken", "--json"], parser=parser)
    record = json.loads(capsys.readouterr().out)
    assert rc == 1 and (record["code"], record["error"]) == (1, "KeyError")
    with pytest.raises(KeyError):
        main(["--debug", "broken"], parser=parser)


def test_an_interrupt_during_start_up_names_the_command(capsys):
    """A Ctrl-C before the command line is parsed (the start-up's imports; here a parser that is
    interrupted) still says which command stopped: ``segsnake batch: interrupted``, 130."""

    class Interrupted(argparse.ArgumentParser):
        def parse_args(self, *args, **kwargs):
            raise KeyboardInterrupt

    for argv, where in ((["batch", "runs.yaml"], "segsnake batch"),
                        (["--debug", "segment", "x.nii"], "segsnake segment"),
                        (["no-such-command"], "segsnake")):
        rc = main(argv, parser=Interrupted(prog="segsnake"))
        assert rc == 130 and capsys.readouterr().err == f"{where}: interrupted\n", argv


# ---------------------------------------------------------------------------------- demo
def test_demo_leaves_no_temporary_directory_and_honours_json(tmp_path):
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    proc = subprocess.run([*SEGSNAKE, "demo", "--kind", "ball", "--json"], env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""  # --json: no progress either
    record = json.loads(proc.stdout)
    assert record["status"] == "ok" and record["out"] is None
    assert record["summary"]["dice"] > 0.95 and "outputs" not in record["summary"]
    assert os.listdir(tmp_path) == []  # its temporary directory is gone


def test_label_map_warning_reaches_stderr_even_when_quiet(ball, tmp_path, capsys):
    truth = ball / "truth.nii.gz"
    import nibabel as nib

    img = nib.load(truth)
    labels = np.asarray(img.dataobj).astype(np.int16) * 4
    labels[:3, :3, :3] = 9
    atlas = tmp_path / "atlas.nii.gz"
    nib.save(nib.Nifti1Image(labels, img.affine), atlas)
    rc, stdout, err = run(["evaluate", truth, atlas, "--quiet"], capsys)
    assert rc == 0 and stdout == ""
    assert err == (f"segsnake evaluate: warning: {atlas}: holds 2 different non-zero values (4, 9):"
                   " a label map? Every non-zero voxel counts as the truth; compare with one "
                   "structure with --label N\n")


def test_every_command_runs_blas_in_one_thread():
    """Not only segment: a command's BLAS keeps to one thread (segsnake.parallel.one_blas_thread),
    so that a fit or a shape model gives the same numbers on any number of cores."""
    from conftest import blas_threads

    before = blas_threads()
    if before == {1}:
        pytest.skip("the BLAS here runs one thread already")
    parser = argparse.ArgumentParser(prog="segsnake")
    parser.add_argument("--debug", action="store_true")
    sub = parser.add_subparsers(dest="command")
    probe = sub.add_parser("probe")
    seen = []
    probe.set_defaults(func=lambda args: seen.append(blas_threads()))
    assert main(["probe"], parser=parser) == 0
    assert seen == [{1}] and blas_threads() == before
