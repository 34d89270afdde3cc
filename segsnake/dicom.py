"""A directory holding one DICOM series, read as a 3D :class:`~segsnake.io.Volume`.

SimpleITK's ``ImageSeriesReader`` (GDCM) finds the series, sorts its slices along the slice normal
(ImagePositionPatient) and builds the LPS geometry; :func:`segsnake.io.sitk_affine` turns it into
the same RAS+ affine every other input gets, with the same checks. On top of those, a series must
be one series, and its slices evenly spaced: a missing slice would otherwise silently stretch the
geometry (ITK takes the spacing from the first two slices).
"""

from __future__ import annotations

import numpy as np

from segsnake.errors import InputError
from segsnake.io import (Volume, _one_line, _quiet_stderr, _spatial_shape, check_memory,
                         sitk_affine, sitk_volume)

__all__ = ["load_dicom_series"]

# Relative deviation of a slice gap from the mean gap that counts as uneven (a missing slice
# is a deviation of 100 %; rounding in ImagePositionPatient's decimal strings is ~1e-6).
_GAP_TOLERANCE = 0.01


def load_dicom_series(path: str, volume_index: int | None, nan: str,
                      bytes_per_voxel: float | None) -> Volume:
    """Read the DICOM series in directory ``path``.

    Parameters
    ----------
    path : str
        A directory with the files of exactly one series (other files are ignored).
    volume_index : int or None
        Which component of a multi-component series (as for a 4D image).
    nan : {"refuse", "fill"}
        As :func:`segsnake.io.load_volume` (DICOM pixels are integers: never NaN in practice).
    bytes_per_voxel : float or None
        Memory guard, checked from the first slice's header before any pixel is read.

    Returns
    -------
    Volume
        ``header`` is None; ``affine`` is RAS+ as for every input.

    Raises
    ------
    InputError
        No series or several series in the directory, a single slice (2D), unreadable or
        unevenly spaced slices, or any check :func:`segsnake.io.load_volume` makes.
    """
    import SimpleITK as sitk

    with _quiet_stderr():
        ids = sitk.ImageSeriesReader.GetGDCMSeriesIDs(path)
    if not ids:
        raise InputError(f"{path}: is a directory with no DICOM series "
                         "(give an image file or a directory holding one DICOM series)")
    if len(ids) > 1:
        raise InputError(f"{path}: holds {len(ids)} DICOM series; put each series in its own "
                         "directory and give that directory")
    with _quiet_stderr():
        files = list(sitk.ImageSeriesReader.GetGDCMSeriesFileNames(path, ids[0]))
    first = sitk.ImageFileReader()
    first.SetFileName(files[0])
    try:
        with _quiet_stderr():
            first.ReadImageInformation()
    except RuntimeError as exc:
        raise InputError(f"{path}: not a readable DICOM series ({_one_line(exc)})") from None
    size = tuple(int(s) for s in first.GetSize())
    # One file per slice, or a single multi-frame file that is the whole volume.
    size = size[:3] if len(files) == 1 and len(size) >= 3 else size[:2] + (len(files),)
    ncomp = int(first.GetNumberOfComponents())
    full = size + ((ncomp,) if ncomp > 1 else ())
    shape3, vidx = _spatial_shape(path, full, volume_index)
    if bytes_per_voxel is not None:
        check_memory(shape3, bytes_per_voxel, what=path)
        check_memory(full, 8.0, what=path)  # the whole series is read
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(files)
    reader.MetaDataDictionaryArrayUpdateOn()  # per-slice positions, for the spacing check
    try:
        with _quiet_stderr():
            image = reader.Execute()
    except RuntimeError as exc:
        raise InputError(f"{path}: truncated or corrupt DICOM data ({_one_line(exc)})") from None
    _check_even_slices(path, reader, image, len(files))
    affine, spacing = sitk_affine(path, image.GetSpacing(), image.GetOrigin(),
                                  image.GetDirection(), image.GetDimension())
    return sitk_volume(path, image, affine, spacing, shape3, ncomp, vidx, nan)


def _check_even_slices(path: str, reader, image, n: int) -> None:
    """Refuse a series whose slice positions along the normal are not evenly spaced."""
    if n < 3:  # a single (multi-frame) file or two slices: no gaps to compare
        return
    positions = []
    for i in range(n):
        if not reader.HasMetaDataKey(i, "0020|0032"):
            return  # no ImagePositionPatient: GDCM ordered the files another way; nothing to check
        try:
            positions.append([float(v) for v in reader.GetMetaData(i, "0020|0032").split("\\")])
        except ValueError:
            raise InputError(f"{path}: slice {i} has an unreadable ImagePositionPatient") from None
    direction = np.asarray(image.GetDirection(), dtype=np.float64).reshape(3, 3)
    along = np.asarray(positions) @ direction[:, 2]  # position along the slice normal
    gaps = np.diff(along)
    mean = float(np.mean(gaps))
    if mean == 0.0 or np.any(np.abs(gaps - mean) > _GAP_TOLERANCE * abs(mean)):
        raise InputError(f"{path}: DICOM slices are not evenly spaced (gaps from "
                         f"{float(np.min(gaps)):.3g} to {float(np.max(gaps)):.3g} mm: a missing "
                         "or duplicated slice?)")
