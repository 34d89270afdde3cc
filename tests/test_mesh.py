"""``--mesh NAME.stl|.obj|.ply``: the surface in world coordinates, written with the other outputs."""

from __future__ import annotations

import os

import numpy as np
import pytest
import pyvista as pv

from segsnake.cli import main
from segsnake.commands.phantom import write_phantom
from segsnake.io import load_volume
from segsnake.meshes import world_mesh, write_mesh, write_surface
from segsnake.phantoms import make_phantom


@pytest.fixture(scope="module")
def rotated(tmp_path_factory):
    """A small ball on a rotated, anisotropic grid: world coordinates differ from index x spacing."""
    out = tmp_path_factory.mktemp("ph")
    ph = make_phantom("ball", seed=1, shape=(32, 32, 24), spacing=(1.0, 1.0, 1.5), noise=0.05,
                      grid_rotation=(10.0, 0.0, 20.0))
    write_phantom(ph, out)
    return ph, out / "image.nii.gz"


@pytest.mark.parametrize("name", ["surface.stl", "surface.obj", "surface.PLY"])
def test_mesh_formats_hold_the_vtp_surface_in_world_mm(tmp_path, rotated, name):
    from segsnake.pipeline import initial_model
    from segsnake.config import SegmentConfig

    ph, image = rotated
    volume = load_volume(image)
    config = SegmentConfig(center=list(ph.init["center"]), radii=list(ph.init["radii"]))
    model = initial_model(config, volume.spacing, volume.shape)
    write_surface(str(tmp_path / "surface.vtp"), model, volume)
    write_mesh(str(tmp_path / name), model, volume)
    vtp = pv.read(tmp_path / "surface.vtp")
    mesh = pv.read(tmp_path / name)
    assert mesh.n_cells == vtp.n_cells
    # Same points (STL stores each triangle's corners: compare the sets).
    np.testing.assert_allclose(np.unique(np.round(mesh.points, 3), axis=0),
                               np.unique(np.round(vtp.points, 3), axis=0), atol=2e-3)
    assert abs(mesh.volume - vtp.volume) < 1e-3 * vtp.volume


def test_segment_writes_the_mesh_with_the_other_outputs(tmp_path, rotated, capsys):
    ph, image = rotated
    init = ["--center", *map(str, ph.init["center"]), "--radii", *map(str, ph.init["radii"])]
    out = tmp_path / "seg"
    rc = main(["segment", str(image), "--out", str(out), "--mesh", "ball.stl", *init])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert "ball.stl" in cap.out
    assert sorted(os.listdir(out)) == sorted(["mask.nii.gz", "surface.vtp", "snake.json",
                                              "qc.png", "ball.stl"])
    mesh, vtp = pv.read(out / "ball.stl"), pv.read(out / "surface.vtp")
    np.testing.assert_allclose(mesh.bounds, vtp.bounds, atol=1e-3)
    # Again without --overwrite: refused before any work because the mesh exists (exit 5).
    for name in ("mask.nii.gz", "surface.vtp", "snake.json", "qc.png"):
        (out / name).unlink()
    rc = main(["segment", str(image), "--out", str(out), "--mesh", "ball.stl", *init])
    err = capsys.readouterr().err
    assert rc == 5 and "ball.stl: already exists" in err
    # A new set over it (--overwrite) replaces the earlier set's mesh, which its snake.json
    # names: with another mesh, or none, the old one goes (it stayed before, beside a result
    # it did not show); a file of the user's is kept.
    assert main(["segment", str(image), "--out", str(out), "--overwrite", "--mesh", "ball.stl",
                 "-q", *init]) == 0
    (out / "notes.txt").write_text("mine")
    assert main(["segment", str(image), "--out", str(out), "--overwrite", "-q", "--mesh",
                 "b.ply", *init]) == 0
    assert sorted(os.listdir(out)) == sorted(["mask.nii.gz", "surface.vtp", "snake.json",
                                              "qc.png", "b.ply", "notes.txt"])
    assert main(["segment", str(image), "--out", str(out), "--overwrite", "-q", *init]) == 0
    assert "b.ply" not in os.listdir(out) and "notes.txt" in os.listdir(out)


@pytest.mark.parametrize("name, problem", [("ball.vtk", "must end in .stl, .obj, .ply"),
                                           ("sub/ball.stl", "without a directory"),
                                           (".stl", "must end in")])
def test_bad_mesh_names_are_usage_errors(tmp_path, rotated, capsys, name, problem):
    _, image = rotated
    rc = main(["segment", str(image), "--out", str(tmp_path / "seg"), "--mesh", name])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and problem in err and len(err.splitlines()) == 1
    assert not (tmp_path / "seg").exists()


def test_a_failed_mesh_write_leaves_no_output(tmp_path, rotated, capsys, monkeypatch):
    ph, image = rotated

    def disk_full(path, model, volume):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("segsnake.runner.write_mesh", disk_full)
    init = ["--center", *map(str, ph.init["center"]), "--radii", *map(str, ph.init["radii"])]
    rc = main(["segment", str(image), "--out", str(tmp_path / "seg"), "--mesh", "b.ply", *init])
    err = capsys.readouterr().err
    assert rc == 5 and "b.ply: cannot write (No space left on device)" in err
    assert not (tmp_path / "seg").exists()


def test_surface_vtp_holds_the_models_world_triangles_without_pyvista(tmp_path, rotated):
    # surface.vtp is built from VTK's own classes (pyvista's import cost every run 0.14 s): the
    # file must read back as the model's default mesh in world mm, the points float32 as before.
    import subprocess
    import sys

    from segsnake.config import SegmentConfig
    from segsnake.meshes import world_triangles
    from segsnake.pipeline import initial_model

    ph, image = rotated
    volume = load_volume(image)
    config = SegmentConfig(center=list(ph.init["center"]), radii=list(ph.init["radii"]))
    model = initial_model(config, volume.spacing, volume.shape)
    path = tmp_path / "surface.vtp"
    write_surface(str(path), model, volume)
    points, tris = world_triangles(model, volume)
    vtp = pv.read(path)
    assert vtp.points.dtype == np.float32
    np.testing.assert_array_equal(vtp.points, points)
    assert vtp.is_all_triangles
    np.testing.assert_array_equal(vtp.faces.reshape(-1, 4)[:, 1:], tris)
    np.testing.assert_array_equal(vtp.points, world_mesh(model, volume).points)
    # and writing it loads no pyvista (the STL/OBJ/PLY writer still does)
    code = ("import sys; from segsnake.io import load_volume; "
            "from segsnake.meshes import write_surface; "
            "from segsnake.surfaces import SphereModel; "
            f"v = load_volume({str(image)!r}); "
            "write_surface(sys.argv[1], SphereModel.ellipsoid((10, 10, 10), (4, 3, 2)), v); "
            "print('pyvista' in sys.modules)")
    run = subprocess.run([sys.executable, "-c", code, str(tmp_path / "s.vtp")],
                         capture_output=True, text=True, check=True)
    assert run.stdout.strip() == "False"


def _signed_volume(mesh) -> float:
    """The volume a closed triangle mesh encloses, positive when its triangles face outward."""
    tris = np.asarray(mesh.faces).reshape(-1, 4)[:, 1:]
    p = np.asarray(mesh.points, dtype=np.float64)
    return float(np.einsum("ij,ij->i", p[tris[:, 0]], np.cross(p[tris[:, 1]], p[tris[:, 2]]))
                 .sum() / 6)


def test_a_mirrored_grid_gives_outward_surfaces_and_a_world_start(tmp_path, capsys):
    # A LAS grid (the affine's determinant negative, as FSL's MNI templates and many DICOM
    # conversions have): the mirror once turned a --world start inside out (exit 4, "the snake
    # collapsed or turned inside out") and every written surface inward.
    import nibabel as nib

    ph = make_phantom("ball", seed=2, shape=(32, 32, 32), noise=0.05)
    affine = np.diag([-1.0, 1.0, 1.0, 1.0])
    affine[0, 3] = 31.0
    nib.save(nib.Nifti1Image(ph.image, affine), tmp_path / "las.nii.gz")
    nib.save(nib.Nifti1Image(ph.truth.astype(np.uint8), affine), tmp_path / "truth.nii.gz")
    centre = affine[:3, :3] @ np.asarray(ph.init["center"], float) + affine[:3, 3]
    rc = main(["segment", str(tmp_path / "las.nii.gz"), "--out", str(tmp_path / "seg"), "-q",
               "--world", "--center", *map(str, centre), "--radii", *map(str, ph.init["radii"]),
               "--truth", str(tmp_path / "truth.nii.gz"), "--mesh", "ball.stl"])
    assert rc == 0, capsys.readouterr().err
    summary = __import__("json").loads((tmp_path / "seg" / "snake.json").read_text())["summary"]
    assert summary["dice"] >= 0.97
    for name in ("surface.vtp", "ball.stl"):
        mesh = pv.read(tmp_path / "seg" / name)
        assert _signed_volume(mesh) == pytest.approx(summary["volume_mm3"], rel=0.02), name
