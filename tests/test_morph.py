"""Minimum-energy paths between snakes (issue 19, item 2; seed 000 eqs. (15)-(19))."""

import csv
import json

import numpy as np
import pytest
import scipy.optimize as opt
from scipy.spatial.transform import Rotation

from segsnake.cli import main
from segsnake.morph import great_circle, l2_centre, morph, plane_path, sphere_path
from segsnake.priors import inner_product
from segsnake.surfaces import SphereModel

R1 = Rotation.from_euler("xyz", [10, 50, -20], degrees=True).as_matrix()
E1 = SphereModel.ellipsoid((1, 2, 3), (3, 4, 5), m1=6, m2=5)
E2 = SphereModel.ellipsoid((10, 0, -4), (6, 2, 3), R1, m1=6, m2=5)


def _bumpy(model, seed, amp=0.4):
    rng = np.random.default_rng(seed)
    return model.with_params(model.params + amp * rng.normal(size=model.params.shape))


@pytest.mark.parametrize("path", ["plane", "sphere"])
def test_ends_are_the_inputs_exactly(path):
    a, b = _bumpy(E1, 0), _bumpy(E2, 1)
    taus, shapes = morph(a, b, 4, path)
    assert np.array_equal(shapes[0].params, a.params) and np.array_equal(shapes[-1].params, b.params)
    assert np.allclose(taus, [0, 1 / 3, 2 / 3, 1])


def test_plane_path_between_ellipsoids_is_the_affine_interpolation():
    A1, A2 = np.diag([3.0, 4.0, 5.0]), R1 @ np.diag([6.0, 2.0, 3.0])
    b1, b2 = np.array([1.0, 2, 3]), np.array([10.0, 0, -4])
    for tau, shape in zip(np.linspace(0, 1, 6), plane_path(E1, E2, np.linspace(0, 1, 6))):
        A = (1 - tau) * A1 + tau * A2
        expected = SphereModel.unit(6, 5).transformed(A, (1 - tau) * b1 + tau * b2)
        assert np.allclose(shape.params, expected.params, atol=1e-12)
        assert shape.volume() == pytest.approx(4 / 3 * np.pi * abs(np.linalg.det(A)), rel=1e-10)


def test_eq15_minimizer_is_eq17():
    """Minimize F(tau, sigma) = tau |s1 - s|^2 + (1 - tau) |s2 - s|^2 numerically (exact Gram)."""
    s1, s2 = _bumpy(E2, 3), _bumpy(E1, 4)  # the paper's sigma1, sigma2
    tau = 0.3

    def F(x):
        p = x.reshape(-1, 3)
        d1, d2 = s1.params - p, s2.params - p
        val = tau * inner_product(E1, d1, d1) + (1 - tau) * inner_product(E1, d2, d2)
        from segsnake.priors import param_gram

        B = param_gram(E1)
        return val, (-2 * (tau * B @ d1 + (1 - tau) * B @ d2)).ravel()

    res = opt.minimize(F, np.zeros(s1.params.size), jac=True, method="L-BFGS-B",
                       options={"ftol": 1e-15, "gtol": 1e-12, "maxiter": 5000})
    # eq. (17): C = tau C1 + (1 - tau) C2, i.e. our path from A = sigma2 to B = sigma1 at tau
    ours = plane_path(s2, s1, [tau])[0]
    assert np.max(np.abs(res.x.reshape(-1, 3) - ours.params)) < 1e-4
    value, grad = F(ours.params.ravel())
    assert value <= res.fun + 1e-12 and np.max(np.abs(grad)) < 1e-12 * value
    assert np.allclose(ours.params, tau * s1.params + (1 - tau) * s2.params, atol=1e-14)


def test_eq18_is_a_unit_speed_great_circle():
    a, b = _bumpy(E1, 5), _bumpy(E2, 6)
    ca, _ = l2_centre(a)
    cb, _ = l2_centre(b)
    s1 = ca / np.sqrt(inner_product(a, ca, ca))
    s2 = cb / np.sqrt(inner_product(b, cb, cb))
    theta = np.arccos(inner_product(a, s1, s2))
    assert 0.1 < theta < np.pi - 0.1
    for tau in (-0.5, 0.0, 0.25, 0.5, 0.9, 1.0, 1.5):
        g = great_circle(a, s1, s2, tau)
        assert inner_product(a, g, g) == pytest.approx(1.0, abs=1e-12)  # on the Hilbert sphere
        assert np.arccos(np.clip(inner_product(a, g, s1), -1, 1)) == pytest.approx(abs(tau) * theta if abs(tau) * theta <= np.pi else 2 * np.pi - abs(tau) * theta, abs=1e-7)
    assert np.allclose(great_circle(a, s1, s2, 0.0), s1) and np.allclose(great_circle(a, s1, s2, 1.0), s2)


@pytest.mark.parametrize("path", ["plane", "sphere"])
def test_volumes_along_a_path_are_finite_and_smooth(path):
    a, b = _bumpy(E1, 7, 0.2), _bumpy(E2, 8, 0.2)
    _, shapes = morph(a, b, 41, path)
    vol = np.array([s.volume() for s in shapes])
    assert np.all(np.isfinite(vol)) and np.all(vol > 0)
    second = np.abs(np.diff(vol, 2))
    assert second.max() < 1e-2 * np.ptp(vol)  # no jumps: second differences O(h^2)


def test_sphere_path_keeps_centroid_and_norm_linear():
    a, b = _bumpy(E1, 9), _bumpy(E2, 10)
    (ca, ga), (cb, gb) = l2_centre(a), l2_centre(b)
    na, nb = np.sqrt(inner_product(a, ca, ca)), np.sqrt(inner_product(b, cb, cb))
    for tau, s in zip((0.25, 0.5), sphere_path(a, b, (0.25, 0.5))):
        c, g = l2_centre(s)
        assert np.allclose(g, (1 - tau) * ga + tau * gb, atol=1e-10)
        assert np.sqrt(inner_product(s, c, c)) == pytest.approx((1 - tau) * na + tau * nb, rel=1e-12)


def test_align_removes_pose():
    a = _bumpy(E1, 11, 0.2)
    b = a.transformed(R1 * 2.0, (30, 0, 0))  # the same shape, moved and scaled
    _, shapes = morph(a, b, 3, "plane", align=True)
    assert np.allclose(shapes[0].params, shapes[2].params, atol=1e-8)
    assert np.allclose(shapes[1].params, shapes[0].params, atol=1e-8)


def test_morph_cli(tmp_path, capsys):
    pa, pb = tmp_path / "a.json", tmp_path / "b.json"
    E1.save(pa)
    E2.save(pb)
    out = tmp_path / "m"
    assert main(["morph", str(pa), str(pb), "--steps", "3", "--out", str(out), "--json"]) == 0
    rec = json.loads(capsys.readouterr().out)
    assert [r["tau"] for r in rec["steps"]] == [0.0, 0.5, 1.0]
    rows = list(csv.DictReader(open(out / "morph.csv")))
    assert float(rows[0]["volume_mm3"]) == pytest.approx(4 / 3 * np.pi * 60, rel=1e-12)
    assert float(rows[2]["volume_mm3"]) == pytest.approx(4 / 3 * np.pi * 36, rel=1e-12)
    import pyvista as pv

    assert pv.read(out / "step_001.vtp").n_points > 100
    from segsnake.surfaces import load_model

    assert np.allclose(load_model(out / "step_001.json").params, 0.5 * (E1.params + E2.params))
    assert main(["morph", str(pa), str(pb), "--steps", "3", "--out", str(out)]) == 5
    # masks on an image's grid: their voxel counts follow the volumes
    import nibabel as nib

    nib.save(nib.Nifti1Image(np.zeros((24, 24, 24), np.float32), np.eye(4)), str(tmp_path / "g.nii.gz"))
    a2 = SphereModel.ellipsoid((12, 12, 12), (4, 5, 6), m1=6, m2=5)
    b2 = SphereModel.ellipsoid((12, 12, 12), (8, 7, 6), m1=6, m2=5)
    a2.save(tmp_path / "a2.json")
    b2.save(tmp_path / "b2.json")
    assert main(["morph", str(tmp_path / "a2.json"), str(tmp_path / "b2.json"), "--steps", "3",
                 "--out", str(tmp_path / "mm"), "--like", str(tmp_path / "g.nii.gz"), "-q"]) == 0
    counts = [int(np.asarray(nib.load(str(tmp_path / "mm" / f"step_00{i}.nii.gz")).dataobj).sum())
              for i in range(3)]
    vols = [4 / 3 * np.pi * 120, None, 4 / 3 * np.pi * 336]
    assert counts[0] == pytest.approx(vols[0], rel=0.05) and counts[2] == pytest.approx(vols[2], rel=0.05)
    assert counts[0] < counts[1] < counts[2]
    SphereModel.unit(8, 5).save(tmp_path / "c.json")
    assert main(["morph", str(pa), str(tmp_path / "c.json"), "--out", str(tmp_path / "n")]) == 3
    assert not (tmp_path / "n").exists()
