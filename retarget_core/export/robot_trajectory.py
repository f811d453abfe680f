"""What a robot controller reads: the delivered curves as joint commands in the robot file's own
terms, resampled at a control rate.

For a rig imported from a URDF or MJCF file (``rig.metadata["source_format"]``), the section
``robot`` of animation.json holds:

- ``joints``: the file's moving joints, in the file's order and with its names (a MuJoCo ball
  joint as its three DOFs ``<name>_x/_y/_z``); coupled joints (mimic, tendon) are listed with
  the values the coupling gives them and named in ``couplings``;
- ``rate_hz``, ``times`` (T,) s from 0, ``positions`` (T, J) rad / m: the B-spline curves
  evaluated at the control rate (not interpolated frames);
- ``base``: the robot's base link (URDF) or root body (MJCF) as ``position`` (T, 3) m and
  ``quaternion_wxyz`` (T, 4) (signs kept continuous) in the frame the robot file is written
  in, which the 6-DOF root places in the clip's world: the wrist trajectory an arm has to
  follow;
- ``velocity``: per joint the file's limit (rad/s or m/s; URDF ``<limit velocity>``, MJCF has
  none), the largest speed of the delivered curve (its analytic derivative at the control
  samples and at the frames) and the times where the limit is exceeded. A limit is reported,
  never silently clipped: slowing the motion down is the user's decision (retarget a clip
  played slower).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError

ROBOT_FORMATS = ("urdf", "mjcf")


def is_robot(rig) -> bool:
    return rig.metadata.get("source_format") in ROBOT_FORMATS


def robot_joint_dofs(rig) -> list[int]:
    """DOF indices in the robot file's joint order (``metadata["joint_order"]``; a ball joint
    gives its three DOFs); without that record, every DOF after the free root."""
    order = rig.metadata.get("joint_order")
    names = rig.dof_names
    if not order:
        return [i for i, d in enumerate(rig.dofs) if d.joint != 0]
    out = []
    for j in order:
        if j in names:
            out.append(names.index(j))
        else:  # a ball joint's three DOFs
            parts = [f"{j}_{a}" for a in "xyz"]
            if not all(p in names for p in parts):
                raise InputError(f"the robot joint {j!r} has no DOF in the rig", element="metadata joint_order")
            out += [names.index(p) for p in parts]
    return out


def _base_frame(rig) -> tuple[int, np.ndarray]:
    """(rig joint, (4, 4) offset) of the robot's base link / root body."""
    md = rig.metadata
    record = None
    if md.get("source_format") == "urdf":
        record = md.get("link_frames", {}).get(md.get("base_link"))
    elif md.get("source_format") == "mjcf":
        record = md.get("body_offsets", {}).get(md.get("root_body"))
    if record is None:
        return 1, np.eye(4)
    return rig.joint_index(record[0]), np.asarray(record[1], dtype=np.float64)


def quaternions_wxyz(rotations: np.ndarray) -> np.ndarray:
    """(T, 4) unit quaternions (w, x, y, z) of (T, 3, 3) rotations, each sign chosen to be
    nearest the previous one (no flips between samples)."""
    from scipy.spatial.transform import Rotation

    xyzw = Rotation.from_matrix(rotations).as_quat()
    q = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    for t in range(1, len(q)):
        if q[t] @ q[t - 1] < 0:
            q[t] = -q[t]
    return q


def robot_trajectory(rig, curves, duration: float, rate_hz: float, frame_times: np.ndarray | None = None) -> dict:
    """The ``robot`` section (see the module docstring) of the B-spline ``curves`` (one per
    DOF) over [0, ``duration``] s sampled at ``rate_hz``; ``frame_times`` (F,) s: where the
    speed is checked as well (default: the control samples only)."""
    rate = float(rate_hz)
    if not (np.isfinite(rate) and rate > 0):
        raise InputError(f"the control rate must be a positive number of Hz, got {rate_hz!r}", element="rate")
    n = int(np.floor(duration * rate + 1e-9)) + 1
    times = np.arange(n) / rate
    dofs = robot_joint_dofs(rig)
    names = [rig.dof_names[i] for i in dofs]
    q = np.stack([np.asarray(c(times), dtype=np.float64) for c in curves], axis=-1)
    kin = rig.kinematics()
    joint, offset = _base_frame(rig)
    base = np.stack([kin.pose(qt).world[joint] @ offset for qt in q])
    check_at = times if frame_times is None else np.union1d(times, np.asarray(frame_times, dtype=np.float64))
    limits = rig.metadata.get("velocity_limits") or {}
    velocity = {}
    exceeded = []
    for name, i in zip(names, dofs):
        speed = np.abs(np.asarray(curves[i].derivative(check_at), dtype=np.float64))
        limit = limits.get(name)
        entry = {"limit": limit, "max": float(speed.max(initial=0.0)),
                 "unit": "m/s" if rig.dofs[i].kind == "translate" else "rad/s"}
        if limit is not None:
            over = check_at[speed > limit * (1 + 1e-9)]
            entry["exceeded_at"] = over.tolist()
            if len(over):
                exceeded.append(name)
        velocity[name] = entry
    coupled = [c for c in rig.metadata.get("couplings", []) if c["dof"] in names]
    return {
        "source_format": rig.metadata.get("source_format"), "source_file": rig.metadata.get("source_file"),
        "joints": names, "rate_hz": rate, "times": times.tolist(), "positions": q[:, dofs].tolist(),
        "base": {"name": rig.metadata.get("base_link") or rig.metadata.get("root_body") or rig.joint_names[joint],
                 "frame": "the robot file's own frame, placed in the clip's world by the free root",
                 "position": base[:, :3, 3].tolist(), "quaternion_wxyz": quaternions_wxyz(base[:, :3, :3]).tolist()},
        "couplings": coupled,
        "velocity": velocity,
        "velocity_limits": "from the file" if limits else "none in the file",
        "velocity_exceeded": exceeded,
    }
