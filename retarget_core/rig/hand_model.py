"""The hand model: what a rig's skeleton and skinned surface say about the hand, with joint names
used only as optional hints.

Everything is measured on the rig at its bind pose, in world coordinates (metres):

- the palm joint: the lowest common ancestor of the finger chains (a forearm, a mount or a
  camera stand above it, and surface owned by them, are not the hand);
- each finger chain, its articulations (joints at the same place, such as a robot knuckle's
  abduction and flexion links, are one articulation; a one-DOF hinge is read on the finger's
  middle, wherever on its axis the file put it: :func:`hinge_centred_positions`), its knuckle
  (leading joints that run inside the palm, such as metacarpals, are found by ray casting
  between neighbouring chains: a finger starts where the surface separates it from its
  neighbour) and its tip;
- the thumb: the chain that points away from the others (opposition), or for two chains the one
  whose base is nearer the wrist;
- the palm frame: the wrist point (proximal end of the palm surface), forward (wrist to the
  knuckles), lateral (across the knuckles, toward the thumb) and the palmar normal;
- the palmar side, decided by votes that never read a bone's local axes: the rig's flexion
  limits (fingers bend much further toward the palm than away), the curl of the fingers at
  rest, and the thumb lying in front of the palm; handedness follows from the palmar side
  and the thumb's side;
- per segment: direction, palmar direction (carried down the finger by parallel transport;
  the thumb's pad faces halfway between the palm normal and the fingers), flexion axis
  (positive rotation curls toward the palm), abduction axis, rest flexion angle, length,
  girth.

When the geometry cannot tell (no branching palm, fewer than two finger chains, no thumb that
stands out, palmar votes that disagree), :func:`hand_model` raises an InputError naming the
joints involved and the mapping file that settles it (:class:`HandMapping`)::

    {"palm": "hand_r", "handedness": "right",
     "fingers": {"thumb": ["thumb_01_r", "thumb_02_r", "thumb_03_r"],
                 "index": ["index_01_r", "index_02_r", "index_03_r"]}}
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from .model import Rig

FINGER_NAMES = ("thumb", "index", "middle", "ring", "pinky")
NON_THUMB_NAMES = FINGER_NAMES[1:]

#: Joints closer than this fraction of the hand's size are one articulation.
COINCIDENT_FRACTION = 0.01
#: Skin weight share below which a vertex counts as not carried by a joint (blended skin moves
#: when a rig is bound bent; the frames are measured on skin carried by one part alone).
MAX_FINGER_SHARE = 0.05
#: The thumb must point at least this far (degrees) from the other chains' mean direction,
#: and this much further than the next most deviating chain.
THUMB_MIN_DEVIATION_DEG = 20.0
THUMB_MARGIN_DEG = 10.0
#: A palmar decision needs a combined vote at least this strong (votes are in [-1, 1]).
PALMAR_MIN_VOTE = 0.15

#: rig metadata key of the rig's own :class:`HandMapping` (a MANO rig knows its fingers), used when
#: no mapping is given
HAND_MAPPING_METADATA = "hand_mapping"

MAPPING_HELP = (
    "settle it with a hand mapping file (JSON: {\"palm\": JOINT, \"handedness\": \"right\"|\"left\", "
    "\"fingers\": {\"thumb\": [JOINTS knuckle first], \"index\": [...], ...}}), passed as --hand-map "
    "(or --source-hand-map for the source rig)"
)

# Finger words in joint names: hints only (Rigify f_index.01.R, Mixamo RightHandIndex1,
# Unreal index_01_r, Shadow ff/mf/rf/lf/th prefixes, MANO-style names).
_HINTS = (
    ("thumb", re.compile(r"thumb|(^|[^a-z])th[^a-z]|pollex", re.I)),
    ("index", re.compile(r"index|(^|[^a-z])ff[^a-z]|pointer", re.I)),
    ("middle", re.compile(r"middle|(^|[^a-z])mf[^a-z]", re.I)),
    ("ring", re.compile(r"ring|(^|[^a-z])rf[^a-z]", re.I)),
    ("pinky", re.compile(r"pinky|pinkie|little|(^|[^a-z])lf[^a-z]", re.I)),
)


@dataclass
class HandMapping:
    """An explicit answer to what detection could not tell: the palm joint, each finger's
    articulated joints (knuckle first; metacarpals left out) and the handedness. Any field may be
    omitted; what is given wins over detection."""

    palm: str | None = None
    fingers: dict[str, list[str]] | None = None
    handedness: str | None = None

    @classmethod
    def from_dict(cls, data, *, source: str = "") -> "HandMapping":
        if not isinstance(data, dict):
            raise InputError("a hand mapping is a JSON object", source=source)
        unknown = set(data) - {"palm", "fingers", "handedness"}
        if unknown:
            raise InputError(f"unknown keys {sorted(unknown)} in a hand mapping (known: palm, fingers, handedness)",
                             source=source)
        fingers = data.get("fingers")
        if fingers is not None:
            if not isinstance(fingers, dict) or not fingers:
                raise InputError("'fingers' must map finger names to lists of joint names", source=source)
            for name, joints in fingers.items():
                if name not in FINGER_NAMES:
                    raise InputError(f"unknown finger {name!r} in a hand mapping; use {', '.join(FINGER_NAMES)}",
                                     source=source)
                if not isinstance(joints, list) or not joints or not all(isinstance(j, str) for j in joints):
                    raise InputError(f"finger {name!r}: give a non-empty list of joint names", source=source)
        handedness = data.get("handedness")
        if handedness not in (None, "right", "left"):
            raise InputError(f"handedness must be 'right' or 'left', got {handedness!r}", source=source)
        palm = data.get("palm")
        if palm is not None and not isinstance(palm, str):
            raise InputError("'palm' must be a joint name", source=source)
        return cls(palm=palm, fingers=fingers, handedness=handedness)

    def to_dict(self) -> dict:
        return {k: v for k, v in (("palm", self.palm), ("handedness", self.handedness), ("fingers", self.fingers))
                if v is not None}


def load_hand_mapping(path) -> HandMapping:
    """Read a hand mapping JSON file (see :class:`HandMapping`)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise InputError(f"cannot read the hand mapping: {exc}", source=str(path)) from None
    except json.JSONDecodeError as exc:
        raise InputError(f"the hand mapping is not valid JSON: {exc}", source=str(path)) from None
    return HandMapping.from_dict(data, source=str(path))


@dataclass
class Segment:
    """One articulation of a finger and the bone after it (to the next articulation or the tip).

    joints: the rig joints at this articulation, proximal first; start, end (3,) m; direction
    (3,) unit; palmar (3,) unit, perpendicular to direction, toward the pad; flexion_axis (3,)
    unit: a positive rotation about it curls the segment toward the palm; abduction_axis (3,)
    unit (= palmar: a rotation about it swings the segment sideways); rest_flexion: the bend
    (radians, positive toward the palm) from the previous segment (the palm's forward axis for
    a knuckle) at the bind pose."""

    joints: list[int]
    start: np.ndarray
    end: np.ndarray
    direction: np.ndarray
    palmar: np.ndarray
    flexion_axis: np.ndarray
    abduction_axis: np.ndarray
    rest_flexion: float

    @property
    def length(self) -> float:
        return float(np.linalg.norm(self.end - self.start))


@dataclass
class FingerModel:
    """One finger. joints: every articulated joint from the knuckle to the last (merged
    articulations expanded, proximal first); metacarpals: leading chain joints inside the palm;
    segments: one per articulation; tip (3,): the apex of the fingertip (a surface vertex,
    ``tip_vertex``); link_vertices: per joint in ``joints``, the surface vertices it owns (largest
    skin weight); length (m): knuckle to tip along the segments; girth (m): median distance of
    the finger's surface to its axis."""

    name: str
    joints: list[int]
    metacarpals: list[int]
    segments: list[Segment]
    tip: np.ndarray
    tip_vertex: int
    link_vertices: list[np.ndarray]
    length: float
    girth: float
    flex_dofs: list[int] = field(default_factory=list)
    abduction_dofs: list[int] = field(default_factory=list)

    @property
    def is_thumb(self) -> bool:
        return self.name == "thumb"

    @property
    def knuckle(self) -> np.ndarray:
        return self.segments[0].start

    @property
    def vertices(self) -> np.ndarray:
        return np.concatenate(self.link_vertices) if self.link_vertices else np.zeros(0, dtype=np.int64)

    def segment_of(self, joint: int) -> Segment:
        for s in self.segments:
            if joint in s.joints:
                return s
        raise KeyError(joint)


@dataclass
class HandModel:
    """What :func:`hand_model` found. fingers: thumb first (when there is one), then across the
    palm away from it; wrist (3,): the proximal end of the palm, on its mid-plane; forward,
    lateral (toward the thumb side), palmar (3,): the palm frame (orthonormal); palm_joints: the
    palm joint and any joints between it and the fingers' metacarpals; hand_vertices (V,) bool:
    vertices of the hand proper (the forearm, a mount and other parts excluded); palm_vertices:
    ids of palm-joint-owned hand vertices; excluded_joints: joints that are not the hand;
    notes: how each decision was made (for reports and error messages)."""

    rig_name: str
    palm_joint: int
    palm_joints: list[int]
    fingers: list[FingerModel]
    handedness: str
    wrist: np.ndarray
    forward: np.ndarray
    lateral: np.ndarray
    palmar: np.ndarray
    palm_length: float
    palm_width: float
    palm_thickness: float
    hand_vertices: np.ndarray
    palm_vertices: np.ndarray
    excluded_joints: list[int]
    notes: list[str] = field(default_factory=list)

    def finger(self, name: str) -> FingerModel | None:
        for f in self.fingers:
            if f.name == name:
                return f
        return None

    @property
    def finger_names(self) -> list[str]:
        return [f.name for f in self.fingers]

    def articulation_palmar(self, finger: FingerModel, k: int, follow: float = 0.5) -> np.ndarray:
        """(3,) unit: the palmar direction at the k-th articulation of ``finger``: between the
        palmar sides of the two bones it joins (segment k-1's, or the palm's for k = 0), turned
        toward the distal bone's by ``follow`` (0..1).

        Blend skinning turns the skin over a bent joint by the share of the bend its skin
        weights give the distal bone (:func:`retarget_core.rig.anatomy.articulation_sites`
        measures it), so a point straight palmar (or dorsal) of a joint along this direction is
        the same material point whether the rig was bound straight or bent. When the two sides
        are more than 120 degrees apart (a thumb whose pad faces away from the palm's side) the
        segment's own palmar direction is used."""
        own = finger.segments[k].palmar
        before = self.palmar if k == 0 else finger.segments[k - 1].palmar
        if float(np.linalg.norm(own + before)) < 1.0:
            return own
        mean = follow * own + (1.0 - follow) * before
        return mean / np.linalg.norm(mean)

    def hand_faces(self, faces: np.ndarray) -> np.ndarray:
        """Ids of the faces (F, 3) whose three vertices are all hand vertices."""
        return np.nonzero(self.hand_vertices[np.asarray(faces)].all(axis=1))[0]

    def palm_frame(self) -> np.ndarray:
        """(4, 4): origin at the wrist, columns lateral (toward the thumb), forward, dorsal."""
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = self.lateral, self.forward, -self.palmar, self.wrist
        return m

    def summary(self) -> dict:
        return {
            "palm_joint": self.palm_joint,
            "handedness": self.handedness,
            "fingers": {f.name: f.joints for f in self.fingers},
            "metacarpals": {f.name: f.metacarpals for f in self.fingers if f.metacarpals},
            "excluded_joints": self.excluded_joints,
            "notes": list(self.notes),
        }


# ---- helpers -------------------------------------------------------------------------------------
def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v)
    return v / n if n > 1e-12 else v * 0.0


def _perp(v, axis) -> np.ndarray:
    """v with its component along the unit ``axis`` removed, normalised."""
    return _unit(v - (v @ axis) * axis)


def _transport(vector: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Carry ``vector`` by the smallest rotation taking unit a to unit b."""
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(np.clip(a @ b, -1.0, 1.0))
    if s < 1e-12:
        return _perp(vector, b)
    k = axis / s
    angle = np.arctan2(s, c)
    rotated = vector * np.cos(angle) + np.cross(k, vector) * np.sin(angle) + k * (k @ vector) * (1 - np.cos(angle))
    return _perp(rotated, b)


def _distance_to_polyline(points: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    """(N,) distance of points (N, 3) to a polyline (M, 3)."""
    best = np.full(len(points), np.inf)
    for a, b in zip(polyline[:-1], polyline[1:]):
        ab = b - a
        t = np.clip((points - a) @ ab / max(ab @ ab, 1e-18), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(points - (a + t[:, None] * ab), axis=1))
    return best


def _closest_on_polyline(point: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    best, where = np.inf, polyline[0]
    for a, b in zip(polyline[:-1], polyline[1:]):
        ab = b - a
        t = float(np.clip((point - a) @ ab / max(ab @ ab, 1e-18), 0.0, 1.0))
        p = a + t * ab
        d = np.linalg.norm(point - p)
        if d < best:
            best, where = d, p
    return where


def _ambiguous(rig: Rig, what: str) -> InputError:
    return InputError(f"cannot tell {what}; {MAPPING_HELP}", source=rig.name, element="hand model")


def finger_hint(names: list[str]) -> str | None:
    """The finger a list of joint names suggests (only a hint), or None."""
    found = set()
    for finger, pattern in _HINTS:
        if any(pattern.search(f"_{n}_") for n in names):
            found.add(finger)
    return found.pop() if len(found) == 1 else None


# ---- detection -----------------------------------------------------------------------------------
@dataclass
class _Chain:
    joints: list[int]  # from the branch's child to the leaf
    groups: list[list[int]]  # articulations: coincident joints merged
    points: np.ndarray  # (A, 3) articulation positions
    tip: np.ndarray
    tip_vertex: int
    vertices: np.ndarray

    @property
    def polyline(self) -> np.ndarray:
        return np.vstack([self.points, self.tip])

    @property
    def length(self) -> float:
        return float(np.linalg.norm(np.diff(self.polyline, axis=0), axis=1).sum())


def _chain_geometry(joints: list[int], positions, weights, vertices, scale, mesh) -> _Chain | None:
    owner = weights.argmax(axis=1)
    groups: list[list[int]] = []
    for j in joints:
        if groups and np.linalg.norm(positions[j] - positions[groups[-1][0]]) <= COINCIDENT_FRACTION * scale:
            groups[-1].append(j)
        else:
            groups.append([j])
    points = np.array([positions[g[0]] for g in groups])
    owned = np.nonzero(np.isin(owner, joints))[0]
    last = np.nonzero(np.isin(owner, groups[-1]))[0]
    if len(owned) == 0 or len(last) == 0:
        return None
    # The tip: where the last link's axis (from its articulation toward its surface's centre, so
    # a curled or re-rolled finger reads the same) leaves the surface: the centre of a flat robot
    # fingertip, the apex of a round one.
    # Measured on the skin the last link carries alone (blended skin at a bent joint moves).
    alone = last[weights[last][:, groups[-1]].sum(axis=1) >= 1.0 - MAX_FINGER_SHARE]
    along = _unit(vertices[alone if len(alone) >= 3 else last].mean(axis=0) - points[-1])
    if not np.any(along) and len(points) > 1:
        along = _unit(points[-1] - points[-2])
    reach = float(np.max((vertices[last] - points[-1]) @ along))
    tip = None
    if reach > 0:
        hits, _, _ = mesh.ray.intersects_location(points[-1][None], along[None], multiple_hits=True)
        t = (hits - points[-1]) @ along if len(hits) else np.zeros(0)
        ok = (t >= 0.5 * reach) & (t <= 1.05 * reach + 1e-6)
        if ok.any():
            tip = hits[ok][np.argmax(t[ok])]
    if tip is None:
        tip = vertices[last[np.argmax((vertices[last] - points[-1]) @ along)]]
    tip_vertex = int(last[np.argmin(np.linalg.norm(vertices[last] - tip, axis=1))])
    return _Chain(joints, groups, points, np.array(tip, dtype=np.float64), tip_vertex, owned)


#: A hinge whose axis is within 60 degrees of its bone (a roll about the bone) is left where it is:
#: its place along the axis is where the bone starts.
ROLL_AXIS_COS = 0.5


def hinge_centred_positions(rig: Rig, world: np.ndarray, owner: np.ndarray) -> np.ndarray:
    """(J, 3) m: each joint's bind position, a hinge (one rotate DOF across its bone) moved
    along its own axis to the middle of the skin its link owns around the middle half of its
    bone (``owner`` (V,): each vertex's joint; the bone runs to the first child joint away
    from it, or to a leaf's skin centre).

    Where on its axis a hinge sits changes nothing in the kinematics, and robot files place it
    where the motor is: the LEAP hand's finger hinges sit 11-15 mm to the side of the finger's
    middle. Read as they are, the finger's bones, its palmar midline and its tip lean to that
    side, and the axial curves, markers and contacts with them. A skinned human hand's joints
    have two or three DOFs (none is moved on the demo human hands)."""
    bind = np.asarray(world[:, :3, 3], dtype=np.float64)
    positions = bind.copy()
    children: list[list[int]] = [[] for _ in range(rig.n_joints)]
    for j, joint in enumerate(rig.joints):
        if joint.parent >= 0:
            children[joint.parent].append(j)
    # children first: a bone runs to its child's moved position, so where the child sat on its
    # own axis does not tilt it
    for j in range(rig.n_joints - 1, 0, -1):
        dofs = [d for d in rig.dofs if d.joint == j]
        if len(dofs) != 1 or dofs[0].kind != "rotate":
            continue
        link = rig.surface.vertices[owner == j]
        if len(link) < 3:
            continue
        axis = world[j][:3, :3] @ np.asarray(dofs[0].axis, dtype=np.float64)
        axis /= np.linalg.norm(axis)
        # first the middle of all its skin along the axis: the bone from there to the child
        # (or to the skin's centre) tells a hinge across the bone from a roll about it
        along = (link - bind[j]) @ axis
        rough = bind[j] + axis * 0.5 * (along.min() + along.max())
        ends = [positions[c] - rough for c in children[j]]
        ends = [e for e in ends if np.linalg.norm(e) > 1e-9] or [link.mean(axis=0) - rough]
        raw = ends[0]
        if abs(float(raw @ axis)) > ROLL_AXIS_COS * float(np.linalg.norm(raw)):
            continue
        # the bone across the axis (the same wherever on its axis the hinge sits), and the skin
        # around its middle half: skin blended toward the neighbours at either joint would pull
        # the middle toward them
        bone = raw - (raw @ axis) * axis
        length = float(np.linalg.norm(bone))
        bone /= length
        t = (link - bind[j]) @ bone
        if not children[j]:
            length = float(t.max())
        middle = link[(t >= 0.25 * length) & (t <= 0.75 * length)]
        if len(middle) < 3:
            continue
        along = (middle - bind[j]) @ axis
        positions[j] = bind[j] + axis * 0.5 * (along.min() + along.max())
    return positions


def hand_model(rig: Rig, mapping: HandMapping | None = None) -> HandModel:
    """The hand model of ``rig`` (see the module docstring); ``mapping`` settles what detection
    cannot. Raises InputError when the rig is not a hand the model can read."""
    if mapping is None and rig.metadata.get(HAND_MAPPING_METADATA):
        mapping = HandMapping.from_dict(rig.metadata[HAND_MAPPING_METADATA], source=f"{rig.name} (its own hand mapping)")
    mapping = mapping or HandMapping()
    notes: list[str] = []
    n = rig.n_joints
    world = rig.kinematics().bind_world
    vertices = rig.surface.vertices
    weights = rig.surface.dense_weights(n)
    owner = weights.argmax(axis=1)
    positions = hinge_centred_positions(rig, world, owner)
    scale = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    parents = [j.parent for j in rig.joints]
    children: list[list[int]] = [[] for _ in range(n)]
    for j, p in enumerate(parents):
        if p >= 0:
            children[p].append(j)
    owned_count = np.bincount(owner, minlength=n)
    subtree = owned_count.astype(np.int64).copy()
    for j in range(n - 1, 0, -1):  # parents come first
        subtree[parents[j]] += subtree[j]

    mesh = _ray_mesh(rig)

    def ancestors(j):
        out = []
        while j >= 0:
            out.append(j)
            j = parents[j]
        return out

    def by_name(name, what):
        if name not in rig.joint_names:
            raise InputError(f"the hand mapping names {what} {name!r}, which the rig does not have",
                             source=rig.name, element="hand mapping")
        return rig.joint_index(name)

    # 1. Finger chains.
    if mapping.fingers:
        named = {f: [by_name(j, f"joint of {f}") for j in js] for f, js in mapping.fingers.items()}
        chains = {}
        for f, js in named.items():
            chain = _chain_geometry(js, positions, weights, vertices, scale, mesh)
            if chain is None:
                raise InputError(f"finger {f!r} of the hand mapping owns no surface", source=rig.name,
                                 element="hand mapping")
            chains[f] = chain
        chain_list = list(chains.values())
    else:
        geo_children = [[c for c in children[j] if subtree[c] > 0] for j in range(n)]
        leaves = [j for j in range(n) if subtree[j] > 0 and not geo_children[j]]
        chain_list = []
        for leaf in leaves:
            path = [leaf]
            while parents[path[-1]] >= 0 and len(geo_children[parents[path[-1]]]) == 1 and parents[parents[path[-1]]] >= 0:
                path.append(parents[path[-1]])
            path.reverse()
            # A chain that climbs to the top of the tree is the whole body, not a finger.
            if parents[path[0]] < 0:
                continue
            chain = _chain_geometry(path, positions, weights, vertices, scale, mesh)
            if chain is not None and len(chain.groups) >= 2:
                chain_list.append(chain)
        if chain_list:
            longest = max(c.length for c in chain_list)
            chain_list = [c for c in chain_list if c.length >= 0.25 * longest]
        if len(chain_list) >= 3:
            # Parts such as a camera stand branch far from the fingers: drop chains whose base is
            # further from the median base than twice the median finger length.
            bases = np.array([c.points[0] for c in chain_list])
            median = np.median(bases, axis=0)
            reach = 2.0 * float(np.median([c.length for c in chain_list]))
            kept = [c for c, b in zip(chain_list, bases) if np.linalg.norm(b - median) <= reach]
            for c in chain_list:
                if c not in kept:
                    notes.append(f"chain ending at {rig.joints[c.joints[-1]].name!r} branches far from the fingers: "
                                 "not part of the hand")
            chain_list = kept
        if len(chain_list) < 2:
            found = ", ".join(rig.joints[c.joints[-1]].name for c in chain_list) or "none"
            raise InputError(
                f"cannot find a hand: fewer than two finger chains (jointed branches that own surface) "
                f"branch from a palm (found: {found}); {MAPPING_HELP}", source=rig.name, element="hand model")

    # 2. The palm joint: where the chains branch.
    if mapping.palm is not None:
        palm_joint = by_name(mapping.palm, "palm joint")
    else:
        common = set(ancestors(parents[chain_list[0].joints[0]]))
        for c in chain_list[1:]:
            common &= set(ancestors(parents[c.joints[0]]))
        if not common:
            raise _ambiguous(rig, "the palm joint: the finger chains share no ancestor")
        palm_joint = max(common, key=lambda j: len(ancestors(j)))
    palm_joints = {palm_joint}
    for c in chain_list:
        j = parents[c.joints[0]]
        while j >= 0 and j != palm_joint and j not in palm_joints:
            palm_joints.add(j)
            j = parents[j]
    palm_pos = positions[palm_joint]

    # 3. The thumb.
    names: dict[int, str] = {}
    if mapping.fingers:
        for i, f in enumerate(chains):
            names[i] = f
        thumb = next((i for i, f in names.items() if f == "thumb"), None)
    else:
        thumb = _find_thumb(rig, chain_list, palm_pos, notes)

    # 4. Palm frame, metacarpals, palm frame again from the knuckles.
    others = [i for i in range(len(chain_list)) if i != thumb]
    starts = {i: 0 for i in range(len(chain_list))}
    frame = _palm_axes(rig, chain_list, starts, thumb, palm_pos, palm_joints, owner, vertices, first_pass=True)
    if not mapping.fingers and len(others) >= 2:
        webs = [_web_position(chain_list, i, [k for k in others if k != i], mesh, frame[0]) for i in others]
        found = [w for w in webs if w is not None]
        # One web line for the whole palm (the median), so one finger fused to its neighbour in
        # the surface does not move its own knuckle.
        web = float(np.median(found)) if found else -np.inf
        notes.append(f"the fingers separate {1000 * (web - palm_pos @ frame[0]):.0f} mm past the palm joint "
                     f"(median of {len(found)} of {len(others)} fingers)"
                     if found else "no web found between the fingers: no metacarpals stripped")
        starts.update(_metacarpal_counts(rig, chain_list, others, web, frame[0], frame[2], world, notes))
        for i in others:
            if starts[i]:
                notes.append(f"{rig.joints[chain_list[i].joints[0]].name!r}..: "
                             f"{starts[i]} joint(s) inside the palm (metacarpals)")
        frame = _palm_axes(rig, chain_list, starts, thumb, palm_pos, palm_joints, owner, vertices)
    forward, lateral, normal, centroid, palm_ids, frame_ids = frame

    # 5. The palmar side (and so the handedness).
    if mapping.handedness is not None and thumb is not None:
        sign = -1.0 if mapping.handedness == "right" else 1.0
        notes.append(f"handedness {mapping.handedness} from the hand mapping")
    else:
        sign = _palmar_sign(rig, chain_list, starts, thumb, normal, forward, centroid, world, notes)
    palmar = sign * normal
    if thumb is None:
        handedness = mapping.handedness or "unknown"
    else:
        # lateral points to the thumb; with a right hand's palm facing -Z and fingers +Y the
        # thumb is on -X = cross(forward, palmar).
        handedness = "right" if lateral @ np.cross(forward, palmar) > 0 else "left"

    # 6. Wrist point and hand vertices.
    if len(frame_ids):
        # across the palm: the middle of the whole palm (the thumb's blended base is palm too)
        across = (vertices[palm_ids].mean(axis=0) - centroid) @ lateral
        proj = (vertices[frame_ids] - centroid) @ forward
        wrist = centroid + lateral * float(across) + forward * float(np.percentile(proj, 2.0))
    else:
        wrist = palm_pos.copy()
    hand_joint_set = set(palm_joints)
    for i, c in enumerate(chain_list):
        hand_joint_set |= set(c.joints)
    hand_vertices = np.isin(owner, sorted(hand_joint_set))
    palm_owned = np.isin(owner, sorted(palm_joints))
    margin = 0.1 * float(np.linalg.norm(np.mean([c.points[starts[i]] for i, c in enumerate(chain_list)], axis=0) - wrist))
    hand_vertices &= ~(palm_owned & (((vertices - wrist) @ forward) < -margin))
    excluded = sorted(set(range(n)) - hand_joint_set)

    # 7. Names across the palm, from the thumb side.
    if not mapping.fingers:
        knuckles = {i: chain_list[i].points[starts[i]] for i in others}
        order = sorted(others, key=lambda i: -float((knuckles[i] - wrist) @ lateral))
        names = {thumb: "thumb"} if thumb is not None else {}
        names.update(_name_fingers(rig, chain_list, order, notes))

    # 8. Finger models.
    knuckle_mean = np.mean([chain_list[i].points[starts[i]] for i in others], axis=0) if others else wrist
    fingers = []
    for i, c in enumerate(chain_list):
        finger = _finger_model(rig, world, names[i], c, starts[i], palmar, forward, knuckle_mean, owner, vertices)
        finger.flex_dofs = [_dof_about(rig, world, j, finger.segment_of(j).flexion_axis) for j in finger.joints]
        finger.abduction_dofs = [_dof_about(rig, world, j, finger.segment_of(j).abduction_axis) for j in finger.joints]
        fingers.append(finger)
    fingers.sort(key=lambda f: FINGER_NAMES.index(f.name) if f.name in FINGER_NAMES else len(FINGER_NAMES))

    width_points = [f.knuckle for f in fingers if not f.is_thumb]
    palm_width = float(np.ptp([(p - wrist) @ lateral for p in width_points])) if len(width_points) > 1 else 0.0
    palm_length = float((knuckle_mean - wrist) @ forward)
    thickness = float(np.ptp((vertices[palm_ids] - centroid) @ palmar)) if len(palm_ids) else 0.0
    return HandModel(
        rig_name=rig.name, palm_joint=palm_joint, palm_joints=sorted(palm_joints), fingers=fingers,
        handedness=handedness, wrist=wrist, forward=forward, lateral=lateral, palmar=palmar,
        palm_length=palm_length, palm_width=palm_width, palm_thickness=thickness,
        hand_vertices=hand_vertices, palm_vertices=palm_ids, excluded_joints=excluded, notes=notes,
    )


def _find_thumb(rig: Rig, chains: list[_Chain], palm_pos: np.ndarray, notes: list[str]) -> int | None:
    """Index of the thumb chain: the one pointing furthest from the mean of the others."""
    directions = np.array([_unit(c.tip - c.points[0]) for c in chains])
    hints = [finger_hint([rig.joints[j].name for j in c.joints]) for c in chains]
    hinted = [i for i, h in enumerate(hints) if h == "thumb"]
    if len(chains) == 2:
        # Two chains point away from each other equally: the thumb's base is nearer the wrist.
        d = [float(np.linalg.norm(c.points[0] - palm_pos)) for c in chains]
        near = int(np.argmin(d))
        if d[1 - near] - d[near] < 0.15 * max(d) and len(hinted) != 1:
            raise _ambiguous(rig, "which of the two finger chains is the thumb (their bases are as far from the palm joint)")
        thumb = hinted[0] if len(hinted) == 1 else near
        notes.append(f"thumb: {rig.joints[chains[thumb].joints[0]].name!r} (of two chains, the base nearer the wrist)")
        return thumb
    deviation = []
    for i in range(len(chains)):
        rest = _unit(np.delete(directions, i, axis=0).mean(axis=0))
        deviation.append(float(np.degrees(np.arccos(np.clip(directions[i] @ rest, -1, 1)))))
    order = np.argsort(deviation)[::-1]
    best, second = deviation[order[0]], deviation[order[1]]
    if best >= THUMB_MIN_DEVIATION_DEG and best - second >= THUMB_MARGIN_DEG:
        thumb = int(order[0])
        if hinted and thumb not in hinted:
            notes.append(f"joint names suggest {rig.joints[chains[hinted[0]].joints[0]].name!r} is the thumb; "
                         "the geometry says otherwise and wins")
        notes.append(f"thumb: {rig.joints[chains[thumb].joints[0]].name!r} points {best:.0f} degrees from the "
                     f"other fingers (next {second:.0f})")
        return thumb
    if len(hinted) == 1:
        notes.append(f"thumb: {rig.joints[chains[hinted[0]].joints[0]].name!r} by its name (the geometry cannot tell: "
                     f"{best:.0f} against {second:.0f} degrees)")
        return hinted[0]
    listed = ", ".join(f"{rig.joints[chains[i].joints[0]].name!r} {deviation[i]:.0f} deg" for i in order[:3])
    raise _ambiguous(rig, f"which finger chain is the thumb: no chain points clearly away from the others ({listed})")


def _palm_axes(rig, chains, starts, thumb, palm_pos, palm_joints, owner, vertices, *, first_pass=False):
    """(forward, lateral toward the thumb, normal (sign undecided), palm centroid, palm vertex ids,
    the ids of those no finger carries (the frame and the wrist are measured on them)).

    The palm is the surface owned by the palm joints and the metacarpals (leading chain joints
    inside the palm), without what lies far behind the palm joint (a forearm, a mount). Its
    normal is the palm slab's thinnest principal axis when the slab is clearly flat, else the
    normal of the plane through the wrist and the knuckles; forward runs from the palm's centre
    to the knuckles within the palm plane."""
    others = [i for i in range(len(chains)) if i != thumb]
    knuckles = np.array([chains[i].points[starts[i]] for i in others])
    knuckle_mean = knuckles.mean(axis=0)
    palm_owners = set(palm_joints)
    for i in others:
        palm_owners |= {j for g in chains[i].groups[:starts[i]] for j in g}
    palm_owned = np.nonzero(np.isin(owner, sorted(palm_owners)))[0]
    forward = _unit(knuckle_mean - palm_pos)
    if not np.any(forward):
        forward = _unit(np.mean([c.tip for c in chains], axis=0) - palm_pos)
    reach = max(float(np.linalg.norm(knuckle_mean - palm_pos)), 1e-3)
    ids = palm_owned[((vertices[palm_owned] - palm_pos) @ forward) >= -0.5 * reach]
    # The frame and the wrist are measured on palm skin that no finger carries: skin blended
    # with a finger or the thumb moves when a rig is bound with them bent, the palm does not.
    finger_joints = sorted({j for c in chains for j in c.joints} - palm_owners)
    carried = rig.surface.dense_weights(len(rig.joints))[ids][:, finger_joints].sum(axis=1)
    rigid = ids[carried <= MAX_FINGER_SHARE]
    frame_ids = rigid if len(rigid) >= max(10, len(ids) // 4) else ids
    centroid = vertices[frame_ids].mean(axis=0) if len(frame_ids) else palm_pos
    # Lateral: across the knuckles; then the normal (the slab's thinnest axis when the palm is
    # clearly flat, else from the wrist-to-knuckles direction), then forward completes the frame.
    if len(others) >= 2:
        spread = knuckles - knuckle_mean
        if first_pass:
            # Before the metacarpals are known, a chain's first joint may be set back along the
            # fingers (a robot's palm-cupping joint): take the spread across the fingers' mean
            # direction. After, the knuckles' own line (which a curl at rest does not change).
            along = _unit(np.mean([chains[i].tip - chains[i].points[starts[i]] for i in others], axis=0))
            spread -= np.outer(spread @ along, along)
        lateral = _unit(np.linalg.svd(spread, full_matrices=False)[2][0])
    else:
        lateral = _perp(chains[thumb].points[0] - knuckle_mean, forward)
    towards = knuckle_mean - centroid if np.linalg.norm(knuckle_mean - centroid) > 1e-6 else forward
    normal = _unit(np.cross(_perp(towards, lateral), lateral))
    if len(frame_ids) >= 10:
        _, sv, axes = np.linalg.svd(vertices[frame_ids] - centroid, full_matrices=False)
        slab = _perp(axes[2], lateral)
        if sv[2] < 0.6 * sv[1] and abs(slab @ normal) > 0.7:
            normal = slab
    forward = _unit(np.cross(lateral, normal))
    if forward @ towards < 0:
        forward = -forward
    if thumb is not None and (chains[thumb].points[0] - knuckle_mean) @ lateral < 0:
        lateral = -lateral
    normal = _unit(np.cross(forward, lateral))
    return forward, lateral, normal, centroid, ids, frame_ids


def _ray_mesh(rig: Rig):
    import trimesh

    return trimesh.Trimesh(rig.surface.vertices, rig.surface.faces, process=False)


def _web_position(chains, i, neighbours, mesh, forward) -> float | None:
    """Where chain i separates from its nearest neighbour, along ``forward`` (m): from this sample
    on, a ray from the finger's axis to the neighbour's axis leaves the surface. None when it never
    does (a webbed hand, or fingers fused in the surface)."""
    polyline = chains[i].polyline
    seg = np.diff(polyline, axis=0)
    seg_len = np.linalg.norm(seg, axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg_len)])
    samples = np.linspace(0.0, arc[-1] * 0.9, 46)
    k = np.clip(np.searchsorted(arc, samples, side="right") - 1, 0, len(seg) - 1)
    points = polyline[k] + (samples - arc[k])[:, None] * (seg[k] / np.maximum(seg_len[k], 1e-12)[:, None])
    targets = np.array([min((_closest_on_polyline(p, chains[n].polyline) for n in neighbours),
                            key=lambda q, p=p: np.linalg.norm(q - p)) for p in points])
    gaps = targets - points
    dist = np.linalg.norm(gaps, axis=1)
    free = np.zeros(len(points), dtype=bool)
    locations, ray_ids, _ = mesh.ray.intersects_location(points, gaps / np.maximum(dist, 1e-12)[:, None],
                                                         multiple_hits=False)
    for loc, r in zip(locations, ray_ids):
        free[r] |= np.linalg.norm(loc - points[r]) < dist[r] * 0.999
    if not free[-1]:
        return None
    web = len(free) - 1
    while web > 0 and free[web - 1]:
        web -= 1
    return float(points[web] @ forward)


def _flexion_capacity(rig: Rig, chain: _Chain, k: int, world: np.ndarray, normal: np.ndarray) -> float | None:
    """The largest rotation (radians) articulation k of a chain can make out of the palm plane
    (toward either side); None when the chain's joints carry no DOFs at all."""
    joints = set(chain.joints)
    dofs = [d for d in rig.dofs if d.joint in joints and d.kind == "rotate"]
    if not dofs:
        return None
    r = _unit(chain.tip - chain.points[k])
    best = 0.0
    for d in dofs:
        if d.joint in chain.groups[k]:
            m = abs(float(np.cross(world[d.joint][:3, :3] @ d.axis, r) @ normal))
            if m >= 0.5:
                best = max(best, m * min(max(d.upper - d.rest, d.rest - d.lower), np.pi))
    return best


#: An articulation that can bend the finger out of the palm plane by more than this is a knuckle
#: (or a finger joint), never a metacarpal.
KNUCKLE_MIN_FLEXION = np.radians(20.0)


def _metacarpal_counts(rig, chains, others, web, forward, normal, world, notes) -> dict[int, int]:
    """Per non-thumb chain, how many leading articulations lie inside the palm (metacarpals).

    First, articulations whose bone ends before the web (within a quarter of its length) and that cannot flex the finger (no DOF,
    or only abduction; with no DOFs on the chain, the web alone decides). Then, against the
    knuckle line of all fingers (their median), an articulation whose bone ends at that line is a
    metacarpal even when it moves (a robot's palm-cupping joint). Two articulations always stay."""
    counts = {}
    for i in others:
        c, k = chains[i], 0
        # a bone "ends before the web" within a quarter of its own length (knuckles sit at the web)
        while k < len(c.points) - 2 and \
                c.points[k + 1] @ forward <= web + 0.25 * np.linalg.norm(c.points[k + 1] - c.points[k]):
            capacity = _flexion_capacity(rig, c, k, world, normal)
            if capacity is not None and capacity >= KNUCKLE_MIN_FLEXION:
                break
            k += 1
        counts[i] = k
    line = float(np.median([chains[i].points[counts[i]] @ forward for i in others]))
    first = float(np.median([(chains[i].points[counts[i] + 1] - chains[i].points[counts[i]]) @ forward
                             for i in others]))
    for i in others:
        c = chains[i]
        while counts[i] < len(c.points) - 2 and c.points[counts[i] + 1] @ forward <= line + 0.3 * first:
            counts[i] += 1
    return counts


def _palmar_sign(rig, chains, starts, thumb, normal, forward, centroid, world, notes) -> float:
    """+1 when the palm faces +normal, -1 when it faces -normal, from three votes in [-1, 1]."""
    others = [i for i in range(len(chains)) if i != thumb]
    # (a) flexion limits: fingers bend much further toward the palm than away from it.
    toward, total = 0.0, 0.0
    for i in others:
        c = chains[i]
        for k, group in enumerate(c.groups[starts[i]:], start=starts[i]):
            r = _unit(c.tip - c.points[k])
            for d in rig.dofs:
                if d.joint not in group or d.kind != "rotate":
                    continue
                a = world[d.joint][:3, :3] @ d.axis
                m = float(np.cross(a, r) @ normal)
                if abs(m) < 0.5:
                    continue
                plus, minus = min(d.upper - d.rest, np.pi), min(d.rest - d.lower, np.pi)
                if m < 0:
                    plus, minus = minus, plus
                toward += abs(m) * (plus - minus)
                total += abs(m) * (plus + minus)
    limits = toward / total if total > 1e-9 else 0.0
    # (b) curl at rest: fingers bent at rest bend toward the palm.
    bends = []
    for i in others:
        p = chains[i].polyline[starts[i]:]
        u = [_unit(b - a) for a, b in zip(p[:-1], p[1:])]
        bends.append(float((u[-1] - forward) @ normal))
    curl = float(np.clip(np.mean(bends) / 0.5, -1, 1)) if bends else 0.0
    # (c) the thumb lies in front of the palm.
    if thumb is not None:
        t = chains[thumb]
        opposition = float(np.clip(((t.tip - centroid) @ normal) / (0.15 * max(t.length, 1e-6)), -1, 1))
    else:
        opposition = 0.0
    votes = {"flexion limits": limits, "curl at rest": curl, "thumb in front of the palm": opposition}
    weights = {"flexion limits": 1.0, "curl at rest": 0.7, "thumb in front of the palm": 0.5}
    combined = sum(weights[k] * v for k, v in votes.items())
    text = ", ".join(f"{k} {v:+.2f}" for k, v in votes.items())
    strong_against = [k for k, v in votes.items() if abs(v) >= 0.5 and np.sign(v) != np.sign(combined)]
    if abs(combined) < PALMAR_MIN_VOTE or strong_against:
        raise _ambiguous(rig, f"which side of the hand is the palm (votes for +normal: {text}; "
                              "give the handedness)")
    notes.append(f"palmar side: votes {text}")
    return float(np.sign(combined))


def _name_fingers(rig, chains, order, notes) -> dict[int, str]:
    """Names for the non-thumb chains in order across the palm from the thumb side."""
    count = len(order)
    if count <= 4:
        names = list(NON_THUMB_NAMES[:count])
        hints = [finger_hint([rig.joints[j].name for j in chains[i].joints]) for i in order]
        if all(h in NON_THUMB_NAMES for h in hints) and len(set(hints)) == count and \
                [NON_THUMB_NAMES.index(h) for h in hints] == sorted(NON_THUMB_NAMES.index(h) for h in hints):
            if hints != names:
                notes.append(f"fingers named from their joint names: {', '.join(hints)}")
            names = hints
    else:
        names = list(NON_THUMB_NAMES) + [f"finger{k + 1}" for k in range(4, count)]
    return {i: name for i, name in zip(order, names)}


def _bending_direction(rig: Rig, world: np.ndarray, group: list[int], direction: np.ndarray):
    """Where the articulation's main bending DOF (the rotational DOF across the bone with the
    widest range) curls the bone: (unit direction (3,), signed). ``signed`` is False when its
    range is about symmetric (within 20 degrees): the rig then says in which plane the joint
    bends but not toward which side. None when the joints carry no such DOF."""
    best, best_range = None, 0.0
    for d in rig.dofs:
        if d.joint in group and d.kind == "rotate":
            a = world[d.joint][:3, :3] @ d.axis
            if abs(a @ direction) > 0.5:
                continue  # a twist about the bone
            plus, minus = min(d.upper - d.rest, np.pi), min(d.rest - d.lower, np.pi)
            if plus + minus > best_range:
                best_range = plus + minus
                best = (_perp(np.cross(a, direction) * (1.0 if plus >= minus else -1.0), direction),
                        abs(plus - minus) >= np.radians(20.0))
    return best


def _finger_model(rig, world, name, chain: _Chain, start, palmar, forward, knuckle_mean, owner, vertices) -> FingerModel:
    groups = chain.groups[start:]
    polyline = chain.polyline[start:]
    directions = [_unit(b - a) for a, b in zip(polyline[:-1], polyline[1:])]
    if name == "thumb":
        # The thumb's pad faces halfway between the palm and the fingers (opposition); a round
        # thumb turned about its own axis looks the same, so where its joints bend (a flexion
        # range much larger on one side) says it better when the rig has DOFs.
        pad = _perp(palmar, directions[0]) + _perp(knuckle_mean - polyline[0], directions[0])
        palmar_k = _perp(pad, directions[0])
    else:
        palmar_k = _perp(palmar, directions[0])
    segments = []
    previous = None if name == "thumb" else forward
    for k, group in enumerate(groups):
        if k > 0:
            palmar_k = _transport(palmar_k, directions[k - 1], directions[k])
        if name == "thumb":
            # A link's pad turns with the link, and the next joint bends in the link's own frame,
            # so the next articulation's bending (carried back onto this bone) gives this link's
            # pad; the last link has only its own joint's.
            # Prefer a joint whose range says the side (signed); else the plane the last joint
            # bends in (a finger's distal joints flex, whatever their limits), carried back along
            # the thumb, with the side nearer the estimate.
            bending = None
            if k + 1 < len(groups):
                after = _bending_direction(rig, world, groups[k + 1], directions[k + 1])
                if after is not None and after[1]:
                    bending = _transport(after[0], directions[k + 1], directions[k])
            if bending is None:
                own = _bending_direction(rig, world, group, directions[k])
                if own is not None and own[1]:
                    bending = own[0]
            if bending is None:
                distal = _bending_direction(rig, world, groups[-1], directions[-1])
                if distal is not None:
                    bending = distal[0]
                    for j in range(len(groups) - 1, k, -1):
                        bending = _transport(bending, directions[j], directions[j - 1])
                    if bending @ palmar_k < 0:
                        bending = -bending
            if bending is not None and bending @ palmar_k > 0.0:
                palmar_k = bending
        flex_axis = _unit(np.cross(directions[k], palmar_k))
        if previous is None:
            bend = 0.0
        else:
            # positive when ``previous`` turns about the flexion axis toward the palm
            bend = float(np.arctan2(np.cross(previous, directions[k]) @ flex_axis, previous @ directions[k]))
        segments.append(Segment(list(group), polyline[k].copy(), polyline[k + 1].copy(), directions[k],
                                palmar_k, flex_axis, palmar_k.copy(), bend))
        previous = directions[k]
    joints = [j for g in groups for j in g]
    link_vertices = [np.nonzero(owner == j)[0] for j in joints]
    # each link's surface against its own bone, so a finger curled at rest measures as straight
    # (its middle part: skinning bulges the surface near a bent joint)
    distances = []
    for k, g in enumerate(groups):
        ids = np.nonzero(np.isin(owner, g))[0]
        a, b = polyline[k], polyline[k + 1]
        t = (vertices[ids] - a) @ (b - a) / max((b - a) @ (b - a), 1e-18)
        middle = ids[(t >= 0.2) & (t <= 0.8)]
        if len(middle):
            distances.append(_distance_to_polyline(vertices[middle], polyline[k:k + 2]))
    girth = float(np.median(np.concatenate(distances))) if distances else 0.0
    length = float(np.linalg.norm(np.diff(polyline, axis=0), axis=1).sum())
    metacarpals = [j for g in chain.groups[:start] for j in g]
    return FingerModel(name, joints, metacarpals, segments, chain.tip.copy(), chain.tip_vertex, link_vertices,
                       length, girth)


def _dof_about(rig: Rig, world: np.ndarray, joint: int, axis: np.ndarray, min_alignment: float = 0.7) -> int:
    """Index of the rotational DOF of ``joint`` whose world axis is best aligned (either sign, at
    least ``min_alignment``) with ``axis``; -1 when there is none."""
    best, best_dot = -1, min_alignment
    for k, d in enumerate(rig.dofs):
        if d.joint == joint and d.kind == "rotate":
            dot = abs(float((world[joint][:3, :3] @ d.axis) @ axis))
            if dot >= best_dot:
                best, best_dot = k, dot
    return best
