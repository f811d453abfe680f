"""Collision terms of the per-frame objective (beyond the paper), as squared hinges in mm^2:

- G_P, hand-object penetration, both ways: sum over hand sample points x of max(0, -sdf_O(x))^2,
  sdf_O the object's signed distance sampled once per run on a grid in the object's frame
  (:mod:`retarget_core.mesh.sdf_grid`), queried by trilinear interpolation
  (:class:`ObjectCollision`); plus, over object sample points y, max(0, -sdf_B(y))^2 for the hand
  part B it is in, a part's grid as for G_SC (:class:`ObjectInHand`): a box corner or a mug
  handle pokes into a finger between the hand's sample points, where the first half cannot see
  it;
- G_SC, self collision: for every pair of hand parts that do not share a surface edge
  (:mod:`retarget_core.rig.parts`: fingers, phalanges, robot links), sum over the sample points
  x of one part of max(0, -sdf_B(x))^2, sdf_B the other part's signed distance sampled at rest
  in its joint's frame (rigid for a robot link, the part's dominant joint for a skinned hand).

Both are least-squares residuals r = sqrt(lambda) * mm * max(0, -sdf) with analytic
Jacobians, so the Gauss-Newton warm start and the polish of the delivered curve see them like
the contacts. A point in a joint's frame moves with the hand's point and with the frame: the
derivative has both parts (:meth:`Kinematics.rigid_points_vjp`).

Only points near the other body at the seed are evaluated (:meth:`focus`; the far ones cannot
reach it within one frame's solve); :meth:`missed` tells when a point left out ended inside,
and the solve then goes on with it (as for the table).
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from ..mesh.sdf_grid import SdfGrids, owner_spheres
from ..mesh.surface_points import SurfacePoints

MM = 1000.0
#: Object grid: node spacing and reach beyond the object (m). Trilinear interpolation of a
#: distance field across a surface of curvature radius R errs by about h^2 / (8 R): 0.03 mm for
#: a 4 cm bottle at 3 mm.
OBJECT_SPACING = 0.003
OBJECT_MARGIN = 0.008
#: Part grids (m): 0.06 mm on a 14 mm finger at 2.5 mm.
PART_SPACING = 0.0025
PART_MARGIN = 0.005
#: At the seed, points farther than this (m) from the other body are left out of the solve.
FOCUS_MARGIN = 0.005
#: Object sample points for the object-into-hand half of G_P: one object vertex per cube of this
#: edge (m). The demo objects' edges are about 2 mm; a dense scan is thinned to this.
OBJECT_POINT_SPACING = 0.002
#: Self collision sample points: one vertex of a part per cube of this edge (m) at rest, the
#: cubes grown by 1.2x until at most ``sampling.self_collision_samples`` remain, so the points
#: cover a part whatever order its vertices come in. Until stop 49 every part had 32 vertices,
#: picked evenly by vertex id: between them robot4's thumb tip went 11 mm into its index tip
#: with the term on (2.1 % of the hand's volume on apple_rotate).
PART_POINT_SPACING = 0.003


@dataclass(frozen=True)
class CollisionGrids:
    """What the collision terms precompute for a run, built once (:func:`collision_grids`) and
    shipped to every worker with the problem: the object's grid (in its frame), the hand's
    parts and their grids (each in its joint's frame at rest). Absent parts are None."""

    object: SdfGrids | None = None
    parts: object = None  # retarget_core.rig.parts.HandParts
    part_grids: SdfGrids | None = None


def object_grid(object_vertices: np.ndarray, object_faces: np.ndarray) -> SdfGrids:
    return SdfGrids.of_meshes([(object_vertices, object_faces)], OBJECT_SPACING, OBJECT_MARGIN)


def part_grids(kin, parts) -> SdfGrids:
    """Each part's closed rest mesh in its joint's frame, as a grid."""
    rig = kin.rig
    rest = kin.skin(rig.rest_pose)
    meshes = []
    for name, (v, f) in zip(parts.names, parts.posed(rest)):
        inv = np.linalg.inv(kin.bind_world[rig.joint_index(name)])
        meshes.append((v @ inv[:3, :3].T + inv[:3, 3], f))
    return SdfGrids.of_meshes(meshes, PART_SPACING, PART_MARGIN)


def grid_spheres(grids: SdfGrids):
    """Per grid, the sphere around its box in the grid's frame: centres (G, 3) m, radii (G,) m.
    Outside it a query reads FAR, so a point there needs no query."""
    half = (grids.shapes - 1) * grids.spacing[:, None] / 2
    return grids.origins + half, np.linalg.norm(half, axis=1)


def _digest(*arrays) -> str:
    h = hashlib.sha1()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()


#: Grids kept per process, by content (a service or a test session retargets the same rig and
#: object many times; each entry is a few MB).
_CACHE: OrderedDict = OrderedDict()
_CACHE_SIZE = 8


def clear_grid_cache() -> None:
    """Forget the grids kept in this process (:func:`collision_grids`)."""
    _CACHE.clear()


def _cached(key, build):
    if key in _CACHE:
        _CACHE.move_to_end(key)
        return _CACHE[key]
    value = _CACHE[key] = build()
    while len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)
    return value


def collision_grids(rig, object_vertices, object_faces, config) -> CollisionGrids:
    """The grids the configuration's collision terms need (none when both are off: the object's
    for G_P, the parts' for G_SC and for the object-into-hand half of G_P), cached by
    the content of the object and of the rig's surface, skin and rest frames."""
    from ..rig.parts import rig_parts

    obj = None
    if config.weights.lambda_p > 0:
        obj = _cached(("object", _digest(object_vertices, object_faces)),
                      lambda: object_grid(object_vertices, object_faces))
    parts = grids = None
    if config.weights.lambda_sc > 0 or config.weights.lambda_p > 0:  # both need the parts' grids
        kin = rig.kinematics()
        s = rig.surface
        key = ("parts", _digest(s.vertices, s.faces, s.joint_indices, s.joint_weights, kin.bind_world),
               tuple(rig.joint_names))

        def build():
            p = rig_parts(rig)
            return p, part_grids(kin, p)

        parts, grids = _cached(key, build)
    return CollisionGrids(obj, parts, grids)


class ObjectCollision:
    """G_P for one rig and object. ``stride``: every stride-th hand vertex is a sample point;
    ``grids``: the object's grid when built already (:func:`object_grid`)."""

    def __init__(self, kin, object_vertices: np.ndarray, object_faces: np.ndarray, stride: int,
                 grids: SdfGrids | None = None):
        self.kin = kin
        self.grids = grids if grids is not None else object_grid(object_vertices, object_faces)
        surface = kin.rig.surface
        self.vertices = np.arange(0, surface.n_vertices, max(1, int(stride)))
        self.all = kin.bind(SurfacePoints.from_vertices(self.vertices, surface.faces))
        self.focused = np.arange(len(self.vertices))
        self.binding = self.all
        self.level = None  # (K,) per focused point: 0, or -inf where it costs nothing (keep_out); None: all 0

    def _sdf(self, points: np.ndarray, object_pose: np.ndarray):
        """Signed distances (K,) m and world gradients (K, 3) at world points (K, 3)."""
        return self.grids.query_in(np.linalg.inv(object_pose)[None], points, 0)

    def _below(self, pose, object_pose: np.ndarray, level: float, among: np.ndarray | None = None):
        """(ids (K,), signed distances (K,) m) of the sample points (of ``among``, default all)
        whose grid value at pose is below ``level`` m."""
        x = self.kin.points(pose, self.all)
        if among is not None:
            x = x[among]
        below, d = self.grids.below_in(np.linalg.inv(object_pose)[None], x, 0, level)
        return (below if among is None else among[below]), d

    def focus(self, pose, object_pose: np.ndarray) -> None:
        near, d = self._below(pose, object_pose, FOCUS_MARGIN)
        self.focused = near[d < FOCUS_MARGIN]
        self.binding = self.all.subset(self.focused) if len(self.focused) else None
        self.level = None

    def keep_out(self, pose, object_pose: np.ndarray) -> None:
        """From now until the next :meth:`focus`, only the focused points outside the object at
        ``pose`` cost (as before: where they go in); those inside there cost nothing wherever
        they go (their level is -inf)."""
        if self.binding is not None:
            d, _ = self._sdf(self.kin.points(pose, self.binding), object_pose)
            self.level = np.where(d < 0, -np.inf, 0.0)

    def _depth(self, pose, object_pose):
        """(signed distances above each focused point's level (K,) m, world gradients (K, 3))."""
        d, g = self._sdf(self.kin.points(pose, self.binding), object_pose)
        return (d if self.level is None else d - self.level), g

    def deepest(self, pose, object_pose: np.ndarray) -> float:
        """How deep the deepest focused point is in the object at pose, m (0: none inside)."""
        if self.binding is None:
            return 0.0
        return max(0.0, float(-self._depth(pose, object_pose)[0].min()))

    def missed(self, pose, object_pose: np.ndarray) -> bool:
        """True when a sample point left out by :meth:`focus` is inside the object at pose."""
        if len(self.focused) == len(self.vertices):
            return False
        out = np.ones(len(self.vertices), bool)
        out[self.focused] = False
        _, d = self._below(pose, object_pose, 0.0, np.flatnonzero(out))
        return bool(np.any(d < 0))

    def whole_value(self, pose, object_pose: np.ndarray, weight: float) -> float:
        """lambda * G_P over every sample point at pose (no focus needed): what
        :meth:`focus` at pose then :meth:`value_and_cot` give, querying only the points that
        may be inside."""
        _, d = self._below(pose, object_pose, 0.0)
        pen = np.maximum(-d, 0.0) * MM
        return weight * float(pen @ pen)

    def value_and_cot(self, pose, object_pose, weight: float):
        """(value, points (K, 3), cotangent (K, 3)) of lambda * G_P at the focused points."""
        if self.binding is None:
            return 0.0, None
        d, g = self._depth(pose, object_pose)
        pen = np.maximum(-d, 0.0) * MM
        if not pen.any():
            return 0.0, None
        return weight * float(pen @ pen), (-2.0 * weight * MM) * pen[:, None] * g

    def residuals(self, pose, object_pose, weight: float, jacobian: bool):
        """(r (H,), dr/dq transposed (D, H) or None) at the focused points inside the object
        (the others have r = 0)."""
        if self.binding is None:
            return None
        s = np.sqrt(weight) * MM
        d, g = self._depth(pose, object_pose)
        # the points outside have r = 0 and no slope: only the points inside are rows
        hit = np.flatnonzero(d < 0)
        jt = None
        if jacobian:
            jt = np.zeros((self.kin.n_dofs, 0))
            if len(hit):
                _, jx = self.kin.points_jacobian(pose, self.binding.subset(hit))
                jt = -s * np.einsum("pad,pa->dp", jx, g[hit])
        return -s * d[hit], jt


def cube_samples(vertices: np.ndarray, spacing: float) -> np.ndarray:
    """Ids (K,) of the vertices (V, 3) m kept as sample points: the first vertex (lowest id, so
    the choice is the same on every machine) in each occupied cube of ``spacing`` m, so the
    points cover the surface evenly whatever its meshing."""
    v = np.asarray(vertices, dtype=np.float64)
    cell = np.floor((v - v.min(axis=0)) / spacing).astype(np.int64)
    _, first = np.unique(cell, axis=0, return_index=True)
    return np.sort(first)


def squared_hinge(d: np.ndarray, gw: np.ndarray, weight: float):
    """lambda * sum (mm * max(0, -d))^2 over signed distances d (K,) m with world gradients
    gw (K, 3): (value, ids of the points inside (H,), their cotangents (H, 3)), the form every
    collision term shares."""
    pen = np.maximum(-d, 0.0) * MM
    hit = np.flatnonzero(pen > 0)
    return weight * float(pen @ pen), hit, (-2.0 * weight * MM) * pen[hit, None] * gw[hit]


class ObjectInHand:
    """The object-into-hand half of G_P for one rig and object: object sample points y
    (:func:`cube_samples` at :data:`OBJECT_POINT_SPACING`, fixed in the object's frame) against the hand parts' grids
    (each rigid in its joint's frame, as for G_SC). An item is a (point, part) pair; the term is
    lambda * sum over items of (mm * max(0, -sdf_part(y)))^2. ``parts`` and ``grids`` when built
    already (:func:`collision_grids`)."""

    def __init__(self, kin, object_vertices: np.ndarray, parts=None, grids: SdfGrids | None = None):
        from ..rig.parts import rig_parts

        self.kin = kin
        if parts is None:
            parts, grids = rig_parts(kin.rig), None
        self.parts = parts
        self.grids = grids if grids is not None else part_grids(kin, parts)
        self.part_joint = np.array([kin.rig.joint_index(n) for n in parts.names], dtype=np.int64)
        points = np.asarray(object_vertices, dtype=np.float64)[cube_samples(object_vertices, OBJECT_POINT_SPACING)]
        # sorted by x, so a part's sphere visits only the slab of points within its reach
        self.points = np.ascontiguousarray(points[np.argsort(points[:, 0], kind="stable")])
        self.grid_centre, self.grid_radius = grid_spheres(self.grids)
        self.item_point = self.item_grid = np.zeros(0, np.int64)
        self.focused_all = True  # until the first focus, which the first evaluation then makes
        self.level = None  # (K,) per focused item: 0, or -inf where it costs nothing (keep_out); None: all 0

    @property
    def n_points(self) -> int:
        return len(self.points)

    def _world(self, object_pose: np.ndarray, points: np.ndarray) -> np.ndarray:
        """The world positions (K, 3) of the sample points ``points`` (K,) at the object's pose."""
        return self.points[points] @ object_pose[:3, :3].T + object_pose[:3, 3]

    def _grid_frames(self, pose) -> np.ndarray:
        """(G, 4, 4) maps from world into each part grid's frame at pose."""
        return np.linalg.inv(pose.world[self.part_joint])

    def _below(self, pose, object_pose: np.ndarray, level: float):
        """(points (K,), grids (K,), signed distances (K,) m) of the items reading below
        ``level`` m at pose, grid by grid, points ascending (so every run sums alike). Only the
        object points within a part grid's bounding sphere are read (beyond it, FAR)."""
        world = pose.world[self.part_joint]  # (G, 4, 4)
        centre = np.einsum("gab,gb->ga", world[:, :3, :3], self.grid_centre) + world[:, :3, 3]
        inv = np.linalg.inv(object_pose)
        from_object = self._grid_frames(pose) @ object_pose  # object frame -> each grid's
        return self.grids.pairs_below(from_object, self.points, centre @ inv[:3, :3].T + inv[:3, 3],
                                      self.grid_radius, level)

    def focus(self, pose, object_pose: np.ndarray) -> None:
        p, g, d = self._below(pose, object_pose, FOCUS_MARGIN)
        keep = d < FOCUS_MARGIN
        self.item_point, self.item_grid = p[keep], g[keep]
        self.focused_all = False
        self.level = None

    def _sdf(self, pose, object_pose: np.ndarray):
        """At the focused items: (distances above each item's level (K,) m, world gradients
        (K, 3), world points (K, 3), the joints of the grids' frames (K,))."""
        y = self._world(object_pose, self.item_point)
        d, gw = self.grids.query_in(self._grid_frames(pose), y, self.item_grid)
        return (d if self.level is None else d - self.level), gw, y, self.part_joint[self.item_grid]

    def keep_out(self, pose, object_pose: np.ndarray) -> None:
        """As :meth:`ObjectCollision.keep_out`: until the next :meth:`focus`, only the items
        whose point is outside its part at ``pose`` cost."""
        if self.focused_all:
            self.focus(pose, object_pose)
        self.level = None
        if len(self.item_point):
            self.level = np.where(self._sdf(pose, object_pose)[0] < 0, -np.inf, 0.0)

    def deepest(self, pose, object_pose: np.ndarray) -> float:
        """How deep the deepest focused item's point is in its part at pose, m (0: none)."""
        if self.focused_all:
            self.focus(pose, object_pose)
        if not len(self.item_point):
            return 0.0
        return max(0.0, float(-self._sdf(pose, object_pose)[0].min()))

    def missed(self, pose, object_pose: np.ndarray) -> bool:
        """True when an item left out by :meth:`focus` reads inside its part at pose."""
        p, g, d = self._below(pose, object_pose, 0.0)
        inside = d < 0
        if not inside.any():
            return False
        n = len(self.grid_radius)
        return bool(np.setdiff1d(p[inside] * n + g[inside], self.item_point * n + self.item_grid).size)

    def whole_value(self, pose, object_pose: np.ndarray, weight: float) -> float:
        """lambda * this half of G_P over every item at pose (no focus needed)."""
        _, _, d = self._below(pose, object_pose, 0.0)
        pen = np.maximum(-d, 0.0) * MM
        return weight * float(pen @ pen)

    def value_and_grad(self, pose, object_pose: np.ndarray, weight: float, want_grad: bool):
        """(lambda * this half of G_P, its gradient (D,) or None) at the focused items. The
        point is fixed in the world; the part's frame moves with q, which from the frame reads
        as the point moving the other way (:meth:`Kinematics.rigid_points_vjp`)."""
        if self.focused_all:
            self.focus(pose, object_pose)
        if not len(self.item_point):
            return 0.0, None
        d, gw, y, joint = self._sdf(pose, object_pose)
        value, hit, c = squared_hinge(d, gw, weight)
        if not len(hit):
            return 0.0, None
        if not want_grad:
            return value, None
        return value, -self.kin.rigid_points_vjp(pose, joint[hit], y[hit], c)

    def residuals(self, pose, object_pose: np.ndarray, weight: float, jacobian: bool):
        """(r (H,), dr/dq transposed (D, H) or None) over the focused items inside their part."""
        if self.focused_all:
            self.focus(pose, object_pose)
        if not len(self.item_point):
            return None
        s = np.sqrt(weight) * MM
        d, gw, y, joint = self._sdf(pose, object_pose)
        hit = np.flatnonzero(d < 0)
        jt = None
        if jacobian:
            jt = np.zeros((self.kin.n_dofs, 0))
            if len(hit):
                jr = self.kin.rigid_points_jacobian(pose, joint[hit], y[hit])  # (D, 3, H)
                jt = s * np.einsum("dah,ha->dh", jr, gw[hit])
        return -s * d[hit], jt


class SelfCollision:
    """G_SC for one rig: parts, their grids and sample points; ``samples``: points per part;
    ``parts`` and ``grids`` when built already (:func:`collision_grids`)."""

    def __init__(self, kin, samples: int, parts=None, grids: SdfGrids | None = None):
        from ..rig.parts import rig_parts

        self.kin = kin
        rig = kin.rig
        if parts is None:
            parts, grids = rig_parts(rig), None
        self.parts = parts
        self.part_joint = np.array([rig.joint_index(n) for n in parts.names], dtype=np.int64)
        self.grids = grids if grids is not None else part_grids(kin, parts)
        # sample vertices: each part's surface vertices one per cube at rest, the cubes grown
        # until at most ``samples`` remain (even over the surface, whatever its meshing)
        faces = rig.surface.faces
        vertex_part = np.full(rig.surface.n_vertices, -1, dtype=np.int64)
        vertex_part[faces.ravel()] = np.repeat(parts.face_part, 3)
        rest = kin.skin(rig.rest_pose)
        chosen, owner = [], []
        for p in range(parts.n_parts):
            ids = np.flatnonzero(vertex_part == p)
            spacing = PART_POINT_SPACING
            kept = cube_samples(rest[ids], spacing) if len(ids) else ids
            while len(kept) > samples:
                spacing *= 1.2
                kept = cube_samples(rest[ids], spacing)
            ids = ids[kept] if len(ids) else ids
            chosen.append(ids)
            owner.append(np.full(len(ids), p))
        self.vertices = np.concatenate(chosen)
        self.owner = np.concatenate(owner).astype(np.int64)
        self.all = kin.bind(SurfacePoints.from_vertices(self.vertices, faces))
        # every (sample point, other part's grid) of the non-adjacent pairs, both ways
        pt, gr = [], []
        for a, b in parts.non_adjacent_pairs():
            for near, far in ((a, b), (b, a)):
                ids = np.flatnonzero(self.owner == near)
                pt.append(ids)
                gr.append(np.full(len(ids), far))
        self.item_point = np.concatenate(pt) if pt else np.zeros(0, np.int64)
        self.item_grid = np.concatenate(gr) if gr else np.zeros(0, np.int64)
        self.item_owner = self.owner[self.item_point]
        self.grid_centre, self.grid_radius = grid_spheres(self.grids)
        self._focus_items(np.arange(len(self.item_point)))

    def _focus_items(self, items: np.ndarray) -> None:
        """Evaluate only ``items``: their sample points get a binding of their own."""
        self.focused = items
        self._focused_mask = np.zeros(self.n_items, np.bool_)
        self._focused_mask[items] = True
        self.points, self.item_local = np.unique(self.item_point[items], return_inverse=True)
        self.binding = self.all.subset(self.points) if len(self.points) else None

    @property
    def n_items(self) -> int:
        return len(self.item_point)

    def _sdf(self, pose, x: np.ndarray, items: np.ndarray):
        """At the items' world points x (K, 3): distances (K,), world gradients (K, 3), the
        points and the joints of the grids' frames (K,)."""
        d, gw = self.grids.query_in(np.linalg.inv(pose.world[self.part_joint]), x, self.item_grid[items])
        return d, gw, x, self.part_joint[self.item_grid[items]]

    def _below(self, pose, level: float, left_out: bool = False):
        """(items (K,), signed distances (K,) m) of the items (those not focused, with
        ``left_out``) whose grid value at pose is below ``level`` m. Only the items whose part's
        posed points and the other part's grid (rigid in its joint's frame) have meeting spheres
        are read: most pairs of a hand are far apart."""
        x = self.kin.points(pose, self.all)
        world = pose.world[self.part_joint]  # (P, 4, 4)
        grid_centre = np.einsum("pab,pb->pa", world[:, :3, :3], self.grid_centre) + world[:, :3, 3]
        centre, radius = owner_spheres(x, self.owner, self.parts.n_parts)
        return self.grids.items_below(np.linalg.inv(world), x, self.item_point, self.item_grid, self.item_owner,
                                      centre, radius, grid_centre, self.grid_radius, level,
                                      self._focused_mask if left_out else None)

    def focus(self, pose) -> None:
        if not self.n_items:
            return
        items, d = self._below(self.kin._as_pose(pose), FOCUS_MARGIN)
        self._focus_items(items[d < FOCUS_MARGIN])

    def widen(self, pose) -> bool:
        """Add to the focus the items within :data:`FOCUS_MARGIN` of their other part at
        ``pose`` (those focused stay); True when any was added."""
        if not self.n_items:
            return False
        items, d = self._below(self.kin._as_pose(pose), FOCUS_MARGIN, left_out=True)
        new = items[d < FOCUS_MARGIN]
        if not len(new):
            return False
        self._focus_items(np.union1d(self.focused, new))
        return True

    def whole_value(self, pose, weight: float) -> float:
        """lambda * G_SC over every item at pose (no focus needed), querying only the items
        that may be inside."""
        if not self.n_items:
            return 0.0
        _, d = self._below(self.kin._as_pose(pose), 0.0)
        pen = np.maximum(-d, 0.0) * MM
        return weight * float(pen @ pen)

    def missed(self, pose) -> bool:
        if len(self.focused) == self.n_items:
            return False
        _, d = self._below(self.kin._as_pose(pose), 0.0, left_out=True)
        return bool(np.any(d < 0))

    def value_and_grad(self, pose, weight: float, want_grad: bool):
        """(lambda * G_SC, its gradient (D,) or None)."""
        if self.binding is None:
            return 0.0, None
        x_pts = self.kin.points(pose, self.binding)
        d, gw, x, joint = self._sdf(pose, x_pts[self.item_local], self.focused)
        value, hit, c = squared_hinge(d, gw, weight)
        if not len(hit):
            return 0.0, None
        if not want_grad:
            return value, None
        cot = np.zeros_like(x_pts)
        np.add.at(cot, self.item_local[hit], c)
        grad = self.kin.points_vjp(pose, self.binding, cot)
        grad -= self.kin.rigid_points_vjp(pose, joint[hit], x[hit], c)
        return value, grad

    def residuals(self, pose, weight: float, jacobian: bool):
        """(r (H,), dr/dq transposed (D, H) or None) over the focused items inside the other
        part (the others have r = 0)."""
        if self.binding is None:
            return None
        s = np.sqrt(weight) * MM
        x_pts = self.kin.points(pose, self.binding)
        d, gw, x, joint = self._sdf(pose, x_pts[self.item_local], self.focused)
        hit = np.flatnonzero(d < 0)  # only the items inside are rows (the others have r = 0)
        jt = None
        if jacobian:
            jt = np.zeros((self.kin.n_dofs, 0))
            if len(hit):
                hit_points, local = np.unique(self.item_local[hit], return_inverse=True)
                _, jx = self.kin.points_jacobian(pose, self.binding.subset(hit_points))  # (H', 3, D)
                jp = jx[local].transpose(2, 1, 0)  # (D, 3, H)
                jr = self.kin.rigid_points_jacobian(pose, joint[hit], x[hit])
                jt = -s * np.einsum("dah,ha->dh", jp - jr, gw[hit])
        return -s * d[hit], jt
