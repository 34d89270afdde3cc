"""SegmentConfig validation and YAML loading: every error names the file, the line and the problem."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from segsnake.cli import main
from segsnake.config import (
    LineDict,
    SegmentConfig,
    load_segment_config,
    load_yaml,
)
from segsnake.errors import ConfigError


def write(tmp_path: Path, text: str, name: str = "c.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def config_error(path: Path) -> str:
    with pytest.raises(ConfigError) as info:
        load_segment_config(path)
    message = str(info.value)
    assert "\n" not in message
    return message


# -- defaults and round trips ------------------------------------------------------------------


def test_defaults_are_the_documented_ones():
    c = SegmentConfig()
    assert (c.shape, c.feature, c.threshold, c.max_iter, c.tol) == ("sphere", "edge", "auto", 300, 1e-6)
    assert (c.coarse_to_fine, c.prior_weight, c.prior_space, c.nan, c.polarity, c.world) == (
        True, None, None, "refuse", "auto", False)  # (the prior's: by its kind)
    assert c.prior_used() == (1.0, "affine")
    assert c.replace(atlas="atlas", structure="s").prior_used() == (5.0, "similarity")
    assert c.replace(atlas="atlas", structure="s", prior_weight=2,
                     prior_space="rigid").prior_used() == (2.0, "rigid")
    assert c.m1 is c.m2 is c.scale is c.center is c.volume is None
    assert c.mesh is None  # no extra surface file unless asked
    assert c.energy == "auto"  # pipeline.region_energy decides
    assert c.init is None  # a new initial shape unless a saved snake is given
    assert c.prior_modes == 0  # a shape-model prior uses no modes unless asked
    assert c.centerline is None  # a cylinder from its axis end points unless a centerline
    assert c.atlas is c.structure is None  # no atlas start unless a folder is given
    assert len(SegmentConfig.keys()) == 29


def test_to_dict_round_trip_and_normalisation():
    c = SegmentConfig.from_mapping({"shape": "cylinder", "axis_start": [0, 0, 1], "axis_end": [0, 0, 9],
                                    "radius": 3, "m1": 8.0, "threshold": "0.25", "max-iter": 50})
    # ints become floats in vectors, 8.0 becomes the int 8, "0.25" the float 0.25, - reads as _
    assert c.axis_start == [0.0, 0.0, 1.0] and isinstance(c.axis_start[0], float)
    assert c.m1 == 8 and isinstance(c.m1, int)
    assert c.threshold == 0.25 and c.max_iter == 50 and c.radius == 3.0
    assert SegmentConfig.from_mapping(c.to_dict()) == c


def test_replace_precedence_flag_over_yaml_over_default(tmp_path):
    path = write(tmp_path, "m1: 8\nscale: 1.5\nfeature: surface\n")
    from_yaml = load_segment_config(path)
    final = from_yaml.replace(m1=12, scale=None, polarity="dark")  # scale flag not given
    assert (final.m1, final.scale, final.feature, final.polarity) == (12, 1.5, "surface", "dark")
    assert final.m2 is None and final.max_iter == 300  # untouched defaults
    assert from_yaml.m1 == 8  # replace returns a copy
    with pytest.raises(ConfigError, match=r"m2: must be >= 4, got 2"):
        from_yaml.replace(m2=2)
    with pytest.raises(ConfigError, match=r"unknown option 'polarit' \(did you mean 'polarity'\?\)"):
        from_yaml.replace(polarit="dark")


def test_empty_file_gives_defaults_and_prior_is_relative_to_the_file(tmp_path):
    assert load_segment_config(write(tmp_path, "")) == SegmentConfig()
    sub = tmp_path / "cfg"
    sub.mkdir()
    c = load_segment_config(write(sub, "prior: shapes/ref.json\nprior_weight: 0.5\n"))
    assert c.prior == str(sub / "shapes" / "ref.json")
    assert c.prior_weight == 0.5


def test_yaml_extras_exponent_floats_anchors_and_merge_keys(tmp_path):
    # PyYAML alone reads "1e-5" as a string; our loader reads it as a float.
    path = write(tmp_path, "base: &b {m1: 6, m2: 7}\ncase:\n  <<: *b\n  tol: 1e-5\n  m2: 9\n")
    data = load_yaml(path)
    assert data["case"] == {"m1": 6, "m2": 9, "tol": 1e-5}
    assert isinstance(data["case"]["tol"], float)
    assert isinstance(data["case"], LineDict) and data["case"].key_marks["tol"] == (4, 3)


# -- errors ---------------------------------------------------------------------------------------


def test_yaml_syntax_error_has_line_and_column(tmp_path):
    msg = config_error(write(tmp_path, "shape: sphere\nm1: 8\n  m2: 9\n"))
    assert msg.startswith(f"{tmp_path / 'c.yaml'}:3:5: YAML syntax error")
    msg = config_error(write(tmp_path, "center: [1, 2, 3\nm1: 8\n"))
    assert msg.endswith(":2:3: YAML syntax error: expected ',' or ']', but got ':' "
                        "(while parsing a flow sequence)")


def test_yaml_syntax_error_exit_2_through_the_cli(tmp_path, capsys):
    path = write(tmp_path, "defaults:\n  m1: 8\ncases:\n  - image: a.nii\n    name: [x\n", "runs.yaml")
    assert main(["batch", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"segsnake batch: error: {path}:6:1: YAML syntax error")
    assert len(err.splitlines()) == 1
    assert not (tmp_path / "runs-results").exists()  # nothing ran


def test_duplicate_key_is_refused_with_both_lines(tmp_path):
    msg = config_error(write(tmp_path, "m1: 8\nshape: sphere\nm1: 9\n"))
    assert ":3:1:" in msg and "duplicate key 'm1' (first given at line 1)" in msg


@pytest.mark.parametrize("key, expected", [
    ("maxiter", "max_iter"), ("polarty", "polarity"), ("radi", "radii"), ("corse_to_fine", "coarse_to_fine"),
    ("prior_wieght", "prior_weight"), ("seedpoint", "seed_point"),
])
def test_unknown_key_suggests_the_closest(tmp_path, key, expected):
    msg = config_error(write(tmp_path, f"shape: sphere\n\n{key}: 1\n"))
    assert msg == f"{tmp_path / 'c.yaml'}:3:1: unknown option {key!r} (did you mean {expected!r}?)"


def test_unknown_key_without_close_match_has_no_suggestion(tmp_path):
    msg = config_error(write(tmp_path, "zzzqqq: 1\n"))
    assert msg.endswith(":1:1: unknown option 'zzzqqq'")


@pytest.mark.parametrize("line, fragment", [
    ("m1: 3", "m1: must be >= 4, got 3"),
    ("m2: 201", "m2: must be <= 200, got 201"),
    ("m1: 8.5", "m1: must be an integer, got 8.5"),
    ("m1: eight", "m1: must be an integer, got 'eight' (a string)"),
    ("max_iter: 0", "max_iter: must be >= 1, got 0"),
    ("tol: 0", "tol: must be > 0, got 0"),
    ("tol: -1e-3", "tol: must be > 0, got -0.001"),
    ("radius: -2", "radius: must be > 0, got -2"),
    ("scale: .nan", "scale: must be a finite number, got nan"),
    ("radii: [4, 0, 4]", "radii: must be 3 numbers > 0, got [4.0, 0.0, 4.0]"),
    ("center: [1, 2]", "center: must be a list of 3 numbers [x, y, z], got a list of 2"),
    ("seed_point: [1, a, 2]", "seed_point: must be a list of 3 numbers"),
    ("world: 1", "world: must be true or false, got 1"),
    ("coarse_to_fine: 'no'", "coarse_to_fine: must be true or false, got 'no' (a string)"),
    ("shape: sphre", "shape: must be one of sphere, cylinder; got 'sphre' (a string) (did you mean 'sphere'?)"),
    ("nan: fil", "nan: must be one of refuse, fill; got 'fil' (a string) (did you mean 'fill'?)"),
    ("prior_space: kendall", "prior_space: must be one of affine, linear, similarity, rigid, scaling, translation"),
    ("threshold: high", "threshold: must be 'auto' or a number, got 'high'"),
    ("prior_weight: -0.5", "prior_weight: must be >= 0, got -0.5"),
    ("volume: -1", "volume: must be >= 0, got -1"),
    ("prior: 3", "prior: must be a file path, got 3"),
    ("feature: [edge]", "feature: must be one of edge, surface; got a list of 1"),
])
def test_wrong_types_and_ranges_are_named_with_the_line(tmp_path, line, fragment):
    msg = config_error(write(tmp_path, f"# a comment\nshape: sphere\n{line}\n"
                                       if not line.startswith("shape") else f"# a comment\n\n{line}\n"))
    assert msg.startswith(f"{tmp_path / 'c.yaml'}:3:1: ")
    assert fragment in msg


def test_consistency_error_points_at_the_key(tmp_path):
    msg = config_error(write(tmp_path, "shape: cylinder\naxis_start: [1, 2, 3]\naxis_end: [1, 2, 3]\n"))
    assert ":3:1: axis_start and axis_end coincide" in msg


def test_an_axis_without_a_shape_is_a_cylinders(tmp_path):
    # (as a centerline is: the axis and the radius were ignored, and a sphere ran from the image)
    config = load_segment_config(write(tmp_path, "axis_start: [1, 2, 3]\naxis_end: [1, 2, 9]\n"
                                                 "radius: 2\n"))
    assert config.shape == "cylinder"
    # A sphere's leftovers under a cylinder on top, and a cylinder's radius alone, load as before.
    base = load_segment_config(write(tmp_path, "center: [9, 9, 9]\nradii: [3, 3, 3]\n"))
    top = base.replace(axis_start=[1, 2, 3], axis_end=[1, 2, 9], radius=2.0)
    assert top.shape == "cylinder" and top.radii == [3.0, 3.0, 3.0]
    assert load_segment_config(write(tmp_path, "radius: 13\n")).radius == 13.0


def test_file_problems_are_config_errors_naming_the_file(tmp_path):
    missing = tmp_path / "nope.yaml"
    assert config_error(missing) == f"{missing}: config file not found"
    assert config_error(tmp_path).endswith("is a directory, not a YAML file")
    binary = tmp_path / "b.yaml"
    binary.write_bytes(b"m1: \xff\xfe\n")
    assert "not a UTF-8 text file" in config_error(binary)
    assert config_error(write(tmp_path, "- m1\n- 8\n")).endswith(
        ":1:1: a segment config must be a mapping of option: value, got a list of 2")


def test_valid_values_pass_unchanged(tmp_path):
    c = load_segment_config(write(tmp_path, (
        "shape: cylinder\naxis_start: [10, 10, 2]\naxis_end: [10, 10, 30.5]\nradius: 4.5\n"
        "world: yes\nm1: 4\nm2: 200\nscale: 0.75\nfeature: surface\nthreshold: 0.3\n"
        "seed_point: [10, 10, 15]\nmax_iter: 1\ntol: 1e-9\ncoarse_to_fine: false\n"
        "prior_weight: 2\nprior_space: similarity\nvolume: 0\nnan: fill\npolarity: dark\n")))
    expected = dataclasses.replace(
        SegmentConfig(), shape="cylinder", axis_start=[10.0, 10.0, 2.0], axis_end=[10.0, 10.0, 30.5],
        radius=4.5, world=True, m1=4, m2=200, scale=0.75, feature="surface", threshold=0.3,
        seed_point=[10.0, 10.0, 15.0], max_iter=1, tol=1e-9, coarse_to_fine=False, prior_weight=2.0,
        prior_space="similarity", volume=0, nan="fill", polarity="dark")
    assert c == expected


def test_coarse_to_fine_flag_overrides_the_file_both_ways(tmp_path):
    from segsnake.cli import build_parser
    from segsnake.commands.segment import config_from_args

    on, off = tmp_path / "on.yaml", tmp_path / "off.yaml"
    on.write_text("coarse_to_fine: true\n")
    off.write_text("coarse_to_fine: false\n")

    def parse(*flags):
        return config_from_args(build_parser().parse_args(["segment", "a.nii", "--out", "o",
                                                           *flags]))

    assert parse("--config", str(on)).coarse_to_fine
    assert not parse("--config", str(on), "--no-coarse-to-fine").coarse_to_fine
    assert parse("--config", str(off), "--coarse-to-fine").coarse_to_fine
    assert not parse("--config", str(off)).coarse_to_fine
    assert not parse("--no-coarse-to-fine").coarse_to_fine
    assert parse().coarse_to_fine
