"""Run configuration (retarget_core.solve.config) and trajectory refinement
(retarget_core.refine)."""

import dataclasses
import math

import numpy as np
import pytest

from retarget_core.errors import InputError
from retarget_core.execute import Executor
from retarget_core.refine import (
    acceleration_violations,
    interpolate_violations,
    lowpass_and_remove_peaks,
    refine_trajectory,
)
from retarget_core.solve.config import PRESETS, RetargetConfig, load_config, n_control_points

FPS = 120.0
E_ANG = math.radians(500.0)  # rad/s^2
E_LIN = 5.0  # m/s^2


# ------------------------------------------------------------------------------------ config


def test_presets_load():
    assert set(PRESETS) == {"paper", "default"}
    paper = RetargetConfig.preset("paper")
    assert paper.solver.algorithm == "LD_MMA"
    assert paper.solver.maxeval == 100
    assert paper.solver.xtol_rel == pytest.approx(1e-4)
    assert paper.solver.gradient == "analytic"
    w = paper.weights
    assert (w.lambda_m, w.lambda_cd, w.lambda_cn, w.lambda_c, w.lambda_t) == (1, 1, 1, 1, 1)
    assert w.lambda_j == 50.0 and w.lambda_p == 0.0
    assert paper.refinement.e_acc_angular == 500.0 and paper.refinement.e_acc_linear == 500.0
    assert paper.refinement.e_acc_angular_si == pytest.approx(math.radians(500.0))
    assert paper.refinement.e_acc_linear_si == pytest.approx(5.0)
    assert paper.refinement.max_iterations == 20
    # how a run executes (workers, Dask scheduler, atlas cache) is the Executor's, not the run
    # configuration's: the presets no longer carry it
    assert not {"workers", "dask_scheduler", "atlas_cache"} & set(paper.to_dict())
    default = RetargetConfig.preset("default")
    assert default.solver.gradient == "analytic"
    # the paper's weights except the beyond-the-paper root gauge and a lighter prior (the
    # collision terms are off in both until they are cheap enough)
    assert dataclasses.replace(default.weights, lambda_r=0.0, lambda_j=50.0) == paper.weights
    assert paper.weights.lambda_r == 0.0 and default.weights.lambda_r > 0
    assert default.weights.lambda_p == 0.0 and default.weights.lambda_sc == 0.0
    assert default.weights.lambda_j == 20.0
    assert paper.refinement.patience == 0 and paper.solver.warm_start_iterations == 0
    assert not paper.contacts.keep_source_gap
    d = default.to_dict()
    assert d["solver"]["maxeval"] == default.solver.maxeval
    assert d["fit"]["control_points_per_second"] == default.fit.control_points_per_second
    # load_config with no file is the preset
    assert load_config(None, preset="paper") == paper
    with pytest.raises(InputError, match="preset"):
        RetargetConfig.preset("nope")


def test_toml_override_applies(tmp_path):
    p = tmp_path / "run.toml"
    p.write_text(
        "[weights]\nlambda_j = 20\nlambda_p = 0.5\n"
        "[solver]\nmaxeval = 40\n"
        "[refinement]\ne_acc_angular = 250.0\n"
        "[fit]\ncontrol_points = 60\n"
        "[passes]\nfilter = false\n"
    )
    cfg = load_config(p, preset="paper")
    assert cfg.weights.lambda_j == 20.0 and isinstance(cfg.weights.lambda_j, float)
    assert cfg.weights.lambda_p == 0.5
    assert cfg.weights.lambda_m == 1.0  # untouched keys keep the preset value
    assert cfg.solver.maxeval == 40
    assert cfg.solver.xtol_rel == pytest.approx(1e-4)
    assert cfg.refinement.e_acc_angular == 250.0
    assert cfg.fit.control_points == 60 and cfg.fit.control_points_per_second is None
    assert cfg.passes.filter is False and cfg.passes.refine is True
    # overrides go on top of the file; dotted and nested forms both work
    cfg2 = load_config(p, preset="paper", overrides={"solver.maxeval": 7,
                                                     "refinement": {"max_iterations": 5}})
    assert cfg2.solver.maxeval == 7 and cfg2.refinement.max_iterations == 5
    assert cfg2.weights.lambda_j == 20.0


@pytest.mark.parametrize(
    "text, key",
    [
        ("[solver]\nmaxevals = 10\n", "solver.maxevals"),
        ("[solvers]\nmaxeval = 10\n", "solvers"),
        ("bogus = 1\n", "bogus"),
        ("[weights]\nlambda_j = -1.0\n", "weights.lambda_j"),
        ("[solver]\nmaxeval = 0\n", "solver.maxeval"),
        ("[solver]\nmaxeval = \"many\"\n", "solver.maxeval"),
        ("[solver]\nmaxeval = 10.5\n", "solver.maxeval"),
        ("[passes]\nfit = 1\n", "passes.fit"),
        ("[refinement]\ne_acc_linear = 0\n", "refinement.e_acc_linear"),
        ("[solver]\ngradient = \"central\"\n", "solver.gradient"),
        ("weights = 3\n", "weights"),
        ("[markers]\ndistance = \"cubic\"\n", "markers.distance"),
        ("[markers]\nhuber_width = -0.1\n", "markers.huber_width"),
        ("[fit]\ncontrol_points = 60\ncontrol_points_per_second = 10.0\n", "fit.control_points"),
    ],
)
def test_bad_toml_names_the_key(tmp_path, text, key):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(InputError) as info:
        load_config(p)
    assert info.value.element == key
    assert key in str(info.value)
    assert str(p) in str(info.value)


def test_bad_override_names_the_key():
    with pytest.raises(InputError, match=r"solver\.maxevals: unknown key"):
        load_config(None, overrides={"solver.maxevals": 3})
    with pytest.raises(InputError, match=r"weights\.lambda_m"):
        load_config(None, overrides={"weights": {"lambda_m": -0.1}})


# The executor settings left the run configuration (they never change the result): an old TOML
# file or override that still sets one is refused, naming the executor option that replaces it.
# Formerly these tests read workers / dask_scheduler / atlas_cache back from the config.
EXECUTOR_OPTIONS = {"workers": "--workers", "dask_scheduler": "--dask-scheduler", "atlas_cache": "--atlas-cache"}


@pytest.mark.parametrize("key, toml", [("workers", "workers = 3\n"),
                                       ("dask_scheduler", 'dask_scheduler = "tcp://10.0.0.5:8786"\n'),
                                       ("atlas_cache", 'atlas_cache = "/tmp/atlases"\n')])
def test_executor_keys_in_a_toml_file_name_the_executor_option(tmp_path, key, toml):
    p = tmp_path / "run.toml"
    p.write_text(toml + "[solver]\nmaxeval = 40\n")
    with pytest.raises(InputError) as info:
        load_config(p)
    assert info.value.element == key
    assert str(p) in str(info.value)
    assert EXECUTOR_OPTIONS[key] in str(info.value) and "executor" in str(info.value)


@pytest.mark.parametrize("key, value", [("workers", 2), ("dask_scheduler", "tcp://127.0.0.1:8786"),
                                        ("atlas_cache", "/tmp/atlases")])
def test_executor_keys_in_overrides_name_the_executor_option(key, value):
    for overrides in ({key: value}, {key: value, "solver.maxeval": 7}):
        with pytest.raises(InputError) as info:
            load_config(None, overrides=overrides)
        assert info.value.element == key
        assert EXECUTOR_OPTIONS[key] in str(info.value) and "executor" in str(info.value)


def test_executor_validates_its_options():
    assert Executor().dask_scheduler == "" and Executor().workers == 1  # in-process by default
    for good in ("tcp://127.0.0.1:1", "tcp://dask-scheduler.internal:65535", "tcp://[::1]:8786", ""):
        assert Executor(dask_scheduler=good).dask_scheduler == good
        assert Executor(dask_scheduler=good).describe()["dask_scheduler"] == good
    for bad in ("127.0.0.1:8786", "tcp://host", "tcp://host:0", "tcp://host:70000", "http://host:8786",
                "tcp://host:8786/x", "tcp://ho st:8786", 8786):
        with pytest.raises(InputError) as info:
            Executor(dask_scheduler=bad)
        assert info.value.element == "executor.dask_scheduler", bad
        assert "executor.dask_scheduler" in str(info.value)
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(InputError) as info:
            Executor(workers=bad)
        assert info.value.element == "executor.workers", bad
    assert Executor(workers=3).describe()["workers"] == 3


def test_missing_and_malformed_file(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_config(tmp_path / "nope.toml")
    p = tmp_path / "broken.toml"
    p.write_text("[solver\nmaxeval = 3\n")
    with pytest.raises(InputError, match="invalid TOML"):
        load_config(p)


def test_n_control_points():
    paper = RetargetConfig.preset("paper")
    assert paper.n_control_points(703, 120.0) == 59  # ~60 in the paper's table
    assert paper.n_control_points(1145, 120.0) == 95
    cfg = load_config(None, overrides={"fit.control_points": 60})
    assert cfg.n_control_points(703, 120.0) == 60
    assert cfg.n_control_points(30, 120.0) == 30  # never more than the frames
    assert paper.n_control_points(10, 120.0) == 4  # at least a cubic segment
    assert n_control_points(1200, 120.0, paper) == 100
    with pytest.raises(InputError):
        paper.n_control_points(100, 0.0)


# ------------------------------------------------------------------------------ refinement


def _smooth(F=120, D=3):
    t = np.arange(F) / FPS
    q = np.stack([0.3 * np.sin(2 * np.pi * 0.5 * t + k) for k in range(D)], axis=1)
    q[:, -1] *= 0.1  # metres
    return q


IS_ROT = np.array([True, True, False])


def test_acceleration_violations_flag_spike_neighbours():
    q = _smooth()
    assert not acceleration_violations(q, FPS, IS_ROT, E_ANG, E_LIN).any()
    k = 50
    q[k, 1] += math.radians(5.0)  # second difference 5 deg at k±1, 10 deg at k (> 4.17 deg)
    v = acceleration_violations(q, FPS, IS_ROT, E_ANG, E_LIN)
    assert sorted(map(tuple, np.argwhere(v).tolist())) == [(k - 1, 1), (k, 1), (k + 1, 1)]
    # a spike of 3 degrees: only the centre (6 deg) exceeds 4.17 deg
    q2 = _smooth()
    q2[k, 0] += math.radians(3.0)
    v2 = acceleration_violations(q2, FPS, IS_ROT, E_ANG, E_LIN)
    assert sorted(map(tuple, np.argwhere(v2).tolist())) == [(k, 0)]
    # linear DOF: threshold 5 m/s^2 / 120 fps = 4.17 cm of second difference
    q3 = _smooth()
    q3[k, 2] += 0.03
    v3 = acceleration_violations(q3, FPS, IS_ROT, E_ANG, E_LIN)
    assert sorted(map(tuple, np.argwhere(v3).tolist())) == [(k, 2)]
    # end frames never violate
    q4 = _smooth()
    q4[0, 0] += 1.0
    q4[-1, 0] -= 1.0
    v4 = acceleration_violations(q4, FPS, IS_ROT, E_ANG, E_LIN)
    assert not v4[0].any() and not v4[-1].any() and v4[1, 0] and v4[-2, 0]


def test_interpolation_fills_gap_linearly():
    F = 20
    q = np.zeros((F, 2))
    q[:, 0] = np.arange(F) * 2.0
    q[:, 1] = 5.0
    q[6:10, 0] = 99.0
    viol = np.zeros((F, 2), dtype=bool)
    viol[6:10, 0] = True
    viol[0:3, 1] = True
    viol[17:, 1] = True
    q[0:3, 1] = -1.0
    q[17:, 1] = 7.0
    out = interpolate_violations(q, viol)
    np.testing.assert_allclose(out[:, 0], np.arange(F) * 2.0)
    np.testing.assert_allclose(out[:, 1], 5.0)  # ends hold the nearest valid value
    # unflagged entries untouched, input not modified
    assert q[7, 0] == 99.0
    # gap between unequal neighbours
    q = np.zeros((5, 1))
    q[0, 0], q[4, 0] = 1.0, 5.0
    v = np.zeros((5, 1), dtype=bool)
    v[1:4] = True
    np.testing.assert_allclose(interpolate_violations(q, v)[:, 0], [1, 2, 3, 4, 5])


def test_refine_converges_with_good_resolver():
    truth = _smooth()
    q = truth.copy()
    rng = np.random.default_rng(0)
    for k in (20, 21, 60, 90):
        q[k] += rng.normal(0, 0.3, size=3)
    calls = []

    def resolve(frames, seeds):
        calls.append(frames.copy())
        assert seeds.shape == (frames.size, 3)
        return truth[frames]

    out, rep = refine_trajectory(q, FPS, IS_ROT, resolve, e_acc_angular=E_ANG,
                                 e_acc_linear=E_LIN, max_iterations=20)
    assert rep.converged
    assert 1 <= rep.iterations <= 3
    assert rep.n_unresolved == 0 and rep.unresolved.shape == q.shape
    assert len(rep.violations_per_iteration) == rep.iterations + 1
    assert rep.violations_per_iteration[-1] == 0
    assert rep.frames_resolved_per_iteration[0] == calls[0].size
    assert {20, 21, 60, 90} <= set(calls[0].tolist())
    assert not acceleration_violations(out, FPS, IS_ROT, E_ANG, E_LIN).any()
    np.testing.assert_allclose(out, truth)
    assert rep.to_dict()["converged"] is True


def test_refine_seeds_are_interpolated_rows():
    truth = _smooth()
    q = truth.copy()
    q[40, 0] += 0.5
    seen = {}

    def resolve(frames, seeds):
        for f, s in zip(frames, seeds):
            seen.setdefault(int(f), s.copy())
        return seeds  # accept the interpolation as the solution

    out, rep = refine_trajectory(q, FPS, IS_ROT, resolve, e_acc_angular=E_ANG,
                                 e_acc_linear=E_LIN)
    assert rep.converged
    # frame 40's seed: DOF 0 interpolated between frames 38 and 42, other DOFs unchanged
    np.testing.assert_allclose(seen[40][0], 0.5 * (truth[38, 0] + truth[42, 0]))
    np.testing.assert_allclose(seen[40][1:], truth[40, 1:])


def test_refine_stops_at_cap_and_reports_unresolved():
    q = _smooth()
    k = 70
    q[k, 1] += 0.5
    spiked = q.copy()

    def resolve(frames, seeds):  # the solver keeps falling back into the bad minimum
        return spiked[frames]

    out, rep = refine_trajectory(q, FPS, IS_ROT, resolve, e_acc_angular=E_ANG,
                                 e_acc_linear=E_LIN, max_iterations=5)
    assert not rep.converged
    assert rep.iterations == 5
    assert len(rep.frames_resolved_per_iteration) == 5
    assert rep.violations_per_iteration == [3] * 6
    assert rep.n_unresolved == 3
    assert rep.unresolved_frames.tolist() == [k - 1, k, k + 1]
    assert rep.unresolved[:, 1].sum() == 3 and not rep.unresolved[:, [0, 2]].any()
    np.testing.assert_allclose(out, spiked)


def test_refine_zero_iterations_and_bad_resolver():
    q = _smooth()
    q[30, 0] += 0.5
    out, rep = refine_trajectory(q, FPS, IS_ROT, lambda f, s: s, e_acc_angular=E_ANG,
                                 e_acc_linear=E_LIN, max_iterations=0)
    assert rep.iterations == 0 and rep.n_unresolved == 3
    with pytest.raises(InputError, match="resolve"):
        refine_trajectory(q, FPS, IS_ROT, lambda f, s: s[:, :2], e_acc_angular=E_ANG,
                          e_acc_linear=E_LIN)
    bad = q.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InputError, match="frame 3"):
        acceleration_violations(bad, FPS, IS_ROT, E_ANG, E_LIN)


# ------------------------------------------------------------------------------ filtering


def test_lowpass_removes_high_frequency_keeps_slow():
    F = 600
    t = np.arange(F) / FPS
    slow = 0.5 * np.sin(2 * np.pi * 1.0 * t)
    fast = 0.05 * np.sin(2 * np.pi * 40.0 * t)
    q = np.stack([slow + fast, slow], axis=1)
    out, changed = lowpass_and_remove_peaks(q, FPS, cutoff_hz=10.0, peak_threshold=1.0)
    inner = slice(30, -30)
    np.testing.assert_allclose(out[inner, 0], slow[inner], atol=2e-3)
    np.testing.assert_allclose(out[inner, 1], slow[inner], atol=2e-3)
    assert changed.all()
    # with a tolerance only frames moved by more than it are flagged and others kept verbatim
    out2, changed2 = lowpass_and_remove_peaks(q, FPS, cutoff_hz=10.0, peak_threshold=1.0,
                                              change_tolerance=0.04)
    assert changed2.any() and not changed2.all()
    np.testing.assert_array_equal(out2[~changed2], q[~changed2])


def test_peak_removal_replaces_isolated_outlier():
    F = 200
    t = np.arange(F) / FPS
    q = np.stack([0.2 * np.sin(2 * np.pi * 0.5 * t), 0.01 * t], axis=1)
    clean = q.copy()
    q[100, 0] += 0.8
    out, changed = lowpass_and_remove_peaks(q, FPS, cutoff_hz=None,
                                            peak_threshold=[math.radians(10.0), 0.02])
    assert changed.tolist() == [f == 100 for f in range(F)]
    # replaced by the running median: within one frame's step (~5 mrad) of the clean value
    assert abs(out[100, 0] - clean[100, 0]) < 6e-3
    np.testing.assert_array_equal(out[np.arange(F) != 100], q[np.arange(F) != 100])


def test_filter_short_signals():
    for F in (1, 2, 3, 5, 12):
        q = np.linspace(0.0, 1.0, F)[:, None] * np.ones((1, 2))
        out, changed = lowpass_and_remove_peaks(q, FPS, cutoff_hz=10.0, peak_threshold=0.5)
        assert out.shape == q.shape and changed.shape == (F,)
        assert np.all(np.isfinite(out))
    # cutoff at or above Nyquist: no low-pass
    q = np.random.default_rng(1).normal(0, 0.01, size=(50, 2))
    out, changed = lowpass_and_remove_peaks(q, FPS, cutoff_hz=60.0, peak_threshold=1.0)
    np.testing.assert_array_equal(out, q)
    assert not changed.any()


def test_refinement_patience_stops_a_stale_loop_and_keeps_the_best_round():
    """A re-solve that always puts the spike back (the optimum really is there): with patience
    the loop stops after that many stale rounds instead of running to the cap."""
    fps = 120.0
    q = np.zeros((40, 1))
    q[20, 0] = 0.5  # a spike far above E_acc
    calls = []

    def resolve(frames, seeds):
        calls.append(len(frames))
        out = seeds.copy()
        out[frames == 20] = 0.5
        return out

    _, capped = refine_trajectory(q, fps, [True], resolve, e_acc_angular=1.0, e_acc_linear=1.0, max_iterations=20)
    assert capped.iterations == 20 and not capped.converged
    calls.clear()
    best, patient = refine_trajectory(q, fps, [True], resolve, e_acc_angular=1.0, e_acc_linear=1.0,
                                      max_iterations=20, patience=3)
    assert patient.iterations == 3 and len(calls) == 3  # no round beats the start: 3 stale ones
    assert patient.unresolved[20, 0] and best[20, 0] == 0.5
    assert patient.violations_per_iteration[-1] >= min(patient.violations_per_iteration)
