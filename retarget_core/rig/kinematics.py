"""Vectorised forward kinematics, linear blend skinning and ANALYTIC Jacobians.

For a surface point p skinned by joints j with weights w_j (barycentric blends of its face's
vertices included), ``p(q) = sum_j M_j(q) y_j`` where ``y_j = w_j [x_rest; 1]`` and
``M_j = G_j(q) inv(G_j(rest))``. A rotational DOF d of joint a, with world axis omega_d
through the world point o_d, moves every joint in a's subtree rigidly, so

    dp/dq_d = omega_d x (sum_{j in sub(a)} M_j y_j  -  W_sub(a) o_d),   W_sub(a) = sum_{j in sub(a)} w_j

and a translational DOF gives ``dp/dq_d = W_sub(a) axis_d``. Normals are the skinned,
barycentrically blended rest vertex normals ``u = sum_j R_j z_j`` (R_j the rotation of M_j),
normalised; ``du/dq_d = omega_d x sum_{j in sub(a)} R_j z_j`` and the normalisation is
differentiated exactly. All of it is evaluated for many points at once with a handful of
batched matrix products, which is what makes per-frame IK with MMA cheap.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..mesh.surface_points import SurfacePoints
from .model import Rig, SkinnedMesh


@dataclass(frozen=True)
class Pose:
    """The rig evaluated at one DOF vector.

    q: (D,); world: (J, 4, 4) joint world transforms; skin: (J, 4, 4) skinning transforms
    (world @ inv(bind)); dof_axis: (D, 3) world axis of each DOF; dof_origin: (D, 3) world
    pivot of each DOF (metres).
    """

    q: np.ndarray
    world: np.ndarray
    skin: np.ndarray
    dof_axis: np.ndarray
    dof_origin: np.ndarray


@dataclass(frozen=True)
class SurfaceBinding:
    """Precomputed skinning data of P surface points; build with :meth:`Kinematics.bind`.

    y: (J, 4, P) weighted homogeneous rest positions per joint (row 3 holds the weights);
    z: (J, 3, P) weighted rest normals per joint; weight_sub: (J, P) summed weights of each
    joint's subtree.
    """

    y: np.ndarray
    z: np.ndarray
    weight_sub: np.ndarray

    @property
    def n_points(self) -> int:
        return self.y.shape[2]

    def subset(self, ids: np.ndarray) -> "SurfaceBinding":
        """The binding of points ``ids`` (K,) of this one."""
        return SurfaceBinding(y=np.ascontiguousarray(self.y[:, :, ids]), z=np.ascontiguousarray(self.z[:, :, ids]),
                              weight_sub=np.ascontiguousarray(self.weight_sub[:, ids]))


class Kinematics:
    """Evaluator of one rig. Build once (``rig.kinematics()``), then call per frame."""

    def __init__(self, rig: Rig):
        self.rig = rig
        joints, dofs = rig.joints, rig.dofs
        n_joints, n_dofs = len(joints), len(dofs)
        self.n_joints, self.n_dofs = n_joints, n_dofs
        self.parent = np.array([j.parent for j in joints], dtype=np.int64)
        self.rest_local = np.stack([np.asarray(j.rest_local, dtype=np.float64) for j in joints])

        depth = np.zeros(n_joints, dtype=np.int64)
        for i in range(1, n_joints):
            depth[i] = depth[self.parent[i]] + 1
        self.levels = [np.nonzero(depth == k)[0] for k in range(int(depth.max()) + 1)]

        # Ancestor-or-self matrix: subtree[a, j] = 1 when joint j lies in the subtree of a.
        subtree = np.eye(n_joints)
        for i in range(n_joints - 1, 0, -1):
            subtree[self.parent[i]] += subtree[i]
        self.subtree = (subtree > 0).astype(np.float64)

        self.dof_joint = np.array([d.joint for d in dofs], dtype=np.int64)
        axes = np.array([np.asarray(d.axis, dtype=np.float64) for d in dofs]).reshape(n_dofs, 3)
        self.is_rotation = np.array([d.kind == "rotate" for d in dofs], dtype=bool)
        rot = self.is_rotation.astype(np.float64)

        # Per-DOF constant parts of the DOF transform A(q) = I + sin q K + (1 - cos q) K^2 + q T.
        skew = np.zeros((n_dofs, 4, 4))
        skew[:, 0, 1], skew[:, 0, 2] = -axes[:, 2], axes[:, 1]
        skew[:, 1, 0], skew[:, 1, 2] = axes[:, 2], -axes[:, 0]
        skew[:, 2, 0], skew[:, 2, 1] = -axes[:, 1], axes[:, 0]
        skew *= rot[:, None, None]
        self._k = skew
        self._k2 = skew @ skew
        trans = np.zeros((n_dofs, 4, 4))
        trans[:, :3, 3] = axes * (1.0 - rot)[:, None]
        self._t = trans
        self._axes_local = axes

        # joints parents first (the compiled forward kinematics reads it, rig/forward_kernel.py)
        self._order = np.concatenate(self.levels).astype(np.int64)
        self.bind_world = self._bind_world(rig.rest_pose)
        self.inv_bind = np.linalg.inv(self.bind_world)
        self._vertex_bindings: dict[str, SurfaceBinding] = {}

    def _bind_world(self, q: np.ndarray) -> np.ndarray:
        """(J, 4, 4) world transforms at q, joint by joint in NumPy: reading a rig needs only
        this, once, and must not start the compiler (numba's import and code take ~125 MB,
        past what the service allows an upload's validation in its tests); :meth:`pose` is the
        compiled pass, checked against this at the rest pose (tests/test_kinematics.py)."""
        a = self._dof_transforms(np.asarray(q, dtype=np.float64))
        local = self.rest_local.copy()
        for d, j in enumerate(self.dof_joint):
            local[j] = local[j] @ a[d]
        world = np.empty_like(local)
        for j in self._order:
            world[j] = local[j] if self.parent[j] < 0 else world[self.parent[j]] @ local[j]
        return world

    # ---- forward kinematics ----------------------------------------------------------------
    def _dof_transforms(self, q: np.ndarray) -> np.ndarray:
        """(D, 4, 4) each DOF's own transform A(q) = I + sin q K + (1 - cos q) K^2 + q T."""
        s = np.sin(q)[:, None, None]
        c = (1.0 - np.cos(q))[:, None, None]
        return np.eye(4) + s * self._k + c * self._k2 + q[:, None, None] * self._t

    def _forward(self, q: np.ndarray, inv_bind: np.ndarray):
        """(world, skin = world @ inv_bind, dof_axis, dof_origin) at q (D,)
        (:func:`~retarget_core.rig.forward_kernel.forward`)."""
        from .forward_kernel import forward  # numba is imported here, on the first pose

        return forward(np.ascontiguousarray(q, dtype=np.float64), self._order, self.parent, self.dof_joint,
                        np.ascontiguousarray(self._k), np.ascontiguousarray(self._k2), np.ascontiguousarray(self._t),
                        np.ascontiguousarray(self.rest_local), np.ascontiguousarray(inv_bind),
                        np.ascontiguousarray(self._axes_local))

    def pose(self, q) -> Pose:
        """Evaluate joint transforms and DOF frames at q: (D,) DOF values."""
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (self.n_dofs,):
            raise InputError(f"pose must have shape ({self.n_dofs},), got {q.shape}", element="DOF vector")
        world, skin, dof_axis, dof_origin = self._forward(q, self.inv_bind)
        return Pose(q=q, world=world, skin=skin, dof_axis=dof_axis, dof_origin=dof_origin)

    # ---- binding surface points ------------------------------------------------------------
    def _mesh(self, mesh: str) -> SkinnedMesh:
        if mesh == "surface":
            return self.rig.surface
        if mesh == "visual" and self.rig.visual is not None:
            return self.rig.visual
        raise KeyError(f"rig {self.rig.name!r} has no mesh {mesh!r}")

    def _binding(self, weights: np.ndarray, rest_points: np.ndarray, rest_normals: np.ndarray) -> SurfaceBinding:
        """weights: (P, J); rest_points, rest_normals: (P, 3)."""
        wt = np.ascontiguousarray(weights.T)  # (J, P)
        y = np.empty((self.n_joints, 4, len(rest_points)))
        y[:, :3, :] = wt[:, None, :] * rest_points.T[None]
        y[:, 3, :] = wt
        z = wt[:, None, :] * rest_normals.T[None]
        return SurfaceBinding(y=y, z=np.ascontiguousarray(z), weight_sub=self.subtree @ wt)

    def bind(self, points: SurfacePoints, mesh: str = "surface") -> SurfaceBinding:
        """Skinning data of surface points given as (face, barycentric) on ``mesh``."""
        m = self._mesh(mesh)
        points.validate(m.faces)
        corners = m.faces[points.faces]  # (P, 3)
        dense, vertex_normals = self._vertex_data(mesh)
        weights = np.einsum("pk,pkj->pj", points.barycentric, dense[corners])
        rest = np.einsum("pk,pkd->pd", points.barycentric, m.vertices[corners])
        normals = np.einsum("pk,pkd->pd", points.barycentric, vertex_normals[corners])
        return self._binding(weights, rest, normals)

    def _vertex_data(self, mesh: str):
        """Dense skin weights (V, J) and rest vertex normals (V, 3) of ``mesh``, computed once
        (a solve binds new contact points every frame)."""
        cache = self.__dict__.setdefault("_vertex_data_cache", {})
        if mesh not in cache:
            m = self._mesh(mesh)
            cache[mesh] = (m.dense_weights(self.n_joints), m.vertex_normals())
        return cache[mesh]

    def bind_vertices(self, mesh: str = "surface") -> SurfaceBinding:
        """Skinning data of every vertex of ``mesh`` (cached)."""
        if mesh not in self._vertex_bindings:
            dense, normals = self._vertex_data(mesh)
            self._vertex_bindings[mesh] = self._binding(dense, self._mesh(mesh).vertices, normals)
        return self._vertex_bindings[mesh]

    # ---- evaluation ------------------------------------------------------------------------
    def _as_pose(self, pose_or_q) -> Pose:
        return pose_or_q if isinstance(pose_or_q, Pose) else self.pose(pose_or_q)

    def points(self, pose: Pose | np.ndarray, binding: SurfaceBinding) -> np.ndarray:
        """(P, 3) world positions of bound surface points."""
        pose = self._as_pose(pose)
        # sum over joints j and homogeneous coordinates b of M_j[a, b] y_j[b, p], as one product.
        m = pose.skin[:, :3, :].transpose(1, 0, 2).reshape(3, -1)  # (3, J*4)
        return (m @ binding.y.reshape(-1, binding.n_points)).T

    def _subtree_sums(self, transforms: np.ndarray, weighted: np.ndarray) -> np.ndarray:
        """Per joint a, sum over its subtree of transforms[j] @ weighted[j]: (J, R, P)."""
        contrib = transforms @ weighted  # (J, R, P)
        n_joints, rows, n_points = contrib.shape
        return (self.subtree @ contrib.reshape(n_joints, -1)).reshape(n_joints, rows, n_points)

    def _lever_maps(self, pose: Pose) -> np.ndarray:
        """(D, 3, 4) maps from a subtree's [sum of skinned points; sum of weights] to the
        derivative of a point: [K_d | -omega_d x o_d] for rotations, [0 | axis_d] for translations."""
        axis, origin = pose.dof_axis, pose.dof_origin
        maps = np.zeros((self.n_dofs, 3, 4))
        maps[:, 0, 1], maps[:, 0, 2] = -axis[:, 2], axis[:, 1]
        maps[:, 1, 0], maps[:, 1, 2] = axis[:, 2], -axis[:, 0]
        maps[:, 2, 0], maps[:, 2, 1] = -axis[:, 1], axis[:, 0]
        maps[:, :, 3] = -np.cross(axis, origin)
        if not self.is_rotation.all():
            tr = ~self.is_rotation
            maps[tr] = 0.0
            maps[tr, :, 3] = axis[tr]
        return maps

    def points_jacobian(self, pose: Pose | np.ndarray, binding: SurfaceBinding):
        """Positions (P, 3) and their Jacobian (P, 3, D) with respect to every DOF (the
        Jacobian is returned as a transposed view of a (D, 3, P) array)."""
        pose = self._as_pose(pose)
        sums = self._subtree_sums(pose.skin, binding.y)  # (J, 4, P); row 3 = subtree weights
        jac = self._lever_maps(pose) @ sums[self.dof_joint]  # (D, 3, P)
        # joint 0 is the only root (Rig.validate), so its subtree sum is the point itself.
        return sums[0, :3].T, jac.transpose(2, 1, 0)

    def points_vjp(self, pose: Pose | np.ndarray, binding: SurfaceBinding, cotangent: np.ndarray) -> np.ndarray:
        """(D,) gradient sum_p cotangent[p] . dpoint_p/dq without forming the Jacobian:
        cotangent (P, 3). This is what a solver needs for a scalar objective, at O(J P) cost."""
        pose = self._as_pose(pose)
        cotangent = np.asarray(cotangent, dtype=np.float64)
        # Per joint: moments sum_p c_jp (x) r_p, whose antisymmetric part is sum_p c_jp x r_p,
        # and forces sum_p w_jp r_p; the last row of y carries the weights.
        moments = (pose.skin @ binding.y) @ cotangent  # (J, 4, 3)
        torque = np.stack(
            [moments[:, 1, 2] - moments[:, 2, 1], moments[:, 2, 0] - moments[:, 0, 2], moments[:, 0, 1] - moments[:, 1, 0]],
            axis=1,
        )
        force = moments[:, 3, :]
        return self._wrench_gradient(pose, torque, force)

    def _wrench_gradient(self, pose: Pose, torque: np.ndarray, force: np.ndarray) -> np.ndarray:
        """(D,) gradient from per-joint torques and forces (J, 3) of cotangents on the points a
        joint moves: each DOF sees the sums over its joint's subtree."""
        torque, force = self.subtree @ torque, self.subtree @ force
        a = self.dof_joint
        axis, origin = pose.dof_axis, pose.dof_origin
        grad = np.einsum("da,da->d", axis, torque[a] - np.cross(origin, force[a]))
        tr = ~self.is_rotation
        if tr.any():
            grad[tr] = np.einsum("da,da->d", axis[tr], force[a[tr]])
        return grad

    def rigid_points_vjp(self, pose: Pose | np.ndarray, joints: np.ndarray, points: np.ndarray,
                         cotangent: np.ndarray) -> np.ndarray:
        """(D,) gradient sum_k cotangent[k] . dx_k/dq for points (K, 3) world that move rigidly
        with joint ``joints[k]`` (K,) at this pose: the velocity of a point fixed in a joint's
        frame, which is what a query in that frame (a collision grid) differentiates through."""
        pose = self._as_pose(pose)
        c = np.asarray(cotangent, dtype=np.float64)
        torque = np.zeros((self.n_joints, 3))
        force = np.zeros((self.n_joints, 3))
        np.add.at(torque, joints, np.cross(points, c))
        np.add.at(force, joints, c)
        return self._wrench_gradient(pose, torque, force)

    def rigid_points_jacobian(self, pose: Pose | np.ndarray, joints: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(D, 3, K) Jacobian of points (K, 3) world moving rigidly with ``joints`` (K,)."""
        pose = self._as_pose(pose)
        moves = self.subtree[self.dof_joint][:, joints]  # (D, K): DOF d moves joint joints[k]
        axis, origin = pose.dof_axis, pose.dof_origin
        lever = np.asarray(points, dtype=np.float64)[None] - origin[:, None, :]  # (D, K, 3)
        vel = np.cross(axis[:, None, :], lever)
        tr = ~self.is_rotation
        if tr.any():
            vel[tr] = axis[tr][:, None, :]
        return (vel * moves[:, :, None]).transpose(0, 2, 1)

    def normals_vjp(self, pose: Pose | np.ndarray, binding: SurfaceBinding, cotangent: np.ndarray):
        """Unit normals (P, 3) and the (D,) gradient sum_p cotangent[p] . dnormal_p/dq, without
        forming the Jacobian: with u = sum_j R_j z_j and n = u/|u|, dn = (I - n n^T) du / |u|,
        du/dq_d = omega_d x sum_{j in sub(a)} R_j z_j, so the gradient is omega_d . (subtree sum of
        sum_p (R_j z_jp) x w_p) with w = (I - n n^T) cotangent / |u|."""
        pose = self._as_pose(pose)
        contrib = pose.skin[:, :3, :3] @ binding.z  # (J, 3, P)
        u = contrib.sum(axis=0)  # (3, P)
        length = np.sqrt(np.einsum("ap,ap->p", u, u))
        n = u / length
        c = np.asarray(cotangent, dtype=np.float64).T  # (3, P)
        w = (c - n * np.einsum("ap,ap->p", n, c)) / length
        moments = contrib @ w.T  # (J, 3, 3): sum_p a_p (x) w_p
        torque = np.stack([moments[:, 1, 2] - moments[:, 2, 1], moments[:, 2, 0] - moments[:, 0, 2],
                           moments[:, 0, 1] - moments[:, 1, 0]], axis=1)
        torque = self.subtree @ torque
        grad = np.einsum("da,da->d", pose.dof_axis, torque[self.dof_joint])
        grad[~self.is_rotation] = 0.0
        return n.T, grad

    def normals(self, pose: Pose | np.ndarray, binding: SurfaceBinding) -> np.ndarray:
        """(P, 3) unit skinned normals of bound surface points."""
        pose = self._as_pose(pose)
        r = pose.skin[:, :3, :3].transpose(1, 0, 2).reshape(3, -1)  # (3, J*3)
        u = (r @ binding.z.reshape(-1, binding.n_points)).T
        return u / np.linalg.norm(u, axis=1, keepdims=True)

    def normals_jacobian(self, pose: Pose | np.ndarray, binding: SurfaceBinding):
        """Unit normals (P, 3) and their Jacobian (P, 3, D) (a transposed view of (D, 3, P))."""
        pose = self._as_pose(pose)
        sums = self._subtree_sums(pose.skin[:, :3, :3], binding.z)  # (J, 3, P)
        u = sums[0]  # (3, P)
        # Rotations: du = K_d @ sums; translations leave normals unchanged (their block is 0).
        du = self._lever_maps(pose)[:, :, :3] @ sums[self.dof_joint]  # (D, 3, P)
        length = np.sqrt(np.einsum("ap,ap->p", u, u))
        n = u / length
        # dn = (I - n n^T) du / |u|, written out per component to avoid large temporaries.
        radial = du[:, 0] * n[0]
        radial += du[:, 1] * n[1]
        radial += du[:, 2] * n[2]
        dn = radial[:, None, :] * n
        np.subtract(du, dn, out=dn)
        dn *= 1.0 / length
        return n.T, dn.transpose(2, 1, 0)

    def skin(self, pose: Pose | np.ndarray, mesh: str = "surface") -> np.ndarray:
        """(V, 3) posed vertices of ``mesh`` by linear blend skinning."""
        return self.points(pose, self.bind_vertices(mesh))


