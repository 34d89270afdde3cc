"""Exact measurements of spline snakes (issue 19, item 3) against closed forms."""

import csv
import io
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.special import ellipeinc, ellipkinc

from segsnake.cli import main
from segsnake.measure import closed_area, measure
from segsnake.surfaces import CylinderModel, SphereModel

ROT = Rotation.from_euler("xyz", [20, 30, 40], degrees=True).as_matrix()


def ellipsoid_area(a: float, b: float, c: float) -> float:
    """Legendre's closed form with incomplete elliptic integrals (a >= b >= c)."""
    a, b, c = sorted([a, b, c], reverse=True)
    phi = np.arccos(c / a)
    m = a * a * (b * b - c * c) / (b * b * (a * a - c * c))
    return 2 * np.pi * c * c + 2 * np.pi * a * b / np.sin(phi) * (
        ellipeinc(phi, m) * np.sin(phi) ** 2 + ellipkinc(phi, m) * np.cos(phi) ** 2)


def test_sphere_exact():
    r = 5.0
    m = measure(SphereModel.ellipsoid((1, 2, 3), (r, r, r), m1=7, m2=6))
    assert m.volume == pytest.approx(4 / 3 * np.pi * r**3, rel=1e-12)
    assert m.area == pytest.approx(4 * np.pi * r**2, rel=1e-12)
    assert m.sphericity == pytest.approx(1.0, rel=1e-12)
    assert m.max_diameter == pytest.approx(2 * r, rel=1e-9)
    assert np.allclose(m.centroid, (1, 2, 3), atol=1e-12)
    assert np.allclose(m.principal_lengths, 2 * r, rtol=1e-12)
    assert m.mean_curvature["mean"] == pytest.approx(1 / r, rel=1e-12)
    assert m.mean_curvature["std"] < 1e-9 and m.gaussian_curvature["std"] < 1e-9
    assert m.gaussian_curvature["mean"] == pytest.approx(1 / r**2, rel=1e-12)
    assert m.mean_curvature["integral"] == pytest.approx(4 * np.pi * r, rel=1e-12)


def test_rotated_ellipsoid_far_from_origin():
    radii = np.array([7.0, 4.0, 2.0])
    m = measure(SphereModel.ellipsoid((10, -5, 100), radii, ROT, m1=9, m2=9))
    assert m.volume == pytest.approx(4 / 3 * np.pi * radii.prod(), rel=1e-12)
    assert m.area == pytest.approx(ellipsoid_area(*radii), rel=1e-12)
    assert np.allclose(m.centroid, (10, -5, 100), atol=1e-10)
    assert np.allclose(m.principal_lengths, 2 * radii, rtol=1e-12)
    # the principal axes are the rotation's columns (up to sign)
    assert np.allclose(np.abs(np.array(m.principal_axes)), np.abs(ROT.T), atol=1e-10)
    assert m.max_diameter == pytest.approx(14.0, rel=1e-9)
    assert m.gaussian_curvature["integral"] == pytest.approx(4 * np.pi, rel=1e-9)  # Gauss-Bonnet
    a, b, c = radii
    # extremes over the quadrature nodes: inside the true range, within 3 % of its ends
    k_max, k_min = a * a / (b * c) ** 2, c * c / (a * b) ** 2
    assert 0.97 * k_max < m.gaussian_curvature["max"] <= k_max * (1 + 1e-9)
    assert k_min * (1 - 1e-9) <= m.gaussian_curvature["min"] < 1.03 * k_min
    assert m.sphericity == pytest.approx(
        np.pi ** (1 / 3) * (8 * np.pi * radii.prod()) ** (2 / 3) / ellipsoid_area(*radii), rel=1e-12)


def test_cylinder_with_caps():
    r, h = 2.0, 10.0
    m = measure(CylinderModel.from_axis((1, 1, 1), (1, 1, 1 + h), r, m1=8, m2=4))
    assert m.volume == pytest.approx(np.pi * r * r * h, rel=1e-12)
    assert m.area == pytest.approx(2 * np.pi * r * h + 2 * np.pi * r * r, rel=1e-12)
    assert np.allclose(m.centroid, (1, 1, 1 + h / 2), atol=1e-12)
    assert m.max_diameter == pytest.approx(np.hypot(h, 2 * r), rel=1e-9)
    assert m.mean_curvature["mean"] == pytest.approx(1 / (2 * r), rel=1e-12)
    assert abs(m.gaussian_curvature["integral"]) < 1e-12
    # solid cylinder: second moments h^2/12 along, r^2/4 across -> lengths 2 sqrt(5 lambda)
    assert np.allclose(m.principal_lengths, [2 * np.sqrt(5 * h * h / 12)] + [2 * np.sqrt(5 * r * r / 4)] * 2,
                       rtol=1e-12)


def test_bumpy_shape_volume_and_area_match_dense_mesh():
    rng = np.random.default_rng(3)
    base = SphereModel.ellipsoid((0, 0, 0), (6, 5, 4), m1=10, m2=8)
    model = base.with_params(base.params + 0.6 * rng.normal(size=base.params.shape))
    m = measure(model)
    mesh = model.to_mesh(samples_u=24 * model.m1, samples_v=24 * model.m2)
    assert m.volume == pytest.approx(mesh.volume, rel=5e-4)
    assert m.area == pytest.approx(mesh.area, rel=5e-4)
    assert m.max_diameter >= np.max(np.linalg.norm(mesh.points[:, None] - mesh.points[None, ::997], axis=-1))
    assert closed_area(model) == pytest.approx(m.area, rel=1e-12)


def test_measure_cli_json_and_csv(tmp_path, capsys):
    path = tmp_path / "e.json"
    SphereModel.ellipsoid((0, 0, 0), (3, 4, 5)).save(path)
    assert main(["measure", str(path), "--json"]) == 0
    rec = json.loads(capsys.readouterr().out)
    assert rec["status"] == "ok" and rec["volume"] == pytest.approx(80 * np.pi, rel=1e-12)
    assert main(["measure", str(path), "--csv"]) == 0
    rows = dict(csv.reader(io.StringIO(capsys.readouterr().out)))
    assert float(rows["area"]) == pytest.approx(ellipsoid_area(3, 4, 5), rel=1e-12)
    assert float(rows["principal_lengths.0"]) == pytest.approx(10.0, rel=1e-12)
    assert main(["measure", str(tmp_path / "missing.json")]) == 3
    assert "missing.json: no such file" in capsys.readouterr().err
