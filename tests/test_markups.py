"""3D Slicer markups files as ``--center``/``--seed-point``/``--axis-start``/``--axis-end`` (issue 17,
item 5): LPS and RAS clicks give the same start as the equivalent ``--world`` numbers; a bad file
is one line naming it and a documented exit code."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest

from segsnake.cli import main
from segsnake.commands.phantom import write_phantom
from segsnake.config import SegmentConfig, load_segment_config
from segsnake.errors import InputError
from segsnake.markups import read_markups, resolve_markups
from segsnake.phantoms import make_phantom
from segsnake.surfaces import model_from_dict


def write_markups(path: Path, points, system: str = "LPS", kind: str = "Fiducial",
                  extra_points=()) -> Path:
    """A markups file as Slicer writes it; ``points`` are RAS and written in ``system``."""
    flip = np.array([-1.0, -1.0, 1.0]) if system == "LPS" else np.ones(3)
    cps = [{"id": str(n + 1), "label": f"F-{n + 1}", "position": list(np.asarray(p) * flip),
            "positionStatus": "defined"} for n, p in enumerate(points)]
    doc = {"@schema": "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/"
                      "Markups/Resources/Schema/markups-schema-v1.0.3.json#",
           "markups": [{"type": kind, "coordinateSystem": system, "coordinateUnits": "mm",
                        "controlPoints": cps + list(extra_points)}]}
    path.write_text(json.dumps(doc))
    return path


@pytest.fixture(scope="module")
def rotated(tmp_path_factory):
    """A small ball on a rotated, anisotropic grid (world != scaled index) and its affine."""
    d = tmp_path_factory.mktemp("rot")
    ph = make_phantom("ball", seed=5, shape=(24, 24, 16), spacing=(1.0, 1.0, 1.5), noise=0.1,
                      grid_rotation=(20.0, -10.0, 30.0))
    write_phantom(ph, d)
    image = d / "image.nii.gz"
    return ph, image, nib.load(image).affine


def run(args, capsys) -> tuple[int, str]:
    rc = main(["segment", *map(str, args)])
    return rc, capsys.readouterr().err


def initial_points(out: Path) -> np.ndarray:
    record = json.loads((out / "snake.json").read_text())
    return model_from_dict(record["initial_model"]).control_points()


def test_read_markups_lps_and_ras(tmp_path):
    ras = np.array([[10.0, -20.0, 30.0], [1.5, 2.5, -3.5]])
    undefined = {"id": "9", "position": [0, 0, 0], "positionStatus": "undefined"}
    for system in ("LPS", "RAS"):
        p = write_markups(tmp_path / f"{system}.mrk.json", ras, system, extra_points=[undefined])
        assert np.allclose(read_markups(str(p)), ras, atol=0)
    # The schema's default coordinate system is LPS.
    doc = {"markups": [{"type": "Fiducial", "controlPoints": [{"position": [1, 2, 3]}]}]}
    (tmp_path / "default.mrk.json").write_text(json.dumps(doc))
    assert np.allclose(read_markups(str(tmp_path / "default.mrk.json")), [[-1, -2, 3]])


def test_markups_click_gives_the_world_start(rotated, tmp_path, capsys):
    """LPS and RAS markups clicks start exactly where the same --world numbers (and the same voxel
    indices without --world) start."""
    ph, image, affine = rotated
    ijk = np.asarray(ph.init["center"], dtype=float)
    world = affine[:3, :3] @ ijk + affine[:3, 3]
    common = ["--quiet", "--max-iter", "2"]
    rc, err = run([image, "--out", tmp_path / "w", *common, "--world", "--center", *world,
                   "--radii", 4, 4, 4], capsys)
    assert rc == 0, err
    reference = initial_points(tmp_path / "w")
    for system in ("LPS", "RAS"):
        click = write_markups(tmp_path / f"click-{system}.mrk.json", [world], system)
        rc, err = run([image, "--out", tmp_path / system, *common, "--world", "--center", click,
                       "--radii", 4, 4, 4], capsys)
        assert rc == 0, err
        assert np.allclose(initial_points(tmp_path / system), reference, atol=1e-9)
    # Without --world the click is converted to voxel indices: the same as typing them.
    radii = [4 / s for s in (1.0, 1.0, 1.5)]
    rc, err = run([image, "--out", tmp_path / "v", *common, "--center", *ijk, "--radii", *radii],
                  capsys)
    assert rc == 0, err
    rc, err = run([image, "--out", tmp_path / "vm", *common, "--center",
                   tmp_path / "click-LPS.mrk.json", "--radii", *radii], capsys)
    assert rc == 0, err
    assert np.allclose(initial_points(tmp_path / "vm"), initial_points(tmp_path / "v"), atol=1e-9)


def test_axis_from_a_line_markup(rotated, tmp_path):
    """--axis-start LINE.mrk.json with two points = --axis-start/--axis-end with one each = the
    voxel indices typed, and with --world the world numbers."""
    _, _, affine = rotated
    a, b = np.array([12.0, 12.0, 3.0]), np.array([12.0, 12.0, 12.0])
    wa, wb = (affine[:3, :3] @ p + affine[:3, 3] for p in (a, b))

    def to_index(xyz):
        return np.linalg.solve(affine[:3, :3], (np.asarray(xyz) - affine[:3, 3]).T).T

    line = write_markups(tmp_path / "axis.mrk.json", [wa, wb], "LPS", kind="Line")
    start = write_markups(tmp_path / "start.mrk.json", [wa], "RAS")
    end = write_markups(tmp_path / "end.mrk.json", [wb], "LPS")
    base = SegmentConfig(shape="cylinder", radius=3.0)
    for given in ({"axis_start": str(line)}, {"axis_start": str(start), "axis_end": str(end)}):
        for world, (ea, eb) in ((False, (a, b)), (True, (wa, wb))):
            config = resolve_markups(dataclasses.replace(base, world=world, **given), to_index)
            assert np.allclose(config.axis_start, ea, atol=1e-9)
            assert np.allclose(config.axis_end, eb, atol=1e-9)


def _missing(d: Path) -> Path:
    return d / "nowhere.mrk.json"


def _not_json(d: Path) -> Path:
    (d / "bad.mrk.json").write_text("{not json")
    return d / "bad.mrk.json"


def _not_markups(d: Path) -> Path:
    (d / "other.json").write_text(json.dumps({"format": "segsnake-result"}))
    return d / "other.json"


def _empty(d: Path) -> Path:
    return write_markups(d / "empty.mrk.json", [])


def _two_points(d: Path) -> Path:
    return write_markups(d / "two.mrk.json", [[0, 0, 0], [1, 1, 1]])


def _bad_system(d: Path) -> Path:
    p = write_markups(d / "ijk.mrk.json", [[0, 0, 0]])
    doc = json.loads(p.read_text())
    doc["markups"][0]["coordinateSystem"] = "IJK"
    p.write_text(json.dumps(doc))
    return p


def _bad_position(d: Path) -> Path:
    p = write_markups(d / "pos.mrk.json", [[0, 0, 0]])
    doc = json.loads(p.read_text())
    doc["markups"][0]["controlPoints"][0]["position"] = [1, "x"]
    p.write_text(json.dumps(doc))
    return p


BAD = [
    ("missing", _missing, 3, "no such markups file"),
    ("not JSON", _not_json, 3, "JSON error"),
    ("not markups", _not_markups, 3, "not a 3D Slicer markups file"),
    ("no point", _empty, 3, "no control point"),
    ("two points for --center", _two_points, 3, "--center takes a markups file with one point"),
    ("coordinate system", _bad_system, 3, "coordinateSystem 'IJK'"),
    ("position", _bad_position, 3, "position must be 3 finite numbers"),
]


@pytest.mark.parametrize("name,make,code,words", BAD, ids=[b[0] for b in BAD])
def test_bad_markups(rotated, tmp_path, capsys, name, make, code, words):
    _, image, _ = rotated
    path = make(tmp_path)
    out = tmp_path / "out"
    rc, err = run([image, "--out", out, "--quiet", "--center", path, "--radii", 4, 4, 4], capsys)
    assert rc == code, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"segsnake segment: error: {path}: "), err
    assert words in lines[0], err
    assert not out.exists()


def test_axis_line_and_axis_end_together(rotated, tmp_path, capsys):
    _, image, _ = rotated
    line = write_markups(tmp_path / "axis.mrk.json", [[0, 0, 0], [0, 0, 5]], kind="Line")
    rc, err = run([image, "--out", tmp_path / "o", "--quiet", "--shape", "cylinder",
                   "--axis-start", line, "--axis-end", 1, 2, 3, "--radius", 3], capsys)
    assert rc == 2 and str(line) in err and len(err.strip().splitlines()) == 1, err


def test_position_flag_takes_three_numbers_or_one_file(rotated, tmp_path, capsys):
    _, image, _ = rotated
    rc, err = run([image, "--out", tmp_path / "o", "--quiet", "--center", 1, 2,
                   "--radii", 4, 4, 4], capsys)
    assert rc == 2 and "--center takes three numbers" in err, err
    assert len(err.strip().splitlines()) == 1


def test_yaml_markups_path_is_relative_to_the_yaml(tmp_path):
    (tmp_path / "run.yaml").write_text("center: clicks/c.mrk.json\nradii: [3, 3, 3]\n")
    config = load_segment_config(tmp_path / "run.yaml")
    assert config.center == str(tmp_path / "clicks" / "c.mrk.json")


def test_read_markups_errors_name_the_file(tmp_path):
    with pytest.raises(InputError, match=r"^.*empty\.mrk\.json: the markups file holds no"):
        read_markups(str(_empty(tmp_path)))


def test_batch_lists_missing_markups_files_before_anything_runs(rotated, tmp_path, capsys):
    """A case's position given as a markups file is one of the batch's inputs: checked up front
    (exit 3, with its line, relative to the YAML file); a present one passes validation."""
    from segsnake.batch import load_batch

    _, image, _ = rotated
    (tmp_path / "here.mrk.json").write_text("{}")
    path = tmp_path / "runs.yaml"
    path.write_text(f"output_dir: out\ndefaults:\n  radii: [4, 4, 4]\ncases:\n"
                    f"  - name: a\n    image: {image}\n    center: here.mrk.json\n"
                    f"  - name: b\n    image: {image}\n    center: clicks/nope.mrk.json\n",
                    encoding="utf-8")
    assert main(["batch", str(path)]) == 3
    err = capsys.readouterr().err.splitlines()
    assert err == [f"segsnake batch: error: {path}: 1 input file of the batch cannot be read "
                   "(nothing was run):",
                   f"  {path}:10:5: center {tmp_path / 'clicks' / 'nope.mrk.json'}: no such file"]
    assert not (tmp_path / "out").exists()
    assert load_batch(path, check_files=False).cases[0].config.center == str(tmp_path / "here.mrk.json")
