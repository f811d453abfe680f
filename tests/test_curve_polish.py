"""The polish of the delivered curves (fit/polish.py): the coefficient system against finite
differences, the banded layout against the dense one, and a polish that never scores worse,
stays within the limits and is the same for any worker count."""

import numpy as np
import pytest

from retarget_core.execute import Executor
from retarget_core.fit.polish import CoefficientLayout, basis_matrix, coefficient_system, polish_curves
from retarget_core.fit.splines import BSplineCurve, evaluate_curves, fit_trajectory


def _curves(problem, q):
    rig = problem.rig
    times = np.arange(len(q)) / 120.0
    return fit_trajectory(times, q, 6, limits=(rig.lower, rig.upper)), times


def _kept(report) -> list:
    """The summed objectives after each kept step of a polish: its trials in order, a kept step
    being one that scored lower than the last kept value."""
    kept, current = [], report.objective_before
    for value in report.history:
        if value < current:
            kept.append(value)
            current = value
    return kept


def test_basis_matrix_reproduces_the_curve():
    knots = np.r_[[0.0] * 4, 0.3, 0.5, [1.0] * 4]
    c = BSplineCurve(knots, np.array([0.2, -1.0, 0.5, 2.0, 0.1, -0.3]))
    t = np.linspace(-0.1, 1.1, 37)
    np.testing.assert_allclose(basis_matrix(c, t) @ c.coeffs, c(t), atol=1e-12)


def test_the_coefficient_system_is_the_gradient_of_the_summed_least_squares_cost(solved_demo):
    problem, _, q = solved_demo
    q = q[:12]
    curves, times = _curves(problem, q)
    lay = CoefficientLayout(curves, times)
    frames = np.arange(len(times))
    flat = np.concatenate([c.coeffs for c in curves])

    def systems_at(c):
        split = [c[lay.offsets[d]:lay.offsets[d + 1]] for d in range(len(curves))]
        poses = evaluate_curves([BSplineCurve(x.knots, s, x.degree) for x, s in zip(curves, split)], times)
        with Executor(workers=1).frame_runner(problem) as runner:
            return runner.systems(frames, poses)

    base = systems_at(flat)
    ab, g = coefficient_system(base, lay.columns, lay.lifts, lay.n, lay.band)
    # the banded J^T J equals the dense sum of A_f^T (J^T J)_f A_f
    dense = np.zeros((lay.n, lay.n))
    for (_, _, _, hf), cols, a in zip(base, lay.columns, lay.lifts):
        dense[np.ix_(cols, cols)] += a.T @ hf @ a
    for r in range(lay.band + 1):
        np.testing.assert_allclose(ab[lay.band - r, r:], np.diag(dense, r), rtol=1e-10, atol=1e-9)
    assert np.abs(np.triu(dense, lay.band + 1)).max() == 0.0
    # d(sum r^2)/dc = 2 J^T r, by central differences on a few coefficients
    rng = np.random.default_rng(3)
    for k in rng.choice(lay.n, size=5, replace=False):
        h = 1e-6
        up, down = flat.copy(), flat.copy()
        up[k] += h
        down[k] -= h
        fd = (sum(s[1] for s in systems_at(up)) - sum(s[1] for s in systems_at(down))) / (2 * h)
        assert fd == pytest.approx(2 * g[lay.position[k]], rel=1e-4, abs=1e-3), k


def test_polish_never_scores_worse_stays_in_limits_and_ignores_the_worker_count(solved_demo):
    problem, _, q = solved_demo
    rig = problem.rig
    curves, times = _curves(problem, q)
    out = {}
    for workers in (1, 2):
        with Executor(workers=workers).frame_runner(problem) as runner:
            out[workers] = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=3)
    polished, report = out[1]
    assert report.accepted >= 1 and report.objective_after < report.objective_before
    assert report.objective_after <= min(report.history)  # only steps that scored better were kept
    for c, before, lo, hi in zip(polished, curves, rig.lower, rig.upper):
        assert lo - 1e-12 <= c.coeffs.min() and c.coeffs.max() <= hi + 1e-12
        np.testing.assert_array_equal(c.knots, before.knots)  # only the coefficients move
    for a, b in zip(polished, out[2][0]):
        np.testing.assert_array_equal(a.coeffs, b.coeffs)


def test_polish_stops_at_the_first_step_that_gains_less_than_the_tolerance(solved_demo):
    """With a tolerance the polish is the tolerance-free run cut after its first kept step that
    lowered the summed objective by less than that share: same steps, same values, then a stop
    reported as converged."""
    problem, _, q = solved_demo
    rig = problem.rig
    curves, times = _curves(problem, q)
    with Executor(workers=1).frame_runner(problem) as runner:
        _, free = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6)
        kept = _kept(free)
        assert len(kept) >= 3 and not free.converged
        gains = -np.diff(np.r_[free.objective_before, kept]) / np.r_[free.objective_before, kept][:-1]
        tolerance = float(np.median(gains))
        stop = int(np.flatnonzero(gains < tolerance)[0])  # the first kept step gaining less
        _, cut = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6, tolerance=tolerance)
        assert cut.converged and cut.accepted == stop + 1
        assert cut.objective_after == kept[stop]
        _, one = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6, tolerance=1.0)
        assert one.converged and one.accepted == 1 and one.objective_after == kept[0]
        # with patience the last that many kept steps are judged together (every pair gains
        # less than the whole objective here)
        _, two = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6, tolerance=1.0, patience=2)
        assert two.converged and two.accepted == 2 and two.objective_after == kept[1]
        # a small step next to a large one does not stop it: the run goes on until two kept
        # steps together lowered the objective by less than the tolerance of its value before them
        values = np.r_[free.objective_before, kept]
        pair = (values[:-2] - values[2:]) / values[:-2]  # pair[i]: kept steps i and i + 1 together
        tolerance2 = float(np.median(pair))
        stop2 = int(np.flatnonzero(pair < tolerance2)[0]) + 1  # the later step of the first such pair
        _, cut2 = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6, tolerance=tolerance2,
                                patience=2)
        assert cut2.converged and cut2.accepted == stop2 + 1 and cut2.objective_after == kept[stop2]


def test_polish_towards_the_solved_frames_stops_when_it_is_as_good_or_gains_little_of_the_gap(solved_demo):
    """Given the solved frames, the polish works towards their summed objective: a curve that
    already scores no worse takes no step; otherwise the tolerance-free run is cut after the
    first kept step that reached the solved frames' objective or closed less than the
    tolerance of the remaining gap to it."""
    problem, _, q = solved_demo
    rig = problem.rig
    curves, times = _curves(problem, q)
    with Executor(workers=1).frame_runner(problem) as runner:
        fitted = evaluate_curves(curves, times)
        _, none = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6, solved=fitted)
        assert none.converged and none.accepted == 0 and none.iterations == 0
        assert none.objective_solved == pytest.approx(none.objective_before, rel=1e-12)

        _, free = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6)
        _, ref = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=0, solved=q)
        reference = ref.objective_solved
        assert np.isfinite(reference) and reference < free.objective_before  # the fit scores worse
        kept = _kept(free)
        assert len(kept) >= 3
        before = np.r_[free.objective_before, kept][:-1]
        gains = (before - np.array(kept)) / np.maximum(before - reference, 1e-300)
        # a tolerance that cuts the run in its middle (the median of the steps' gap shares)
        tolerance = float(np.median(gains))
        reached = np.array(kept) <= reference
        stops = np.flatnonzero((gains < tolerance) | reached)
        stop = int(stops[0])
        _, cut = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6,
                               tolerance=tolerance, solved=q)
        assert cut.converged and cut.accepted == stop + 1
        assert cut.objective_after == kept[stop]
        assert cut.objective_solved == reference


def test_the_polish_is_done_within_a_share_of_the_solved_frames_objective(solved_demo):
    """With ``within``, the polish stops at its first kept step that scores within that share
    above the solved frames' objective (the tolerance-free run cut there); a share no step
    reaches runs every iteration; a share the fitted curve already meets takes no step."""
    problem, _, q = solved_demo
    rig = problem.rig
    curves, times = _curves(problem, q)
    with Executor(workers=1).frame_runner(problem) as runner:
        _, free = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6, solved=q)
        kept = _kept(free)
        reference = free.objective_solved
        ratios = np.array(kept) / reference
        assert len(kept) >= 4 and np.all(ratios > 1.0)  # every kept step is still above the frames
        within = float(0.5 * (ratios[1] + ratios[2])) - 1.0  # reached first by the third kept step
        _, cut = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6, solved=q, within=within)
        assert cut.converged and cut.accepted == 3 and cut.objective_after == kept[2]
        _, runs = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6, solved=q,
                                within=0.5 * (float(ratios[-1]) - 1.0))
        assert runs.accepted == len(kept) and runs.objective_after == kept[-1]
        _, done = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6, solved=q,
                                within=free.objective_before / reference)
        assert done.converged and done.accepted == 0 and done.objective_after == free.objective_before


def test_a_window_of_kept_steps_is_judged_on_the_gap_it_closed_together(solved_demo):
    """With the solved frames and ``patience`` W, the polish is the tolerance-free run cut at
    its first kept step k (k >= W) whose last W steps together closed less than ``tolerance`` of
    the gap to the solved frames' objective left before them; so a run of small steps followed
    by a large one is not cut where step by step it would be."""
    problem, _, q = solved_demo
    rig = problem.rig
    curves, times = _curves(problem, q)
    with Executor(workers=1).frame_runner(problem) as runner:
        _, free = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6, solved=q)
        kept = _kept(free)
        reference = free.objective_solved
        values = np.r_[free.objective_before, kept]
        assert len(kept) >= 4 and values[-1] > reference
        for window in (1, 3):
            closed = (values[:-window] - values[window:]) / (values[:-window] - reference)
            tolerance = float(np.median(closed))
            stop = int(np.flatnonzero(closed < tolerance)[0]) + window - 1  # index into kept
            _, cut = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6, solved=q,
                                   tolerance=tolerance, patience=window)
            assert cut.converged and cut.accepted == stop + 1 and cut.objective_after == kept[stop], window
        # a window longer than the run never judges: every step is kept
        _, long = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6, solved=q,
                                tolerance=1.0, patience=len(kept) + 1)
        assert long.accepted == len(kept) and not long.converged
