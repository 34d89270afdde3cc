"""A DICOM series directory as input: same voxels at the same world positions as the NIfTI it was
written from, the same segmentation, and one-line errors for directories that are not one series."""

from __future__ import annotations

import time
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk

from segsnake.cli import main
from segsnake.errors import InputError
from segsnake.io import load_volume
from segsnake.phantoms import make_phantom


def write_dicom_series(nifti: Path, out_dir: Path, series_uid: str = "1.2.826.0.1.3680043.2.1125.1"
                       ) -> list[Path]:
    """Write the NIfTI as an int16 DICOM series (one file per slice), as SimpleITK's example does.

    Each slice carries its own ImagePositionPatient (LPS) and the volume's ImageOrientationPatient,
    so the reader has to recover the geometry and the slice order from the tags.
    """
    image = sitk.Cast(sitk.ReadImage(str(nifti)), sitk.sitkInt16)
    out_dir.mkdir(parents=True, exist_ok=True)
    direction = image.GetDirection()
    orientation = "\\".join(f"{v:.10g}" for v in (direction[0], direction[3], direction[6],
                                                  direction[1], direction[4], direction[7]))
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    files = []
    for k in range(image.GetDepth()):
        slice_ = image[:, :, k]
        position = image.TransformIndexToPhysicalPoint((0, 0, k))
        tags = {
            "0008|0060": "MR", "0008|0016": "1.2.840.10008.5.1.4.1.1.4",
            "0020|000d": series_uid + ".0", "0020|000e": series_uid,
            "0008|0018": f"{series_uid}.{k + 1}", "0020|0013": str(k + 1),
            "0020|0037": orientation, "0020|0032": "\\".join(f"{v:.10g}" for v in position),
            "0018|0050": f"{image.GetSpacing()[2]:.10g}",
            "0008|0021": time.strftime("%Y%m%d"), "0008|0031": time.strftime("%H%M%S"),
        }
        for key, value in tags.items():
            slice_.SetMetaData(key, value)
        path = out_dir / f"{series_uid.rsplit('.', 1)[-1]}-{k:03d}.dcm"
        writer.SetFileName(str(path))
        writer.Execute(slice_)
        files.append(path)
    return files


def int16_nifti(data: np.ndarray, affine: np.ndarray, path: Path) -> Path:
    """DICOM pixels are integers: the NIfTI holds the same int16 values."""
    nib.save(nib.Nifti1Image(np.round(data).astype(np.int16), affine), str(path))
    return path


def test_series_has_the_niftis_voxels_at_the_same_world_positions(tmp_path):
    # Anisotropic voxels and k running towards the feet: DICOM's LPS and GDCM's slice sort (along
    # the normal, i.e. the reverse of k here) both have to come out right.
    rng = np.random.default_rng(0)
    data = rng.integers(-500, 1500, size=(12, 10, 7)).astype(np.float64)
    affine = np.array([[0.8, 0, 0, -10.0], [0, 0.9, 0, 20.0], [0, 0, -2.5, 30.0], [0, 0, 0, 1]])
    nifti = int16_nifti(data, affine, tmp_path / "image.nii.gz")
    write_dicom_series(nifti, tmp_path / "series")
    ref = load_volume(nifti)
    dcm = load_volume(tmp_path / "series")
    assert dcm.shape == ref.shape
    # Every voxel of the series sits where the NIfTI voxel of the same value sits.
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in dcm.shape], indexing="ij"), -1).reshape(-1, 3)
    back = np.rint(ref.world_to_index(dcm.index_to_world(ijk))).astype(int)
    np.testing.assert_allclose(ref.world_to_index(dcm.index_to_world(ijk)), back, atol=1e-4)
    np.testing.assert_array_equal(dcm.data.reshape(-1), ref.data[tuple(back.T)])
    np.testing.assert_allclose(dcm.spacing, ref.spacing, rtol=1e-6)


def test_series_segments_to_the_same_mask_as_the_nifti(tmp_path, capsys):
    ph = make_phantom("ball", seed=3, shape=(40, 40, 30), spacing=(1.0, 1.0, 1.5), noise=0.05)
    # Spacing and origin exact in float32 and in decimal text: the series' slice gap, computed
    # from the positions, then equals the NIfTI's pixdim to the last bit.
    # Scaled so that the int16 rounding keeps the noise's detail.
    nifti = int16_nifti(ph.image * 10.0, ph.affine, tmp_path / "image.nii.gz")
    write_dicom_series(nifti, tmp_path / "series")
    init = ["--center", *map(str, ph.init["center"]), "--radii", *map(str, ph.init["radii"])]
    masks = {}
    for name, image in (("nifti", nifti), ("dicom", tmp_path / "series")):
        rc = main(["segment", str(image), "--out", str(tmp_path / name), "-q", *init])
        assert rc == 0, capsys.readouterr().err
        mask = nib.load(str(tmp_path / name / "mask.nii.gz"))
        masks[name] = (np.asarray(mask.dataobj), mask.affine)
    assert masks["dicom"][0].sum() > 1000
    np.testing.assert_array_equal(masks["dicom"][0], masks["nifti"][0])
    np.testing.assert_allclose(masks["dicom"][1], masks["nifti"][1], atol=1e-4)


def _error(path) -> str:
    with pytest.raises(InputError) as info:
        load_volume(path)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(str(path))
    return msg


def test_directories_that_are_not_one_even_series_are_refused(tmp_path, capsys):
    assert "no DICOM series" in _error(tmp_path)  # empty directory
    data = np.arange(8 * 8 * 6, dtype=np.float64).reshape(8, 8, 6)
    nifti = int16_nifti(data, np.diag([1.0, 1.0, 2.0, 1.0]), tmp_path / "image.nii.gz")
    files = write_dicom_series(nifti, tmp_path / "gap")
    files[3].unlink()  # a missing slice would silently stretch the volume
    assert "not evenly spaced" in _error(tmp_path / "gap")
    write_dicom_series(nifti, tmp_path / "two", series_uid="1.2.3.4")
    write_dicom_series(nifti, tmp_path / "two", series_uid="1.2.3.5")
    assert "holds 2 DICOM series" in _error(tmp_path / "two")
    # Through the command: exit 3, one line naming the directory.
    rc = main(["segment", str(tmp_path / "gap"), "--out", str(tmp_path / "seg")])
    err = capsys.readouterr().err.strip()
    assert rc == 3 and len(err.splitlines()) == 1 and str(tmp_path / "gap") in err
