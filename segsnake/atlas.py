"""An atlas' structure as a start and a shape prior (``segment --atlas DIR``; issue 15).

A click does not say where a deep nucleus ends: the thalamus, the caudate and the hippocampus
border tissues of their own intensity, and no image energy separates them (docs/benchmarks.md,
sessions 14-35). The field's tools bring that knowledge from other brains: FSL FIRST registers
the image to MNI152 and fits shape models trained on labelled brains; FreeSurfer registers an
atlas of labelled brains. The atlas start does the same with what segsnake has:

1. the image is registered to the atlas' template (an affine map; :mod:`segsnake.registration`);
2. the structure (``--structure`` names it, or the label under the click) is carried onto the
   image's grid through that map (its indicator, trilinear, kept at >= 0.5, holes filled);
3. its boundary is fitted by a deformable sphere (:func:`segsnake.fit.fit_mesh` on
   :func:`segsnake.mask_mesh.mask_surface`), which starts the segmentation and is its shape
   prior (:mod:`segsnake.model_prior`, in ``--prior-space``).

An atlas is a folder: ``template.nii.gz`` (a T1 template, zero outside the head or brain) and one
or more label images ``NAME.nii.gz`` on the template's world (any grid), each with ``NAME.csv``
(``value,name`` per line, no header) naming its labels. A structure is ``SET:LABEL`` (a label's
name or value in label set SET), ``LABEL`` (searched in every set), or ``SET`` alone (all of the
set's labels as one object: SUIT's cerebellar lobules as the cerebellum).
"""

from __future__ import annotations

import csv
import os
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from segsnake.errors import InputError

__all__ = ["Atlas", "LabelSet", "Structure", "read_atlas", "find_structure", "structure_mask",
           "TEMPLATE_NAME", "atlas_start", "FIT_RMS_VOXELS", "FIT_RMS_PERCENT"]

#: How closely the sphere fits the structure's mask, in voxels of the image (RMS distance to its
#: smoothed boundary): the mask is a staircase of those voxels, and the registration that placed
#: it errs by more, so a finer fit would only add control points for the segmentation to carry.
FIT_RMS_VOXELS = 0.5
#: ... or within this share (%) of the structure's diagonal, whichever is larger: a large
#: structure's folds (the cerebellum's folia) are not what its start and prior need.
FIT_RMS_PERCENT = 1.0

#: The template's file name in an atlas folder.
TEMPLATE_NAME = "template.nii.gz"


@dataclass(frozen=True)
class LabelSet:
    """One label image of an atlas: integer labels on its grid, and their names. Its voxels are
    read when first asked for (:attr:`labels`): an atlas may hold many sets, a run uses one."""

    name: str
    path: str
    affine: NDArray
    names: dict[int, str]  # (without 0, which is no label)

    @cached_property
    def labels(self) -> NDArray:
        """The (i, j, k) integer labels, 0 = none.

        Raises
        ------
        InputError
            The file's voxels cannot be read.
        """
        image, _ = _nifti_header(self.path)
        # (labels stored as floats with a scale carry rounding: 11.000001 is label 11)
        return np.rint(_nifti_voxels(self.path, image)).astype(np.int32)


@dataclass(frozen=True)
class Atlas:
    """A template and the label sets drawn on its world."""

    folder: str
    template: NDArray
    template_affine: NDArray
    label_sets: tuple[LabelSet, ...]


@dataclass(frozen=True)
class Structure:
    """The labels of one label set that make one object."""

    label_set: LabelSet
    values: tuple[int, ...]
    description: str

    @cached_property
    def voxels(self) -> NDArray:
        """Where the structure is drawn on its label set's grid (boolean)."""
        return np.isin(self.label_set.labels, self.values)


def _read_names(path: str) -> dict[int, str]:
    names: dict[int, str] = {}
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            for n, row in enumerate(csv.reader(fh), start=1):
                if not row or not "".join(row).strip():
                    continue
                try:
                    names[int(row[0])] = row[1].strip() if len(row) > 1 else row[0].strip()
                except ValueError:
                    raise InputError(f"{path}:{n}: expected 'value,name' with an integer value, "
                                     f"got {','.join(row)!r}") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read the label names: {exc.strerror or exc}") from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"{path}: not a UTF-8 CSV of label names ({exc})") from None
    names.pop(0, None)  # (0 is no label: never part of a structure)
    return names


def _nifti_header(path: str):
    """The NIfTI file's image (nibabel reads its voxels only when asked) and its affine, checked
    for registration; a file that cannot be read or a grid it cannot use as :class:`InputError`."""
    import nibabel as nib

    from segsnake.io import _quiet_nibabel
    from segsnake.registration import grid_problem

    try:
        with _quiet_nibabel():
            image = nib.load(path)
    except Exception as exc:  # (nibabel raises many kinds for a damaged file)
        raise InputError(f"{path}: cannot read it as NIfTI: {exc}") from None
    affine = np.asarray(image.affine, dtype=np.float64)
    problem = grid_problem(affine)
    if problem is not None:
        raise InputError(f"{path}: {problem}")
    return image, affine


def _nifti_voxels(path: str, image) -> NDArray:
    """The voxels of :func:`_nifti_header`'s ``image``; a damaged file as :class:`InputError`."""
    from segsnake.io import _quiet_nibabel

    try:
        with _quiet_nibabel():
            return np.asarray(image.dataobj)
    except Exception as exc:  # (a truncated or corrupt data block)
        raise InputError(f"{path}: cannot read its voxels: {exc}") from None


def read_atlas(folder: str) -> Atlas:
    """Read an atlas folder (see the module's docstring).

    Raises
    ------
    InputError
        No such folder, no template, no label set, or a file that cannot be read.
    """
    if not os.path.isdir(folder):
        raise InputError(f"{folder}: no such atlas folder")
    tpath = os.path.join(folder, TEMPLATE_NAME)
    if not os.path.isfile(tpath):
        raise InputError(f"{folder}: an atlas folder needs {TEMPLATE_NAME} (its T1 template)")
    image, template_affine = _nifti_header(tpath)
    if len(image.shape) != 3:
        raise InputError(f"{tpath}: the template must be a 3D image, got {len(image.shape)}D")
    template = _nifti_voxels(tpath, image)
    sets = []
    for entry in sorted(os.listdir(folder)):
        if not entry.endswith(".nii.gz") or entry == TEMPLATE_NAME:
            continue
        name = entry[: -len(".nii.gz")]
        path = os.path.join(folder, entry)
        names_path = os.path.join(folder, name + ".csv")
        if not os.path.isfile(names_path):
            raise InputError(f"{path}: a label set needs its names in {name}.csv "
                             f"('value,name' per line)")
        image, affine = _nifti_header(path)  # (its header: the voxels when asked for)
        if len(image.shape) != 3:
            raise InputError(f"{path}: a label set must be a 3D image, got {len(image.shape)}D")
        sets.append(LabelSet(name, path, affine, _read_names(names_path)))
    if not sets:
        raise InputError(f"{folder}: the atlas has no label set (NAME.nii.gz with NAME.csv)")
    return Atlas(folder, template, template_affine, tuple(sets))


def _label_value(label_set: LabelSet, label: str) -> int | None:
    wanted = label.strip().lower()
    for value, name in label_set.names.items():
        if name.lower() == wanted:
            return value
    try:
        value = int(wanted)
    except ValueError:
        return None
    return value if value in label_set.names else None


def find_structure(atlas: Atlas, structure: str | None, at_world: NDArray | None = None,
                   to_template: NDArray | None = None) -> Structure:
    """The structure ``structure`` names, or (``structure`` None) the label under a click.

    Parameters
    ----------
    atlas : Atlas
    structure : str or None
        ``SET:LABEL``, ``LABEL`` or ``SET`` (module docstring).
    at_world : ndarray, optional
        The click in the image's world (mm), used when ``structure`` is None.
    to_template : ndarray, optional
        The image world -> template world map (:func:`segsnake.registration.register_affine`),
        needed with ``at_world``.

    Raises
    ------
    InputError
        A name no label set holds (the choices listed), or a click on no label.
    """
    sets = {s.name: s for s in atlas.label_sets}
    if structure is None:
        if at_world is None or to_template is None:
            raise InputError(f"{atlas.folder}: name the atlas' structure (--structure) or click "
                             f"in it (--center)")
        point = (to_template @ np.r_[np.asarray(at_world, dtype=float), 1.0])
        for s in atlas.label_sets:
            idx = np.rint(np.linalg.solve(s.affine, point)[:3]).astype(int)
            if np.all(idx >= 0) and np.all(idx < s.labels.shape):
                value = int(s.labels[tuple(idx)])
                if value in s.names:
                    return Structure(s, (value,), f"{s.name}:{s.names[value]}")
        raise InputError(f"{atlas.folder}: the click lies on no label of the atlas (after "
                         f"registration); name the structure with --structure")
    text = structure.strip()
    if text in sets:
        s = sets[text]
        return Structure(s, tuple(sorted(s.names)), s.name)
    set_name, _, label = text.rpartition(":")
    candidates = [sets[set_name]] if set_name in sets else atlas.label_sets if not set_name \
        else None
    if candidates is None:
        raise InputError(f"{atlas.folder}: no label set {set_name!r} (the atlas has "
                         f"{', '.join(sets)})")
    for s in candidates:
        value = _label_value(s, label)
        if value is not None:
            return Structure(s, (value,), f"{s.name}:{s.names[value]}")
    names = sorted({f"{s.name}:{n}" for s in candidates for n in s.names.values()})
    like, more = _names_like(label, names)
    if like:  # ("thalamus" for an atlas' "thalamus-lh" and "thalamus-rh")
        offered = like[0] if len(like) == 1 else f"{', '.join(like[:-1])} or {like[-1]}"
        raise InputError(f"{atlas.folder}: no structure {structure!r}; did you mean "
                         f"{offered}{f' (or {more} more like it)' if more else ''}?")
    shown = ", ".join(names[:12]) + (f" and {len(names) - 12} more" if len(names) > 12 else "")
    raise InputError(f"{atlas.folder}: no structure {structure!r}; the atlas has {shown}, and "
                     f"each label set as a whole ({', '.join(sets)})")


#: At most this many of an atlas' names are offered for a structure it does not have.
MAX_SUGGESTIONS = 6


def _names_like(asked: str, names: list[str]) -> tuple[list[str], int]:
    """The ``SET:LABEL`` names a user who typed ``asked`` may have meant, and how many more
    there were beyond :data:`MAX_SUGGESTIONS`: those whose label holds every word of it
    (``putamen lh`` -> ``aseg:putamen-lh``), else every word of three characters or more
    (``thalamus`` -> ``aseg:thalamus-lh``, ``aseg:thalamus-rh``; a name of short words alone,
    ``lh``, would match half the atlas), else those difflib finds close to it, closest first
    (``Left-Thalamus``, ``hipocampus``)."""
    import difflib
    import re

    words = [w for w in re.split(r"[^a-z0-9]+", asked.lower()) if w]
    labels = {n: n.rpartition(":")[2].lower() for n in names}  # (as find_structure splits)
    found = []
    if any(len(w) >= 3 for w in words):  # (every word, then the long ones: "putamen lh")
        for kept in (words, [w for w in words if len(w) >= 3]):
            found = found or [n for n, label in labels.items() if all(w in label for w in kept)]
    if not found:
        close = difflib.get_close_matches(asked.lower(), sorted(set(labels.values())),
                                          n=MAX_SUGGESTIONS, cutoff=0.6)
        found = [n for c in close for n, label in labels.items() if label == c]
    return found[:MAX_SUGGESTIONS], max(0, len(found) - MAX_SUGGESTIONS)


def structure_mask(structure: Structure, shape: tuple[int, int, int], affine: NDArray,
                   to_template: NDArray) -> NDArray:
    """The structure on an image's grid: its indicator carried through ``to_template`` (image
    world -> template world), trilinear, kept at >= 0.5, with its holes filled.

    A label set of several labels is one object (the cerebellum's lobules): the holes its
    union leaves between them (the fourth ventricle's recess) are filled.
    """
    from scipy import ndimage

    s = structure.label_set
    inside = structure.voxels
    mask = np.zeros(tuple(shape), dtype=bool)
    if not inside.any():
        return mask
    # image voxel -> image world -> template world -> label set voxel
    to_labels = np.linalg.solve(s.affine, to_template @ np.asarray(affine, dtype=np.float64))
    # Only the image's box that the structure's box maps into (and a voxel around) is computed.
    idx = np.argwhere(inside)
    lo, hi = idx.min(axis=0) - 1, idx.max(axis=0) + 1
    corners = np.array([[a, b, c, 1.0] for a in (lo[0], hi[0]) for b in (lo[1], hi[1])
                        for c in (lo[2], hi[2])])
    in_image = np.linalg.solve(to_labels, corners.T)[:3]
    start = np.clip(np.floor(in_image.min(axis=1)).astype(int) - 1, 0, shape)
    stop = np.clip(np.ceil(in_image.max(axis=1)).astype(int) + 2, 0, shape)
    if np.any(stop <= start):
        return mask
    indicator = inside.astype(np.float32)
    offset = to_labels[:3, :3] @ start + to_labels[:3, 3]
    box = ndimage.affine_transform(indicator, to_labels[:3, :3], offset,
                                   output_shape=tuple(stop - start), order=1) >= 0.5
    mask[tuple(slice(a, b) for a, b in zip(start, stop))] = ndimage.binary_fill_holes(box)
    return mask


def atlas_start(image: NDArray, affine: NDArray, spacing, atlas: Atlas, structure: str | None,
                click_world: NDArray | None = None, params=None, m1: int | None = None,
                m2: int | None = None) -> tuple:
    """The atlas' structure on the image, fitted by a deformable sphere.

    Parameters
    ----------
    image, affine, spacing
        The image (index order), its NIfTI affine and voxel size (mm).
    atlas : Atlas
    structure : str or None
        As :func:`find_structure` takes it (None: the label under ``click_world``).
    click_world : ndarray, optional
        The click (image world mm).
    params : segsnake.registration.RegistrationParams, optional
    m1, m2 : int, optional
        The fit's size (both or neither); default the smallest in
        :data:`segsnake.fit.M2_SCHEDULE` within :data:`FIT_RMS_VOXELS` or
        :data:`FIT_RMS_PERCENT`.

    Returns
    -------
    (SphereModel, dict)
        The fit, in mm of the image's scaled index space, and a record: the structure, the
        image -> template maps (the head's and the refined), the mask's voxels, its pieces and
        the share of its voxels outside the largest (a snake is one closed surface: the largest
        piece is fitted), and the fit's errors.

    Raises
    ------
    InputError
        No such structure, or one that does not land on the image.
    segsnake.registration.RegistrationError
        The registration failed.
    """
    from scipy import ndimage

    from segsnake.fit import fit_mesh
    from segsnake.mask_mesh import mask_surface
    from segsnake.parameterize import TopologyError
    from segsnake.registration import refine_around, register_affine

    head = register_affine(image, affine, atlas.template, atlas.template_affine, params)
    found = find_structure(atlas, structure, click_world, head)
    focus = found.voxels
    if not focus.any():
        raise InputError(f"{found.label_set.path}: {found.description} is named in "
                         f"{found.label_set.name}.csv but drawn on no voxel")
    to_template = refine_around(image, affine, atlas.template, atlas.template_affine, head, focus,
                                found.label_set.affine, params)
    mask = structure_mask(found, image.shape, affine, to_template)
    if not mask.any():
        raise InputError(f"{atlas.folder}: the atlas' {found.description} lands on no voxel of "
                         f"the image (the registration placed it outside the field of view)")
    pieces, count = ndimage.label(mask)
    sizes = np.bincount(pieces.ravel())[1:]
    dropped = 1.0 - sizes.max() / sizes.sum()
    try:
        surface = mask_surface(mask, tuple(float(s) for s in spacing))
        diagonal = float(np.linalg.norm(np.ptp(surface.points, axis=0)))
        fit = fit_mesh(surface.points, surface.faces, m1=m1, m2=m2,
                       rms_target=None if m1 is not None else
                       max(FIT_RMS_VOXELS * float(min(spacing)),
                           FIT_RMS_PERCENT / 100.0 * diagonal))
    except (ValueError, TopologyError) as exc:
        raise InputError(f"{atlas.folder}: the atlas' {found.description} on the image cannot "
                         f"be fitted by a sphere: {exc}") from None
    record = {"atlas": os.path.abspath(atlas.folder), "structure": found.description,
              "labels": list(found.values), "image_to_template": to_template.tolist(),
              "head_to_template": head.tolist(),
              "mask_voxels": int(mask.sum()), "fit_rms_mm": fit.steps[-1].error.rms,
              "m1": fit.model.m1, "m2": fit.model.m2, "pieces": int(count),
              "dropped_fraction": float(dropped)}
    return fit.model, record
