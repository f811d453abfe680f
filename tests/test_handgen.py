"""The procedural hand generator and the demo library."""

import numpy as np
import pytest

from retarget_core.errors import InputError
from retarget_core.rig.demo_hands import DEMO_HANDS, demo_hand, source_human_spec
from retarget_core.rig.handgen import FingerSpec, JointSpec, build_hand, with_resolution

EXPECTED_FINGERS = {
    "source_human": 5, "human_alt": 5, "witch": 5, "alien": 3,
    "prosthetic_1dof": 5, "prosthetic_2dof": 5, "robot4": 4,
}


@pytest.mark.parametrize("name", list(DEMO_HANDS))
def test_demo_hand_dof_counts_and_closed_manifold_surface(demo_rigs, name):
    rig = demo_rigs[name]
    assert rig.n_dofs == DEMO_HANDS[name][1]
    report = rig.surface.topology()
    assert report.closed and report.manifold and report.components == 1
    assert report.unreferenced_vertices == 0
    rig.validate()
    fingers = {j.name.rstrip("0123456789") for j in rig.joints if j.name not in ("root", "wrist")}
    assert len(fingers) == EXPECTED_FINGERS[name]


def test_paper_dof_counts():
    # The paper's table: human 54, alien 42, prosthetic 26, Allegro 22 (6-DOF root included).
    assert DEMO_HANDS["source_human"][1] == 54
    assert DEMO_HANDS["witch"][1] == 54
    assert DEMO_HANDS["alien"][1] == 42
    assert DEMO_HANDS["prosthetic_2dof"][1] == 26
    assert DEMO_HANDS["robot4"][1] == 22


def test_witch_fingers_are_longer_and_thinner_than_the_source(demo_rigs):
    def finger_extent(rig):
        v = rig.surface.vertices
        return v[:, 1].max()

    assert finger_extent(demo_rigs["witch"]) > 1.25 * finger_extent(demo_rigs["source_human"])


def test_witch_link_lengths_follow_the_papers_lambda_a(demo_rigs):
    """The paper's witch: lambda_A 1.55 on index to pinky, 1.15 on the thumb (rest link lengths
    over the source's, from joint 1 to joint 3)."""
    from retarget_core.rig.demo_hands import WITCH_THUMB_LENGTH_SCALE

    def links(rig, finger):
        world = rig.kinematics().bind_world
        p = np.array([world[rig.joint_index(f"{finger}{k}")][:3, 3] for k in (1, 2, 3)])
        return np.linalg.norm(np.diff(p, axis=0), axis=1)

    for finger, scale in (("thumb", WITCH_THUMB_LENGTH_SCALE), ("index", 1.55), ("middle", 1.55), ("pinky", 1.55)):
        ratio = links(demo_rigs["witch"], finger) / links(demo_rigs["source_human"], finger)
        np.testing.assert_allclose(ratio, scale, rtol=1e-6, err_msg=finger)


def test_fingertips_follow_the_last_joint_only(demo_rigs):
    rig = demo_rigs["source_human"]
    tip_joint = rig.joint_index("middle3")
    v = rig.surface.vertices
    tip = np.argmax(np.where(np.abs(v[:, 0] - v[np.argmax(v[:, 1]), 0]) < 0.01, v[:, 1], -np.inf))
    dense = rig.surface.dense_weights(rig.n_joints)
    assert dense[tip, tip_joint] > 0.99


def test_finger_curls_toward_the_palm(demo_rigs):
    rig = demo_rigs["source_human"]
    kin = rig.kinematics()
    q = rig.rest_pose.copy()
    for k in (1, 2, 3):
        q[rig.dof_index(f"index{k}_flex")] = np.radians(60)
    moved = kin.skin(q) - kin.skin(rig.rest_pose)
    index_tip = np.argmax(np.where(rig.surface.dense_weights(rig.n_joints)[:, rig.joint_index("index3")] > 0.99,
                                   rig.surface.vertices[:, 1], -np.inf))
    assert moved[index_tip, 2] < -0.03  # palm faces -Z


def test_finer_resolution_gives_more_vertices():
    coarse = build_hand(with_resolution(source_human_spec(), 0.006))
    fine = build_hand(with_resolution(source_human_spec(), 0.004))
    assert fine.surface.n_vertices > 1.5 * coarse.surface.n_vertices
    assert coarse.n_dofs == fine.n_dofs == 54


def test_bad_specs_are_rejected():
    with pytest.raises(InputError, match="unknown DOF"):
        JointSpec(("bend",), {"bend": (0, 90)})
    with pytest.raises(InputError, match="no limits"):
        JointSpec(("flex",), {})
    with pytest.raises(InputError, match="one more radius"):
        FingerSpec("index", (0, 0.09, 0), (0, 1, 0), (0.04, 0.02), (0.01, 0.009),
                   (JointSpec(("flex",), {"flex": (0, 90)}),) * 2)


def test_unknown_demo_hand_name():
    with pytest.raises(KeyError, match="unknown demo hand"):
        demo_hand("octopus")
