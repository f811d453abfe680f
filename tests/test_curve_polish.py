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
        kept, current = [], free.objective_before
        for value in free.history:  # the trials, in order: a kept step is one that scored lower
            if value < current:
                kept.append(value)
                current = value
        assert len(kept) >= 3 and not free.converged
        gains = -np.diff(np.r_[free.objective_before, kept]) / np.r_[free.objective_before, kept][:-1]
        tolerance = float(np.median(gains))
        stop = int(np.flatnonzero(gains < tolerance)[0])  # the first kept step gaining less
        _, cut = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6, tolerance=tolerance)
        assert cut.converged and cut.accepted == stop + 1
        assert cut.objective_after == kept[stop]
        _, one = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6, tolerance=1.0)
        assert one.converged and one.accepted == 1 and one.objective_after == kept[0]
        # with patience, only that many small steps in a row stop it (every step is small here)
        _, two = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6, tolerance=1.0, patience=2)
        assert two.converged and two.accepted == 2 and two.objective_after == kept[1]
        # a small step followed by a large one does not stop it: the run goes on past the first
        # small step until `patience` small ones come in a row
        stop2 = next((i for i in range(1, len(gains)) if gains[i] < tolerance and gains[i - 1] < tolerance), None)
        _, cut2 = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6, tolerance=tolerance,
                                patience=2)
        if stop2 is None:
            assert not cut2.converged and cut2.accepted == len(kept)
        else:
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
        kept, current = [], free.objective_before
        for value in free.history:
            if value < current:
                kept.append(value)
                current = value
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


def test_the_small_gain_stop_waits_until_the_curve_is_near_the_solved_frames(solved_demo):
    """With ``stall_within``, a step that closes little of the gap stops the polish only once
    the curve scores within that share above the solved frames' objective: with every step
    counted small (tolerance 1), the run is the tolerance-free one cut at its first kept step
    within that share; a share no kept step reaches runs every iteration; a huge share stops as
    without it (after the first step)."""
    problem, _, q = solved_demo
    rig = problem.rig
    curves, times = _curves(problem, q)
    with Executor(workers=1).frame_runner(problem) as runner:
        _, free = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6, solved=q)
        kept, current = [], free.objective_before
        for value in free.history:
            if value < current:
                kept.append(value)
                current = value
        reference = free.objective_solved
        ratios = np.array(kept) / reference
        assert len(kept) >= 4 and np.all(ratios > 1.0)  # every kept step is still above the frames
        within = float(0.5 * (ratios[1] + ratios[2])) - 1.0  # reached first by the third kept step
        _, cut = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6, tolerance=1.0,
                               solved=q, stall_within=within)
        assert cut.converged and cut.accepted == 3 and cut.objective_after == kept[2]
        _, runs = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6, tolerance=1.0,
                                solved=q, stall_within=0.5 * (float(ratios[-1]) - 1.0))
        assert runs.accepted == len(kept) and runs.objective_after == kept[-1]
        _, huge = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6, tolerance=1.0,
                                solved=q, stall_within=1e9)
        _, plain = polish_curves(runner, curves, times, rig.lower, rig.upper, iterations=6, tolerance=1.0, solved=q)
        assert huge.converged and huge.accepted == plain.accepted == 1 and huge.objective_after == kept[0]
