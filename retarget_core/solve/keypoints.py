"""Keypoint-only retargeting, for robot teams whose capture gives keypoints, not a hand mesh
(``handretarget retarget-keypoints``): per frame, the target hand's named keypoints meet given
positions (T, K, 3) m in the least-squares sense, root included; no contacts, no object.

A keypoint name is either one of the rig's markers (its annotations: a ``*Fingertip`` marker sits
on the finger's pad; several target points are averaged) or one of its joints (a robot file's
link: the link frame's origin). The frames are solved in order, each by the frame solver's
bounded Levenberg-Marquardt steps (:func:`~retarget_core.solve.frame_solver.gauss_newton_warm_start`)
seeded from the frame before (the first from a rigid fit of the keypoints at rest), with a
small pull towards that seed (:data:`SMOOTHING`, mm^2 per rad^2 or per cm^2): keypoints rarely fix
every DOF (a fingertip fixes three of a four-DOF finger's), and the pull keeps what they leave
free where it was instead of letting it drift. MMA does not follow: the objective is a plain
sum of squares, which Levenberg-Marquardt solves to convergence (MMA added nothing on the
bench's frames).
"""

from __future__ import annotations

import difflib
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..mesh.geometry import rigid_fit
from ..mesh.surface_points import SurfacePoints
from ..rig.anatomy import set_root_transform
from ..rig.kinematics import SurfaceBinding
from .frame_solver import gauss_newton_warm_start

MM = 1000.0
#: Pull towards the seed (the previous frame's solution), per squared radian (or per squared
#: centimetre of a prismatic DOF), in the keypoints' squared millimetres: one radian of a DOF
#: the keypoints leave free costs as much as a keypoint one millimetre off.
SMOOTHING = 1.0
#: Levenberg-Marquardt trial steps per frame (it stops earlier once a step gains < 1e-6 of the
#: cost); the first frame starts from the rest fingers and gets more.
ITERATIONS = 30
FIRST_FRAME_ITERATIONS = 200
#: A frame whose farthest keypoint ends more than this (mm) off is solved again from the rest
#: fingers (and the root it found), the lower objective kept: seeded from the frame before, a
#: finger can end pressed against a limit on the wrong side of it.
RETRY_MM = 1.0
#: Keypoint files: at most this many frames and keypoints.
MAX_FRAMES = 1_000_000
MAX_KEYPOINTS = 256
#: A hand's keypoints lie within this (m) of their mean; beyond it the file is not in metres.
MAX_HAND_SPREAD = 1.0


@dataclass(frozen=True)
class Keypoints:
    """Target keypoints: ``names`` (K,), ``positions`` (T, K, 3) m (NaN: not seen in that
    frame), ``fps`` frames per second."""

    names: tuple
    positions: np.ndarray
    fps: float

    @property
    def n_frames(self) -> int:
        return self.positions.shape[0]


def load_keypoints(path, fps: float | None = None) -> Keypoints:
    """Keypoints from an .npz with ``positions`` (T, K, 3) metres, ``names`` (K,) strings and
    ``fps`` (a scalar; ``fps`` given here overrides it). Every frame needs three seen keypoints
    (NaN rows are unseen) to place the root."""
    source = str(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError, EOFError) as err:
        raise InputError(f"not a readable .npz file: {err}", source=source) from None
    for key in ("positions", "names"):
        if key not in arrays:
            raise InputError(f"missing array {key!r} (expected positions (T, K, 3) m, names (K,), fps)",
                             source=source, element=key)
    positions = np.asarray(arrays["positions"])
    if positions.ndim != 3 or positions.shape[2] != 3 or not np.issubdtype(positions.dtype, np.number):
        raise InputError(f"must be a numeric (T, K, 3) array, got shape {positions.shape} ({positions.dtype})",
                         source=source, element="positions")
    n_frames, n_keys, _ = positions.shape
    if not 1 <= n_frames <= MAX_FRAMES or not 3 <= n_keys <= MAX_KEYPOINTS:
        raise InputError(f"needs 1-{MAX_FRAMES} frames and 3-{MAX_KEYPOINTS} keypoints, got {n_frames} x {n_keys}",
                         source=source, element="positions")
    positions = positions.astype(np.float64)
    if np.isinf(positions).any():
        raise InputError("holds infinite values (use NaN for a keypoint not seen in a frame)", source=source,
                         element="positions")
    seen = np.isfinite(positions).all(axis=2)
    if (np.isnan(positions).any(axis=2) & ~np.isnan(positions).all(axis=2)).any():
        raise InputError("a keypoint is partly NaN: a keypoint not seen in a frame is NaN in all three "
                         "coordinates", source=source, element="positions")
    short = np.flatnonzero(seen.sum(axis=1) < 3)
    if len(short):
        raise InputError(f"frame {int(short[0])} has {int(seen[short[0]].sum())} seen keypoints; every frame needs "
                         f"at least 3 to place the hand's root ({len(short)} frames short)", source=source,
                         element="positions")
    centre = np.nanmean(positions, axis=1, keepdims=True)
    spread = float(np.median(np.nanmax(np.linalg.norm(positions - centre, axis=2), axis=1)))
    if spread > MAX_HAND_SPREAD:
        raise InputError(f"a frame's keypoints lie up to {spread:.3g} from their mean (median over frames); a hand "
                         f"spans a few tenths of a metre: positions are in metres (millimetres given?)",
                         source=source, element="positions")
    names = arrays["names"]
    if names.shape != (n_keys,) or names.dtype.kind not in "US":
        raise InputError(f"must be ({n_keys},) strings (one per keypoint), got shape {names.shape} ({names.dtype})",
                         source=source, element="names")
    names = tuple(str(n) for n in names)
    if len(set(names)) != len(names):
        raise InputError(f"repeats a name: {sorted({n for n in names if names.count(n) > 1})}", source=source,
                         element="names")
    if fps is None:
        if "fps" not in arrays:
            raise InputError("no frame rate: store fps in the file or give --fps", source=source, element="fps")
        fps = float(np.asarray(arrays["fps"]).reshape(-1)[0])
    if not (np.isfinite(fps) and 0 < fps <= 10000):
        raise InputError(f"must be in (0, 10000] frames per second, got {fps!r}", source=source, element="fps")
    return Keypoints(names, positions, float(fps))


@dataclass(frozen=True)
class KeypointSites:
    """Where each keypoint sits on the rig: a marker's target points (their mean) or a joint's
    origin. ``marker_points`` SurfacePoints (M,) with ``average`` (K, M) (zero rows for joint
    keypoints); ``joint`` (K,) the joint of a joint keypoint, -1 for a marker's."""

    names: tuple
    marker_points: SurfacePoints
    average: np.ndarray
    joint: np.ndarray
    kinds: tuple = field(default=())


def keypoint_sites(rig, names, annotations=None) -> KeypointSites:
    """Resolve keypoint ``names`` on ``rig``: a marker of ``annotations`` (its target points) or
    a joint (link) of the rig, markers first. An unknown name is an InputError listing the
    closest names of both kinds."""
    from ..transfer.annotations import _signature_of, resolve_points

    if annotations is not None:
        # the markers' target points are indices into the mesh the annotations were made on
        made, here = annotations.target, _signature_of(rig)
        if (made.vertices, made.faces) != (here.vertices, here.faces) or (
                made.surface_sha256 is not None and made.surface_sha256 != here.surface_sha256):
            raise InputError(f"the annotations' markers were made on rig {made.rig!r}'s surface ({made.vertices} "
                             f"vertices, {made.faces} faces{', another surface hash' if made.vertices == here.vertices else ''}); "
                             f"rig {rig.name!r} has {here.vertices} vertices, {here.faces} faces: give annotations made "
                             f"for this rig (handretarget annotate propose), or none to have them proposed",
                             element="annotations")
    markers = {m.name: m for m in (annotations.markers if annotations is not None else ())}
    joints = {name: i for i, name in enumerate(rig.joint_names)}
    faces, bary, rows, joint, kinds = [], [], [], [], []
    for k, name in enumerate(names):
        if name in markers:
            pts = resolve_points(list(markers[name].target), rig.surface.faces, rig.surface.n_vertices,
                                 what=f"marker {name!r} target")
            rows.append((k, len(faces), len(pts.faces)))
            faces += list(pts.faces)
            bary += list(pts.barycentric)
            joint.append(-1)
            kinds.append("marker")
        elif name in joints:
            joint.append(joints[name])
            kinds.append("joint")
        else:
            known = list(markers) + list(joints)
            near = difflib.get_close_matches(name, known, n=5, cutoff=0.5)
            raise InputError(f"keypoint {name!r} is neither a marker of the annotations nor a joint (link) of rig "
                             f"{rig.name!r}" + (f"; closest: {', '.join(near)}" if near else "")
                             + f" (markers: {', '.join(markers) or 'none'}; {len(joints)} joints: "
                             f"{', '.join(list(joints)[:12])}{' ...' if len(joints) > 12 else ''})",
                             element="names")
    average = np.zeros((len(names), len(faces)))
    for k, start, count in rows:
        average[k, start:start + count] = 1.0 / count
    points = SurfacePoints(np.asarray(faces, dtype=np.int64).reshape(-1),
                           np.asarray(bary, dtype=np.float64).reshape(-1, 3))
    return KeypointSites(tuple(names), points, average, np.asarray(joint, dtype=np.int64), tuple(kinds))


class KeypointObjective:
    """sum over seen keypoints of |x_k(q) - p_k|^2 (mm^2) + SMOOTHING |q - seed|^2 over the
    non-root DOFs, in the least-squares form the frame solver's Levenberg-Marquardt steps read
    (:meth:`normal_equations`, :meth:`residual_cost`)."""

    def __init__(self, rig, sites: KeypointSites):
        self.kin = rig.kinematics()
        self.sites = sites
        self.binding = None
        if len(sites.marker_points.faces):
            # a keypoint is the mean of its marker's points, and skinning is linear in the bound
            # rest data: the mean's binding is the mean of theirs, one point per keypoint (K
            # instead of the markers' few hundred; joint keypoints get zero columns)
            b, avg = self.kin.bind(sites.marker_points), sites.average.T
            self.binding = SurfaceBinding(y=np.ascontiguousarray(b.y @ avg), z=np.ascontiguousarray(b.z @ avg),
                                          weight_sub=np.ascontiguousarray(b.weight_sub @ avg))
        self.is_joint = sites.joint >= 0
        self.pull = np.array([d.joint != 0 for d in rig.dofs]) * np.sqrt(SMOOTHING)
        # a prismatic DOF in cm, so its pull is per cm^2 like a rotation's per rad^2
        self.pull = self.pull * np.where([d.kind == "rotate" for d in rig.dofs], 1.0, 100.0)
        self.targets = np.zeros((len(sites.names), 3))
        self.seen = np.ones(len(sites.names), dtype=bool)
        self.seed = rig.rest_pose.copy()
        self.evaluations = 0

    def set_frame(self, targets: np.ndarray, seed: np.ndarray) -> None:
        self.seen = np.isfinite(targets).all(axis=1)
        self.targets = np.where(self.seen[:, None], targets, 0.0)
        self.seed = np.asarray(seed, dtype=np.float64).copy()

    def positions(self, pose) -> np.ndarray:
        """(K, 3) m: every keypoint at ``pose``."""
        x = np.zeros((len(self.sites.names), 3))
        if self.binding is not None:
            x += self.kin.points(pose, self.binding)
        if self.is_joint.any():
            x[self.is_joint] = pose.world[self.sites.joint[self.is_joint], :3, 3]
        return x

    def _blocks(self, q: np.ndarray, jacobian: bool):
        pose = self.kin.pose(q)
        x = self.positions(pose)
        r_key = ((x - self.targets) * MM)[self.seen].T.ravel()  # axis-major rows
        r_pull = self.pull * (q - self.seed)
        if not jacobian:
            return np.concatenate([r_key, r_pull]), None
        n = len(q)
        jk = np.zeros((n, 3, len(x)))
        if self.binding is not None:
            _, jx = self.kin.points_jacobian(pose, self.binding)  # (K, 3, D) view
            jk += jx.transpose(2, 1, 0)
        if self.is_joint.any():
            joints = self.sites.joint[self.is_joint]
            jk[:, :, self.is_joint] = self.kin.rigid_points_jacobian(pose, joints, x[self.is_joint])
        jt = np.concatenate([(jk[:, :, self.seen] * MM).reshape(n, -1), np.diag(self.pull)], axis=1)
        return np.concatenate([r_key, r_pull]), jt

    def normal_equations(self, q: np.ndarray):
        self.evaluations += 1
        r, jt = self._blocks(q, True)
        return float(r @ r), jt @ r, jt @ jt.T

    def residual_cost(self, q: np.ndarray) -> float:
        self.evaluations += 1
        r, _ = self._blocks(q, False)
        return float(r @ r)

    def widen_self_focus(self, q: np.ndarray) -> bool:  # no collision rows to widen
        return False


@dataclass
class KeypointSolve:
    """The solved frames q (T, D); per frame the keypoint error (T, K) mm at the solution (NaN
    where unseen); objective evaluations; seconds (wall, root included); frames solved again
    from the rest fingers (:data:`RETRY_MM`)."""

    q: np.ndarray
    error_mm: np.ndarray
    evaluations: int
    seconds: float
    retried: int = 0


def solve_keypoints(rig, sites: KeypointSites, keypoints: Keypoints) -> KeypointSolve:
    """Every frame of ``keypoints`` solved in order (module docstring)."""
    t0 = time.perf_counter()
    objective = KeypointObjective(rig, sites)
    kin = objective.kin
    lower, upper = rig.lower, rig.upper
    coupling = rig.coupling()
    lower, upper = coupling.bounds(lower, upper)  # coupled DOFs kept exactly, as in every solve
    active = coupling.free.copy()
    rest = rig.rest_pose
    rest_pose = kin.pose(rest)
    rest_keys = objective.positions(rest_pose)
    root_now = rest_pose.world[0]
    q = np.empty((keypoints.n_frames, rig.n_dofs))
    error = np.full((keypoints.n_frames, len(sites.names)), np.nan)
    seed = None
    root = np.array([d.joint == 0 for d in rig.dofs])
    retried = 0
    for f in range(keypoints.n_frames):
        targets = keypoints.positions[f]
        if seed is None:
            seen = np.isfinite(targets).all(axis=1)
            seed = set_root_transform(rig, rest, rigid_fit(rest_keys[seen], targets[seen]) @ root_now)
        objective.set_frame(targets, seed)
        steps = FIRST_FRAME_ITERATIONS if f == 0 else ITERATIONS

        def solve_from(start):
            sol = coupling.apply(gauss_newton_warm_start(objective, coupling.apply(np.clip(start, lower, upper)),
                                                         lower, upper, active, steps, coupling))
            x = objective.positions(kin.pose(sol))
            return sol, np.linalg.norm(x - targets, axis=1) * MM

        q[f], err = solve_from(seed)
        if np.nanmax(np.where(objective.seen, err, 0.0)) > RETRY_MM:
            # stuck against a limit: the same frame from the rest fingers, keeping the root it found
            rested = np.where(root, q[f], rest)
            steps = FIRST_FRAME_ITERATIONS
            other, other_err = solve_from(rested)
            if objective.residual_cost(other) < objective.residual_cost(q[f]):
                q[f], err = other, other_err
            retried += 1
        error[f, objective.seen] = err[objective.seen]
        seed = q[f]
    return KeypointSolve(q, error, objective.evaluations, time.perf_counter() - t0, retried)


def write_keypoint_result(out_dir, rig, sites: KeypointSites, keypoints: Keypoints, solved: KeypointSolve, *,
                          rate_hz: float | None = None, control_points_per_second: float = 10.0) -> dict:
    """animation.json (one cubic B-spline per DOF through the solved frames, sampled at the
    frames; a robot rig's joint commands in its file's order at ``rate_hz``, default the
    keypoints' rate) and keypoints.json (errors at the solved frames and at the delivered curve,
    time per frame) in ``out_dir``; returns {name: path}."""
    import json

    from ..export import write_animation_json
    from ..export.robot_trajectory import is_robot, robot_trajectory
    from ..fit.splines import coupled_curves, evaluate_curves, fit_trajectory
    from ..files import atomic_path
    from ..jsonio import to_jsonable
    from ..rig.anatomy import continuous_root_angles

    n = keypoints.n_frames
    times = np.arange(n) / keypoints.fps
    coupling = rig.coupling()
    q = coupling.apply(continuous_root_angles(rig, solved.q))
    curves, values = None, q
    if n >= 4:
        n_control = int(min(n, max(4, round(control_points_per_second * n / keypoints.fps))))
        curves = coupled_curves(fit_trajectory(times, q, n_control, optimize_knots=False,
                                               limits=coupling.bounds(rig.lower, rig.upper)), coupling)
        values = evaluate_curves(curves, times)
    if rate_hz is not None and not (is_robot(rig) and curves):
        raise InputError("a control rate resamples a robot's joint commands from the delivered curves: this rig is "
                         + ("not a URDF / MJCF robot" if not is_robot(rig) else "too short for a spline (4 frames)"),
                         element="rate")
    robot = None
    if is_robot(rig) and curves:
        robot = robot_trajectory(rig, curves, float(times[-1]), rate_hz or keypoints.fps, frame_times=times)
    objective = KeypointObjective(rig, sites)
    delivered = np.full_like(solved.error_mm, np.nan)
    for f in range(n):
        seen = np.isfinite(keypoints.positions[f]).all(axis=1)
        x = objective.positions(objective.kin.pose(values[f]))
        delivered[f, seen] = np.linalg.norm(x - keypoints.positions[f], axis=1)[seen] * MM
    report = {
        "rig": rig.name, "frames": n, "fps": keypoints.fps, "keypoints": list(keypoints.names),
        "sites": list(sites.kinds),
        "seconds": solved.seconds, "ms_per_frame": 1000.0 * solved.seconds / n,
        "evaluations_per_frame": solved.evaluations / n, "frames_retried": solved.retried,
        "error_mm": {"delivered": _error_figures(delivered, keypoints.names),
                     "solved": _error_figures(solved.error_mm, keypoints.names)},
        "values": "spline" if curves else "frames",
    }
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"animation.json": out / "animation.json", "keypoints.json": out / "keypoints.json"}
    write_animation_json(paths["animation.json"], rig.dof_names, times, values, extra=to_jsonable({
        "rig": rig.name, "fps": keypoints.fps, "dof_kinds": [d.kind for d in rig.dofs], "lower": rig.lower,
        "upper": rig.upper, "values": "spline" if curves else "frames", "keypoints": list(keypoints.names)}),
        robot=robot)
    with atomic_path(paths["keypoints.json"], suffix=".json.tmp") as tmp:
        tmp.write_text(json.dumps(to_jsonable(report), indent=1, allow_nan=False), encoding="utf-8")
    return paths


def _error_figures(error_mm: np.ndarray, names) -> dict:
    """Median, p95 and max (mm) over every seen (frame, keypoint), and the median per keypoint."""
    seen = error_mm[np.isfinite(error_mm)]
    return {"median": float(np.median(seen)), "p95": float(np.percentile(seen, 95)), "max": float(seen.max()),
            "per_keypoint_median": {str(n): float(np.nanmedian(error_mm[:, k])) if np.isfinite(error_mm[:, k]).any()
                                    else None for k, n in enumerate(names)}}
