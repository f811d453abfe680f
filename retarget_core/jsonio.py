"""Plain JSON types from the values the core computes (numpy arrays and scalars, dataclasses,
paths), for every JSON file and JSON string the core writes."""

from __future__ import annotations

import math
import os
from dataclasses import asdict, is_dataclass
from typing import Mapping

import numpy as np


def to_jsonable(value):
    """``value`` made of JSON types only, recursively:

    * a dataclass instance -> its ``to_dict()`` when it has one, else ``dataclasses.asdict``;
    * a mapping -> a dict whose keys are ``str(key)``;
    * a numpy array (any shape), list or tuple -> a list (a 0-d array -> its scalar);
    * bools -> bool, integers (numpy included) -> int, floats (numpy included) -> float, and
      every non-finite float (NaN, inf) -> None; any other numpy scalar -> ``.item()``;
    * a path (``os.PathLike``) -> ``os.fspath(value)``.

    Anything else (str, None, ...) is returned unchanged, so ``json.dumps`` still raises on a
    value JSON cannot hold."""
    if is_dataclass(value) and not isinstance(value, type):
        if hasattr(value, "to_dict"):
            return to_jsonable(value.to_dict())
        return to_jsonable(asdict(value))
    if isinstance(value, Mapping):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return [to_jsonable(v) for v in value.tolist()] if value.ndim else to_jsonable(value.item())
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return value if math.isfinite(value) else None
    if isinstance(value, np.generic):
        return to_jsonable(value.item())
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return value
