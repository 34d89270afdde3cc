"""End-to-end accuracy of the segmentation pipeline on phantoms with known truth (issue 4)."""

import numpy as np
import pytest
from conftest import perturbed_init

from segsnake.config import SegmentConfig
from segsnake.errors import SegmentationError
from segsnake.metrics import dice, jaccard
from segsnake.phantoms import make_phantom
from segsnake.edge_stages import _center_and_axis
from segsnake.pipeline import segment_volume


def _segment(ph, seed, region_params=None, **options):
    """Segment the phantom from its suggested start perturbed with ``seed`` (issue 14); with
    ``seed=None`` from the suggested start itself (regression tests of a measured case only)."""
    init = ph.init if seed is None else perturbed_init(ph, seed)
    config = SegmentConfig.from_mapping({**init, **options})
    return segment_volume(ph.image, ph.spacing, config, region_params=region_params)


def _mid_surface_distance(model, params):
    """Mean |distance from the axis - mid radius| over the snake (hollow cylinder)."""
    g = params["geometry"]
    c, a = np.asarray(g["center_mm"]), np.asarray(g["axis"], dtype=float)
    s = model.evaluate(np.linspace(0, 1, 64, endpoint=False), np.linspace(0.1, 0.9, 17))[0]
    rel = s.reshape(-1, 3) - c
    radial = rel - np.outer(rel @ a, a)
    return float(np.mean(np.abs(np.linalg.norm(radial, axis=1) - g["mid_radius_mm"])))


@pytest.mark.parametrize("kind,options,start", [
    ("ball", {"noise": 0.3}, 1),
    ("ellipsoid", {"noise": 0.1}, 2),
    ("blob", {"noise": 0.2}, 3),
    ("ball", {"noise": 0.1, "spacing": (1.0, 1.0, 2.0)}, 4),
    ("ellipsoid", {"noise": 0.3, "spacing": (1.0, 1.0, 2.0)}, 5),
    ("blob", {"noise": 0.1, "spacing": (1.0, 1.0, 2.0)}, 6),
])
def test_sphere_phantoms_from_a_perturbed_start(kind, options, start):
    ph = make_phantom(kind, seed=3, **options)
    res = _segment(ph, start)
    truth = ph.truth.astype(bool)
    assert dice(res.mask, truth) >= 0.95
    # The surface sits on the boundary, not an edge width inside it: volume within 6 %.
    assert abs(res.mask.sum() / truth.sum() - 1) < 0.06
    assert res.polarity == "bright"


@pytest.mark.parametrize("kind,start", [("ball", None), ("ellipsoid", None), ("ball", 7),
                                        ("ellipsoid", 8)])
def test_a_normal_near_a_pole_does_not_freeze_the_refinement(kind, start):
    # Seed 2: one grid normal in the second knot interval from a pole turned over early in the
    # refinement, and the fold check then refused every step (Dice 0.90 and 0.84; measured
    # from the phantom's unperturbed start, kept here as the regression case it was: the edge
    # stages' fold check against the stage's start).
    ph = make_phantom(kind, seed=2, noise=0.1)
    res = _segment(ph, start, energy="edge")
    assert dice(res.mask, ph.truth.astype(bool)) >= 0.99
    u, v = np.linspace(0, 1, 60, endpoint=False), np.linspace(0.001, 0.999, 60)
    s, n = res.model.evaluate(u, v)[0], res.model.normals(u, v)
    r = s - s.reshape(-1, 3).mean(axis=0)
    assert np.all(np.einsum("uvd,uvd->uv", n, r) > 0)  # and no fold near the poles either


def test_fold_check_rows_leave_out_the_pole_intervals():
    from segsnake.stage import Admissible
    from segsnake.surfaces import CylinderModel, SphereModel

    def rows(model):
        return Admissible(model, np.array([1e9, 1e9])).n0.shape[1]

    # three grid rows per knot interval: two intervals left out at each pole, one when M2 = 4
    # (two would leave nothing to check), none for a cylinder
    assert [rows(SphereModel.unit(6, m2)) for m2 in (4, 5, 9)] == [6, 3, 15]
    assert rows(CylinderModel.unit(6, 4)) == 12


def test_an_edge_stage_refuses_a_fold_and_a_region_stage_prices_it_instead():
    from segsnake.stage import Admissible
    from segsnake.surfaces import SphereModel

    ball = SphereModel.ellipsoid((20, 20, 20), (10, 10, 10))
    dented = ball.params.copy()  # its upper half pushed down to -0.3 of its height: turned over
    top = dented[:, 2] > 20
    dented[top, 2] = 20 - 0.3 * (dented[top, 2] - 20)
    assert ball.with_params(dented).volume(order=8) > 0.2 * ball.volume(order=8)
    assert not Admissible(ball, np.array([1e9, 1e9]))(dented)  # normals turned over
    assert Admissible(ball, np.array([1e9, 1e9]), follow=True)(dented)
    collapsed = ball.params.copy()
    collapsed[:, 2] = 20 + 0.01 * (collapsed[:, 2] - 20)  # flat: below MIN_VOLUME_FRACTION
    assert not Admissible(ball, np.array([1e9, 1e9]), follow=True)(collapsed)


def test_a_tube_ring_may_not_tilt_over_or_flatten():
    from segsnake.stage import Admissible
    from segsnake.surfaces import CylinderModel

    tube = CylinderModel.from_axis([0, 0, 0], [0, 0, 40], 5.0, m1=8, m2=4)
    check = Admissible(tube, np.array([1e9, 1e9]))
    grid = tube.params.reshape(8, 7, 3)

    def with_row(l, factor):  # ring l scaled about its centre within its own plane
        g = grid.copy()
        centre = g[:, l].mean(axis=0)
        g[:, l] = centre + factor * (g[:, l] - centre)
        return g.reshape(-1, 3)

    assert check(with_row(3, 0.5))  # a narrowing is fine
    assert not check(with_row(3, 0.0))  # pinched: the rings near it keep < 2 % of their area
    assert not check(with_row(3, -1.0))  # turned inside out (its normals turn too)
    tilted = grid.copy()  # the middle ring tilted beyond the plane of the tube's axis
    tilted[:, 3, 2] += 1.2 * tilted[:, 3, 0] * 40 / 4 / 5.0
    assert not check(tilted.reshape(-1, 3))
    assert Admissible(tube, np.array([1e9, 1e9]), follow=True)(with_row(3, 0.5))


def test_a_region_stage_prices_a_surface_that_crosses_itself_instead_of_refusing_it():
    # A hairpin tube (legs 16 mm apart, radius 3 mm) whose legs' control points are moved
    # towards each other: pushed 8 mm, the legs overlap (81 mm^3 wrapped twice). A region stage
    # takes the step (a refusal only kept the surface from crossing further; one that had
    # crossed stayed so, docs/benchmarks.md session 14), and its energy carries the price of
    # the crossing, crossing_weight per mm^3.
    from segsnake.stage import Admissible, stage_energy
    from segsnake.rasterize import crossing_volume
    from segsnake.surfaces import CylinderModel

    axis = [(5, 10, 5), (5, 10, 35), (13, 10, 45), (21, 10, 35), (21, 10, 5)]
    start = CylinderModel.from_centerline(axis, 3.0, m1=8, m2=12)
    points = start.params.reshape(-1, 3)

    def legs_moved(d):  # each leg's control points d mm towards the other (the bend stays)
        moved = points.copy()
        moved[:, 0] += d * np.clip((13 - points[:, 0]) / 4, -1, 1) * (points[:, 2] < 36)
        return moved.reshape(start.params.shape)

    assert Admissible(start, np.array([1e9, 1e9]), follow=True)(legs_moved(8))

    class Volume:  # G = x: the flux is the volume integral of 1
        def sample(self, p):
            return p[:, 0].copy(), np.tile([1.0, 0.0, 0.0], (len(p), 1))

    crossed = legs_moved(8)
    volume = crossing_volume(start.with_params(crossed))
    assert volume > 40.0
    priced = stage_energy(start, Volume(), 1.0, 4, None, region=True, crossing_weight=2.0)
    free = stage_energy(start, Volume(), 1.0, 4, None, region=True)
    assert priced.value_and_grad(crossed)[0] - free.value_and_grad(crossed)[0] == \
        pytest.approx(2.0 * volume)
    apart = legs_moved(4)  # narrowed in places, apart: no price
    assert priced.value_and_grad(apart)[0] == free.value_and_grad(apart)[0]


def test_dark_object_on_bright_background_is_found_with_auto_polarity():
    ph = make_phantom("ball", seed=4, noise=0.2, foreground=20.0, background=100.0)
    res = _segment(ph, 9)
    assert res.polarity == "dark"
    assert dice(res.mask, ph.truth.astype(bool)) >= 0.95


def test_internal_edges_inside_the_initial_surface_do_not_trap_the_snake():
    # A bright ball with a dark core (an internal edge, like a ventricle) well inside the start.
    ph = make_phantom("ball", seed=5, noise=0.1)
    image = ph.image.copy()
    idx = np.indices(image.shape).reshape(3, -1).T
    centre = np.asarray(ph.init["center"])
    core = np.linalg.norm(idx - centre, axis=1).reshape(image.shape) < 4.0
    image[core] = 20.0
    ph.image = image
    res = _segment(ph, 10)
    assert dice(res.mask, ph.truth.astype(bool)) >= 0.95


@pytest.mark.parametrize("std", [50])
def test_hollow_cylinder_of_table_7_2(std):
    ph = make_phantom("hollow-cylinder", seed=0, std=std)
    res = _segment(ph, 11, feature="surface")
    assert jaccard(res.mask, ph.truth.astype(bool)) >= 0.94
    # The refinement's a-priori quadrature is within one doubling of the order its check
    # accepts (at the stages' four feature widths it took more: this fails there).
    refine = next(h for h in res.history if h["stage"] == "refine")
    first = refine["quadrature_checks"][0]["order"]
    assert all(o <= 2 * f for o, f in zip(refine["quadrature_order"], first))


def test_cylinder_along_x_is_closed_by_its_caps():
    # Along x the lookup's integration axis runs through the tube's ends: an open tube's flux
    # missed its caps' (measured before: "no boundary found", until a turned frame put x
    # across it). Closed by its caps, the flux is the volume integral in any orientation.
    ph = make_phantom("hollow-cylinder", seed=1, std=50, axis=(1.0, 0.0, 0.0))
    res = _segment(ph, 12, feature="surface")
    assert jaccard(res.mask, ph.truth.astype(bool)) >= 0.94
    c, axis = _center_and_axis(res.model)
    assert abs(axis[0]) > 10 * max(abs(axis[1]), abs(axis[2]))  # the snake stayed along x


def test_short_oblique_tube_from_its_end_clicks_ends_at_its_rims():
    # A short hollow tube along (-0.63, -0.32, -0.70), started to 15 % of its length from each
    # end (bench_tubes.py's end-point click): with open ends in a rotated frame the capture
    # flared the ends to 1.7 x the radius and ran them 30 mm past the rims, and the refinement
    # stopped there ("no boundary found"; perturbed by 1e-12, Dice 0.63). Closed by its caps,
    # the capture stops inside the rims.
    axis = (-0.6323984977372045, -0.32285622772920797, -0.7041562300201516)
    ph = make_phantom("hollow-cylinder", seed=1, std=50.0, length=70.0, radius=20.0, axis=axis)
    g = ph.params["geometry"]
    a0, a1 = np.asarray(g["axis_start_mm"]), np.asarray(g["axis_end_mm"])
    init = {"shape": "cylinder", "axis_start": list(a0 + 0.15 * (a1 - a0)),
            "axis_end": list(a1 - 0.15 * (a1 - a0)), "radius": 10.0}
    res = segment_volume(ph.image, ph.spacing,
                         SegmentConfig.from_mapping({**init, "feature": "surface"}))
    assert dice(res.mask, ph.truth.astype(bool)) >= 0.95
    c0, along, radius = res.model.axis_and_radius()
    assert abs(np.linalg.norm(along) - 70.0) < 5.0 and abs(radius - 20.0) < 1.5


def test_tube_leaving_the_volume_ends_on_its_faces():
    # A long hollow tube runs through the volume's faces: beyond them the edge stages' densities
    # are zero (no edge is known there), and the tension ends the tube on the faces (with the
    # lookup clamped, the face's density went on outside and the capture ran a tube along
    # (0.44, -0.85, -0.29) out of the volume).
    axis = (0.44, -0.85, -0.29)
    ph = make_phantom("hollow-cylinder", seed=5, std=50.0, axis=axis)
    res = _segment(ph, 20, feature="surface")
    assert jaccard(res.mask, ph.truth.astype(bool)) >= 0.94
    lo, hi = np.zeros(3), (np.asarray(ph.image.shape) - 1) * np.asarray(ph.spacing)
    for ring in res.model.end_rings(32):  # each end ring reaches a face of the volume
        assert min(np.min(ring - lo), np.min(hi - ring)) < 1.0


@pytest.mark.slow
def test_oblique_cylinder_from_a_perturbed_start():
    # Along (-0.72, 0.56, 0.41) every array axis leaves the caps tilted by 24 degrees or more;
    # with open ends in permuted frames only, this short tube gave Jaccard 0.67.
    axis = (-0.6204749, 0.48984205, 0.35688701)
    ph = make_phantom("hollow-cylinder", seed=3, std=50, axis=axis, length=70.0, radius=20.0)
    res = _segment(ph, 13, feature="surface")
    assert jaccard(res.mask, ph.truth.astype(bool)) >= 0.94


@pytest.mark.slow
@pytest.mark.parametrize("std,minimum,start", [(0, 0.94, 14), (10, 0.94, 15), (30, 0.94, 16),
                                               (50, 0.94, 17), (70, 0.92, 18), (90, 0.92, 19)])
def test_table_7_2_all_rows(std, minimum, start):
    ph = make_phantom("hollow-cylinder", seed=1, std=std)
    res = _segment(ph, start, feature="surface")
    assert jaccard(res.mask, ph.truth.astype(bool)) >= minimum
    if std == 0:
        assert _mid_surface_distance(res.model, ph.params) < 0.3


def test_snake_in_empty_space_is_a_failure_not_a_mask():
    image = np.zeros((32, 32, 32), np.float32)
    image[16, 16, 16] = 100.0
    config = SegmentConfig.from_mapping({"center": [5, 5, 5], "radii": [3, 3, 3]})
    # Depending on how fast it shrinks, the snake either collapses or stops on nothing.
    with pytest.raises(SegmentationError, match="no boundary found|collapsed|constant"):
        segment_volume(image, (1.0, 1.0, 1.0), config)
    with pytest.raises(SegmentationError, match="no boundary found|collapsed"):
        segment_volume(image, (1.0, 1.0, 1.0), config.replace(energy="edge"))


def test_stage_refines_an_untrustworthy_quadrature(monkeypatch):
    # A narrow Gaussian blob (width 0.25) that the a-priori order (from a 16x too wide feature
    # size) samples too coarsely: order 4 is off by about 0.2 % there, order 8 by 1e-7. With a
    # tolerance between the two, the stage must move on to order 8 and stop there.
    from test_energy import AnalyticSampler

    from segsnake import stage
    from segsnake.energy import FluxTerm
    from segsnake.surfaces import SphereModel

    monkeypatch.setattr(stage, "QUADRATURE_RTOL", 1e-4)
    sampler = AnalyticSampler("blob", s=0.25)
    model = SphereModel.ellipsoid([0.1, -0.05, 0.0], [0.5, 0.6, 0.45], m1=6, m2=6)
    assert stage.quadrature_order(1.5 * max(stage.longest_intervals(model)), 4.0) == 4
    out, info = stage.run_stage(model, sampler, -1.0, SegmentConfig(), None, None, 0.1,
                                feature_mm=4.0)
    checks = [c for c in info["quadrature_checks"] if c["when"] == "converged"]
    assert [c["order"] for c in checks] == [[4, 4], [8, 8]]
    assert checks[0]["relative_error"] > 1e-4 >= checks[1]["relative_error"]
    e8, e16 = (FluxTerm(out, sampler, order=o).value_and_grad(out.params)[0] for o in (8, 16))
    assert abs(e8 - e16) <= 1e-4 * abs(e16)

    # Checked while running (here after every iteration, with a tight tolerance), the
    # first round stops at its first iteration and the stage goes on at order 8, from the
    # last shape it trusted: the start (not from the step the coarse rule made).
    monkeypatch.setattr(stage, "QUADRATURE_CHECK_EVERY", 1)
    monkeypatch.setattr(stage, "QUADRATURE_RTOL_RUNNING", 1e-5)
    starts, ends = [], []
    real = stage.minimize_energy

    def spy(m, energy, **kwargs):
        starts.append(m.params.copy())
        res = real(m, energy, **kwargs)
        ends.append(res.model.params.copy())
        return res

    monkeypatch.setattr(stage, "minimize_energy", spy)
    out, info = stage.run_stage(model, sampler, -1.0, SegmentConfig(), None, None, 0.1,
                                feature_mm=4.0)
    first = info["quadrature_checks"][0]
    assert first["when"] == "running" and first["order"] == [4, 4]
    assert first["relative_error"] > 1e-5
    assert not np.array_equal(ends[0], model.params)  # the first round did move
    assert np.array_equal(starts[1], model.params)
    assert {tuple(c["order"]) for c in info["quadrature_checks"][1:]} == {(8, 8)}
    assert info["quadrature_resolved"] and info["quadrature_order"] == (8, 8)


def test_seed_point_is_a_world_position_with_world(monkeypatch):
    # With --world every position is in world mm, the seed point too (it used to be read as
    # voxel indices whatever --world said).
    from segsnake import features

    ph = make_phantom("ball", seed=3, noise=0.1)
    seen = []
    real = features.edge_map

    def spy(*args, **kwargs):
        seen.append(kwargs.get("seed"))
        return real(*args, **kwargs)

    monkeypatch.setattr(features, "edge_map", spy)
    shift = np.array([100.0, -50.0, 20.0])  # world = index * spacing + shift (spacing 1 mm)
    init = perturbed_init(ph, 20)
    centre = np.asarray(init["center"], dtype=float)
    config = SegmentConfig.from_mapping({
        "world": True, "center": list(centre + shift), "radii": init["radii"],
        "seed_point": list(centre + shift)})
    res = segment_volume(ph.image, ph.spacing, config, index_from_world=lambda p: p - shift)
    assert np.allclose(seen[0], centre)
    assert dice(res.mask, ph.truth.astype(bool)) >= 0.95


def test_stage_stopped_by_the_iteration_cap_reports_its_quadrature():
    from test_energy import AnalyticSampler

    from segsnake import stage
    from segsnake.surfaces import SphereModel

    sampler = AnalyticSampler("blob", s=0.25)
    model = SphereModel.ellipsoid([0.1, -0.05, 0.0], [0.5, 0.6, 0.45], m1=6, m2=6)
    capped = SegmentConfig.from_mapping({"max_iter": 3})
    _, info = stage.run_stage(model, sampler, -1.0, capped, None, None, 0.1, feature_mm=4.0)
    assert info["iterations"] == 3 and len(info["quadrature_checks"]) == 1
    # Checked even though the cap stopped it (with the running tolerance: it is still moving),
    # and resolved exactly when the check agreed.
    check = info["quadrature_checks"][0]
    assert check["when"] == "capped"
    assert info["quadrature_resolved"] is (check["relative_error"] <= stage.QUADRATURE_RTOL_RUNNING)
    _, full = stage.run_stage(model, sampler, -1.0, SegmentConfig(), None, None, 0.1,
                              feature_mm=4.0)
    assert full["quadrature_resolved"] is True
