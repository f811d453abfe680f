"""Trajectory refinement (paper appendix "Trajectory Refinement"), pure numpy / scipy.

A trajectory is an ``(F, D)`` array ``q`` of per-frame solutions (SI: radians for rotational
DOFs, metres for translational ones) sampled at ``fps``. This module never sees the
objective: re-solving is delegated to a callback ``resolve(frames, seeds) -> solutions`` that
solves each requested frame independently from the given seed row.

- :func:`acceleration_violations` flags (frame, DOF) entries whose finite acceleration exceeds
  E_acc;
- :func:`interpolate_violations` replaces flagged entries by linear interpolation between the
  nearest valid neighbours of the same DOF;
- :func:`refine_trajectory` iterates flag -> interpolate -> re-solve until no violation is left
  or the iteration cap is hit, and reports what remains (to be left out of the spline fit);
- :func:`lowpass_and_remove_peaks` is the filtering pass run before refinement (the caller
  re-solves the frames it changed).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy import ndimage

from retarget_core.errors import InputError

__all__ = [
    "RefinementReport",
    "ResolveFn",
    "acceleration_violations",
    "interpolate_violations",
    "lowpass_and_remove_peaks",
    "refine_trajectory",
]

#: ``resolve(frames (n,) int, seeds (n, D)) -> (n, D)``: re-solve each frame independently,
#: starting from its seed row.
ResolveFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


def _as_trajectory(q, name: str = "q") -> np.ndarray:
    q = np.asarray(q, dtype=float)
    if q.ndim != 2:
        raise InputError(f"expected an (F, D) array, got shape {q.shape}", element=name)
    bad = ~np.isfinite(q)
    if bad.any():
        f, d = np.argwhere(bad)[0]
        raise InputError(f"non-finite value at frame {f}, DOF {d}", element=name)
    return q


def _check_fps(fps) -> float:
    fps = float(fps)
    if not np.isfinite(fps) or fps <= 0:
        raise InputError(f"fps must be positive, got {fps!r}", element="fps")
    return fps


def _per_dof(value, n_dofs: int, name: str) -> np.ndarray:
    arr = np.broadcast_to(np.asarray(value, dtype=float), (n_dofs,)) if np.ndim(value) == 0 \
        else np.asarray(value, dtype=float)
    if arr.shape != (n_dofs,):
        raise InputError(f"expected a scalar or shape ({n_dofs},), got {arr.shape}", element=name)
    if np.any(~np.isfinite(arr)) or np.any(arr < 0):
        raise InputError("must be finite and non-negative", element=name)
    return arr


def _thresholds(is_rotation, n_dofs: int, e_acc_angular: float, e_acc_linear: float):
    rot = np.asarray(is_rotation, dtype=bool)
    if rot.shape != (n_dofs,):
        raise InputError(f"expected shape ({n_dofs},), got {rot.shape}", element="is_rotation")
    for name, v in (("e_acc_angular", e_acc_angular), ("e_acc_linear", e_acc_linear)):
        if not np.isfinite(v) or v <= 0:
            raise InputError(f"must be positive, got {v!r}", element=name)
    return np.where(rot, float(e_acc_angular), float(e_acc_linear))


def acceleration_violations(q, fps: float, is_rotation, e_acc_angular: float,
                            e_acc_linear: float) -> np.ndarray:
    """``(F, D)`` bool mask of entries whose finite acceleration exceeds E_acc.

    The measure is ``|(q[f+1] - q[f]) - (q[f] - q[f-1])| / dt`` with ``dt = 1 / fps``:
    the second difference divided by ``dt`` **once**, exactly as in the paper's code (a true
    acceleration would divide by ``dt**2``; with E_acc = 500 deg/s^2 at 120 fps the check
    allows ~4.2 degrees of second difference). ``e_acc_angular`` (rad/s^2) applies to DOFs with
    ``is_rotation`` true, ``e_acc_linear`` (m/s^2) to the others. The first and last frames
    never violate (no centred difference there)."""
    q = _as_trajectory(q)
    fps = _check_fps(fps)
    F, D = q.shape
    thr = _thresholds(is_rotation, D, e_acc_angular, e_acc_linear)
    out = np.zeros((F, D), dtype=bool)
    if F < 3:
        return out
    acc = np.abs(q[2:] - 2.0 * q[1:-1] + q[:-2]) * fps
    out[1:-1] = acc > thr
    return out


def interpolate_violations(q, violations) -> np.ndarray:
    """Copy of ``q`` with every flagged entry replaced, per DOF, by the linear interpolation
    (in frame index) between the nearest unflagged frames left and right of it; before the
    first / after the last unflagged frame the nearest unflagged value is held. A DOF with no
    unflagged frame is left unchanged."""
    q = _as_trajectory(q)
    viol = np.asarray(violations, dtype=bool)
    if viol.shape != q.shape:
        raise InputError(f"expected shape {q.shape}, got {viol.shape}", element="violations")
    out = q.copy()
    frames = np.arange(q.shape[0])
    for d in np.flatnonzero(viol.any(axis=0)):
        bad = viol[:, d]
        good = ~bad
        if not good.any():
            continue
        out[bad, d] = np.interp(frames[bad], frames[good], q[good, d])
    return out


@dataclass
class RefinementReport:
    """Outcome of :func:`refine_trajectory`.

    ``violations_per_iteration[i]`` is the number of violating (frame, DOF) entries found by
    the i-th check (one more check than ``iterations`` unless the loop converged on its last
    allowed round); ``frames_resolved_per_iteration[i]`` the number of frames re-solved in
    round i. ``unresolved`` is the ``(F, D)`` mask of entries still violating at the end — leave
    them out of the spline fit. ``held``: frames given their solution from before the
    refinement back because its re-solve left the branch (``pipeline.hold_branches``)."""

    iterations: int
    converged: bool
    violations_per_iteration: list[int] = field(default_factory=list)
    frames_resolved_per_iteration: list[int] = field(default_factory=list)
    unresolved: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), dtype=bool))
    held: list = field(default_factory=list)

    @property
    def n_unresolved(self) -> int:
        """Violating (frame, DOF) entries left."""
        return int(self.unresolved.sum())

    @property
    def unresolved_frames(self) -> np.ndarray:
        """Indices of frames with at least one unresolved DOF."""
        return np.flatnonzero(self.unresolved.any(axis=1))

    def to_dict(self) -> dict:
        return {
            "iterations": self.iterations,
            "converged": self.converged,
            "violations_per_iteration": list(self.violations_per_iteration),
            "frames_resolved_per_iteration": list(self.frames_resolved_per_iteration),
            "n_unresolved": self.n_unresolved,
            "n_unresolved_frames": int(self.unresolved_frames.size),
            "held": [int(f) for f in self.held],
        }


def refine_trajectory(q, fps: float, is_rotation, resolve: ResolveFn, *, e_acc_angular: float,
                      e_acc_linear: float, max_iterations: int = 20, patience: int = 0
                      ) -> tuple[np.ndarray, RefinementReport]:
    """Iterative acceleration refinement.

    Each round: flag violations (:func:`acceleration_violations`); stop if there are none;
    replace the flagged entries by interpolation (per DOF, in a single pass over the current
    trajectory, so re-solved frames are independent of each other); re-solve every frame with
    at least one flagged DOF via ``resolve(frames, seeds)`` with the interpolated row as seed;
    write the solutions back. At most ``max_iterations`` rounds; the entries still violating
    after the last round are returned in ``report.unresolved``. ``patience`` > 0 also stops
    once that many rounds in a row failed to lower the violation count below its best, and
    returns the best trajectory seen (re-solves that keep landing on the same poses are not
    worth 20 rounds).

    ``e_acc_angular`` is in rad/s^2, ``e_acc_linear`` in m/s^2 (see
    :class:`retarget_core.solve.config.Refinement` for the paper's values in deg / cm)."""
    q = _as_trajectory(q).copy()
    fps = _check_fps(fps)
    F, D = q.shape
    _thresholds(is_rotation, D, e_acc_angular, e_acc_linear)
    if int(max_iterations) != max_iterations or max_iterations < 0:
        raise InputError(f"must be a non-negative integer, got {max_iterations!r}",
                         element="max_iterations")

    report = RefinementReport(iterations=0, converged=False)
    viol = acceleration_violations(q, fps, is_rotation, e_acc_angular, e_acc_linear)
    report.violations_per_iteration.append(int(viol.sum()))
    best = (int(viol.sum()), q.copy(), viol)
    stale = 0
    while viol.any() and report.iterations < max_iterations and not (patience > 0 and stale >= patience):
        seeds = interpolate_violations(q, viol)
        frames = np.flatnonzero(viol.any(axis=1))
        solved = np.asarray(resolve(frames.copy(), seeds[frames].copy()), dtype=float)
        if solved.shape != (frames.size, D):
            raise InputError(f"resolve returned shape {solved.shape}, expected "
                             f"{(frames.size, D)}", element="resolve")
        if not np.all(np.isfinite(solved)):
            raise InputError("resolve returned non-finite values", element="resolve")
        q[frames] = solved
        report.iterations += 1
        report.frames_resolved_per_iteration.append(int(frames.size))
        viol = acceleration_violations(q, fps, is_rotation, e_acc_angular, e_acc_linear)
        report.violations_per_iteration.append(int(viol.sum()))
        if int(viol.sum()) < best[0]:
            best, stale = (int(viol.sum()), q.copy(), viol), 0
        else:
            stale += 1
    if patience > 0 and int(viol.sum()) > best[0]:
        q, viol = best[1], best[2]
    report.converged = not viol.any()
    report.unresolved = viol
    return q, report


def lowpass_and_remove_peaks(q, fps: float, cutoff_hz: float | None, peak_threshold, *,
                             peak_window: int = 7, order: int = 4, change_tolerance=0.0
                             ) -> tuple[np.ndarray, np.ndarray]:
    """Filtering pass run before refinement (paper: "re-solve ... after applying low-pass and
    peak removal filters").

    1. Peak removal: per DOF, samples deviating from a running median (window ``peak_window``
       frames, edges padded with the nearest value) by more than ``peak_threshold`` (scalar or
       per-DOF ``(D,)``, in the DOF's units) are replaced by the median.
    2. Zero-phase low-pass: Butterworth of ``order`` at ``cutoff_hz`` applied forwards and
       backwards (``scipy.signal.butter`` in second-order sections + ``sosfiltfilt``, the
       numerically robust form of ``filtfilt``). Skipped when ``cutoff_hz`` is ``None`` or at /
       above Nyquist (the filter would pass everything) or the clip has fewer than 3 frames;
       the padding is shortened for short clips.

    Returns ``(q_filtered, changed)``: ``changed[f]`` is true when some DOF of frame ``f``
    moved by more than ``change_tolerance`` (scalar or ``(D,)``). Rows of changed frames hold
    the filtered values (the seeds the caller re-solves from); other rows are the input,
    untouched."""
    q = _as_trajectory(q)
    fps = _check_fps(fps)
    F, D = q.shape
    thr = _per_dof(peak_threshold, D, "peak_threshold")
    tol = _per_dof(change_tolerance, D, "change_tolerance")
    if int(peak_window) != peak_window or peak_window < 1:
        raise InputError(f"must be a positive integer, got {peak_window!r}", element="peak_window")
    if int(order) != order or order < 1:
        raise InputError(f"must be a positive integer, got {order!r}", element="order")

    out = q.copy()
    if F == 0 or D == 0:
        return out, np.zeros(F, dtype=bool)

    # 1. peak removal against a running median
    window = min(int(peak_window), F)
    if window >= 3:
        med = ndimage.median_filter(out, size=(window, 1), mode="nearest")
        peaks = np.abs(out - med) > thr
        out[peaks] = med[peaks]

    # 2. zero-phase low-pass
    nyquist = 0.5 * fps
    if cutoff_hz is not None and F >= 3:
        cutoff = float(cutoff_hz)
        if not np.isfinite(cutoff) or cutoff <= 0:
            raise InputError(f"must be positive, got {cutoff_hz!r}", element="cutoff_hz")
        if cutoff < nyquist:
            from scipy import signal  # here: importing scipy.signal costs every process ~0.4 s

            sos = signal.butter(int(order), cutoff / nyquist, btype="low", output="sos")
            # sosfiltfilt's default pad length; it must be shorter than the signal
            default_pad = 3 * (2 * len(sos) + 1 - min((sos[:, 2] == 0).sum(),
                                                      (sos[:, 5] == 0).sum()))
            padlen = min(default_pad, F - 1)
            out = signal.sosfiltfilt(sos, out, axis=0, padlen=padlen)

    changed = (np.abs(out - q) > tol).any(axis=1)
    result = q.copy()
    result[changed] = out[changed]
    return result, changed
