"""One frame's bounded IK with nlopt's MMA (Method of Moving Asymptotes)."""

from __future__ import annotations

from dataclasses import dataclass

import nlopt
import numpy as np

from ..rig.coupling import DofCoupling
from .objective import FrameObjective

ROOT_TRANSLATION_WINDOW = 0.05  # metres around the seed
ROOT_ROTATION_WINDOW = 0.6  # radians around the seed
#: Gauss-Newton steps on the whole hand-object term after a warm start (see :func:`warm_start`).
WHOLE_OBJECT_ITERATIONS = 5
#: A warm start that leaves the hand this deep in the object (m) is tried again with the term
#: keeping out what was out (:func:`warm_start`).
RETRY_DEPTH = 0.001

#: What a frame solve may fail with numerically: nlopt's generic failure (RuntimeError) and
#: forced stop, floating-point and linear-algebra errors. Only these make a "failed frame";
#: any other exception is a programming error and propagates.
NUMERICAL_FAILURES = (RuntimeError, nlopt.ForcedStop, FloatingPointError, np.linalg.LinAlgError)

SUCCESS_CODES = (nlopt.SUCCESS, nlopt.STOPVAL_REACHED, nlopt.FTOL_REACHED, nlopt.XTOL_REACHED,
                 nlopt.MAXEVAL_REACHED, nlopt.MAXTIME_REACHED)


@dataclass
class FrameSolution:
    """q (D,), objective value, evaluations used, nlopt's result code (or -1000 when the solve
    raised), and the error message when it failed."""

    q: np.ndarray
    value: float
    evaluations: int
    code: int
    error: str = ""

    @property
    def ok(self) -> bool:
        return not self.error and np.all(np.isfinite(self.q))


def solve_frame(objective: FrameObjective, seed: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                active: np.ndarray, *, maxeval: int, xtol_rel: float, ftol_rel: float = 0.0,
                gradient: str = "analytic", fd_step: float = 1e-3, kinds=None, root_mask=None,
                algorithm: str = "LD_MMA", warm_start_iterations: int = 0,
                coupling: DofCoupling | None = None) -> FrameSolution:
    """Minimise the objective over the ``active`` DOFs (bool (D,)) within [lower, upper], from
    ``seed`` (D,), optionally after a warm start of up to ``warm_start_iterations`` bounded
    Gauss-Newton steps (:func:`warm_start`).
    ``coupling``: the rig's DOF couplings, kept exactly (the
    solver moves the free DOFs; followers are computed from their leaders). ``gradient =
    "forward"`` replaces the analytic gradient by forward differences (one extra evaluation
    per active DOF) — only to measure the speed-up."""
    coupling = coupling if coupling is not None else DofCoupling.identity(len(lower))
    lower, upper = coupling.bounds(lower, upper)
    active = np.asarray(active, dtype=bool) & coupling.free
    base = coupling.apply(np.clip(np.asarray(seed, dtype=np.float64), lower, upper))
    if not np.all(np.isfinite(base)):
        return FrameSolution(base, np.nan, 0, -1000, "the seed is not finite (NaN in an earlier pass's result?)")
    objective.set_seed(base)
    if warm_start_iterations > 0:
        base = warm_start(objective, base, lower, upper, active, warm_start_iterations, coupling)
    n = int(active.sum())
    best = {"value": np.inf, "q": base.copy()}
    start_evals = objective.evaluations

    def full(x):
        q = base.copy()
        q[active] = x
        return coupling.apply(q)

    def fun(x, grad):
        q = full(x)
        if grad.size:
            if gradient == "forward":
                value, _ = objective.value_and_grad(q, want_grad=False)
                g = np.empty(n)
                hi = upper[active]
                for k in range(n):
                    xx = np.array(x, dtype=np.float64)
                    step = fd_step if xx[k] + fd_step <= hi[k] else -fd_step
                    xx[k] += step
                    g[k] = (objective.value_and_grad(full(xx), want_grad=False)[0] - value) / step
                grad[:] = g
            else:
                value, g = objective.value_and_grad(q)
                grad[:] = coupling.pull_gradient(g)[active]
        else:
            value, _ = objective.value_and_grad(q, want_grad=False)
        if value < best["value"]:
            best["value"], best["q"] = value, q
        return float(value)

    # MMA sizes its first moves from the bounds; the root's are metres and full turns wide, so
    # confine the root to a neighbourhood of the seed (the root pass tracks it frame to frame)
    # and give every DOF a sensible first step.
    lo, hi = lower.copy(), upper.copy()
    translate = np.array([k == "translate" for k in kinds]) if kinds is not None else np.zeros(len(lower), bool)
    root = np.asarray(root_mask, bool) if root_mask is not None else np.zeros(len(lower), bool)
    lo = np.where(root & translate, np.maximum(lo, base - ROOT_TRANSLATION_WINDOW), lo)
    hi = np.where(root & translate, np.minimum(hi, base + ROOT_TRANSLATION_WINDOW), hi)
    lo = np.where(root & ~translate, np.maximum(lo, base - ROOT_ROTATION_WINDOW), lo)
    hi = np.where(root & ~translate, np.minimum(hi, base + ROOT_ROTATION_WINDOW), hi)
    opt = nlopt.opt(getattr(nlopt, algorithm), n)
    opt.set_lower_bounds(lo[active])
    opt.set_upper_bounds(hi[active])
    opt.set_initial_step(np.where(translate, 0.005, 0.05)[active])
    opt.set_min_objective(fun)
    opt.set_maxeval(int(maxeval))
    opt.set_xtol_rel(float(xtol_rel))
    if ftol_rel > 0:
        opt.set_ftol_rel(float(ftol_rel))
    try:
        x = opt.optimize(base[active])
        code = opt.last_optimize_result()
        q = full(x)
        value = float(opt.last_optimum_value())
        if best["value"] < value:  # MMA reports its last iterate; keep the best one seen
            q, value = best["q"], best["value"]
        if not (np.isfinite(value) and np.all(np.isfinite(q))):
            return FrameSolution(base, np.nan, objective.evaluations - start_evals, code,
                                 "the objective is not finite (NaN in the frame's markers or contacts?)")
        return FrameSolution(q, value, objective.evaluations - start_evals, code)
    except nlopt.RoundoffLimited:  # not a RuntimeError: the best point so far is still good
        return FrameSolution(best["q"], best["value"], objective.evaluations - start_evals, nlopt.ROUNDOFF_LIMITED)
    except NUMERICAL_FAILURES as err:  # a numerically failed frame is reported and skipped, never silently zero
        if isinstance(err, (RecursionError, NotImplementedError)):  # RuntimeErrors that are bugs
            raise
        return FrameSolution(base, np.nan, objective.evaluations - start_evals, -1000, f"{type(err).__name__}: {err}")
    # anything else (TypeError, IndexError, ...) is a programming error: it fails the run


def warm_start(objective: FrameObjective, seed: np.ndarray, lower: np.ndarray, upper: np.ndarray,
               active: np.ndarray, iterations: int, coupling: DofCoupling) -> np.ndarray:
    """Close the hand from ``seed`` (D,) (the root pass's pose, fingers at rest) onto the
    contacts and markers: :func:`gauss_newton_warm_start` without the hand-object term, then,
    where the hand and the object overlap, :data:`WHOLE_OBJECT_ITERATIONS` steps with it. When
    that leaves a point more than :data:`RETRY_DEPTH` in, a second warm start from the seed
    where only what was outside the object at the seed costs (:meth:`FrameObjective.keep_object_out`),
    the same steps after; the pose with the lower objective is kept (q (D,)). The objective is
    left focused at the returned pose.

    Why both (measured with lambda_p = 10; "jumps": :func:`~retarget_core.refine.branches.branch_jumps`
    of the full pass, 300 frames of the bench clip onto human_alt, 120 of hammer_power onto robot4):
    - the whole term from the start (stops 34-35): the rows of whatever sat inside at the
      open-handed seed fought the contacts, and the fingers jittered from frame to frame;
    - each point held at its depth at the seed (stops 36-38): the closing fingers were held in
      the object, 26 jumps on the bench clip (the coherence pass then traced 1137 frames, 43 s
      of an 83 s run);
    - without the term alone: none there, where the open fingers lie through the object at the
      seed, but on the hammer the fingers close through its thin handle (15 jumps, delivered
      p95 penetration 15.1 mm);
    - keeping out what was out alone: the hammer meets every goal (p95 1.06 mm, contact
      3.70 mm), the bench clip has 18 jumps;
    - both, the lower kept: no jumps on the bench clip, the hammer meets every goal (p95
      1.36 mm, contact 3.71 mm).
    Self collision stays in whole (at the seed the fingers are at rest): without it, contacts
    that pull two fingers together closed them through each other (robot4 on apple_rotate:
    self intersection median 6.4 % of the hand's volume, 0.11 % with it). Its rows follow the
    trial steps (:func:`gauss_newton_warm_start`'s ``refocus``)."""

    def then_whole(q):
        # the points near the table, the object or another part, picked again where the warm
        # start ended (it moves the fingers the most); a few steps push out what is in
        objective.focus_samples(q)
        if objective.object_penetration(q) > 0:
            q = gauss_newton_warm_start(objective, q, lower, upper, active, WHOLE_OBJECT_ITERATIONS, coupling)
        return q

    with objective.hand_object_off():
        through = gauss_newton_warm_start(objective, seed, lower, upper, active, iterations, coupling)
    through = then_whole(through)
    if objective.object_depth(through) <= RETRY_DEPTH:
        return through
    objective.focus_samples(seed)
    objective.keep_object_out(seed)
    around = then_whole(gauss_newton_warm_start(objective, seed, lower, upper, active, iterations, coupling))
    if objective.whole_value(around) < objective.whole_value(through):
        return around  # focused there by then_whole
    objective.focus_samples(through)
    return through


def gauss_newton_warm_start(objective: FrameObjective, seed: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                            active: np.ndarray, iterations: int, coupling: DofCoupling | None = None,
                            refocus: bool = True) -> np.ndarray:
    """Bounded Levenberg-Marquardt steps on the least-squares form of the objective
    (:meth:`FrameObjective.residuals`, through its normal equations), from ``seed`` (D,); at
    most ``iterations`` trial steps. MMA alone needs hundreds of evaluations to close a
    hand from rest onto a few hundred contacts; this reaches the basin in about ten, then MMA
    polishes the whole objective. DOFs at a bound whose step points outward are held for that
    step (projected LM); the system is (A, A) with A the active DOF count, so no large
    factorisation is ever formed. With a ``coupling`` the system is carried to the free DOFs
    (P^T g, P^T H P with P = :meth:`DofCoupling.lift`) and ``active`` must leave the followers out.
    ``refocus``: each trial adds to the self-collision rows the parts' points near another part
    at the trial pose, so a step that closes two parts into each other is judged with them
    (False: the rows of the focus the objective came with)."""
    active_idx = np.nonzero(active)[0]
    couple = coupling is not None and not coupling.empty
    lift = coupling.lift() if couple else None

    def system(at):
        _, g, h = objective.normal_equations(at)
        return (lift.T @ g, lift.T @ h @ lift) if couple else (g, h)

    q = np.clip(seed, lower, upper).copy()
    cost = objective.residual_cost(q)  # every cost compared below comes from residual_cost
    g_all, h_all = system(q)
    mu = 1e-3
    for _ in range(max(0, int(iterations) - 1)):
        g = g_all[active_idx]
        h = h_all[np.ix_(active_idx, active_idx)]
        x = q[active_idx]
        lo, hi = lower[active_idx], upper[active_idx]
        free = ~(((x <= lo) & (g > 0)) | ((x >= hi) & (g < 0)))
        if not free.any():
            break
        hf = h[np.ix_(free, free)]
        damp = mu * (np.diag(hf) + 1e-9 * max(1.0, float(np.diag(hf).max())))
        try:
            step = -np.linalg.solve(hf + np.diag(damp), g[free])
        except np.linalg.LinAlgError:
            break
        trial = q.copy()
        trial[active_idx[free]] = np.clip(x[free] + step, lo[free], hi[free])
        if couple:
            trial = coupling.apply(trial)
        if refocus and objective.widen_self_focus(trial):
            # parts the trial brings near each other join the self-collision rows before the
            # trial is judged: focused only at the open-handed seed, contacts that pull two
            # fingertips together closed them through each other in one step, unseen. Outside
            # at q their rows are zero, so q's cost and system change only where one was inside
            # at q already.
            seen = objective.residual_cost(q)
            if seen != cost:
                cost = seen
                g_all, h_all = system(q)
        # a trial is judged by its cost alone; the Jacobian is formed only for a step taken
        # (rejected trials, often half of them, cost a fraction of an iteration)
        cost_new = objective.residual_cost(trial)
        if np.isfinite(cost_new) and cost_new < cost:
            converged = cost - cost_new < 1e-6 * cost
            q, cost = trial, cost_new
            mu = max(mu / 3.0, 1e-9)
            if converged:
                break
            g_all, h_all = system(q)
        else:
            mu *= 4.0
            if mu > 1e8:
                break
    return q
