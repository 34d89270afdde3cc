"""Options of ``segsnake segment`` as one validated dataclass, and YAML loading with line numbers.

:class:`SegmentConfig` is the single description of a segmentation run: the ``segment`` command builds
it from flags (optionally on top of ``--config FILE.yaml``), and ``segsnake batch`` builds one per case
from ``defaults:`` merged with the case's overrides. Precedence is always
command-line flag > YAML value > dataclass default.

YAML is read with a small loader that remembers where every key sits, so a validation error names the
file, line and column of the offending key (``runs.yaml:12:5: m1: must be >= 4, got 2``) instead of
only the key. Everything here is pure: errors are raised as :class:`~segsnake.errors.ConfigError`,
nothing is printed.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import numbers
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

import yaml

from segsnake.errors import ConfigError

__all__ = [
    "SegmentConfig",
    "LineDict",
    "LineList",
    "load_yaml",
    "load_segment_config",
    "suggest",
    "locate",
]

SHAPES = ("sphere", "cylinder")
FEATURES = ("edge", "surface")
PRIOR_SPACES = ("affine", "linear", "similarity", "rigid", "scaling", "translation")
#: The prior's weight and the transformations it ignores unless ``prior_weight`` and
#: ``prior_space`` are given (:meth:`SegmentConfig.prior_used`). A prior file: weight 1, any
#: affine pose (the user's own reference, perhaps of another subject). An atlas' structure,
#: already placed by an affine registration: any pose and size but its own proportions, and a
#: weight in the flat part of the tuning case's sweep (the left thalamus: 0.783 at weight 1,
#: 0.804-0.809 from 2 to 20; similarity against affine and rigid 0.813 / 0.619 / 0.783;
#: docs/benchmarks.md, session 36): where a nucleus meets a neighbour of its intensity the atlas
#: is the only thing that says where it ends.
PRIOR_WEIGHT_FILE = 1.0
PRIOR_SPACE_FILE = "affine"
PRIOR_WEIGHT_ATLAS = 5.0
PRIOR_SPACE_ATLAS = "similarity"
NAN_POLICIES = ("refuse", "fill")
POLARITIES = ("auto", "bright", "dark", "none")
ENERGIES = ("auto", "region", "edge")
M_MIN, M_MAX = 4, 200


# --------------------------------------------------------------------------------------------------
# YAML with positions
# --------------------------------------------------------------------------------------------------


class LineDict(dict):
    """A ``dict`` from YAML that remembers where each key was written.

    Attributes
    ----------
    key_marks : dict
        Key -> ``(line, column)``, both 1-based, of the key in its file.
    mark : tuple or None
        ``(line, column)`` of the mapping itself.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.key_marks: dict[Any, tuple[int, int]] = {}
        self.mark: tuple[int, int] | None = None


class LineList(list):
    """A ``list`` from YAML that remembers where each item starts (``item_marks``, 1-based)."""

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        self.item_marks: list[tuple[int, int]] = []
        self.mark: tuple[int, int] | None = None


def _mark(node: yaml.Node) -> tuple[int, int]:
    return node.start_mark.line + 1, node.start_mark.column + 1


class _Loader(yaml.SafeLoader):
    """SafeLoader that builds :class:`LineDict`/:class:`LineList`, refuses duplicate keys and
    reads ``1e-6`` as a float (PyYAML follows YAML 1.1, where a float needs a dot: ``tol: 1e-6``
    would silently become the *string* "1e-6")."""


def _construct_mapping(loader: _Loader, node: yaml.MappingNode) -> LineDict:
    # A key written twice is a mistake (PyYAML would silently keep the last); a key that overrides
    # one brought in by a merge key (<<: *anchor) is not, so check duplicates before merging.
    own: dict[Any, tuple[int, int]] = {}
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge":
            continue
        key = loader.construct_object(key_node, deep=True)
        try:
            hash(key)
        except TypeError:
            raise yaml.constructor.ConstructorError(
                None, None, "a mapping key must be a plain value", key_node.start_mark) from None
        if key in own:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r} (first given at line {own[key][0]})",
                key_node.start_mark)
        own[key] = _mark(key_node)
    loader.flatten_mapping(node)  # merged pairs first, then the mapping's own (which win)
    data = LineDict()
    data.mark = _mark(node)
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        data[key] = loader.construct_object(value_node, deep=True)
        data.key_marks[key] = _mark(key_node)
    return data


def _construct_sequence(loader: _Loader, node: yaml.SequenceNode) -> LineList:
    data = LineList(loader.construct_object(child, deep=True) for child in node.value)
    data.item_marks = [_mark(child) for child in node.value]
    data.mark = _mark(node)
    return data


_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)
_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_SEQUENCE_TAG, _construct_sequence)
# YAML 1.2 floats: exponent without a dot ("1e-6", "5E3"); add_implicit_resolver copies the class
# table first, so the global SafeLoader is untouched.
_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def load_yaml(path: str | os.PathLike[str]) -> Any:
    """Read a YAML file into plain Python values that remember their positions.

    Parameters
    ----------
    path : str or path-like
        The file to read.

    Returns
    -------
    object
        Mappings are :class:`LineDict`, sequences :class:`LineList`; an empty file gives ``None``.

    Raises
    ------
    ConfigError
        The file is missing, unreadable or not UTF-8 text, or its YAML is malformed
        (message ``FILE:LINE:COL: problem``) or has a duplicate key.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{p}: config file not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{p}: is a directory, not a YAML file") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{p}: not a UTF-8 text file ({exc.reason} at byte {exc.start})") from None
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read config file: {exc.strerror or exc}") from None
    try:
        return yaml.load(text, Loader=_Loader)  # noqa: S506 - _Loader derives from SafeLoader
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        problem = exc.problem or exc.context or "invalid YAML"
        if exc.context and exc.problem and exc.context != exc.problem:
            problem = f"{problem} ({exc.context})"
        where = f"{p}:{mark.line + 1}:{mark.column + 1}" if mark is not None else str(p)
        kind = "YAML error" if isinstance(exc, yaml.constructor.ConstructorError) else "YAML syntax error"
        raise ConfigError(f"{where}: {kind}: {_one_line(problem)}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: YAML error: {_one_line(str(exc))}") from None


def locate(source: str, container: Any = None, key: Any = None) -> str:
    """``"FILE:LINE:COL"`` for ``key`` of a YAML-loaded ``container`` (or the container itself).

    Falls back to ``source`` alone when the position is unknown (a mapping not read from YAML).
    """
    mark = None
    if isinstance(container, LineDict):
        mark = container.key_marks.get(key, container.mark) if key is not None else container.mark
    elif isinstance(container, LineList):
        if isinstance(key, int) and 0 <= key < len(container.item_marks):
            mark = container.item_marks[key]
        else:
            mark = container.mark
    return f"{source}:{mark[0]}:{mark[1]}" if mark else source


def suggest(word: str, choices: Any) -> str:
    """`` (did you mean 'x'?)`` for the closest of ``choices``, or an empty string."""
    close = difflib.get_close_matches(str(word), [str(c) for c in choices], n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


# --------------------------------------------------------------------------------------------------
# Field validators: each returns the normalised value or raises ValueError with "must be ..."
# --------------------------------------------------------------------------------------------------


def _is_number(v: Any) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


def _describe(v: Any) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return f"{v} (a boolean)"
    if isinstance(v, str):
        return f"{v!r} (a string)"
    if isinstance(v, (list, tuple)):
        return f"a list of {len(v)}"
    if isinstance(v, dict):
        return "a mapping"
    return repr(v)


def _float(v: Any, *, low: float | None = None, strict_low: bool = False) -> float:
    if not _is_number(v):
        raise ValueError(f"must be a number, got {_describe(v)}")
    x = float(v)
    if not math.isfinite(x):
        raise ValueError(f"must be a finite number, got {x}")
    if low is not None and (x <= low if strict_low else x < low):
        raise ValueError(f"must be {'>' if strict_low else '>='} {low:g}, got {x:g}")
    return x


def _int(v: Any, *, low: int | None = None, high: int | None = None) -> int:
    # 8.0 from a YAML file is accepted as 8; 8.5 is not.
    if _is_number(v) and not isinstance(v, numbers.Integral) and float(v).is_integer():
        v = int(v)
    if not isinstance(v, numbers.Integral) or isinstance(v, bool):
        raise ValueError(f"must be an integer, got {_describe(v)}")
    if low is not None and v < low:
        raise ValueError(f"must be >= {low}, got {v}")
    if high is not None and v > high:
        raise ValueError(f"must be <= {high}, got {v}")
    return int(v)


def _bool(v: Any) -> bool:
    if not isinstance(v, bool):
        raise ValueError(f"must be true or false, got {_describe(v)}")
    return v


def _choice(choices: tuple[str, ...]) -> Callable[[Any], str]:
    def check(v: Any) -> str:
        if not isinstance(v, str) or v not in choices:
            hint = suggest(v, choices) if isinstance(v, str) else ""
            raise ValueError(f"must be one of {', '.join(choices)}; got {_describe(v)}{hint}")
        return v

    return check


def _vec3(positive: bool = False) -> Callable[[Any], list[float]]:
    def check(v: Any) -> list[float]:
        if not isinstance(v, (list, tuple)) or len(v) != 3 or not all(_is_number(x) for x in v):
            raise ValueError(f"must be a list of 3 numbers [x, y, z], got {_describe(v)}")
        out = [float(x) for x in v]
        if not all(math.isfinite(x) for x in out):
            raise ValueError(f"must be 3 finite numbers, got {out}")
        if positive and min(out) <= 0:
            raise ValueError(f"must be 3 numbers > 0, got {out}")
        return out

    return check


def _threshold(v: Any) -> str | float:
    if v == "auto":
        return "auto"
    if isinstance(v, str):  # from a command line or a quoted YAML value
        try:
            v = float(v)
        except ValueError:
            raise ValueError(f"must be 'auto' or a number, got {v!r}") from None
    if not _is_number(v):
        raise ValueError(f"must be 'auto' or a number, got {_describe(v)}")
    return _float(v)


def _path(v: Any) -> str:
    if isinstance(v, os.PathLike):
        v = os.fspath(v)
    if not isinstance(v, str) or not v:
        raise ValueError(f"must be a file path, got {_describe(v)}")
    return v


def _text(v: Any) -> str:
    if isinstance(v, int) and not isinstance(v, bool):  # (a label's value, unquoted in YAML)
        v = str(v)
    if not isinstance(v, str) or not v.strip():
        raise ValueError(f"must be a name, got {_describe(v)}")
    return v.strip()


def _mesh_name(v: Any) -> str:
    from segsnake.meshes import MESH_SUFFIXES, mesh_suffix

    if not isinstance(v, str) or not v:
        raise ValueError(f"must be a file name, got {_describe(v)}")
    # A plain name: the mesh is one of the run's outputs and goes into its output directory with
    # the others (written and moved into place together with them).
    if os.path.basename(v) != v or v in (".", ".."):
        raise ValueError(f"must be a file name without a directory (it is written into --out), "
                         f"got {v!r}")
    if mesh_suffix(v) is None:
        raise ValueError(f"must end in {', '.join(MESH_SUFFIXES)} (the mesh format), got {v!r}")
    return v


def _position(v: Any) -> list[float] | str:
    # A position is three numbers or a 3D Slicer markups file (segsnake.markups reads it once the
    # image, whose affine converts it, is loaded).
    if isinstance(v, (str, os.PathLike)):
        return _path(v)
    return _vec3()(v)


def _centerline(v: Any) -> str | list[list[float]]:
    # A centerline file (segsnake.centerline_files reads it once the image is loaded), or its
    # points given inline: rows [x, y, z] or [x, y, z, radius], in the positions' units.
    if isinstance(v, (str, os.PathLike)):
        return _path(v)
    rows = v if isinstance(v, (list, tuple)) else None
    if rows is None or len(rows) < 2 or not all(
            isinstance(r, (list, tuple)) and len(r) in (3, 4) and all(_is_number(x) for x in r)
            for r in rows) or len({len(r) for r in rows}) != 1:
        raise ValueError(f"must be a centerline file (.csv, .json, .mrk.json) or a list of >= 2 "
                         f"points, each [x, y, z] or each [x, y, z, radius]; got {_describe(v)}")
    out = [[float(x) for x in r] for r in rows]
    if not all(math.isfinite(x) for r in out for x in r):
        raise ValueError("must hold finite numbers only")
    return out


def _optional(check: Callable[[Any], Any]) -> Callable[[Any], Any]:
    def wrapped(v: Any) -> Any:
        return None if v is None else check(v)

    return wrapped


# Field name -> validator. Every SegmentConfig field has one (checked at import time below).
_VALIDATORS: dict[str, Callable[[Any], Any]] = {
    "shape": _choice(SHAPES),
    "center": _optional(_position),
    "radii": _optional(_vec3(positive=True)),
    "axis_start": _optional(_position),
    "axis_end": _optional(_position),
    "radius": _optional(lambda v: _float(v, low=0.0, strict_low=True)),
    "centerline": _optional(_centerline),
    "world": _bool,
    "m1": _optional(lambda v: _int(v, low=M_MIN, high=M_MAX)),
    "m2": _optional(lambda v: _int(v, low=M_MIN, high=M_MAX)),
    "scale": _optional(lambda v: _float(v, low=0.0, strict_low=True)),
    "feature": _choice(FEATURES),
    "threshold": _threshold,
    "seed_point": _optional(_position),
    "max_iter": lambda v: _int(v, low=1),
    "tol": lambda v: _float(v, low=0.0, strict_low=True),
    "coarse_to_fine": _bool,
    "prior": _optional(_path),
    "prior_weight": _optional(lambda v: _float(v, low=0.0)),
    "prior_space": _optional(_choice(PRIOR_SPACES)),
    "prior_modes": lambda v: _int(v, low=0),
    "volume": _optional(lambda v: _int(v, low=0)),
    "nan": _choice(NAN_POLICIES),
    "polarity": _choice(POLARITIES),
    "energy": _choice(ENERGIES),
    "mesh": _optional(_mesh_name),
    "init": _optional(_path),
    "atlas": _optional(_path),
    "structure": _optional(_text),
}

# Options that are positions: three numbers, or a 3D Slicer markups file (segsnake.markups).
POSITION_KEYS = ("center", "seed_point", "axis_start", "axis_end")
# Options whose value is (or may be) a file path: relative paths in a YAML file are relative to it.
PATH_KEYS = ("prior", "init", "centerline", "atlas") + POSITION_KEYS
# The options that describe a new initial shape, which a start from a saved snake (init) replaces.
SHAPE_KEYS = ("center", "radii", "axis_start", "axis_end", "radius", "centerline")
# A cylinder's axis or centerline given without a shape implies it (its radius alone does not:
# a YAML base or batch defaults may hold one for the shapes given on top).
CYLINDER_KEYS = ("axis_start", "axis_end", "centerline")
# The options a centerline (a cylinder along a polyline) replaces.
CENTERLINE_EXCLUDES = ("center", "radii", "axis_start", "axis_end")


@dataclass
class SegmentConfig:
    """Every option of ``segsnake segment``; field names are a contract shared with the CLI and YAML.

    ``centerline`` (a polyline along a tube: a file, or its points) has the positions' units
    (its radii the radius's). Positions (``center``, ``axis_start``, ``axis_end``,
    ``seed_point``) are voxel indices
    ``(i, j, k)`` along the array axes, or a 3D Slicer markups file (``.mrk.json``, read by
    :func:`segsnake.markups.resolve_markups` once the image is loaded), and lengths
    (``radii``, ``radius``) are in voxels, as the ``segment`` flags take them; with ``world`` true they are NIfTI world millimetres instead
    (:func:`segsnake.pipeline.initial_model` converts either to mm of scaled index space).
    ``scale`` is in mm. ``None`` means "choose automatically / model default".
    """

    shape: str = "sphere"
    center: list[float] | str | None = None  # str: a markups file (segsnake.markups)
    radii: list[float] | None = None
    axis_start: list[float] | str | None = None
    axis_end: list[float] | str | None = None
    radius: float | None = None
    # A cylinder along a polyline: a .csv/.json/.mrk.json file (segsnake.centerline_files), or
    # its rows [x, y, z(, radius)] once read; implies shape cylinder.
    centerline: str | list[list[float]] | None = None
    world: bool = False
    m1: int | None = None
    m2: int | None = None
    scale: float | None = None
    feature: str = "edge"
    threshold: str | float = "auto"
    seed_point: list[float] | str | None = None
    max_iter: int = 300
    tol: float = 1e-6
    coarse_to_fine: bool = True  # region energy: finer grids after the rounds (pipeline)
    prior: str | None = None
    prior_weight: float | None = None  # None: by the prior's kind (prior_used); 0: off
    prior_space: str | None = None  # None: by the prior's kind (prior_used)
    prior_modes: int = 0  # modes of a shape-model prior (MODEL.json) used by the prior
    volume: int | None = None
    nan: str = "refuse"
    polarity: str = "auto"
    energy: str = "auto"  # segsnake.pipeline.region_energy: region for a sphere, else edge
    mesh: str | None = None  # the surface also as NAME.stl/.obj/.ply in the output directory
    # A saved snake to start from (snake.json, or a markups file of export-points): replaces the
    # new sphere or cylinder and the stages that bring a rough start onto the boundary.
    init: str | None = None
    # An atlas folder (segsnake.atlas): the image registered to its template, its structure
    # (``structure``, or the label under ``center``) fitted, as the start and the shape prior.
    atlas: str | None = None
    structure: str | None = None

    # -- construction -------------------------------------------------------------------------

    @classmethod
    def keys(cls) -> tuple[str, ...]:
        """The valid option names, in declaration order."""
        return tuple(f.name for f in dataclasses.fields(cls))

    @classmethod
    def from_mapping(cls, d: Mapping[str, Any] | None, *, source: str = "<config>",
                     base: "SegmentConfig | None" = None) -> "SegmentConfig":
        """Validate a mapping of options and build a config.

        Parameters
        ----------
        d : mapping or None
            Option name -> value. ``-`` in a name is read as ``_`` (``max-iter`` = ``max_iter``).
            A :class:`LineDict` from :func:`load_yaml` makes errors point at the key's line.
        source : str
            Name used in error messages (usually the YAML file).
        base : SegmentConfig, optional
            Values for keys absent from ``d`` (defaults to the dataclass defaults).

        Returns
        -------
        SegmentConfig

        Raises
        ------
        ConfigError
            Unknown key (with the closest valid key suggested), wrong type or out-of-range value,
            or inconsistent options; the message starts with ``source[:LINE:COL]``.
        """
        if d is None:
            d = {}
        if not isinstance(d, Mapping):
            raise ConfigError(f"{locate(source, d)}: options must be a mapping of key: value, "
                              f"got {_describe(d)}")
        values = dataclasses.asdict(base) if base is not None else {}
        seen: dict[str, Any] = {}
        for raw_key, value in d.items():
            where = locate(source, d, raw_key)
            if not isinstance(raw_key, str):
                raise ConfigError(f"{where}: option names must be text, got {raw_key!r}")
            key = raw_key.replace("-", "_")
            if key not in _VALIDATORS:
                raise ConfigError(f"{where}: unknown option {raw_key!r}{suggest(key, _VALIDATORS)}")
            if key in seen:
                raise ConfigError(f"{where}: option {key!r} given twice (as {seen[key]!r} "
                                  f"and {raw_key!r})")
            seen[key] = raw_key
            try:
                values[key] = _VALIDATORS[key](value)
            except ValueError as exc:
                raise ConfigError(f"{where}: {key}: {exc}") from None
        if "shape" not in seen and values.get("shape", "sphere") == "sphere" and \
                any(values.get(k) is not None for k in CYLINDER_KEYS):
            values["shape"] = "cylinder"  # a centerline or an axis is a tube's: the cylinder
        config = cls(**values)
        problem = config._consistency_problem()
        if problem is not None:
            key, message = problem
            # Point at the offending key when it was given here; otherwise at the mapping.
            raw = seen.get(key)
            where = locate(source, d, raw) if raw is not None else locate(source, d)
            raise ConfigError(f"{where}: {message}")
        return config

    def _consistency_problem(self) -> tuple[str, str] | None:
        """Checks that involve more than one option: ``(key, message)`` or ``None``."""
        if self.init is not None:
            given = [k for k in SHAPE_KEYS if getattr(self, k) is not None]
            if given:
                verb = "describes" if len(given) == 1 else "describe"
                return "init", (f"init starts from a saved snake; {', '.join(given)} {verb} a "
                                f"new initial shape: give one or the other")
        if self.structure is not None and self.atlas is None:
            return "structure", "structure names a structure of an atlas: give the atlas too"
        if self.atlas is not None:
            if self.structure is not None and self.center is not None:
                return "structure", ("structure names the atlas' structure and center clicks in "
                                     "it: give one or the other")
            if self.structure is None and self.center is None:
                return "atlas", ("atlas needs its structure named (structure) or a click in it "
                                 "(center)")
            if (self.m1 is None) != (self.m2 is None):
                return "atlas", "atlas fits its structure at m1 x m2: give both or neither"
            if self.prior_modes:
                return "prior_modes", ("prior_modes needs a shape model (prior); the atlas' "
                                       "structure has no modes")
            given = [k for k in ("init", "prior", "radii", "axis_start", "axis_end", "radius",
                                 "centerline") if getattr(self, k) is not None]
            if self.shape != "sphere":
                given.insert(0, f"shape {self.shape}")
            if given:
                verb = "gives" if len(given) == 1 else "give"
                return "atlas", (f"atlas starts from the atlas' structure, which is also its "
                                 f"prior; {', '.join(given)} {verb} another start or prior: give "
                                 f"one or the other")
        if self.centerline is not None:
            if self.shape != "cylinder":
                return "shape", (f"centerline initializes a cylinder; shape {self.shape} does not "
                                 f"take one")
            given = [k for k in CENTERLINE_EXCLUDES if getattr(self, k) is not None]
            if given:
                verb = "describes" if len(given) == 1 else "describe"
                return "centerline", (f"centerline gives the tube's axis; {', '.join(given)} "
                                      f"{verb} another initial shape: give one or the other")
        if isinstance(self.axis_start, list) and isinstance(self.axis_end, list):
            length = math.dist(self.axis_start, self.axis_end)
            if length == 0.0:
                return "axis_end", "axis_start and axis_end coincide: the cylinder axis has zero length"
        return None

    def prior_used(self) -> tuple[float, str]:
        """The prior's weight and space: as given, else those of its kind (an atlas' structure
        or a prior file: :data:`PRIOR_WEIGHT_ATLAS` and the others)."""
        atlas = self.atlas is not None
        weight = self.prior_weight if self.prior_weight is not None else \
            PRIOR_WEIGHT_ATLAS if atlas else PRIOR_WEIGHT_FILE
        return weight, self.prior_space or (PRIOR_SPACE_ATLAS if atlas else PRIOR_SPACE_FILE)

    def to_dict(self) -> dict[str, Any]:
        """Plain, JSON- and YAML-serialisable dict of every option (lists copied)."""
        return dataclasses.asdict(self)

    def replace(self, **overrides: Any) -> "SegmentConfig":
        """A validated copy with ``overrides`` applied on top of this config.

        ``None`` values are ignored: they mean "not given" (an unset command-line flag), so a flag
        the user did not pass never erases a value from a YAML file. Unknown names raise
        :class:`ConfigError` with a suggestion, like :meth:`from_mapping`.
        """
        given = {k: v for k, v in overrides.items() if v is not None}
        return type(self).from_mapping(given, source="command line", base=self)


if set(_VALIDATORS) != set(SegmentConfig.keys()):  # pragma: no cover - developer guard
    raise RuntimeError("segsnake.config: validators and SegmentConfig fields differ")


def resolve_paths(options: dict[str, Any], base_dir: str | os.PathLike[str]) -> dict[str, Any]:
    """Make relative path options (``prior``, markups files given as positions) absolute against
    ``base_dir``; returns a new dict (values that are not text, such as numbers, unchanged)."""
    out = dict(options)
    for key in PATH_KEYS:
        value = out.get(key)
        if isinstance(value, str) and value and not os.path.isabs(os.path.expanduser(value)):
            out[key] = str(Path(base_dir) / value)
        elif isinstance(value, str) and value:
            out[key] = os.path.expanduser(value)
    return out


def resolve_config_paths(config: "SegmentConfig", base_dir: str | os.PathLike[str]) -> "SegmentConfig":
    """``config`` with its relative path options (:data:`PATH_KEYS`) made absolute against
    ``base_dir`` (the YAML file's folder)."""
    return dataclasses.replace(config, **resolve_paths(
        {k: getattr(config, k) for k in PATH_KEYS}, base_dir))


def load_segment_config(path: str | os.PathLike[str]) -> SegmentConfig:
    """Read ``segment --config FILE.yaml``: a flat mapping of :class:`SegmentConfig` options.

    Relative paths inside (``prior``) are taken relative to the YAML file's directory. An empty
    file gives the defaults.

    Raises
    ------
    ConfigError
        Missing/unreadable file, YAML syntax error (with line and column), unknown key, wrong type
        or range (with the key's line).
    """
    p = Path(path)
    data = load_yaml(p)
    if data is None:
        return SegmentConfig()
    if not isinstance(data, LineDict):
        raise ConfigError(f"{locate(str(p), data)}: a segment config must be a mapping of "
                          f"option: value, got {_describe(data)}")
    return resolve_config_paths(SegmentConfig.from_mapping(data, source=str(p)), p.parent)
