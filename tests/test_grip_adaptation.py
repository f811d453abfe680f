"""Grip adaptation (issue 21): a clip whose object was substituted by a wider one, or by a thick
drill-like handle, leaves the captured hand several mm inside the new object. The default preset
then turns the hand-object penetration term on for that run (contacts.source_depth_limit), and
the delivered curve stays out of the object: intersection median < 0.5 % of the hand's volume,
p95 penetration <= 2 mm over the contact frames, exact volumes (handretarget evaluate)."""

import json

import numpy as np
import pytest

from retarget_core.clip.demo import grasp_window, make_demo_clip, source_rig
from retarget_core.clip.substitute import substitute_object
from retarget_core.evaluate.report import write_evaluation
from retarget_core.execute import Executor
from retarget_core.inputs import RunInputs
from retarget_core.pipeline import retarget
from retarget_core.rig.demo_hands import demo_hand
from retarget_core.solve.config import load_config
from retarget_core.transfer.propose import propose_annotations

RES = 0.005
FAST = {"solver.maxeval": 15, "solver.root_maxeval": 10, "refinement.max_iterations": 2}


def _thicker(vertices, sx, sy):
    """The bottle scaled about its own axis by sx, sy across it (its height kept)."""
    v = np.array(vertices, dtype=np.float64)
    axis = 0.5 * (v[:, :2].min(axis=0) + v[:, :2].max(axis=0))
    v[:, :2] = axis + (v[:, :2] - axis) * (sx, sy)
    return v


@pytest.fixture(scope="module")
def setup():
    source = source_rig(RES)
    target = demo_hand("human_alt", resolution=RES)
    clip = grasp_window(make_demo_clip("bottle_pick_place", resolution=RES, rig=source), 80)
    return source, target, clip, propose_annotations(source, target)


def _run(setup, sx, sy, tmp_path, **overrides):
    source, target, clip, annotations = setup
    new, report = substitute_object(clip, _thicker(clip.object_vertices, sx, sy), clip.object_faces,
                                    transform=np.eye(4), allow_intersection=True)
    config = load_config(None, "default", {**FAST, **overrides})
    result = retarget(RunInputs.of(new, source, target, annotations), config, Executor(workers=1))
    result.write(tmp_path, pictures=False)
    write_evaluation(tmp_path, stride=2, render=False)
    return result, report, json.loads((tmp_path / "metrics.json").read_text())["summary"]


@pytest.mark.parametrize("name, sx, sy", [("bottle 1.15x wider", 1.15, 1.15), ("thick drill-like handle", 1.35, 1.1)])
def test_the_default_preset_keeps_the_hand_out_of_a_thicker_object(setup, tmp_path, name, sx, sy):
    result, report, m = _run(setup, sx, sy, tmp_path)
    assert max(report["hand_depth_mm"]) > 2.0  # the captured hand is inside the new object
    assert result.summary["source_depth_max_mm"] == pytest.approx(max(report["hand_depth_mm"]), abs=0.05)
    assert result.summary["penetration_term"].startswith("on (weights.lambda_p = 10)")
    assert m["hand_object_intersection_percent_median"] < 0.5, m
    assert m["penetration_mm_p95"] <= 2.0, m
    assert m["contact_error_median_mm"] < 3.0, m


def test_without_the_term_the_hand_follows_the_capture_into_the_wider_bottle(setup, tmp_path):
    result, _, m = _run(setup, 1.15, 1.15, tmp_path, **{"contacts.source_depth_limit": 0.0})
    assert result.summary["penetration_term"] == "off" and result.summary["source_depth_max_mm"] is None
    assert m["penetration_mm_p95"] > 2.0, m  # what the switch is for


def test_a_clean_capture_leaves_the_term_off(setup):
    source, target, clip, annotations = setup
    from retarget_core.pipeline import collision_for_source_depth

    config = load_config(None, "default")
    same, found = collision_for_source_depth(clip, config)
    assert same is config and found["penetration_term"] == "off" and found["max_mm"] < 1.0
    explicit = load_config(None, "default", {"weights.lambda_p": 3.0})
    assert collision_for_source_depth(clip, explicit) == (explicit, None)
