"""Volume input and output: one Volume type, strict input checks, atomic outputs.

Reading: NIfTI (``.nii``, ``.nii.gz``, Analyze ``.hdr/.img``) through nibabel,
a directory as one DICOM series (:mod:`segsnake.dicom`), everything else
(``.nrrd``, ``.mha``, ``.mhd``, ...) through SimpleITK, into a
:class:`Volume` whose ``data[i, j, k]`` is float32 and C-ordered with ``i`` along
the file's first index axis, ``spacing`` the voxel size in mm (column norms of
the voxel-to-world affine) and ``affine`` the 4x4 voxel-to-world (RAS+, mm)
matrix. For SimpleITK inputs (LPS world) the affine is
``diag(-1, -1, 1) [D diag(spacing) | origin]``, what nibabel would report for
the same image written as NIfTI.

Every problem with an input is an :class:`~segsnake.errors.InputError` whose
one-line message starts with the file name: missing or unreadable file, not an
image, truncated or corrupt (gzip) data, 2D images, 4D images without a
chosen volume, NaN/Inf voxels (refused unless ``nan="fill"``), zero, negative
or non-finite spacing, a singular affine, and volumes too large for memory.

Writing: masks and images go back with exactly the reference's shape, affine,
qform and sform (the NIfTI header is copied, only the data type and scaling
change), through :func:`atomic_write`: a temporary file in the destination
directory, renamed when complete; an existing output is kept unless
``overwrite=True``; a failed write leaves nothing behind.
"""

from __future__ import annotations

import contextlib
import gzip
import os
import re
import tempfile
import warnings
import zlib
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from segsnake.errors import ConfigError, InputError, OutputError

__all__ = [
    "Volume",
    "load_volume",
    "save_mask",
    "save_volume",
    "atomic_write",
    "beyond_memory",
    "check_memory",
    "check_not_input",
    "total_memory_bytes",
    "memory_limit_bytes",
    "PIPELINE_BYTES_PER_VOXEL",
    "REGION_BYTES_PER_VOXEL",
]

# Peak bytes per voxel of load + edge map + lookup, measured by
# benchmarks/bench_features.py (about 92 at 181 x 217 x 181) with a margin for the snake.
PIPELINE_BYTES_PER_VOXEL = 160.0
# The same for the region energy (filled objects), whose arrays live in a window around the
# surface: at worst the whole volume, measured 17 bytes per voxel beyond the ~100 MiB of the
# libraries (a ball filling a 256^3 volume: 371 MiB peak) and 23 (the Colin27 brain, 181 x 217
# x 181: 257 MiB; benchmarks/bench_memory.py), with a margin.
REGION_BYTES_PER_VOXEL = 32.0

# Address space a run takes beyond its arrays after the memory check: libraries loaded later
# (VTK, SimpleITK's writers), thread stacks and per-thread malloc arenas. Measured: 461 MB from the
# check to the peak (VmPeak) of a 64^3 run with 2 threads; counted only against ulimit -v.
ADDRESS_SPACE_OVERHEAD = 512 * 1024 * 1024

_NIFTI_SUFFIXES = (".nii", ".nii.gz", ".hdr", ".img", ".hdr.gz", ".img.gz")
_LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0])
# Voxel sizes outside this range (mm) are header garbage; they would also turn a scale in mm
# into kernels of 1e30 voxels downstream.
_SPACING_RANGE = (1e-6, 1e6)


@dataclass
class Volume:
    """A 3D image in memory.

    Attributes
    ----------
    data : ndarray, float32, shape (nx, ny, nz), C order
        Voxel values, ``data[i, j, k]``.
    spacing : tuple of 3 float
        Voxel size in mm along i, j, k (> 0).
    affine : ndarray, shape (4, 4)
        Voxel index to world (RAS+, mm).
    path : str or None
        The file it was read from.
    header : object or None
        The NIfTI header (nibabel) for NIfTI inputs, else None.
    warnings : list of str
        Things the loader changed and the user should be told (``nan="fill"``).
    source_shape : tuple of int or None
        The file's full array shape (e.g. ``(nx, ny, nz, 1)``), so a mask can be
        written with exactly that shape.
    volume_index : int or None
        Which volume of a 4D file this is.
    """

    data: np.ndarray
    spacing: tuple[float, float, float]
    affine: np.ndarray
    path: str | None = None
    header: object | None = None
    warnings: list[str] = field(default_factory=list)
    source_shape: tuple[int, ...] | None = None
    volume_index: int | None = None

    @property
    def shape(self) -> tuple[int, int, int]:
        """Array shape (nx, ny, nz)."""
        return tuple(self.data.shape)  # type: ignore[return-value]

    def index_to_world(self, ijk: np.ndarray) -> np.ndarray:
        """Voxel indices (N, 3) (or (3,)) to world coordinates (mm, RAS+)."""
        p = np.asarray(ijk, dtype=np.float64)
        return p @ self.affine[:3, :3].T + self.affine[:3, 3]

    def world_to_index(self, xyz: np.ndarray) -> np.ndarray:
        """World coordinates (N, 3) (or (3,)) to continuous voxel indices."""
        p = np.asarray(xyz, dtype=np.float64)
        return np.linalg.solve(self.affine[:3, :3], (p - self.affine[:3, 3]).T).T

    def index_to_mm(self, ijk: np.ndarray) -> np.ndarray:
        """Voxel indices to scaled index space (``(i sx, j sy, k sz)`` mm)."""
        return np.asarray(ijk, dtype=np.float64) * np.asarray(self.spacing)

    def mm_to_index(self, p: np.ndarray) -> np.ndarray:
        """Scaled index space (mm) to continuous voxel indices."""
        return np.asarray(p, dtype=np.float64) / np.asarray(self.spacing)


# ---------------------------------------------------------------------------- memory
def total_memory_bytes() -> int:
    """Physical memory of this machine in bytes (``os.sysconf``), 0 if unknown."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        return 0


def fmt_bytes(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB", "PB"):
        if n < 1024 or unit == "PB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024.0
    return f"{n:.1f} PB"  # pragma: no cover


def _read_limit(directory: str) -> int | None:
    """The memory limit file of one cgroup directory: bytes, 0 for none, None if absent."""
    for name in ("memory.max", "memory.limit_in_bytes"):
        try:
            with open(os.path.join(directory, name), encoding="utf-8") as fh:
                text = fh.read().strip()
        except OSError:
            continue
        if text == "max":
            return 0
        try:
            value = int(text)
        except ValueError:
            continue
        # cgroup v1 writes "no limit" as a huge number (PAGE_COUNTER_MAX pages).
        return value if 0 < value < 1 << 60 else 0
    return None


def _cgroup_limit_bytes(root: str = "/sys/fs/cgroup", membership: str = "/proc/self/cgroup"
                        ) -> int:
    """The memory limit of this process's cgroup, 0 if none: the smallest v2 ``memory.max`` or
    v1 ``memory.limit_in_bytes`` of its group (``membership`` names it) and the group's
    ancestors up to ``root`` (v2) or ``root/memory`` (v1), a parent's limit bounding its
    children."""
    groups = []
    try:
        with open(membership, encoding="utf-8") as fh:
            for line in fh:
                parts = line.strip().split(":", 2)
                if len(parts) == 3 and parts[1] == "":
                    groups.append((root, parts[2]))
                elif len(parts) == 3 and "memory" in parts[1].split(","):
                    groups.append((os.path.join(root, "memory"), parts[2]))
    except OSError:
        pass
    groups += [(root, "/"), (os.path.join(root, "memory"), "/")]
    limits = []
    for mount, rel in groups:
        d = os.path.normpath(os.path.join(mount, rel.lstrip("/")))
        while True:  # the group, then each ancestor up to the mount (inside a container's view)
            value = _read_limit(d) if os.path.isdir(d) else None
            if value:
                limits.append(value)
            if d == os.path.normpath(mount) or len(d) <= len(os.path.normpath(mount)):
                break
            d = os.path.dirname(d)
    return min(limits) if limits else 0


def _address_space_left() -> int:
    """``ulimit -v`` (RLIMIT_AS) minus the address space this process uses already and
    :data:`ADDRESS_SPACE_OVERHEAD`, 0 if no limit."""
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    except (ImportError, OSError, ValueError):  # pragma: no cover - not POSIX
        return 0
    if soft == resource.RLIM_INFINITY or soft <= 0:
        return 0
    used = 0
    try:
        with open("/proc/self/status", encoding="utf-8") as fh:
            for line in fh:
                if line.startswith("VmSize:"):
                    used = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError, IndexError):
        pass
    return max(int(soft) - used - ADDRESS_SPACE_OVERHEAD, 1)


def memory_limit_bytes() -> tuple[int, str]:
    """The memory this process may use and what sets it: the smallest of physical memory,
    ``ulimit -v`` (what is left of RLIMIT_AS) and the cgroup's limit; ``(0, "")`` if unknown."""
    limits = [(total_memory_bytes(), "this machine's memory"),
              (_address_space_left(), "the address space left under ulimit -v"),
              (_cgroup_limit_bytes(), "the cgroup's memory limit")]
    known = [(n, what) for n, what in limits if n > 0]
    return min(known) if known else (0, "")


def beyond_memory(need: float, total_bytes: int | None = None) -> str | None:
    """``"more than SOURCE (SIZE)"`` when ``need`` bytes exceed what this process may use
    (:func:`memory_limit_bytes`, or ``total_bytes``), else None (also when the limit is unknown):
    the tail of every up-front memory refusal."""
    if total_bytes is None:
        total, source = memory_limit_bytes()
    else:
        total, source = int(total_bytes), "the memory given"
    return f"more than {source} ({fmt_bytes(total)})" if 0 < total < need else None


def check_memory(
    shape: tuple[int, ...],
    bytes_per_voxel: float = PIPELINE_BYTES_PER_VOXEL,
    *,
    what: str = "volume",
    total_bytes: int | None = None,
) -> int:
    """Estimate the memory a volume needs and refuse it if this process may use less.

    Parameters
    ----------
    shape : tuple of int
        Array shape (voxels counted over all of it).
    bytes_per_voxel : float
        Peak bytes needed per voxel by the work planned on it.
    what : str
        Name used in the message (the file name).
    total_bytes : int, optional
        Memory to compare with (default: :func:`memory_limit_bytes`, the smallest of physical
        memory, ``ulimit -v`` and the cgroup's limit).

    Returns
    -------
    int
        The estimate in bytes.

    Raises
    ------
    InputError
        Naming the file, the estimate, the limit and what sets it, with the advice to crop or
        resample the image.
    """
    nvox = 1
    for s in shape:
        nvox *= max(int(s), 0)
    estimate = int(nvox * float(bytes_per_voxel))
    beyond = beyond_memory(estimate, total_bytes)
    if beyond is not None:
        dims = "x".join(str(int(s)) for s in shape)
        raise InputError(
            f"{what}: a {dims} volume needs about {fmt_bytes(estimate)} of memory, {beyond}; "
            "crop the image to the structure or resample it to larger voxels first"
        )
    return estimate


# ---------------------------------------------------------------------------- loading
def _is_nifti_name(path: str) -> bool:
    low = path.lower()
    return low.endswith(_NIFTI_SUFFIXES)


def _check_file(path: str) -> None:
    if not os.path.exists(path):
        raise InputError(f"{path}: no such file")
    if os.path.isdir(path):
        raise InputError(f"{path}: is a directory, not an image file")
    if not os.access(path, os.R_OK):
        raise InputError(f"{path}: permission denied")
    try:
        size = os.path.getsize(path)
        with open(path, "rb") as fh:
            head = fh.read(2)
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if size == 0:
        raise InputError(f"{path}: empty file, not an image")
    if path.lower().endswith(".gz") and head != b"\x1f\x8b":
        raise InputError(f"{path}: not a gzip file (corrupt or misnamed .gz)")


def _check_directory(path: str) -> None:
    """A directory is read as a DICOM series: it must be listable."""
    if not os.access(path, os.R_OK | os.X_OK):
        raise InputError(f"{path}: permission denied (a DICOM series directory must be readable)")


def _one_line(exc: BaseException) -> str:
    """A reader's exception as one short line (SimpleITK's C++ location prefix removed)."""
    text = str(exc)
    for marker in ("sitk::ERROR:", "ITK ERROR:"):
        if marker in text:
            text = text.split(marker, 1)[1]
    text = re.sub(r"^\s*\w+\(0x[0-9a-fA-F]+\):\s*", "", text)
    msg = " ".join(t.strip() for t in text.splitlines() if t.strip()) or type(exc).__name__
    return msg[:200]


class _SeveralVolumes(InputError):
    """A 4D image of several volumes, read without saying which (``volumes``: how many)."""

    def __init__(self, message: str, volumes: int) -> None:
        super().__init__(message)
        self.volumes = volumes


def _spatial_shape(
    path: str, shape: tuple[int, ...], volume_index: int | None,
) -> tuple[tuple[int, int, int], int | None]:
    """Validate dimensions; returns the 3D shape and which volume (None for 3D)."""
    shp = tuple(int(s) for s in shape)
    if any(s <= 0 for s in shp):
        raise InputError(f"{path}: invalid image dimensions {shp}")
    while len(shp) > 3 and shp[-1] == 1:
        shp = shp[:-1]
    if len(shp) < 3 or any(s == 1 for s in shp[:3]):
        dims = "x".join(str(s) for s in shape)
        raise InputError(f"{path}: is a 2D image ({dims}); segsnake needs a 3D volume")
    if len(shp) > 4:
        raise InputError(
            f"{path}: has {len(shp)} dimensions {shp}; only 3D or 4D images are supported"
        )
    if len(shp) == 4:
        nvol = shp[3]
        if volume_index is None:
            raise _SeveralVolumes(
                f"{path}: is a 4D image with {nvol} volumes; "
                f"choose one with --volume N (0..{nvol - 1})", nvol
            )
        if not 0 <= int(volume_index) < nvol:
            raise InputError(f"{path}: --volume {volume_index} is out of range (0..{nvol - 1})")
        return shp[:3], int(volume_index)  # type: ignore[return-value]
    if volume_index is not None and int(volume_index) != 0:
        raise InputError(f"{path}: is a 3D image; --volume {volume_index} does not exist (only 0)")
    return shp[:3], None  # type: ignore[return-value]


def _check_dtype(path: str, dtype: np.dtype) -> None:
    dtype = np.dtype(dtype)
    if dtype.kind == "c":
        raise InputError(
            f"{path}: complex-valued voxels ({dtype}); segsnake needs a real scalar image"
        )
    if dtype.kind not in "biuf" or dtype.fields is not None:
        raise InputError(f"{path}: voxel type {dtype} is not a real scalar (RGB or vector image?)")


def _check_geometry(path: str, affine: np.ndarray) -> tuple[float, float, float]:
    aff = np.asarray(affine, dtype=np.float64)
    if aff.shape != (4, 4) or not np.all(np.isfinite(aff)):
        raise InputError(f"{path}: voxel-to-world affine has non-finite entries")
    lin = aff[:3, :3]
    spacing = np.sqrt(np.sum(lin * lin, axis=0))
    if not np.all(np.isfinite(spacing)) or np.any(spacing <= 0):
        raise InputError(
            f"{path}: invalid voxel spacing {tuple(float(s) for s in spacing)} (must be > 0)"
        )
    if np.any(spacing < _SPACING_RANGE[0]) or np.any(spacing > _SPACING_RANGE[1]):
        raise InputError(
            f"{path}: implausible voxel spacing {tuple(float(s) for s in spacing)} mm "
            f"(expected {_SPACING_RANGE[0]:g} to {_SPACING_RANGE[1]:g} mm)"
        )
    # Singular (or numerically singular) direction: columns nearly dependent.
    cosines = lin / spacing
    if abs(np.linalg.det(cosines)) < 1e-6:
        raise InputError(
            f"{path}: voxel-to-world affine is singular (voxel axes are not independent)"
        )
    return tuple(float(s) for s in spacing)  # type: ignore[return-value]


def _finish(path: str, arr: np.ndarray, nan: str) -> tuple[np.ndarray, list[str]]:
    """Check finiteness in the source type, fill if asked, cast to float32 C order."""
    notes: list[str] = []
    arr = np.asarray(arr)
    _check_dtype(path, arr.dtype)
    if arr.dtype.kind == "f":
        finite = np.isfinite(arr)
        bad = int(arr.size - np.count_nonzero(finite))
        if bad:
            if nan == "refuse":
                raise InputError(
                    f"{path}: {bad} voxels are NaN or Inf; fix the image or use --nan fill "
                    f"to replace them with the image minimum"
                )
            good = arr[finite]
            if good.size == 0:
                raise InputError(f"{path}: every voxel is NaN or Inf")
            fill = good.min()
            arr = np.where(finite, arr, fill)
            notes.append(
                f"{path}: replaced {bad} NaN/Inf voxels with the image minimum {float(fill):g}"
            )
        if arr.dtype.itemsize > 4 and arr.size:
            big = float(np.max(np.abs(arr)))
            if big > np.finfo(np.float32).max:
                raise InputError(f"{path}: voxel values up to {big:g} exceed the float32 range")
    out = np.ascontiguousarray(arr, dtype=np.float32)
    return out, notes


def load_volume(
    path: str | os.PathLike,
    *,
    volume_index: int | None = None,
    nan: str = "refuse",
    bytes_per_voxel: float | None = PIPELINE_BYTES_PER_VOXEL,
    one_of_several: bool = True,
) -> Volume:
    """Read and validate a 3D image.

    Parameters
    ----------
    path : str or path-like
        ``.nii``/``.nii.gz`` (nibabel), a directory holding one DICOM series, or any
        format SimpleITK reads.
    volume_index : int, optional
        Which volume of a 4D image (required when the 4th axis is longer than 1).
    nan : {"refuse", "fill"}
        NaN/Inf voxels: refuse the image (default, the message gives the count)
        or replace them with the minimum of the finite voxels (noted in
        ``Volume.warnings``).
    bytes_per_voxel : float or None
        Memory guard: the image is refused before its data are read if
        ``voxels x bytes_per_voxel`` exceeds physical memory (None: no check).
    one_of_several : bool
        Whether the caller can say which volume of a 4D image it means (``volume_index``);
        False (a mask, a truth, a grid to match): a 4D image of several volumes is refused as
        such, without pointing to a choice the command does not offer.

    Returns
    -------
    Volume

    Raises
    ------
    InputError
        For every problem with the file (one line, naming the file).
    """
    if nan not in ("refuse", "fill"):
        raise ConfigError(f"nan must be 'refuse' or 'fill', got {nan!r}")
    if volume_index is not None and (isinstance(volume_index, bool) or int(volume_index) < 0):
        raise ConfigError(f"--volume must be a non-negative integer, got {volume_index!r}")
    spath = os.fspath(path)
    series = os.path.isdir(spath)
    if series:
        _check_directory(spath)
    else:
        _check_file(spath)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if series:
                from segsnake.dicom import load_dicom_series

                vol = load_dicom_series(spath, volume_index, nan, bytes_per_voxel)
            elif _is_nifti_name(spath):
                vol = _load_nibabel(spath, volume_index, nan, bytes_per_voxel)
            else:
                vol = _load_sitk(spath, volume_index, nan, bytes_per_voxel)
    except _SeveralVolumes as exc:
        if one_of_several:
            raise
        raise InputError(f"{spath}: is a 4D image with {exc.volumes} volumes; this input must "
                         f"be one 3D volume (save the one you mean as a 3D file)") from None
    except InputError:
        raise
    except MemoryError:
        raise InputError(
            f"{spath}: out of memory while reading; crop or resample the image first"
        ) from None
    except (EOFError, zlib.error, gzip.BadGzipFile) as exc:
        raise InputError(
            f"{spath}: truncated or corrupt compressed data ({_one_line(exc)})"
        ) from None
    except Exception as exc:  # any reader failure is an unreadable input, never a traceback
        msg = _one_line(exc)
        if "damaged" in msg or "Expected" in msg or "mmap" in msg:
            raise InputError(f"{spath}: truncated or corrupt image data ({msg})") from None
        raise InputError(f"{spath}: not a readable image ({msg})") from None
    return vol


@contextlib.contextmanager
def _quiet_nibabel():
    """nibabel logs header fixes to stderr; the core never prints."""
    import logging

    logger = logging.getLogger("nibabel.global")
    old = logger.level
    logger.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        logger.setLevel(old)


def _load_nibabel(path: str, volume_index: int | None, nan: str, bpv: float | None) -> Volume:
    import nibabel as nib
    from nibabel.filebasedimages import ImageFileError
    from nibabel.spatialimages import HeaderDataError

    with _quiet_nibabel():
        try:
            img = nib.load(path)
        except (ImageFileError, HeaderDataError) as exc:
            code = _nifti_datatype(path) if "data code" in str(exc) else None
            if code is not None:
                what = _NIFTI_DATATYPES.get(code, "an unknown type")
                raise InputError(
                    f"{path}: NIfTI datatype {code} ({what}) cannot be read; save the image as "
                    f"uint8, int16 or float32 (datatype 2, 4 or 16), e.g. fslmaths {path} "
                    f"OUT.nii.gz -odt char, or nibabel/SimpleITK with that type") from None
            raise InputError(f"{path}: not a NIfTI/Analyze image ({_one_line(exc)})") from None
        if not isinstance(img, nib.spatialimages.SpatialImage):
            raise InputError(f"{path}: not a volume image")
        header = img.header
        _check_dtype(path, header.get_data_dtype())
        shape3, vidx = _spatial_shape(path, img.shape, volume_index)
        if bpv is not None:
            check_memory(shape3, bpv, what=path)
        _check_raw_pixdim(path, img)
        affine = np.asarray(img.affine, dtype=np.float64)
        spacing = _check_geometry(path, affine)
        dataobj = img.dataobj
        full = tuple(int(s) for s in img.shape)
        # Read only the requested volume of a 4D file.
        if vidx is not None:
            index = (slice(None),) * 3 + (vidx,) + (0,) * (len(full) - 4)
            arr = np.asanyarray(dataobj[index])
        else:
            arr = np.asanyarray(dataobj).reshape(shape3)
        if tuple(arr.shape) != shape3:
            raise InputError(f"{path}: data shape {arr.shape} does not match the header {shape3}")
    data, notes = _finish(path, arr, nan)
    return Volume(
        data=data, spacing=spacing, affine=affine, path=path, header=header.copy(),
        warnings=notes, source_shape=full, volume_index=vidx,
    )


# NIfTI datatype codes nibabel cannot read, named for the message (nifti1.h).
_NIFTI_DATATYPES = {1: "1 bit per voxel", 32: "complex64", 128: "RGB24", 1792: "complex128",
                    2048: "complex256", 2304: "RGBA32"}


def _nifti_datatype(path: str) -> int | None:
    """The ``datatype`` field of a NIfTI-1 header (bytes 70-71, either byte order), or None."""
    try:
        opener = gzip.open if path.lower().endswith(".gz") else open
        with opener(path, "rb") as fh:
            head = fh.read(348)
    except (OSError, EOFError, zlib.error):
        return None
    if len(head) < 72:
        return None
    for order in ("<", ">"):
        if int(np.frombuffer(head[:4], dtype=order + "i4")[0]) == 348:
            return int(np.frombuffer(head[70:72], dtype=order + "i2")[0])
    return None


def _meta_data_problem(path: str, shape: tuple[int, ...], ncomp: int) -> str | None:
    """What is wrong with the data file of a MetaImage header (``.mhd``), or None.

    ITK reports a missing *or short* data file as "No such file or directory" on the header;
    this names the data file and says which it is.
    """
    try:
        with open(path, "rb") as fh:
            text = fh.read(65536).decode("latin-1")
    except OSError:
        return None
    fields = {}
    for line in text.splitlines():
        key, sep, value = line.partition("=")
        if sep:
            fields[key.strip()] = value.strip()
    name = fields.get("ElementDataFile")
    if not name or name.upper() in ("LOCAL", "LIST") or "%" in name:
        return None
    data = name if os.path.isabs(name) else os.path.join(os.path.dirname(path), name)
    if not os.path.exists(data):
        return (f"its data file {data} (ElementDataFile) does not exist; copy it next to the "
                f"header or correct ElementDataFile")
    if fields.get("CompressedData", "False").lower() == "true":
        return None
    sizes = {"MET_UCHAR": 1, "MET_CHAR": 1, "MET_USHORT": 2, "MET_SHORT": 2, "MET_UINT": 4,
             "MET_INT": 4, "MET_ULONG": 8, "MET_LONG": 8, "MET_ULONG_LONG": 8,
             "MET_LONG_LONG": 8, "MET_FLOAT": 4, "MET_DOUBLE": 8}
    per = sizes.get(fields.get("ElementType", ""))
    if per is None:
        return None
    need = per * max(ncomp, 1)
    for n in shape:
        need *= int(n)
    try:
        header = max(int(fields.get("HeaderSize", "0")), 0)
    except ValueError:
        header = 0
    have = os.path.getsize(data)
    if have < need + header:
        return (f"its data file {data} holds {have} bytes but the header needs {need + header} "
                f"({'x'.join(str(int(n)) for n in shape)} voxels of {fields['ElementType']}): the "
                f"data file is truncated (copy it again)")
    return None


def _check_raw_pixdim(path: str, img) -> None:
    """nibabel silently turns zero or negative pixdim into 1 or abs; refuse them instead.

    Only when the pixdims define the geometry (no sform).
    """
    hdr = img.header
    if "sform_code" in hdr and int(hdr["sform_code"]) > 0:
        return
    import nibabel as nib

    holder = img.file_map.get("header") or img.file_map.get("image")
    fname = None if holder is None else holder.filename
    if fname is None:  # pragma: no cover - loaded from memory
        return
    with nib.openers.ImageOpener(fname) as fobj:
        raw = type(hdr).from_fileobj(fobj, check=False)
    ndim = min(3, int(raw["dim"][0]) if 0 < int(raw["dim"][0]) <= 7 else 3)
    pix = np.asarray(raw["pixdim"][1 : 1 + ndim], dtype=np.float64)
    if not np.all(np.isfinite(pix)) or np.any(pix <= 0):
        raise InputError(
            f"{path}: invalid voxel spacing (pixdim) {tuple(float(p) for p in pix)} (must be > 0)"
        )


@contextlib.contextmanager
def _quiet_stderr():
    """ITK's MetaIO and friends write diagnostics straight to file descriptor 2; the core never
    prints, so fd 2 points to /dev/null while SimpleITK reads or writes (errors still raise)."""
    try:
        saved = os.dup(2)
    except OSError:  # pragma: no cover - no stderr at all
        yield
        return
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, 2)
        finally:
            os.close(devnull)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _load_sitk(path: str, volume_index: int | None, nan: str, bpv: float | None) -> Volume:
    import SimpleITK as sitk

    reader = sitk.ImageFileReader()
    reader.SetFileName(path)
    try:
        with _quiet_stderr():
            reader.ReadImageInformation()
    except RuntimeError as exc:
        raise InputError(f"{path}: not a readable image ({_one_line(exc)})") from None
    dim = int(reader.GetDimension())
    size = tuple(int(s) for s in reader.GetSize())
    ncomp = int(reader.GetNumberOfComponents())
    full = size + ((ncomp,) if ncomp > 1 else ())
    # Components of a vector image are treated like the volumes of a 4D image.
    if ncomp > 1 and dim > 3:
        raise InputError(
            f"{path}: a {dim}D image with {ncomp} components per voxel is not supported"
        )
    shape3, vidx = _spatial_shape(path, full, volume_index)
    if bpv is not None:
        check_memory(shape3, bpv, what=path)
        check_memory(full, 8.0, what=path)  # the whole file is read
    affine, spacing = sitk_affine(path, reader.GetSpacing(), reader.GetOrigin(),
                                  reader.GetDirection(), dim)
    try:
        with _quiet_stderr():
            image = reader.Execute()
    except RuntimeError as exc:  # the header was readable, the data are not
        problem = _meta_data_problem(path, size, ncomp) if path.lower().endswith(".mhd") \
            else None
        if problem is not None:
            raise InputError(f"{path}: {problem}") from None
        raise InputError(f"{path}: truncated or corrupt image data ({_one_line(exc)})") from None
    return sitk_volume(path, image, affine, spacing, shape3, ncomp, vidx, nan)


def sitk_affine(path: str, spacing, origin, direction, dim: int
                ) -> tuple[np.ndarray, tuple[float, float, float]]:
    """The RAS+ voxel-to-world affine and the checked spacing of a SimpleITK (LPS) geometry.

    Parameters
    ----------
    path : str
        The input, named in error messages.
    spacing, origin, direction : sequences of float
        SimpleITK's ``GetSpacing()``, ``GetOrigin()`` and ``GetDirection()`` (row-major
        ``dim x dim``); only their first three axes are used.
    dim : int
        The image dimension.

    Raises
    ------
    InputError
        Non-positive, non-finite or implausible spacing, or a singular direction.
    """
    spacing_itk = np.asarray(spacing, dtype=np.float64)[:3]
    origin3 = np.asarray(origin, dtype=np.float64)[:3]
    direction3 = np.asarray(direction, dtype=np.float64).reshape(dim, dim)[:3, :3]
    if not np.all(np.isfinite(spacing_itk)) or np.any(spacing_itk <= 0):
        raise InputError(
            f"{path}: invalid voxel spacing {tuple(float(s) for s in spacing_itk)} (must be > 0)"
        )
    affine = np.eye(4)
    affine[:3, :3] = _LPS_TO_RAS @ direction3 @ np.diag(spacing_itk)
    affine[:3, 3] = _LPS_TO_RAS @ origin3
    return affine, _check_geometry(path, affine)


def sitk_volume(path: str, image, affine: np.ndarray, spacing: tuple[float, float, float],
                shape3: tuple[int, int, int], ncomp: int, vidx: int | None, nan: str) -> Volume:
    """A :class:`Volume` from a SimpleITK image already read and checked (one volume chosen)."""
    import SimpleITK as sitk

    arr = sitk.GetArrayViewFromImage(image)  # (z, y, x), (z, y, x, c) or (t, z, y, x)
    if ncomp > 1:
        arr = arr[..., 0 if vidx is None else vidx]
    elif arr.ndim == 4:
        arr = arr[0 if vidx is None else vidx]
    arr = np.asarray(arr).reshape(tuple(reversed(shape3))).transpose(2, 1, 0)
    data, notes = _finish(path, arr, nan)
    if np.shares_memory(data, arr):  # never keep a view into SimpleITK's buffer
        data = data.copy()
    return Volume(
        data=data, spacing=spacing, affine=affine, path=path, header=None,
        warnings=notes, source_shape=shape3, volume_index=vidx,
    )


# ---------------------------------------------------------------------------- writing
def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def check_not_input(path: str | os.PathLike, *inputs: str | os.PathLike | None) -> None:
    """Refuse an output path that names one of the inputs (OutputError)."""
    out = os.path.realpath(os.fspath(path))
    for src in inputs:
        if src is None:
            continue
        s = os.fspath(src)
        same = os.path.realpath(s) == out
        if not same and os.path.exists(out) and os.path.exists(s):
            with contextlib.suppress(OSError):
                same = os.path.samefile(s, out)
        if same:
            raise OutputError(
                f"{os.fspath(path)}: output path is the input file; choose another name"
            )


def atomic_write(
    path: str | os.PathLike,
    writer: Callable[[str], object],
    overwrite: bool = False,
) -> str:
    """Write a file atomically: ``writer(tmp_path)`` then rename onto ``path``.

    The temporary file lies in the destination directory and its name keeps
    the final name as suffix (``.tmp-XXXXXX.<name>``, e.g.
    ``.tmp-k3j9a1.mask.nii.gz``) so writers that dispatch on the extension
    work. It is flushed to disk before the rename. On any failure it is
    removed and an earlier file at ``path`` is left untouched.

    Parameters
    ----------
    path : str or path-like
        Final path.
    writer : callable
        Receives the temporary path (an existing empty file) and writes the
        content there.
    overwrite : bool
        Replace an existing file (default: refuse with OutputError).

    Returns
    -------
    str
        The final path.

    Raises
    ------
    OutputError
        Existing file without ``overwrite``, missing or read-only directory,
        disk full, or any other OS error while writing.
    """
    final = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(final))
    name = os.path.basename(final)
    if not name:
        raise OutputError(f"{final}: not a file name")
    if os.path.isdir(final):
        raise OutputError(f"{final}: is a directory")
    if not os.path.isdir(directory):
        raise OutputError(f"{final}: directory {directory} does not exist")
    exists = f"{final}: already exists; use --overwrite to replace it"
    if os.path.lexists(final) and not overwrite:
        raise OutputError(exists)
    try:
        fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix="." + name, dir=directory)
    except OSError as exc:
        raise OutputError(f"{final}: cannot write in {directory} ({exc.strerror or exc})") from None
    os.close(fd)
    try:
        writer(tmp)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        if overwrite:
            os.replace(tmp, final)
        else:
            # link() fails if the name appeared meanwhile: never clobber without --overwrite.
            try:
                os.link(tmp, final)
            except FileExistsError:
                raise OutputError(exists) from None
            except OSError:
                if os.path.lexists(final):
                    raise OutputError(exists) from None
                os.replace(tmp, final)  # filesystem without hard links
            else:
                os.unlink(tmp)
    except OutputError:
        _remove(tmp)
        raise
    except OSError as exc:
        _remove(tmp)
        raise OutputError(f"{final}: write failed ({exc.strerror or _one_line(exc)})") from None
    except BaseException:
        _remove(tmp)
        raise
    from segsnake.outdir import fsync_dir

    fsync_dir(directory)
    return final


def _remove(p: str) -> None:
    with contextlib.suppress(OSError):
        os.unlink(p)


def _output_array(arr: np.ndarray, reference: Volume) -> np.ndarray:
    if tuple(arr.shape) != tuple(reference.data.shape):
        raise ValueError(
            f"array shape {arr.shape} differs from the reference's {reference.data.shape}"
        )
    src = reference.source_shape
    if src is not None and reference.volume_index is None and len(src) > 3 \
            and int(np.prod(src)) == arr.size:
        return arr.reshape(src)  # e.g. (nx, ny, nz, 1): write the input's exact shape
    return arr


def _nifti_image(arr: np.ndarray, reference: Volume, dtype: np.dtype):
    import nibabel as nib

    hdr = reference.header
    if isinstance(hdr, (nib.Nifti1Header, nib.Nifti2Header)):
        klass = nib.Nifti2Image if isinstance(hdr, nib.Nifti2Header) else nib.Nifti1Image
        h = klass.header_class.from_header(hdr)
        h.set_data_dtype(dtype)
        h.set_data_shape(arr.shape)
        h["scl_slope"] = np.nan
        h["scl_inter"] = np.nan
        h.set_intent("none", (), name="")
        # affine=None: the copied header's qform and sform (codes, values) are written as is.
        img = klass(arr, None, header=h)
    else:
        img = nib.Nifti1Image(arr, reference.affine)
        img.header.set_qform(reference.affine, code=1)
        img.header.set_sform(reference.affine, code=1)
        img.header.set_xyzt_units("mm")
        img.header.set_data_dtype(dtype)
    if np.dtype(dtype).kind in "ui":
        img.header["cal_min"] = 0
        img.header["cal_max"] = int(arr.max()) if arr.size else 0
    return img


def sitk_image(array: np.ndarray, affine: np.ndarray):
    """A SimpleITK image of ``array`` (index order i, j, k) whose physical frame is the one
    ``affine`` maps its indices into (its columns orthogonal: SimpleITK's grids are)."""
    import SimpleITK as sitk

    affine = np.asarray(affine, dtype=np.float64)
    image = sitk.GetImageFromArray(np.ascontiguousarray(array.transpose(2, 1, 0)))
    lin = affine[:3, :3]
    spacing = np.sqrt(np.sum(lin * lin, axis=0))
    image.SetSpacing(tuple(float(s) for s in spacing))
    image.SetDirection(tuple(float(d) for d in (lin / spacing).reshape(-1)))
    image.SetOrigin(tuple(float(o) for o in affine[:3, 3]))
    return image


def _sitk_image(arr: np.ndarray, reference: Volume):
    # (SimpleITK's physical frame is LPS, the NIfTI affine's RAS)
    lps = np.eye(4)
    lps[:3] = _LPS_TO_RAS @ np.asarray(reference.affine, dtype=np.float64)[:3]
    return sitk_image(arr.reshape(reference.data.shape), lps)


def _save(arr: np.ndarray, reference: Volume, path, overwrite: bool, dtype) -> None:
    spath = os.fspath(path)
    check_not_input(spath, reference.path)
    out = _output_array(arr, reference)
    if _is_nifti_name(spath):
        import nibabel as nib

        img = _nifti_image(out, reference, dtype)

        def writer(tmp: str) -> None:
            nib.save(img, tmp)
    else:
        import SimpleITK as sitk

        image = _sitk_image(out, reference)

        def writer(tmp: str) -> None:
            with _quiet_stderr():
                sitk.WriteImage(image, tmp, True)
    atomic_write(spath, writer, overwrite=overwrite)


def save_mask(
    mask: np.ndarray, reference: Volume, path: str | os.PathLike, *, overwrite: bool = False,
) -> None:
    """Write a binary mask (uint8 0/1) on the reference's grid.

    Parameters
    ----------
    mask : ndarray, bool or integer, shape = reference.data.shape
        Non-zero voxels become 1.
    reference : Volume
        The image the mask belongs to: shape, affine, qform and sform (with
        their codes) are copied exactly (a singleton 4th axis too).
    path : str or path-like
        ``.nii``/``.nii.gz`` (nibabel) or another SimpleITK format (geometry
        converted back to LPS).
    overwrite : bool
        Replace an existing file.

    Raises
    ------
    OutputError
        Output exists (without overwrite), is the input file, or cannot be written.
    """
    m = np.asarray(mask)
    data = (m != 0).astype(np.uint8)
    _save(data, reference, path, overwrite, np.uint8)


def save_volume(
    data: np.ndarray, reference: Volume, path: str | os.PathLike, *, overwrite: bool = False,
) -> None:
    """Write a float32 image on the reference's grid (same geometry rules as :func:`save_mask`)."""
    arr = np.ascontiguousarray(np.asarray(data, dtype=np.float32))
    _save(arr, reference, path, overwrite, np.float32)
