"""Synthetic phantoms: determinism, exact truth geometry, noise/bias levels, Table 7.2, CLI."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
from scipy import ndimage

from segsnake import phantoms as P
from segsnake.cli import main
from segsnake.errors import ConfigError

SMALL = {
    "ball": dict(shape=(40, 40, 40)),
    "ellipsoid": dict(shape=(40, 40, 40)),
    "blob": dict(shape=(40, 40, 40)),
    "hollow-cylinder": dict(shape=(48, 48, 48), std=30.0),
    "tube": dict(shape=(48, 40, 48), spacing=(2.0, 2.0, 2.0)),
    "s-vessel": dict(spacing=(2.0, 2.0, 2.0)),
    "exiting-tube": dict(spacing=(2.0, 2.0, 2.0)),
    "brain": dict(shape=(60, 72, 60), spacing=(3.0, 3.0, 3.0)),
}


# ------------------------------------------------------------------------------------------
# Registry, determinism, options
# ------------------------------------------------------------------------------------------


def test_registry_has_every_kind():
    assert set(P.PHANTOMS) == {"ball", "ellipsoid", "blob", "hollow-cylinder", "tube", "s-vessel",
                               "exiting-tube", "brain"}


@pytest.mark.parametrize("kind", sorted(SMALL))
def test_same_seed_same_bytes_other_seed_other_bytes(kind):
    a = P.make_phantom(kind, seed=7, **SMALL[kind])
    b = P.make_phantom(kind, seed=7, **SMALL[kind])
    c = P.make_phantom(kind, seed=8, **SMALL[kind])
    assert a.image.dtype == np.float32 and a.truth.dtype == np.uint8
    assert a.image.tobytes() == b.image.tobytes()
    assert a.truth.tobytes() == b.truth.tobytes()
    assert json.dumps(a.params, allow_nan=False) == json.dumps(b.params, allow_nan=False)
    assert a.image.tobytes() != c.image.tobytes()
    assert set(np.unique(a.truth)) == {0, 1}
    # The record is JSON-able and the init is in the segment command's terms (mm).
    json.dumps(a.init, allow_nan=False)
    assert a.init["shape"] in ("sphere", "cylinder")


def test_make_phantom_errors():
    with pytest.raises(ConfigError, match="kinds: ball, ellipsoid, blob, hollow-cylinder"):
        P.make_phantom("donut")
    with pytest.raises(ConfigError, match="does not take option.*contrast"):
        P.make_phantom("ball", contrast="t1")
    with pytest.raises(ConfigError, match="noise"):
        P.make_phantom("ball", noise=-0.1)
    with pytest.raises(ConfigError, match="spacing"):
        P.make_phantom("ball", spacing=(1, 0, 1))
    with pytest.raises(ConfigError, match="seed"):
        P.make_phantom("ball", seed=-1)
    with pytest.raises(ConfigError, match="contrast"):
        P.make_phantom("brain", contrast="t2", shape=(32, 32, 32))
    # "hollow_cylinder" is accepted as an alias of the CLI name.
    assert P.make_phantom("hollow_cylinder", shape=(32, 32, 32)).params["kind"] == "hollow-cylinder"


def test_affine_encodes_spacing_and_grid_rotation():
    ph = P.ball(0, shape=(20, 24, 16), spacing=(0.8, 1.0, 2.5), grid_rotation=(10, 20, 30))
    lin = ph.affine[:3, :3]
    np.testing.assert_allclose(np.linalg.norm(lin, axis=0), [0.8, 1.0, 2.5], atol=1e-12)
    assert np.linalg.det(lin) == pytest.approx(0.8 * 1.0 * 2.5)
    assert not np.allclose(lin, np.diag([0.8, 1.0, 2.5]))  # really rotated
    # The field-of-view centre maps to the world origin.
    centre = np.r_[(np.array(ph.truth.shape) - 1) / 2, 1.0]
    np.testing.assert_allclose((ph.affine @ centre)[:3], 0.0, atol=1e-12)


# ------------------------------------------------------------------------------------------
# Geometry of the truth and of the partial-volume image
# ------------------------------------------------------------------------------------------


def test_ball_truth_volume_matches_analytic_volume():
    ph = P.ball(3, radius=17.0, noise=0.0)
    vol = 4.0 / 3.0 * np.pi * 17.0**3
    assert ph.params["truth_volume_mm3"] == pytest.approx(vol, rel=0.01)
    # Partial volume: the clean image integrates to the volume far more precisely.
    occ = (ph.image - 20.0) / 80.0
    assert float(occ.sum()) == pytest.approx(vol, rel=0.002)
    # The 50 % level of the clean image is the truth surface, voxel by voxel.
    np.testing.assert_array_equal(ph.image > 60.0, ph.truth.astype(bool))


@pytest.mark.parametrize("kind", ["ellipsoid", "blob", "tube"])
def test_clean_image_half_level_is_the_truth(kind):
    ph = P.make_phantom(kind, seed=2, noise=0.0)
    np.testing.assert_array_equal(ph.image > 60.0, ph.truth.astype(bool))
    assert ph.image.min() == pytest.approx(20.0) and ph.image.max() == pytest.approx(100.0)


def test_ellipsoid_and_blob_volumes_match_analytic():
    e = P.ellipsoid(4, radii=(22.0, 15.0, 10.0), rotation=(30, 40, 50), noise=0.0)
    assert e.params["geometry"]["volume_mm3_analytic"] == pytest.approx(
        4 / 3 * np.pi * 22 * 15 * 10)
    assert e.params["truth_volume_mm3"] == pytest.approx(4 / 3 * np.pi * 22 * 15 * 10, rel=0.01)
    b = P.blob(5, amplitude=0.3, noise=0.0)
    g = b.params["geometry"]
    assert b.params["truth_volume_mm3"] == pytest.approx(g["volume_mm3_analytic"], rel=0.01)
    # Star-shaped around its centre and one piece.
    assert ndimage.label(b.truth)[1] == 1


def test_anisotropic_spacing_keeps_the_physical_object():
    kw = dict(radii=(20.0, 14.0, 9.0), rotation=(10, 60, -20), center=(31.0, 30.0, 33.0),
              noise=0.0)
    iso = P.ellipsoid(0, spacing=(1.0, 1.0, 1.0), **kw)
    aniso = P.ellipsoid(0, spacing=(1.0, 1.0, 2.0), **kw)
    assert iso.truth.shape == (64, 64, 64) and aniso.truth.shape == (64, 64, 32)
    # Voxel centres of the 2 mm grid are every other centre of the 1 mm grid: same truth there.
    np.testing.assert_array_equal(aniso.truth, iso.truth[:, :, ::2])
    assert aniso.params["truth_volume_mm3"] == pytest.approx(iso.params["truth_volume_mm3"],
                                                             rel=0.01)
    np.testing.assert_allclose(np.linalg.norm(aniso.affine[:3, :3], axis=0), [1, 1, 2])


# ------------------------------------------------------------------------------------------
# Noise and bias
# ------------------------------------------------------------------------------------------


def _background_region(ph: P.Phantom, margin: float = 6.0) -> np.ndarray:
    """Voxels farther than ``margin`` mm from the object (unaffected by partial volume)."""
    return ndimage.distance_transform_edt(~ph.truth.astype(bool), sampling=ph.spacing) > margin


@pytest.mark.parametrize("noise", [0.03, 0.1, 0.25])
def test_gaussian_noise_std_matches_fraction_of_contrast(noise):
    ph = P.ball(1, noise=noise, foreground=150.0, background=30.0)
    bg = ph.image[_background_region(ph)]
    assert bg.size > 50_000
    assert float(bg.std()) == pytest.approx(noise * 120.0, rel=0.05)
    assert float(bg.mean()) == pytest.approx(30.0, abs=noise * 120.0 * 0.05)
    assert ph.params["geometry"]["noise_std"] == pytest.approx(noise * 120.0)


def test_rician_noise_is_rayleigh_in_a_zero_background():
    ph = P.ball(1, noise=0.1, rician=True, foreground=100.0, background=0.0)
    bg = ph.image[_background_region(ph)].astype(np.float64)
    sigma = 10.0
    assert bg.min() >= 0.0
    assert bg.mean() == pytest.approx(sigma * np.sqrt(np.pi / 2), rel=0.03)
    assert bg.std() == pytest.approx(sigma * np.sqrt(2 - np.pi / 2), rel=0.05)


@pytest.mark.parametrize("amplitude", [0.2, 0.4])
def test_bias_field_amplitude_and_independence_from_noise_stream(amplitude):
    clean = P.ball(2, noise=0.0)
    biased = P.ball(2, noise=0.0, bias=amplitude)
    ratio = biased.image / clean.image
    assert float(ratio.max() - ratio.min()) == pytest.approx(amplitude, abs=1e-4)
    assert float(ratio.max() + ratio.min()) / 2 == pytest.approx(1.0, abs=1e-4)
    # Smooth: neighbouring voxels differ by a tiny fraction of the range.
    assert float(np.abs(np.diff(ratio, axis=0)).max()) < amplitude * 0.1
    # Noise draws do not depend on the bias option (separate random streams).
    n0 = P.ball(2, noise=0.1).image - clean.image
    n1 = P.ball(2, noise=0.1, bias=amplitude).image - biased.image
    np.testing.assert_allclose(n0, n1, atol=1e-3)


def test_blur_is_gaussian_in_mm():
    sharp = P.ball(0, noise=0.0, spacing=(1.0, 1.0, 2.0))
    blurred = P.ball(0, noise=0.0, spacing=(1.0, 1.0, 2.0), blur=2.0)
    expect = ndimage.gaussian_filter(sharp.image, (2.0, 2.0, 1.0), mode="nearest")
    np.testing.assert_allclose(blurred.image, expect, atol=1e-4)
    assert float(np.abs(blurred.image - sharp.image).max()) > 10.0


# ------------------------------------------------------------------------------------------
# Hollow cylinder (003 section 7.3.4, Table 7.2)
# ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cylinder_clean():
    return P.hollow_cylinder(0)


def test_cylinder_wall_fraction_and_truth(cylinder_clean):
    ph = cylinder_clean
    g = ph.params["geometry"]
    assert g["snr_db"] is None  # infinite SNR, written as null
    json.dumps(ph.params, allow_nan=False)
    assert ph.truth.shape == (128, 128, 128)
    assert set(np.unique(ph.image)) == {0.0, 255.0}
    assert float((ph.image == 255).mean()) == pytest.approx(0.015, abs=0.001)
    assert g["wall_fraction"] == pytest.approx(float((ph.image == 255).mean()))
    R, L = g["mid_radius_mm"], g["length_mm"]
    assert float(ph.truth.sum()) == pytest.approx(np.pi * R**2 * L, rel=0.01)
    # The truth boundary runs through the middle of the wall: the wall is half inside.
    wall = ph.image == 255
    assert float((wall & ph.truth.astype(bool)).sum() / wall.sum()) == pytest.approx(0.5, abs=0.05)


@pytest.mark.parametrize("std", sorted(P.TABLE_7_2))
def test_cylinder_snr_matches_table_7_2(cylinder_clean, std):
    noisy = P.hollow_cylinder(0, std=float(std))
    noise = noisy.image.astype(np.float64) - cylinder_clean.image
    assert noise.std() == pytest.approx(std, rel=0.01)
    snr = 10 * np.log10(cylinder_clean.image.var(dtype=np.float64) / std**2)
    assert abs(snr - P.TABLE_7_2[std]) < 0.5
    assert noisy.params["geometry"]["snr_db"] == pytest.approx(snr)
    assert noisy.image.min() < 0  # not clipped by default (see the docstring)
    assert P.hollow_cylinder(0, std=float(std), clip=True).image.min() == 0.0


def test_cylinder_init_jaccard_is_about_0_12(cylinder_clean):
    ph = cylinder_clean
    init = P.rasterize_init(ph.params["init_mm"], ph.truth.shape, ph.spacing)
    t = ph.truth.astype(bool)
    jac = (init & t).sum() / (init | t).sum()
    assert jac == pytest.approx(0.12, abs=0.03)
    assert (init & ~t).sum() == 0  # entirely inside the interior
    assert ph.init["shape"] == "cylinder"
    assert ph.params["init_mm"]["radius"] == pytest.approx(ph.params["geometry"]["mid_radius_mm"] / 2,
                                                           abs=1e-3)


# ------------------------------------------------------------------------------------------
# Tube and brain
# ------------------------------------------------------------------------------------------


def test_tube_is_one_vessel_with_varying_radius_and_init_inside():
    ph = P.tube(1, noise=0.0)
    t = ph.truth.astype(bool)
    assert ndimage.label(t)[1] == 1
    lo, hi = ph.params["geometry"]["radius_range_mm"]
    assert hi / lo > 1.3
    # Both straight parts leave through the k = 0 face.
    assert ndimage.label(t[:, :, 0])[1] == 2
    init = P.rasterize_init(ph.params["init_mm"], t.shape, ph.spacing)
    assert init.sum() > 500 and (init & ~t).sum() == 0


def _on_centerline(ph: P.Phantom, points_voxels) -> tuple[np.ndarray, np.ndarray]:
    """(distance to the true centreline in mm, true radius there) of points in voxel indices."""
    sw = P.tube_truth(ph.params)
    s, d = sw.nearest(np.asarray(points_voxels) * np.asarray(ph.spacing))
    return d, sw.radius_at(s)


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (0.6, 0.6, 2.5)])
def test_s_vessel_truth_volume_centreline_and_clicks(spacing):
    ph = P.s_vessel(3, radius=4.0, spacing=spacing, noise=0.0)
    g = ph.params["geometry"]
    cl = g["centerline"]
    L = 2 * 15.0 + 2 * 20.0 * np.pi / 2  # two straights, two quarter turns of radius 20
    assert cl["closed"] and cl["length_mm"] == pytest.approx(L, rel=1e-3)
    assert cl["volume_mm3_analytic"] == pytest.approx(np.pi * 16.0 * L, rel=1e-4)
    # Voxel-centre sampling of the truth: within 1 % of pi r^2 L (1 mm) and 2 % (2.5 mm slices).
    tol = 0.01 if spacing[2] == 1.0 else 0.02
    assert ph.params["truth_volume_mm3"] == pytest.approx(np.pi * 16.0 * L, rel=tol)
    t = ph.truth.astype(bool)
    assert ndimage.label(t)[1] == 1 and not t[0].any() and not t[-1].any()
    # The recorded centreline lies inside the truth mask (the voxel nearest each point, away from
    # the flat ends, where rounding may step beyond the cap), its radius is the option's.
    idx = np.rint(np.asarray(cl["points_voxels"])).astype(int)
    away = (np.asarray(cl["arc_length_mm"]) > 3.0) & (np.asarray(cl["arc_length_mm"]) < L - 3.0)
    assert away.sum() > 80 and t[tuple(idx[away].T)].all()
    np.testing.assert_allclose(cl["radius_mm"], 4.0)
    np.testing.assert_allclose(np.diff(cl["arc_length_mm"]),
                               np.linalg.norm(np.diff(cl["points_mm"], axis=0), axis=1), rtol=1e-3)
    # World mm = the affine applied to the voxel indices.
    vox = np.c_[np.asarray(cl["points_voxels"]), np.ones(len(idx))]
    np.testing.assert_allclose((ph.affine @ vox.T).T[:, :3], cl["points_world_mm"], atol=1e-6)
    # Five clicks, each within half a radius of the true centreline (the shift is <= 0.2 r).
    click = g["click"]
    assert len(click["points_voxels"]) == 5
    d, r = _on_centerline(ph, click["points_voxels"])
    assert np.all(d <= 0.5 * r) and np.all(d <= P.CLICK_SHIFT * r + 1e-9) and d.max() > 0.01
    # The shift is drawn in a ball: its part along the centreline does not move a point off it.
    assert np.all(d <= np.asarray(click["shift_mm"]) + 1e-6)
    np.testing.assert_allclose(np.asarray(click["radius_mm"]), 2.0)
    # The end-point click: the centreline at 15 % and 85 % of its length, half the radius.
    ends = ph.init
    assert ends == g["ends_init"] and ends["shape"] == "cylinder"
    d, _ = _on_centerline(ph, [ends["axis_start"], ends["axis_end"]])
    assert d.max() < 0.01
    a = np.asarray(ends["axis_start"]) * spacing
    b = np.asarray(ends["axis_end"]) * spacing
    sw = P.tube_truth(ph.params)
    s_ab = sw.nearest(np.stack([a, b]))[0] - cl["arc_offset_mm"]
    np.testing.assert_allclose(s_ab, [0.15 * L, 0.85 * L], atol=0.05)
    assert g["ends_init_mm"]["radius"] == pytest.approx(2.0)


def test_tube_phantoms_are_deterministic_with_their_clicks():
    a, b, c = (P.s_vessel(s, spacing=(2.0, 2.0, 2.0)) for s in (5, 5, 6))
    assert a.params["geometry"]["click"] == b.params["geometry"]["click"]
    assert a.params["geometry"]["click"] != c.params["geometry"]["click"]
    # The seed turns the S (rotation drawn in [-25, 25] degrees per axis).
    assert a.params["options"]["rotation"] != c.params["options"]["rotation"]
    assert max(abs(x) for x in a.params["options"]["rotation"]) <= 25.0


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (0.6, 0.6, 2.5)])
def test_exiting_tube_touches_exactly_two_faces(spacing):
    ph = P.exiting_tube(2, spacing=spacing, noise=0.0)
    t = ph.truth.astype(bool)
    touched = {f"{'ijk'[ax]}{'-+'[end]}" for ax in range(3) for end in (0, 1)
               if np.take(t, (0, -1)[end], axis=ax).any()}
    assert touched == {"i-", "k+"} == set(ph.params["geometry"]["faces"])
    cl = ph.params["geometry"]["centerline"]
    assert not cl["closed"] and "volume_mm3_analytic" not in cl
    # The in-volume centreline ends on those faces (the box is half a voxel beyond the centres).
    p0, p1 = np.asarray(cl["points_voxels"])[[0, -1]]
    assert p0[0] == pytest.approx(-0.5, abs=0.05) and p1[2] == pytest.approx(t.shape[2] - 0.5,
                                                                              abs=0.05)
    # Straight: the truth's volume is pi r^2 times the length inside, up to the oblique ends.
    r = ph.params["options"]["radius"]
    assert ph.params["truth_volume_mm3"] == pytest.approx(np.pi * r * r * cl["length_mm"], rel=0.03)
    with pytest.raises(ConfigError, match="too large"):
        P.exiting_tube(0, radius=20.0, spacing=(2.0, 2.0, 2.0))


def test_arch_is_smooth_and_turns_through_180_degrees():
    ph = P.tube(0, noise=0.0)
    cl = ph.params["geometry"]["centerline"]
    pts = np.asarray(cl["points_mm"])
    # No jump along the centreline (the arch used to start 2 x drift away from its legs).
    steps = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    assert steps.max() < 1.05
    t0, t1 = pts[3] - pts[0], pts[-1] - pts[-4]
    assert np.dot(t0, t1) / np.linalg.norm(t0) / np.linalg.norm(t1) < -0.999
    # Both legs leave through the k = 0 face: the in-volume centreline starts and ends there.
    assert np.asarray(cl["points_voxels"])[[0, -1], 2] == pytest.approx([-0.5, -0.5], abs=0.05)
    # A 5-point click and an end-point click on the true centreline.
    d, r = _on_centerline(ph, ph.params["geometry"]["click"]["points_voxels"])
    assert np.all(d <= 0.5 * r)


def test_truth_profile_matches_the_closed_forms():
    # The Table 7.2 cylinder is straight: sections pi R^2, diameters 2 R.
    cyl = P.hollow_cylinder(0, shape=(48, 48, 48))
    R = cyl.params["geometry"]["mid_radius_mm"]
    prof = P.truth_profile(cyl.params, [1.0, 10.0, 30.0])
    np.testing.assert_allclose(prof["area"], np.pi * R * R, rtol=1e-4)
    for key in ("equivalent_diameter", "min_diameter", "max_diameter"):
        np.testing.assert_allclose(prof[key], 2 * R, rtol=1e-4)
    # A tapered S vessel: the measured section follows pi r(s)^2 through both bends.
    ph = P.s_vessel(1, radius=4.0, taper=1.5, spacing=(2.0, 2.0, 2.0), noise=0.0)
    cl = ph.params["geometry"]["centerline"]
    prof = P.truth_profile(ph.params, step=10.0)
    assert len(prof["arc_length"]) == int(np.ceil((cl["length_mm"] - 5.0) / 10.0))
    r = 4.0 + 2.0 * prof["arc_length"] / cl["length_mm"]
    np.testing.assert_allclose(prof["area"], np.pi * r * r, rtol=1e-3)
    np.testing.assert_allclose(prof["max_diameter"], 2 * r, rtol=1e-3)
    np.testing.assert_allclose(
        prof["center_world"],
        np.interp(prof["arc_length"], cl["arc_length_mm"], np.asarray(cl["points_world_mm"])[:, 0]
                  )[:, None] * [1, 0, 0] + prof["center_world"] * [0, 1, 1], atol=0.02)


@pytest.fixture(scope="module")
def brains():
    kw = dict(spacing=(2.0, 2.0, 2.0), noise=0.0)
    return {c: P.brain(0, contrast=c, **kw) for c in ("t1", "pd")}


def test_brain_classes_present_and_truth_is_the_brain(brains):
    ph = brains["t1"]
    lab = ph.labels
    assert ph.truth.shape == (90, 108, 90)
    counts = np.bincount(lab.ravel(), minlength=6)
    assert np.all(counts > 1000), counts
    t = ph.truth.astype(bool)
    # Truth = WM + GM (+ the ventricles they enclose); no outer CSF, skull or scalp.
    assert np.all(t[lab >= 4])
    assert not np.any(t & (lab <= 2))
    # The only CSF inside the brain is the two lateral ventricles (ellipsoids 4.5 x 26 x 7 mm).
    ventricles_mm3 = 2 * 4 / 3 * np.pi * 4.5 * 26 * 7 * ph.params["geometry"]["scale"] ** 3
    assert (lab[t] == 3).sum() * 8.0 == pytest.approx(ventricles_mm3, rel=0.05)
    assert 0.5 < (lab[t] == 5).sum() / t.sum() < 0.95  # mostly white matter
    # Folded surface: the smooth hull differs from the truth, but not by much.
    assert 0.95 < ph.params["geometry"]["hull_dice"] < 0.995
    # Default grid is BrainWeb's.
    assert P._grid(None, (1, 1, 1), P._BRAINWEB_FOV)[0] == (181, 217, 181)
    init = P.rasterize_init(ph.params["init_mm"], t.shape, ph.spacing)
    assert init.sum() > 0 and (init & ~t).sum() == 0


def test_brain_contrasts_order_the_tissues(brains):
    med = {}
    for c, ph in brains.items():
        # Class medians at voxel centres away from boundaries (erode each class once).
        med[c] = {}
        for k, name in enumerate(ph.params["labels"]):
            core = ndimage.binary_erosion(ph.labels == k)
            med[c][name] = float(np.median(ph.image[core]))
    t1, pd = med["t1"], med["pd"]
    assert t1["scalp"] > t1["wm"] > t1["gm"] > t1["csf"] > t1["background"]
    assert t1["skull"] < t1["gm"]
    assert pd["csf"] > pd["gm"] > pd["wm"] > pd["skull"]
    for c in ("t1", "pd"):
        for name, v in med[c].items():
            assert v == pytest.approx(P.BRAIN_INTENSITIES[c][name], abs=1.0), (c, name)


def test_brain_noise_is_a_fraction_of_the_brightest_tissue_and_bias_spans_the_head(brains):
    ph = P.brain(0, spacing=(2.0, 2.0, 2.0), noise=0.05, contrast="t1")
    bg = ph.labels == 0
    bg &= ndimage.binary_erosion(bg, iterations=3)
    assert float(ph.image[bg].std()) == pytest.approx(5.0, rel=0.05)
    biased = P.brain(0, spacing=(2.0, 2.0, 2.0), noise=0.0, bias=0.4, contrast="t1")
    clean = brains["t1"].image
    head = clean > 1.0
    ratio = biased.image[head] / clean[head]
    assert 0.37 < float(ratio.max() - ratio.min()) <= 0.4 + 1e-4


# ------------------------------------------------------------------------------------------
# Command line
# ------------------------------------------------------------------------------------------


def test_cli_phantom_writes_image_truth_and_json(tmp_path):
    out = tmp_path / "ph"
    argv = ["phantom", "ball", "--out", str(out), "--seed", "4", "--shape", "24", "28", "20",
            "--spacing", "1.5", "1", "2", "--noise", "0.1", "--bias", "0.2"]
    assert main(argv) == 0
    ref = P.ball(4, shape=(24, 28, 20), spacing=(1.5, 1.0, 2.0), noise=0.1, bias=0.2)
    img = nib.load(out / "image.nii.gz")
    tru = nib.load(out / "truth.nii.gz")
    for im in (img, tru):
        assert im.shape == (24, 28, 20)
        np.testing.assert_allclose(im.affine, ref.affine, atol=1e-6)
        np.testing.assert_allclose(im.header.get_zooms()[:3], (1.5, 1.0, 2.0))
    np.testing.assert_array_equal(np.asanyarray(img.dataobj), ref.image)
    np.testing.assert_array_equal(np.asanyarray(tru.dataobj), ref.truth)
    for im in (img, tru):
        assert int(im.header["qform_code"]) > 0 and int(im.header["sform_code"]) > 0
    rec = json.loads((out / "phantom.json").read_text())
    assert rec["kind"] == "ball" and rec["seed"] == 4 and rec["spacing"] == [1.5, 1.0, 2.0]
    assert rec["init"] == ref.init and rec["params"]["options"]["noise"] == 0.1
    np.testing.assert_allclose(rec["affine"], ref.affine)


def test_cli_phantom_oblique_grid_keeps_spacing(tmp_path):
    out = tmp_path / "obl"
    assert main(["phantom", "tube", "--out", str(out), "--spacing", "2", "2", "3",
                 "--grid-rotation", "0", "30", "15"]) == 0
    from segsnake.io import load_volume

    vol = load_volume(out / "image.nii.gz")
    assert vol.spacing == pytest.approx((2.0, 2.0, 3.0))
    assert not np.allclose(vol.affine[:3, :3], np.diag([2.0, 2.0, 3.0]))
    np.testing.assert_allclose(vol.affine, P.tube(0, spacing=(2, 2, 3),
                                                  grid_rotation=(0, 30, 15)).affine, atol=1e-5)


def test_cli_phantom_refuses_to_overwrite_and_bad_options(tmp_path, capsys):
    out = tmp_path / "ph"
    assert main(["phantom", "hollow-cylinder", "--out", str(out), "--shape", "32", "32", "32",
                 "--std", "10"]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    capsys.readouterr()
    assert main(["phantom", "hollow-cylinder", "--out", str(out), "--shape", "32", "32", "32",
                 "--std", "50"]) == 5
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "exists" in err and "--overwrite" in err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert main(["phantom", "hollow-cylinder", "--out", str(out), "--shape", "32", "32", "32",
                 "--std", "50", "--overwrite"]) == 0
    assert (out / "image.nii.gz").read_bytes() != before["image.nii.gz"]
    assert main(["phantom", "pyramid", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "kinds: ball, ellipsoid, blob, hollow-cylinder, tube, s-vessel, exiting-tube, brain" in err
    assert main(["phantom", "ball", "--out", str(tmp_path / "y"), "--contrast", "pd"]) == 2
    assert "--contrast does not apply" in capsys.readouterr().err
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_cli_phantom_subprocess(tmp_path):
    exe = Path(sys.executable).with_name("segsnake")
    cmd = [str(exe), "phantom", "brain", "--out", str(tmp_path / "b"), "--shape", "40", "48", "40",
           "--spacing", "4.5", "4.5", "4.5", "--contrast", "pd", "--noise", "0.05"]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    rec = json.loads((tmp_path / "b" / "phantom.json").read_text())
    assert rec["params"]["options"]["contrast"] == "pd"
    assert nib.load(tmp_path / "b" / "truth.nii.gz").shape == (40, 48, 40)


# ------------------------------------------------------------------------------------------
# data_synthetic/ recipes
# ------------------------------------------------------------------------------------------

ROOT = Path(__file__).resolve().parents[1]


def _make_sets():
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_sets", ROOT / "data_synthetic" / "make_sets.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_recipes_expand_to_the_standard_sets():
    ms = _make_sets()
    sets = ms.load_sets()
    brain = list(ms.expand(sets["brain-sweep"]))
    assert len(brain) == 30 and len({n for n, _, _ in brain}) == 30
    combos = {(o["contrast"], o["noise"], o["bias"]) for _, _, o in brain}
    assert combos == {(c, n, b) for c in ("t1", "pd") for n in (0.01, 0.03, 0.05, 0.07, 0.09)
                      for b in (0.0, 0.2, 0.4)}
    assert ("t1_n3_rf20", 0, {"contrast": "t1", "noise": 0.03, "bias": 0.2}) in brain
    cyl = list(ms.expand(sets["cylinder-table-7-2"]))
    assert [o["std"] for _, _, o in cyl] == [0, 10, 30, 50, 70, 90]
    blobs = list(ms.expand(sets["organ-blobs"]))
    assert len(blobs) == 20 and {s for _, s, _ in blobs} == set(range(10))


def test_make_sets_writes_volumes_and_a_batch_file(tmp_path, capsys):
    ms = _make_sets()
    assert ms.main(["--out", str(tmp_path), "--set", "arch-tubes", "--limit", "2"]) == 0
    d = tmp_path / "arch-tubes"
    assert sorted(p.name for p in d.iterdir()) == ["cases.yaml", "tube0", "tube1"]
    for name in ("image.nii.gz", "truth.nii.gz", "phantom.json"):
        assert (d / "tube1" / name).is_file()
    import yaml

    doc = yaml.safe_load((d / "cases.yaml").read_text())
    case = doc["cases"][1]
    assert case["name"] == "tube1" and case["image"] == "tube1/image.nii.gz"
    assert case["shape"] == "cylinder" and case == {**case, **P.tube(1, noise=0.1, blur=0.8).init}
    assert ms.main(["--out", str(tmp_path), "--set", "nope"]) == 2
    assert "unknown set(s) nope" in capsys.readouterr().err


@pytest.mark.slow
def test_full_size_brain_has_the_brainweb_grid():
    ph = P.brain(0, noise=0.09, bias=0.4, contrast="pd")
    assert ph.truth.shape == ph.image.shape == (181, 217, 181)
    assert tuple(ph.spacing) == (1.0, 1.0, 1.0)
