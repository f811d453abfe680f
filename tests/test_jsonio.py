"""The one numpy-to-JSON conversion (retarget_core.jsonio.to_jsonable) on hand-written values."""

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from retarget_core.jsonio import to_jsonable


@dataclass
class _Plain:
    a: np.ndarray
    b: float


@dataclass
class _WithToDict:
    a: int

    def to_dict(self):
        return {"doubled": self.a * 2}


def test_numpy_values_become_json_types():
    value = {
        "ints": np.arange(3, dtype=np.int32),
        "matrix": np.array([[1.5, np.nan], [np.inf, -np.inf]]),
        "scalar_array": np.array(2.25),
        "tuple": (np.float32(0.5), np.int64(7), np.bool_(True)),
        3: "int key",
        "strings": np.array(["x", "y"]),
        "path": Path("a") / "b.json",
        "none": None,
    }
    out = to_jsonable(value)
    assert out == {
        "ints": [0, 1, 2],
        "matrix": [[1.5, None], [None, None]],
        "scalar_array": 2.25,
        "tuple": [0.5, 7, True],
        "3": "int key",
        "strings": ["x", "y"],
        "path": str(Path("a") / "b.json"),
        "none": None,
    }
    assert type(out["ints"][0]) is int and type(out["tuple"][0]) is float and type(out["tuple"][2]) is bool
    assert type(out["strings"][0]) is str
    json.dumps(out, allow_nan=False)  # strict JSON: no NaN / Infinity tokens


def test_non_finite_python_floats_and_numpy_scalars_become_none():
    assert to_jsonable([math.nan, math.inf, np.float64(-np.inf), np.float16(np.nan), 1.0]) == [None, None, None, None,
                                                                                              1.0]
    assert to_jsonable(np.zeros((2, 0))) == [[], []]
    assert to_jsonable(()) == []


def test_dataclasses_use_their_to_dict_when_they_have_one():
    assert to_jsonable(_Plain(np.array([1.0, np.nan]), 2.0)) == {"a": [1.0, None], "b": 2.0}
    assert to_jsonable([_WithToDict(np.int64(4))]) == [{"doubled": 8}]


def test_values_json_cannot_hold_are_left_for_json_to_refuse():
    thing = object()
    assert to_jsonable({"x": thing})["x"] is thing
    with pytest.raises(TypeError):
        json.dumps(to_jsonable({"x": thing}))
