"""dcc_client.curves: cubic B-splines -> Blender F-curve keyframes (standard library only),
checked against scipy, the core's BSplineCurve, a real fit and the USD export."""

import ast
import json
import math
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.interpolate import BSpline

from dcc_client.curves import (
    DofCurve,
    Keyframe,
    Keyframes,
    bezier_keyframes_eval,
    bspline_eval,
    bspline_to_keyframes,
    curves_from_result_json,
)
from retarget_core.fit import BSplineCurve, fit_trajectory

MODULE = Path(__file__).resolve().parents[1] / "dcc_client" / "curves.py"
TOL = 1e-9


def random_clamped(rng, n, kind="nonuniform", degree=3, end=None):
    """(knots, coeffs) of a random clamped B-spline on [0, end] seconds. kind: "uniform",
    "nonuniform", "double" / "triple" (one interior knot repeated 2 / 3 times)."""
    end = float(rng.uniform(0.5, 5.0)) if end is None else end
    n_inner = n - degree - 1
    if kind == "uniform":
        inner = np.linspace(0.0, end, n_inner + 2)[1:-1]
    else:
        inner = np.sort(rng.uniform(0.02 * end, 0.98 * end, n_inner))
        if kind in ("double", "triple") and n_inner >= 3:
            m = 2 if kind == "double" else 3
            inner[1:1 + m] = inner[1]
    knots = np.concatenate([np.zeros(degree + 1), inner, np.full(degree + 1, end)])
    coeffs = rng.normal(scale=rng.uniform(0.1, 3.0), size=n)
    return knots, coeffs


def f32(x):
    return struct.unpack("f", struct.pack("f", x))[0]


def keys_error(keys, curve, fps, start_frame, times):
    """max |F-curve(start + t fps) - curve(t)| over times (seconds)."""
    got = np.array([bezier_keyframes_eval(keys, start_frame + t * fps) for t in times])
    return float(np.abs(got - curve(times)).max())


# ---- de Boor -------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["uniform", "nonuniform", "double", "triple"])
def test_de_boor_equals_scipy_with_derivatives(kind):
    rng = np.random.default_rng({"uniform": 1, "nonuniform": 2, "double": 3, "triple": 4}[kind])
    worst = 0.0
    for _ in range(12):
        knots, coeffs = random_clamped(rng, int(rng.integers(4, 16)), kind)
        ref = BSpline(knots, coeffs, 3, extrapolate=True)
        a, b = knots[0], knots[-1]
        # inside, at every knot (right-continuous; left limit at the end), and outside
        times = np.concatenate([rng.uniform(a, b, 60), knots, [a - 0.3, b + 0.4]])
        for m in range(5):
            want = ref(times, nu=m)
            got = np.array([bspline_eval(list(knots), list(coeffs), float(t), derivative=m) for t in times])
            scale = max(1.0, float(np.abs(want).max()))
            err = float(np.abs(got - want).max()) / scale
            worst = max(worst, err)
            assert err <= 1e-12, (m, err)
    print(f"de Boor vs scipy ({kind}): max relative error {worst:.2e}")


def test_de_boor_other_degrees_and_unclamped_knots():
    rng = np.random.default_rng(5)
    for degree in (0, 1, 2, 4, 5):
        n = degree + 5
        knots = np.sort(rng.uniform(0, 3, n + degree + 1))  # unclamped: base interval [t_p, t_n]
        coeffs = rng.normal(size=n)
        ref = BSpline(knots, coeffs, degree)
        times = np.concatenate([rng.uniform(knots[degree], knots[n], 40), knots[degree:n + 1]])
        for m in range(degree + 2):
            want = ref(times, nu=m)
            got = np.array([bspline_eval(knots, coeffs, t, degree=degree, derivative=m) for t in times])
            assert np.abs(got - want).max() <= 1e-12 * max(1.0, np.abs(want).max()), (degree, m)


def test_de_boor_one_sided_at_knots():
    """Right-continuous inside; the left limit at the last knot; a triple knot has a kink."""
    knots = [0, 0, 0, 0, 1, 1, 1, 2, 2, 2, 2]
    coeffs = [0.0, 1.0, 3.0, 2.0, -1.0, 0.5, 4.0]
    curve = BSplineCurve(knots, coeffs)
    assert bspline_eval(knots, coeffs, 1.0) == pytest.approx(curve(1.0), abs=1e-15)
    assert bspline_eval(knots, coeffs, 1.0, derivative=1) == pytest.approx(curve.derivative(1.0), abs=1e-12)
    # derivative 1 right at 1: from the second piece; just before 1: the first piece
    left = BSpline(np.array(knots, float), np.array(coeffs), 3)(1.0 - 1e-9, nu=1)
    assert abs(bspline_eval(knots, coeffs, 1.0, derivative=1) - left) > 1.0
    assert bspline_eval(knots, coeffs, 2.0) == pytest.approx(coeffs[-1], abs=1e-15)
    assert bspline_eval(knots, coeffs, 2.0, derivative=1) == pytest.approx(curve.derivative(2.0), abs=1e-12)


# ---- keyframes -----------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["uniform", "nonuniform", "double", "triple"])
def test_keyframes_equal_bspline(kind):
    rng = np.random.default_rng({"uniform": 11, "nonuniform": 12, "double": 13, "triple": 14}[kind])
    fps, start = 30.0, 0.0
    worst = 0.0
    for _ in range(15):
        knots, coeffs = random_clamped(rng, int(rng.integers(4, 30)), kind)
        keys = bspline_to_keyframes(list(knots), list(coeffs), fps=fps, start_frame=start)
        breaks = np.unique(knots)
        assert isinstance(keys, Keyframes) and keys.extrapolation == "CONSTANT"
        assert len(keys) == len(breaks)
        np.testing.assert_allclose([k.frame for k in keys], start + breaks * fps, rtol=0, atol=1e-12)
        for i, k in enumerate(keys):
            assert isinstance(k, Keyframe) and k.interpolation == "BEZIER"
            assert k.handle_left_type == k.handle_right_type == "FREE"
            # handles a third of the adjacent interval away
            h_prev = (k.frame - keys[i - 1].frame) if i else (keys[1].frame - k.frame)
            h_next = (keys[i + 1].frame - k.frame) if i < len(keys) - 1 else h_prev
            assert k.handle_left[0] == pytest.approx(k.frame - h_prev / 3, abs=1e-12)
            assert k.handle_right[0] == pytest.approx(k.frame + h_next / 3, abs=1e-12)
        times = rng.uniform(knots[0], knots[-1], 100)
        scipy_ref = BSpline(knots, coeffs, 3)
        core = BSplineCurve(knots, coeffs)
        err_scipy = keys_error(keys, scipy_ref, fps, start, times)
        err_core = keys_error(keys, core, fps, start, times)
        # at the keys, and held outside
        err_keys = keys_error(keys, core, fps, start, np.concatenate([breaks, [knots[0] - 1.0, knots[-1] + 2.0]]))
        worst = max(worst, err_scipy, err_core, err_keys)
        assert err_scipy <= TOL and err_core <= TOL and err_keys <= TOL
    print(f"keyframes vs B-spline ({kind}): max error {worst:.2e}")


def test_linear_extrapolation_follows_end_slopes():
    rng = np.random.default_rng(21)
    knots, coeffs = random_clamped(rng, 9)
    curve = BSplineCurve(knots, coeffs, extrapolation="linear")
    keys = bspline_to_keyframes(knots, coeffs, fps=24.0, start_frame=1.0, extrapolation="linear")
    assert keys.extrapolation == "LINEAR"
    times = np.concatenate([rng.uniform(knots[0] - 2, knots[-1] + 2, 100), [knots[0] - 5, knots[-1] + 5]])
    assert keys_error(keys, curve, 24.0, 1.0, times) <= TOL
    # the same keys with CONSTANT extrapolation hold the end values
    held = BSplineCurve(knots, coeffs, extrapolation="held")
    assert keys_error(keys, held, 24.0, 1.0, times) > 1e-3
    got = [bezier_keyframes_eval(keys, 1.0 + t * 24.0, "CONSTANT") for t in times]
    np.testing.assert_allclose(got, held(times), rtol=0, atol=TOL)


@pytest.mark.parametrize("degree", [1, 2])
def test_lower_degrees(degree):
    rng = np.random.default_rng(30 + degree)
    for _ in range(5):
        knots, coeffs = random_clamped(rng, int(rng.integers(degree + 1, 12)), degree=degree)
        keys = bspline_to_keyframes(knots, coeffs, fps=25.0, degree=degree)
        times = rng.uniform(knots[0], knots[-1], 100)
        assert keys_error(keys, BSpline(knots, coeffs, degree), 25.0, 0.0, times) <= TOL


@pytest.mark.parametrize("fps, start_frame", [(24.0, 1.0), (29.97, 0.0), (60.0, -10.5), (23.976, 1001.0)])
def test_fps_and_start_frame_mapping(fps, start_frame):
    rng = np.random.default_rng(40)
    knots, coeffs = random_clamped(rng, 12, end=3.0)
    keys = bspline_to_keyframes(knots, coeffs, fps=fps, start_frame=start_frame)
    # frame = start_frame + t * fps; the clip's t = 0 is start_frame
    assert keys[0].frame == start_frame
    assert keys[-1].frame == pytest.approx(start_frame + 3.0 * fps, abs=1e-9)
    np.testing.assert_allclose([k.frame for k in keys], start_frame + np.unique(knots) * fps, rtol=0, atol=1e-9)
    assert keys[0].value == pytest.approx(coeffs[0], abs=1e-14)
    assert keys[-1].value == pytest.approx(coeffs[-1], abs=1e-14)
    times = rng.uniform(0, 3.0, 100)
    assert keys_error(keys, BSplineCurve(knots, coeffs), fps, start_frame, times) <= TOL
    # whole frames of the clip: frame k of the clip is t = k / fps
    clip_frames = np.arange(int(3.0 * fps))
    got = [bezier_keyframes_eval(keys, start_frame + k) for k in clip_frames]
    np.testing.assert_allclose(got, BSplineCurve(knots, coeffs)(clip_frames / fps), rtol=0, atol=TOL)


def test_keys_accept_mappings():
    knots, coeffs = random_clamped(np.random.default_rng(41), 7)
    keys = bspline_to_keyframes(knots, coeffs, fps=30.0)
    as_dicts = [k._asdict() for k in keys]
    frames = [t * 30.0 for t in np.linspace(-0.5, knots[-1] + 0.5, 23)]
    for f in frames:
        assert bezier_keyframes_eval(as_dicts, f) == bezier_keyframes_eval(keys, f)
    # a sequence of frames gives a list
    assert bezier_keyframes_eval(keys, frames) == [bezier_keyframes_eval(keys, f) for f in frames]
    assert bezier_keyframes_eval(keys, np.array(frames)) == [bezier_keyframes_eval(keys, f) for f in frames]


# ---- a real fit, the USD export, result.json ------------------------------------------------
def synthetic_fit(n_frames=90, fps=30.0):
    t = np.arange(n_frames) / fps
    q = np.stack([0.4 * np.sin(2.1 * t) + 0.1 * np.cos(7.0 * t), 0.02 * t ** 2 - 0.3, np.tanh(3 * (t - 1.5))], axis=1)
    return t, fit_trajectory(t, q, 12, optimize_knots=True)


def test_real_fitted_curve():
    fps = 30.0
    t, curves = synthetic_fit(fps=fps)
    rng = np.random.default_rng(50)
    worst, worst32 = 0.0, 0.0
    for c in curves:
        interior = c.knots[4:-4]
        assert len(np.unique(interior)) == len(interior)  # the fit's knots: no repeats
        keys = bspline_to_keyframes(c.knots.tolist(), c.coeffs.tolist(), fps=fps, extrapolation=c.extrapolation)
        times = np.concatenate([rng.uniform(t[0], t[-1], 100), t])
        err = keys_error(keys, c, fps, 0.0, times)
        worst = max(worst, err)
        assert err <= TOL
        # what Blender stores: 32-bit floats
        keys32 = [Keyframe(f32(k.frame), f32(k.value), tuple(map(f32, k.handle_left)), tuple(map(f32, k.handle_right)))
                  for k in keys]
        worst32 = max(worst32, keys_error(keys32, c, fps, 0.0, times))
    print(f"fitted curves: max error {worst:.2e}; with float32 keys {worst32:.2e}")
    assert worst32 < 1e-5


@pytest.fixture(scope="module")
def usd_result(tmp_path_factory):
    from retarget_core.export import write_animation_usd
    from retarget_core.rig.demo_hands import demo_hand

    rig = demo_hand("prosthetic_2dof", resolution=0.006)
    fps, n_frames = 30.0, 75
    times = np.arange(n_frames) / fps
    rng = np.random.default_rng(60)
    q = np.empty((n_frames, rig.n_dofs))
    for d in range(rig.n_dofs):
        lo, hi = max(rig.lower[d], rig.rest_pose[d] - 0.05), min(rig.upper[d], rig.rest_pose[d] + 0.05)
        w, ph = rng.uniform(0.5, 3.0), rng.uniform(0, 2 * np.pi)
        q[:, d] = 0.5 * (lo + hi) + 0.4 * (hi - lo) * np.sin(w * times + ph)
    curves = fit_trajectory(times, q, 10)
    out = tmp_path_factory.mktemp("usd") / "animation.usda"
    write_animation_usd(out, rig=rig, rig_file=None, dof_curves=curves, fps=fps, n_frames=n_frames)
    return dict(path=out, rig=rig, curves=curves, fps=fps, n_frames=n_frames)


def test_curve_read_back_from_usd(usd_result):
    from retarget_core.export import read_dof_bsplines, read_dof_splines

    fps = usd_result["fps"]
    back = read_dof_bsplines(usd_result["path"])
    splines = read_dof_splines(usd_result["path"])
    assert sorted(back) == sorted(usd_result["rig"].dof_names)
    codes = np.linspace(-5.0, usd_result["n_frames"] + 5.0, 100)  # time codes = frames, incl. extrapolation
    worst, worst_ts, worst_handles = 0.0, 0.0, 0.0
    for name, curve in zip(usd_result["rig"].dof_names, usd_result["curves"]):
        b = back[name]
        # frame 0 = time code 0 = t 0
        keys = bspline_to_keyframes(b.knots.tolist(), b.coeffs.tolist(), fps=fps, start_frame=0.0,
                                    extrapolation=b.extrapolation)
        got = np.array([bezier_keyframes_eval(keys, c) for c in codes])
        ts = np.array([splines[name].Eval(float(c)) for c in codes])
        err, err_ts = float(np.abs(got - curve(codes / fps)).max()), float(np.abs(got - ts).max())
        worst, worst_ts = max(worst, err), max(worst_ts, err_ts)
        assert err <= TOL and err_ts <= TOL
        # the Ts knots are the same keys: time, value and handles (width, slope per time code)
        knots = splines[name].GetKnots()
        times = sorted(knots.keys())
        assert len(times) == len(keys)
        for i, (tc, k) in enumerate(zip(times, keys)):
            kn = knots[tc]
            d = [abs(tc - k.frame), abs(kn.GetValue() - k.value)]
            if i > 0:
                w, s = kn.GetPreTanWidth(), kn.GetPreTanSlope()
                d += [abs(tc - w - k.handle_left[0]), abs(kn.GetValue() - s * w - k.handle_left[1])]
            if i < len(keys) - 1:
                w, s = kn.GetPostTanWidth(), kn.GetPostTanSlope()
                d += [abs(tc + w - k.handle_right[0]), abs(kn.GetValue() + s * w - k.handle_right[1])]
            worst_handles = max(worst_handles, max(d))
    print(f"USD read-back: keys vs curve {worst:.2e}, vs Ts.Spline.Eval {worst_ts:.2e}, "
          f"keys vs Ts knots {worst_handles:.2e}")
    assert worst_handles <= 1e-12


def _result_doc(curves, fps=30.0):
    """A result.json document as RetargetResult.to_dict / write produce it."""
    from retarget_core.result import RetargetResult

    n, d = 5, len(curves)
    res = RetargetResult(
        rig_name="hand", dof_names=[f"dof_{i}" for i in range(d)], dof_kinds=["rotate"] * d,
        lower=-np.ones(d), upper=np.ones(d), fps=fps, times=np.arange(n) / fps, q=np.zeros((n, d)), curves=curves,
        unresolved=np.zeros((n, d), bool), timings={}, counts={}, contact_distance_mm=np.full(n, np.nan),
        contact_count=np.zeros(n, int), marker_error_mm=np.full(n, np.nan), summary={}, config={})
    return json.loads(json.dumps(res.to_dict(), allow_nan=False))


def test_curves_from_result_json():
    fps = 30.0
    t, curves = synthetic_fit(fps=fps)
    curves[1].extrapolation = "linear"
    doc = _result_doc(curves, fps)
    for source in (doc, json.dumps(doc), json.dumps(doc).encode()):
        out = curves_from_result_json(source)
        assert list(out) == ["dof_0", "dof_1", "dof_2"]
        for c, (name, dc) in zip(curves, out.items()):
            knots, coeffs = dc  # unpacks as a pair
            assert isinstance(dc, DofCurve) and dc.degree == 3 and dc.extrapolation == c.extrapolation
            assert knots == c.knots.tolist() and coeffs == c.coeffs.tolist()
            keys = bspline_to_keyframes(knots, coeffs, fps=doc["fps"], extrapolation=dc.extrapolation)
            times = np.linspace(-0.5, t[-1] + 0.5, 100)
            assert keys_error(keys, c, fps, 0.0, times) <= TOL


def test_curves_from_result_json_errors():
    t, curves = synthetic_fit()
    doc = _result_doc(curves)
    with pytest.raises(ValueError, match="format"):
        curves_from_result_json({**doc, "format": "other"})
    # result.json is at version 2 now (RESULT_VERSION; it gained unused_settings, frames and
    # provenance), so the version a reader must refuse is the next one
    from retarget_core.result import RESULT_VERSION

    with pytest.raises(ValueError, match="version"):
        curves_from_result_json({**doc, "version": RESULT_VERSION + 1})
    with pytest.raises(ValueError, match="fit pass was off"):
        curves_from_result_json({**doc, "curves": None})
    with pytest.raises(ValueError, match="one per DOF"):
        curves_from_result_json({**doc, "curves": doc["curves"][:2]})
    with pytest.raises(ValueError, match="not valid JSON"):
        curves_from_result_json("{nope")
    bad = json.loads(json.dumps(doc))
    bad["curves"][2]["knots"][5] = None  # NaN is written as null
    with pytest.raises(ValueError, match=r"curves\[2\] \(DOF 'dof_2'\): knot 5"):
        curves_from_result_json(bad)
    bad = json.loads(json.dumps(doc))
    bad["curves"][1]["coefficients"].pop()
    with pytest.raises(ValueError, match=r"curves\[1\].*wrong number of knots"):
        curves_from_result_json(bad)
    bad = json.loads(json.dumps(doc))
    bad["curves"][0]["extrapolation"] = "cycle"
    with pytest.raises(ValueError, match="extrapolation"):
        curves_from_result_json(bad)


# ---- general Bezier segments (as Blender evaluates arbitrary handles) -----------------------
def _bez(p, u):
    s = 1 - u
    return s ** 3 * p[0] + 3 * s * s * u * p[1] + 3 * s * u * u * p[2] + u ** 3 * p[3]


def test_arbitrary_free_handles_solved_for_u():
    rng = np.random.default_rng(70)
    worst = 0.0
    for _ in range(200):
        f0, f1 = 0.0, float(rng.uniform(1, 40))
        # handles anywhere inside the segment (x(u) monotone), values anywhere
        x1, x2 = f0 + rng.uniform(0, 1) * (f1 - f0), f1 - rng.uniform(0, 1) * (f1 - f0)
        y = rng.normal(size=4)
        keys = [Keyframe(f0, y[0], (f0 - 1, 0.0), (x1, y[1])), Keyframe(f1, y[3], (x2, y[2]), (f1 + 1, 0.0))]
        for u in rng.uniform(0, 1, 5):
            frame = _bez((f0, x1, x2, f1), u)
            if not f0 < frame < f1:
                continue
            got = bezier_keyframes_eval(keys, frame)
            assert abs(got - _bez(y, u)) <= TOL
            worst = max(worst, abs(got - _bez(y, u)))
    print(f"arbitrary handles: max error {worst:.2e}")


def test_non_monotone_and_overlong_handles():
    # handles crossing (x(u) turns back): Blender takes the first u with x(u) = frame
    keys = [Keyframe(0.0, 0.0, (-1.0, 0.0), (9.0, 1.0)), Keyframe(10.0, 1.0, (1.0, 0.0), (11.0, 1.0))]
    for frame in (0.5, 3.0, 5.0, 9.5):
        us = np.linspace(0, 1, 200001)
        xs = _bez((0.0, 9.0, 1.0, 10.0), us)
        first = us[np.argmax(xs >= frame)]
        assert bezier_keyframes_eval(keys, frame) == pytest.approx(_bez((0.0, 1.0, 0.0, 1.0), first), abs=1e-4)
    # a handle longer than the segment is shortened along itself (Blender's correction)
    long = [Keyframe(0.0, 0.0, (-1.0, 0.0), (20.0, 4.0)), Keyframe(10.0, 1.0, (7.0, 1.0), (11.0, 1.0))]
    short = [Keyframe(0.0, 0.0, (-1.0, 0.0), (10.0, 2.0)), Keyframe(10.0, 1.0, (7.0, 1.0), (11.0, 1.0))]
    for frame in np.linspace(0.1, 9.9, 17):
        assert bezier_keyframes_eval(long, frame) == pytest.approx(bezier_keyframes_eval(short, frame), abs=1e-12)


def test_segment_interpolation_modes():
    keys = [{"frame": 0.0, "value": 1.0, "handle_left": (-1, 1), "handle_right": (1, 5), "interpolation": "LINEAR"},
            {"frame": 4.0, "value": 3.0, "handle_left": (3, 0), "handle_right": (5, 9), "interpolation": "CONSTANT"},
            {"frame": 6.0, "value": -1.0, "handle_left": (5, 0), "handle_right": (7, 0)}]
    assert bezier_keyframes_eval(keys, 1.0) == pytest.approx(1.5)
    assert bezier_keyframes_eval(keys, 5.0) == 3.0
    assert bezier_keyframes_eval(keys, 8.0, "LINEAR") == pytest.approx(1.0)  # along the right handle: slope 1
    assert bezier_keyframes_eval(keys, -2.0, "LINEAR") == pytest.approx(0.0)  # LINEAR first key: towards key 2
    assert bezier_keyframes_eval(keys, -2.0) == 1.0


# ---- bad input -----------------------------------------------------------------------------
GOOD_K = [0, 0, 0, 0, 0.5, 1, 1, 1, 1]
GOOD_C = [0.0, 1.0, 2.0, 1.0, 0.0]


@pytest.mark.parametrize("knots, coeffs, kwargs, match", [
    (GOOD_K[:-1], GOOD_C, {}, "wrong number of knots: 8 for 5 coefficients"),
    (GOOD_K, GOOD_C + [1.0], {}, "wrong number of knots"),
    ([0, 0, 0, 1, 1, 1, 1], [0.0, 1.0, 2.0], {}, "at least 4 coefficients, got 3"),
    ([0, 0, 0, 0, 0.7, 0.5, 1, 1, 1], GOOD_C, {}, "non-decreasing: knot 5 = 0.5 < knot 4 = 0.7"),
    ([0, 0, 0, 0, math.nan, 1, 1, 1, 1], GOOD_C, {}, "knot 4 must be finite"),
    (GOOD_K, [0.0, math.nan, 2.0, 1.0, 0.0], {}, "coefficient 1 must be finite"),
    (GOOD_K, [0.0, math.inf, 2.0, 1.0, 0.0], {}, "coefficient 1 must be finite"),
    (GOOD_K, ["a", 1.0, 2.0, 1.0, 0.0], {}, "coefficient 0 must be a number"),
    ([1] * 9, GOOD_C, {}, "empty interval"),
    ([0, 0, 0, 0.1, 0.5, 1, 1, 1, 1], GOOD_C, {}, "clamped"),
    ([0, 0, 0, 0, 0, 1, 1, 1, 1], GOOD_C, {}, "clamped"),
    ([0] * 4 + [0.5] * 4 + [1] * 4, [0.0] * 8, {}, "interior knot 0.5 appears 4 times"),
    (GOOD_K, GOOD_C, {"fps": 0.0}, "fps must be positive"),
    (GOOD_K, GOOD_C, {"fps": math.nan}, "fps must be finite"),
    (GOOD_K, GOOD_C, {"start_frame": math.inf}, "start_frame must be finite"),
    (GOOD_K, GOOD_C, {"extrapolation": "cycle"}, "extrapolation must be one of"),
    ([0, 0, 0, 0, 0, 1, 1, 1, 1, 1], GOOD_C, {"degree": 4}, "degrees 1 to 3"),
    (GOOD_K, GOOD_C, {"degree": 2.5}, "degree must be an integer"),
    (GOOD_K, GOOD_C, {"degree": None}, "degree must be an integer"),
])
def test_bad_keyframe_input(knots, coeffs, kwargs, match):
    kwargs = {"fps": 30.0, **kwargs}
    with pytest.raises(ValueError, match=match):
        bspline_to_keyframes(knots, coeffs, **kwargs)


def test_bad_eval_input():
    with pytest.raises(ValueError, match="t must be finite"):
        bspline_eval(GOOD_K, GOOD_C, math.nan)
    with pytest.raises(ValueError, match="derivative must be an integer >= 0"):
        bspline_eval(GOOD_K, GOOD_C, 0.5, derivative=-1)
    with pytest.raises(ValueError, match="wrong number of knots"):
        bspline_eval(GOOD_K, GOOD_C[:-1], 0.5)
    with pytest.raises(ValueError, match="non-decreasing"):
        bspline_eval([0, 0, 0, 0, 1, 0.5, 1, 1, 1], GOOD_C, 0.5)
    keys = bspline_to_keyframes(GOOD_K, GOOD_C, fps=30.0)
    with pytest.raises(ValueError, match="no keyframes"):
        bezier_keyframes_eval([], 1.0)
    with pytest.raises(ValueError, match="frames must increase: keyframe 1"):
        bezier_keyframes_eval([keys[0], keys[0], keys[1]], 1.0)
    with pytest.raises(ValueError, match="frame must be finite"):
        bezier_keyframes_eval(keys, math.nan)
    with pytest.raises(ValueError, match="frame 1 must be finite"):
        bezier_keyframes_eval(keys, [0.0, math.inf])
    with pytest.raises(ValueError, match="extrapolation must be"):
        bezier_keyframes_eval(keys, 1.0, "CYCLE")
    with pytest.raises(ValueError, match="keyframe 0 has no 'handle_right'"):
        bezier_keyframes_eval([{"frame": 0, "value": 0, "handle_left": (0, 0)}], 1.0)


# ---- standard library only -----------------------------------------------------------------
def test_module_imports_only_the_standard_library():
    tree = ast.parse(MODULE.read_text(encoding="utf-8"))
    modules = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            modules.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, "relative import"
            modules.add(node.module.split(".")[0])
        elif isinstance(node, ast.Call) and getattr(node.func, "id", None) == "__import__":
            pytest.fail("dynamic import")
    assert modules, "no imports found"
    outside = sorted(m for m in modules if m not in sys.stdlib_module_names)
    assert outside == [], f"imports outside the standard library: {outside}"


def test_module_runs_without_site_packages():
    """In a Python without site-packages (as Blender's, without numpy / scipy)."""
    code = (
        "import importlib.util, sys\n"
        f"spec = importlib.util.spec_from_file_location('curves', {str(MODULE)!r})\n"
        "m = importlib.util.module_from_spec(spec); spec.loader.exec_module(m)\n"
        "keys = m.bspline_to_keyframes([0,0,0,0,0.5,1,1,1,1], [0,1,2,1,0], fps=30.0, start_frame=1.0)\n"
        "v = m.bezier_keyframes_eval(keys, 1.0 + 0.25 * 30.0)\n"
        "assert abs(v - m.bspline_eval([0,0,0,0,0.5,1,1,1,1], [0,1,2,1,0], 0.25)) < 1e-12\n"
        "assert not any(n in sys.modules for n in ('numpy', 'scipy'))\n"
        "print(len(keys), keys.extrapolation)\n"
    )
    out = subprocess.run([sys.executable, "-I", "-S", "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["3", "CONSTANT"]
