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

SECTIONS = tuple(f.name for f in dataclasses.fields(RetargetConfig) if dataclasses.is_dataclass(getattr(RetargetConfig(), f.name)))


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


# ---- a demo hand's resolution (issue 16, High: a clip's "demo:source_human@0.0007" took the job
# process to 1.6 GB; Low: "@0" passed validation and failed as an internal error)

@pytest.mark.parametrize("res", ["0", "0.0", "-0.004", "nan", "inf", "-inf", "0.0007", "0.0005", "0.021", "1", "x",
                                 "1e-300"])
def test_resolve_rig_refuses_a_demo_resolution_out_of_range(res):
    from retarget_core.rig.io import resolve_rig

    with pytest.raises(InputError, match="1 to 20 mm") as err:
        resolve_rig(f"demo:source_human@{res}")
    assert err.value.element == "rig"


def test_resolve_rig_builds_within_range():
    from retarget_core.rig.io import DEMO_RESOLUTION_RANGE, demo_resolution, resolve_rig

    assert DEMO_RESOLUTION_RANGE == (0.001, 0.02)
    assert demo_resolution("0.001") == 0.001 and demo_resolution("0.02") == 0.02
    assert demo_resolution("") == 0.002
    assert resolve_rig("demo:robot4@0.02").surface.n_vertices > 0


@pytest.mark.parametrize("res", ["0", "0.0007", "nan", "-1", "inf"])
def test_a_clip_may_not_choose_a_tiny_source_resolution(res):
    import types

    from retarget_core.inputs import clip_source_rig

    with pytest.raises(InputError, match="resolution") as err:
        clip_source_rig(types.SimpleNamespace(source_rig=f"demo:source_human@{res}"))
    assert err.value.element == "source_rig"


def test_a_clip_may_not_name_an_unknown_demo_hand():
    import types

    from retarget_core.inputs import clip_source_rig

    with pytest.raises(InputError, match="unknown demo hand") as err:
        clip_source_rig(types.SimpleNamespace(source_rig="demo:nobody@0.004"))
    assert err.value.element == "source_rig"
