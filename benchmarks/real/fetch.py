"""Fetch the public scans of the real-data benchmark and build its cases in a cache outside the repo.

Usage::

    .venv/bin/python benchmarks/real/fetch.py              # fetch (once), build, verify checksums
    .venv/bin/python benchmarks/real/fetch.py --record     # write new checksums (after a change
                                                           # to the derivation, say why in the commit)

The cache is ``$SEGSNAKE_REAL_DATA`` or ``~/.cache/segsnake/real``. Only the package registries
are reachable here, so the sources are packages:

- Debian ``mricron-data`` (``apt-get download``, unpacked with ``dpkg-deb -x``);
- the ``pyradiomics`` 3.0.1 source archive from PyPI (``pip download --no-binary :all:``; its
  metadata step imports numpy, so it runs in a small venv of its own in the cache).

Each source archive's SHA-256 is checked against ``checksums.json`` before it is used, and each
built case file's after it is written: the files are written deterministically (NIfTI bytes from
nibabel, gzip with a zero timestamp), so a second fetch gives byte-identical cases. The derivation
of every reference and click is in :mod:`cases`.
"""

from __future__ import annotations

import argparse
import gzip
import hashlib
import json
import os
import subprocess
import sys
import tarfile
from typing import Any

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
for p in (HERE, os.path.dirname(HERE), ROOT):
    if p not in sys.path:
        sys.path.insert(0, p)

import cases as derive  # noqa: E402

CHECKSUMS = os.path.join(HERE, "checksums.json")
MRICRON = {"package": "mricron-data", "version": "1.2.20211006+dfsg-4",
           "file": "mricron-data_1.2.20211006+dfsg-4_all.deb"}
PYRADIOMICS = {"package": "pyradiomics", "version": "3.0.1", "file": "pyradiomics-3.0.1.tar.gz"}
TEMPLATES = "usr/share/mricron/templates"

MRICRON_SOURCE = ("Debian package mricron-data 1.2.20211006+dfsg-4 (usr/share/mricron/templates); "
                  "licence as stated by its debian/copyright: BSD-3-clause (Copyright 2006-2010, "
                  "Chris Rorden)")
LUNG_SOURCE = ("pyradiomics 3.0.1 source archive on PyPI (data/lung2_image.nrrd, "
               "data/lung2_label.nrrd); licence as stated by the archive's LICENSE.txt: "
               "BSD 3-clause (Copyright 2017 Harvard Medical School); its data/README.md names "
               "no other licence")

#: The AAL structures (label numbers and names from aal.nii.txt).
AAL_CASES = [
    ("colin27-thalamus-r", "right thalamus (AAL 78, Thalamus_R)", [78], False, "benchmark"),
    ("colin27-caudate-l", "left caudate (AAL 71, Caudate_L)", [71], False, "benchmark"),
    ("colin27-hippocampus-r", "right hippocampus (AAL 38, Hippocampus_R)", [38], False, "benchmark"),
    ("colin27-cerebellum", "cerebellum (AAL 91-116, holes filled)", list(range(91, 117)), True,
     "benchmark"),
    # The peers' settings are tuned on this one, which no table reports.
    ("colin27-thalamus-l", "left thalamus (AAL 77, Thalamus_L)", [77], False, "tuning"),
]


def cache_dir(path: str | None = None) -> str:
    """The cache directory: ``path``, ``$SEGSNAKE_REAL_DATA`` or ``~/.cache/segsnake/real``."""
    return os.path.abspath(path or os.environ.get("SEGSNAKE_REAL_DATA")
                           or os.path.join(os.path.expanduser("~"), ".cache", "segsnake", "real"))


def sha256(path: str) -> str:
    """SHA-256 of a file's bytes; of a ``.gz`` file's uncompressed bytes (another zlib build
    compresses the same NIfTI to other bytes)."""
    h = hashlib.sha256()
    opener = gzip.open if path.endswith(".gz") and not path.endswith(".tar.gz") else open
    with opener(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _clicks_digest(cases: list[dict]) -> str:
    """SHA-256 of every case's name, role, structure and initialization, canonical JSON."""
    keep = [{k: c[k] for k in ("name", "role", "structure", "init")} for c in cases]
    return hashlib.sha256(json.dumps(keep, sort_keys=True).encode()).hexdigest()


def _run(cmd: list[str], cwd: str | None = None) -> None:
    proc = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        raise SystemExit(f"fetch: {' '.join(cmd)} failed ({proc.returncode}): " + " | ".join(tail))


def _verified(path: str, expected: str | None, record: bool) -> str:
    got = sha256(path)
    if not record and got != expected:
        raise SystemExit(f"fetch: {path}: SHA-256 {got} differs from the recorded "
                         f"{expected or '(none)'}")
    return got


def fetch_sources(cache: str, recorded: dict, record: bool = False) -> dict[str, str]:
    """Download the two source archives into ``cache/sources`` (once) and check them."""
    src = os.path.join(cache, "sources")
    os.makedirs(src, exist_ok=True)
    deb = os.path.join(src, MRICRON["file"])
    if not os.path.exists(deb):
        print(f"fetch: apt-get download {MRICRON['package']}={MRICRON['version']}", file=sys.stderr)
        cmd = ["apt-get", "download", f"{MRICRON['package']}={MRICRON['version']}"]
        if subprocess.run(cmd, cwd=src, capture_output=True).returncode != 0:
            _run(["apt-get", "update"])  # an empty package list on a new machine
            _run(cmd, cwd=src)
    tgz = os.path.join(src, PYRADIOMICS["file"])
    if not os.path.exists(tgz):
        env = os.path.join(cache, "envs", "fetch")
        py = os.path.join(env, "bin", "python")
        if not os.path.exists(py):
            _run([sys.executable, "-m", "venv", env])
            _run([py, "-m", "pip", "install", "--quiet", "wheel", "setuptools", "numpy"])
        print(f"fetch: pip download {PYRADIOMICS['package']}=={PYRADIOMICS['version']}", file=sys.stderr)
        _run([py, "-m", "pip", "download", "--quiet", "--no-deps", "--no-binary", ":all:",
              "--no-build-isolation", "-d", src, f"{PYRADIOMICS['package']}=={PYRADIOMICS['version']}"])
    sums = recorded.get("sources", {})
    return {MRICRON["file"]: _verified(deb, sums.get(MRICRON["file"]), record),
            PYRADIOMICS["file"]: _verified(tgz, sums.get(PYRADIOMICS["file"]), record)}


def _unpack(cache: str) -> tuple[str, str]:
    """Unpack the sources (once); return the templates folder and the pyradiomics data folder."""
    mricron = os.path.join(cache, "unpacked", "mricron")
    if not all(os.path.exists(os.path.join(mricron, TEMPLATES, f))
               for f in ("ch2.nii.gz", "ch2bet.nii.gz", "aal.nii.gz")):
        os.makedirs(mricron, exist_ok=True)
        _run(["dpkg-deb", "-x", os.path.join(cache, "sources", MRICRON["file"]), mricron])
    radio = os.path.join(cache, "unpacked", "pyradiomics")
    data = os.path.join(radio, "pyradiomics-3.0.1", "data")
    if not os.path.exists(os.path.join(data, "lung2_label.nrrd")):
        with tarfile.open(os.path.join(cache, "sources", PYRADIOMICS["file"])) as tf:
            members = [m for m in tf.getmembers() if m.name.endswith(
                ("data/lung2_image.nrrd", "data/lung2_label.nrrd", "data/README.md", "LICENSE.txt"))]
            tf.extractall(radio, members=members, filter="data")
    return os.path.join(mricron, TEMPLATES), data


def write_nifti(path: str, data: np.ndarray, affine: np.ndarray) -> None:
    """A gzipped NIfTI-1 file whose bytes depend on ``data`` and ``affine`` only."""
    import nibabel as nib

    img = nib.Nifti1Image(data, affine)
    img.set_qform(affine, code=1)
    img.set_sform(affine, code=1)
    tmp = path + ".part"
    with open(tmp, "wb") as fh:
        fh.write(gzip.compress(img.to_bytes(), compresslevel=6, mtime=0))
    os.replace(tmp, path)


def _load(path: str) -> tuple[np.ndarray, np.ndarray]:
    """An image (NIfTI, or NRRD through SimpleITK, LPS turned into RAS) as segsnake reads it:
    the array along the file's own axes and its RAS affine."""
    from segsnake.io import load_volume

    vol = load_volume(path)
    return vol.data, vol.affine


def build_cases(cache: str) -> list[dict[str, Any]]:
    """Write the images, references and ``cases.json`` into ``cache/cases``; return the cases."""
    templates, lung = _unpack(cache)
    out = os.path.join(cache, "cases")
    os.makedirs(out, exist_ok=True)
    cases: list[dict[str, Any]] = []

    def add(name: str, structure: str, image: str, truth_name: str, truth: np.ndarray,
            affine: np.ndarray, init: dict, source: str, role: str = "benchmark") -> None:
        write_nifti(os.path.join(out, truth_name), truth.astype(np.uint8), affine)
        cases.append({"name": name, "structure": structure, "role": role, "image": image,
                      "truth": truth_name, "init": init, "source": source})

    t1, aff = _load(os.path.join(templates, "ch2.nii.gz"))
    write_nifti(os.path.join(out, "colin27_t1.nii.gz"), t1.astype(np.uint8), aff)
    bet, bet_aff = _load(os.path.join(templates, "ch2bet.nii.gz"))
    atlas, atlas_aff = _load(os.path.join(templates, "aal.nii.gz"))
    for other, other_aff in ((bet, bet_aff), (atlas, atlas_aff)):
        if other.shape != t1.shape or not np.allclose(other_aff, aff):
            raise SystemExit("fetch: ch2bet or aal is not on ch2's grid")
    sp = np.sqrt((aff[:3, :3] ** 2).sum(axis=0))
    brain = derive.brain_reference(bet)
    add("colin27-brain", "brain (ch2bet non-zero, largest component)", "colin27_t1.nii.gz",
        "colin27_brain.nii.gz", brain, aff, derive.sphere_click(brain, sp), MRICRON_SOURCE)
    for name, structure, labels, fill, role in AAL_CASES:
        ref = derive.atlas_reference(np.rint(atlas), labels, fill)
        add(name, structure, "colin27_t1.nii.gz", name.replace("-", "_") + ".nii.gz", ref, aff,
            derive.sphere_click(ref, sp), MRICRON_SOURCE, role=role)

    ct, ct_aff = _load(os.path.join(lung, "lung2_image.nrrd"))
    label, _ = _load(os.path.join(lung, "lung2_label.nrrd"))
    # The trachea is tracked along array axis 2, which must run from inferior to superior.
    if int(np.argmax(np.abs(ct_aff[2, :3]))) != 2 or ct_aff[2, 2] <= 0:
        raise SystemExit("fetch: lung2's third array axis is not inferior-to-superior")
    write_nifti(os.path.join(out, "lung2_ct.nii.gz"), ct.astype(np.int16), ct_aff)
    csp = np.sqrt((ct_aff[:3, :3] ** 2).sum(axis=0))
    tumour = label == 1
    add("lung2-tumour", "lung tumour (lung2_label == 1)", "lung2_ct.nii.gz", "lung2_tumour.nii.gz",
        tumour, ct_aff, derive.sphere_click(tumour, csp), LUNG_SOURCE)
    trachea, slices = derive.trachea_reference(ct)
    add("lung2-trachea", f"trachea above the carina (air < {derive.AIR_HU:g} HU, axial slices "
        f"{slices[-1]}-{slices[0]})", "lung2_ct.nii.gz", "lung2_trachea.nii.gz", trachea, ct_aff,
        derive.tube_click(trachea, slices, csp), LUNG_SOURCE)

    tmp = os.path.join(out, "cases.json.part")  # a running benchmark never reads half of it
    with open(tmp, "w") as fh:
        json.dump(cases, fh, indent=1)
    os.replace(tmp, os.path.join(out, "cases.json"))
    return cases


def case_checksums(cache: str, cases: list[dict]) -> dict[str, str]:
    """SHA-256 of every built image and reference (uncompressed), and of the clicks."""
    folder = os.path.join(cache, "cases")
    names = sorted({c["image"] for c in cases} | {c["truth"] for c in cases})
    return {"clicks": _clicks_digest(cases), **{n: sha256(os.path.join(folder, n)) for n in names}}


def _cached_cases_verified(cache: str, recorded: dict) -> list[dict] | None:
    """The cached cases if every built file and the clicks match ``recorded``, else None."""
    path = os.path.join(cache, "cases", "cases.json")
    if not recorded.get("cases") or not os.path.exists(path):
        return None
    with open(path) as fh:
        cases = json.load(fh)
    try:
        return cases if case_checksums(cache, cases) == recorded["cases"] else None
    except OSError:
        return None


def load_cases(cache: str | None = None) -> list[dict[str, Any]]:
    """The built cases (``cases.json``), with absolute ``image``/``truth`` paths.

    Raises FileNotFoundError (saying how to build them) when the cache has none.
    """
    folder = os.path.join(cache_dir(cache), "cases")
    path = os.path.join(folder, "cases.json")
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path} not found: run `make bench-real-data` "
                                f"(benchmarks/real/fetch.py) first")
    with open(path) as fh:
        cases = json.load(fh)
    for c in cases:
        c["image"] = os.path.join(folder, c["image"])
        c["truth"] = os.path.join(folder, c["truth"])
    return cases


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", help="cache directory (default $SEGSNAKE_REAL_DATA or "
                                    "~/.cache/segsnake/real)")
    ap.add_argument("--record", action="store_true", help="write the checksums to checksums.json")
    args = ap.parse_args(argv)
    cache = cache_dir(args.cache)
    recorded: dict = {}
    if os.path.exists(CHECKSUMS) and not args.record:
        with open(CHECKSUMS) as fh:
            recorded = json.load(fh)
    cases = None if args.record else _cached_cases_verified(cache, recorded)
    if cases is not None:  # nothing to do: make bench-real* call this every time
        print(f"fetch: {len(cases)} cases in {os.path.join(cache, 'cases')}, checksums verified")
        return 0
    sources = fetch_sources(cache, recorded, args.record)
    cases = build_cases(cache)
    built = case_checksums(cache, cases)
    if args.record:
        with open(CHECKSUMS, "w") as fh:
            json.dump({"sources": sources, "cases": built}, fh, indent=1)
            fh.write("\n")
        print(f"fetch: wrote {CHECKSUMS}")
    else:
        bad = [n for n, s in built.items() if recorded.get("cases", {}).get(n) != s]
        if bad:
            print(f"fetch: {len(bad)} case files differ from checksums.json: {', '.join(bad)}",
                  file=sys.stderr)
            return 1
    for c in cases:
        print(f"{c['name']:24s} {c['role']:9s} {c['init']}")
    print(f"fetch: {len(cases)} cases in {os.path.join(cache, 'cases')}, checksums "
          f"{'recorded' if args.record else 'verified'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
