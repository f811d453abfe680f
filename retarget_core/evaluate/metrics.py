"""Per-frame and per-clip quality metrics of a retargeted motion: contact error and coverage,
marker error, smoothness per DOF, DOF limit violations, and the summary of a per-frame series.
The retarget's own figures (result.json) and ``handretarget evaluate`` both compute the contact
error with :func:`contact_distance_per_frame` (or its parts :func:`contact_distances` and
:func:`median_per_frame_mm`) and the marker error with :func:`marker_error_per_frame`.

Inputs in SI units (metres, radians, seconds); reports in the units people read: millimetres
for contact and marker distances, degrees (rotation DOFs) or centimetres (translation DOFs)
per second squared / cubed for smoothness. Every summary is a small frozen dataclass with a
``to_dict()`` that is JSON-serialisable (NaN -> None).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Sequence

import numpy as np

from ..errors import InputError
from ..jsonio import to_jsonable
from ..mesh.geometry import SURFACE_TOLERANCE_M
from ..mesh.surface_points import SurfacePoints

#: A source contact counts as realised on the target within this distance (metres; up to
#: ``SURFACE_TOLERANCE_M`` beyond it, so round-off never decides).
DEFAULT_COVERAGE_THRESHOLD = 0.005
#: DOF values beyond a limit by more than this (radians or metres) count as violations.
DEFAULT_LIMIT_TOLERANCE = 1e-6

_RAD_TO_DEG = 180.0 / math.pi
_MM = 1000.0
_M_TO_CM = 100.0


def _mask(mask, n: int, element: str) -> np.ndarray:
    if mask is None:
        return np.ones(n, dtype=bool)
    m = np.asarray(mask)
    if m.shape != (n,):
        raise InputError(f"must have shape ({n},), got {m.shape}", element=element)
    return m.astype(bool)


# ------------------------------------------------------------------------------------------
# distances: contacts and markers
# ------------------------------------------------------------------------------------------
def contact_distances(kinematics, q: np.ndarray, contacts) -> np.ndarray:
    """Per contact (N,) metres: the distance between each target-hand contact point, posed at
    its frame's DOF values, and its point on the object's surface.

    kinematics: the target rig's :class:`~retarget_core.rig.kinematics.Kinematics`; q (T, D)
    DOF values per frame (radians / metres); contacts: the contact pairs of every frame, split
    by ``frame_offsets`` (T+1,) (a :class:`~retarget_core.solve.targets.ContactTargets`, or any
    object with ``frame_offsets``, ``target_faces`` (N,), ``target_barycentric`` (N, 3) and
    ``surface_points(f)`` (N_f, 3) world metres). Rows follow the contacts' order."""
    q = np.asarray(q, dtype=np.float64)
    offsets = np.asarray(contacts.frame_offsets, dtype=np.int64)
    if len(offsets) != len(q) + 1:
        raise InputError(f"contacts are split into {len(offsets) - 1} frames, q has {len(q)}",
                         element="frame_offsets")
    distances = np.full(int(offsets[-1]), np.nan)
    for f in range(len(q)):
        sl = slice(int(offsets[f]), int(offsets[f + 1]))
        if sl.stop > sl.start:
            points = SurfacePoints(contacts.target_faces[sl], contacts.target_barycentric[sl])
            posed = kinematics.points(kinematics.pose(q[f]), kinematics.bind(points))
            distances[sl] = np.linalg.norm(posed - contacts.surface_points(f), axis=1)
    return distances


def median_per_frame_mm(distances: np.ndarray, frame_offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The contact error: per frame, the median (mm) of that frame's distances (N,) metres
    (rows ``frame_offsets[f]:frame_offsets[f + 1]``), NaN on a frame without any; and the
    count (T,) int64 of distances per frame."""
    offsets = np.asarray(frame_offsets, dtype=np.int64)
    count = np.diff(offsets)
    median = np.full(len(count), np.nan)
    for f in np.flatnonzero(count):
        median[f] = _MM * np.median(distances[offsets[f]:offsets[f + 1]])
    return median, count


def contact_distance_per_frame(kinematics, q: np.ndarray, contacts) -> tuple[np.ndarray, np.ndarray]:
    """Per frame at the poses q (T, D): the median distance (T,) mm between the posed target
    contact points and their object-surface points (NaN on frames without contacts) and the
    contact count (T,) int64. Inputs as :func:`contact_distances`."""
    return median_per_frame_mm(contact_distances(kinematics, q, contacts), contacts.frame_offsets)


def marker_figure_weights(markers) -> np.ndarray:
    """(Np,) weights summing to 1 under which every marker counts once (1 / K for each pair of a
    marker of K pairs), whatever weights the solve gave the markers (``proportion_weights``):
    the figure measures all markers, not the ones the solve was asked to favour."""
    names = getattr(markers, "names", None)
    if names is not None and len(names) == len(markers.pair_target):
        _, of, count = np.unique(np.asarray(names, dtype=str), return_inverse=True, return_counts=True)
        weight = 1.0 / count[of]
    else:
        weight = np.asarray(markers.pair_weight, dtype=np.float64)
    return weight / weight.sum()


def marker_error_per_frame(kinematics, q: np.ndarray, markers) -> np.ndarray:
    """Per frame at the poses q (T, D): the marker error (T,) mm, the mean distance between
    the posed target marker points and the source markers with every marker counting once
    (:func:`marker_figure_weights`: a marker of K pairs weighs each 1/K, whatever weights the
    solve used); NaN for every frame when there are no marker pairs.

    markers: a :class:`~retarget_core.solve.targets.MarkerTargets` (or any object with
    ``target_faces`` (Mt,), ``target_barycentric`` (Mt, 3), ``pair_target`` (Np,) into them,
    ``pair_weight`` (Np,), optionally ``names`` (Np,), and ``source_positions`` (T, Np, 3)
    world metres)."""
    q = np.asarray(q, dtype=np.float64)
    marker = np.full(len(q), np.nan)
    if not len(markers.pair_target):
        return marker
    if len(markers.source_positions) != len(q):
        raise InputError(f"source markers have {len(markers.source_positions)} frames, q has {len(q)}",
                         element="source_positions")
    binding = kinematics.bind(SurfacePoints(markers.target_faces, markers.target_barycentric))
    weight = marker_figure_weights(markers)
    for f in range(len(q)):
        x = kinematics.points(kinematics.pose(q[f]), binding)[markers.pair_target]
        marker[f] = _MM * float(weight @ np.linalg.norm(x - markers.source_positions[f], axis=1))
    return marker


@dataclass(frozen=True)
class ContactCoverage:
    """Share of a frame's source contacts realised on the target hand.

    ``n_source``: source contacts; ``n_transferred``: of them carried onto the target;
    ``n_realised``: transferred and within ``threshold_m`` of their object point;
    ``share``: n_realised / n_source (NaN when the frame has no source contact)."""

    n_source: int
    n_transferred: int
    n_realised: int
    share: float
    threshold_m: float

    def to_dict(self) -> dict:
        return to_jsonable(asdict(self))


def contact_coverage(
    distances: np.ndarray,
    transferred: np.ndarray | None = None,
    threshold_m: float = DEFAULT_COVERAGE_THRESHOLD,
) -> ContactCoverage:
    """Contact coverage of one frame.

    distances (N,) metres: per source contact, the distance between its target-hand point and
    its object point (any value, NaN included, for contacts that were not transferred);
    transferred (N,) bool: which source contacts exist on the target (default all). A dropped
    contact counts as not realised; a contact is realised when its distance is at most
    threshold_m + ``SURFACE_TOLERANCE_M`` (1e-9 m: a distance at the threshold up to round-off
    counts as within it).
    """
    d = np.asarray(distances, dtype=np.float64).reshape(-1)
    t = _mask(transferred, len(d), "transferred")
    if not (threshold_m >= 0):
        raise InputError(f"must be >= 0, got {threshold_m!r}", element="threshold_m")
    realised = t & np.isfinite(d) & (d <= threshold_m + SURFACE_TOLERANCE_M)
    n = len(d)
    return ContactCoverage(
        n_source=int(n),
        n_transferred=int(t.sum()),
        n_realised=int(realised.sum()),
        share=float(realised.sum() / n) if n else math.nan,
        threshold_m=float(threshold_m),
    )


def coverage_per_frame(distances: np.ndarray, frame_offsets: np.ndarray, source_count: np.ndarray | None = None,
                       threshold_m: float = DEFAULT_COVERAGE_THRESHOLD) -> np.ndarray:
    """Per frame (T,): :func:`contact_coverage` of the frame. distances (N,) metres of the
    transferred contacts, split by ``frame_offsets`` (T+1,) (as :func:`contact_distances`
    gives them); source_count (T,): the frame's source contacts before the transfer (default:
    as many as were transferred); the ones the transfer dropped count as not realised. NaN on
    a frame without a transferred contact."""
    offsets = np.asarray(frame_offsets, dtype=np.int64)
    count = np.diff(offsets)
    share = np.full(len(count), np.nan)
    for f in np.flatnonzero(count):
        d = np.asarray(distances[offsets[f]:offsets[f + 1]], dtype=np.float64)
        total = int(source_count[f]) if source_count is not None else len(d)
        every = np.concatenate([d, np.full(max(total - len(d), 0), np.nan)])
        share[f] = contact_coverage(every, np.arange(len(every)) < len(d), threshold_m).share
    return share


# ------------------------------------------------------------------------------------------
# DOF trajectories: smoothness and limits
# ------------------------------------------------------------------------------------------
def _dof_values(values, element: str = "values") -> np.ndarray:
    v = np.asarray(values, dtype=np.float64)
    if v.ndim == 1:
        v = v[:, None]
    if v.ndim != 2:
        raise InputError(f"must be a (T, D) array, got shape {v.shape}", element=element)
    return v


def _rotation_mask(kinds, n_dofs: int) -> np.ndarray:
    """kinds: sequence of "rotate" / "translate" strings, or a boolean mask (True = rotation)."""
    k = np.asarray(kinds)
    if k.shape != (n_dofs,):
        raise InputError(f"must give one kind per DOF ({n_dofs}), got shape {k.shape}", element="kinds")
    if k.dtype == bool:
        return k.copy()
    out = np.zeros(n_dofs, dtype=bool)
    for i, kind in enumerate(k.tolist()):
        if kind == "rotate":
            out[i] = True
        elif kind != "translate":
            raise InputError(f"must be 'rotate' or 'translate', got {kind!r}", element=f"kinds[{i}]")
    return out


@dataclass(frozen=True)
class Smoothness:
    """Finite-difference acceleration and jerk per DOF.

    All arrays (D,): ``accel_rms`` / ``accel_max`` (max of |a|) in deg/s^2 for rotation DOFs
    and cm/s^2 for translation DOFs; ``jerk_rms`` / ``jerk_max`` in deg/s^3 or cm/s^3;
    ``rotation`` True for rotation DOFs. NaN where the clip is too short (acceleration needs
    3 frames, jerk 4) or a DOF has no finite difference."""

    fps: float
    rotation: np.ndarray
    accel_rms: np.ndarray
    accel_max: np.ndarray
    jerk_rms: np.ndarray
    jerk_max: np.ndarray

    def units(self, order: int) -> list[str]:
        """Unit of each DOF's value for derivative ``order`` (2: acceleration, 3: jerk)."""
        return [("deg" if r else "cm") + f"/s^{order}" for r in self.rotation]

    def to_dict(self, dof_names: Sequence[str] | None = None) -> dict:
        names = list(dof_names) if dof_names is not None else [str(i) for i in range(len(self.rotation))]
        if len(names) != len(self.rotation):
            raise InputError(f"need {len(self.rotation)} DOF names, got {len(names)}", element="dof_names")
        return to_jsonable(
            {
                "fps": self.fps,
                "dofs": {
                    n: {
                        "kind": "rotate" if r else "translate",
                        "accel_unit": ("deg" if r else "cm") + "/s^2",
                        "jerk_unit": ("deg" if r else "cm") + "/s^3",
                        "accel_rms": ar,
                        "accel_max": am,
                        "jerk_rms": jr,
                        "jerk_max": jm,
                    }
                    for n, r, ar, am, jr, jm in zip(
                        names, self.rotation, self.accel_rms, self.accel_max, self.jerk_rms, self.jerk_max
                    )
                },
            }
        )


def _rms_max(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n_dofs = x.shape[1]
    rms = np.full(n_dofs, math.nan)
    mx = np.full(n_dofs, math.nan)
    for j in range(n_dofs):
        col = x[:, j]
        col = col[np.isfinite(col)]
        if len(col):
            rms[j] = math.sqrt(float(np.mean(col * col)))
            mx[j] = float(np.abs(col).max())
    return rms, mx


def dof_derivatives(values: np.ndarray, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """Acceleration (T-2, D) and jerk (T-3, D) of DOF values (T, D) sampled at ``fps``, by
    finite differences in the values' own units per s^2 / s^3: a[t] = (x[t+2] - 2 x[t+1] +
    x[t]) fps^2 (centred on frame t+1), j[t] = (x[t+3] - 3 x[t+2] + 3 x[t+1] - x[t]) fps^3.
    Exact for polynomials of degree 2 (acceleration) and 3 (jerk)."""
    v = _dof_values(values)
    if not (fps > 0 and math.isfinite(fps)):
        raise InputError(f"must be a positive number, got {fps!r}", element="fps")
    accel = np.diff(v, n=2, axis=0) * fps**2 if len(v) >= 3 else np.zeros((0, v.shape[1]))
    jerk = np.diff(v, n=3, axis=0) * fps**3 if len(v) >= 4 else np.zeros((0, v.shape[1]))
    return accel, jerk


def dof_smoothness(values: np.ndarray, fps: float, kinds) -> Smoothness:
    """Smoothness per DOF of a trajectory.

    values (T, D): radians for rotation DOFs, metres for translation DOFs; fps: frames per
    second; kinds: (D,) "rotate" / "translate" strings (as ``Dof.kind``) or a boolean mask
    (True = rotation). Returns RMS and max of |acceleration| (deg/s^2, cm/s^2) and of |jerk|
    (deg/s^3, cm/s^3) per DOF."""
    v = _dof_values(values)
    rotation = _rotation_mask(kinds, v.shape[1])
    scale = np.where(rotation, _RAD_TO_DEG, _M_TO_CM)
    accel, jerk = dof_derivatives(v, fps)
    a_rms, a_max = _rms_max(accel * scale)
    j_rms, j_max = _rms_max(jerk * scale)
    return Smoothness(float(fps), rotation, a_rms, a_max, j_rms, j_max)


@dataclass(frozen=True)
class LimitViolations:
    """DOF values outside [lower, upper] by more than ``tolerance``.

    ``count``: frame x DOF entries in violation; ``frames``: frames with at least one;
    ``per_dof`` (D,): violations per DOF; ``worst_excess``: the largest excess beyond a limit
    (radians or metres, the DOF's own unit; 0 when none); ``worst_frame`` / ``worst_dof``:
    where (-1 when none)."""

    count: int
    frames: int
    per_dof: np.ndarray
    worst_excess: float
    worst_frame: int
    worst_dof: int
    tolerance: float

    def to_dict(self, dof_names: Sequence[str] | None = None) -> dict:
        out = to_jsonable(asdict(self))
        if dof_names is not None and self.worst_dof >= 0:
            out["worst_dof_name"] = str(list(dof_names)[self.worst_dof])
        return out


def dof_limit_violations(
    values: np.ndarray, lower: np.ndarray, upper: np.ndarray, tolerance: float = DEFAULT_LIMIT_TOLERANCE
) -> LimitViolations:
    """Limit violations of a trajectory: values (T, D), lower (D,), upper (D,) in the DOFs'
    units (radians / metres); an entry violates when it is below ``lower - tolerance`` or
    above ``upper + tolerance``. NaN values are not violations."""
    v = _dof_values(values)
    lo = np.asarray(lower, dtype=np.float64).reshape(-1)
    hi = np.asarray(upper, dtype=np.float64).reshape(-1)
    if lo.shape != (v.shape[1],) or hi.shape != (v.shape[1],):
        raise InputError(f"limits must have shape ({v.shape[1]},), got {lo.shape} and {hi.shape}", element="lower")
    with np.errstate(invalid="ignore"):
        excess = np.maximum(lo - v, v - hi)  # > 0 outside, NaN for NaN values
    excess = np.where(np.isfinite(excess), excess, -np.inf)
    bad = excess > tolerance
    if bad.any():
        f, j = np.unravel_index(int(np.argmax(excess)), excess.shape)
        worst, worst_f, worst_j = float(excess[f, j]), int(f), int(j)
    else:
        worst, worst_f, worst_j = 0.0, -1, -1
    return LimitViolations(
        count=int(bad.sum()),
        frames=int(bad.any(axis=1).sum()),
        per_dof=bad.sum(axis=0).astype(np.int64),
        worst_excess=worst,
        worst_frame=worst_f,
        worst_dof=worst_j,
        tolerance=float(tolerance),
    )


# ------------------------------------------------------------------------------------------
# per-clip summary
# ------------------------------------------------------------------------------------------
def summarize_series(values: np.ndarray) -> dict:
    """Summary of one per-frame series (T,): frames, finite frames, mean, median, p95, min,
    max and the frame of the max; NaN frames (unavailable / failed) are left out and counted.
    JSON-serialisable; statistics are None when no frame is finite."""
    x = np.asarray(values, dtype=np.float64).reshape(-1)
    finite = np.isfinite(x)
    out = {"frames": int(len(x)), "finite_frames": int(finite.sum())}
    if finite.any():
        y = x[finite]
        out.update(
            mean=float(y.mean()),
            median=float(np.median(y)),
            p95=float(np.percentile(y, 95)),
            min=float(y.min()),
            max=float(y.max()),
            argmax_frame=int(np.flatnonzero(finite)[int(np.argmax(y))]),
        )
    else:
        out.update(mean=None, median=None, p95=None, min=None, max=None, argmax_frame=None)
    return out
