"""Per-frame objective, its analytic gradients, the frame solver and the identity retarget."""

import re

import numpy as np
import pytest

from retarget_core.clip.demo import build_demo_timeline, clip_from_timeline, source_rig
from retarget_core.execute import Executor
from retarget_core.fit import fit_trajectory
from retarget_core.fit.splines import evaluate_curves
from retarget_core.inputs import RunInputs
from retarget_core.mesh.surface_points import SurfacePoints
from retarget_core.pairing.dense import pair_contacts
from retarget_core.pipeline import retarget
from retarget_core.solve.config import RetargetConfig
from retarget_core.solve.frame_solver import gauss_newton_warm_start, solve_frame
from retarget_core.solve.objective import FrameData
from retarget_core.solve.problem import Problem, build_solver_state, method_objective, solve_frames
from retarget_core.solve.targets import contact_targets, marker_targets
from retarget_core.transfer.annotations import resolve_points
from retarget_core.transfer.clip_transfer import transfer_clip
from retarget_core.transfer.propose import propose_annotations


@pytest.fixture(scope="module")
def setup():
    rig = source_rig()
    obj, timeline = build_demo_timeline("bottle_pick_place", time_scale=0.15, rig=rig)
    clip = clip_from_timeline("bottle_pick_place", obj, timeline, rig, 0.004)
    annotations = propose_annotations(rig, rig)
    pairs = pair_contacts(clip)
    transferred = transfer_clip(pairs, rig, rig, annotations)
    return rig, clip, annotations, pairs, transferred


def _problem(setup, marker_distance=None, **weights):
    rig, clip, annotations, pairs, transferred = setup
    cfg = RetargetConfig.preset("default")
    cfg.markers.distance = marker_distance or cfg.markers.distance
    for k, v in weights.items():
        setattr(cfg.weights, k, v)
    markers = marker_targets(clip, rig, rig, annotations)
    contacts = contact_targets(clip, pairs, transferred.contacts, keep_source_gap=True)
    return Problem(rig, cfg, markers, contacts, clip.object_poses, clip.table_pose, clip.table_half_extents,
                   clip.object_vertices, clip.object_faces)


def _busiest_frame(problem):
    return int(np.argmax(np.diff(problem.contacts.frame_offsets)))


def _central_difference(fun, q, h=1e-6):
    return np.array([(fun(q + h * e) - fun(q - h * e)) / (2 * h) for e in np.eye(len(q))])


TERMS = {
    "markers": dict(lambda_c=0.0, lambda_t=0.0, lambda_j=0.0, lambda_p=0.0),
    "contact distance": dict(lambda_m=0.0, lambda_cn=0.0, lambda_t=0.0, lambda_j=0.0, lambda_p=0.0),
    "contact normal": dict(lambda_m=0.0, lambda_cd=0.0, lambda_t=0.0, lambda_j=0.0, lambda_p=0.0),
    "prior": dict(lambda_m=0.0, lambda_c=0.0, lambda_t=0.0, lambda_p=0.0),
    "penetration": dict(lambda_m=0.0, lambda_c=0.0, lambda_t=0.0, lambda_j=0.0, lambda_p=1.0),
}


@pytest.mark.parametrize("term", sorted(TERMS))
def test_each_term_gradient_matches_central_differences(setup, term):
    problem = _problem(setup, **TERMS[term])
    objective = method_objective(problem, "root")
    f = _busiest_frame(problem)
    objective.set_frame(problem.frame_data(f))
    rng = np.random.default_rng(3)
    q = setup[1].dof_values[f] + rng.normal(scale=0.08, size=problem.rig.n_dofs)
    q[:3] = setup[1].dof_values[f, :3] + rng.normal(scale=0.004, size=3)  # fingers pushed into the bottle
    value, grad = objective.value_and_grad(q)
    assert value > 0
    fd = _central_difference(lambda x: objective.value_and_grad(x, want_grad=False)[0], q)
    assert np.abs(fd).max() > 0
    assert np.abs(grad - fd).max() <= 1e-5 * np.abs(fd).max()


def test_table_term_gradient_with_the_hand_pushed_into_the_table(setup):
    problem = _problem(setup, lambda_m=0.0, lambda_c=0.0, lambda_j=0.0, lambda_p=0.0)
    objective = method_objective(problem, "root")
    objective.set_frame(problem.frame_data(0))
    q = setup[1].dof_values[0].copy()
    table_top = problem.table_pose[2, 3] + problem.table_half_extents[2]
    points = problem.rig.kinematics().skin(q)
    q[2] += table_top - points[:, 2].min() - 0.006  # the lowest vertex 6 mm deep
    value, grad = objective.value_and_grad(q)
    assert value > 0
    assert grad[2] < 0  # moving up reduces the penalty
    fd = _central_difference(lambda x: objective.value_and_grad(x, want_grad=False)[0], q)
    assert np.abs(grad - fd).max() <= 1e-5 * np.abs(fd).max()


def test_table_block_is_the_hinge_in_least_squares_form(setup, monkeypatch):
    """The curve polish's Gauss-Newton model of the table: sum r^2 is lambda_t G_T and 2 J^T r
    its gradient (central differences), exactly without the floor; with it, the shallow
    points' rows are capped and the deep ones unchanged."""
    from retarget_core.solve import objective as objective_module

    problem = _problem(setup, lambda_m=0.0, lambda_c=0.0, lambda_j=0.0, lambda_p=0.0, lambda_t=2.0)
    objective = method_objective(problem, "root")
    objective.set_frame(problem.frame_data(0))
    q = setup[1].dof_values[0].copy()
    q[3:6] += 0.05  # tilted, so the depth varies across the points inside
    table_top = problem.table_pose[2, 3] + problem.table_half_extents[2]
    points = problem.rig.kinematics().skin(q)
    q[2] += table_top - points[:, 2].min() - 0.006  # the lowest vertex 6 mm deep
    objective.focus_samples(q)
    pose = objective.kin.pose(q)
    n = problem.rig.n_dofs
    value = objective.value_and_grad(q, want_grad=False)[0]
    assert value > 0

    monkeypatch.setattr(objective_module, "TABLE_FLOOR_MM", 0.0)
    r, jt = objective.table_block(pose, n)
    assert len(r) > 10 and jt.shape == (n, len(r))
    assert r @ r == pytest.approx(value, rel=1e-12)
    fd = _central_difference(lambda x: objective.value_and_grad(x, want_grad=False)[0], q)
    assert np.abs(2 * jt @ r - fd).max() <= 1e-5 * np.abs(fd).max()
    # the same block inside the system, beside the (here zero) least-squares terms
    cost, g, h = objective.normal_equations(q, table=True)
    assert cost == pytest.approx(value, rel=1e-12)
    np.testing.assert_allclose(g, jt @ r, rtol=1e-10, atol=1e-12 * np.abs(g).max())
    np.testing.assert_allclose(h, jt @ jt.T, rtol=1e-10, atol=1e-12 * np.abs(h).max())
    assert objective.normal_equations(q)[0] == 0.0  # the warm start's system leaves it out

    monkeypatch.setattr(objective_module, "TABLE_FLOOR_MM", 0.5)
    r_floor, jt_floor = objective.table_block(pose, n)
    np.testing.assert_array_equal(r_floor, r)
    shallow = r * r / 2.0 < 0.5  # depth in mm below the floor (lambda_t = 2)
    assert shallow.any() and (~shallow).any()
    np.testing.assert_allclose(jt_floor[:, ~shallow], jt[:, ~shallow], rtol=1e-12)
    assert np.all(np.abs(jt_floor[:, shallow]) <= np.abs(jt[:, shallow]) + 1e-12)


def test_residual_form_equals_objective_and_its_jacobian_matches(setup):
    problem = _problem(setup, lambda_t=0.0, lambda_p=0.0)
    objective = method_objective(problem, "root")
    f = _busiest_frame(problem)
    objective.set_frame(problem.frame_data(f))
    q = setup[1].dof_values[f] + np.random.default_rng(5).normal(scale=0.05, size=problem.rig.n_dofs)
    r, jac = objective.residuals(q)
    assert np.isclose(r @ r, objective.value_and_grad(q, want_grad=False)[0], rtol=1e-10)
    fd = _central_difference(lambda x: objective.residuals(x)[0], q).T
    assert np.abs(jac - fd).max() <= 1e-5 * np.abs(fd).max()


@pytest.mark.parametrize("distance", ["squared", "huber"])
def test_normal_equations_and_residual_cost_equal_the_residual_form(setup, distance):
    """What the warm start uses: (sum r^2, J^T r, J^T J) summed per term without forming J, and
    the Jacobian-free sum r^2 of a trial step, against the stacked residuals and Jacobian."""
    problem = _problem(setup, marker_distance=distance, lambda_t=0.0, lambda_p=0.0)
    objective = method_objective(problem, "root")
    f = _busiest_frame(problem)
    objective.set_frame(problem.frame_data(f))
    objective.set_seed(setup[1].dof_values[f])
    rng = np.random.default_rng(21)
    for _ in range(3):
        q = setup[1].dof_values[f] + rng.normal(scale=0.1, size=problem.rig.n_dofs)
        r, jac = objective.residuals(q)
        cost, g, h = objective.normal_equations(q)
        assert np.isclose(cost, r @ r, rtol=1e-12)
        assert np.isclose(objective.residual_cost(q), r @ r, rtol=1e-12)
        assert np.allclose(g, jac.T @ r, rtol=1e-10, atol=1e-10 * np.abs(g).max())
        assert np.allclose(h, jac.T @ jac, rtol=1e-10, atol=1e-10 * np.abs(h).max())
        assert np.allclose(h, h.T)


@pytest.mark.parametrize("distance", ["squared", "huber"])
def test_marker_term_gradient_and_residual_form_for_each_distance(setup, distance):
    problem = _problem(setup, marker_distance=distance, lambda_c=0.0, lambda_t=0.0, lambda_j=0.0, lambda_p=0.0)
    objective = method_objective(problem, "root")
    f = _busiest_frame(problem)
    objective.set_frame(problem.frame_data(f))
    q = setup[1].dof_values[f] + np.random.default_rng(11).normal(scale=0.08, size=problem.rig.n_dofs)
    value, grad = objective.value_and_grad(q)
    fd = _central_difference(lambda x: objective.value_and_grad(x, want_grad=False)[0], q)
    assert value > 0 and np.abs(fd).max() > 0
    assert np.abs(grad - fd).max() <= 1e-5 * np.abs(fd).max()
    r, jac = objective.residuals(q)
    assert np.isclose(r @ r, value, rtol=1e-10)
    fd_r = _central_difference(lambda x: objective.residuals(x)[0], q).T
    assert np.abs(jac - fd_r).max() <= 1e-5 * np.abs(fd_r).max()


def test_marker_penalty_known_values(setup):
    """A pair 4 mm off with delta = 3 mm costs 2 * 3 * (sqrt(16 + 9) - 3) = 12 (mm^2); squared,
    16. Near zero both are d^2; far off the Huber pull (d rho / d d) tends to 2 delta = 6
    while the squared one grows as 2 d."""
    d2 = np.array([0.0, 16.0, 1e6, 1e-6])
    huber = method_objective(_problem(setup, marker_distance="huber"), "root")
    huber.marker_delta = 3.0
    rho, slope = huber._marker_penalty(d2)
    assert np.allclose(rho[:2], [0.0, 12.0])
    assert np.isclose(rho[3], 1e-6, rtol=1e-6) and np.isclose(slope[0], 1.0)
    assert np.isclose(2 * np.sqrt(d2[2]) * slope[2], 6.0, rtol=1e-5)  # d rho / d d = 2 d slope
    rho, slope = method_objective(_problem(setup, marker_distance="squared"), "root")._marker_penalty(d2)
    assert np.allclose(rho, d2) and np.allclose(slope, 1.0)


def test_frame_solve_from_rest_reaches_the_capture(setup):
    """Markers and contacts of a captured frame, seeded at rest fingers and the true root: the
    warm-started solve recovers the finger pose; MMA alone at the same cap does worse."""
    problem = _problem(setup, lambda_p=0.0)
    objective = method_objective(problem, "root")
    rig, clip = problem.rig, setup[1]
    f = _busiest_frame(problem)
    objective.set_frame(problem.frame_data(f))
    seed = rig.rest_pose.copy()
    seed[:6] = clip.dof_values[f, :6]
    common = dict(maxeval=100, xtol_rel=1e-4, kinds=[d.kind for d in rig.dofs],
                  root_mask=[d.joint == 0 for d in rig.dofs])
    warm = solve_frame(objective, seed, rig.lower, rig.upper, np.ones(rig.n_dofs, bool), warm_start_iterations=20,
                       **common)
    plain = solve_frame(objective, seed, rig.lower, rig.upper, np.ones(rig.n_dofs, bool), **common)
    assert warm.ok and plain.ok
    rmse = np.degrees(np.sqrt(np.mean((warm.q - clip.dof_values[f])[6:] ** 2)))
    assert rmse < 2.0
    assert warm.value < plain.value
    assert np.all(warm.q >= rig.lower - 1e-12) and np.all(warm.q <= rig.upper + 1e-12)


def test_warm_start_respects_bounds_and_never_increases_the_cost(setup):
    problem = _problem(setup, lambda_t=0.0, lambda_p=0.0)
    objective = method_objective(problem, "root")
    rig = problem.rig
    objective.set_frame(problem.frame_data(_busiest_frame(problem)))
    upper = rig.upper.copy()
    upper[6:] = np.minimum(upper[6:], rig.rest_pose[6:] + 0.1)  # a tight box the solution presses on
    seed = setup[1].dof_values[0].copy()
    seed[6:] = rig.rest_pose[6:]
    q = gauss_newton_warm_start(objective, seed, rig.lower, upper, np.ones(rig.n_dofs, bool), 20)
    assert np.all(q <= upper + 1e-12) and np.all(q >= rig.lower - 1e-12)
    assert np.any(np.isclose(q[6:], upper[6:]))
    r0, _ = objective.residuals(seed)
    r1, _ = objective.residuals(q)
    assert r1 @ r1 < r0 @ r0


def test_forward_difference_mode_agrees_with_analytic(setup):
    problem = _problem(setup, lambda_p=0.0)
    objective = method_objective(problem, "root")
    rig, clip = problem.rig, setup[1]
    f = _busiest_frame(problem)
    objective.set_frame(problem.frame_data(f))
    seed = clip.dof_values[f].copy()
    seed[6:] = 0.5 * (seed[6:] + rig.rest_pose[6:])
    common = dict(maxeval=40, xtol_rel=1e-4, kinds=[d.kind for d in rig.dofs],
                  root_mask=[d.joint == 0 for d in rig.dofs])
    analytic = solve_frame(objective, seed, rig.lower, rig.upper, np.ones(rig.n_dofs, bool), **common)
    forward = solve_frame(objective, seed, rig.lower, rig.upper, np.ones(rig.n_dofs, bool), gradient="forward",
                          fd_step=1e-7, **common)
    # forward mode spends one evaluation per DOF on every gradient
    assert forward.evaluations > 10 * analytic.evaluations / 2
    assert abs(forward.value - analytic.value) < 0.05 * analytic.value


def test_failed_frame_is_reported_not_zero(setup):
    problem = _problem(setup, lambda_p=0.0)
    objective = method_objective(problem, "root")
    rig = problem.rig
    data = problem.frame_data(0)
    objective.set_frame(FrameData(np.full_like(data.markers, np.nan), data.contacts, data.object_points,
                                  data.object_normals, data.object_pose))
    seed = setup[1].dof_values[0]
    sol = solve_frame(objective, seed, rig.lower, rig.upper, np.ones(rig.n_dofs, bool), maxeval=20, xtol_rel=1e-4)
    assert not sol.ok
    assert sol.error
    assert np.allclose(sol.q, seed)  # the seed comes back, never zeros


def test_identity_retarget_recovers_the_capture(setup):
    """A demo clip made with the source rig, retargeted onto that rig with identity annotations:
    DOF RMSE under 2 degrees and fingertip error under 2 mm over contact frames, for the
    solved trajectory and for the fitted splines."""
    rig, clip, annotations, pairs, _ = setup
    cfg = RetargetConfig.preset("default")
    cfg.passes.fit = False  # every pass up to the fit (the spline is fitted below, 45 control points)
    traj = retarget(RunInputs.of(clip, rig, rig, annotations), cfg, Executor(workers=2), pairs=pairs)
    times = np.arange(clip.n_frames) / clip.fps
    # the clip runs at 0.15 of the demo's duration: a whole pick and place in about a second, so
    # the spline needs more control points per second than a real-speed capture
    curves = fit_trajectory(times, traj.q, 45, mask=~traj.unresolved,
                            optimize_knots=False)
    fitted = evaluate_curves(curves, times)
    contact = np.diff(traj.contacts.frame_offsets) > 0
    assert contact.sum() > 20
    kin = rig.kinematics()
    tips = [resolve_points([m.target[0]], rig.surface.faces, rig.surface.n_vertices, what=m.name)
            for m in annotations.markers if m.name.endswith("Fingertip")]
    tips = kin.bind(SurfacePoints(np.concatenate([t.faces for t in tips]), np.concatenate([t.barycentric for t in tips])))
    assert tips.n_points == 5
    for q in (traj.q, fitted):
        err = (q - clip.dof_values)[contact][:, 6:]
        rmse = np.degrees(np.sqrt(np.mean(err ** 2)))
        tip_err = [np.linalg.norm(kin.points(q[f], tips) - kin.points(clip.dof_values[f], tips), axis=1).max()
                   for f in np.nonzero(contact)[0]]
        assert rmse < 2.0, rmse
        # worst fingertip per frame: RMS over contact frames under 2 mm, median under 1 mm
        assert np.sqrt(np.mean(np.square(tip_err))) < 0.002, tip_err
        assert np.median(tip_err) < 0.001, tip_err
    assert traj.counts["passes"]["full"]["failed"] == [] and traj.curves is None


def test_scale_finger_markers_keeps_the_source_proportions_and_stretches_the_witch(setup):
    """``markers.scale_fingers``: onto the source's own rig with every target marker on its
    source point every marker stays put (with the proposed target areas, whose centroids are
    not the source points, they move under 2 mm); onto the witch each finger link keeps its direction per frame and takes the witch's rest length
    ratio, and markers off the finger chains do not move."""
    from retarget_core.rig.demo_hands import demo_hand
    from retarget_core.solve.targets import FINGER_CHAIN, scale_finger_markers

    rig, clip, annotations = setup[:3]
    import dataclasses

    markers = marker_targets(clip, rig, rig, annotations)
    on_source = dataclasses.replace(markers, target_faces=markers.source_faces,
                                    target_barycentric=markers.source_barycentric,
                                    pair_target=np.arange(len(markers.pair_target)))
    same = scale_finger_markers(on_source, rig, rig)
    np.testing.assert_allclose(same.source_positions, markers.source_positions, atol=1e-12)
    near = scale_finger_markers(markers, rig, rig)
    assert 0 < np.abs(near.source_positions - markers.source_positions).max() < 0.002

    witch = demo_hand("witch", 0.004)
    w_markers = marker_targets(clip, rig, witch, propose_annotations(rig, witch))
    scaled = scale_finger_markers(w_markers, rig, witch)
    names = np.array(w_markers.names, dtype=object)
    kin = witch.kinematics()
    t_rest = kin.points(witch.rest_pose, kin.bind(SurfacePoints(w_markers.target_faces, w_markers.target_barycentric)))

    def at(x, name):  # (T, 3) or (3,) pair-weighted centroid of a marker
        s = np.flatnonzero(names == name)
        w = w_markers.pair_weight[s] / w_markers.pair_weight[s].sum()
        return (x[..., s, :] * w[:, None]).sum(axis=-2)

    s_kin = rig.kinematics()
    s_rest = s_kin.points(rig.rest_pose, s_kin.bind(SurfacePoints(w_markers.source_faces, w_markers.source_barycentric)))
    on_chain = np.zeros(len(names), bool)
    checked = 0
    for finger in ("Thumb", "Index", "Middle", "Ring", "Pinky"):
        chain = [finger + p for p in FINGER_CHAIN if finger + p in set(names)]
        on_chain |= np.isin(names, chain[1:])
        np.testing.assert_allclose(at(scaled.source_positions, chain[0]), at(w_markers.source_positions, chain[0]))
        for a, b in zip(chain, chain[1:]):
            old = at(w_markers.source_positions, b) - at(w_markers.source_positions, a)
            new = at(scaled.source_positions, b) - at(scaled.source_positions, a)
            ratio = (np.linalg.norm(at(t_rest[w_markers.pair_target], b) - at(t_rest[w_markers.pair_target], a))
                     / np.linalg.norm(at(s_rest, b) - at(s_rest, a)))
            np.testing.assert_allclose(new, ratio * old, atol=1e-12)
            checked += 1
    assert checked >= 10
    # the witch's fingers are longer: the scaled tips move out
    assert np.mean(np.linalg.norm(scaled.source_positions - w_markers.source_positions, axis=2)[:, on_chain]) > 0.005
    np.testing.assert_array_equal(scaled.source_positions[:, ~on_chain], w_markers.source_positions[:, ~on_chain])


def test_frame_solvers_run_one_blas_thread(setup):
    """A frame worker (and the in-process solver) pins BLAS / OpenMP to one thread: with two
    workers on two cores a second BLAS thread each oversubscribes them (the bench took 80 s
    instead of 44 s)."""
    from threadpoolctl import threadpool_info, threadpool_limits

    with threadpool_limits(limits=2):
        before = [pool["num_threads"] for pool in threadpool_info()]
        build_solver_state(_problem(setup))  # what every pool worker, Dask thread and in-process run does
        after = [pool["num_threads"] for pool in threadpool_info()]
    if not before or max(before) < 2:
        pytest.skip("a single-core machine: BLAS runs one thread anyway")
    assert after == [1] * len(after)


def test_programming_errors_propagate_numerical_failures_are_reported(setup):
    """Only numerical failures make a "failed frame" (reported, the seed kept); a programming
    error inside a frame solve (a TypeError from the objective) propagates and fails the run."""
    problem = _problem(setup, lambda_p=0.0)
    rig = problem.rig
    seed = setup[1].dof_values[0]

    def raising(error):
        def value_and_grad(q, want_grad=True):
            raise error
        return value_and_grad

    common = dict(maxeval=20, xtol_rel=1e-4)
    for stage_error in (TypeError("unsupported operand type(s)"), IndexError("index 99 is out of bounds")):
        objective = method_objective(problem, "root")
        objective.set_frame(problem.frame_data(0))
        objective.value_and_grad = raising(stage_error)
        with pytest.raises(type(stage_error), match=re.escape(str(stage_error))):
            solve_frame(objective, seed, rig.lower, rig.upper, np.ones(rig.n_dofs, bool), **common)

    objective = method_objective(problem, "root")
    objective.set_frame(problem.frame_data(0))
    objective.value_and_grad = raising(RuntimeError("nlopt failure in frame"))
    sol = solve_frame(objective, seed, rig.lower, rig.upper, np.ones(rig.n_dofs, bool), **common)
    assert not sol.ok and "RuntimeError" in sol.error and "nlopt failure in frame" in sol.error
    assert np.allclose(sol.q, seed)

    # the same through the worker-side batch solve the passes use
    state = build_solver_state(problem)
    state["root"].value_and_grad = raising(RuntimeError("nlopt failure in frame"))
    (f, q, _, error), = solve_frames(state, [0], [seed], "root")
    assert f == 0 and "nlopt failure in frame" in error and np.allclose(q, np.clip(seed, rig.lower, rig.upper))
    state["root"].value_and_grad = raising(TypeError("a bug"))
    with pytest.raises(TypeError, match="a bug"):
        solve_frames(state, [0], [seed], "root")
