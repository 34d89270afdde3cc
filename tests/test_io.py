"""Volume I/O: reading, validation of bad inputs, exact geometry on output, atomic writes."""

import contextlib
import errno
import gzip
import hashlib
import os
import shutil
import subprocess
import tempfile

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from segsnake.errors import ConfigError, InputError, OutputError
from segsnake.io import (
    Volume,
    atomic_write,
    check_memory,
    check_not_input,
    load_volume,
    save_mask,
    save_volume,
)

AFFINE = np.array([[0.0, -1.2, 0.1, 10.0], [0.9, 0.0, 0.0, -3.0], [0.0, 0.05, 2.5, 7.0],
                   [0, 0, 0, 1]])


def digest(path):
    with open(path, "rb") as fh:
        return hashlib.sha256(fh.read()).hexdigest()


def write_nifti(path, data, affine=AFFINE, qcode=1, scode=2, header=None):
    img = nib.Nifti1Image(data, affine, header=header)
    img.header.set_qform(affine, qcode)
    img.header.set_sform(affine, scode)
    nib.save(img, str(path))
    return str(path)


@pytest.fixture
def image(tmp_path):
    data = np.random.default_rng(0).standard_normal((6, 7, 8)).astype(np.float32)
    return write_nifti(tmp_path / "img.nii.gz", data), data


# ----------------------------------------------------------------------------- reading
def test_load_nifti(image):
    path, data = image
    before = digest(path)
    vol = load_volume(path)
    assert vol.data.dtype == np.float32 and vol.data.flags.c_contiguous
    assert np.array_equal(vol.data, data)
    ref = nib.load(path)
    assert np.array_equal(vol.affine, ref.affine)
    assert np.allclose(vol.spacing, np.linalg.norm(AFFINE[:3, :3], axis=0), rtol=1e-6)
    assert vol.path == path and vol.warnings == []
    ijk = np.array([[0, 0, 0], [1, 2, 3], [5.5, 6, 7]])
    assert np.allclose(vol.world_to_index(vol.index_to_world(ijk)), ijk)
    assert np.allclose(vol.index_to_world(ijk[1]), ref.affine[:3, :3] @ ijk[1] + ref.affine[:3, 3])
    assert digest(path) == before


def test_load_integer_and_scaled_nifti(tmp_path):
    data = np.arange(2 * 3 * 4 * 5, dtype=np.int16).reshape(4, 5, 6)
    img = nib.Nifti1Image(data, np.eye(4))
    img.header.set_slope_inter(0.5, 10.0)
    nib.save(img, str(tmp_path / "s.nii"))
    vol = load_volume(tmp_path / "s.nii")
    assert np.allclose(vol.data, data * 0.5 + 10.0)


@pytest.mark.parametrize("ext", [".nrrd", ".mha", ".mhd"])
def test_load_simpleitk_formats_affine_like_nibabel(tmp_path, ext):
    data = np.random.default_rng(1).standard_normal((5, 6, 7)).astype(np.float32)
    im = sitk.GetImageFromArray(data.transpose(2, 1, 0))
    im.SetSpacing((0.9, 1.2, 2.5))
    im.SetOrigin((1.0, 2.0, 3.0))
    im.SetDirection((0, 1, 0, -1, 0, 0, 0, 0, 1))
    path = str(tmp_path / ("b" + ext))
    sitk.WriteImage(im, path)
    vol = load_volume(path)
    assert np.array_equal(vol.data, data)
    assert vol.spacing == pytest.approx((0.9, 1.2, 2.5))
    sitk.WriteImage(im, str(tmp_path / "b.nii"))  # what nibabel reports for the same image
    assert np.allclose(vol.affine, nib.load(str(tmp_path / "b.nii")).affine, atol=1e-6)


def test_four_d_volumes(tmp_path):
    data = np.random.default_rng(2).standard_normal((5, 6, 7, 3)).astype(np.float32)
    path = write_nifti(tmp_path / "4d.nii.gz", data)
    with pytest.raises(InputError, match=r"4D image with 3 volumes; choose one with --volume N"):
        load_volume(path)
    # an input whose command offers no choice (a truth, a mask to evaluate): refused as such
    with pytest.raises(InputError, match=r"4D image with 3 volumes; this input must be one 3D "
                                         r"volume \(save the one you mean as a 3D file\)$"):
        load_volume(path, one_of_several=False)
    vol = load_volume(path, volume_index=2)
    assert np.array_equal(vol.data, data[..., 2])
    with pytest.raises(InputError, match="out of range"):
        load_volume(path, volume_index=3)
    single = write_nifti(tmp_path / "4d1.nii.gz", data[..., :1])
    vol1 = load_volume(single)
    assert vol1.data.shape == (5, 6, 7) and vol1.source_shape == (5, 6, 7, 1)
    assert np.array_equal(load_volume(single, volume_index=0).data, vol1.data)
    with pytest.raises(InputError, match="3D image; --volume 1 does not exist"):
        load_volume(single, volume_index=1)
    save_mask(vol1.data > 0, vol1, tmp_path / "m.nii.gz")
    out = nib.load(str(tmp_path / "m.nii.gz"))
    assert out.shape == (5, 6, 7, 1)  # the input's exact shape


def test_nan_policy(tmp_path):
    data = np.random.default_rng(3).standard_normal((5, 6, 7)).astype(np.float32)
    data[1, 2, 3] = np.nan
    data[2, 2, 2] = np.inf
    data[0, 0, 0] = -np.inf
    path = write_nifti(tmp_path / "nan.nii.gz", data)
    before = digest(path)
    with pytest.raises(InputError, match=r"nan.nii.gz: 3 voxels are NaN or Inf; .*--nan fill"):
        load_volume(path)
    vol = load_volume(path, nan="fill")
    finite_min = data[np.isfinite(data)].min()
    assert np.all(np.isfinite(vol.data))
    assert vol.data[1, 2, 3] == finite_min and vol.data[0, 0, 0] == finite_min
    assert len(vol.warnings) == 1 and "replaced 3 NaN/Inf voxels" in vol.warnings[0]
    assert digest(path) == before
    with pytest.raises(ConfigError):
        load_volume(path, nan="zero")


# ----------------------------------------------------------------------------- bad inputs
def _one_line(exc):
    msg = str(exc.value)
    assert "\n" not in msg
    return msg


def test_missing_directory_empty_and_not_an_image(tmp_path):
    cases = {
        str(tmp_path / "none.nii.gz"): "no such file",
        str(tmp_path): "is a directory",
    }
    (tmp_path / "empty.nii").write_bytes(b"")
    cases[str(tmp_path / "empty.nii")] = "empty file"
    (tmp_path / "text.nii").write_text("hello, I am not an image\n" * 20)
    cases[str(tmp_path / "text.nii")] = "not a"
    (tmp_path / "text.nrrd").write_text("hello\n" * 20)
    cases[str(tmp_path / "text.nrrd")] = "not a readable image"
    (tmp_path / "plain.nii.gz").write_bytes(b"not gzip at all" * 30)
    cases[str(tmp_path / "plain.nii.gz")] = "not a gzip file"
    (tmp_path / "notes.txt").write_text("just text\n")
    cases[str(tmp_path / "notes.txt")] = "not a readable image"
    for path, expected in cases.items():
        with pytest.raises(InputError) as exc:
            load_volume(path)
        msg = _one_line(exc)
        assert msg.startswith(path) and expected in msg, msg


def test_truncated_and_corrupt_gzip(image, tmp_path):
    path, _ = image
    raw = open(path, "rb").read()
    for name, blob in (("trunc.nii.gz", raw[: len(raw) // 2]),
                       ("flip.nii.gz", raw[:40] + bytes([raw[40] ^ 0xFF]) + raw[41:])):
        p = tmp_path / name
        p.write_bytes(blob)
        with pytest.raises(InputError) as exc:
            load_volume(p)
        assert _one_line(exc).startswith(str(p))
    # uncompressed and truncated: data shorter than the header says
    big = write_nifti(tmp_path / "u.nii", np.ones((10, 10, 10), np.float32))
    blob = open(big, "rb").read()
    (tmp_path / "ut.nii").write_bytes(blob[:-1000])
    with pytest.raises(InputError) as exc:
        load_volume(tmp_path / "ut.nii")
    _one_line(exc)


@pytest.mark.parametrize("shape", [(8, 9), (8, 9, 1), (1, 8, 9), (8, 1, 1, 1)])
def test_two_d_images_refused(tmp_path, shape):
    path = write_nifti(tmp_path / "flat.nii.gz", np.ones(shape, np.float32))
    with pytest.raises(InputError, match="2D image"):
        load_volume(path)


def test_two_d_itk_refused(tmp_path):
    im = sitk.GetImageFromArray(np.ones((8, 9), np.float32))
    sitk.WriteImage(im, str(tmp_path / "flat.mha"))
    with pytest.raises(InputError, match="2D image"):
        load_volume(tmp_path / "flat.mha")


@pytest.mark.parametrize("pix", [(0.0, 1.0, 1.0), (1.0, -2.0, 1.0), (1.0, 1.0, np.nan),
                                 (np.inf, 1, 1)])
def test_bad_pixdim_refused(tmp_path, pix):
    img = nib.Nifti1Image(np.ones((4, 5, 6), np.float32), None)
    img.header.set_qform(np.eye(4), 1)
    img.header.set_sform(np.eye(4), 0)
    img.header["pixdim"][1:4] = pix
    nib.save(img, str(tmp_path / "p.nii"))
    with pytest.raises(InputError, match="spacing"):
        load_volume(tmp_path / "p.nii")


def test_singular_and_nonfinite_affine_refused(tmp_path):
    sing = np.eye(4)
    sing[:3, 1] = sing[:3, 0]  # two voxel axes along x
    img = nib.Nifti1Image(np.ones((4, 5, 6), np.float32), None)
    img.header.set_sform(sing, 2)
    nib.save(img, str(tmp_path / "s.nii"))
    with pytest.raises(InputError, match="singular"):
        load_volume(tmp_path / "s.nii")
    zero = np.diag([1.0, 0.0, 1.0, 1.0])
    img.header.set_sform(zero, 2)
    nib.save(img, str(tmp_path / "z.nii"))
    with pytest.raises(InputError, match="spacing"):
        load_volume(tmp_path / "z.nii")
    nanaff = np.eye(4)
    nanaff[0, 3] = np.nan
    img.header.set_sform(nanaff, 2)
    nib.save(img, str(tmp_path / "n.nii"))
    with pytest.raises(InputError, match="non-finite"):
        load_volume(tmp_path / "n.nii")


def _write_mha(path, dims, spacing, etype="MET_FLOAT", matrix=None, data=None, cut=0):
    dtype = {"MET_FLOAT": "<f4", "MET_UCHAR": "u1", "MET_SHORT": "<i2", "MET_DOUBLE": "<f8"}[etype]
    n = int(np.prod(dims))
    arr = np.zeros(n, dtype) if data is None else np.asarray(data, dtype).ravel()
    mat = np.eye(3).ravel() if matrix is None else np.ravel(matrix)
    mat = " ".join(str(float(x)) for x in mat)
    head = (f"ObjectType = Image\nNDims = {len(dims)}\nBinaryData = True\n"
            "BinaryDataByteOrderMSB = False\n"
            f"TransformMatrix = {mat}\nOffset = {' '.join(['0'] * len(dims))}\n"
            f"ElementSpacing = {' '.join(str(s) for s in spacing)}\n"
            f"DimSize = {' '.join(str(d) for d in dims)}\nElementType = {etype}\n"
            "ElementDataFile = LOCAL\n")
    blob = head.encode() + arr.tobytes()
    with open(path, "wb") as fh:
        fh.write(blob[: len(blob) - cut] if cut else blob)
    return str(path)


@pytest.mark.parametrize("spacing", [(0, 1, 1), (1, -1, 1), (1, 1, float("nan"))])
def test_itk_bad_spacing_refused(tmp_path, spacing):
    path = _write_mha(tmp_path / "a.mha", (4, 5, 6), spacing)
    with pytest.raises(InputError) as exc:
        load_volume(path)
    assert _one_line(exc).startswith(path)


def test_itk_singular_direction_refused(tmp_path):
    path = _write_mha(tmp_path / "a.mha", (4, 5, 6), (1, 1, 1),
                      matrix=[[1, 0, 0], [1, 0, 0], [0, 0, 1]])
    with pytest.raises(InputError):
        load_volume(path)


def test_complex_and_rgb_refused(tmp_path):
    nib.save(nib.Nifti1Image(np.ones((4, 5, 6), np.complex64), np.eye(4)), str(tmp_path / "c.nii"))
    with pytest.raises(InputError, match="complex"):
        load_volume(tmp_path / "c.nii")
    rgb = np.zeros((4, 5, 6), dtype=[("R", "u1"), ("G", "u1"), ("B", "u1")])
    nib.save(nib.Nifti1Image(rgb, np.eye(4)), str(tmp_path / "rgb.nii"))
    with pytest.raises(InputError, match="scalar"):
        load_volume(tmp_path / "rgb.nii")


def test_float64_beyond_float32_refused(tmp_path):
    data = np.ones((4, 5, 6))
    data[1, 1, 1] = 1e300
    nib.save(nib.Nifti1Image(data, np.eye(4)), str(tmp_path / "big.nii"))
    with pytest.raises(InputError, match="float32 range"):
        load_volume(tmp_path / "big.nii")


def test_memory_guard(image):
    path, _ = image
    with pytest.raises(InputError) as exc:
        check_memory((1000, 1000, 1000), 160, what="x.nii", total_bytes=8 * 2**30)
    msg = _one_line(exc)
    assert "x.nii: a 1000x1000x1000 volume needs about 149.0 GB" in msg
    assert "crop the image" in msg and "resample" in msg
    assert check_memory((10, 10, 10), 8, total_bytes=2**20) == 8000
    with pytest.raises(InputError, match="crop the image"):
        load_volume(path, bytes_per_voxel=1e15)


# ----------------------------------------------------------------------------- writing
def test_save_mask_keeps_exact_geometry(tmp_path):
    data = np.random.default_rng(4).standard_normal((6, 7, 8)).astype(np.float32)
    hdr = nib.Nifti1Header()
    hdr.set_xyzt_units("mm", "sec")
    path = write_nifti(tmp_path / "in.nii.gz", data, qcode=1, scode=4, header=hdr)
    vol = load_volume(path)
    mask = vol.data > 0.3
    out = tmp_path / "out.nii.gz"
    save_mask(mask, vol, out)
    ref, got = nib.load(path), nib.load(str(out))
    assert got.shape == ref.shape and got.get_data_dtype() == np.uint8
    assert np.array_equal(np.asanyarray(got.dataobj), mask.astype(np.uint8))
    for key in ("qform_code", "sform_code", "quatern_b", "quatern_c", "quatern_d", "qoffset_x",
                "qoffset_y", "qoffset_z", "srow_x", "srow_y", "srow_z", "pixdim", "xyzt_units"):
        assert np.array_equal(got.header[key], ref.header[key]), key
    assert np.array_equal(got.affine, ref.affine)
    # float image too
    save_volume(vol.data * 2, vol, tmp_path / "img2.nii")
    back = load_volume(tmp_path / "img2.nii")
    assert np.array_equal(back.data, vol.data * 2) and np.array_equal(back.affine, vol.affine)


def test_save_mask_for_itk_reference_round_trips(tmp_path):
    data = np.random.default_rng(5).standard_normal((5, 6, 7)).astype(np.float32)
    im = sitk.GetImageFromArray(data.transpose(2, 1, 0))
    im.SetSpacing((0.9, 1.2, 2.5))
    im.SetOrigin((1.0, 2.0, 3.0))
    im.SetDirection((0, 1, 0, -1, 0, 0, 0, 0, 1))
    sitk.WriteImage(im, str(tmp_path / "a.nrrd"))
    vol = load_volume(tmp_path / "a.nrrd")
    for name in ("m.nii.gz", "m.nrrd"):
        save_mask(vol.data > 0, vol, tmp_path / name)
        back = load_volume(tmp_path / name)
        assert np.array_equal(back.data, (data > 0).astype(np.float32))
        assert np.allclose(back.affine, vol.affine, atol=1e-6)


def test_phantom_style_reference_without_header(tmp_path):
    ref = Volume(data=np.zeros((4, 5, 6), np.float32), spacing=(1.0, 2.0, 3.0),
                 affine=np.diag([1.0, 2.0, 3.0, 1.0]), path=None, header=None)
    save_mask(np.ones((4, 5, 6), bool), ref, tmp_path / "m.nii.gz")
    got = nib.load(str(tmp_path / "m.nii.gz"))
    assert np.array_equal(got.affine, ref.affine)
    assert int(got.header["qform_code"]) == 1 and int(got.header["sform_code"]) == 1


def test_output_rules(image, tmp_path):
    path, _ = image
    vol = load_volume(path)
    before = digest(path)
    out = tmp_path / "mask.nii.gz"
    save_mask(vol.data > 0, vol, out)
    first = digest(out)
    with pytest.raises(OutputError, match="already exists; use --overwrite"):
        save_mask(vol.data < 0, vol, out)
    assert digest(out) == first
    save_mask(vol.data < 0, vol, out, overwrite=True)
    assert digest(out) != first
    with pytest.raises(OutputError, match="output path is the input file"):
        save_mask(vol.data > 0, vol, path, overwrite=True)
    with pytest.raises(OutputError, match="does not exist"):
        save_mask(vol.data > 0, vol, tmp_path / "nodir" / "m.nii.gz")
    with pytest.raises(OutputError, match="is a directory"):
        save_mask(vol.data > 0, vol, tmp_path)
    with pytest.raises(ValueError):
        save_mask(np.ones((2, 2, 2)), vol, tmp_path / "wrong.nii.gz")
    assert digest(path) == before
    assert sorted(os.listdir(tmp_path)) == ["img.nii.gz", "mask.nii.gz"]
    link = tmp_path / "alias.nii.gz"
    os.symlink(path, link)
    with pytest.raises(OutputError, match="input file"):
        check_not_input(link, path)


def test_atomic_write_temp_name_permissions_and_failure(tmp_path):
    seen = []

    def writer(tmp):
        seen.append(tmp)
        with open(tmp, "w") as fh:
            fh.write("new")

    final = tmp_path / "result.snake.json"
    atomic_write(final, writer)
    name = os.path.basename(seen[0])
    assert name.startswith(".tmp-") and name.endswith(".result.snake.json")
    assert os.path.dirname(seen[0]) == str(tmp_path)
    assert final.read_text() == "new"
    umask = os.umask(0)
    os.umask(umask)
    assert os.stat(final).st_mode & 0o777 == 0o666 & ~umask

    def failing(tmp):
        with open(tmp, "w") as fh:
            fh.write("partial")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    with pytest.raises(OutputError, match="No space left on device"):
        atomic_write(final, failing, overwrite=True)
    assert final.read_text() == "new"
    assert os.listdir(tmp_path) == ["result.snake.json"]

    def crashing(tmp):
        raise RuntimeError("bug")

    with pytest.raises(RuntimeError):
        atomic_write(tmp_path / "other.json", crashing)
    assert os.listdir(tmp_path) == ["result.snake.json"]


@contextlib.contextmanager
def _tmpfs(size, readonly=False):
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("needs root to mount a tmpfs")
    where = tempfile.mkdtemp()
    opts = f"size={size}" + (",ro" if readonly else "")
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", where], capture_output=True)
    if res.returncode != 0:
        os.rmdir(where)
        pytest.skip("cannot mount a tmpfs here")
    try:
        yield where
    finally:
        subprocess.run(["umount", where], capture_output=True)
        os.rmdir(where)


def test_full_disk_leaves_no_partial_file(image):
    path, _ = image
    vol = load_volume(path)
    big = Volume(data=np.random.default_rng(6).standard_normal((64, 64, 64)).astype(np.float32),
                 spacing=vol.spacing, affine=vol.affine, header=vol.header)
    with _tmpfs("64k") as where:
        with open(os.path.join(where, "earlier.txt"), "w") as fh:
            fh.write("keep me")
        with pytest.raises(OutputError, match="No space left on device"):
            save_volume(big.data, big, os.path.join(where, "img.nii"))
        assert os.listdir(where) == ["earlier.txt"]


def test_read_only_directory_refused(image):
    path, _ = image
    vol = load_volume(path)
    with _tmpfs("64k", readonly=True) as where:
        with pytest.raises(OutputError, match="cannot write"):
            save_mask(vol.data > 0, vol, os.path.join(where, "m.nii.gz"))
        assert os.listdir(where) == []


# ----------------------------------------------------------------------------- property test
def _check_valid(vol):
    assert isinstance(vol, Volume)
    assert vol.data.dtype == np.float32 and vol.data.ndim == 3 and vol.data.flags.c_contiguous
    assert min(vol.data.shape) >= 2
    assert np.all(np.isfinite(vol.data))
    assert len(vol.spacing) == 3 and all(np.isfinite(s) and s > 0 for s in vol.spacing)
    assert np.all(np.isfinite(vol.affine)) and abs(np.linalg.det(vol.affine[:3, :3])) > 0
    assert np.allclose(vol.spacing, np.linalg.norm(vol.affine[:3, :3], axis=0))


def _load_or_refuse(path, event, **options):
    """Load ``path``: a valid Volume or a one-line InputError naming it; the file untouched."""
    before = digest(path)
    try:
        vol = load_volume(path, **options)
    except InputError as exc:
        assert "\n" not in str(exc) and str(exc).startswith(path)
        event("InputError: " + str(exc)[len(path) + 2:][:60])
    else:
        _check_valid(vol)
        event("loaded")
    assert digest(path) == before


_DTYPES = [np.uint8, np.int8, np.int16, np.uint16, np.int32, np.int64, np.float32, np.float64,
           np.complex64]
_WILD = st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=32),
                  st.sampled_from([0.0, -1.0, 1.0, 1e-30, 1e30]))


@st.composite
def nifti_case(draw):
    ndim = draw(st.sampled_from([3, 3, 3, 4, 4, 1, 2, 5]))
    sizes = st.sampled_from([2, 3, 4, 5, 2, 3, 4, 5, 1])
    shape = tuple(draw(st.lists(sizes, min_size=ndim, max_size=ndim)))
    dtype = np.dtype(draw(st.sampled_from(_DTYPES + [np.float32, np.int16, np.uint8])))
    seed = draw(st.integers(0, 2**16))
    rng = np.random.default_rng(seed)
    if dtype.kind == "f":
        data = rng.standard_normal(shape).astype(dtype)
        if draw(st.booleans()) and data.size:
            bad = draw(st.sampled_from([np.nan, np.inf, -np.inf, 1e38]))
            data.flat[rng.integers(0, data.size)] = bad
    elif dtype.kind == "c":
        data = rng.standard_normal(shape).astype(dtype)
    else:
        info = np.iinfo(dtype)
        data = rng.integers(info.min, info.max, shape, endpoint=True).astype(dtype)
    return dict(
        data=data,
        pixdim=[draw(st.one_of(st.floats(0.1, 5.0), _WILD)) for _ in range(3)],
        qcode=draw(st.sampled_from([0, 1, 2, 3, 4, 7])),
        scode=draw(st.sampled_from([0, 1, 2, 3, 4, 9])),
        srow=draw(st.one_of(st.none(), st.lists(st.one_of(st.floats(-3, 3), _WILD), min_size=12,
                                                max_size=12))),
        slope=draw(st.sampled_from([None, 0.0, 2.0, np.nan, np.inf, -1.5])),
        gz=draw(st.booleans()),
        cut=draw(st.sampled_from([0] * 8 + [1, 7, 100, 349, 400])),
        flip=draw(st.one_of(*[st.none()] * 4, st.integers(0, 347))),
        nan=draw(st.sampled_from(["refuse", "fill"])),
        volume_index=draw(st.sampled_from([None, 0, 1, 4])),
    )


@settings(max_examples=150, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(case=nifti_case())
def test_property_nifti_loader_returns_valid_volume_or_input_error(case):
    with tempfile.TemporaryDirectory() as d:
        img = nib.Nifti1Image(case["data"], np.eye(4), dtype=case["data"].dtype)
        hdr = img.header
        with np.errstate(all="ignore"):
            hdr["pixdim"][1:4] = case["pixdim"]
            hdr["qform_code"] = case["qcode"]
            hdr["sform_code"] = case["scode"]
            if case["srow"] is not None:
                srow = np.asarray(case["srow"], dtype=np.float32).reshape(3, 4)
                hdr["srow_x"], hdr["srow_y"], hdr["srow_z"] = srow
            if case["slope"] is not None:
                hdr["scl_slope"] = case["slope"]
                hdr["scl_inter"] = 0.0
        raw = os.path.join(d, "raw.nii")
        try:
            img.to_filename(raw)
        except Exception:  # nibabel refuses to write some combinations: nothing to load
            return
        blob = bytearray(open(raw, "rb").read())
        if case["flip"] is not None:
            blob[case["flip"]] ^= 0xA5
        if case["cut"]:
            blob = blob[: max(0, len(blob) - case["cut"])]
        path = os.path.join(d, "case.nii.gz" if case["gz"] else "case.nii")
        if case["gz"]:
            with gzip.open(path, "wb") as fh:
                fh.write(bytes(blob))
        else:
            with open(path, "wb") as fh:
                fh.write(bytes(blob))
        _load_or_refuse(path, event, nan=case["nan"], volume_index=case["volume_index"])


@st.composite
def itk_case(draw):
    n = draw(st.sampled_from([3, 3, 3, 3, 2, 4]))
    dims = draw(st.lists(st.sampled_from([2, 3, 4, 5, 2, 3, 4, 1]), min_size=n, max_size=n))
    spacing = draw(st.lists(st.one_of(st.floats(0.1, 5.0), st.floats(0.1, 5.0), _WILD),
                            min_size=n, max_size=n))
    kind = draw(st.sampled_from(["identity", "identity", "rotation", "singular", "nan"]))
    matrix = None
    if kind == "rotation":
        rng = np.random.default_rng(draw(st.integers(0, 999)))
        matrix = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    elif kind == "singular":
        matrix = [[1, 0, 0], [1, 0, 0], [0, 0, 1]]
    elif kind == "nan":
        matrix = [[1, 0, 0], [0, np.nan, 0], [0, 0, 1]]
    return dict(dims=dims, spacing=spacing, matrix=matrix if n == 3 else None,
                etype=draw(st.sampled_from(["MET_FLOAT", "MET_UCHAR", "MET_SHORT", "MET_DOUBLE"])),
                cut=draw(st.sampled_from([0, 0, 0, 0, 1, 50])),
                nan_value=draw(st.sampled_from([None, None, np.nan, np.inf])))


@settings(max_examples=60, deadline=None, derandomize=True, database=None)
@given(case=itk_case())
def test_property_itk_loader_returns_valid_volume_or_input_error(case):
    with tempfile.TemporaryDirectory() as d:
        dims, etype = case["dims"], case["etype"]
        data = np.random.default_rng(len(dims)).standard_normal(int(np.prod(dims))) * 10
        if case["nan_value"] is not None and etype in ("MET_FLOAT", "MET_DOUBLE"):
            data[0] = case["nan_value"]
        data = np.clip(data, -100, 100) if etype != "MET_UCHAR" else np.abs(data) % 255
        path = _write_mha(os.path.join(d, "case.mha"), dims, case["spacing"], etype, case["matrix"],
                          data=data, cut=case["cut"])
        _load_or_refuse(path, event)
