"""qc.png: slices through the click, a legend, the truth's contour, world-mm axes with the
anatomical directions a viewer shows (radiological: the patient's right on the left)."""

from __future__ import annotations

import numpy as np
import pytest

from segsnake.anatomy import axis_directions, view_axes
from segsnake.cli import main
from segsnake.config import SegmentConfig
from segsnake.io import Volume
from segsnake.pipeline import initial_model
from segsnake.qc import click_index, qc_figure, slice_panel


def rotation_z(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def test_directions_of_lps_permuted_and_oblique_grids():
    # A DICOM-like LPS grid stored in RAS+: i towards L, j towards P.
    assert axis_directions(np.diag([-1.0, -1.0, 2.0, 1.0])) == ((0, 1, 2), (-1, -1, 1))
    # Axial slices stored along j (i -> x, j -> z, k -> y).
    perm = np.eye(4)[:, [0, 2, 1, 3]]
    assert axis_directions(perm)[0] == (0, 2, 1)
    # Oblique by 30 degrees about z: the dominant directions.
    aff = np.eye(4)
    aff[:3, :3] = rotation_z(30)
    assert axis_directions(aff) == ((0, 1, 2), (1, 1, 1))
    # 45 degrees on both in-plane axes: still three distinct labels.
    aff[:3, :3] = rotation_z(45)
    assert sorted(axis_directions(aff)[0]) == [0, 1, 2]
    # A slice across the z axis of the permuted grid is axial: x across, y up.
    assert view_axes(perm, 1) == (0, 2, 0, 1)


def test_click_index_from_the_options():
    volume = Volume(np.zeros((10, 10, 10), np.float32), (2.0, 2.0, 2.0),
                    np.diag([2.0, 2.0, 2.0, 1.0]))
    assert click_index(SegmentConfig(), volume) is None
    np.testing.assert_allclose(click_index(SegmentConfig(center=[1, 2, 3]), volume), [1, 2, 3])
    np.testing.assert_allclose(click_index(SegmentConfig(seed_point=[4, 5, 6]), volume), [4, 5, 6])
    cyl = SegmentConfig(shape="cylinder", axis_start=[2, 2, 0], axis_end=[2, 2, 8], radius=2)
    np.testing.assert_allclose(click_index(cyl, volume), [2, 2, 4])
    world = SegmentConfig(center=[4, 6, 8], world=True)
    np.testing.assert_allclose(click_index(world, volume), [2, 3, 4])


@pytest.fixture
def picture():
    """A ball on an LPS-stored, anisotropic grid whose i axis is the patient's left-right."""
    shape, spacing = (30, 26, 20), (1.0, 1.2, 1.5)
    affine = np.diag([-1.0, -1.2, 1.5, 1.0])
    affine[:3, 3] = (10.0, 20.0, -5.0)
    idx = np.stack(np.meshgrid(*map(np.arange, shape), indexing="ij"), -1) * spacing
    mask = np.linalg.norm(idx - np.array([15.0, 15.0, 15.0]), axis=-1) < 7
    truth = np.linalg.norm(idx - np.array([15.5, 15.0, 15.0]), axis=-1) < 7
    image = mask.astype(np.float32) * 100
    model = initial_model(SegmentConfig(center=[15, 12.5, 10], radii=[7, 5.8, 4.7]), spacing, shape)
    return image, spacing, affine, mask, truth, model


def test_qc_figure_goes_through_the_click_with_legend_truth_and_anatomy(picture):
    image, spacing, affine, mask, truth, model = picture
    click = (9.0, 7.0, 12.0)  # away from the result's centre (15, 12.5, 10)
    fig = qc_figure(image, spacing, mask, model, model, affine=affine, truth=truth, click=click)
    panels = fig.axes[:3]
    titles = [ax.get_title() for ax in panels]
    assert titles[0].startswith("axial: k = 12") and titles[1].startswith("coronal: j = 7")
    assert titles[2].startswith("sagittal: i = 9")
    # World coordinates of the click: x = 10 - 9 = 1, y = 20 - 1.2 * 7 = 11.6, z = -5 + 18 = 13.
    assert titles[0].endswith("z = 13.0 mm") and titles[2].endswith("x = 1.0 mm")
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    assert legend == ["final surface", "initial surface", "truth", "click (slices through it)"]
    # Three contours per panel (truth, initial, final) and the click's cross at its world x, y.
    axial = panels[0]
    assert len(axial.collections) >= 3
    cross = [line for line in axial.lines if line.get_marker() == "+"][0]
    np.testing.assert_allclose([cross.get_xdata()[0], cross.get_ydata()[0]], [1.0, 11.6])
    # Radiological layout: R (larger x) on the left, A (larger y) up; world mm extents.
    x0, x1 = axial.get_xlim()
    y0, y1 = axial.get_ylim()
    assert x0 > x1 and y1 > y0
    np.testing.assert_allclose(sorted((x0, x1)), [10 - 29.5, 10.5])
    assert axial.get_xlabel().startswith("x (mm)") and axial.get_ylabel() == "y (mm)"
    letters = {t.get_text(): t.get_position() for t in axial.texts}
    assert letters["R"][0] < letters["L"][0] and letters["A"][1] > letters["P"][1]
    sagittal = panels[2]
    letters = {t.get_text(): t.get_position() for t in sagittal.texts}
    assert letters["A"][0] < letters["P"][0] and letters["S"][1] > letters["I"][1]


def test_slice_panel_keeps_the_montage_call(picture):
    from matplotlib.figure import Figure

    image, spacing, _, mask, _, _ = picture
    ax = Figure().add_subplot(1, 1, 1)
    slice_panel(ax, image, np.asarray(spacing), 2, 10, [(mask, "red", "solid", 1.0)])
    assert ax.get_title() == "k (z) = 10" and ax.get_xlabel() == "i (x) mm"


def test_segment_draws_the_truth_and_slices_through_the_click(tmp_path, capsys, monkeypatch):
    from segsnake.commands.phantom import write_phantom
    from segsnake.phantoms import make_phantom

    ph = make_phantom("ball", seed=1, shape=(32, 32, 32), noise=0.05)
    write_phantom(ph, tmp_path / "ph")
    seen = {}

    def record(path, image, spacing, mask, model, init_model=None, **kwargs):
        seen.update(kwargs)
        open(path, "wb").close()

    monkeypatch.setattr("segsnake.runner.write_qc_picture", record)
    centre = [float(c) + 2 for c in ph.init["center"]]
    rc = main(["segment", str(tmp_path / "ph" / "image.nii.gz"), "--out", str(tmp_path / "seg"),
               "--truth", str(tmp_path / "ph" / "truth.nii.gz"), "-q", "--center", *map(str, centre),
               "--radii", *map(str, ph.init["radii"])])
    assert rc == 0, capsys.readouterr().err
    np.testing.assert_allclose(seen["click"], centre)
    np.testing.assert_array_equal(seen["truth"] != 0, ph.truth != 0)
    np.testing.assert_allclose(seen["affine"], ph.affine)
