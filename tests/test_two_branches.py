"""A clip with two root branches that fit about equally well: the delivered curve does not jump.

The demo robot4 hand (proposed annotations, no edits) has four fingers with other proportions
than the source's, so the 25 markers cannot all be met and its root has two poses about 55
degrees apart that score alike. The clip is built for it: the demo bottle held and lifted
(contact in every frame) while hand and bottle turn slowly about the vertical through the
bottle, so the source root turns a known amount every frame. Solved frame by frame (coherence
pass off), the root flips between the branches; the default preset must deliver a curve whose
root changes per frame by at most 10 degrees / 10 mm, its shift at most twice the source's own
largest. (Until stop 44 this test used the LEAP hand, whose root flipped by 110 degrees; with
the proposer's finger curves drawn through every articulation its frames no longer flip, 17
degrees at most, and neither do the prosthetics', 3 degrees.)
With the patch sizing of the default preset (``contacts.keep_patch_size``, stop 48) the solved
frames no longer flip out and back: they switch branch for good (frame 103, 61 degrees; with the
pass: frame 56, 52 degrees). There the branch the hand came on stops fitting: traced on across
it, its objective rises 5x (25315 against 5069 on the branch taken, stop 48's trace), so the
pass keeps that switch ("a jump no branch avoids") and removes the others (18 jumps -> 2). Until
stop 47 the test asked the pass to halve the largest solved step; now it asks for what the pass
promises: far fewer jumps, none larger than before, and none of them out and back (a flip the
neighbours' branch would have covered); the delivered curve's bounds are unchanged.
Not yet asserted: issue 20's "rotation at most twice the source's": the delivered root turns up
to 1.8 degrees a frame against the source's 0.5.
"""

import dataclasses

import numpy as np
import pytest

from retarget_core.clip.demo import grasp_window, make_demo_clip, source_rig
from retarget_core.execute import Executor
from retarget_core.inputs import RunInputs
from retarget_core.pipeline import retarget
from retarget_core.rig.anatomy import continuous_root_angles, root_transform, set_root_transform
from retarget_core.rig.io import resolve_rig
from retarget_core.solve.config import load_config
from retarget_core.transfer.propose import propose_annotations

TURN_DEG_PER_FRAME = 0.5


def _rot_z(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def turned_clip(clip, source, deg_per_frame):
    """The clip with hand and object turned by ``deg_per_frame`` more each frame about the
    vertical (z, the table's normal) through the object's first position."""
    centre = clip.object_poses[0][:3, 3].copy()
    hand = clip.hand_vertices.astype(np.float64).copy()
    poses, dofs = clip.object_poses.copy(), clip.dof_values.copy()
    for t in range(clip.n_frames):
        m = np.eye(4)
        m[:3, :3] = _rot_z(np.radians(deg_per_frame * t))
        m[:3, 3] = centre - m[:3, :3] @ centre
        hand[t] = hand[t] @ m[:3, :3].T + m[:3, 3]
        poses[t] = m @ poses[t]
        dofs[t] = set_root_transform(source, dofs[t], m @ root_transform(source, dofs[t]))
    return dataclasses.replace(clip, hand_vertices=hand.astype(clip.hand_vertices.dtype), object_poses=poses,
                               dof_values=dofs)


def root_steps(rig, q):
    """Per step of q (T, D): the root's rotation (T-1,) degrees and its origin's shift (T-1,) mm."""
    world = np.array([rig.kinematics().pose(x).world[0] for x in q])
    r = np.einsum("tji,tjk->tik", world[:-1, :3, :3], world[1:, :3, :3])
    angle = np.degrees(np.arccos(np.clip((np.trace(r, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    return angle, 1000 * np.linalg.norm(world[1:, :3, 3] - world[:-1, :3, 3], axis=1)


def out_and_back(rig, q, angle=10.0, shift=10.0, within=5):
    """The steps k of q (T, D) where the root turns more than ``angle`` degrees or moves more
    than ``shift`` mm and is back within both of frame k's pose at one of the next ``within``
    frames: a flip, not a switch of branch."""
    world = np.array([rig.kinematics().pose(x).world[0] for x in q])

    def apart(i, j):
        r = world[i, :3, :3].T @ world[j, :3, :3]
        a = np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1)))
        return a > angle or 1000 * np.linalg.norm(world[i, :3, 3] - world[j, :3, 3]) > shift

    return [k for k in range(len(q) - 1)
            if apart(k, k + 1) and any(not apart(k, j) for j in range(k + 2, min(len(q), k + 2 + within)))]


@pytest.fixture(scope="module")
def two_branch_case():
    source = source_rig()
    # the hold and lift: 116 frames starting just after the grasp closed
    window = grasp_window(make_demo_clip("bottle_pick_place", rig=source), 240).slice(124, 240)
    assert (window.contact_labels > 0).any(axis=1).all()
    clip = turned_clip(window, source, TURN_DEG_PER_FRAME)
    target = resolve_rig("demo:robot4")
    inputs = RunInputs.of(clip, source, target, propose_annotations(source, target))
    results = {on: retarget(inputs, load_config(None, "default", {"passes.coherence": on}), Executor(workers=2))
               for on in (True, False)}
    return source, clip, target, results


def test_the_delivered_root_stays_on_one_branch(two_branch_case):
    source, clip, target, results = two_branch_case
    src_angle, src_shift = root_steps(source, clip.dof_values)
    np.testing.assert_allclose(src_angle, TURN_DEG_PER_FRAME, atol=1e-6)  # the built turn

    # frame by frame the root flips between two branches far apart ...
    alone = results[False]
    solved_angle, _ = root_steps(target, alone.q)
    assert solved_angle.max() > 30, solved_angle.max()  # the source turns 0.5 degrees a frame
    # ... that fit about equally well (the solved frames' contact error with and without the
    # coherence pass within 1 mm: neither branch is a bad fit the pass could simply reject)
    coherent = results[True]
    assert abs(coherent.summary["solved_contact_distance_median_mm"]
               - alone.summary["solved_contact_distance_median_mm"]) < 1.0, (coherent.summary, alone.summary)
    # the pass finds the flips and re-solves them from the neighbours' branch
    coherence = coherent.counts["passes"]["coherence"]
    assert coherence["jumps_before"] > 0 and coherence["jumps_after"] < coherence["jumps_before"], coherence
    assert coherence["jumps_after"] <= coherence["jumps_before"] // 3, coherence
    coherent_angle, coherent_shift = root_steps(target, coherent.q)
    assert coherent_angle.max() <= solved_angle.max(), (coherent_angle.max(), solved_angle.max())
    assert not out_and_back(target, coherent.q), out_and_back(target, coherent.q)

    # the delivered curve: no jump
    angle, shift = root_steps(target, coherent.sampled())
    assert angle.max() <= 10.0, (angle.max(), int(angle.argmax()), src_angle.max())
    assert shift.max() <= min(10.0, 2 * src_shift.max()), (shift.max(), int(shift.argmax()), src_shift.max())
    # and it scores like the solved frames
    assert coherent.summary["contact_distance_median_mm"] <= 1.1 * coherent.summary[
        "solved_contact_distance_median_mm"], coherent.summary


def test_root_angles_made_continuous_keep_every_pose(demo_rigs):
    """Euler triples in other charts (whole turns, (a + pi, pi - b, c + pi)) come back nearest
    the frame before, each frame's root rotation unchanged (known answer: the same matrices)."""
    rig = demo_rigs["source_human"]
    idx = [rig.dof_index(n) for n in ("root_rx", "root_ry", "root_rz")]
    t = np.linspace(0, 1, 30)
    q = np.repeat(rig.rest_pose[None], len(t), axis=0)
    q[:, idx[0]] = 0.3 + 0.5 * t
    q[:, idx[1]] = 1.45 + 0.25 * t  # through b = 90 degrees (gimbal lock) and beyond
    q[:, idx[2]] = -0.4 + 0.3 * t
    charts = q.copy()
    charts[5:12, idx] = np.stack([q[5:12, idx[0]] + np.pi, np.pi - q[5:12, idx[1]], q[5:12, idx[2]] - np.pi], 1)
    charts[15:20, idx[2]] += 2 * np.pi
    charts[22:, idx[0]] -= 2 * np.pi
    kin = rig.kinematics()
    for a, b in zip(q, charts):  # the same rotations written differently
        np.testing.assert_allclose(kin.pose(a).world[0], kin.pose(b).world[0], atol=1e-12)
    fixed = continuous_root_angles(rig, charts)
    np.testing.assert_allclose(fixed, q, atol=1e-12)
    for a, b in zip(q, fixed):
        np.testing.assert_allclose(kin.pose(a).world[0], kin.pose(b).world[0], atol=1e-12)
    # a single frame has nothing to follow: it comes back as it was
    np.testing.assert_array_equal(continuous_root_angles(rig, charts[5:6]), charts[5:6])


def test_out_and_back_tells_a_flip_from_a_switch(demo_rigs):
    """Known answers: a root that turns 60 degrees for one frame and back is a flip; one that
    turns 60 degrees and stays is a switch; a steady 0.5 degrees a frame is neither."""
    rig = demo_rigs["source_human"]
    q = np.repeat(rig.rest_pose[None], 20, axis=0)
    base = root_transform(rig, rig.rest_pose)

    def turned(deg):
        m = np.eye(4)
        m[:3, :3] = _rot_z(np.radians(deg))
        return set_root_transform(rig, rig.rest_pose, m @ base)

    steady = np.array([turned(0.5 * t) for t in range(20)])
    assert out_and_back(rig, steady) == []
    flip = steady.copy()
    flip[8] = turned(60.0)
    assert out_and_back(rig, flip) == [7]  # out at step 7 (back at step 8 is no flip from frame 8's view)
    switch = steady.copy()
    switch[8:] = [turned(60.0 + 0.5 * t) for t in range(12)]
    assert out_and_back(rig, switch) == []
