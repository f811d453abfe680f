"""The coherence post-pass: jumps found from rigid steps of marker points (known answers), and
frames that left their neighbours' branch brought back, with a lower objective, the same for
any worker count."""

import numpy as np
import pytest

from retarget_core.execute import Executor
from retarget_core.pipeline import coherence_pass
from retarget_core.refine.branches import (JUMP_MIN_ANGLE, branch_jumps, branch_runs, choose_branch_path,
                                          rigid_steps)
from retarget_core.solve.problem import build_solver_state, frame_value



def _rotation(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def test_rigid_steps_give_the_angle_and_shift_of_each_step():
    rng = np.random.default_rng(4)
    base = rng.normal(size=(12, 3)) * 0.05
    angles = [0.0, 0.1, 0.7, 2.5]
    shifts = [np.zeros(3), [0.01, 0, 0], [0, -0.02, 0.005], [0.3, 0.1, -0.2]]
    frames, r, t = [base], np.eye(3), np.zeros(3)
    for a, s, axis in zip(angles, shifts, ([0, 0, 1], [1, 2, 3], [1, 0, 0], [0.3, -1, 0.2])):
        r, t = _rotation(axis, a) @ r, t + np.asarray(s, float)
        frames.append(base @ r.T + t)
    got_angle, got_shift = rigid_steps(np.array(frames))
    want_shift = [np.linalg.norm((f1 - f0).mean(axis=0)) for f0, f1 in zip(frames[:-1], frames[1:])]
    np.testing.assert_allclose(got_angle, angles, atol=1e-7)
    np.testing.assert_allclose(got_shift, want_shift, atol=1e-12)


def test_a_flip_the_source_does_not_make_is_two_jumps_and_their_runs():
    rng = np.random.default_rng(5)
    base = rng.normal(size=(10, 3)) * 0.04
    source = np.repeat(base[None], 12, axis=0) + np.linspace(0, 0.02, 12)[:, None, None]  # a slow slide
    target = source.copy()
    flip = _rotation([0, 1, 0], 2.0)
    target[5:9] = (target[5:9] - target[5:9].mean(axis=1, keepdims=True)) @ flip.T + target[5:9].mean(axis=1,
                                                                                                     keepdims=True)
    jumps = branch_jumps(target, source)
    assert np.nonzero(jumps)[0].tolist() == [4, 8]
    # the source turning as much is no jump: the same flip on both sides
    assert not branch_jumps(target, target).any()
    # a small turn is under the floor
    small = source.copy()
    small[6:] = small[6:] @ _rotation([0, 0, 1], 0.5 * JUMP_MIN_ANGLE).T
    assert not branch_jumps(small, source).any()
    # each stretch is carried across the whole clip (a trace stops where it rejoins)
    forward, backward = branch_runs(jumps, 1), branch_runs(jumps, -1)
    assert [r.tolist() for r in forward] == [list(range(5, 12)), [9, 10, 11]]
    assert [r.tolist() for r in backward] == [[4, 3, 2, 1, 0], list(range(8, -1, -1))]


def _branches(n_frames=8, seed=6):
    """Marker points of a slowly sliding hand on two branches: A, and B = A turned 90 degrees."""
    rng = np.random.default_rng(seed)
    base = rng.normal(size=(10, 3)) * 0.04
    source = np.repeat(base[None], n_frames, axis=0) + np.linspace(0, 0.01, n_frames)[:, None, None]
    centre = source.mean(axis=1, keepdims=True)
    turned = (source - centre) @ _rotation([0, 0, 1], np.pi / 2).T + centre
    return source, source.copy(), turned


def test_the_branch_path_has_the_fewest_jumps_then_the_lowest_objective():
    source, a, b = _branches()
    # the frames' own solutions: A A B B A A A A (two jumps); frames 2 and 3 also hold an A
    # candidate, a little worse than their own B
    points = [np.array([a[t]]) for t in range(8)]
    values = [np.array([1.0]) for _ in range(8)]
    for t in (2, 3):
        points[t] = np.array([b[t], a[t]])
        values[t] = np.array([1.0, 1.2])
    path, left = choose_branch_path(points, values, source)
    assert left == 0 and path.tolist() == [0, 0, 1, 1, 0, 0, 0, 0]
    # both branches everywhere: no path jumps, so the lower summed objective wins (B, 8 x 0.9)
    points = [np.array([a[t], b[t]]) for t in range(8)]
    values = [np.array([1.0, 0.9]) for _ in range(8)]
    path, left = choose_branch_path(points, values, source)
    assert left == 0 and path.tolist() == [1] * 8
    # B cheaper on the first half only: a switch would be a jump, so one branch throughout,
    # the one with the lower sum (A: 8 against B: 4 x 0.5 + 4 x 3 = 14)
    values = [np.array([1.0, 0.5]) if t < 4 else np.array([1.0, 3.0]) for t in range(8)]
    path, left = choose_branch_path(points, values, source)
    assert left == 0 and path.tolist() == [0] * 8
    # equal values: the frame's own solution (index 0) wins the tie
    path, _ = choose_branch_path(points, [np.ones(2) for _ in range(8)], source)
    assert path.tolist() == [0] * 8
    # a jump no candidate avoids is left, and counted, once
    points = [np.array([a[t]]) if t < 4 else np.array([b[t]]) for t in range(8)]
    path, left = choose_branch_path(points, [np.ones(1) for _ in range(8)], source)
    assert left == 1 and path.tolist() == [0] * 8
    # the source turning the same way is no jump
    source_turned = np.concatenate([a[:4], b[4:]])
    assert choose_branch_path(points, [np.ones(1) for _ in range(8)], source_turned)[1] == 0



@pytest.mark.parametrize("workers", [1, 2])
def test_frames_turned_off_their_branch_are_brought_back(solved_demo, workers):
    problem, config, q = solved_demo
    rig = problem.rig
    bad = np.arange(20, 26)
    turned = q.copy()
    rz = rig.dof_index("root_rz")
    turned[bad, rz] += 1.5  # the hand swung about its root, as a second branch would put it
    executor = Executor(workers=workers)
    with executor.frame_runner(problem) as runner:
        fixed, report = coherence_pass(runner, problem, turned)
        again, again_report = coherence_pass(runner, problem, q)
    assert report.jumps_before >= 2 and report.jumps_after == 0, (report.jumps_before, report.jumps_after)
    assert set(bad.tolist()) <= set(report.replaced)
    state = build_solver_state(problem)
    for f in bad:
        assert frame_value(state, f, fixed[f]) < frame_value(state, f, turned[f])
        # back on the neighbours' branch: as good as the full pass's own solution (root Euler
        # angles near gimbal lock may differ for the same pose, so the objective is compared)
        assert frame_value(state, f, fixed[f]) <= 1.01 * frame_value(state, f, q[f]), f
    assert len(report.replaced) < len(q) // 2  # runs stop where frames were on the branch already
    # only frames on the path's other candidates are replaced: everywhere else the input stays
    untouched = np.setdiff1d(np.arange(len(q)), report.replaced)
    np.testing.assert_array_equal(fixed[untouched], turned[untouched])
    if workers == 2:
        with Executor(workers=1).frame_runner(problem) as runner:
            one, _ = coherence_pass(runner, problem, turned)
        np.testing.assert_array_equal(one, fixed)  # the same for any worker count
    # on the full pass's own result the pass leaves no more jumps than it found, and changes
    # nothing when it found none
    assert again_report.jumps_after <= again_report.jumps_before, vars(again_report)
    if again_report.jumps_before == 0:
        np.testing.assert_array_equal(again, q)
