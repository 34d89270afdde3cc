"""Surface kernel: exact reproduction, interpolation, poles, affine invariance, volume, meshes, I/O."""

import json

import numpy as np
import pytest

from segsnake.surfaces import CylinderModel, SphereModel, load_model

SIZES = [4, 5, 9, 20, 50]
U = np.linspace(0, 1, 121)
V = np.linspace(0, 1, 117)


def _random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


@pytest.mark.parametrize("m1", SIZES)
@pytest.mark.parametrize("m2", SIZES)
def test_unit_sphere_is_reproduced_exactly(m1, m2):
    s = SphereModel.unit(m1, m2)
    sig, _, _ = s.evaluate(U, V)
    assert np.abs(np.linalg.norm(sig, axis=-1) - 1).max() < 1e-9
    # The parameterization is the exact one, not only the radius.
    uu, vv = np.meshgrid(U, V, indexing="ij")
    exact = np.stack([np.cos(2 * np.pi * uu) * np.sin(np.pi * vv),
                      np.sin(2 * np.pi * uu) * np.sin(np.pi * vv), np.cos(np.pi * vv)], -1)
    assert np.abs(sig - exact).max() < 1e-9


@pytest.mark.parametrize("m1", SIZES)
@pytest.mark.parametrize("m2", SIZES)
def test_unit_cylinder_is_reproduced_exactly(m1, m2):
    c = CylinderModel.unit(m1, m2)
    sig, _, _ = c.evaluate(U, V)
    assert np.abs(np.hypot(sig[..., 0], sig[..., 1]) - 1).max() < 1e-9
    assert np.abs(sig[..., 2] - V[None, :]).max() < 1e-9


@pytest.mark.parametrize("model", [SphereModel.unit(7, 6), CylinderModel.unit(7, 5)])
def test_interpolation_and_partition_of_unity(model):
    rng = np.random.default_rng(1)
    model = model.with_params(model.params + 0.2 * rng.normal(size=model.params.shape))
    C = model.control_points()
    u = np.arange(model.m1) / model.m1
    v = np.arange(0, model.m2 + 1) / model.m2
    sig, _, _ = model.evaluate(u, v)
    np.testing.assert_allclose(sig, C[:, 1:-1], atol=1e-12)  # l = 0..M2
    gb = model.grid_basis(U, V)
    np.testing.assert_allclose(gb.Bu.sum(axis=1), 1.0, atol=1e-13)
    np.testing.assert_allclose(gb.Bv.sum(axis=1), 1.0, atol=1e-13)


@pytest.mark.parametrize("model", [SphereModel.unit(6, 5), CylinderModel.unit(6, 4)])
def test_affine_invariance(model):
    rng = np.random.default_rng(2)
    model = model.with_params(model.params + 0.1 * rng.normal(size=model.params.shape))
    A = rng.normal(size=(3, 3))
    b = rng.normal(size=3)
    moved = model.transformed(A, b)
    s0, su0, sv0 = model.evaluate(U, V)
    s1, su1, sv1 = moved.evaluate(U, V)
    np.testing.assert_allclose(s1, s0 @ A.T + b, atol=1e-12)
    np.testing.assert_allclose(su1, su0 @ A.T, atol=1e-11)
    np.testing.assert_allclose(moved.control_points(), model.control_points() @ A.T + b, atol=1e-12)


def test_random_perturbations_keep_poles_closed_and_smooth():
    rng = np.random.default_rng(3)
    base = SphereModel.unit(8, 7)
    for _ in range(5):
        s = base.with_params(base.params + 0.3 * rng.normal(size=base.params.shape))
        u = np.linspace(0, 1, 64, endpoint=False)
        ends, _, _ = s.evaluate(u, [0.0, 1.0])
        np.testing.assert_allclose(ends[:, 0], np.broadcast_to(s.pole("cN"), (64, 3)), atol=1e-12)
        np.testing.assert_allclose(ends[:, 1], np.broadcast_to(s.pole("cS"), (64, 3)), atol=1e-12)
        # sigma_v at the pole lies in the tangent plane spanned by T1, T2 (eq. (9), (10)).
        _, _, sv = s.evaluate(u, [0.0, 1.0])
        expected_n = s.pole("T1N")[None] * np.cos(2 * np.pi * u)[:, None] + \
            s.pole("T2N")[None] * np.sin(2 * np.pi * u)[:, None]
        np.testing.assert_allclose(sv[:, 0], expected_n, atol=1e-10)
        # Normals approaching the pole from every u direction converge (linearly, the surface is
        # C1) to the outward pole normal T1 x T2 (north) and -(T1 x T2) (south).
        for v_pole, pole_normal in ((0.0, np.cross(s.pole("T1N"), s.pole("T2N"))),
                                    (1.0, -np.cross(s.pole("T1S"), s.pole("T2S")))):
            pole_normal = pole_normal / np.linalg.norm(pole_normal)
            angles = []
            for eps in (1e-3, 1e-4, 1e-5):
                n = s.normals(u, [abs(v_pole - eps)])[:, 0]
                angles.append(np.degrees(np.arccos(np.clip(n @ pole_normal, -1, 1))).max())
            assert angles[1] < angles[0] / 5 and angles[2] < angles[1] / 5
            assert angles[2] < 0.1


@pytest.mark.parametrize("m1,m2", [(4, 4), (9, 9), (20, 13)])
def test_volume_area_and_orientation(m1, m2):
    rng = np.random.default_rng(4)
    assert abs(SphereModel.unit(m1, m2).volume() - 4 * np.pi / 3) < 1e-9
    assert abs(SphereModel.unit(m1, m2).area() - 4 * np.pi) < 1e-9
    radii = np.array([2.0, 3.0, 0.5])
    e = SphereModel.ellipsoid(rng.normal(size=3), radii, _random_rotation(rng), m1, m2)
    assert abs(e.volume() - 4 * np.pi * radii.prod() / 3) < 1e-9
    assert e.reversed().volume() < 0  # the sign tells the orientation
    # Outward: normals point away from the centre.
    n = e.normals(U[:-1], V[1:-1])
    sig, _, _ = e.evaluate(U[:-1], V[1:-1])
    assert np.all(np.einsum("uvd,uvd->uv", n, sig - sig.reshape(-1, 3).mean(0)) > 0)


def test_cylinder_volume_with_caps_and_orientation():
    c = CylinderModel.from_axis([1, 2, 3], [4, 6, 3], radius=2.0, m1=8, m2=4)
    assert abs(c.volume() - np.pi * 4 * 5) < 1e-9
    assert abs(c.area() - 2 * np.pi * 2 * 5) < 1e-9
    n = c.normals(U[:-1], V)
    sig, _, _ = c.evaluate(U[:-1], V)
    axis = np.array([3.0, 4.0, 0.0]) / 5
    rel = sig - np.array([1, 2, 3])
    radial = rel - (rel @ axis)[..., None] * axis
    assert np.all(np.einsum("uvd,uvd->uv", n, radial) > 0)


@pytest.mark.parametrize("model", [SphereModel.unit(6, 5), CylinderModel.unit(6, 3)])
def test_partial_derivatives_match_central_differences(model):
    rng = np.random.default_rng(5)
    model = model.with_params(model.params + 0.2 * rng.normal(size=model.params.shape))
    u = np.array([0.013, 0.31, 0.77])
    v = np.array([0.021, 0.41, 0.93])  # off the knots (phi'' jumps there)
    h = 1e-6
    _, su, sv = model.evaluate(u, v)
    fd_u = (model.evaluate(u + h, v)[0] - model.evaluate(u - h, v)[0]) / (2 * h)
    fd_v = (model.evaluate(u, v + h)[0] - model.evaluate(u, v - h)[0]) / (2 * h)
    np.testing.assert_allclose(su, fd_u, atol=1e-6)
    np.testing.assert_allclose(sv, fd_v, atol=1e-6)


def test_pointwise_call_matches_grid_evaluation():
    s = SphereModel.ellipsoid([1, 0, 0], [1, 2, 3], m1=7, m2=6)
    grid, _, _ = s.evaluate(U[:5], V[:4])
    uu, vv = np.meshgrid(U[:5], V[:4], indexing="ij")
    np.testing.assert_allclose(s(uu, vv), grid, atol=1e-13)


@pytest.mark.parametrize("m1,m2", [(8, 6), (12, 9), (20, 20)])
def test_interpolating_a_sampled_sphere_reproduces_it(m1, m2):
    r, center = 3.5, np.array([10.0, -2.0, 4.0])
    exact = SphereModel.ellipsoid(center, (r, r, r), m1=m1, m2=m2)
    u = np.arange(m1) / m1
    v = np.arange(1, m2) / m2
    samples = exact.evaluate(u, v)[0]
    fitted = SphereModel.from_points(samples, center + [0, 0, r], center - [0, 0, r])
    sig, _, _ = fitted.evaluate(U, V)
    assert np.abs(np.linalg.norm(sig - center, axis=-1) - r).max() < 1e-9


def test_interpolating_a_star_shaped_blob_is_exact_at_samples_and_smooth_between():
    m1, m2 = 16, 12

    def blob(u, v):
        th, ph = 2 * np.pi * u, np.pi * v
        rad = 5 * (1 + 0.15 * np.sin(3 * th) * np.sin(ph) ** 2 + 0.1 * np.cos(2 * ph))
        return np.stack([rad * np.cos(th) * np.sin(ph), rad * np.sin(th) * np.sin(ph),
                         rad * np.cos(ph)], -1)

    uu, vv = np.meshgrid(np.arange(m1) / m1, np.arange(1, m2) / m2, indexing="ij")
    model = SphereModel.from_points(blob(uu, vv), blob(0.0, 0.0), blob(0.0, 1.0))
    sig, _, _ = model.evaluate(np.arange(m1) / m1, np.arange(1, m2) / m2)
    np.testing.assert_allclose(sig, blob(uu, vv), atol=1e-12)
    # Between samples: close to the underlying smooth shape (relative error ~ h^2 of the radius).
    fu, fv = np.meshgrid(U, V, indexing="ij")
    dense = model(fu, fv)
    assert np.abs(np.linalg.norm(dense, axis=-1) - np.linalg.norm(blob(fu, fv), axis=-1)).max() < 0.15
    # Smooth: no kinks, the normals vary continuously across a knot.
    n_left = model.normals([0.5 - 1e-7], V[5:-5])
    n_right = model.normals([0.5 + 1e-7], V[5:-5])
    assert np.abs(n_left - n_right).max() < 1e-5


def test_meshes_are_closed_manifold_and_outward():
    s = SphereModel.ellipsoid([1, 2, 3], [2, 3, 4], m1=9, m2=7)
    m = s.to_mesh(48, 40)
    assert m.is_manifold and m.n_open_edges == 0
    assert abs(m.volume - s.volume()) / s.volume() < 0.01
    c = CylinderModel.from_axis([0, 0, 0], [0, 0, 5], 2.0)
    mc = c.to_mesh(caps=True)
    assert mc.is_manifold and abs(mc.volume - c.volume()) / c.volume() < 0.01
    assert c.to_mesh(caps=False).n_open_edges > 0
    for mesh, centre in ((m, [1, 2, 3]), (mc, [0, 0, 2.5])):
        nm = mesh.compute_normals(cell_normals=True, point_normals=False, consistent_normals=False,
                                  auto_orient_normals=False, split_vertices=False)
        out = np.einsum("ij,ij->i", nm.cell_data["Normals"], mesh.cell_centers().points - centre)
        assert np.all(out > 0)


def test_curved_centerline_tube_keeps_its_radius():
    t = np.linspace(0, np.pi, 31)  # odd: the arc midpoint is a vertex
    line = np.column_stack([20 * np.cos(t), 20 * np.sin(t), np.zeros_like(t)])
    tube = CylinderModel.from_centerline(line, 3.0, m1=8, m2=12)
    u = np.arange(8) / 8
    ring, _, _ = tube.evaluate(u, [0.5])
    centre = np.array([0.0, 20.0, 0.0])  # the arc's midpoint at v = 0.5
    np.testing.assert_allclose(np.linalg.norm(ring[:, 0] - centre, axis=-1), 3.0, rtol=1e-3)
    assert tube.volume() > 0


@pytest.mark.parametrize("model", [SphereModel.ellipsoid([1, 2, 3], [1, 2, 3]),
                                   CylinderModel.from_axis([0, 0, 0], [1, 2, 9], 1.5)])
def test_save_load_round_trip_is_exact(model, tmp_path):
    rng = np.random.default_rng(6)
    model = model.with_params(model.params + rng.normal(size=model.params.shape) / 3)
    path = tmp_path / "model.json"
    model.save(path)
    back = load_model(path)
    assert type(back) is type(model) and (back.m1, back.m2) == (model.m1, model.m2)
    assert np.array_equal(back.params, model.params)
    d = json.loads(path.read_text())
    assert d["kind"] == model.kind and len(d["control_points"]) == model.m1


def test_bad_sizes_are_refused():
    with pytest.raises(ValueError, match="M1 must be >= 4"):
        SphereModel.unit(3, 5)
    with pytest.raises(ValueError, match="parameters"):
        SphereModel(5, 5, np.zeros((3, 3)))
