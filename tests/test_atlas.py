"""The atlas start (``segment --atlas DIR``): an image registered to an atlas' template
(:mod:`segsnake.registration`), a structure carried onto it and fitted (:mod:`segsnake.atlas`),
then refined with the fit as its prior, or returned as registered where the image holds no
boundary for it.

The phantom is a small "head": an ellipsoidal brain with a bright nucleus, a dark ventricle and
a patch of brain drawn as a label but with no boundary in the image. The subject is the same
voxels with seeded noise under a moved affine (rotated, shifted, scaled), so that the map the
registration must find is known exactly.
"""

from __future__ import annotations

import json

import nibabel as nib
import numpy as np
import pytest

from segsnake.atlas import Atlas, LabelSet, find_structure, read_atlas, structure_mask
from segsnake.cli import main
from segsnake.errors import InputError
from segsnake.registration import RegistrationError, RegistrationParams, refine_around, \
    register_affine

SEED = 11
VOXEL_MM = 2.0
SHAPE = (40, 44, 36)
NAMES = {1: "nucleus", 2: "ventricle", 3: "patch"}


def _ellipsoid(centre_mm, radii_mm) -> np.ndarray:
    grid = np.indices(SHAPE).astype(float) * VOXEL_MM
    centre = np.asarray(SHAPE) * VOXEL_MM / 2 + np.asarray(centre_mm, float)
    r = sum(((g - c) / a) ** 2 for g, c, a in zip(grid, centre, radii_mm))
    return r <= 1.0


def _head() -> tuple[np.ndarray, np.ndarray]:
    """The template's intensities and its labels (index order, 2 mm voxels)."""
    brain = _ellipsoid((0, 0, 0), (30, 34, 26))
    labels = np.zeros(SHAPE, np.int16)
    labels[_ellipsoid((10, 6, 0), (7, 9, 6))] = 1
    labels[_ellipsoid((-9, -2, 5), (5, 11, 4))] = 2
    labels[_ellipsoid((-8, -10, -10), (6, 6, 5))] = 3
    image = np.where(brain, 100.0, 0.0)
    image[labels == 1] = 170.0
    image[labels == 2] = 30.0
    return image, labels


def _moved() -> np.ndarray:
    """The subject's world from the template's: rotated 10 degrees about z and 6 about x,
    shifted (8, -6, 4) mm, scaled by 1.05."""
    a, b = np.deg2rad(10.0), np.deg2rad(6.0)
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    out = np.eye(4)
    out[:3, :3] = 1.05 * rz @ rx
    out[:3, 3] = [8.0, -6.0, 4.0]
    return out


TEMPLATE_AFFINE = np.diag([VOXEL_MM, VOXEL_MM, VOXEL_MM, 1.0])
TEMPLATE_AFFINE[:3, 3] = [-40.0, -44.0, -36.0]


@pytest.fixture(scope="module")
def atlas_case(tmp_path_factory):
    """An atlas folder and a moved, noisy subject (with the nucleus' and patch's truths)."""
    root = tmp_path_factory.mktemp("atlas")
    image, labels = _head()
    folder = root / "atlas"
    folder.mkdir()
    nib.save(nib.Nifti1Image(image.astype(np.float32), TEMPLATE_AFFINE),
             str(folder / "template.nii.gz"))
    nib.save(nib.Nifti1Image(labels, TEMPLATE_AFFINE), str(folder / "deep.nii.gz"))
    (folder / "deep.csv").write_text("".join(f"{k},{v}\n" for k, v in NAMES.items()))
    subject_affine = _moved() @ TEMPLATE_AFFINE
    noisy = image + np.random.default_rng(SEED).normal(0.0, 8.0, SHAPE)
    paths = {"atlas": folder, "image": root / "subject.nii.gz"}
    nib.save(nib.Nifti1Image(noisy.astype(np.float32), subject_affine), str(paths["image"]))
    for value, name in NAMES.items():
        paths[name] = root / f"truth_{name}.nii.gz"
        nib.save(nib.Nifti1Image((labels == value).astype(np.uint8), subject_affine),
                 str(paths[name]))
    return paths


def test_registration_finds_the_known_map_and_repeats_it():
    image, _ = _head()
    noisy = image + np.random.default_rng(SEED).normal(0.0, 8.0, SHAPE)
    moved = _moved()
    found = register_affine(noisy, moved @ TEMPLATE_AFFINE, image, TEMPLATE_AFFINE)
    # Where the map matters (the brain), the found map agrees with the true one, moved^-1.
    idx = np.argwhere(image > 0)[::50]
    world = np.c_[idx * VOXEL_MM + TEMPLATE_AFFINE[:3, 3], np.ones(len(idx))]
    subject_world = world @ moved.T
    err = np.linalg.norm((subject_world @ found.T - world)[:, :3], axis=1)
    assert err.max() < 1.0, err.max()  # (mm; a quarter of the coarse level's voxel)
    # (measured: 0.17 mm at most; the map from world coordinates alone errs by 16 mm)
    again = register_affine(noisy, moved @ TEMPLATE_AFFINE, image, TEMPLATE_AFFINE)
    np.testing.assert_array_equal(found, again)


def test_a_scan_reaching_far_below_the_head_registers_too():
    # The subject's grid runs 90 mm below the head, through a neck of soft tissue: the two
    # grids' centres lie 45 mm apart, and the head's map starts from the best of several starts.
    image, _ = _head()
    below = 45
    tall = np.zeros((SHAPE[0], SHAPE[1], SHAPE[2] + below), np.float32)
    tall[:, :, below:] = image
    idx = np.indices(tall.shape[:2]) * VOXEL_MM
    neck = np.hypot(idx[0] - 40.0, idx[1] - 44.0) < 18.0
    tall[:, :, : below + 4][neck] = np.maximum(tall[:, :, : below + 4][neck], 60.0)
    tall += np.random.default_rng(SEED).normal(0.0, 8.0, tall.shape)
    affine = TEMPLATE_AFFINE.copy()
    affine[2, 3] -= below * VOXEL_MM
    found = register_affine(tall, affine, image, TEMPLATE_AFFINE)
    idx = np.argwhere(image > 0)[::50]
    world = np.c_[idx * VOXEL_MM + TEMPLATE_AFFINE[:3, 3], np.ones(len(idx))]
    err = np.linalg.norm((world @ found.T - world)[:, :3], axis=1)
    assert err.max() < 1.0, err.max()  # (measured 0.18 mm; from the grids' centres alone 68)


def test_the_second_stage_mends_the_map_where_the_structure_lies():
    # From the true map shifted by 3 mm and turned by 2 degrees, the second stage, reading the
    # nucleus and 10 mm around it, brings the nucleus' points to a third of that.
    image, labels = _head()
    noisy = image + np.random.default_rng(SEED).normal(0.0, 8.0, SHAPE)
    moved = _moved()
    truth = np.linalg.inv(moved)
    a = np.deg2rad(2.0)
    off = np.eye(4)
    off[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    off[:3, 3] = [3.0, 0.0, 0.0]
    start = off @ truth
    nucleus = labels == 1
    found = refine_around(noisy, moved @ TEMPLATE_AFFINE, image, TEMPLATE_AFFINE, start,
                          nucleus, TEMPLATE_AFFINE)
    idx = np.argwhere(nucleus)
    world = np.c_[idx * VOXEL_MM + TEMPLATE_AFFINE[:3, 3], np.ones(len(idx))] @ moved.T

    def err(m):
        return np.linalg.norm((world @ m.T - world @ truth.T)[:, :3], axis=1).max()

    assert err(start) > 3.0
    assert err(found) < 0.4 * err(start), (err(start), err(found))  # (measured: 3.09 -> 0.75 mm)
    with pytest.raises(RegistrationError, match="empty"):
        refine_around(noisy, moved @ TEMPLATE_AFFINE, image, TEMPLATE_AFFINE, start,
                      np.zeros(SHAPE, bool), TEMPLATE_AFFINE)


def test_registration_refuses_what_it_cannot_represent():
    image, _ = _head()
    sheared = TEMPLATE_AFFINE.copy()
    sheared[0, 1] = 0.5
    with pytest.raises(RegistrationError, match="sheared"):
        register_affine(image, sheared, image, TEMPLATE_AFFINE)
    with pytest.raises(RegistrationError, match="empty"):
        register_affine(image, TEMPLATE_AFFINE, np.zeros(SHAPE), TEMPLATE_AFFINE)
    with pytest.raises(RegistrationError, match="image is empty"):
        register_affine(np.zeros(SHAPE), TEMPLATE_AFFINE, image, TEMPLATE_AFFINE)
    with pytest.raises(RegistrationError, match="needs at least 4 of them along each axis"):
        register_affine(image[:, :, 18:19], TEMPLATE_AFFINE, image, TEMPLATE_AFFINE)
    with pytest.raises(RegistrationError, match="zero or undefined voxel size"):
        register_affine(image, np.diag([0.0, 2.0, 2.0, 1.0]), image, TEMPLATE_AFFINE,
                        RegistrationParams())


def test_structures_are_found_by_name_value_set_or_click(atlas_case):
    atlas = read_atlas(str(atlas_case["atlas"]))
    assert find_structure(atlas, "deep:nucleus").values == (1,)
    assert find_structure(atlas, "ventricle").values == (2,)
    assert find_structure(atlas, "deep:3").description == "deep:patch"
    assert find_structure(atlas, "deep").values == (1, 2, 3)
    # a click at the nucleus' centre (template world), with the identity map
    centre = np.asarray(SHAPE) * VOXEL_MM / 2 + [10, 6, 0] + TEMPLATE_AFFINE[:3, 3]
    assert find_structure(atlas, None, centre, np.eye(4)).description == "deep:nucleus"
    with pytest.raises(InputError, match="no structure 'putamen'.*deep:nucleus"):
        find_structure(atlas, "putamen")
    # a name the atlas nearly has: its labels offered, not the whole list
    with pytest.raises(InputError, match=r"no structure 'nucleu'; did you mean deep:nucleus\?$"):
        find_structure(atlas, "nucleu")
    with pytest.raises(InputError, match=r"did you mean deep:ventricle\?$"):
        find_structure(atlas, "deep:ventricel")
    # several offered, joined "A, B or C"; more than six cut with how many were left out
    many = Atlas(atlas.folder, atlas.template, atlas.template_affine, (LabelSet(
        "big", "big.nii.gz", np.eye(4), {v: f"lobule-{v}" for v in range(1, 10)}),))
    with pytest.raises(InputError, match=r"did you mean big:lobule-1, big:lobule-2, "
                                         r"big:lobule-3, big:lobule-4, big:lobule-5 or "
                                         r"big:lobule-6 \(or 3 more like it\)\?$"):
        find_structure(many, "lobule")
    with pytest.raises(InputError, match="the atlas has big:lobule-1"):  # ("lh": too short)
        find_structure(many, "lh")
    with pytest.raises(InputError, match="no label set 'aseg'"):
        find_structure(atlas, "aseg:nucleus")
    with pytest.raises(InputError, match="on no label"):
        find_structure(atlas, None, TEMPLATE_AFFINE[:3, 3], np.eye(4))


def test_the_structure_lands_on_another_grid_through_the_map(atlas_case):
    atlas = read_atlas(str(atlas_case["atlas"]))
    nucleus = find_structure(atlas, "nucleus")
    _, labels = _head()
    same = structure_mask(nucleus, SHAPE, TEMPLATE_AFFINE, np.eye(4))
    np.testing.assert_array_equal(same, labels == 1)
    # a subject grid shifted by (2, -1, 3) voxels in the world: the mask moves with it
    shifted = TEMPLATE_AFFINE.copy()
    shifted[:3, 3] += VOXEL_MM * np.array([2, -1, 3])
    moved = structure_mask(nucleus, SHAPE, shifted, np.eye(4))
    np.testing.assert_array_equal(moved, np.roll(labels == 1, (-2, 1, -3), axis=(0, 1, 2)))


def test_the_structure_lands_where_it_lies_on_a_turned_anisotropic_grid(atlas_case):
    # The image's grid: 1.5 x 1.5 x 3 mm voxels, turned 25 degrees about z and 10 about x, its
    # box covering only part of the head (the nucleus cut by a face). The mask must be the
    # nucleus' analytic ellipsoid sampled at the image's voxel centres, where they lie in it.
    atlas = read_atlas(str(atlas_case["atlas"]))
    nucleus = find_structure(atlas, "nucleus")
    a, b = np.deg2rad(25.0), np.deg2rad(10.0)
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    grid = np.eye(4)
    grid[:3, :3] = rz @ rx @ np.diag([1.5, 1.5, 3.0])
    centre = np.asarray(SHAPE) * VOXEL_MM / 2 + [10, 6, 0] + TEMPLATE_AFFINE[:3, 3]
    shape = (30, 30, 4)
    grid[:3, 3] = centre - grid[:3, :3] @ [15.0, 15.0, 2.0]  # (the nucleus' top cut off)
    mask = structure_mask(nucleus, shape, grid, np.eye(4))
    world = np.c_[np.indices(shape).reshape(3, -1).T, np.ones(np.prod(shape))] @ grid.T
    # the nucleus as drawn: voxel centres of the 2 mm grid within the ellipsoid; the oracle
    # reads the analytic ellipsoid at the image's centres (its drawn staircase differs by a
    # voxel at most)
    r = sum(((world[:, k] - centre[k]) / ax) ** 2 for k, ax in enumerate((7, 9, 6)))
    oracle = (r <= 1.0).reshape(shape)
    assert oracle.any() and not oracle.all()
    overlap = 2 * (mask & oracle).sum() / (mask.sum() + oracle.sum())
    assert overlap > 0.9, overlap  # (measured 0.952)


@pytest.mark.parametrize("damage, message", [
    ("no template", "needs template.nii.gz"),
    ("no names", "needs its names in deep.csv"),
    ("bad names", "deep.csv:2: expected 'value,name'"),
    ("latin-1 names", "deep.csv: not a UTF-8 CSV"),
    ("sheared labels", "deep.nii.gz: its affine is sheared"),
])
def test_a_damaged_atlas_folder_is_refused_with_its_file(atlas_case, tmp_path, damage, message):
    import shutil

    folder = tmp_path / "atlas"
    shutil.copytree(atlas_case["atlas"], folder)
    if damage == "no template":
        (folder / "template.nii.gz").unlink()
    elif damage == "no names":
        (folder / "deep.csv").unlink()
    elif damage == "bad names":
        (folder / "deep.csv").write_text("1,nucleus\nthree,patch\n")
    elif damage == "latin-1 names":
        (folder / "deep.csv").write_bytes("1,noyau caud\xe9\n".encode("latin-1"))
    else:
        sheared = TEMPLATE_AFFINE.copy()
        sheared[0, 1] = 0.5
        nib.save(nib.Nifti1Image(_head()[1], sheared), str(folder / "deep.nii.gz"))
    with pytest.raises(InputError, match=message):
        read_atlas(str(folder))


def test_a_label_set_is_read_when_asked_for_and_a_damaged_one_says_so(atlas_case, tmp_path):
    import shutil

    folder = tmp_path / "atlas"
    shutil.copytree(atlas_case["atlas"], folder)
    whole = (folder / "deep.nii.gz").read_bytes()
    (folder / "deep.nii.gz").write_bytes(whole[: len(whole) // 2])  # (its header intact)
    atlas = read_atlas(str(folder))  # (the header only: the set's names are there)
    structure = find_structure(atlas, "nucleus")
    with pytest.raises(InputError, match="deep.nii.gz: cannot read"):
        structure.voxels


def _segment(capsys, *args) -> tuple[int, dict, str]:
    rc = main(["segment", *map(str, args), "--json", "--quiet"])
    cap = capsys.readouterr()
    return rc, (json.loads(cap.out) if cap.out.strip() else {}), cap.err


def test_segment_from_the_atlas_finds_the_moved_nucleus(atlas_case, tmp_path, capsys):
    rc, out, err = _segment(capsys, atlas_case["image"], "--out", tmp_path / "seg", "--atlas",
                            atlas_case["atlas"], "--structure", "deep:nucleus", "--truth",
                            atlas_case["nucleus"])
    assert rc == 0, err
    assert out["dice"] > 0.9, out  # (measured 0.985)
    assert not out["warnings"], out["warnings"]
    saved = json.loads((tmp_path / "seg" / "snake.json").read_text())
    start = saved["settings"]["atlas_start"]
    assert start["structure"] == "deep:nucleus"
    # the maps recorded are the registration's, the inverse of the subject's move: the head's
    # to 1 mm at the corners of the brain's box, the refined one at the corners of the
    # nucleus' (the second stage holds where the structure is)
    middle = np.asarray(SHAPE) * VOXEL_MM / 2 + TEMPLATE_AFFINE[:3, 3]
    corners = [2 * np.subtract(c, 0.5) for c in np.ndindex(2, 2, 2)]
    for key, centre, half in (("head_to_template", middle, (30, 34, 26)),
                              ("image_to_template", middle + [10, 6, 0], (7, 9, 6))):
        found = np.asarray(start[key])
        for c in corners:
            p = np.r_[centre + c * half, 1.0]
            assert np.linalg.norm(found @ (_moved() @ p) - p) < 1.0, (key, p)


def test_a_click_names_the_structure_under_it(atlas_case, tmp_path, capsys):
    # The nucleus' centre, voxel (25, 25, 18) of the subject (its voxels are the template's).
    rc, out, err = _segment(capsys, atlas_case["image"], "--out", tmp_path / "seg", "--atlas",
                            atlas_case["atlas"], "--center", 25, 25, 18, "--truth",
                            atlas_case["nucleus"])
    assert rc == 0, err
    saved = json.loads((tmp_path / "seg" / "snake.json").read_text())
    assert saved["settings"]["atlas_start"]["structure"] == "deep:nucleus"
    assert out["dice"] > 0.9, out


def test_a_structure_the_image_does_not_show_is_returned_as_registered(atlas_case, tmp_path,
                                                                        capsys):
    # The patch is brain like its surroundings: no boundary to refine on. The result is the
    # atlas' patch as registered, with a warning that says so (exit 0).
    rc, out, err = _segment(capsys, atlas_case["image"], "--out", tmp_path / "seg", "--atlas",
                            atlas_case["atlas"], "--structure", "patch", "--truth",
                            atlas_case["patch"])
    assert rc == 0, err
    assert any("not refined" in w for w in out["warnings"]), out["warnings"]
    assert out["dice"] > 0.85, out  # (measured 0.965: the registration's placement alone)
    assert out["energy"] is None

    def strict(constant):
        raise ValueError(f"snake.json holds {constant}, which JSON does not")

    saved = json.loads((tmp_path / "seg" / "snake.json").read_text(), parse_constant=strict)
    assert saved["summary"]["energy"] is None
    assert (saved["settings"]["prior_weight"], saved["settings"]["prior_space"]) == \
        (5.0, "similarity")  # (an atlas' defaults, as used)


def test_a_set_of_separate_structures_warns_that_the_snake_took_one(atlas_case, tmp_path,
                                                                      capsys):
    # The whole set "deep" is three separate ellipsoids: one closed surface follows the largest,
    # and the run says how much it left out.
    rc, out, err = _segment(capsys, atlas_case["image"], "--out", tmp_path / "seg", "--atlas",
                            atlas_case["atlas"], "--structure", "deep")
    assert rc == 0, err
    pieces = [w for w in out["warnings"] if "lands on the image in 3 pieces" in w]
    assert pieces and "name one structure" in pieces[0], out["warnings"]


def test_a_label_named_but_not_drawn_is_refused_naming_its_file(atlas_case, tmp_path, capsys):
    import shutil

    folder = tmp_path / "atlas"
    shutil.copytree(atlas_case["atlas"], folder)
    (folder / "deep.csv").write_text("1,nucleus\n2,ventricle\n3,patch\n4,putamen\n")
    rc = main(["segment", str(atlas_case["image"]), "--out", str(tmp_path / "seg"), "--atlas",
               str(folder), "--structure", "putamen"])
    err = capsys.readouterr().err
    assert rc == 3, err
    assert "deep.nii.gz: deep:putamen is named in deep.csv but drawn on no voxel" in err


@pytest.mark.parametrize("extra, code, message", [
    (["--structure", "nucleus"], 2, "structure names a structure of an atlas"),
    (["--atlas", "ATLAS", "--structure", "nucleus", "--center", "1", "2", "3"], 2,
     "give one or the other"),
    (["--atlas", "ATLAS", "--m1", "9", "--structure", "nucleus"], 2, "give both or neither"),
    (["--atlas", "ATLAS"], 2, "atlas needs its structure named"),
    (["--atlas", "ATLAS", "--prior-modes", "2", "--structure", "nucleus"], 2,
     "the atlas' structure has no modes"),
    (["--atlas", "ATLAS", "--structure", "nucleus", "--out", "ATLAS"], 5,
     "--out lies in the atlas folder"),
    (["--atlas", "ATLAS", "--structure", "nucleus", "--init", "x.json"], 2,
     "atlas starts from the atlas' structure"),
    (["--atlas", "ATLAS", "--structure", "putamen"], 3, "no structure 'putamen'"),
    (["--atlas", "NOWHERE", "--structure", "nucleus"], 3, "no such atlas folder"),
])
def test_atlas_options_that_cannot_work_are_refused(atlas_case, tmp_path, capsys, extra, code,
                                                     message):
    extra = [str(atlas_case["atlas"]) if e == "ATLAS" else
             str(tmp_path / "nowhere") if e == "NOWHERE" else e for e in extra]
    out = [] if "--out" in extra else ["--out", str(tmp_path / "seg")]
    rc = main(["segment", str(atlas_case["image"]), *out, *extra])
    err = capsys.readouterr().err
    assert rc == code, err
    assert message in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "seg" / "mask.nii.gz").exists()
