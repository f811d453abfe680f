"""Foreign hands: test fixtures that disguise the demo hands the way real rigs differ, with ground truth.

Every builder is a pure function ``(rig, truth, ...) -> (rig, truth)`` returning a NEW valid rig
(``rig.validate()`` passes) and the truth carried through the change, so they compose:

    rig, truth = foreign_demo("source_human")            # demo hand + its truth
    rig, truth = rename(*reroll(rig, truth, 90), "mixamo")
    rig, truth = mirror(*move(rig, truth, transform))

What a hand model must recover is in :class:`Truth`: which joints form which finger, the palm
joint, the handedness and, per joint, the world direction of the palmar side of its segment.
The disguises never change what the hand IS (its skeleton geometry and surface), only how it
is written down (names, joint order, bone rolls, where a hinge sits on its axis, world
placement, mirror image, bind pose, extra metacarpal joints, DOFs), except :func:`drop_fingers`
which rebuilds a hand with fewer fingers and :func:`strip_dofs` which removes every DOF but the
free root's.

Conventions (see ``retarget_core.rig.model``): joint local = rest_local @ A_1(q_1) @ ...,
world G_j = G_parent @ local_j, surfaces authored at the bind pose q = rest. The free root
(joint 0, DOFs root_tx..root_rz about world axes, identity rest) is kept as the standard free
root in every variant (its DOF names too), because the pipeline relies on it
(``anatomy.set_root_transform``).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field, replace

import numpy as np

from retarget_core.rig.demo_hands import DEMO_HANDS
from retarget_core.rig.handgen import build_hand
from retarget_core.rig.model import Dof, Joint, Rig, SkinnedMesh

FINGERS = ("thumb", "index", "middle", "ring", "pinky")

__all__ = [
    "FINGERS", "Truth", "truth_of", "foreign_demo", "demo_variant_spec", "variant_q", "posed_vertices",
    "rename", "reroll", "move", "mirror", "drop_fingers", "insert_metacarpals", "bake_pose",
    "curl_at_rest", "rotate_thumb_at_rest", "strip_dofs", "rot_x", "rot_y", "rot_z", "rigid",
]


# ---- small geometry helpers ---------------------------------------------------------------------
def rot_x(deg: float) -> np.ndarray:
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], float)


def rot_y(deg: float) -> np.ndarray:
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], float)


def rot_z(deg: float) -> np.ndarray:
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], float)


def rigid(rotation=None, translation=None) -> np.ndarray:
    """(4, 4) transform from a (3, 3) rotation and a (3,) translation."""
    m = np.eye(4)
    if rotation is not None:
        m[:3, :3] = rotation
    if translation is not None:
        m[:3, 3] = translation
    return m


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


# ---- truth ---------------------------------------------------------------------------------------
@dataclass
class Truth:
    """Ground truth of a (variant) hand.

    fingers: canonical finger name -> variant joint names of its articulated joints, knuckle
    (MCP / thumb CMC) first, distal last; metacarpal joints are not included.
    palm: variant name of the palm joint (where the finger chains branch).
    handedness: "right" or "left".
    palmar: variant joint name -> (3,) unit world direction at the bind pose pointing to the
    palmar side of that joint's segment (the original joint's bind -Z carried through every change).
    original: variant joint name -> original (demo) joint name; inserted joints (metacarpals) are
    absent.
    dof_original: variant DOF name -> (original DOF name, scale, offset): the variant's DOF value
    is ``scale * q_original + offset`` for the same motion (see :func:`variant_q`).
    metacarpals: canonical finger name -> variant name of its inserted metacarpal joint.
    to_variant: (4, 4) map from the original hand's world to the variant's world at rest (the
    product of :func:`move` transforms and :func:`mirror` reflections; bind-pose bakes are not
    in it).
    stripped_dofs: the DOFs :func:`strip_dofs` removed (deep copies, as they were).
    palm_origin: (3,) world position of the physical wrist end of the palm at the bind pose
    (the demo palm joint's origin, carried through moves and mirrors). It differs from the
    palm joint's position when the palm joint is the free root and the hand was moved: the
    root stays at the world origin (identity rest) while the hand goes elsewhere.
    source: the demo hand's name; steps: the variants applied, in order.
    """

    fingers: dict[str, list[str]]
    palm: str
    handedness: str
    palmar: dict[str, np.ndarray]
    original: dict[str, str]
    dof_original: dict[str, tuple[str, float, float]] = field(default_factory=dict)
    metacarpals: dict[str, str] = field(default_factory=dict)
    to_variant: np.ndarray = field(default_factory=lambda: np.eye(4))
    stripped_dofs: list[Dof] = field(default_factory=list)
    palm_origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    source: str = ""
    steps: list[str] = field(default_factory=list)

    def finger_of(self, joint: str) -> str | None:
        """Canonical finger of a variant joint (None for the palm, root and metacarpals)."""
        for name, joints in self.fingers.items():
            if joint in joints:
                return name
        return None

    def copy(self) -> "Truth":
        return copy.deepcopy(self)


def truth_of(rig: Rig) -> Truth:
    """Truth of an unmodified demo hand: fingers by the demo naming ``<finger><k>``, the palm is
    'wrist' (joint 0 when there is none), palmar = -Z column of each joint's bind frame."""
    names = rig.joint_names
    fingers = {}
    for f in FINGERS:
        chain = []
        k = 1
        while f"{f}{k}" in names:
            chain.append(f"{f}{k}")
            k += 1
        if chain:
            fingers[f] = chain
    bind = rig.kinematics().bind_world
    palmar = {n: _unit(-bind[i][:3, 2]) for i, n in enumerate(names)}
    return Truth(
        fingers=fingers,
        palm="wrist" if "wrist" in names else names[0],
        handedness="right",
        palmar=palmar,
        original={n: n for n in names},
        dof_original={d.name: (d.name, 1.0, 0.0) for d in rig.dofs},
        palm_origin=bind[names.index("wrist") if "wrist" in names else 0][:3, 3].copy(),
        source=rig.name,
    )


def demo_variant_spec(name: str, resolution: float = 0.005, drop=()):
    """The HandSpec of demo hand ``name`` without the fingers named in ``drop``."""
    factory, _ = DEMO_HANDS[name]
    spec = factory(resolution=resolution)
    drop = set(drop)
    unknown = drop - {f.name for f in spec.fingers}
    if unknown:
        raise KeyError(f"demo hand {name!r} has no finger(s) {sorted(unknown)}")
    return replace(spec, fingers=tuple(f for f in spec.fingers if f.name not in drop))


def foreign_demo(name: str, resolution: float = 0.005, drop=()) -> tuple[Rig, Truth]:
    """A demo hand (optionally without some fingers) and its truth; the starting point of every variant."""
    rig = build_hand(demo_variant_spec(name, resolution, drop))
    rig.metadata["fixture_resolution"] = resolution
    truth = truth_of(rig)
    if drop:
        truth.steps.append(f"drop_fingers({','.join(sorted(drop))})")
    return rig, truth


# ---- rebuilding rigs ------------------------------------------------------------------------------
def _copy_dof(d: Dof, **changes) -> Dof:
    fields = dict(name=d.name, joint=d.joint, kind=d.kind, axis=np.array(d.axis, float), lower=float(d.lower),
                  upper=float(d.upper), rest=float(d.rest))
    fields.update(changes)
    return Dof(**fields)


def _copy_mesh(m: SkinnedMesh | None, vertices=None, faces=None, joint_indices=None) -> SkinnedMesh | None:
    if m is None:
        return None
    return SkinnedMesh(
        np.array(m.vertices if vertices is None else vertices, float),
        np.array(m.faces if faces is None else faces),
        np.array(m.joint_indices if joint_indices is None else joint_indices),
        np.array(m.joint_weights),
    )


def _new_rig(rig: Rig, joints, dofs, surface, visual="same", step="") -> Rig:
    out = Rig(
        name=rig.name,
        joints=joints,
        dofs=dofs,
        surface=surface,
        visual=_copy_mesh(rig.visual) if isinstance(visual, str) else visual,
        metadata={**copy.deepcopy(rig.metadata)},
    )
    if step:
        out.metadata["foreign_steps"] = list(rig.metadata.get("foreign_steps", [])) + [step]
    out.validate(source=f"foreign hand {rig.name!r} after {step or 'a change'}")
    return out


def _reorder(rig: Rig, order: list[int], step: str) -> Rig:
    """The same rig with its joints in ``order`` (old indices; parents must come first) and its
    DOFs regrouped joint by joint (their order within a joint kept)."""
    new_of = np.empty(len(order), dtype=np.int64)
    new_of[np.asarray(order)] = np.arange(len(order))
    joints = []
    for old in order:
        j = rig.joints[old]
        parent = -1 if j.parent < 0 else int(new_of[j.parent])
        joints.append(Joint(j.name, parent, np.array(j.rest_local, float)))
    dofs = []
    for old in order:
        dofs += [_copy_dof(d, joint=int(new_of[old])) for d in rig.dofs if d.joint == old]
    surface = _copy_mesh(rig.surface, joint_indices=new_of[rig.surface.joint_indices])
    visual = None if rig.visual is None else _copy_mesh(rig.visual, joint_indices=new_of[rig.visual.joint_indices])
    return _new_rig(rig, joints, dofs, surface, visual, step)


def posed_vertices(rig: Rig, q, mesh: str = "surface") -> np.ndarray:
    """(V, 3) vertices of ``mesh`` posed at q."""
    return rig.kinematics().skin(np.asarray(q, float), mesh)


def variant_q(original: Rig, variant: Rig, truth: Truth, q_original) -> np.ndarray:
    """The variant's DOF vector for the original's ``q_original`` (DOFs the variant added, e.g.
    metacarpal flexion, get their rest value)."""
    q_original = np.asarray(q_original, float)
    q = variant.rest_pose.copy()
    for i, d in enumerate(variant.dofs):
        if d.name in truth.dof_original:
            name, scale, offset = truth.dof_original[d.name]
            q[i] = scale * q_original[original.dof_index(name)] + offset
    return q


# ---- 1. rename ------------------------------------------------------------------------------------
_RIGIFY_FINGER = {"thumb": "thumb", "index": "f_index", "middle": "f_middle", "ring": "f_ring", "pinky": "f_pinky"}
_RIGIFY_PALM = {"index": "palm.01", "middle": "palm.02", "ring": "palm.03", "pinky": "palm.04"}


def _style_name(style: str, side: str, finger: str | None, k: int | None, role: str) -> str:
    """A joint name in ``style``; role: 'finger' (k-th joint from 1), 'metacarpal', 'palm', 'root'."""
    r = side == "right"
    if style == "rigify":
        s = ".R" if r else ".L"
        if role == "finger":
            return f"{_RIGIFY_FINGER[finger]}.{k:02d}{s}"
        if role == "metacarpal":
            return f"{_RIGIFY_PALM.get(finger, 'palm.' + finger)}{s}"
        return ("hand" if role == "palm" else "forearm") + s
    if style == "mixamo":
        s = "Right" if r else "Left"
        if role == "finger":
            return f"{s}Hand{finger.capitalize()}{k}"
        if role == "metacarpal":
            return f"{s}Hand{finger.capitalize()}0"
        return f"{s}Hand" if role == "palm" else f"{s}ForeArm"
    if style == "unreal":
        s = "r" if r else "l"
        if role == "finger":
            return f"{finger}_{k:02d}_{s}"
        if role == "metacarpal":
            return f"{finger}_metacarpal_{s}"
        return f"hand_{s}" if role == "palm" else f"lowerarm_{s}"
    raise ValueError(f"unknown style {style!r}")


def rename(rig: Rig, truth: Truth, style: str, seed: int = 0) -> tuple[Rig, Truth]:
    """Rename joints (and their DOFs) in ``style``: "rigify" (f_index.01.R, thumb.01.R, hand.R,
    palm.01.R), "mixamo" (RightHandIndex1, RightHand), "unreal" (index_01_r, hand_r) or "ids"
    (meaningless j07 / d13 names, joints shuffled with ``seed`` keeping parents first). DOF
    names become ``<new joint>_<old suffix>`` (named styles) or meaningless (ids); the free
    root's DOFs keep their standard names."""
    n = rig.n_joints
    if style == "ids":
        rng = np.random.default_rng(seed)
        placed, order = {0}, [0]
        children = {i: [c for c in range(n) if rig.joints[c].parent == i] for i in range(n)}
        available = list(children[0])
        while available:
            pick = available.pop(int(rng.integers(len(available))))
            order.append(pick)
            placed.add(pick)
            available += children[pick]
        rig = _reorder(rig, order, "")
        labels = rng.permutation(n)
        new_names = {j.name: f"j{int(labels[i]):02d}" for i, j in enumerate(rig.joints)}
    else:
        new_names = {}
        for i, j in enumerate(rig.joints):
            finger = truth.finger_of(j.name)
            if finger is not None:
                name = _style_name(style, truth.handedness, finger, truth.fingers[finger].index(j.name) + 1, "finger")
            elif j.name in truth.metacarpals.values():
                f = next(f for f, m in truth.metacarpals.items() if m == j.name)
                name = _style_name(style, truth.handedness, f, None, "metacarpal")
            elif j.name == truth.palm:
                name = _style_name(style, truth.handedness, None, None, "palm")
            elif i == 0:
                name = _style_name(style, truth.handedness, None, None, "root")
            else:
                name = f"{style}_extra_{i:02d}"
            new_names[j.name] = name
    joints = [Joint(new_names[j.name], j.parent, np.array(j.rest_local, float)) for j in rig.joints]
    dofs, dof_names = [], {}
    if style == "ids":
        labels = np.random.default_rng(seed + 1).permutation(rig.n_dofs)
    for i, d in enumerate(rig.dofs):
        if d.joint == 0:
            new = d.name
        elif style == "ids":
            new = f"d{int(labels[i]):02d}"
        else:
            old_joint = rig.joints[d.joint].name
            suffix = d.name[len(old_joint) + 1:] if d.name.startswith(old_joint + "_") else d.name
            new = f"{new_names[old_joint]}_{suffix}"
        dof_names[d.name] = new
        dofs.append(_copy_dof(d, name=new))
    out = _new_rig(rig, joints, dofs, _copy_mesh(rig.surface), step=f"rename({style})")
    t = truth.copy()
    t.fingers = {f: [new_names[j] for j in js] for f, js in truth.fingers.items()}
    t.palm = new_names[truth.palm]
    t.palmar = {new_names[k]: v.copy() for k, v in truth.palmar.items()}
    t.original = {new_names[k]: v for k, v in truth.original.items()}
    t.metacarpals = {f: new_names[m] for f, m in truth.metacarpals.items()}
    t.dof_original = {dof_names[k]: v for k, v in truth.dof_original.items()}
    t.steps.append(f"rename({style})")
    return out, t


# ---- 2. reroll ------------------------------------------------------------------------------------
def reroll(rig: Rig, truth: Truth, degrees: float, joints=None) -> tuple[Rig, Truth]:
    """Rotate each chosen joint's frame about its own bone (local Y) by ``degrees`` without
    changing the kinematics: rest_local' = R_parent^T rest_local R, DOF axes R^T a. Default:
    every non-root joint. The surface and every posed surface are unchanged."""
    chosen = set(range(1, rig.n_joints)) if joints is None else {rig.joint_index(n) for n in joints}
    r = rigid(rot_y(degrees))
    rolls = [r if i in chosen else np.eye(4) for i in range(rig.n_joints)]
    new_joints = []
    for i, j in enumerate(rig.joints):
        left = np.eye(4) if j.parent < 0 else rolls[j.parent].T
        new_joints.append(Joint(j.name, j.parent, left @ j.rest_local @ rolls[i]))
    dofs = [_copy_dof(d, axis=rolls[d.joint][:3, :3].T @ d.axis) for d in rig.dofs]
    out = _new_rig(rig, new_joints, dofs, _copy_mesh(rig.surface), step=f"reroll({degrees})")
    t = truth.copy()
    t.steps.append(f"reroll({degrees})")
    return out, t


def slide_hinges(rig: Rig, truth: Truth, offsets: dict[str, float]) -> tuple[Rig, Truth]:
    """Each named joint (one rotate DOF) moved ``offsets[name]`` metres along its own hinge
    axis without changing the kinematics, as a robot file places a joint wherever on its motor's
    axis the maker chose (the LEAP hand's sit 11-15 mm to the side of the finger's middle):
    rest_local' = rest_local T(s a), each child's rest_local' = T(-s a) rest_local. A rotation
    about a fixes a, so every posed joint frame below and every posed surface are unchanged."""
    slide = {}
    for name, s in offsets.items():
        j = rig.joint_index(name)
        dofs = [d for d in rig.dofs if d.joint == j]
        if len(dofs) != 1 or dofs[0].kind != "rotate":
            raise ValueError(f"{name}: slide_hinges needs a joint with one rotate DOF")
        slide[j] = float(s) * np.asarray(dofs[0].axis, float)
    joints = []
    for i, j in enumerate(rig.joints):
        local = np.array(j.rest_local, float)
        if i in slide:
            local = local @ rigid(translation=slide[i])
        if j.parent in slide:
            local = rigid(translation=-slide[j.parent]) @ local
        joints.append(Joint(j.name, j.parent, local))
    out = _new_rig(rig, joints, [_copy_dof(d) for d in rig.dofs], _copy_mesh(rig.surface), step="slide_hinges")
    t = truth.copy()
    t.steps.append("slide_hinges")
    return out, t


def hinge_offsets(rig, offset: float = 0.009) -> dict[str, float]:
    """Every joint of ``rig`` with one rotate DOF whose axis runs across its bone (more than
    60 degrees from the direction to its first child; a roll about the bone is left out: its
    place along the axis is where the bone starts), slid ``offset`` metres, alternating in sign."""
    world = rig.kinematics().bind_world
    out = {}
    for i, j in enumerate(rig.joints):
        dofs = [d for d in rig.dofs if d.joint == i]
        if i == 0 or [d.kind for d in dofs] != ["rotate"]:
            continue
        kids = [k for k, c in enumerate(rig.joints) if c.parent == i]
        if kids:
            bone = _unit(world[kids[0]][:3, 3] - world[i][:3, 3])
            if abs(float(bone @ (world[i][:3, :3] @ dofs[0].axis))) > 0.5:
                continue
        out[j.name] = offset * (-1) ** len(out)
    return out


# ---- 3. move --------------------------------------------------------------------------------------
def move(rig: Rig, truth: Truth, transform: np.ndarray) -> tuple[Rig, Truth]:
    """The whole hand rigidly moved by ``transform`` (4, 4) at rest: the root keeps its identity
    rest (the free root's), the transform goes into the root's children's rest_local, and
    surface (and visual) vertices are transformed. With the root DOFs at rest every pose of the
    result is ``transform`` applied to the original's."""
    transform = np.asarray(transform, float)
    rot = transform[:3, :3]
    if np.abs(rot.T @ rot - np.eye(3)).max() > 1e-9 or np.linalg.det(rot) < 0:
        raise ValueError("move needs a rigid transform (use mirror for reflections)")
    joints = [Joint(j.name, j.parent, transform @ j.rest_local if j.parent == 0 else np.array(j.rest_local, float))
              for j in rig.joints]

    def moved(m):
        if m is None:
            return None
        return _copy_mesh(m, vertices=m.vertices @ rot.T + transform[:3, 3])

    out = _new_rig(rig, joints, [_copy_dof(d) for d in rig.dofs], moved(rig.surface), moved(rig.visual), step="move")
    t = truth.copy()
    t.palmar = {k: rot @ v for k, v in truth.palmar.items()}
    t.to_variant = transform @ truth.to_variant
    t.palm_origin = rot @ truth.palm_origin + transform[:3, 3]
    t.steps.append("move")
    return out, t


# ---- 4. mirror ------------------------------------------------------------------------------------
_FLIP = np.diag([-1.0, 1.0, 1.0, 1.0])


def mirror(rig: Rig, truth: Truth) -> tuple[Rig, Truth]:
    """The mirror image (X -> -X): a right hand becomes a left one. Joint world frames F become
    M F D (M = D = diag(-1, 1, 1), so every rotation stays proper), i.e. rest_local' = D
    rest_local D; rotation axes a -> -D a, translation axes a -> D a, limits unchanged; vertices
    reflected and faces re-wound so normals still point outward.

    The free root keeps its world-axis DOFs, so its coordinates change sign where the mirror
    flips them: root_tx, root_ry and root_rz (recorded in ``truth.dof_original``). With that,
    posing the mirror at the mapped q equals mirroring the original posed at q."""
    d3 = _FLIP[:3, :3]
    joints = [Joint(j.name, j.parent, _FLIP @ j.rest_local @ _FLIP) for j in rig.joints]
    dofs, signs = [], {}
    for d in rig.dofs:
        a = np.asarray(d.axis, float)
        mirrored = -d3 @ a if d.kind == "rotate" else d3 @ a
        if d.joint == 0:
            s = float(mirrored @ a)
            if abs(abs(s) - 1) > 1e-9:
                raise ValueError(f"root DOF {d.name!r} is not along a mirror-symmetric axis")
            lo, hi, rest = (d.lower, d.upper, d.rest) if s > 0 else (-d.upper, -d.lower, -d.rest)
            dofs.append(_copy_dof(d, lower=lo, upper=hi, rest=rest))
            signs[d.name] = 1.0 if s > 0 else -1.0
        else:
            dofs.append(_copy_dof(d, axis=mirrored))

    def mirrored_mesh(m):
        if m is None:
            return None
        return _copy_mesh(m, vertices=m.vertices * np.array([-1.0, 1.0, 1.0]), faces=m.faces[:, [0, 2, 1]])

    out = _new_rig(rig, joints, dofs, mirrored_mesh(rig.surface), mirrored_mesh(rig.visual), step="mirror")
    t = truth.copy()
    t.handedness = "left" if truth.handedness == "right" else "right"
    t.palmar = {k: d3 @ v for k, v in truth.palmar.items()}
    t.to_variant = _FLIP @ truth.to_variant
    t.palm_origin = d3 @ truth.palm_origin
    for name, (orig, scale, offset) in truth.dof_original.items():
        s = signs.get(name, 1.0)
        t.dof_original[name] = (orig, s * scale, s * offset)
    t.steps.append("mirror")
    return out, t


# ---- 5. drop fingers -------------------------------------------------------------------------------
def drop_fingers(rig: Rig, truth: Truth, names) -> tuple[Rig, Truth]:
    """The same demo hand rebuilt without the fingers ``names`` (a closed surface needs a
    rebuild, not deleted faces): only for an unmodified hand from :func:`foreign_demo`; apply
    the other variants afterwards."""
    if truth.steps or "fixture_resolution" not in rig.metadata:
        raise ValueError("drop_fingers rebuilds the hand from its spec: apply it first, to a hand from foreign_demo")
    drop = tuple(sorted(set(names)))
    if not set(drop) <= set(truth.fingers):
        raise KeyError(f"hand has no finger(s) {sorted(set(drop) - set(truth.fingers))}")
    return foreign_demo(truth.source, rig.metadata["fixture_resolution"], drop)


# ---- 6. metacarpals --------------------------------------------------------------------------------
def _segment_distance(points, a, b):
    ab = b - a
    t = (points - a) @ ab / (ab @ ab)
    closest = a + np.clip(t, 0.0, 1.0)[:, None] * ab
    return np.linalg.norm(points - closest, axis=1), t


def insert_metacarpals(rig: Rig, truth: Truth, fraction: float = 0.2, flex_deg: float | None = 5.0,
                       prefix: str = "metacarpal_") -> tuple[Rig, Truth]:
    """Insert a joint between the palm joint and each non-thumb finger's knuckle, ``fraction``
    of the way from the palm's wrist end (``truth.palm_origin``, the palm joint's origin
    unless a root palm was moved) to the knuckle, its bone (Y) pointing at the knuckle and its
    -Z to the knuckle's palmar side; the knuckle becomes its child with unchanged world frames.
    Each metacarpal gets one flex DOF of +-``flex_deg`` (None: no DOF). The palm's skin weight
    of vertices nearest each metacarpal bone (past its start) moves onto that metacarpal, so at
    metacarpal DOFs 0 every pose is the original's. The thumb stays a child of the palm joint."""
    kin = rig.kinematics()
    bind = kin.bind_world
    palm = rig.joint_index(truth.palm)
    inserts = {}  # knuckle index -> (finger, metacarpal world frame at bind)
    for finger, chain in truth.fingers.items():
        if finger == "thumb":
            continue
        k = rig.joint_index(chain[0])
        if rig.joints[k].parent != palm:
            raise ValueError(f"{finger} does not hang off the palm joint")
        start, end = truth.palm_origin, bind[k][:3, 3]
        y = _unit(end - start)
        p = truth.palmar[chain[0]]
        z = -_unit(p - (p @ y) * y)
        frame = rigid(np.column_stack([np.cross(y, z), y, z]), start + fraction * (end - start))
        inserts[k] = (finger, frame)
    if not inserts:
        raise ValueError("hand has no non-thumb finger")

    joints, dofs, new_of, meta = [], [], {}, {}
    names = set(rig.joint_names)
    for i, j in enumerate(rig.joints):
        if i in inserts:
            finger, frame = inserts[i]
            name = prefix + finger
            while name in names:
                name += "_"
            names.add(name)
            # The palm's world at bind (its DOFs at rest) is bind[palm]; the metacarpal's DOFs rest at 0.
            joints.append(Joint(name, new_of[palm], np.linalg.inv(bind[palm]) @ frame))
            m = len(joints) - 1
            meta[finger] = (m, name, frame)
            if flex_deg is not None:
                lim = float(np.radians(flex_deg))
                dofs.append(Dof(f"{name}_flex", m, "rotate", np.array([-1.0, 0.0, 0.0]), -lim, lim, 0.0))
            rest_local = np.linalg.inv(frame) @ bind[palm] @ j.rest_local
            parent = m
        else:
            rest_local = np.array(j.rest_local, float)
            parent = -1 if j.parent < 0 else new_of[j.parent]
        joints.append(Joint(j.name, parent, rest_local))
        new_of[i] = len(joints) - 1
        dofs += [_copy_dof(d, joint=new_of[i]) for d in rig.dofs if d.joint == i]

    remap = np.array([new_of[i] for i in range(rig.n_joints)])

    def reskinned(mesh):
        if mesh is None:
            return None
        ji = remap[mesh.joint_indices]
        v = mesh.vertices
        dist = []
        params = []
        for finger, (m, _, frame) in meta.items():
            knuckle = bind[rig.joint_index(truth.fingers[finger][0])][:3, 3]
            dd, tt = _segment_distance(v, frame[:3, 3], knuckle)
            dist.append(dd)
            params.append(tt)
        dist, params = np.stack(dist, axis=1), np.stack(params, axis=1)
        nearest = np.argmin(dist, axis=1)
        past_start = params[np.arange(len(v)), nearest] >= 0.0
        targets = np.array([meta[f][0] for f in meta])[nearest]
        slot = (ji == new_of[palm]) & past_start[:, None]
        ji = np.where(slot, targets[:, None], ji)
        return SkinnedMesh(v.copy(), mesh.faces.copy(), ji, mesh.joint_weights.copy())

    out = _new_rig(rig, joints, dofs, reskinned(rig.surface), reskinned(rig.visual), step="insert_metacarpals")
    t = truth.copy()
    for finger, (m, name, frame) in meta.items():
        t.metacarpals[finger] = name
        t.palmar[name] = -frame[:3, 2]
    t.steps.append("insert_metacarpals")
    return out, t


# ---- 7./8. bind-pose bakes -------------------------------------------------------------------------
def bake_pose(rig: Rig, truth: Truth, offsets: dict[str, float], step: str = "bake_pose") -> tuple[Rig, Truth]:
    """Make the pose q_bind + o the new bind pose, o = ``offsets`` (DOF name -> radians or metres),
    with exactly the original kinematics: rest_local' = the joint's local transform at that
    pose, each DOF's axis re-expressed past the offsets of the later DOFs of its joint, limits
    shifted by -o and rest values kept, so the variant at q' is the original at q' + o and the
    reachable set is unchanged. The surface becomes the original's posed at q_bind + o."""
    o = np.zeros(rig.n_dofs)
    for name, value in offsets.items():
        o[rig.dof_index(name)] = value
    rest = rig.rest_pose
    target = rest + o
    if np.any(target < rig.lower - 1e-12) or np.any(target > rig.upper + 1e-12):
        raise ValueError("the baked pose lies outside the DOF limits")
    if np.any(o[[i for i, d in enumerate(rig.dofs) if d.joint == 0]] != 0):
        raise ValueError("bake_pose must not move the free root")
    kin = rig.kinematics()
    dof_a = kin._dof_transforms(o)  # A_i(o_i): the offset part of each DOF (same-axis motions compose)
    joints = []
    dofs = []
    for i, j in enumerate(rig.joints):
        mine = [k for k, d in enumerate(rig.dofs) if d.joint == i]
        local = np.array(j.rest_local, float)
        for k in mine:
            local = local @ dof_a[k]
        joints.append(Joint(j.name, j.parent, local))
        suffix = np.eye(4)
        new = {}
        for k in reversed(mine):
            d = rig.dofs[k]
            if np.abs(suffix[:3, 3]).max() > 0:
                raise ValueError(f"cannot bake a translation offset followed by DOF {d.name!r}")
            new[k] = _copy_dof(d, axis=suffix[:3, :3].T @ d.axis, lower=d.lower - o[k], upper=d.upper - o[k])
            suffix = dof_a[k] @ suffix
        dofs += [new[k] for k in mine]
    before = kin.pose(rest).world
    after = kin.pose(target).world
    surface = _copy_mesh(rig.surface, vertices=kin.skin(target, "surface"))
    visual = None if rig.visual is None else _copy_mesh(rig.visual, vertices=kin.skin(target, "visual"))
    out = _new_rig(rig, joints, dofs, surface, visual, step=step)
    t = truth.copy()
    names = rig.joint_names
    p = names.index(truth.palm)
    t.palm_origin = (after[p] @ np.linalg.inv(before[p]) @ np.append(truth.palm_origin, 1.0))[:3]
    for i, name in enumerate(names):
        if name in t.palmar:
            t.palmar[name] = _unit(after[i][:3, :3] @ before[i][:3, :3].T @ truth.palmar[name])
    for i, d in enumerate(rig.dofs):
        orig, scale, offset = truth.dof_original[d.name] if d.name in truth.dof_original else (None, 1.0, 0.0)
        if orig is not None:
            t.dof_original[d.name] = (orig, scale, offset - o[i])
    t.steps.append(step)
    return out, t


def _flex_dof_names(rig: Rig, truth: Truth, joint: str, kinds) -> list[str]:
    """Variant DOF names of ``joint`` whose original DOF is one of ``kinds`` (e.g. 'flex')."""
    i = rig.joint_index(joint)
    out = []
    for kind in kinds:
        for d in rig.dofs:
            if d.joint == i and d.name in truth.dof_original and truth.dof_original[d.name][0].endswith("_" + kind):
                out.append(d.name)
        if out:
            return out
    return out


def curl_at_rest(rig: Rig, truth: Truth, degrees: float = 30.0) -> tuple[Rig, Truth]:
    """Bake a curl into the bind pose: every non-thumb finger joint's flexion +``degrees``
    (see :func:`bake_pose`). Mirror-safe: a mirrored flexion still curls toward the palm."""
    offsets = {}
    for finger, chain in truth.fingers.items():
        if finger == "thumb":
            continue
        for joint in chain:
            for name in _flex_dof_names(rig, truth, joint, ("flex",)):
                offsets[name] = np.radians(degrees) * _orientation_sign(truth, name)
    if not offsets:
        raise ValueError("no finger flexion DOFs to curl")
    return bake_pose(rig, truth, offsets, step=f"curl_at_rest({degrees})")


def _orientation_sign(truth: Truth, dof: str) -> float:
    """+1 when the variant DOF moves like its original (scale > 0)."""
    return 1.0 if truth.dof_original[dof][1] > 0 else -1.0


def rotate_thumb_at_rest(rig: Rig, truth: Truth, degrees: float = 25.0, kinds=("twist", "abduct")) -> tuple[Rig, Truth]:
    """Bake a rotation of the thumb's base joint into the bind pose: its first DOF kind of
    ``kinds`` that it has (original DOF names) rotated by ``degrees`` (see :func:`bake_pose`)."""
    names = _flex_dof_names(rig, truth, truth.fingers["thumb"][0], kinds)
    if not names:
        raise ValueError(f"thumb base has none of the DOFs {kinds}")
    return bake_pose(rig, truth, {names[0]: np.radians(degrees) * _orientation_sign(truth, names[0])},
                     step=f"rotate_thumb_at_rest({degrees})")


# ---- 9. strip DOFs ---------------------------------------------------------------------------------
def strip_dofs(rig: Rig, truth: Truth) -> tuple[Rig, Truth]:
    """Only the free root's DOFs (joint 0) remain; joints and surface unchanged. The removed
    DOFs are kept in ``truth.stripped_dofs``."""
    kept = [_copy_dof(d) for d in rig.dofs if d.joint == 0]
    out = _new_rig(rig, [Joint(j.name, j.parent, np.array(j.rest_local, float)) for j in rig.joints], kept,
                   _copy_mesh(rig.surface), step="strip_dofs")
    t = truth.copy()
    t.stripped_dofs = [_copy_dof(d) for d in rig.dofs if d.joint != 0]
    t.dof_original = {d.name: truth.dof_original[d.name] for d in kept if d.name in truth.dof_original}
    t.steps.append("strip_dofs")
    return out, t
