"""Grasp synthesis for demonstration clips: place the palm against an object, then close each
finger until its links touch the surface (the classic "autograsp": when a link touches, its
joint and every joint before it stop, the joints after it keep closing).

Works on any generated hand whose finger joints are named ``<finger><k>`` with a
``<finger><k>_flex`` DOF (see :mod:`retarget_core.rig.handgen`). Obstacles are signed
distance functions in world coordinates (negative inside).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from ..mesh.surface_points import SurfacePoints
from ..rig.anatomy import hand_fingers, palm_vertices, root_transform, set_root_transform
from ..rig.hand_model import HandModel
from ..rig.model import Rig

Sdf = Callable[[np.ndarray], np.ndarray]


# ---- hand frames ------------------------------------------------------------------------------
def frame_from_directions(palm_direction, finger_direction) -> np.ndarray:
    """Hand-frame rotation (3, 3) whose -Z (the palm normal) points along ``palm_direction``
    and whose +Y (the fingers) points along ``finger_direction`` (orthogonalised)."""
    z = -np.asarray(palm_direction, float)
    z /= np.linalg.norm(z)
    y = np.asarray(finger_direction, float)
    y = y - (y @ z) * z
    y /= np.linalg.norm(y)
    return np.column_stack([np.cross(y, z), y, z])


# ---- palm --------------------------------------------------------------------------------------
def palm_center(rig: Rig, model: HandModel | None = None) -> np.ndarray:
    """(3,) centre of the palm surface at rest, hand frame (``model``: the rig's hand model
    when already built)."""
    return rig.surface.vertices[palm_vertices(rig, model)].mean(axis=0)


class _Skinner:
    """Skins a fixed subset of surface vertices quickly (binding built once)."""

    def __init__(self, rig: Rig, vertex_ids: np.ndarray):
        self.kin = rig.kinematics()
        self.binding = self.kin.bind(SurfacePoints.from_vertices(vertex_ids, rig.surface.faces))

    def __call__(self, q):
        """(P, 3) the points at ``q`` (D,) or at a :class:`~retarget_core.rig.kinematics.Pose`."""
        return self.kin.points(q, self.binding)


def _min_sdf(points: np.ndarray, obstacles: list[Sdf]) -> float:
    if len(points) == 0:
        return np.inf
    return float(min(np.min(sdf(points)) for sdf in obstacles))


def place_palm(rig: Rig, q: np.ndarray, approach: np.ndarray, obstacles: list[Sdf], standoff: float,
               max_travel: float = 0.15) -> np.ndarray:
    """Slide the hand along ``approach`` (unit, world) until the hand, in its current (open)
    pose, is ``standoff`` metres from the nearest obstacle. The hand starts at q (assumed clear, or is backed off
    first). Returns the new q."""
    skin = _Skinner(rig, np.arange(rig.surface.n_vertices))
    base = root_transform(rig, q)
    approach = np.asarray(approach, float) / np.linalg.norm(approach)

    def gap(s):
        t = base.copy()
        t[:3, 3] += s * approach
        return _min_sdf(skin(set_root_transform(rig, q, t)), obstacles) - standoff

    step = 0.002
    lo = 0.0
    while gap(lo) < 0 and lo > -max_travel:  # start clear of every obstacle
        lo -= step
    hi = None
    s_ = lo
    while s_ < max_travel:  # march toward the object to the first contact, then bisect
        s_ += step
        if gap(s_) < 0:
            hi = s_
            break
        lo = s_
    if hi is not None:
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            if gap(mid) > 0:
                lo = mid
            else:
                hi = mid
    t = base.copy()
    t[:3, 3] += lo * approach
    return set_root_transform(rig, q, t)


def close_fingers(rig: Rig, q: np.ndarray, obstacles: list[Sdf], *, fingers: list[str] | None = None,
                  press: float = 0.0004, steps: int = 60, max_curl: float = 1.0,
                  model: HandModel | None = None) -> tuple[np.ndarray, dict]:
    """Close the named fingers (default: all) from q until their links touch an obstacle,
    pressing in by ``press`` metres (soft finger pads). Returns (q, {finger: [touching link
    indices]}). A link that touches stops its joint and the joints before it. ``model``: the
    rig's hand model when already built (a grasp search closes the fingers many times)."""
    q = np.array(q, dtype=np.float64)
    upper = rig.upper
    touching: dict[str, list[int]] = {}
    kin = rig.kinematics()
    for finger in hand_fingers(rig, model):
        if fingers is not None and finger.name not in fingers:
            continue
        links = [_Skinner(rig, ids) if len(ids) else None for ids in finger.link_vertices]
        active = [d >= 0 for d in finger.flex_dofs]
        touched: list[int] = []

        def link_gaps(qq):
            # Only links at or after the first still-moving joint can change; one pose for all
            first = active.index(True)
            pose = kin.pose(qq)
            return [(_min_sdf(s(pose), obstacles) + press) if (s is not None and k >= first) else np.inf
                    for k, s in enumerate(links)]

        start = q.copy()
        while any(active):
            span = np.array([(upper[d] - start[d]) * max_curl if d >= 0 else 0.0 for d in finger.flex_dofs])

            def at(s, start=start, span=span):
                qq = start.copy()
                for k, d in enumerate(finger.flex_dofs):
                    if active[k]:
                        qq[d] = start[d] + min(s * finger.closing_rate[k], 1.0) * span[k]
                return qq

            gaps = link_gaps(start)
            if min(gaps) < 0:  # already touching where it starts: that link stops here
                hit_link, lo = int(np.argmin(gaps)), 0.0
            else:
                hit_link, lo = None, 0.0
                for s_ in np.linspace(0.0, 1.0, steps + 1)[1:]:
                    if min(link_gaps(at(s_))) < 0:
                        hi = s_
                        for _ in range(30):
                            mid = 0.5 * (lo + hi)
                            if min(link_gaps(at(mid))) < 0:
                                hi = mid
                            else:
                                lo = mid
                        hit_link = int(np.argmin(link_gaps(at(hi))))
                        break
                    lo = s_
            start = at(lo)
            if hit_link is None:
                break
            touched.append(hit_link)
            for k in range(hit_link + 1):
                active[k] = False
        q = start
        touching[finger.name] = sorted(set(touched))
    return q, touching
