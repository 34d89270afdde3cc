"""Which voxels of a truth image are the structure: one label of a label map, or all non-zero.

A truth "mask" is often a label map (an atlas such as AAL: a hundred structures, each its own
value). Counting every non-zero voxel as the truth then compares a single structure with the
whole atlas (Dice near 0, silently); selecting one label compares it with that structure.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from segsnake.errors import InputError

__all__ = ["truth_foreground", "truth_mask", "describe_values", "label_map_warning"]

# How many of a label map's values a message lists before "...".
_SHOWN = 6


def describe_values(values: NDArray) -> str:
    """``"1, 2, 3, ..., 116"``: the first few of the sorted distinct ``values`` and the last."""
    shown = [f"{v:g}" for v in values[:_SHOWN]]
    if len(values) > _SHOWN:
        shown += ["...", f"{values[-1]:g}"]
    return ", ".join(shown)


def label_map_warning(path: str, values: NDArray, how: str) -> str:
    """The warning for a truth that holds several non-zero ``values`` and no label was chosen.

    ``how`` says how to choose one (the caller's option, e.g. ``"--label N"``).
    """
    return (f"{path}: holds {len(values)} different non-zero values ({describe_values(values)}): "
            f"a label map? Every non-zero voxel counts as the truth; compare with one structure "
            f"with {how}")


def truth_foreground(data: NDArray, label: int | None, path: str
                     ) -> tuple[NDArray[np.bool_], NDArray | None]:
    """The truth's foreground, and the label map's values when it looks like one.

    Parameters
    ----------
    data : ndarray
        The truth image's voxels.
    label : int or None
        Select the voxels equal to ``label``; None takes every non-zero voxel.
    path : str
        The truth's file, for messages.

    Returns
    -------
    (mask, values)
        The boolean foreground, and (only when ``label`` is None and the image holds more than
        one non-zero value, i.e. more than two values: a label map or a probability map) the
        sorted distinct non-zero values, so that the caller can warn; otherwise None.

    Raises
    ------
    InputError
        ``label`` does not occur in the image (the message lists the values that do).
    """
    if label is not None:
        mask = data == label
        if not mask.any():
            present = np.unique(data[data != 0])
            found = f"its non-zero values are {describe_values(present)}" if present.size \
                else "it is empty (all zero)"
            raise InputError(f"{path}: no voxel has label {label}; {found}")
        return mask, None
    mask = data != 0
    nonzero = data[mask]
    # Two passes over the non-zero voxels at most: np.unique (a sort) only for a label map.
    if nonzero.size and np.any(nonzero != nonzero[0]):
        return mask, np.unique(nonzero)
    return mask, None


def truth_mask(data: NDArray, label: int | None, path: str, how: str
               ) -> tuple[NDArray[np.bool_], list[str]]:
    """:func:`truth_foreground` and, for an unlabelled label map, its warning.

    ``how`` says how a user chooses a label (the caller's option, e.g. ``"--label N"``).
    """
    mask, values = truth_foreground(data, label, path)
    return mask, [] if values is None else [label_map_warning(path, values, how)]
