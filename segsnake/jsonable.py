"""Plain JSON values from the results segsnake computes (numpy scalars and arrays, paths, inf).

Strict JSON has no NaN or Infinity: non-finite floats become ``null`` (an infinite surface
distance, one mask being empty, is reported as ``null``, as the README documents).
"""

from __future__ import annotations

import math
import os
from typing import Any

__all__ = ["jsonable"]


def jsonable(value: Any) -> Any:
    """A copy of ``value`` made of dicts, lists, str, int, float, bool and None only.

    Parameters
    ----------
    value : object
        Nested dicts/lists/tuples of numbers (Python or numpy), strings, paths.

    Returns
    -------
    object
        The same structure in plain JSON types; non-finite floats are None, anything else
        unknown is its ``str``.
    """
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):  # also numpy.float64, a float subclass: make it a plain float
        return float(value) if math.isfinite(value) else None
    if hasattr(value, "item") and callable(value.item):  # numpy scalars
        try:
            return jsonable(value.item())
        except Exception:  # noqa: BLE001 - an array that is not a scalar: fall through
            pass
    if hasattr(value, "tolist"):
        return jsonable(value.tolist())
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return str(value)
