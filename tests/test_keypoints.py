"""Keypoint-only retargeting (``handretarget retarget-keypoints``, retarget_core/solve/keypoints.py):
keypoints made by posing the LEAP hand (the installed robot model) along a known trajectory are
found again, root included; a link's origin as a keypoint; unseen keypoints; bad files name their
problem; the command writes the robot's joint commands in the URDF's order."""

import json

import numpy as np
import pytest

from installed_models import installed_or_none
from retarget_core.errors import InputError

LEAP = installed_or_none("leap")
pytestmark = pytest.mark.skipif(LEAP is None, reason="the LEAP model's wheel (ghand) is not installed")
SPEC = "installed:leap@0.005"


@pytest.fixture(scope="module")
def leap():
    from retarget_core.clip.demo import source_rig
    from retarget_core.rig.io import resolve_rig
    from retarget_core.transfer.propose import propose_annotations

    rig = resolve_rig(SPEC)
    return rig, propose_annotations(source_rig(), rig)


def test_keypoints_of_a_known_motion_are_found_again_root_included(leap):
    """Every marker of the proposed annotations plus a link (the rig's second joint, a joint
    keypoint: the link frame's origin), 60 frames of smooth motion over 60 % of every DOF's range
    and a turning, moving root: the solved frames put every keypoint within 0.5 mm of where the
    known poses put it (median < 0.02 mm) and the root where it was (1 mm, 1 degree), so the
    hand's pose is found, not only its points."""
    from retarget_core.benchmarks.keypoints import synthetic_keypoints
    from retarget_core.solve.keypoints import KeypointObjective, Keypoints, keypoint_sites, solve_keypoints

    rig, annotations = leap
    link = rig.joint_names[1]
    kp, q_true, _ = synthetic_keypoints(rig, annotations, 60, fps=120.0, seed=3)
    names = kp.names + (link,)
    sites = keypoint_sites(rig, names, annotations)
    assert sites.kinds[-1] == "joint" and set(sites.kinds[:-1]) == {"marker"} and len(names) >= 15
    objective = KeypointObjective(rig, sites)
    positions = np.stack([objective.positions(objective.kin.pose(q)) for q in q_true])
    # the link keypoint is the joint's origin
    np.testing.assert_allclose(positions[:, -1], np.stack([objective.kin.pose(q).world[1, :3, 3] for q in q_true]),
                               atol=1e-12)
    solved = solve_keypoints(rig, sites, Keypoints(names, positions, 120.0))
    assert np.nanmax(solved.error_mm) < 0.5 and np.nanmedian(solved.error_mm) < 0.02
    root = np.array([d.joint == 0 for d in rig.dofs])
    kin = rig.kinematics()
    for q_s, q_t in zip(solved.q, q_true):
        a, b = kin.pose(q_s).world[0], kin.pose(q_t).world[0]
        assert np.linalg.norm(a[:3, 3] - b[:3, 3]) < 1e-3
        angle = np.degrees(np.arccos(np.clip((np.trace(a[:3, :3].T @ b[:3, :3]) - 1) / 2, -1, 1)))
        assert angle < 1.0
    assert np.all(solved.q >= rig.lower - 1e-9) and np.all(solved.q <= rig.upper + 1e-9)
    assert root.sum() == 6


def test_unseen_keypoints_are_left_out_of_their_frames(leap):
    """NaN keypoints (not seen in a frame) cost nothing there: the others are still met and the
    error of the unseen ones is NaN; a keypoint partly NaN is an error."""
    from retarget_core.benchmarks.keypoints import synthetic_keypoints
    from retarget_core.solve.keypoints import Keypoints, keypoint_sites, solve_keypoints

    rig, annotations = leap
    kp, _, _ = synthetic_keypoints(rig, annotations, 20, seed=5)
    positions = kp.positions.copy()
    positions[5:15, 0] = np.nan  # the first keypoint unseen for ten frames
    positions[8, 3] = np.nan
    solved = solve_keypoints(rig, keypoint_sites(rig, kp.names, annotations), Keypoints(kp.names, positions, kp.fps))
    assert np.isnan(solved.error_mm[5:15, 0]).all() and np.isnan(solved.error_mm[8, 3])
    seen = np.isfinite(solved.error_mm)
    assert seen.sum() == positions.shape[0] * positions.shape[1] - 11
    assert solved.error_mm[seen].max() < 0.5


def _write(path, **arrays):
    np.savez(path, **arrays)
    return path


def test_bad_keypoint_files_name_their_problem(tmp_path, leap):
    from retarget_core.solve.keypoints import keypoint_sites, load_keypoints

    good = np.zeros((4, 3, 3))
    good[:, 1, 0] = 0.05
    good[:, 2, 1] = 0.05
    names = np.array(["IndexFingertip", "ThumbFingertip", "PalmRoot"])
    cases = [
        (dict(positions=good), "names"),
        (dict(positions=good[:, :, :2], names=names, fps=30.0), "positions"),
        (dict(positions=good * 1000.0, names=names, fps=30.0), "metres"),
        (dict(positions=good, names=names[:2], fps=30.0), "names"),
        (dict(positions=good, names=np.array(["a", "a", "b"]), fps=30.0), "repeats"),
        (dict(positions=good, names=names), "fps"),
        (dict(positions=good, names=names, fps=-1.0), "fps"),
    ]
    partly = good.copy()
    partly[1, 0, 2] = np.nan
    cases.append((dict(positions=partly, names=names, fps=30.0), "partly NaN"))
    blind = good.copy()
    blind[2, :2] = np.nan
    cases.append((dict(positions=blind, names=names, fps=30.0), "frame 2"))
    for i, (arrays, needle) in enumerate(cases):
        with pytest.raises(InputError, match=needle):
            load_keypoints(_write(tmp_path / f"bad{i}.npz", **arrays))
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="readable"):
        load_keypoints(tmp_path / "junk.npz")
    ok = load_keypoints(_write(tmp_path / "ok.npz", positions=good, names=names, fps=30.0))
    assert ok.names == tuple(names) and ok.fps == 30.0 and load_keypoints(tmp_path / "ok.npz", fps=60.0).fps == 60.0
    rig, annotations = leap
    from retarget_core.rig.demo_hands import demo_hand

    with pytest.raises(InputError, match="made on rig"):  # annotations of another hand's mesh
        keypoint_sites(demo_hand("prosthetic_2dof", 0.006), ("IndexFingertip", "PalmRoot", "ThumbFingertip"),
                       annotations)
    with pytest.raises(InputError, match="IndexFingertip") as err:
        keypoint_sites(rig, ("IndexFingertp", "PalmRoot", "ThumbFingertip"), annotations)
    assert "closest" in str(err.value)


def test_the_command_writes_joint_commands_in_the_urdf_order(tmp_path, leap):
    """``handretarget retarget-keypoints`` on the LEAP hand: animation.json holds the delivered
    spline at the frames and the robot section (the URDF's joints, at --rate); keypoints.json
    the errors at the delivered curve (small: the keypoints came from a smooth motion) and the
    time per frame."""
    from retarget_core.benchmarks.keypoints import synthetic_keypoints
    from retarget_core.cli import main
    from retarget_core.export.robot_trajectory import robot_joint_dofs

    rig, annotations = leap
    kp, _, _ = synthetic_keypoints(rig, annotations, 48, fps=60.0, seed=7)
    path = _write(tmp_path / "keys.npz", positions=kp.positions, names=np.array(kp.names), fps=60.0)
    assert main(["retarget-keypoints", "--rig", SPEC, "--targets", str(path), "--out", str(tmp_path / "out"),
                 "--rate", "100"]) == 0
    doc = json.loads((tmp_path / "out" / "animation.json").read_text())
    assert doc["dof_names"] == rig.dof_names and len(doc["times"]) == 48
    assert doc["extra"]["values"] == "spline"
    robot = doc["robot"]
    assert robot["rate_hz"] == 100 and [j["name"] if isinstance(j, dict) else j for j in robot["joints"]] == \
        [rig.dof_names[i] for i in robot_joint_dofs(rig)]
    report = json.loads((tmp_path / "out" / "keypoints.json").read_text())
    assert report["frames"] == 48 and report["ms_per_frame"] > 0
    assert report["error_mm"]["solved"]["max"] < 0.5
    assert report["error_mm"]["delivered"]["median"] < 1.0  # 10 control points a second through 60 fps frames
