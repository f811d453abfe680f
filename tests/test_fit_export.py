"""Spline fitting of DOF trajectories and the result export (USD layer with baked UsdSkel
animation and native Ts splines; JSON)."""

import json
from pathlib import Path

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, UsdSkel
from scipy.interpolate import BSpline

from retarget_core.errors import InputError
from retarget_core.export import (
    local_joint_transforms,
    read_animation_json,
    read_dof_bsplines,
    read_dof_splines,
    write_animation_json,
    write_animation_usd,
)
from retarget_core.fit import BSplineCurve, clamped_uniform_knots, fit_bspline, fit_trajectory, schoenberg_whitney_ok
from retarget_core.rig.demo_hands import demo_hand
from retarget_core.rig.usd_io import check_usd_compliance, write_rig_usd

FPS = 30.0


def sse(curve, t, y, mask=None):
    r = curve(t) - y
    if mask is not None:
        r = r[mask]
    return float(r @ r)


# ---- fitting ---------------------------------------------------------------------------------
def test_recovers_known_bspline_exactly():
    rng = np.random.default_rng(0)
    t = np.arange(150) / FPS
    knots = clamped_uniform_knots(t[0], t[-1], 12)
    coeffs = rng.normal(size=12)
    y = BSpline(knots, coeffs, 3)(t)
    for optimize in (False, True):
        curve = fit_bspline(t, y, 12, optimize_knots=optimize)
        assert sse(curve, t, y) < 1e-24
        assert np.abs(curve(t) - y).max() < 1e-12
    np.testing.assert_allclose(fit_bspline(t, y, 12, optimize_knots=False).coeffs, coeffs, atol=1e-10)


def test_fits_smooth_function_and_knot_optimisation_never_hurts():
    t = np.arange(240) / FPS
    y = np.sin(1.3 * t) + 0.4 * np.sin(4.1 * t + 0.3) + 0.3 * np.tanh(3 * (t - 5))
    for n in (6, 10, 16, 24):
        uniform = fit_bspline(t, y, n, optimize_knots=False)
        optimised = fit_bspline(t, y, n, optimize_knots=True)
        assert sse(optimised, t, y) <= sse(uniform, t, y) * (1 + 1e-12)
        knots = optimised.knots
        assert np.all(np.diff(knots) >= 0)
        assert knots[0] == t[0] and knots[-1] == t[-1]
        assert np.all(knots[:4] == t[0]) and np.all(knots[-4:] == t[-1])
    good = fit_bspline(t, y, 24)
    assert np.abs(good(t) - y).max() < 5e-3
    # where the uniform knots fit badly, moving them gains a lot
    t2 = np.arange(61) / FPS
    y2 = np.sin(3 * t2) + 0.3 * np.cos(7 * t2)
    assert sse(fit_bspline(t2, y2, 8), t2, y2) < 0.1 * sse(fit_bspline(t2, y2, 8, optimize_knots=False), t2, y2)


def test_masked_frames_are_ignored():
    rng = np.random.default_rng(1)
    t = np.arange(200) / FPS
    y = np.cos(0.7 * t) + 0.1 * rng.normal(size=t.size)
    mask = np.ones(t.size, dtype=bool)
    mask[[17, 90, 91, 150]] = False
    wild = y.copy()
    wild[[17, 90, 91, 150]] = [1e6, -3e5, np.nan, 42.0]  # a NaN in a masked frame is fine too
    for optimize in (False, True):
        a = fit_bspline(t, y, 10, mask=mask, optimize_knots=optimize)
        b = fit_bspline(t, wild, 10, mask=mask, optimize_knots=optimize)
        np.testing.assert_allclose(b.knots, a.knots, atol=1e-14)
        np.testing.assert_allclose(b.coeffs, a.coeffs, atol=1e-12)
    # the mask matters: without it the outlier drags the fit
    c = fit_bspline(t, np.where(np.isnan(wild), 0.0, wild), 10, optimize_knots=False)
    assert np.abs(c(t) - a(t)).max() > 1.0


def test_masked_stretch_still_fits():
    """A long masked stretch empties some uniform knot intervals; the fit falls back to knots
    that satisfy Schoenberg-Whitney instead of failing."""
    t = np.arange(120) / FPS
    y = np.sin(2 * t)
    mask = np.ones(t.size, dtype=bool)
    mask[30:80] = False
    curve = fit_bspline(t, y, 14, mask=mask)
    x = t[mask]
    assert schoenberg_whitney_ok(x, curve.knots)
    assert np.abs(curve(x) - y[mask]).max() < 1e-3


def test_schoenberg_whitney_check():
    x = np.linspace(0, 1, 20)
    assert schoenberg_whitney_ok(x, clamped_uniform_knots(0, 1, 10))
    bad = np.r_[[0.0] * 4, 0.05, 0.06, 0.07, [1.0] * 4]
    assert not schoenberg_whitney_ok(x, bad)
    assert not schoenberg_whitney_ok(x[:5], clamped_uniform_knots(0, 1, 6))


def test_to_bezier_reproduces_curve():
    rng = np.random.default_rng(2)
    t = np.arange(300) / FPS
    y = np.cumsum(rng.normal(size=t.size)) * 0.01
    curve = fit_bspline(t, y, 15)
    segments = curve.to_bezier()
    assert len(segments) == len(curve.breakpoints()) - 1
    for t0, t1, p0, p1, p2, p3 in segments:
        u = np.linspace(0.0, 1.0, 11)
        bez = (1 - u) ** 3 * p0 + 3 * (1 - u) ** 2 * u * p1 + 3 * (1 - u) * u**2 * p2 + u**3 * p3
        np.testing.assert_allclose(bez, curve(t0 + u * (t1 - t0)), atol=1e-12)
        h = t1 - t0
        assert abs(p1 - (p0 + h / 3 * curve.derivative(t0))) < 1e-10
    # segments tile the domain
    assert segments[0][0] == t[0] and segments[-1][1] == t[-1]
    assert all(a[1] == b[0] for a, b in zip(segments, segments[1:]))


def test_extrapolation_and_derivatives():
    t = np.arange(60) / FPS
    y = t**2
    held = fit_bspline(t, y, 6, optimize_knots=False)
    assert abs(held(-1.0) - held(0.0)) < 1e-15 and abs(held(10.0) - held(t[-1])) < 1e-15
    assert held.derivative(10.0) == 0.0
    linear = BSplineCurve(held.knots, held.coeffs, extrapolation="linear")
    end = t[-1]
    assert abs(linear(end + 1.0) - (linear(end) + linear.derivative(end))) < 1e-12
    assert abs(linear.derivative(end) - 2 * end) < 1e-9
    assert abs(held.derivative(0.5, order=2) - 2.0) < 1e-9


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(times=np.arange(5) / FPS, values=np.zeros(5), n_control=8),  # too short
        dict(times=np.arange(20) / FPS, values=np.zeros(20), n_control=8, mask=np.arange(20) < 6),
        dict(times=np.arange(20) / FPS, values=np.r_[np.zeros(19), np.nan], n_control=8),
        dict(times=np.arange(20) / FPS, values=np.zeros(20), n_control=3),
        dict(times=np.r_[0.0, 0.0, np.arange(2, 20)] / FPS, values=np.zeros(20), n_control=6),
        dict(times=np.arange(20) / FPS, values=np.zeros(19), n_control=6),
    ],
)
def test_bad_input(kwargs):
    with pytest.raises(InputError):
        fit_bspline(**kwargs)


def test_too_short_message_names_counts():
    with pytest.raises(InputError, match="too short for 8 control points: 5 usable frames"):
        fit_bspline(np.arange(5) / FPS, np.zeros(5), 8)


def test_fit_trajectory_one_curve_per_dof():
    t = np.arange(90) / FPS
    q = np.stack([np.sin(t), np.cos(2 * t), t], axis=1)
    mask = np.ones(q.shape, dtype=bool)
    mask[10, 1] = False
    curves = fit_trajectory(t, q, 9, mask)
    assert len(curves) == 3 and all(c.n_control == 9 for c in curves)
    assert np.abs(curves[2](t) - t).max() < 1e-10
    with pytest.raises(InputError, match="DOF 0"):
        fit_trajectory(t[:4], q[:4], 9)


# ---- USD export ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def rig():
    return demo_hand("prosthetic_2dof", resolution=0.006)


def smooth_trajectory(rig, n_frames, rng):
    """(F, D) smooth random DOF values inside the limits (root kept near rest)."""
    t = np.arange(n_frames) / FPS
    lo, hi, rest = rig.lower, rig.upper, rig.rest_pose
    q = np.empty((n_frames, rig.n_dofs))
    for d, dof in enumerate(rig.dofs):
        if dof.joint == 0:
            span = 0.05 if dof.kind == "translate" else 0.5
            lo_d, hi_d = max(lo[d], rest[d] - span), min(hi[d], rest[d] + span)
        else:
            lo_d, hi_d = lo[d], hi[d]
        mid, amp = 0.5 * (lo_d + hi_d), 0.4 * (hi_d - lo_d)
        w = rng.uniform(0.5, 3.0, size=2)
        phase = rng.uniform(0, 2 * np.pi, size=2)
        q[:, d] = mid + amp * (0.6 * np.sin(w[0] * t + phase[0]) + 0.4 * np.sin(w[1] * t + phase[1]))
    return t, q


@pytest.fixture(scope="module")
def written(rig, tmp_path_factory):
    rng = np.random.default_rng(7)
    folder = tmp_path_factory.mktemp("result")
    rig_dir = folder / "rigs"
    rig_dir.mkdir()
    rig_file = rig_dir / "hand.usda"
    write_rig_usd(rig, rig_file)
    n_frames = 75
    t, q = smooth_trajectory(rig, n_frames, rng)
    curves = fit_trajectory(t, q, 10)
    box_v = np.array([[x, y, z] for x in (-0.05, 0.05) for y in (-0.03, 0.03) for z in (-0.02, 0.02)])
    box_f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    poses = np.repeat(np.eye(4)[None], n_frames, axis=0)
    angle = np.linspace(0, 1.0, n_frames)
    poses[:, 0, 0], poses[:, 0, 1] = np.cos(angle), -np.sin(angle)
    poses[:, 1, 0], poses[:, 1, 1] = np.sin(angle), np.cos(angle)
    poses[:, :3, 3] = np.stack([0.3 + 0.1 * angle, -0.2 * angle, 0.05 + 0 * angle], axis=1)
    out = folder / "out" / "result.usda"
    write_animation_usd(
        out, rig=rig, rig_file=str(rig_file), dof_curves=curves, fps=FPS, n_frames=n_frames,
        object_vertices=box_v, object_faces=box_f, object_poses=poses, metadata={"clip": "demo", "n": 3},
    )
    return dict(path=out, rig_file=rig_file, curves=curves, poses=poses, n_frames=n_frames, folder=folder)


def test_layer_metadata_and_sublayer(written):
    stage = Usd.Stage.Open(str(written["path"]))
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert stage.GetTimeCodesPerSecond() == FPS and stage.GetFramesPerSecond() == FPS
    assert stage.GetStartTimeCode() == 0 and stage.GetEndTimeCode() == written["n_frames"] - 1
    layer = stage.GetRootLayer()
    assert list(layer.subLayerPaths) == ["../rigs/hand.usda"]
    assert any(lay.realPath == str(written["rig_file"].resolve()) for lay in stage.GetUsedLayers())
    assert json.loads(layer.customLayerData["handretarget:metadata"]) == {"clip": "demo", "n": 3}
    assert [p.name for p in written["path"].parent.iterdir()] == ["result.usda"]  # no temp files
    # the layer only overrides the rig's root, and the composed stage passes USD's checks
    assert layer.GetPrimAtPath(stage.GetDefaultPrim().GetPath()).specifier == Sdf.SpecifierOver
    assert UsdSkel.Root(stage.GetDefaultPrim())
    assert check_usd_compliance(written["path"]) == []


def test_dof_splines_equal_bsplines(written, rig):
    splines = read_dof_splines(written["path"])
    assert sorted(splines) == sorted(rig.dof_names)
    codes = np.linspace(-5.0, written["n_frames"] + 5.0, 100)  # includes extrapolation
    stage = Usd.Stage.Open(str(written["path"]))
    for name, curve in zip(rig.dof_names, written["curves"]):
        spline = splines[name]
        ts_values = np.array([spline.Eval(float(c)) for c in codes])
        np.testing.assert_allclose(ts_values, curve(codes / FPS), atol=1e-9, rtol=0)
        # the attribute answers with the spline too
        attr = [a for a in stage.GetPrimAtPath("/" + stage.GetDefaultPrim().GetName() + "/DofCurves").GetAttributes()
                if (a.GetCustomDataByKey("handretarget") or {}).get("dofName") == name][0]
        assert attr.HasSpline() and attr.GetTypeName() == Sdf.ValueTypeNames.Double
        assert abs(attr.Get(Usd.TimeCode(12.5)) - curve(12.5 / FPS)) < 1e-9
        # slopes are per time code
        assert abs(spline.EvalDerivative(20.3) - curve.derivative(20.3 / FPS) / FPS) < 1e-9
    back = read_dof_bsplines(written["path"])
    for name, curve in zip(rig.dof_names, written["curves"]):
        np.testing.assert_array_equal(back[name].knots, curve.knots)
        np.testing.assert_array_equal(back[name].coeffs, curve.coeffs)
        assert back[name].degree == 3


def test_baked_skel_animation_matches_kinematics(written, rig):
    stage = Usd.Stage.Open(str(written["path"]))
    root = stage.GetDefaultPrim()
    skel = UsdSkel.Skeleton(root.GetChild("Skeleton"))
    assert skel
    cache = UsdSkel.Cache()
    skel_root = UsdSkel.Root(root)
    assert skel_root
    cache.Populate(skel_root, Usd.TraverseInstanceProxies())
    skel_query = cache.GetSkelQuery(skel)
    anim_query = skel_query.GetAnimQuery()
    assert anim_query and anim_query.GetPrim().GetPath() == root.GetPath().AppendChild("Animation")
    binding = UsdSkel.BindingAPI(skel.GetPrim())
    assert binding.GetAnimationSource().GetPath() == anim_query.GetPrim().GetPath()
    anim = UsdSkel.Animation(anim_query.GetPrim())
    assert list(anim.GetJointsAttr().Get()) == list(skel.GetJointsAttr().Get())
    order = [rig.joint_index(n) for n in skel.GetJointNamesAttr().Get()]
    curves = written["curves"]
    for frame in (0, 1, 17, 40, written["n_frames"] - 1):
        q = np.array([c(frame / FPS) for c in curves])
        expected = local_joint_transforms(rig, q)[order]
        got = np.array(skel_query.ComputeJointLocalTransforms(Usd.TimeCode(frame))).reshape(-1, 4, 4)
        np.testing.assert_allclose(got.transpose(0, 2, 1), expected, atol=1e-5)
        # and through the skeleton: world joint transforms equal the rig's kinematics
        world = np.array(skel_query.ComputeJointSkelTransforms(Usd.TimeCode(frame))).reshape(-1, 4, 4)
        np.testing.assert_allclose(world.transpose(0, 2, 1), rig.kinematics().pose(q).world[order], atol=1e-5)
    # every frame is sampled
    assert list(anim.GetRotationsAttr().GetTimeSamples()) == list(range(written["n_frames"]))


def test_object_transform(written):
    stage = Usd.Stage.Open(str(written["path"]))
    xform = UsdGeom.Xformable(stage.GetPrimAtPath("/Object"))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Object/Mesh"))
    assert len(mesh.GetFaceVertexCountsAttr().Get()) == 12
    for frame in (0, 33, written["n_frames"] - 1):
        m = np.array(xform.ComputeLocalToWorldTransform(Usd.TimeCode(frame))).T
        np.testing.assert_allclose(m, written["poses"][frame], atol=1e-12)


def test_usdc_and_embedded_rig(rig, tmp_path):
    """Without a rig file the rig is written into the layer; .usdc keeps the splines."""
    rng = np.random.default_rng(3)
    t, q = smooth_trajectory(rig, 40, rng)
    curves = fit_trajectory(t, q, 6, optimize_knots=False)
    out = tmp_path / "embedded.usdc"
    write_animation_usd(out, rig=rig, rig_file=None, dof_curves=curves, fps=FPS, n_frames=40)
    stage = Usd.Stage.Open(str(out))
    assert list(stage.GetRootLayer().subLayerPaths) == []
    skel = UsdSkel.Skeleton(stage.GetDefaultPrim().GetChild("Skeleton"))
    assert UsdSkel.BindingAPI(skel.GetPrim()).GetAnimationSource()
    splines = read_dof_splines(out)
    for name, curve in zip(rig.dof_names, curves):
        codes = np.linspace(0, 39, 50)
        np.testing.assert_allclose([splines[name].Eval(float(c)) for c in codes], curve(codes / FPS), atol=1e-9)


def test_bad_export_input(rig, tmp_path):
    t, q = smooth_trajectory(rig, 20, np.random.default_rng(4))
    curves = fit_trajectory(t, q, 5, optimize_knots=False)
    with pytest.raises(InputError, match="DOF curves"):
        write_animation_usd(tmp_path / "a.usda", rig=rig, rig_file=None, dof_curves=curves[:-1], fps=FPS, n_frames=20)
    with pytest.raises(InputError, match="fps"):
        write_animation_usd(tmp_path / "a.usda", rig=rig, rig_file=None, dof_curves=curves, fps=0, n_frames=20)
    with pytest.raises(InputError, match="object poses"):
        write_animation_usd(tmp_path / "a.usda", rig=rig, rig_file=None, dof_curves=curves, fps=FPS, n_frames=20,
                            object_vertices=np.eye(3), object_faces=[[0, 1, 2]], object_poses=np.eye(4)[None])
    with pytest.raises(InputError, match="must end in"):
        write_animation_usd(tmp_path / "a.txt", rig=rig, rig_file=None, dof_curves=curves, fps=FPS, n_frames=20)
    assert list(tmp_path.iterdir()) == []


def test_json_round_trip(tmp_path, rig):
    t, q = smooth_trajectory(rig, 25, np.random.default_rng(5))
    path = tmp_path / "anim.json"
    write_animation_json(path, rig.dof_names, t, q, {"fps": FPS, "rig": rig.name})
    doc = read_animation_json(path)
    assert doc["dof_names"] == rig.dof_names
    np.testing.assert_array_equal(doc["times"], t)
    np.testing.assert_array_equal(doc["values"], q)
    assert doc["extra"] == {"fps": FPS, "rig": rig.name}
    with pytest.raises(InputError):
        write_animation_json(path, rig.dof_names[:-1], t, q, {})


def test_bounded_fit_keeps_the_curve_within_the_limits():
    """Samples that press against a limit (a clamped sine): the unconstrained fit overshoots it
    between and at the frames; with bounds the curve stays inside everywhere and still follows
    the data; a curve already inside is left exactly as it was."""
    t = np.linspace(0.0, 2.0, 121)
    y = np.minimum(np.sin(3.0 * t), 0.8)  # flat at the upper limit, with corners
    free = fit_bspline(t, y, 14, optimize_knots=False)
    dense = np.linspace(0.0, 2.0, 4001)
    assert free(dense).max() > 0.8 + 1e-3  # the overshoot being fixed
    bounded = fit_bspline(t, y, 14, optimize_knots=False, bounds=(-2.0, 0.8))
    assert bounded(dense).max() <= 0.8 + 1e-12 and bounded(dense).min() >= -2.0
    np.testing.assert_array_equal(bounded.knots, free.knots)
    assert np.sqrt(np.mean((bounded(t) - y) ** 2)) < 0.02
    # the bounded least squares is optimal: no feasible perturbation of a coefficient lowers the residual
    base = np.sum((bounded(t) - y) ** 2)
    for k in range(bounded.n_control):
        for step in (-1e-3, 1e-3):
            c = bounded.coeffs.copy()
            c[k] = np.clip(c[k] + step, -2.0, 0.8)
            trial = type(bounded)(knots=bounded.knots, coeffs=c, degree=3)
            assert np.sum((trial(t) - y) ** 2) >= base - 1e-12
    inside = fit_bspline(t, 0.5 * np.sin(3.0 * t), 14, optimize_knots=False, bounds=(-2.0, 0.8))
    np.testing.assert_array_equal(inside.coeffs, fit_bspline(t, 0.5 * np.sin(3.0 * t), 14, optimize_knots=False).coeffs)
    with pytest.raises(InputError, match="lower <= upper"):
        fit_bspline(t, y, 14, bounds=(1.0, 0.0))


def test_bounded_fit_where_scipys_bvls_stalls():
    """A finger DOF of human_alt solved over the 1000-frame bench clip (the values as the solve
    left them, tests/data/bounded_fit_stall.npy): 410 frames sit exactly on the +10 degree
    limit. scipy's BVLS gave up there with NaN coefficients (status 0), and the delivered curve
    of that DOF was NaN at 976 frames. The fit must come back finite, inside the limits and
    optimal (no feasible change of one coefficient lowers the residual)."""
    y = np.load(Path(__file__).parent / "data" / "bounded_fit_stall.npy")
    t = np.arange(len(y)) / 120.0
    lo, hi = -np.radians(10.0), np.radians(10.0)
    curve = fit_bspline(t, y, 83, optimize_knots=False, bounds=(lo, hi))
    assert np.all(np.isfinite(curve.coeffs))
    dense = np.linspace(t[0], t[-1], 20001)
    assert curve(dense).max() <= hi + 1e-12 and curve(dense).min() >= lo - 1e-12
    assert np.sqrt(np.mean((curve(t) - y) ** 2)) < 0.01  # rad: it follows the data
    base = np.sum((curve(t) - y) ** 2)
    for k in range(curve.n_control):
        for step in (-1e-4, 1e-4):
            c = curve.coeffs.copy()
            c[k] = np.clip(c[k] + step, lo, hi)
            trial = type(curve)(knots=curve.knots, coeffs=c, degree=3)
            assert np.sum((trial(t) - y) ** 2) >= base - 1e-9


def test_fit_trajectory_limits_per_dof():
    t = np.linspace(0.0, 1.0, 61)
    q = np.stack([np.minimum(np.sin(6 * t), 0.7), np.maximum(np.cos(6 * t), -0.3)], axis=1)
    curves = fit_trajectory(t, q, 10, optimize_knots=False, limits=(np.array([-1.0, -0.3]), np.array([0.7, 1.0])))
    dense = np.linspace(0, 1, 2001)
    assert curves[0](dense).max() <= 0.7 + 1e-12 and curves[1](dense).min() >= -0.3 - 1e-12
