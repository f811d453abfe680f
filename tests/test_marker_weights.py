"""Markers weighted by the target hand's proportions (markers.proportion_width): the rest
mismatch after a rigid fit, its known answers (a hand onto itself, one marker moved), the
weights on a robot hand, and the marker figure that keeps counting every marker once."""

import dataclasses

import numpy as np
import pytest

from retarget_core.clip.demo import make_demo_clip, source_rig
from retarget_core.evaluate.metrics import marker_error_per_frame, marker_figure_weights
from retarget_core.rig.demo_hands import demo_hand
from retarget_core.solve.config import load_config
from retarget_core.solve.targets import marker_targets, proportion_weights, rest_marker_mismatch
from retarget_core.transfer.propose import propose_annotations

RES = 0.006
WIDTH = 0.01  # m


@pytest.fixture(scope="module")
def source_and_clip():
    source = source_rig(RES)
    return source, make_demo_clip("bottle_pick_place", time_scale=0.05, resolution=RES, rig=source)


def identity(ann):
    """The annotations with every marker's target points its source points."""
    return dataclasses.replace(ann, markers=tuple(dataclasses.replace(m, target=m.source) for m in ann.markers))


def marker_weight(markers, name):
    return float(markers.pair_weight[np.asarray(markers.names) == name].sum())


def test_a_hand_onto_itself_keeps_its_weights(source_and_clip):
    source, clip = source_and_clip
    markers = marker_targets(clip, source, source, identity(propose_annotations(source, source)))
    names, _, d = rest_marker_mismatch(markers, source, source)
    assert len(names) == len(set(markers.names)) and np.abs(d).max() < 1e-9
    weighted = proportion_weights(markers, source, source, WIDTH)
    assert np.allclose(weighted.pair_weight, markers.pair_weight, rtol=1e-12)
    assert all(v["weight"] == pytest.approx(1.0) for v in weighted.proportion.values())


def test_a_marker_the_target_cannot_meet_loses_its_weight(source_and_clip):
    """The index fingertip marker's target side put on the thumb tip: at rest it is several
    centimetres from where the source has it, and the rigid fit cannot hide that."""
    source, clip = source_and_clip
    ann = identity(propose_annotations(source, source))
    by_name = {m.name: m for m in ann.markers}
    moved = dataclasses.replace(by_name["IndexFingertip"], target=by_name["ThumbFingertip"].target)
    ann = dataclasses.replace(ann, markers=tuple(moved if m.name == "IndexFingertip" else m for m in ann.markers))
    markers = marker_targets(clip, source, source, ann)
    names, _, d = rest_marker_mismatch(markers, source, source)
    d = dict(zip(names, d))
    assert d["IndexFingertip"] > 0.03
    assert max(v for n, v in d.items() if n != "IndexFingertip") < 0.5 * d["IndexFingertip"]
    weighted = proportion_weights(markers, source, source, WIDTH)
    w = {n: marker_weight(weighted, n) / marker_weight(markers, n) for n in d}
    # 1 / (1 + (d / width)^2), rescaled: every ratio between two markers is that of the formula
    ratio = (1 + (d["ThumbBase"] / WIDTH) ** 2) / (1 + (d["IndexFingertip"] / WIDTH) ** 2)
    assert w["IndexFingertip"] / w["ThumbBase"] == pytest.approx(ratio, rel=1e-9)
    assert w["IndexFingertip"] < 0.1 * np.median(list(w.values()))
    assert weighted.proportion["IndexFingertip"]["weight"] == pytest.approx(w["IndexFingertip"], abs=1e-4)
    assert weighted.pair_weight.sum() == pytest.approx(markers.pair_weight.sum(), rel=1e-12)
    # the marker figure still counts the moved marker as much as any other
    assert np.array_equal(marker_figure_weights(weighted), marker_figure_weights(markers))
    q = np.tile(source.rest_pose, (clip.n_frames, 1))
    kin = source.kinematics()
    assert np.allclose(marker_error_per_frame(kin, q, weighted), marker_error_per_frame(kin, q, markers))


def test_robot_hand_markers_are_weighted_by_their_rest_mismatch(source_and_clip):
    source, clip = source_and_clip
    robot = demo_hand("robot4", RES)
    markers = marker_targets(clip, source, robot, propose_annotations(source, robot))
    weighted = proportion_weights(markers, source, robot, WIDTH)
    report = weighted.proportion
    mismatch = np.array([v["rest_mismatch_mm"] for v in report.values()])
    weight = np.array([v["weight"] for v in report.values()])
    assert mismatch.max() > 20.0  # robot4's fingers are longer than the source's
    # the weights fall as the mismatch grows
    order = np.argsort(mismatch)
    assert np.all(np.diff(weight[order]) <= 1e-9)
    assert weighted.pair_weight.sum() == pytest.approx(markers.pair_weight.sum(), rel=1e-12)


def test_proportion_width_is_a_bounded_setting():
    from retarget_core.errors import InputError

    assert load_config(None, "default", {}).markers.proportion_width >= 0
    with pytest.raises(InputError, match="markers.proportion_width"):
        load_config(None, "default", {"markers.proportion_width": -1.0})
