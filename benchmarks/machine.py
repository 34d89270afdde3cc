"""Where benchmark numbers come from: cores, CPU model, library versions, the checkout's state.

Shared by the ``bench_*.py`` scripts (they run as scripts, so this directory is on sys.path).
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
from typing import Callable

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def machine_info() -> dict:
    """Cores, CPU model, Python/numpy/scipy/scikit-image/SimpleITK versions, git commit."""
    import numpy as np
    import scipy

    cpu = "unknown"
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    info = {"nproc": os.cpu_count(), "affinity": len(os.sched_getaffinity(0)), "cpu": cpu,
            "python": platform.python_version(), "numpy": np.__version__,
            "scipy": scipy.__version__}
    try:
        import skimage

        info["skimage"] = skimage.__version__
        import SimpleITK as sitk

        info["SimpleITK"] = sitk.Version_VersionString()
        info["itk_threads"] = sitk.ProcessObject.GetGlobalDefaultNumberOfThreads()
    except ImportError:
        pass
    # Read-only git queries: which code was measured.
    try:
        info["commit"] = subprocess.run(["git", "-C", ROOT, "rev-parse", "--short", "HEAD"],
                                        capture_output=True, text=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", ROOT, "status", "--porcelain", "segsnake"],
                               capture_output=True, text=True).stdout
        # "XY path" lines: strip nothing before the slice (a leading blank is the X status).
        info["segsnake_modified"] = [ln[3:] for ln in dirty.splitlines() if ln.strip()]
    except OSError:
        pass
    return info


def machine_line(m: dict) -> str:
    """One sentence naming the machine, the library versions and the measured checkout."""
    itk = f" ({m['itk_threads']} ITK threads)" if "itk_threads" in m else ""
    return (f"Machine: {m['nproc']} cores, {m['cpu']}, Python {m['python']}, numpy {m['numpy']}, "
            f"scipy {m['scipy']}, scikit-image {m.get('skimage')}, SimpleITK {m.get('SimpleITK')}"
            f"{itk}; segsnake at {m.get('commit', '?')}"
            + (f" with local changes in {', '.join(m['segsnake_modified'])}"
               if m.get("segsnake_modified") else ""))


def report(info: dict, json_path: str | None, markdown: Callable[[dict], str]) -> int:
    """Write the raw numbers to ``json_path`` (if given), print the markdown; exit status 0."""
    if json_path:
        with open(json_path, "w") as fh:
            json.dump(info, fh, indent=2)
    print(markdown(info))
    return 0
