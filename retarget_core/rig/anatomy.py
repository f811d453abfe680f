"""Hand anatomy of a rig for its consumers (the demo clip generator, the proposer, the source
markers): its finger chains, its palm vertices, the free root as a rigid transform, and the
paper's marker sites, all read from the hand model (:mod:`retarget_core.rig.hand_model`), so
they work on any rig the hand model reads, whatever its joint names and bone rolls.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..mesh.surface_points import SurfacePoints, closest_surface_points
from .hand_model import FINGER_NAMES, FingerModel, HandModel, hand_model
from .model import Rig

__all__ = ["FINGER_NAMES", "Finger", "hand_fingers", "palm_vertices", "source_markers", "closest_hand_points",
           "marker_sites", "place_markers", "surface_along",
           "set_root_transform", "root_transform", "euler_xyz_from_matrix"]

# ---- the free root as a rigid transform -------------------------------------------------------
def euler_xyz_from_matrix(rotation: np.ndarray) -> np.ndarray:
    """Angles (a, b, c) with rotation = Rx(a) @ Ry(b) @ Rz(c) (the root's DOF order); at gimbal
    lock (b = +-90 degrees) c is set to 0."""
    r = np.asarray(rotation, dtype=np.float64)
    sb = np.clip(r[0, 2], -1.0, 1.0)
    b = np.arcsin(sb)
    if abs(sb) < 1.0 - 1e-9:
        a = np.arctan2(-r[1, 2], r[2, 2])
        c = np.arctan2(-r[0, 1], r[0, 0])
    else:  # Rx(a) Ry(+-pi/2): only a +- c is defined; take c = 0
        a = np.arctan2(r[2, 1], r[1, 1])
        b = np.copysign(np.pi / 2, sb)
        c = 0.0
    return np.array([a, b, c])


def set_root_transform(rig: Rig, q: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """A copy of q whose six root DOFs put the root joint at ``transform`` (4, 4), world.
    Assumes the free root of :func:`retarget_core.rig.model.free_root` with an identity rest."""
    q = np.array(q, dtype=np.float64)
    names = rig.dof_names[:6]
    if names != ["root_tx", "root_ty", "root_tz", "root_rx", "root_ry", "root_rz"]:
        raise ValueError(f"rig {rig.name!r} does not start with the standard free root DOFs")
    q[0:3] = transform[:3, 3]
    q[3:6] = euler_xyz_from_matrix(transform[:3, :3])
    return q


def root_transform(rig: Rig, q: np.ndarray) -> np.ndarray:
    """(4, 4) world transform of the root joint at q."""
    return rig.kinematics().pose(q).world[0]


ROOT_ANGLE_DOFS = ("root_rx", "root_ry", "root_rz")


def continuous_root_angles(rig: Rig, q: np.ndarray) -> np.ndarray:
    """q (T, D) radians / metres with each frame's root Euler angles (root_rx, root_ry, root_rz;
    rotation = Rx(a) Ry(b) Rz(c)) written as the triple for the same rotation nearest the
    frame before it, within the DOF limits: a +- 2 pi turns, and (a + pi, pi - b, c + pi).
    Frames solved from different seeds may sit in different of these charts (near b = 90
    degrees they are far apart for rotations that are close), and a curve fitted through the
    angles would then spin the hand round. Every frame keeps its pose; a rig without the
    standard free root comes back as it was."""
    q = np.array(q, dtype=np.float64)
    names = rig.dof_names
    if len(q) < 2 or not all(n in names for n in ROOT_ANGLE_DOFS):
        return q
    idx = np.array([names.index(n) for n in ROOT_ANGLE_DOFS])
    lo, hi = rig.lower[idx], rig.upper[idx]
    turns = 2 * np.pi * np.arange(-3, 4)
    for t in range(1, len(q)):
        prev, (a, b, c) = q[t - 1, idx], q[t, idx]
        best, best_cost = q[t, idx], np.inf
        for base in (np.array([a, b, c]), np.array([a + np.pi, np.pi - b, c + np.pi])):
            choice = base[:, None] + turns[None, :]  # (3, 7): each angle with whole turns added
            ok = (choice >= lo[:, None] - 1e-9) & (choice <= hi[:, None] + 1e-9)
            if not ok.any(axis=1).all():
                continue
            dist = np.where(ok, np.abs(choice - prev[:, None]), np.inf)
            x = choice[np.arange(3), dist.argmin(axis=1)]
            cost = float(np.sum((x - prev) ** 2))
            if cost < best_cost - 1e-12:
                best, best_cost = x, cost
        q[t, idx] = best
    return q


# ---- fingers -----------------------------------------------------------------------------------
@dataclass
class Finger:
    """One finger chain: joint indices (knuckle to distal), their flexion DOF indices (-1 where a
    joint has none), and the surface vertices each joint's link owns (largest skin weight)."""

    name: str
    joints: list[int]
    flex_dofs: list[int]
    link_vertices: list[np.ndarray]
    closing_rate: np.ndarray = field(default_factory=lambda: np.ones(0))


def hand_fingers(rig: Rig, model: HandModel | None = None) -> list[Finger]:
    """The fingers of a hand, thumb first and then across the palm (the hand model's names)."""
    model = model or hand_model(rig)
    fingers = []
    for f in model.fingers:
        n = len(f.joints)
        rate = np.linspace(0.7, 1.0, n) if f.is_thumb else np.linspace(0.8, 1.1, n)
        fingers.append(Finger(f.name, list(f.joints), list(f.flex_dofs), list(f.link_vertices), rate))
    return fingers


def palm_vertices(rig: Rig, model: HandModel | None = None) -> np.ndarray:
    """Ids of the palm's surface vertices on the palmar side (normal within 45 degrees of the
    palm's palmar normal)."""
    model = model or hand_model(rig)
    normals = rig.surface.vertex_normals()
    ids = model.palm_vertices
    return ids[normals[ids] @ model.palmar > 0.7]


def closest_hand_points(rig: Rig, model: HandModel, points: np.ndarray, *, palm_only=False) -> SurfacePoints:
    """The points of the hand's own surface (not a forearm or a mount; with ``palm_only``, of the
    palm: not a finger curled over it or a thumb turned beside it) closest to points (N, 3)."""
    faces = model.hand_faces(rig.surface.faces)
    if palm_only:
        palm = np.zeros(rig.surface.n_vertices, dtype=bool)
        palm[model.palm_vertices] = True
        faces = faces[palm[rig.surface.faces[faces]].all(axis=1)]
    sp = closest_surface_points(rig.surface.vertices, rig.surface.faces[faces], points)
    return SurfacePoints(faces[sp.faces], sp.barycentric)


def _region_faces(rig: Rig, model: HandModel, palm_only: bool) -> np.ndarray:
    faces = model.hand_faces(rig.surface.faces)
    if palm_only:
        palm = np.zeros(rig.surface.n_vertices, dtype=bool)
        palm[model.palm_vertices] = True
        faces = faces[palm[rig.surface.faces[faces]].all(axis=1)]
    return faces


def surface_along(rig: Rig, model: HandModel, origins: np.ndarray, directions: np.ndarray, *,
                  palm_only: bool = False, reach: float = 0.03) -> SurfacePoints:
    """Where rays from ``origins`` (N, 3) along ``directions`` (N, 3) first meet the hand's surface
    (the palm's with ``palm_only``): from inside, the surface point straight off a joint in a
    given direction, whatever the hand's thickness and pose at rest; from outside, where the ray
    enters. A ray that meets no such surface gives the closest point of
    ``origin + reach * direction``."""
    import trimesh

    from ..mesh.surface_points import barycentric_of

    origins = np.asarray(origins, float).reshape(-1, 3)
    directions = np.asarray(directions, float).reshape(-1, 3)
    directions = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    faces = _region_faces(rig, model, palm_only)
    mesh = trimesh.Trimesh(rig.surface.vertices, rig.surface.faces[faces], process=False)
    locations, rays, tri = mesh.ray.intersects_location(origins, directions, multiple_hits=False)
    out_faces = np.full(len(origins), -1, dtype=np.int64)
    out_bary = np.zeros((len(origins), 3))
    if len(rays):
        out_faces[rays] = faces[tri]
        out_bary[rays] = barycentric_of(rig.surface.vertices[rig.surface.faces[faces[tri]]], locations)
    missed = np.nonzero(out_faces < 0)[0]
    if len(missed):
        sp = closest_hand_points(rig, model, origins[missed] + reach * directions[missed], palm_only=palm_only)
        out_faces[missed], out_bary[missed] = sp.faces, sp.barycentric
    return SurfacePoints(out_faces, out_bary)


def articulation_sites(rig: Rig, model: HandModel, finger: FingerModel, ks, side: float) -> np.ndarray:
    """(len(ks), 3) unit directions from the articulations ``ks`` of ``finger`` to the skin
    straight palmar (``side`` +1) or dorsal (-1) of them, as the skin lies on the rig: a first
    ray along the bisector of the two bones finds the skin over the joint, the distal bone's
    share of the skin weights there says how far that skin turned with the joint
    (:meth:`HandModel.articulation_palmar`)."""
    ks = list(ks)
    origins = np.array([finger.segments[k].start for k in ks])
    first = np.array([side * model.articulation_palmar(finger, k) for k in ks])
    hit = surface_along(rig, model, origins, first)
    weights = rig.surface.dense_weights(len(rig.joints))
    out = []
    for i, k in enumerate(ks):
        distal = [j for seg in finger.segments[k:] for j in seg.joints]
        corners = rig.surface.faces[hit.faces[i]]
        follow = float(hit.barycentric[i] @ weights[corners][:, distal].sum(axis=1))
        out.append(side * model.articulation_palmar(finger, k, follow=float(np.clip(follow, 0.0, 1.0))))
    return np.array(out)


# ---- source markers ---------------------------------------------------------------------------
def marker_sites(rig: Rig, model: HandModel) -> dict[str, tuple[np.ndarray, np.ndarray, bool]]:
    """The paper's 25 marker names and where each lies, as a ray (origin (3,), direction (3,),
    palm_only) whose exit from the surface is the marker (:func:`surface_along`), or a site
    (point (3,), None, palm_only) whose closest surface point is, at rest:
    <Finger>Base/Middle/Tip on the back of the finger over its first, second and third
    articulations, <Finger>Fingertip at the apex of the finger, BackIndex/BackRing on the back of
    the palm halfway from the wrist to the index / ring knuckle, WristLeft (thumb side) /
    WristRight at the sides of the wrist, PalmRoot on the palm 20 mm past the wrist. Fingers the
    hand lacks are skipped."""
    sites: dict[str, tuple[np.ndarray, np.ndarray, bool]] = {}
    for finger in model.fingers:
        title = finger.name.capitalize()
        ks = [k for k in range(3) if k < len(finger.segments)]
        for k, direction in zip(ks, articulation_sites(rig, model, finger, ks, -1.0)):
            sites[f"{title}{('Base', 'Middle', 'Tip')[k]}"] = (finger.segments[k].start, direction, False)
        last = finger.segments[-1]
        sites[f"{title}Fingertip"] = (last.start, finger.tip - last.start, False)
    for label, name in (("BackIndex", "index"), ("BackRing", "ring")):
        finger = model.finger(name)
        if finger is not None:
            sites[label] = (0.5 * (model.wrist + finger.knuckle), -model.palmar, True)
    # The sides of the wrist: the palm's closest point to a site 3 cm outside each side (a ray
    # from the wrist would leave through the rounded end of the palm or the forearm, and a ray
    # from outside may meet a thumb base that covers the palm's side).
    near_wrist = model.wrist + model.forward * 0.01
    across = (rig.surface.vertices[model.palm_vertices] - model.wrist) @ model.lateral
    for label, side, extent in (("WristLeft", 1.0, across.max()), ("WristRight", -1.0, -across.min())):
        sites[label] = (near_wrist + side * model.lateral * (extent + 0.03), None, True)
    sites["PalmRoot"] = (model.wrist + model.forward * 0.02, model.palmar, True)
    return sites


#: rig metadata key of fixed marker vertices, {marker name: surface vertex id} (a MANO rig's 25)
MARKERS_METADATA = "markers"


def place_markers(rig: Rig, model: HandModel, sites: dict, names: list[str]) -> SurfacePoints:
    """The named marker sites of :func:`marker_sites` put on the surface; a marker the rig fixes
    to a vertex (``metadata["markers"]``, a MANO rig's paper markers) is that vertex."""
    faces = np.zeros(len(names), dtype=np.int64)
    bary = np.zeros((len(names), 3))
    fixed = rig.metadata.get(MARKERS_METADATA) or {}
    pinned = [i for i, n in enumerate(names) if n in fixed]
    if pinned:
        sp = SurfacePoints.from_vertices(np.array([int(fixed[names[i]]) for i in pinned]), rig.surface.faces)
        faces[pinned], bary[pinned] = sp.faces, sp.barycentric
    names = [None if n in fixed else n for n in names]
    for palm_only in (False, True):
        idx = [i for i, n in enumerate(names) if n is not None and sites[n][2] == palm_only and sites[n][1] is not None]
        if idx:
            sp = surface_along(rig, model, np.array([sites[names[i]][0] for i in idx]),
                               np.array([sites[names[i]][1] for i in idx]), palm_only=palm_only)
            faces[idx], bary[idx] = sp.faces, sp.barycentric
        idx = [i for i, n in enumerate(names) if n is not None and sites[n][2] == palm_only and sites[n][1] is None]
        if idx:
            sp = closest_hand_points(rig, model, np.array([sites[names[i]][0] for i in idx]), palm_only=palm_only)
            faces[idx], bary[idx] = sp.faces, sp.barycentric
    return SurfacePoints(faces, bary)


def source_markers(rig: Rig, model: HandModel | None = None) -> tuple[list[str], np.ndarray, np.ndarray]:
    """The markers of :func:`marker_sites` on the hand's surface.
    Returns (names, faces (M,), barycentric (M, 3))."""
    model = model or hand_model(rig)
    sites = marker_sites(rig, model)
    names = list(sites)
    points = place_markers(rig, model, sites, names)
    return names, points.faces, points.barycentric
