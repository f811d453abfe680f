"""Demonstration clips made with the demo source hand: pick and place, in-hand rotation,
pinch, power grasp, drinking from a mug and a handoff, at 120 fps, with contacts labelled the
way GRAB labels them and the ground-truth DOF trajectory recorded.

World frame: metres, Z up, the table top at z = 0, the person on the -Y side. Grasps come from
:mod:`retarget_core.clip.grasp` (palm placed against the object, fingers closed until they
touch), so fingers really close on the surface; while held, the object follows the hand
rigidly (or turns in the hand for the in-hand rotation).
"""

from __future__ import annotations

import copy
from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable

import igl
import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation, Slerp

from ..mesh.implicit import rounded_box
from ..rig.anatomy import euler_xyz_from_matrix, hand_fingers, root_transform, set_root_transform, source_markers
from ..rig.demo_hands import demo_hand
from ..rig.hand_model import HandModel, hand_model
from ..rig.model import Rig
from .format import Clip
from .grasp import close_fingers, frame_from_directions, palm_center, place_palm
from .objects import DemoObject, make_object

FPS = 120.0
#: An object vertex is in contact when it lies within this distance of the hand (metres).
CONTACT_THRESHOLD = 0.002
SOURCE_RESOLUTION = 0.004
TABLE_CENTER = np.array([0.0, 0.10, -0.02])
TABLE_HALF_EXTENTS = np.array([0.45, 0.35, 0.02])

#: GRAB's right-hand contact codes by source-hand joint (MANO's joint order for the fingers).
_FINGER_CODE_BASE = {"index": 41, "middle": 44, "pinky": 47, "ring": 50, "thumb": 53}
PALM_CODE = 22


def contact_code(joint_name: str) -> int:
    """GRAB contact code of a source hand joint: 22 for the palm, wrist and forearm, 41-55 for
    the 15 finger segments."""
    for finger, base in _FINGER_CODE_BASE.items():
        if joint_name.startswith(finger) and joint_name[len(finger):].isdigit():
            return base + min(int(joint_name[len(finger):]), 3) - 1
    return PALM_CODE


def source_rig(resolution: float = SOURCE_RESOLUTION) -> Rig:
    """The rig every demo clip is made with."""
    return demo_hand("source_human", resolution=resolution)


# ---- timeline ------------------------------------------------------------------------------
def _min_jerk(s: np.ndarray) -> np.ndarray:
    return s**3 * (10 - 15 * s + 6 * s**2)


def _unwrap_near(angles: np.ndarray, reference: np.ndarray) -> np.ndarray:
    return reference + (angles - reference + np.pi) % (2 * np.pi) - np.pi


class Timeline:
    """Frame-by-frame hand DOFs and object poses, built from eased segments."""

    def __init__(self, rig: Rig, q0: np.ndarray, object_pose: np.ndarray, fps: float = FPS, time_scale: float = 1.0):
        self.rig, self.fps, self.time_scale = rig, fps, time_scale
        self.q = [np.array(q0, float)]
        self.objects = [np.array(object_pose, float)]
        self.held = [False]  # per frame: the object moves with the hand
        self.attached: np.ndarray | None = None  # root-from-object while held
        self.nominal_seconds = 0.0  # the length at time_scale 1

    @property
    def nominal_frames(self) -> int:
        """Frames the timeline has at time_scale 1 (including the first)."""
        return 1 + int(round(self.nominal_seconds * self.fps))

    def _frames(self, seconds: float) -> int:
        return max(2, int(round(seconds * self.time_scale * self.fps)))

    def wait(self, seconds: float) -> "Timeline":
        return self.move(seconds, self.q[-1])

    def attach(self) -> "Timeline":
        self.attached = np.linalg.inv(root_transform(self.rig, self.q[-1])) @ self.objects[-1]
        return self

    def detach(self) -> "Timeline":
        self.attached = None
        return self

    def move(self, seconds: float, q_target: np.ndarray, *, object_target: np.ndarray | None = None,
             spin: tuple[np.ndarray, float, np.ndarray] | None = None) -> "Timeline":
        """Ease the hand to q_target; the object follows the hand when attached, else moves to
        ``object_target`` (or stays). ``spin`` = (axis, angle, centre) in the object frame turns a
        held object in the hand about that axis by ``angle`` radians over the segment."""
        n = self._frames(seconds)
        self.nominal_seconds += seconds
        q0, q1 = self.q[-1], np.array(q_target, float)
        t0, t1 = root_transform(self.rig, q0), root_transform(self.rig, q1)
        slerp = Slerp([0, 1], Rotation.from_matrix(np.stack([t0[:3, :3], t1[:3, :3]])))
        obj0 = self.objects[-1]
        obj_slerp = None
        if object_target is not None:
            obj_slerp = Slerp([0, 1], Rotation.from_matrix(np.stack([obj0[:3, :3], object_target[:3, :3]])))
        attached0 = None if self.attached is None else self.attached.copy()
        for s in _min_jerk(np.arange(1, n + 1) / n):
            q = q0 + s * (q1 - q0)
            root = np.eye(4)
            root[:3, :3] = slerp(s).as_matrix()
            root[:3, 3] = t0[:3, 3] + s * (t1[:3, 3] - t0[:3, 3])
            q[0:3] = root[:3, 3]
            q[3:6] = _unwrap_near(euler_xyz_from_matrix(root[:3, :3]), self.q[-1][3:6])
            if self.attached is not None:
                held = attached0
                if spin is not None:
                    axis, angle, center = spin
                    turn = np.eye(4)
                    turn[:3, :3] = Rotation.from_rotvec(np.asarray(axis, float) / np.linalg.norm(axis) * angle * s).as_matrix()
                    turn[:3, 3] = center - turn[:3, :3] @ center
                    held = attached0 @ turn
                    self.attached = held
                obj = root_transform(self.rig, q) @ held
            elif obj_slerp is not None:
                obj = np.eye(4)
                obj[:3, :3] = obj_slerp(s).as_matrix()
                obj[:3, 3] = obj0[:3, 3] + s * (object_target[:3, 3] - obj0[:3, 3])
            else:
                obj = obj0
            self.q.append(q)
            self.objects.append(obj)
            self.held.append(self.attached is not None)
        return self


# ---- scene and grasps --------------------------------------------------------------------------
def _pose(translation=(0, 0, 0), rotvec=(0, 0, 0)) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    m[:3, 3] = translation
    return m


def table_sdf(points: np.ndarray) -> np.ndarray:
    return rounded_box(points, TABLE_CENTER, np.eye(3), TABLE_HALF_EXTENTS, 0.0)


def world_sdf(obj: DemoObject, pose: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    inv = np.linalg.inv(pose)
    return lambda p: obj.sdf(p @ inv[:3, :3].T + inv[:3, 3])


def relaxed_pose(rig: Rig, root: np.ndarray, curl: float = 0.15, thumb_open: float = 0.6,
                 model: HandModel | None = None) -> np.ndarray:
    """Fingers slightly curled, the thumb extended away from the palm by ``thumb_open`` of its
    range (an open hand ready to grasp), root at ``root`` (``model``: the rig's hand model when
    already built)."""
    q = set_root_transform(rig, rig.rest_pose, root)
    for finger in hand_fingers(rig, model):
        for d in finger.flex_dofs:
            if d >= 0:
                q[d] = thumb_open * rig.lower[d] if finger.name == "thumb" else min(curl, rig.upper[d])
    return q


@dataclass
class GraspPlan:
    q_grasp: np.ndarray
    q_pregrasp: np.ndarray
    q_open: np.ndarray
    touching: dict


def plan_grasp(rig: Rig, obj: DemoObject, object_pose: np.ndarray, *, palm_direction, finger_direction,
               target, standoff: float, offsets_u=(-0.015, 0.0, 0.015), offsets_v=(-0.02, -0.01, 0.0, 0.01),
               fingers=None, required=("thumb", "index"), open_curl: float = 0.1, backoff: float = 0.07) -> GraspPlan:
    """Search palm placements around ``target`` (world) on a small grid of offsets along the
    hand's X (u) and Y (v) axes; at each, slide the palm to ``standoff`` from the object, close
    the fingers against the object and the table, and keep the placement whose grasp touches
    with the most fingers (the ``required`` ones first)."""
    rotation = frame_from_directions(palm_direction, finger_direction)
    model = hand_model(rig)  # once: each of the placements below reads it twice
    center = palm_center(rig, model)
    obstacles = [world_sdf(obj, object_pose), table_sdf]
    approach = np.asarray(palm_direction, float) / np.linalg.norm(palm_direction)
    best = None
    for u in offsets_u:
        for v in offsets_v:
            root = np.eye(4)
            root[:3, :3] = rotation
            root[:3, 3] = np.asarray(target, float) - rotation @ (center + np.array([u, v, 0.0])) - approach * backoff
            q = relaxed_pose(rig, root, open_curl, model=model)
            q = place_palm(rig, q, approach, obstacles, standoff)
            q_closed, touching = close_fingers(rig, q, obstacles, fingers=fingers, model=model)
            n_required = sum(1 for f in required if touching.get(f))
            n_links = sum(len(v) for v in touching.values())
            n_fingers = sum(1 for v in touching.values() if v)
            score = (n_required, n_fingers, n_links, -abs(u) - abs(v))
            if best is None or score > best[0]:
                best = (score, q, q_closed, touching)
    _, q_open, q_grasp, touching = best
    pre = root_transform(rig, q_open)
    pre[:3, 3] -= approach * backoff
    q_pregrasp = set_root_transform(rig, q_open, pre)
    return GraspPlan(q_grasp=q_grasp, q_pregrasp=q_pregrasp, q_open=q_open, touching=touching)


def _with_root(rig: Rig, q: np.ndarray, root: np.ndarray) -> np.ndarray:
    return set_root_transform(rig, q, root)


def _lift(rig: Rig, q: np.ndarray, offset=(0, 0, 0), rotvec=(0, 0, 0), pivot=None) -> np.ndarray:
    """q with the root moved by ``offset`` and turned by ``rotvec`` about ``pivot`` (world)."""
    root = root_transform(rig, q)
    turn = _pose(rotvec=rotvec)
    if pivot is not None:
        pivot = np.asarray(pivot, float)
        turn[:3, 3] = pivot - turn[:3, :3] @ pivot
    new = turn @ root
    new[:3, 3] += offset
    return _with_root(rig, q, new)


def _place_object_with_hand(rig: Rig, q_hold: np.ndarray, attached: np.ndarray, object_pose: np.ndarray) -> np.ndarray:
    """Hand DOFs that put a held object (root-from-object ``attached``) at ``object_pose``."""
    return _with_root(rig, q_hold, object_pose @ np.linalg.inv(attached))


START_ROOT = _pose((0.10, -0.30, 0.14))


# ---- the motions -----------------------------------------------------------------------------
def _pick_and_place(rig, obj, time_scale, *, grasp_kwargs, start_pose, place_pose, lift=0.15, extra=None):
    plan = plan_grasp(rig, obj, start_pose, **grasp_kwargs)
    tl = Timeline(rig, relaxed_pose(rig, START_ROOT), start_pose, time_scale=time_scale)
    tl.wait(0.4).move(1.1, plan.q_pregrasp).move(0.6, plan.q_open).move(0.5, plan.q_grasp).attach().wait(0.2)
    q_up = _lift(rig, plan.q_grasp, offset=(0, 0, lift))
    tl.move(0.8, q_up)
    if extra is not None:
        extra(tl)
    q_place = _place_object_with_hand(rig, tl.q[-1], tl.attached, place_pose)
    above = _lift(rig, q_place, offset=(0, 0, 0.05))
    tl.move(1.0, above).move(0.7, q_place).wait(0.2).detach()
    q_release = q_place.copy()
    q_release[6:] = plan.q_open[6:]
    tl.move(0.5, q_release)
    retreat = _lift(rig, q_release, offset=-0.08 * np.asarray(grasp_kwargs["palm_direction"], float) + np.array([0, 0, 0.06]))
    tl.move(0.9, retreat).wait(0.3)
    return tl


def _bottle_pick_place(rig, time_scale):
    obj = make_object("bottle")
    start = _pose((0.0, 0.0, 0.0))
    kwargs = dict(palm_direction=(-1, 0, 0), finger_direction=(0, 1, 0), target=(0.032, 0.0, 0.09), standoff=0.001,
                  offsets_u=(-0.01, 0.0, 0.01), offsets_v=(-0.01, 0.0, 0.01))
    return obj, _pick_and_place(rig, obj, time_scale, grasp_kwargs=kwargs, start_pose=start,
                                place_pose=_pose((-0.18, 0.12, 0.0)))


def _box_pinch(rig, time_scale):
    obj = make_object("box")
    start = _pose((0.0, 0.0, 0.0))
    kwargs = dict(palm_direction=(0, 0, -1), finger_direction=(0, 1, 0), target=(0.0, 0.0, 0.035), standoff=0.025,
                  fingers=("thumb", "index"), required=("thumb", "index"), offsets_u=(-0.03, -0.02, -0.01, 0.0),
                  offsets_v=(0.02, 0.03, 0.04, 0.05))
    return obj, _pick_and_place(rig, obj, time_scale, grasp_kwargs=kwargs, start_pose=start,
                                place_pose=_pose((0.15, 0.10, 0.0), (0, 0, 0.6)), lift=0.10)


def _apple_rotate(rig, time_scale):
    obj = make_object("apple")
    start = _pose((0.0, 0.0, 0.0))
    kwargs = dict(palm_direction=(0, 0, -1), finger_direction=(0, 1, 0), target=(0.0, 0.0, 0.08), standoff=0.012,
                  required=("thumb", "index", "middle"), offsets_u=(-0.02, -0.01, 0.0), offsets_v=(-0.03, -0.02, -0.01, 0.0))

    def rotate(tl):
        center = np.array([0.0, 0.0, 0.04])
        tl.move(1.2, tl.q[-1], spin=((0, 0, 1), 2.0, center))
        tl.move(0.9, tl.q[-1], spin=((0, 0, 1), -1.0, center))

    return obj, _pick_and_place(rig, obj, time_scale, grasp_kwargs=kwargs, start_pose=start,
                                place_pose=_pose((0.0, 0.0, 0.0), (0, 0, 1.0)), lift=0.12, extra=rotate)


def _hammer_power(rig, time_scale):
    obj = make_object("hammer")
    start = _pose((0.0, 0.0, 0.0))
    kwargs = dict(palm_direction=(-1, 0, 0), finger_direction=(0, 1, 0), target=(0.014, 0.0, 0.20), standoff=0.001,
                  required=("thumb", "index", "middle", "ring"))

    def swing(tl):
        q = tl.q[-1]
        wrist = root_transform(rig, q)[:3, 3]
        for _ in range(2):
            tl.move(0.45, _lift(rig, q, rotvec=(0.0, -0.5, 0.0), pivot=wrist))
            tl.move(0.35, _lift(rig, q, rotvec=(0.0, 0.25, 0.0), pivot=wrist))
        tl.move(0.5, q)

    return obj, _pick_and_place(rig, obj, time_scale, grasp_kwargs=kwargs, start_pose=start,
                                place_pose=_pose((0.05, 0.15, 0.0)), lift=0.12, extra=swing)


def _mug_drink(rig, time_scale):
    obj = make_object("mug")
    start = _pose((0.0, 0.0, 0.0), (0, 0, np.pi))  # handle toward -X, away from the right hand
    kwargs = dict(palm_direction=(-1, 0, 0), finger_direction=(0, 1, 0), target=(0.040, 0.0, 0.055), standoff=0.001)

    def drink(tl):
        q = tl.q[-1]
        up = _lift(rig, q, offset=(-0.05, -0.12, 0.15))
        tl.move(0.8, up)
        tilt = _lift(rig, up, rotvec=(0.9, 0.0, 0.0), pivot=root_transform(rig, up)[:3, 3])
        tl.move(0.8, tilt).wait(0.4).move(0.7, up)

    return obj, _pick_and_place(rig, obj, time_scale, grasp_kwargs=kwargs, start_pose=start,
                                place_pose=_pose((-0.1, 0.05, 0.0), (0, 0, np.pi)), lift=0.08, extra=drink)


def _apple_handoff(rig, time_scale):
    obj = make_object("apple")
    start = _pose((0.0, 0.0, 0.0))
    kwargs = dict(palm_direction=(0, 0, -1), finger_direction=(0, 1, 0), target=(0.0, 0.0, 0.08), standoff=0.012,
                  required=("thumb", "index", "middle"), offsets_u=(-0.02, -0.01, 0.0), offsets_v=(-0.03, -0.02, -0.01, 0.0))
    plan = plan_grasp(rig, obj, start, **kwargs)
    tl = Timeline(rig, relaxed_pose(rig, START_ROOT), start, time_scale=time_scale)
    tl.wait(0.4).move(1.1, plan.q_pregrasp).move(0.6, plan.q_open).move(0.5, plan.q_grasp).attach().wait(0.2)
    q_up = _lift(rig, plan.q_grasp, offset=(0, 0, 0.12))
    q_out = _lift(rig, q_up, offset=(0.0, 0.18, 0.10), rotvec=(0.0, 0.0, 0.0))
    tl.move(0.9, q_up).move(1.2, q_out).wait(0.5).detach()
    # The receiver holds the apple while the hand lets go, then carries it off and puts it
    # down far across the table while the hand withdraws.
    q_release = q_out.copy()
    q_release[6:] = plan.q_open[6:]
    tl.move(0.5, q_release)
    backed = _lift(rig, q_release, offset=(0.0, -0.06, 0.02))
    tl.move(0.4, backed)
    q_back = _lift(rig, backed, offset=(0.05, -0.20, -0.07))
    tl.move(1.5, q_back, object_target=_pose((0.05, 0.40, 0.0), (0, 0, 0.8))).wait(0.4)
    return obj, tl


#: name -> (object, motion description, builder)
DEMO_CLIPS: dict[str, tuple[str, str, Callable]] = {
    "bottle_pick_place": ("bottle", "pick up and place", _bottle_pick_place),
    "apple_rotate": ("apple", "in-hand rotation", _apple_rotate),
    "box_pinch": ("box", "pinch", _box_pinch),
    "hammer_power": ("hammer", "power grasp and swing", _hammer_power),
    "mug_drink": ("mug", "lift, drink and place", _mug_drink),
    "apple_handoff": ("apple", "handoff", _apple_handoff),
}


# ---- contacts and assembly ----------------------------------------------------------------
def _corner_reach(vertices: np.ndarray, faces: np.ndarray) -> float:
    """The largest distance (metres) from a point of a triangle of (vertices (V, 3), faces
    (F, 3)) to that triangle's nearest corner: at most the circumradius and the longest edge."""
    corners = vertices[faces]
    edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2)  # (F, 3)
    doubled_area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    longest = edges.max(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        circumradius = np.where(doubled_area > 0, edges.prod(axis=1) / (2.0 * doubled_area), np.inf)
    return float(np.minimum(circumradius, longest).max(initial=0.0))


def label_contacts(rig: Rig, hand_vertices: np.ndarray, object_vertices: np.ndarray, object_poses: np.ndarray,
                   threshold: float = CONTACT_THRESHOLD) -> np.ndarray:
    """GRAB-style labels (T, Vo): an object vertex is in contact when it lies within
    ``threshold`` (metres) of the hand surface; its code is the GRAB code of the joint that owns
    the nearest hand triangle's first vertex. ``hand_vertices`` (T, Vh, 3), ``object_vertices``
    (Vo, 3) in the object's frame, ``object_poses`` (T, 4, 4)."""
    faces = np.ascontiguousarray(rig.surface.faces, dtype=np.int64)
    owner = rig.surface.dense_weights(rig.n_joints).argmax(axis=1)
    codes = np.array([contact_code(name) for name in rig.joint_names], dtype=np.uint8)
    labels = np.zeros((len(hand_vertices), len(object_vertices)), dtype=np.uint8)
    for f in range(len(hand_vertices)):
        hand = np.asarray(hand_vertices[f], dtype=np.float64)
        world = object_vertices @ object_poses[f][:3, :3].T + object_poses[f][:3, 3]
        lo, hi = hand.min(axis=0) - threshold, hand.max(axis=0) + threshold
        near = np.nonzero(np.all((world >= lo) & (world <= hi), axis=1))[0]
        if len(near) == 0:
            continue
        # Every point of a triangle lies within its circumradius (and its longest edge) of a
        # corner, so only object vertices within threshold + the largest such reach of a hand
        # vertex can be within threshold of the surface: only those are measured against the
        # whole surface (the same nearest triangle as measuring all, about 1/10 of the queries)
        reach = _corner_reach(hand, faces)
        gap, _ = cKDTree(hand).query(world[near], distance_upper_bound=threshold + reach)
        near = near[np.isfinite(gap)]
        if len(near) == 0:
            continue
        # a tree built here and queried: point_mesh_squared_distance costs 2-3x the build alone
        surface = igl.AABB()
        surface.init(hand, faces)
        d2, face, _ = surface.squared_distance(hand, faces, np.ascontiguousarray(world[near]))
        hit = d2 <= threshold * threshold
        labels[f, near[hit]] = codes[owner[faces[np.asarray(face)[hit], 0]]]
    return labels


def build_demo_timeline(name: str, *, time_scale: float = 1.0, rig: Rig | None = None) -> tuple[DemoObject, Timeline]:
    """The object and the frame-by-frame timeline of one demo clip (see DEMO_CLIPS)."""
    if name not in DEMO_CLIPS:
        raise KeyError(f"unknown demo clip {name!r}; known: {', '.join(DEMO_CLIPS)}")
    return DEMO_CLIPS[name][2](rig or source_rig(), time_scale)


def clip_from_timeline(name: str, obj: DemoObject, timeline: Timeline, rig: Rig, resolution: float) -> Clip:
    """Skin the hand along the timeline, label contacts and assemble the clip."""
    object_name, motion, _ = DEMO_CLIPS[name]
    q = np.array(timeline.q)
    poses = np.array(timeline.objects)
    kin = rig.kinematics()
    hand = np.stack([kin.skin(qq) for qq in q]).astype(np.float32)
    labels = label_contacts(rig, hand, obj.vertices, poses)
    names, marker_faces, marker_bary = source_markers(rig)
    table_pose = np.eye(4)
    table_pose[:3, 3] = TABLE_CENTER
    clip = Clip(
        fps=timeline.fps,
        hand_faces=rig.surface.faces,
        hand_vertices=hand,
        object_vertices=obj.vertices,
        object_faces=obj.faces,
        object_poses=poses,
        contact_labels=labels,
        table_pose=table_pose,
        table_half_extents=TABLE_HALF_EXTENTS.copy(),
        marker_names=names,
        marker_faces=marker_faces,
        marker_barycentric=marker_bary,
        dof_names=rig.dof_names,
        dof_values=q,
        source_rig=f"demo:source_human@{resolution:g}",
        object_name=object_name,
        motion=motion,
        source=f"demo:{name}",
    )
    clip.validate(source=f"demo clip {name!r}")
    return clip


#: Clips generated in this process, most recent last: the same clip asked again (a test suite
#: asks for the bottle clip dozens of times; a grasp search costs 5-15 s a clip) is a copy.
#: Generation is deterministic, so a copy is what generating again would give.
_GENERATED: OrderedDict[tuple, Clip] = OrderedDict()
GENERATED_CACHE_SIZE = 6


def make_demo_clip(name: str, *, time_scale: float = 1.0, resolution: float = SOURCE_RESOLUTION,
                   rig: Rig | None = None) -> Clip:
    """Generate one demo clip by name (see DEMO_CLIPS). ``time_scale`` < 1 makes it shorter
    (tests); at 1 every clip has 600 to 1200 frames at 120 fps. ``rig`` must be the source rig
    at ``resolution`` when given (it saves rebuilding it)."""
    rig = rig or source_rig(resolution)
    from ..inputs import content_sha256  # here: inputs reads clips

    # keyed on the rig's content, not its name: another rig with the same name is another clip
    key = (name, float(time_scale), float(resolution),
           content_sha256((rig.surface.vertices, rig.surface.faces, rig.dof_names, rig.rest_pose, rig.lower, rig.upper)))
    clip = _GENERATED.get(key)
    if clip is None:
        obj, timeline = build_demo_timeline(name, time_scale=time_scale, rig=rig)
        clip = clip_from_timeline(name, obj, timeline, rig, resolution)
        _GENERATED[key] = clip
        while len(_GENERATED) > GENERATED_CACHE_SIZE:
            _GENERATED.popitem(last=False)
    _GENERATED.move_to_end(key)
    return copy.deepcopy(clip)  # the caller's own: nothing it changes reaches the cache


def grasp_window(clip: Clip, n_frames: int = 120) -> Clip:
    """``n_frames`` consecutive frames of ``clip`` starting half of them before its first
    contact (reach, grasp, lift at the clip's own speed): the demo's and the tests' retarget
    input. A clip shortened with ``time_scale`` < 1 moves faster than the acceleration
    threshold E_acc allows, a window of a natural-speed clip does not."""
    first = int(np.argmax((clip.contact_labels > 0).any(axis=1)))
    start = max(0, min(first - n_frames // 2, clip.n_frames - n_frames))
    return clip.slice(start, start + n_frames)
