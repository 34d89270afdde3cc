"""Truth label maps (issue 17, item 4): ``evaluate --label N``, ``segment --truth-label N``.

A multi-label atlas used as a truth mask compares one structure with the whole atlas (Dice near
0, silently); a label selects the structure, and a truth holding more than two values without one
gets a warning. (The batch key ``truth_label`` is tested in test_batch.py.)
"""

from __future__ import annotations

import json

import nibabel as nib
import numpy as np
import pytest

from segsnake.cli import main
from segsnake.commands.phantom import write_phantom
from segsnake.errors import InputError
from segsnake.labels import describe_values, truth_foreground
from segsnake.phantoms import make_phantom


@pytest.fixture(scope="module")
def atlas(tmp_path_factory):
    """A small noisy ball, its truth, and a label map: the ball is label 3, a corner cube 7."""
    d = tmp_path_factory.mktemp("atlas")
    ph = make_phantom("ball", seed=3, shape=(24, 24, 24), noise=0.1)
    write_phantom(ph, d)
    labels = ph.truth.astype(np.int16) * 3
    labels[:6, :6, :6] = 7
    nib.save(nib.Nifti1Image(labels, ph.affine), d / "atlas.nii.gz")
    return ph, d


def test_truth_foreground():
    data = np.array([0, 3, 3, 7, 0, 12], dtype=np.float32)
    mask, values = truth_foreground(data, 3, "a.nii")
    assert mask.tolist() == [False, True, True, False, False, False] and values is None
    mask, values = truth_foreground(data, None, "a.nii")
    assert mask.tolist() == [False, True, True, True, False, True] and values.tolist() == [3, 7, 12]
    # a plain mask, whatever its foreground value, is not a label map
    assert truth_foreground(np.array([0, 255, 255.0]), None, "m.nii")[1] is None
    assert truth_foreground(np.zeros(4), None, "m.nii")[1] is None
    with pytest.raises(InputError, match=r"^a.nii: no voxel has label 5; its non-zero values are "
                                         r"3, 7, 12$"):
        truth_foreground(data, 5, "a.nii")
    with pytest.raises(InputError, match="it is empty"):
        truth_foreground(np.zeros(3), 1, "e.nii")
    assert describe_values(np.arange(1, 117)) == "1, 2, 3, 4, 5, 6, ..., 116"


def test_evaluate_label(atlas, capsys):
    ph, d = atlas
    truth, labels = str(d / "truth.nii.gz"), str(d / "atlas.nii.gz")
    assert main(["evaluate", truth, labels, "--label", "3", "--json"]) == 0
    cap = capsys.readouterr()
    record = json.loads(cap.out)
    assert record["dice"] == 1.0 and record["label"] == 3 and record["warnings"] == []
    assert cap.err == ""
    # without a label: the whole atlas is the truth, and a warning says so
    assert main(["evaluate", truth, labels, "--json"]) == 0
    cap = capsys.readouterr()
    record = json.loads(cap.out)
    assert record["dice"] < 1.0 and len(record["warnings"]) == 1
    assert cap.err == f"segsnake evaluate: warning: {record['warnings'][0]}\n"
    assert "2 different non-zero values (3, 7)" in cap.err and "--label N" in cap.err
    # a label the atlas does not hold
    assert main(["evaluate", truth, labels, "--label", "4"]) == 3
    cap = capsys.readouterr()
    assert cap.out == "" and cap.err == (f"segsnake evaluate: error: {labels}: no voxel has label 4;"
                                         " its non-zero values are 3, 7\n")


def test_segment_truth_label(atlas, tmp_path, capsys):
    ph, d = atlas
    init = ["--center", *map(str, ph.init["center"]), "--radii", *map(str, ph.init["radii"])]
    image = str(d / "image.nii.gz")
    assert main(["segment", image, "--out", str(tmp_path / "plain"), "--truth",
                 str(d / "truth.nii.gz"), "--json", *init]) == 0
    plain = json.loads(capsys.readouterr().out)
    assert main(["segment", image, "--out", str(tmp_path / "label"), "--truth",
                 str(d / "atlas.nii.gz"), "--truth-label", "3", "--json", *init]) == 0
    cap = capsys.readouterr()
    labelled = json.loads(cap.out)
    assert cap.err == "" and labelled["warnings"] == [] and labelled["truth_label"] == 3
    assert labelled["dice"] == plain["dice"] > 0.9  # label 3 is exactly the plain truth
    stored = json.loads((tmp_path / "label" / "snake.json").read_text())["summary"]
    assert stored["dice"] == labelled["dice"] and stored["truth_label"] == 3

    # no label on an atlas: the warning, on stderr even with --quiet, and in snake.json
    assert main(["segment", image, "--out", str(tmp_path / "atlas"), "--truth",
                 str(d / "atlas.nii.gz"), "--quiet", *init]) == 0
    cap = capsys.readouterr()
    assert cap.out == ""
    assert cap.err.startswith(f"segsnake segment: warning: {d / 'atlas.nii.gz'}: holds 2 "
                              "different non-zero values (3, 7)")
    assert "--truth-label N" in cap.err
    stored = json.loads((tmp_path / "atlas" / "snake.json").read_text())["summary"]
    assert stored["dice"] < plain["dice"] and "label map" in stored["warnings"][0]

    # an absent label stops before any work; --truth-label without --truth is a usage error
    assert main(["segment", image, "--out", str(tmp_path / "no"), "--truth",
                 str(d / "atlas.nii.gz"), "--truth-label", "4", *init]) == 3
    assert "no voxel has label 4" in capsys.readouterr().err
    assert main(["segment", image, "--out", str(tmp_path / "no"), "--truth-label", "4",
                 *init]) == 2
    assert "--truth-label needs --truth" in capsys.readouterr().err
    assert not (tmp_path / "no").exists()
