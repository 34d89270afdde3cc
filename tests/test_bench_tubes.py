"""benchmarks/bench_tubes.py: its cases, click files and the profile comparison (no segmentation)."""

from __future__ import annotations

import csv
import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from segsnake import phantoms as P

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bench():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    spec = importlib.util.spec_from_file_location("bench_tubes", ROOT / "benchmarks" / "bench_tubes.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_cases_cover_curved_exiting_and_the_twelve_oblique_tubes(bench):
    cases = list(bench.cases(seed=3, std=50.0))
    ids = [c["id"] for c in cases]
    assert len(ids) == len(set(ids)) == 20
    assert ids[:8] == ["arch_1x1x1", "arch_0.6x0.6x2.5", "s3_1x1x1", "s3_0.6x0.6x2.5",
                       "s6_1x1x1", "s6_0.6x0.6x2.5", "exit_1x1x1", "exit_0.6x0.6x2.5"]
    assert all(c["seed"] == 3 and c["options"]["noise"] == pytest.approx(50 / 255)
               for c in cases[:8])
    # The recipes' own seed and noise (Table 7.2's std 50 on a 0/255 image) by default.
    default = list(bench.cases())[:8]
    assert all(c["seed"] == 0 and c["options"]["noise"] * 255 == pytest.approx(50.0)
               for c in default)
    assert [c["options"]["spacing"] for c in default[:2]] == [[1.0, 1.0, 1.0], [0.6, 0.6, 2.5]]
    assert list(bench.cases(std=30.0))[2]["options"]["noise"] == pytest.approx(30 / 255)
    oblique = cases[8:]
    assert [c["kind"] for c in oblique] == ["hollow-cylinder"] * 12
    assert {c["seed"] for c in oblique} == set(range(6))
    assert all(c["flags"] == ["--feature", "surface"] and c["options"]["std"] == 50.0
               for c in oblique)


def _write_profile(path: Path, prof: dict, scale: float = 1.0, order=slice(None)) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["arc_length_mm", "x_mm", "y_mm", "z_mm", "area_mm2",
                    "equivalent_diameter_mm", "min_diameter_mm", "max_diameter_mm"])
        for i in np.arange(len(prof["arc_length"]))[order]:
            w.writerow([prof["arc_length"][i], *prof["center_world"][i], prof["area"][i],
                        scale * prof["equivalent_diameter"][i], scale * prof["min_diameter"][i],
                        scale * prof["max_diameter"][i]])


def test_profile_error_against_the_truth(bench, tmp_path):
    ph = P.s_vessel(0, radius=4.0, taper=1.5, spacing=(2.0, 2.0, 2.0), noise=0.0)
    truth = P.truth_profile(ph.params, step=8.0)
    path = tmp_path / "profile.csv"
    _write_profile(path, truth)
    res = bench.profile_error(bench.read_profile(path), ph.params)
    assert res["status"] == "ok" and res["rows_compared"] == len(truth["arc_length"])
    assert res["equivalent_max_rel_error"] < 1e-5 and res["coverage"] > 0.85
    # Diameters 4 % too large, rows in reverse order (a centreline run the other way).
    _write_profile(path, truth, scale=1.04, order=slice(None, None, -1))
    res = bench.profile_error(bench.read_profile(path), ph.params)
    assert res["equivalent_max_rel_error"] == pytest.approx(0.04, abs=1e-4)
    assert res["max_max_rel_error"] == pytest.approx(0.04, abs=1e-4)
    assert res["equivalent_max_rel_error_away_from_ends"] == pytest.approx(0.04, abs=1e-4)
    assert bench.profile_error(bench.read_profile(tmp_path / "none.csv"), ph.params) == {
        "status": "no profile.csv"}


def test_written_case_has_the_click_file_and_commands(bench, tmp_path):
    case = {"id": "s3-test", "kind": "s-vessel", "seed": 1,
            "options": {"radius": 3.0, "spacing": (2.0, 2.0, 2.0)}, "flags": []}
    rec = bench.write_case(case, tmp_path)
    assert rec["image"].is_file() and rec["truth"].is_file()
    with open(rec["click"], newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["x", "y", "z", "radius"] and len(rows) == 6
    click = rec["params"]["geometry"]["click"]
    np.testing.assert_allclose(np.array(rows[1:], float)[:, :3], click["points_voxels"], atol=1e-4)
    np.testing.assert_allclose(np.array(rows[1:], float)[:, 3], click["radius_voxels"], atol=1e-4)
    cmd = bench.segment_cmd("segsnake", rec, "ends", tmp_path / "o", [], 0.0, 0)
    e = rec["ends"]
    i = cmd.index("--axis-start")
    assert cmd[i + 1:i + 4] == [str(v) for v in e["axis_start"]]
    assert cmd[cmd.index("--radius") + 1] == str(e["radius"])
    cmd = bench.segment_cmd("/x/bin/segsnake", rec, "centerline", tmp_path / "o", [], 1e-12, 0)
    assert cmd[:2] == ["/x/bin/python", str(ROOT / "benchmarks" / "perturbed_cli.py")]
    assert cmd[cmd.index("--centerline") + 1] == str(rec["click"])
