"""Every numeric configuration key has an upper bound as well as a lower one (issue 16, High:
"overrides have no upper bounds"; Low: "maxeval >= 2^31, lowpass_order 1e6 pass validation then
fail as an internal error"). On 328eb67 every value below above the old lower bounds was accepted."""

from __future__ import annotations

import dataclasses
import math
import typing

import pytest

from retarget_core.errors import InputError
from retarget_core.solve.config import BOUNDS, PRESETS, RetargetConfig, load_config

SECTIONS = ("weights", "solver", "refinement", "fit", "markers", "sampling")


def numeric_keys():
    cfg = RetargetConfig.preset("paper")
    keys = []
    for section in SECTIONS:
        obj = getattr(cfg, section)
        hints = typing.get_type_hints(type(obj))
        for f in dataclasses.fields(obj):
            tp = hints[f.name]
            args = set(typing.get_args(tp)) or {tp}
            if args & {int, float} and bool not in args:
                keys.append(f"{section}.{f.name}")
    return keys


def test_every_numeric_key_has_bounds():
    assert sorted(numeric_keys()) == sorted(BOUNDS)
    for key, (lo, hi, _) in BOUNDS.items():
        assert math.isfinite(hi) and lo < hi, key


@pytest.mark.parametrize("preset", PRESETS)
def test_presets_are_within_bounds(preset):
    RetargetConfig.preset(preset).validate()


def _value_beyond(key, hi):
    section, name = key.split(".")
    hints = typing.get_type_hints(type(getattr(RetargetConfig(), section)))
    is_int = int in (set(typing.get_args(hints[name])) or {hints[name]})
    if key == "refinement.peak_window":
        return int(hi) + 2  # odd, beyond
    return int(hi) + 1 if is_int else hi * 1.5


@pytest.mark.parametrize("key", sorted(BOUNDS))
def test_above_the_upper_bound_is_refused_naming_the_key_and_range(key):
    lo, hi, open_lo = BOUNDS[key]
    with pytest.raises(InputError) as err:
        load_config(None, overrides={key: _value_beyond(key, hi)})
    assert err.value.element == key
    assert f"{'(' if open_lo else '['}" in str(err.value) and "]" in str(err.value)
    # the bound itself is allowed
    load_config(None, overrides={key: hi if key != "fit.control_points" else int(hi)})


@pytest.mark.parametrize("key,value", [
    ("solver.maxeval", 2**31),                  # Low: nlopt took it as an internal error
    ("solver.root_maxeval", 2**31),
    ("refinement.max_iterations", 10**9),       # High: ran until cancelled
    ("refinement.lowpass_order", 10**6),        # Low: scipy failed inside the job
    ("solver.warm_start_iterations", 10**6),
    ("fit.control_points", 10**7),
    ("fit.control_points_per_second", 1e6),
    ("sampling.table_sample_stride", 10**9),
    ("weights.lambda_j", 1e300),
    ("weights.lambda_m", float("inf")),
    ("solver.xtol_rel", 2.0),
    ("refinement.peak_window", 10**6 + 1),
])
def test_issue_values_are_refused(key, value):
    with pytest.raises(InputError, match="must be in") as err:
        load_config(None, overrides={key: value})
    assert err.value.element == key
    assert key in str(err.value)


def test_lower_bounds_still_hold():
    for key, value in (("solver.maxeval", 0), ("weights.lambda_m", -0.1), ("refinement.lowpass_order", 0),
                       ("fit.control_points", 3), ("sampling.penetration_sample_stride", 0),
                       ("refinement.peak_window", 1), ("refinement.peak_window", 8), ("solver.fd_step", 0.0)):
        with pytest.raises(InputError) as err:
            load_config(None, overrides={key: value})
        assert err.value.element == key


def test_toml_file_values_are_bounded(tmp_path):
    p = tmp_path / "big.toml"
    p.write_text("[solver]\nmaxeval = 2147483648\n")
    with pytest.raises(InputError, match=r"solver\.maxeval: must be in \[1, 10000\]") as err:
        load_config(p)
    assert err.value.source == str(p)
