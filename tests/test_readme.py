"""Every command the README shows runs as written, in order, on a fresh copy of the repository.

Convention (README, "Quick start"): a fenced block whose info string is ``bash runnable`` is run by
this test; ``bash runnable slow`` only by the slow test (``make test-slow``: the batch of 20 cases
takes about a minute); a plain ``bash`` block is shown but not run, and may only hold the commands
of :data:`NOT_RUN` (each needs something a clone does not have, or is the test suite itself).

The copy holds what a clone holds (git's tracked and untracked-not-ignored files); its ``.venv`` is
the environment running these tests, linked entry by entry with a fresh install stamp, so ``make``
finds the project installed and installs nothing. The blocks run in one bash session (``set -e``),
with every directory holding a ``segsnake`` executable removed from PATH: the README's own
``source .venv/bin/activate`` must be what makes the later ``segsnake`` commands work.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"

# A fenced block: its info string and body (blocks in this README are not nested or indented).
FENCE = re.compile(r"^```(?P<info>[^\n`]*)\n(?P<body>.*?)^```[ \t]*$", re.M | re.S)

# Commands a plain ``bash`` block may show without running them, and why.
NOT_RUN = {
    r"make test": "the test suite itself (this test is part of it)",
    r"make bench-real(-data|-quick)?": "fetches public scans and runs for minutes to an hour",
    r"segsnake batch \S+ --scheduler tcp://HOST:\d+": "needs a running Dask cluster",
}


def fenced_blocks(text: str) -> list[tuple[str, str, int]]:
    """``(info string, body, line number)`` of every fenced block of a Markdown text."""
    return [(m.group("info").strip(), m.group("body"), text.count("\n", 0, m.start()) + 1)
            for m in FENCE.finditer(text)]


def commands(body: str) -> list[str]:
    """The commands of a bash block: continuation lines joined, comments and blanks dropped."""
    joined = re.sub(r"\\\n", " ", body)
    out = []
    for line in joined.splitlines():
        line = re.sub(r"(^|\s)#.*$", "", line).strip()
        if line:
            out.append(" ".join(line.split()))
    return out


def runnable(text: str, *, slow: bool) -> list[tuple[str, int]]:
    """The bodies (and lines) of the ``bash runnable`` blocks, with the ``slow`` ones if asked."""
    out = []
    for info, body, line in fenced_blocks(text):
        words = info.split()
        if words[:2] == ["bash", "runnable"] and (slow or "slow" not in words[2:]):
            out.append((body, line))
    return out


def fresh_copy(dest: Path) -> Path:
    """What a clone of the repository holds (plus uncommitted work), with the test's venv."""
    try:
        listed = subprocess.run(["git", "-C", str(ROOT), "ls-files", "-co", "--exclude-standard",
                                 "-z"], check=True, capture_output=True).stdout
        files = [f for f in listed.decode().split("\0") if f]
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout: cannot tell what a fresh clone holds")
    for rel in files:
        src = ROOT / rel
        if src.is_file():
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / rel)  # mtimes kept: make compares them with the stamp
    # The compiled kernels are what the install builds (ignored by git): make checks they are
    # there.
    for so in (ROOT / "segsnake").glob("_*.so"):
        shutil.copy2(so, dest / "segsnake" / so.name)
    venv = Path(sys.prefix)
    if venv == Path(sys.base_prefix) or not (venv / "bin" / "segsnake").is_file():
        pytest.skip("the tests do not run in a virtual environment with segsnake installed")
    (dest / ".venv").mkdir()
    for entry in venv.iterdir():
        if entry.name != ".installed":
            (dest / ".venv" / entry.name).symlink_to(entry)
    (dest / ".venv" / ".installed").touch()  # newer than every copied build input
    # make must see the install as done: a reinstall from here would point the shared
    # environment's editable install at this temporary copy.
    if subprocess.run(["make", "-q", ".venv/.installed"], cwd=dest,
                      capture_output=True).returncode != 0:
        pytest.fail("make would reinstall segsnake in the fresh copy; not running it")
    return dest


def clean_env(tmp: Path) -> dict[str, str]:
    """The environment of a new shell where segsnake is not on the PATH yet."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("VIRTUAL_ENV", "PYTHONPATH", "MAKEFLAGS", "MFLAGS", "MAKELEVEL")}
    path = [d for d in env.get("PATH", "").split(os.pathsep)
            if d and not (Path(d) / "segsnake").exists()]
    env["PATH"] = os.pathsep.join(path)
    env["TMPDIR"] = str(tmp)
    return env


def run_readme(tmp_path: Path, *, slow: bool, timeout: float) -> tuple[Path, str, str]:
    """Run the README's runnable blocks in a fresh copy; returns (copy, stdout, stderr)."""
    if shutil.which("make") is None or shutil.which("bash") is None:
        pytest.skip("make and bash are needed to run the README's commands")
    text = README.read_text(encoding="utf-8")
    repo = fresh_copy(tmp_path / "clone")
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    script = ["set -e",
              'trap \'echo "README command failed with exit code $?: $BASH_COMMAND" >&2\' ERR']
    for i, (body, line) in enumerate(runnable(text, slow=slow)):
        script += [f"echo '@@ block {i} (README.md line {line})'", body]
    proc = subprocess.run(["bash", "--noprofile", "--norc", "-c", "\n".join(script)], cwd=repo,
                          env=clean_env(tmp), capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, (f"exit {proc.returncode}\n--- stdout (end)\n{proc.stdout[-3000:]}"
                                  f"\n--- stderr (end)\n{proc.stderr[-3000:]}")
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert not list(tmp.glob("segsnake-demo-*")), "the demo left its temporary directory behind"
    return repo, proc.stdout, proc.stderr


def _masked(line: str) -> str:
    """A line with its numbers (times, scores) replaced: what must match the README's sample."""
    return re.sub(r"\d+(\.\d+)?", "#", line.strip())


def test_every_bash_block_is_runnable_or_known_not_to_be():
    text = README.read_text(encoding="utf-8")
    blocks = fenced_blocks(text)
    start = text.index("\n## On real scans")
    real_scans = range(text.count("\n", 0, start) + 1,
                       text.count("\n", 0, text.index("\n## ", start + 1)) + 1)
    for info, body, line in blocks:
        words = info.split()
        if not words or words[0] != "bash":
            continue
        if line in real_scans:
            assert words == ["bash"], f"line {line}: the real-scan commands need external data"
        if words[1:2] == ["runnable"]:
            assert set(words[2:]) <= {"slow"}, f"line {line}: unknown marker {info!r}"
            continue
        assert words == ["bash"], f"line {line}: unknown info string {info!r}"
        for command in commands(body):
            assert any(re.fullmatch(p, command) for p in NOT_RUN), (
                f"README.md line {line}: {command!r} is shown but not run; mark its block "
                "'bash runnable' or list it in NOT_RUN with the reason")
    runs = runnable(text, slow=True)
    assert runs and any("make demo" in b for b, _ in runs) and \
        any("source .venv/bin/activate" in b for b, _ in runs)
    assert any("segsnake batch configs/blobs.yaml" in b for b, _ in runs)


def test_readme_commands_run_as_written_on_a_fresh_clone(tmp_path):
    """The runnable blocks but the slow batch: about 40 s on the loaded 2-core machine."""
    from segsnake.batch import load_batch

    repo, out, _ = run_readme(tmp_path, slow=False, timeout=600)
    # The quick start's sample of `make demo` is what it prints (numbers aside).
    text = README.read_text(encoding="utf-8")
    sample = text.split("`make demo` prints something like", 1)[1]
    sample = [_masked(x) for x in fenced_blocks(sample)[0][1].splitlines()]
    demo = out.split("@@ block 0", 1)[1].split("@@ block 1", 1)[0].splitlines()[1:]
    assert [_masked(x) for x in demo] == sample
    # The results are there and right: the sections' examples really segmented something.
    for name in ("seg", "seg-auto", "seg-world", "seg-truth", "tube-seg"):
        assert (repo / name / "mask.nii.gz").is_file(), name
    assert (repo / "model.json").is_file() and (repo / "ref.json").is_file()
    # The slow block's batch has its data: `make data` made every image and truth it names.
    spec = load_batch(repo / "configs" / "blobs.yaml")
    assert len(spec.cases) == 20


@pytest.mark.slow
def test_readme_commands_run_as_written_with_the_batch(tmp_path):
    repo, out, _ = run_readme(tmp_path, slow=True, timeout=1800)
    assert "20 cases: 20 ok, 0 failed (20 run)" in out
    assert "20 cases: 20 ok, 0 failed (0 run, 20 already done)" in out
    assert (repo / "out" / "blobs" / "results.csv").is_file()
