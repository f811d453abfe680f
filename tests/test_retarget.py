"""The whole retarget (retarget_core.retarget) and ``handretarget retarget``: the three files it
writes agree with each other, and bad input is refused up front with a clear message. No
accuracy figures here (the identity-retarget tests cover them)."""

import contextlib
import copy
import dataclasses
import io
import json

import numpy as np
import pytest
from pxr import Usd, UsdSkel

from retarget_core.cli import main
from retarget_core.clip.demo import make_demo_clip, source_rig
from retarget_core.errors import InputError
from retarget_core.export import local_joint_transforms, read_animation_json, read_dof_bsplines
from retarget_core.retarget import RESULT_FORMAT, load_result, retarget
from retarget_core.rig.demo_hands import demo_hand
from retarget_core.solve.config import load_config
from retarget_core.transfer.annotations import save_annotations
from retarget_core.transfer.propose import propose_annotations

TARGET = "prosthetic_1dof"
RES = 0.004
# few evaluations, a short refinement and one process: fast, not accurate
FAST = ["--set", "solver.maxeval=15", "--set", "solver.root_maxeval=10", "--set", "refinement.max_iterations=2",
        "--workers", "1"]


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    folder = tmp_path_factory.mktemp("retarget")
    source = source_rig(RES)
    target = demo_hand(TARGET, RES)
    clip = make_demo_clip("bottle_pick_place", time_scale=0.05, resolution=RES, rig=source)  # 46 frames
    clip.save(folder / "clip.npz")
    annotations = propose_annotations(source, target)
    save_annotations(annotations, folder / "annotations.json")
    return dict(folder=folder, source=source, target=target, clip=clip, annotations=annotations)


def run_cli(argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


def cli_args(setup, out, *extra):
    f = setup["folder"]
    return ["retarget", "--clip", str(f / "clip.npz"), "--rig", f"demo:{TARGET}@{RES}", "--annotations",
            str(f / "annotations.json"), "--out", str(out), *extra]


@pytest.fixture(scope="module")
def written(setup):
    out = setup["folder"] / "out"
    code, stdout, stderr = run_cli(cli_args(setup, out, *FAST))
    assert code == 0, stderr
    return dict(out=out, stdout=stdout, stderr=stderr, doc=json.loads((out / "result.json").read_text()))


# ---- end to end -------------------------------------------------------------------------------
def test_cli_writes_the_files_and_a_summary(written, setup):
    out = written["out"]
    assert {"animation.usda", "result.json", "animation.json", "rig.usda"} <= {p.name for p in out.iterdir()}
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary files left
    text = written["stdout"]
    assert f"onto {TARGET}: 46 frames, 21 DOFs" in text and "median contact distance" in text
    for name in ("animation.usda", "result.json", "animation.json"):
        assert f"wrote {out / name}" in text
    for stage in ("root pass", "full pass", "spline fit"):  # progress lines on stderr
        assert f"{stage}:" in written["stderr"]
    doc = written["doc"]
    assert doc["format"] == RESULT_FORMAT and doc["version"] == 1
    assert doc["dof_names"] == setup["target"].dof_names and len(doc["curves"]) == 21
    assert doc["config"]["solver"]["maxeval"] == 15 and doc["config"]["workers"] == 1
    for key in ("validation", "pairing", "transfer", "root pass", "full pass", "fit", "total"):
        assert doc["timings"][key] >= 0
    assert doc["counts"]["passes"]["full"]["evaluations_per_frame"] <= 15
    assert set(doc["summary"]) >= {"frames", "contact_distance_median_mm", "failed_frames", "marker_error_median_mm"}
    # strict JSON: no NaN / Infinity tokens (frames without contacts are null)
    json.loads((out / "result.json").read_text(), parse_constant=lambda c: pytest.fail(f"{c} in result.json"))
    assert None in doc["contact_distance_mm"] and len(doc["contact_distance_mm"]) == 46


def test_usd_splines_and_baked_animation_equal_the_fitted_curves(written, setup):
    result = load_result(written["out"])
    rig, fps = setup["target"], result.fps
    stage = Usd.Stage.Open(str(written["out"] / "animation.usda"))
    root = stage.GetDefaultPrim()
    attrs = {(a.GetCustomDataByKey("handretarget") or {}).get("dofName"): a
             for a in root.GetChild("DofCurves").GetAttributes()}
    codes = np.linspace(0.0, result.n_frames - 1, 100)
    for name, curve in zip(result.dof_names, result.curves):
        assert attrs[name].HasSpline()
        values = np.array([attrs[name].Get(Usd.TimeCode(float(c))) for c in codes])
        np.testing.assert_allclose(values, curve(codes / fps), atol=1e-9, rtol=0, err_msg=name)
    raw = read_dof_bsplines(written["out"] / "animation.usda")
    for name, curve in zip(result.dof_names, result.curves):
        np.testing.assert_array_equal(raw[name].coeffs, curve.coeffs)

    cache = UsdSkel.Cache()
    cache.Populate(UsdSkel.Root(root), Usd.TraverseInstanceProxies())
    skel = UsdSkel.Skeleton(root.GetChild("Skeleton"))
    query = cache.GetSkelQuery(skel)
    order = [rig.joint_index(n) for n in skel.GetJointNamesAttr().Get()]
    sampled = result.sampled()
    for frame in range(result.n_frames):
        got = np.array(query.ComputeJointLocalTransforms(Usd.TimeCode(frame))).reshape(-1, 4, 4)
        np.testing.assert_allclose(got.transpose(0, 2, 1), local_joint_transforms(rig, sampled[frame])[order],
                                   atol=1e-5)
    assert stage.GetPrimAtPath("/Object/Mesh")  # the object is animated too


def test_result_json_round_trips(written):
    result = load_result(written["out"])
    assert json.loads(json.dumps(result.to_dict(), allow_nan=False)) == written["doc"]
    assert result.q.shape == result.unresolved.shape == (46, 21) and result.unresolved.dtype == bool
    assert np.isnan(result.contact_distance_mm[result.contact_count == 0]).all()
    joints = read_animation_json(written["out"] / "animation.json")
    assert joints["dof_names"] == result.dof_names
    np.testing.assert_allclose(joints["values"], result.sampled(), atol=1e-12)
    np.testing.assert_allclose(joints["times"], np.arange(46) / result.fps)


def test_load_result_refuses_missing_and_other_version(tmp_path, written):
    with pytest.raises(InputError, match="no result.json"):
        load_result(tmp_path)
    doc = dict(written["doc"], version=2)
    (tmp_path / "result.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match="version"):
        load_result(tmp_path)
    (tmp_path / "result.json").write_text(json.dumps({"format": "something else"}))
    with pytest.raises(InputError, match="format"):
        load_result(tmp_path)


# ---- bad input ------------------------------------------------------------------------------
def fast_config(**overrides):
    return load_config(None, "default", {"solver.maxeval": 5, "workers": 1, **overrides})


def test_annotations_for_another_rig(setup):
    other = propose_annotations(setup["source"], setup["source"])  # made for the source hand as target
    with pytest.raises(InputError, match="annotations made for another rig") as err:
        retarget(setup["clip"], setup["source"], setup["target"], other, fast_config())
    assert "source_human" in str(err.value) and "target hand" in str(err.value)


def test_clip_too_short_for_the_spline(setup):
    s = setup
    with pytest.raises(InputError, match=r"too short .* 3 frames, at least 4"):
        retarget(s["clip"].slice(0, 3), s["source"], s["target"], s["annotations"], fast_config())
    with pytest.raises(InputError, match=r"fit.control_points = 60"):
        retarget(s["clip"], s["source"], s["target"], s["annotations"], fast_config(**{"fit.control_points": 60}))


def test_limits_that_exclude_the_rest_pose(setup):
    rig = copy.deepcopy(setup["target"])
    dof = rig.dofs[7]
    rig.dofs[7] = dataclasses.replace(dof, lower=dof.rest + 0.1, upper=dof.rest + 0.5)
    with pytest.raises(InputError, match=rf"DOF '{dof.name}'.*outside its limits"):
        retarget(setup["clip"], setup["source"], rig, setup["annotations"], fast_config())


@pytest.mark.parametrize("setting, key, message", [
    ("solver.maxevals=5", "solver.maxevals", "unknown key"),
    ("weights.lambda_m=-1", "weights.lambda_m", "non-negative"),
    ("solver", "solver", "KEY=VALUE"),
])
def test_bad_config_overrides_exit_2(setup, tmp_path, setting, key, message):
    code, _, err = run_cli(cli_args(setup, tmp_path / "out", "--set", setting))
    assert code == 2
    assert key in err and message in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("hand", ["source_human", "human_alt", "witch"])
def test_human_targets_touch_the_object_within_3mm(hand):
    """Default preset, a natural-speed second of the bottle clip (reach, grasp, lift), proposed
    annotations: the median distance between the target's contact points and their object
    points over contact frames is reported and under 3 mm on the human-like hands (the two
    humans and the long-fingered witch; see the README's motion synthesis figures)."""
    from retarget_core.clip.demo import grasp_window

    source = source_rig(RES)
    target = demo_hand(hand, RES)
    clip = grasp_window(make_demo_clip("bottle_pick_place", resolution=RES, rig=source), 120)
    config = load_config(None, "default", {"workers": 2})
    result = retarget(clip, source, target, propose_annotations(source, target), config)
    median = result.summary["contact_distance_median_mm"]
    assert result.summary["contact_frames"] > 30
    assert result.summary["failed_frames"] == 0
    assert median is not None and median < 3.0, median
