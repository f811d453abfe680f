"""Polish of the delivered curves: the spline coefficients themselves optimised on the same
per-frame objective the frames were solved on, at the frame times.

The least-squares fit of the solved frames cuts across a pose the solve changed quickly (a
contact onset, a branch the coherence pass could not join), so the delivered curve can score
far worse than the frames it was fitted to. Here q_f = B_f c (each DOF's B-spline basis at
frame f times its coefficients) and bounded Levenberg-Marquardt steps on the coefficients
solve the summed Gauss-Newton systems of the frames' least-squares terms (each frame's J^T J
and J^T r from the workers, carried to the coefficients through the basis; every frame
touches only degree + 1 coefficients per DOF; the table's hinge enters the systems too, as
square-root residuals, since nothing settles it after the polish). A step is kept only when
the summed *full* objective at the frames goes down, so the polish never makes the delivered
curve score worse; it works towards the solved frames' summed objective and stops once the
curve scores about as well, or its last few kept steps together closed little of the gap left
(progress comes in bursts: small steps while the damping settles, then large ones).
Coefficients stay within the
DOF limits (a B-spline lies in the convex hull of its coefficients, so the curve does too)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.linalg import solveh_banded

from .splines import BSplineCurve, coupled_curves, evaluate_curves


#: The damping at which a polish iteration gives up: a step damped by mu is about 1 / (1 + mu)
#: of the Gauss-Newton step, so beyond this it could gain only a small part of the tolerance.
#: Up to 1e8 (before stop 41), on Shadow's mug_drink window an iteration whose every step
#: scored worse scored every frame about 19 times more (polish 1.79 -> 1.11 s, same curve);
#: 15 grid cells gave the same figures to the last digit with either bound.
MAX_DAMPING = 1e3


@dataclass
class PolishReport:
    """Iterations taken, steps kept, the summed full objective at the frames before and after."""

    iterations: int = 0
    accepted: int = 0
    converged: bool = False  # stopped before the cap: as good as the solved frames, or a step gained too little
    objective_before: float = float("nan")
    objective_after: float = float("nan")
    #: the summed objective of the solved frames themselves (what the curve is polished towards)
    objective_solved: float = float("nan")
    seconds: float = 0.0
    history: list = field(default_factory=list)

    def to_dict(self) -> dict:
        # no seconds here: this goes in result.json's counts, which any executor gives alike
        # (the time is in its timings, "curve polish")
        return {"iterations": self.iterations, "accepted": self.accepted, "converged": self.converged,
                "objective_before": self.objective_before, "objective_after": self.objective_after,
                "objective_solved": self.objective_solved}


def basis_matrix(curve: BSplineCurve, times: np.ndarray) -> np.ndarray:
    """(T, n) the value of each of ``curve``'s basis functions at ``times`` (held outside)."""
    n = len(curve.coeffs)
    return np.stack([BSplineCurve(curve.knots, np.eye(n)[k], curve.degree, curve.extrapolation)(times)
                     for k in range(n)], axis=1)


class CoefficientLayout:
    """How the curves' coefficients enter the frames. ``bases`` [(T, n_d)] per DOF; the
    coefficients flat DOF after DOF (``offsets``, n in all) and, for the solve, interleaved
    (coefficient k of every DOF, then k + 1: ``order[p]`` is the flat index at position p,
    ``position`` its inverse), where each frame touches a window of degree + 1 per DOF, so
    the summed system is banded (``band``); per frame, ``columns`` (the positions it touches,
    ascending) and ``lifts`` A_f (D, len(columns)) with q_f = A_f c[columns]."""

    def __init__(self, curves: list[BSplineCurve], times: np.ndarray):
        self.bases = [basis_matrix(c, times) for c in curves]
        d_count = len(self.bases)
        self.offsets = np.concatenate([[0], np.cumsum([b.shape[1] for b in self.bases])])
        self.n = int(self.offsets[-1])
        keys = np.concatenate([np.arange(b.shape[1]) * d_count + d for d, b in enumerate(self.bases)])
        self.order = np.argsort(keys, kind="stable")
        self.position = np.empty(self.n, dtype=np.int64)
        self.position[self.order] = np.arange(self.n)
        self.columns, self.lifts = [], []
        for f in range(len(times)):
            touched = [np.nonzero(b[f])[0] for b in self.bases]
            cols = self.position[np.concatenate([t + self.offsets[d] for d, t in enumerate(touched)])]
            a = np.zeros((d_count, sum(len(t) for t in touched)))
            at = 0
            for d, t in enumerate(touched):
                a[d, at:at + len(t)] = self.bases[d][f, t]
                at += len(t)
            ascending = np.argsort(cols)  # so a frame's upper half of the band is its block's
            self.columns.append(cols[ascending])
            self.lifts.append(a[:, ascending])
        self.band = int(max(c.max() - c.min() for c in self.columns))


def polish_curves(runner, curves: list[BSplineCurve], times: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                  *, iterations: int = 4, tolerance: float = 0.0, patience: int = 1, coupling=None,
                  solved: np.ndarray | None = None, within: float = 0.0) -> tuple[list[BSplineCurve], PolishReport]:
    """``curves`` (one per DOF) with coefficients polished on the frames' objective at
    ``times`` (T,) (see the module docstring); ``runner`` a FrameRunner of the run's problem.
    ``lower``, ``upper`` (D,) the DOF limits. ``solved`` (T, D): the solved frames the curves
    were fitted to; their summed objective is what the polish works towards. At most
    ``iterations`` steps; it stops earlier once the curve scores within ``within`` (a share,
    0: at or below) of the solved frames' objective, or when its last ``patience`` kept steps
    together closed less than ``tolerance`` of the gap to that objective left before them
    (without ``solved``: lowered the objective by less than ``tolerance`` of its value then;
    0: every iteration runs while steps are kept). ``coupling``: the rig's
    :class:`~retarget_core.rig.coupling.DofCoupling`, kept exactly: the frames' systems are
    carried to the free DOFs and each follower's curve is its leader's, mapped
    (:func:`~retarget_core.fit.splines.coupled_curves`)."""
    t0 = time.perf_counter()
    report = PolishReport()
    times = np.asarray(times, dtype=np.float64)
    frames = np.arange(len(times))
    couple = coupling is not None and not coupling.empty
    if couple:
        lower, upper = coupling.bounds(lower, upper)
        curves = coupled_curves(curves, coupling)
        lift = coupling.lift()
    lay = CoefficientLayout(curves, times)
    offsets, order, n, band = lay.offsets, lay.order, lay.n, lay.band
    columns, lifts = lay.columns, lay.lifts
    coeffs = np.concatenate([c.coeffs for c in curves])

    def coupled(c):
        # the followers' coefficients from their leaders' (the step leaves them where they were)
        if not couple:
            return c
        return np.concatenate([k.coeffs for k in coupled_curves(_with(curves, c, offsets), coupling)])

    def frame_systems(c):
        systems = runner.systems(frames, poses(c))
        if not couple:
            return systems
        return [(f, cost, lift.T @ g, lift.T @ h @ lift) for f, cost, g, h in systems]
    lo = np.concatenate([np.full(b.shape[1], lower[d]) for d, b in enumerate(lay.bases)])
    hi = np.concatenate([np.full(b.shape[1], upper[d]) for d, b in enumerate(lay.bases)])

    def poses(c):
        return evaluate_curves(_with(curves, c, offsets), times)

    def total(c):
        return float(sum(v for _, v in runner.values(frames, poses(c))))

    mu = 1e-3
    systems = frame_systems(coeffs)
    current = total(coeffs)
    report.objective_before = current
    kept = [current]  # the summed objective before the polish, then after each kept step
    reference = 0.0
    if solved is not None:
        reference = float(sum(v for _, v in runner.values(frames, np.asarray(solved, dtype=np.float64))))
        report.objective_solved = reference
    for it in range(max(0, int(iterations))):
        if solved is not None and current <= (1.0 + max(0.0, within)) * reference:
            report.converged = True  # (about) as good as the frames it was fitted to
            break
        runner.executor.report("curve polish", it, int(iterations))
        report.iterations += 1
        ab, g = coefficient_system(systems, columns, lifts, n, band)
        x = coeffs[order]
        lo_p, hi_p = lo[order], hi[order]
        # within a hair of a bound counts as on it: run-to-run noise of 1e-12 must not decide
        # which coefficients the step may move (the fit leaves coefficients exactly on bounds)
        hair = 1e-9 * np.maximum(1.0, hi_p - lo_p)
        held = ((x <= lo_p + hair) & (g > 0)) | ((x >= hi_p - hair) & (g < 0))
        diag = ab[band].copy()
        improved = False
        while mu < MAX_DAMPING:
            system = ab.copy()
            system[band] = diag + mu * (diag + 1e-9 * max(1.0, float(diag.max(initial=0.0))))
            rhs = -g.copy()
            # a coefficient at a bound pushed outward is held: its row and column leave the system
            if held.any():
                for k in np.nonzero(held)[0]:
                    for r in range(1, band + 1):
                        if k + r < n:
                            system[band - r, k + r] = 0.0
                        if k - r >= 0:
                            system[band - r, k] = 0.0
                    system[band, k] = 1.0
                    rhs[k] = 0.0
            try:
                step = solveh_banded(system, rhs)
            except (np.linalg.LinAlgError, ValueError):
                break
            trial_p = np.clip(x + step, lo_p, hi_p)
            trial = np.empty(n)
            trial[order] = trial_p
            trial = coupled(trial)
            value = total(trial)
            report.history.append(value)
            if np.isfinite(value) and value < current:
                coeffs, current, improved = trial, value, True
                mu = max(mu / 3.0, 1e-9)
                report.accepted += 1
                break
            mu *= 4.0
        if not improved:
            break
        kept.append(current)
        window = max(1, int(patience))
        if tolerance > 0 and len(kept) > window:
            # the share of what was left to gain before the window that it closed: towards the
            # solved frames' objective when known (a relative gain of the whole objective stalls
            # early where most of it is what no pose removes, e.g. markers a hand of other
            # proportions cannot meet)
            start = kept[-1 - window]
            gap = start - reference
            if gap <= 0 or start - current < tolerance * gap:
                report.converged = True
                break
        systems = frame_systems(coeffs)
    runner.executor.report("curve polish", int(iterations), int(iterations))
    report.objective_after = current
    report.seconds = time.perf_counter() - t0
    return _with(curves, coeffs, offsets), report


def coefficient_system(systems, columns, lifts, n: int, band: int):
    """The frames' Gauss-Newton systems carried to the coefficients: J^T J in upper banded
    storage (band + 1, n) (``ab[band + i - j, j] = H[i, j]``, what ``solveh_banded`` reads) and
    J^T r (n,), with q_f = A_f c over the coefficients ``columns[f]`` (ascending; ``lifts[f]``
    is A_f); ``systems``: the workers' (frame, sum r^2, J^T r, J^T J) per frame."""
    flat = np.zeros((band + 1) * n)  # ab row-major: entry (band + i - j, j) at (band + i - j) n + j
    g = np.zeros(n)
    upper = {}  # the upper triangle's (row, column) indices of a k x k block, per k
    for (_, _, gf, hf), cols, a in zip(systems, columns, lifts):
        g[cols] += gf @ a
        block = a.T @ (hf @ a)
        k = len(cols)
        if k not in upper:
            upper[k] = np.triu_indices(k)
        iu, ju = upper[k]
        # ascending columns: the block's upper triangle is the band's; within one frame no
        # (row, column) repeats, so a plain indexed add is exact
        flat[(band + cols[iu] - cols[ju]) * n + cols[ju]] += block[iu, ju]
    return flat.reshape(band + 1, n), g


def _with(curves, coeffs, offsets):
    return [replace(c, coeffs=np.array(coeffs[offsets[d]:offsets[d + 1]])) for d, c in enumerate(curves)]
