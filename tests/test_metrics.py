"""Metrics against SimpleITK and against analytic cases; ``segsnake evaluate`` end to end."""

from __future__ import annotations

import json
import math

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk
from scipy import ndimage
from scipy.spatial import cKDTree

from segsnake import metrics as M
from segsnake import phantoms as P
from segsnake.cli import main
from segsnake.errors import InputError


def _random_shape(seed: int, shape=(40, 36, 28), sigma=3.0, level=0.35) -> np.ndarray:
    """Smoothed-noise blobs: several components, holes and concavities."""
    rng = np.random.default_rng(seed)
    f = ndimage.gaussian_filter(rng.standard_normal(shape), sigma)
    return f > level * f.std()


def _sitk(mask: np.ndarray, spacing) -> sitk.Image:
    # GetImageFromArray reads the array as [z, y, x]: our first axis is SimpleITK's last.
    img = sitk.GetImageFromArray(mask.astype(np.uint8))
    img.SetSpacing(tuple(float(s) for s in spacing[::-1]))
    return img


PAIRS = [
    ("smoothed noise", (0.7, 1.0, 2.5), lambda: (_random_shape(1), _random_shape(2))),
    ("noise vs dilated", (1.0, 1.3, 0.6),
     lambda: (_random_shape(3), ndimage.binary_dilation(_random_shape(3), iterations=2))),
    ("two blobs", (1.0, 1.0, 2.0),
     lambda: (P.blob(1, spacing=(1, 1, 2), noise=0.0).truth,
              P.blob(2, spacing=(1, 1, 2), noise=0.0).truth)),
    # They disagree on a thin shell only: `hausdorff` queries k-d trees (the pairs above take
    # its distance-transform path).
    ("ball vs shifted", (1.0, 0.8, 1.2), lambda: (_ball(40), np.roll(_ball(40), 2, axis=0))),
]


def _ball(r: int) -> np.ndarray:
    g = np.indices((2 * r + 5,) * 3) - (r + 2)
    return np.einsum("i...,i...->...", g, g) <= r * r


@pytest.mark.parametrize("name,spacing,make", PAIRS, ids=[p[0] for p in PAIRS])
def test_overlap_and_hausdorff_agree_with_simpleitk(name, spacing, make):
    a, b = make()
    a, b = a.astype(bool), b.astype(bool)
    assert a.any() and b.any() and not np.array_equal(a, b)
    ia, ib = _sitk(a, spacing), _sitk(b, spacing)
    overlap = sitk.LabelOverlapMeasuresImageFilter()
    overlap.Execute(ib, ia)
    assert M.dice(a, b) == pytest.approx(overlap.GetDiceCoefficient(), abs=1e-12)
    assert M.jaccard(a, b) == pytest.approx(overlap.GetJaccardCoefficient(), abs=1e-12)
    hd = sitk.HausdorffDistanceImageFilter()
    hd.Execute(ia, ib)
    assert M.hausdorff(a, b, spacing) == pytest.approx(hd.GetHausdorffDistance(), abs=1e-6)
    assert M.hausdorff(a, b, spacing) > 2 * min(spacing)  # a non-trivial case
    res = M.evaluate_masks(a, b, spacing)
    assert res["hausdorff_mm"] == M.hausdorff(a, b, spacing)
    assert res["hausdorff95_mm"] <= res["hausdorff_mm"] + 1e-9
    assert 0 < res["assd_mm"] < res["hausdorff95_mm"]


def test_surface_distances_agree_with_a_kdtree():
    """ASSD and HD95 from the EDT equal a brute-force nearest-neighbour computation."""
    spacing = (0.9, 1.2, 2.0)
    a, b = _random_shape(4), _random_shape(5)

    def surface_points(m):
        s = m & ~ndimage.binary_erosion(m, border_value=0)
        return np.argwhere(s) * np.asarray(spacing)

    pa, pb = surface_points(a), surface_points(b)
    d = np.concatenate([cKDTree(pb).query(pa)[0], cKDTree(pa).query(pb)[0]])
    assert M.assd(a, b, spacing) == pytest.approx(d.mean(), rel=1e-9)
    assert M.hausdorff95(a, b, spacing) == pytest.approx(np.percentile(d, 95), rel=1e-9)
    da, db = M.surface_distances(a, b, spacing)
    assert da.size == len(pa) and db.size == len(pb)


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (0.8, 0.8, 2.0), (1.0, 1.5, 2.5)])
@pytest.mark.parametrize("r,d", [(15.0, 3.0), (12.0, 2.0), (14.0, 5.0)])
def test_concentric_balls_give_assd_and_hd95_close_to_the_gap(spacing, r, d):
    n = [int(70 / s) for s in spacing]
    x, y, z = np.meshgrid(*[np.arange(k) * s - 35 for k, s in zip(n, spacing)],
                          indexing="ij", sparse=True)
    rho = np.sqrt(x**2 + y**2 + z**2)
    inner, outer = rho < r, rho < r + d
    h = max(spacing)
    assert M.assd(inner, outer, spacing) == pytest.approx(d, abs=0.25 * h)
    assert M.hausdorff95(inner, outer, spacing) == pytest.approx(d, abs=0.55 * h)
    assert M.hausdorff(inner, outer, spacing) == pytest.approx(d, abs=1.0 * h)
    # Symmetric, and the ratio of the overlaps is the ratio of the volumes.
    assert M.assd(outer, inner, spacing) == pytest.approx(M.assd(inner, outer, spacing), rel=1e-12)
    assert M.dice(inner, outer) == pytest.approx(
        2 * r**3 / (r**3 + (r + d) ** 3), rel=0.02)


def test_volume_difference_and_identity():
    a = np.zeros((10, 10, 10), bool)
    a[2:6, 2:6, 2:6] = True  # 64 voxels
    b = np.zeros_like(a)
    b[2:6, 2:6, 2:8] = True  # 96 voxels
    diff, rel = M.volume_difference(a, b, (0.5, 1.0, 2.0))
    assert diff == pytest.approx(-32.0) and rel == pytest.approx(-1 / 3)
    assert M.dice(a, b) == pytest.approx(2 * 64 / 160)
    assert M.jaccard(a, b) == pytest.approx(64 / 96)
    res = M.evaluate_masks(b, b, (0.5, 1.0, 2.0))
    assert res["dice"] == res["jaccard"] == 1.0
    assert res["hausdorff95_mm"] == res["assd_mm"] == res["hausdorff_mm"] == 0.0
    assert res["volume_pred_mm3"] == res["volume_truth_mm3"] == 96.0
    assert tuple(res) == M.METRIC_KEYS
    # A shift of two slices along the 2 mm axis: maximal Hausdorff distance 4 mm.
    c = np.roll(a, 2, axis=2)
    assert M.hausdorff(a, c, (0.5, 1.0, 2.0)) == pytest.approx(4.0)


def test_empty_masks_conventions():
    e = np.zeros((8, 8, 8), bool)
    f = e.copy()
    f[3:5, 3:5, 3:5] = True
    both = M.evaluate_masks(e, e)
    assert both["dice"] == both["jaccard"] == 1.0
    assert both["hausdorff95_mm"] == both["assd_mm"] == both["hausdorff_mm"] == 0.0
    assert both["volume_difference_rel"] == 0.0
    for pred, truth in ((e, f), (f, e)):
        one = M.evaluate_masks(pred, truth)
        assert one["dice"] == one["jaccard"] == 0.0
        assert math.isinf(one["hausdorff95_mm"]) and math.isinf(one["assd_mm"])
        assert math.isinf(one["hausdorff_mm"])
    assert math.isinf(M.evaluate_masks(f, e)["volume_difference_rel"])
    assert M.evaluate_masks(e, f)["volume_difference_rel"] == -1.0
    with pytest.raises(ValueError, match="non-empty"):
        M.surface_distances(e, f)
    with pytest.raises(ValueError, match="shapes"):
        M.dice(e, np.zeros((8, 8, 9), bool))


# ------------------------------------------------------------------------------------------
# Files and the command line
# ------------------------------------------------------------------------------------------


def _save(path, mask, affine):
    nib.save(nib.Nifti1Image(mask.astype(np.uint8), affine), str(path))
    return path


@pytest.fixture()
def mask_files(tmp_path):
    aff = np.diag([0.8, 1.0, 2.0, 1.0])
    aff[:3, 3] = [-10.0, 5.0, 3.0]
    truth = P.ball(0, shape=(40, 40, 20), spacing=(0.8, 1.0, 2.0), radius=10.0, noise=0.0).truth
    pred = np.roll(truth, 2, axis=0)
    return (_save(tmp_path / "pred.nii.gz", pred, aff),
            _save(tmp_path / "truth.nii.gz", truth, aff), pred, truth, aff)


def test_load_mask_pair_reads_spacing_and_refuses_other_grids(tmp_path, mask_files):
    p, t, pred, truth, aff = mask_files
    a, b, sp = M.load_mask_pair(p, t)
    assert sp == pytest.approx((0.8, 1.0, 2.0))
    np.testing.assert_array_equal(a, pred.astype(bool))
    np.testing.assert_array_equal(b, truth.astype(bool))
    other_shape = _save(tmp_path / "small.nii.gz", truth[:-1], aff)
    with pytest.raises(InputError, match="pred.nii.gz and .*small.nii.gz are on different grids"):
        M.load_mask_pair(p, other_shape)
    moved = aff.copy()
    moved[0, 3] += 1e-3
    other_affine = _save(tmp_path / "moved.nii.gz", truth, moved)
    with pytest.raises(InputError, match="moved.nii.gz.*affines differ"):
        M.load_mask_pair(p, other_affine)
    nearly = aff.copy()
    nearly[0, 3] += 1e-6
    M.load_mask_pair(p, _save(tmp_path / "nearly.nii.gz", truth, nearly))  # within 1e-4: fine
    with pytest.raises(InputError, match="missing.nii.gz"):
        M.load_mask_pair(p, tmp_path / "missing.nii.gz")


def test_cli_evaluate_json_and_text(mask_files, capsys):
    p, t, pred, truth, _ = mask_files
    assert main(["evaluate", str(p), str(t), "--json"]) == 0
    rec = json.loads(capsys.readouterr().out)
    ref = M.evaluate_masks(pred, truth, (0.8, 1.0, 2.0))
    for key in M.METRIC_KEYS:
        assert rec[key] == pytest.approx(ref[key])
    assert rec["hausdorff_mm"] == pytest.approx(1.6)  # a 2-voxel shift along the 0.8 mm axis
    assert 0.8 < rec["dice"] < 1.0
    assert main(["evaluate", str(p), str(t)]) == 0
    out = capsys.readouterr().out
    assert "Dice" in out and f"{ref['dice']:.4f}" in out and "mm" in out
    assert len(out.strip().splitlines()) == len(M.METRIC_KEYS)


def test_cli_evaluate_errors(tmp_path, mask_files, capsys):
    p, t, pred, truth, aff = mask_files
    other = _save(tmp_path / "other.nii.gz", truth[:, :-2], aff)
    before = (p.read_bytes(), other.read_bytes())
    assert main(["evaluate", str(p), str(other)]) == 3
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(p) in err and str(other) in err
    assert (p.read_bytes(), other.read_bytes()) == before
    empty = _save(tmp_path / "empty.nii.gz", np.zeros_like(truth), aff)
    assert main(["evaluate", str(empty), str(t), "--json"]) == 0
    rec = json.loads(capsys.readouterr().out)
    assert rec["dice"] == 0.0 and rec["hausdorff95_mm"] is None and rec["assd_mm"] is None


@pytest.mark.parametrize("corner", [False, True])
def test_distances_do_not_depend_on_the_empty_margin(corner):
    # The distance metrics work on the union's bounding box: padding both masks with background
    # (or moving them against the array border) must not change a single number.
    a, b = _random_shape(5, shape=(14, 12, 10)), _random_shape(6, shape=(14, 12, 10))
    sp = (0.9, 1.1, 2.0)
    pad = ((0, 20), (0, 17), (0, 9)) if corner else ((11, 20), (7, 17), (5, 9))
    big_a, big_b = np.pad(a, pad), np.pad(b, pad)
    got = M.evaluate_masks(big_a, big_b, sp)
    # Reference on the whole array: EDT of the complement of each surface.
    sa = big_a & ~ndimage.binary_erosion(big_a, border_value=0)
    sb = big_b & ~ndimage.binary_erosion(big_b, border_value=0)
    d = np.concatenate([ndimage.distance_transform_edt(~sb, sampling=sp)[sa],
                        ndimage.distance_transform_edt(~sa, sampling=sp)[sb]])
    assert got["assd_mm"] == pytest.approx(d.mean(), rel=1e-12)
    assert got["hausdorff95_mm"] == pytest.approx(np.percentile(d, 95), rel=1e-12)
    hd = max(ndimage.distance_transform_edt(~big_b, sampling=sp)[big_a].max(),
             ndimage.distance_transform_edt(~big_a, sampling=sp)[big_b].max())
    assert got["hausdorff_mm"] == pytest.approx(hd, rel=1e-12)
