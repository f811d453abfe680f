"""The whole retarget (retarget_core.pipeline.retarget) and ``handretarget retarget``: the three
files it writes agree with each other, bad input is refused up front with a clear message, and
result.json records the frame range, the provenance and the settings the method leaves unused.
No accuracy figures here (the identity-retarget tests cover them)."""

import contextlib
import copy
import dataclasses
import hashlib
import io
import json
import re

import numpy as np
import pytest
from pxr import Usd, UsdSkel

import retarget_core
from retarget_core.cli import main
from retarget_core.clip.demo import make_demo_clip, source_rig
from retarget_core.errors import InputError
from retarget_core.export import local_joint_transforms, read_animation_json, read_dof_bsplines
from retarget_core.execute import Executor
from retarget_core.inputs import RunInputs, load_inputs
from retarget_core.pipeline import retarget
from retarget_core.result import RESULT_FORMAT, RESULT_VERSION, load_result
from retarget_core.rig.demo_hands import demo_hand
from retarget_core.rig.io import save_rig
from retarget_core.solve.config import load_config
from retarget_core.transfer.annotations import save_annotations
from retarget_core.transfer.propose import propose_annotations

TARGET = "prosthetic_1dof"
RES = 0.004
# few evaluations, a short refinement and one process: fast, not accurate
FAST_SETTINGS = {"solver.maxeval": 15, "solver.root_maxeval": 10, "refinement.max_iterations": 2}
FAST = [arg for k, v in FAST_SETTINGS.items() for arg in ("--set", f"{k}={v}")] + ["--workers", "1"]


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
    assert doc["format"] == RESULT_FORMAT and doc["version"] == RESULT_VERSION == 2
    assert doc["dof_names"] == setup["target"].dof_names and len(doc["curves"]) == 21
    # the worker count is the executor's now: not in the run configuration, in the provenance
    assert doc["config"]["solver"]["maxeval"] == 15 and "workers" not in doc["config"]
    assert doc["provenance"]["executor"]["workers"] == 1
    assert doc["frames"] == [0, 46] and doc["unused_settings"] == {}  # the paper's method uses every setting
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
    # version 1 (before unused_settings, frames and provenance) is still read ...
    old = {k: v for k, v in written["doc"].items() if k not in ("unused_settings", "frames", "provenance")}
    (tmp_path / "result.json").write_text(json.dumps(dict(old, version=1)))
    result = load_result(tmp_path)
    np.testing.assert_array_equal(result.q, load_result(written["out"]).q)
    assert result.frames == (0, 46) and result.unused_settings == {} and result.provenance == {}
    # ... a version after this reader's (2 is current now) is refused
    doc = dict(written["doc"], version=RESULT_VERSION + 1)
    (tmp_path / "result.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match="version"):
        load_result(tmp_path)
    (tmp_path / "result.json").write_text(json.dumps({"format": "something else"}))
    with pytest.raises(InputError, match="format"):
        load_result(tmp_path)


# ---- bad input ------------------------------------------------------------------------------
def fast_config(**overrides):
    return load_config(None, "default", {"solver.maxeval": 5, **overrides})


def run(clip, source, target, annotations, config, **executor):
    return retarget(RunInputs.of(clip, source, target, annotations), config, Executor(**executor))


def test_annotations_for_another_rig(setup):
    other = propose_annotations(setup["source"], setup["source"])  # made for the source hand as target
    with pytest.raises(InputError, match="annotations made for another rig") as err:
        run(setup["clip"], setup["source"], setup["target"], other, fast_config())
    assert "source_human" in str(err.value) and "target hand" in str(err.value)


def test_clip_too_short_for_the_spline(setup):
    s = setup
    with pytest.raises(InputError, match=r"too short .* 3 frames, at least 4"):
        run(s["clip"].slice(0, 3), s["source"], s["target"], s["annotations"], fast_config())
    with pytest.raises(InputError, match=r"fit.control_points = 60"):
        run(s["clip"], s["source"], s["target"], s["annotations"], fast_config(**{"fit.control_points": 60}))


def test_limits_that_exclude_the_rest_pose(setup):
    rig = copy.deepcopy(setup["target"])
    dof = rig.dofs[7]
    rig.dofs[7] = dataclasses.replace(dof, lower=dof.rest + 0.1, upper=dof.rest + 0.5)
    with pytest.raises(InputError, match=rf"DOF '{dof.name}'.*outside its limits"):
        run(setup["clip"], setup["source"], rig, setup["annotations"], fast_config())


@pytest.mark.parametrize("setting, key, message", [
    ("solver.maxevals=5", "solver.maxevals", "unknown key"),
    ("weights.lambda_m=-1", "weights.lambda_m", "must be in [0, 1000000]"),  # the range of issue 16's bounds
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
    config = load_config(None, "default")
    result = run(clip, source, target, propose_annotations(source, target), config, workers=2)
    median = result.summary["contact_distance_median_mm"]
    assert result.summary["contact_frames"] > 30
    assert result.summary["failed_frames"] == 0
    assert median is not None and median < 3.0, median


# ---- run inputs: frame range, provenance, unused settings, refused executor keys ------------
@pytest.fixture(scope="module")
def long_clip(setup):
    """An 87-frame bottle clip (saved as long.npz), long enough for the range 10:70."""
    clip = make_demo_clip("bottle_pick_place", time_scale=0.1, resolution=RES, rig=setup["source"])
    assert clip.n_frames >= 80
    clip.save(setup["folder"] / "long.npz")
    return clip


def test_a_frame_range_retargets_those_frames_only(setup, long_clip, tmp_path):
    """``frames=(10, 70)`` (RunInputs, or ``--frames 10:70``) gives the 60 frames of that range,
    exactly the run on ``clip.slice(10, 70)``, and result.json records the range."""
    s = setup
    config = load_config(None, "default", FAST_SETTINGS)
    ranged = retarget(RunInputs.of(long_clip, s["source"], s["target"], s["annotations"], frames=(10, 70)), config)
    sliced = retarget(RunInputs.of(long_clip.slice(10, 70), s["source"], s["target"], s["annotations"]), config)
    assert ranged.n_frames == 60 and ranged.q.shape == (60, 21) and ranged.summary["frames"] == 60
    assert ranged.frames == (10, 70) and sliced.frames == (0, 60)
    np.testing.assert_array_equal(ranged.q, sliced.q)
    np.testing.assert_array_equal(ranged.unresolved, sliced.unresolved)
    np.testing.assert_array_equal(ranged.times, np.arange(60) / long_clip.fps)  # times count from the range's start
    doc = json.loads(json.dumps(ranged.to_dict(), allow_nan=False))
    assert doc["frames"] == [10, 70] and doc["provenance"]["frames"] == [10, 70]

    out = tmp_path / "out"
    code, stdout, stderr = run_cli(["retarget", "--clip", str(s["folder"] / "long.npz"), "--rig",
                                    f"demo:{TARGET}@{RES}", "--annotations", str(s["folder"] / "annotations.json"),
                                    "--out", str(out), "--frames", "10:70", *FAST])
    assert code == 0, stderr
    assert "(frames 10:70)" in stdout and f"onto {TARGET}: 60 frames, 21 DOFs" in stdout
    doc = json.loads((out / "result.json").read_text())
    assert doc["frames"] == [10, 70] and doc["summary"]["frames"] == 60 and len(doc["times"]) == 60
    np.testing.assert_array_equal(load_result(out).q, sliced.q)


@pytest.mark.parametrize("frames", ["70:10", "10:99", "5"])
def test_a_bad_frame_range_exits_2(setup, tmp_path, frames):
    code, _, err = run_cli(cli_args(setup, tmp_path / "out", "--frames", frames))
    assert code == 2 and "frames" in err
    assert not (tmp_path / "out").exists()


def _sha256(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_result_json_records_the_provenance(written, setup):
    """result.json's provenance: the project version, the executor, the run configuration and
    the sha256 of every input (the files' bytes for the clip and the annotations)."""
    doc, folder = written["doc"], setup["folder"]
    prov = doc["provenance"]
    assert prov["version"] == retarget_core.__version__
    assert prov["commit"] is None or re.fullmatch(r"[0-9a-f]{40}", prov["commit"])
    assert prov["executor"] == {"workers": 1, "dask_scheduler": "", "atlas_cache": "", "blas_threads": 1}
    assert prov["config"] == doc["config"] and prov["frames"] == [0, 46]
    inputs = prov["inputs"]
    assert set(inputs) == {"clip", "source_rig", "target_rig", "annotations"}
    for name, entry in inputs.items():
        assert re.fullmatch(r"[0-9a-f]{64}", entry["sha256"]), name
    assert inputs["clip"]["sha256"] == _sha256(folder / "clip.npz")
    assert inputs["annotations"]["sha256"] == _sha256(folder / "annotations.json")
    assert inputs["target_rig"]["spec"] == f"demo:{TARGET}@{RES}"
    assert inputs["source_rig"]["spec"] == setup["clip"].source_rig  # the demo hand the clip names

    # load_inputs hashes the files it reads (a rig file too)
    rig_file = folder / "target.usda"
    save_rig(setup["target"], rig_file)
    loaded = load_inputs(folder / "clip.npz", str(rig_file), folder / "annotations.json")
    clip_file = folder / "clip.npz"
    assert loaded.sources["clip"] == {"path": str(clip_file.resolve()), "sha256": _sha256(clip_file)}
    assert loaded.sources["annotations"]["sha256"] == _sha256(folder / "annotations.json")
    assert loaded.sources["target_rig"] == {"path": str(rig_file.resolve()), "sha256": _sha256(rig_file)}
    assert loaded.sources["source_rig"]["sha256"] == inputs["source_rig"]["sha256"]  # the same demo hand
    assert loaded.provenance() == loaded.sources


def test_a_setting_the_method_does_not_use_is_recorded(setup, tmp_path):
    """method = keyvectors has no marker term in its finger passes: a weights.lambda_m given with
    it is listed in result.json's unused_settings (with its value) and noted, never dropped
    silently."""
    out = tmp_path / "out"
    code, stdout, stderr = run_cli(cli_args(setup, out, *FAST, "--set", "method=keyvectors",
                                            "--set", "weights.lambda_m=3"))
    assert code == 0, stderr
    doc = json.loads((out / "result.json").read_text())
    assert doc["config"]["method"] == "keyvectors" and doc["config"]["weights"]["lambda_m"] == 3
    unused = doc["unused_settings"]
    assert unused["weights.lambda_m"]["value"] == 3 and unused["weights.lambda_m"]["why"]
    assert "weights.lambda_c" in unused and "weights.lambda_t" not in unused  # the table term is still used
    assert "weights.lambda_m = 3.0 is not used" in stdout
    assert load_result(out).unused_settings == unused


def test_an_executor_key_in_set_exits_2_naming_the_option(setup, tmp_path):
    code, _, err = run_cli(cli_args(setup, tmp_path / "out", "--set", "workers=2"))
    assert code == 2
    assert "workers" in err and "--workers" in err
    assert not (tmp_path / "out").exists()


def test_a_clip_naming_a_source_rig_file_is_refused(setup, tmp_path):
    """A clip is untrusted input: a file path in its source_rig field is never opened; the
    refusal says to give the source rig explicitly (--source-rig), which then works."""
    folder = setup["folder"]
    rig_file = tmp_path / "source.usda"
    save_rig(setup["source"], rig_file)  # a real rig file: refused for where it is named, not for its content
    clip_path = tmp_path / "clip.npz"
    dataclasses.replace(setup["clip"], source_rig=str(rig_file)).save(clip_path)
    with pytest.raises(InputError, match="--source-rig") as err:
        load_inputs(clip_path, f"demo:{TARGET}@{RES}", folder / "annotations.json")
    assert err.value.element == "source_rig" and str(rig_file) in str(err.value)
    code, _, stderr = run_cli(["retarget", "--clip", str(clip_path), "--rig", f"demo:{TARGET}@{RES}", "--annotations",
                               str(folder / "annotations.json"), "--out", str(tmp_path / "out")])
    assert code == 2 and "--source-rig" in stderr and not (tmp_path / "out").exists()
    # given explicitly, the same file is read (and hashed)
    loaded = load_inputs(clip_path, f"demo:{TARGET}@{RES}", folder / "annotations.json", source_rig=str(rig_file))
    assert loaded.source_rig.name == setup["source"].name
    assert loaded.sources["source_rig"] == {"path": str(rig_file.resolve()), "sha256": _sha256(rig_file)}
