"""The rig model: a joint tree, per-joint DOFs with limits, and linearly blend-skinned surfaces.

Conventions (column vectors, 4x4 homogeneous transforms):

- Joint j's local transform at DOF values q is
  ``rest_local[j] @ A_1(q_1) @ A_2(q_2) @ ...`` where the A are the joint's DOFs in their
  stated order: a rotation by q about a unit axis of the joint frame, or a translation by q
  (metres) along it. ``rest_local`` is therefore the transform at q = 0.
- World transform ``G_j = G_parent(j) @ local_j``; the root's parent is the identity.
- The rest pose is the DOF vector ``rest`` (each DOF's rest value, inside its limits); the
  skinned surfaces are authored in world coordinates at that pose (the bind pose), and
  ``skin = G_j(q) @ inv(G_j(rest))`` carries them to any pose.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..mesh.geometry import vertex_normals
from ..mesh.topology import MeshTopologyReport, check_closed_manifold

#: Named axes accepted in DOF specs (joint-local frame). A leading "-" flips the axis.
NAMED_AXES = {
    "x": (1.0, 0.0, 0.0),
    "y": (0.0, 1.0, 0.0),
    "z": (0.0, 0.0, 1.0),
}

DOF_KINDS = ("rotate", "translate")

#: Limits of the free root: translations in metres, rotations in radians.
ROOT_TRANSLATION_LIMIT = 2.0
#: A joint matrix is rigid when its rotation part is orthonormal within this (max |R^T R - I|;
#: float32 matrices from a DCC are off by ~1e-7) and its homogeneous row is (0, 0, 0, 1) within
#: RIGID_HOMOGENEOUS_TOL; readers re-orthonormalise what passes (:func:`orthonormalized`).
RIGID_ROTATION_TOL = 1e-5
RIGID_HOMOGENEOUS_TOL = 1e-6
ROOT_ROTATION_LIMIT = 2 * np.pi


def parse_axis(axis, *, element: str = "", source: str = "") -> np.ndarray:
    """A unit 3-vector from a name ("x", "-z") or three numbers."""
    if isinstance(axis, str):
        name = axis.strip().lower()
        sign = -1.0 if name.startswith("-") else 1.0
        name = name.lstrip("+-")
        if name not in NAMED_AXES:
            raise InputError(
                f"unknown axis name {axis!r}; use x, y, z (optionally with a leading '-') "
                "or three numbers",
                source=source,
                element=element,
            )
        return sign * np.array(NAMED_AXES[name])
    vec = np.asarray(axis, dtype=np.float64).reshape(-1)
    if vec.shape != (3,) or not np.all(np.isfinite(vec)):
        raise InputError(f"axis must be 3 finite numbers, got {axis!r}", source=source, element=element)
    norm = np.linalg.norm(vec)
    if norm < 1e-9:
        raise InputError("axis has zero length", source=source, element=element)
    return vec / norm


@dataclass
class Joint:
    """One node of the joint tree.

    name: unique; parent: index of the parent joint (-1 for the root; parents come first);
    rest_local: (4, 4) transform from the parent's frame to this joint's frame at q = 0.
    """

    name: str
    parent: int
    rest_local: np.ndarray


@dataclass
class Dof:
    """One scalar degree of freedom of a joint.

    kind: "rotate" (radians about ``axis``) or "translate" (metres along ``axis``);
    axis: (3,) unit vector in the joint's frame; lower <= rest <= upper.
    DOFs of one joint apply in the order they appear in ``Rig.dofs``.
    """

    name: str
    joint: int
    kind: str
    axis: np.ndarray
    lower: float
    upper: float
    rest: float = 0.0


def rigidity_error(m: np.ndarray) -> str | None:
    """Why the 4x4 ``m`` is not a rigid transform within the tolerances (None when it is)."""
    m = np.asarray(m, dtype=np.float64)
    r = m[:3, :3]
    ortho = float(np.abs(r.T @ r - np.eye(3)).max())
    homogeneous = float(np.abs(m[3] - [0, 0, 0, 1]).max())
    if ortho > RIGID_ROTATION_TOL:
        scale = np.linalg.norm(r, axis=0)
        return (f"its rotation part is off orthonormal by {ortho:.3g} (tolerance {RIGID_ROTATION_TOL:g}; "
                f"column lengths {', '.join(f'{x:.6g}' for x in scale)}: a scale or shear)")
    if np.linalg.det(r) < 0:
        return "it mirrors (determinant < 0)"
    if homogeneous > RIGID_HOMOGENEOUS_TOL:
        return f"its last row is off (0, 0, 0, 1) by {homogeneous:.3g} (tolerance {RIGID_HOMOGENEOUS_TOL:g})"
    return None


def orthonormalized(m: np.ndarray) -> np.ndarray:
    """(..., 4, 4): the nearest rigid transforms (rotation by SVD, last row exactly 0 0 0 1)."""
    m = np.array(m, dtype=np.float64)
    u, _, vt = np.linalg.svd(m[..., :3, :3])
    m[..., :3, :3] = u @ vt
    m[..., 3, :] = (0.0, 0.0, 0.0, 1.0)
    return m


def free_root(translation_limit: float = ROOT_TRANSLATION_LIMIT) -> tuple["Joint", list["Dof"]]:
    """The 6-DOF root every hand gets: joint "root" at the world origin with DOFs
    root_tx, root_ty, root_tz (translate) then root_rx, root_ry, root_rz (rotate), world axes."""
    joint = Joint("root", -1, np.eye(4))
    dofs = []
    for name, axis in (("tx", (1, 0, 0)), ("ty", (0, 1, 0)), ("tz", (0, 0, 1))):
        dofs.append(Dof(f"root_{name}", 0, "translate", np.array(axis, float), -translation_limit, translation_limit, 0.0))
    for name, axis in (("rx", (1, 0, 0)), ("ry", (0, 1, 0)), ("rz", (0, 0, 1))):
        dofs.append(Dof(f"root_{name}", 0, "rotate", np.array(axis, float), -ROOT_ROTATION_LIMIT, ROOT_ROTATION_LIMIT, 0.0))
    return joint, dofs


@dataclass
class SkinnedMesh:
    """A triangle mesh skinned to the rig by linear blend skinning.

    vertices: (V, 3) world positions at the bind (rest) pose, metres;
    faces: (F, 3) int64;
    joint_indices: (V, K) int64 and joint_weights: (V, K) float64, K influences per vertex
    (unused slots have weight 0); each row of weights sums to 1.
    """

    vertices: np.ndarray
    faces: np.ndarray
    joint_indices: np.ndarray
    joint_weights: np.ndarray

    def __post_init__(self):
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int64)
        self.joint_indices = np.ascontiguousarray(self.joint_indices, dtype=np.int64)
        self.joint_weights = np.ascontiguousarray(self.joint_weights, dtype=np.float64)
        if self.joint_indices.ndim == 1:
            self.joint_indices = self.joint_indices[:, None]
        if self.joint_weights.ndim == 1:
            self.joint_weights = self.joint_weights[:, None]

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    def dense_weights(self, n_joints: int) -> np.ndarray:
        """(V, J) skin weight matrix."""
        dense = np.zeros((self.n_vertices, n_joints))
        rows = np.repeat(np.arange(self.n_vertices), self.joint_indices.shape[1])
        np.add.at(dense, (rows, self.joint_indices.reshape(-1)), self.joint_weights.reshape(-1))
        return dense

    def vertex_normals(self) -> np.ndarray:
        """(V, 3) unit area-weighted vertex normals at the bind pose."""
        return vertex_normals(self.vertices, self.faces)

    def topology(self) -> MeshTopologyReport:
        return check_closed_manifold(self.faces, self.n_vertices)

    def validate(self, n_joints: int, *, source: str = "", element: str = "surface") -> None:
        """Raise InputError naming the bad part of the mesh or its skin weights."""
        v, f = self.vertices, self.faces
        if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
            raise InputError(f"vertices must have shape (V, 3), got {v.shape}", source=source, element=element)
        if not np.all(np.isfinite(v)):
            bad = int(np.nonzero(~np.all(np.isfinite(v), axis=1))[0][0])
            raise InputError(f"vertex {bad} is NaN or infinite", source=source, element=element)
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise InputError(f"faces must have shape (F, 3), got {f.shape}", source=source, element=element)
        if f.min() < 0 or f.max() >= len(v):
            raise InputError(
                f"face indices must lie in [0, {len(v)}), found {int(f.min())}..{int(f.max())}",
                source=source,
                element=element,
            )
        ji, jw = self.joint_indices, self.joint_weights
        if ji.shape != jw.shape or ji.shape[0] != len(v):
            raise InputError(
                f"skin joint indices {ji.shape} and weights {jw.shape} must both be (V={len(v)}, K)",
                source=source,
                element=element + " skin weights",
            )
        if ji.min() < 0 or ji.max() >= n_joints:
            raise InputError(
                f"skin joint index out of range [0, {n_joints})", source=source, element=element + " skin weights"
            )
        if not np.all(np.isfinite(jw)) or np.any(jw < -1e-9):
            bad = int(np.nonzero(~np.all(np.isfinite(jw) & (jw >= -1e-9), axis=1))[0][0])
            raise InputError(
                f"vertex {bad} has a negative or non-finite skin weight",
                source=source,
                element=element + " skin weights",
            )
        sums = jw.sum(axis=1)
        if np.any(sums < 1e-12):
            bad = int(np.nonzero(sums < 1e-12)[0][0])
            raise InputError(f"vertex {bad} has no skin weight", source=source, element=element + " skin weights")
        off = np.abs(sums - 1.0) > 1e-5
        if np.any(off):
            bad = int(np.nonzero(off)[0][0])
            raise InputError(
                f"skin weights of vertex {bad} sum to {sums[bad]:.6g}, not 1 "
                "(normalise them before use)",
                source=source,
                element=element + " skin weights",
            )


@dataclass
class Rig:
    """A target (or source) hand: joints, DOFs and skinned surfaces.

    ``surface`` is the closed manifold surface every pipeline stage works on (for robot hands
    it is the generated wrapper); ``visual`` optionally holds display geometry that is not
    required to be closed (for example the robot's own link meshes).
    """

    name: str
    joints: list[Joint]
    dofs: list[Dof]
    surface: SkinnedMesh
    visual: SkinnedMesh | None = None
    metadata: dict = field(default_factory=dict)

    # ---- derived facts -------------------------------------------------------------------
    @property
    def n_joints(self) -> int:
        return len(self.joints)

    @property
    def n_dofs(self) -> int:
        return len(self.dofs)

    @property
    def joint_names(self) -> list[str]:
        return [j.name for j in self.joints]

    @property
    def dof_names(self) -> list[str]:
        return [d.name for d in self.dofs]

    @property
    def lower(self) -> np.ndarray:
        return np.array([d.lower for d in self.dofs])

    @property
    def upper(self) -> np.ndarray:
        return np.array([d.upper for d in self.dofs])

    @property
    def rest_pose(self) -> np.ndarray:
        """(D,) DOF values of the rest (bind) pose."""
        return np.array([d.rest for d in self.dofs])

    def joint_index(self, name: str) -> int:
        for i, j in enumerate(self.joints):
            if j.name == name:
                return i
        raise KeyError(f"rig {self.name!r} has no joint {name!r}")

    def dof_index(self, name: str) -> int:
        for i, d in enumerate(self.dofs):
            if d.name == name:
                return i
        raise KeyError(f"rig {self.name!r} has no DOF {name!r}")

    def kinematics(self):
        """The (cached) vectorised evaluator of this rig; see :class:`Kinematics`."""
        from .kinematics import Kinematics

        cached = self.__dict__.get("_kinematics")
        if cached is None:
            cached = Kinematics(self)
            self.__dict__["_kinematics"] = cached
        return cached

    def coupling(self):
        """The (cached) linear couplings between DOFs; see :class:`~retarget_core.rig.coupling.DofCoupling`."""
        from .coupling import DofCoupling

        cached = self.__dict__.get("_coupling")
        if cached is None:
            cached = DofCoupling.of_rig(self)
            self.__dict__["_coupling"] = cached
        return cached

    def random_pose(self, rng: np.random.Generator, *, root_scale: float = 1.0) -> np.ndarray:
        """(D,) a pose drawn uniformly within the limits; root DOFs (joint 0) are drawn within
        +-root_scale (m or rad) of rest, clipped to their limits, so the hand stays near the origin."""
        lo, hi, rest = self.lower, self.upper, self.rest_pose
        q = rng.uniform(lo, hi)
        for i, d in enumerate(self.dofs):
            if d.joint == 0:
                span = 0.1 * root_scale if d.kind == "translate" else root_scale
                q[i] = np.clip(rest[i] + rng.uniform(-span, span), lo[i], hi[i])
        return q

    # ---- validation ----------------------------------------------------------------------
    def validate(self, *, source: str = "", require_closed: bool = True) -> None:
        """Raise InputError naming the file (``source``) and element for any inconsistency:
        joint order, transforms, DOF axes and limits, rest pose within limits, skin weights,
        and (when ``require_closed``) a closed, connected, manifold surface."""
        if not self.joints:
            raise InputError("rig has no joints", source=source)
        names = set()
        for i, j in enumerate(self.joints):
            el = f"joint {j.name!r}"
            if j.name in names:
                raise InputError("joint name is used twice", source=source, element=el)
            names.add(j.name)
            if i == 0 and j.parent != -1:
                raise InputError("the first joint must be the root (parent -1)", source=source, element=el)
            if i > 0 and not (0 <= j.parent < i):
                raise InputError(
                    f"parent index {j.parent} must refer to an earlier joint", source=source, element=el
                )
            m = np.asarray(j.rest_local, dtype=np.float64)
            if m.shape != (4, 4) or not np.all(np.isfinite(m)):
                raise InputError("rest transform must be a finite 4x4 matrix", source=source, element=el)
            why = rigidity_error(m)
            if why is not None:
                raise InputError(f"rest transform is not a rigid transform: {why}", source=source, element=el)
        dof_names = set()
        last_joint = -1
        for d in self.dofs:
            el = f"DOF {d.name!r}"
            if d.name in dof_names:
                raise InputError("DOF name is used twice", source=source, element=el)
            dof_names.add(d.name)
            if not (0 <= d.joint < self.n_joints):
                raise InputError(f"joint index {d.joint} out of range", source=source, element=el)
            if d.joint < last_joint:
                raise InputError("DOFs must be listed joint by joint, in joint order", source=source, element=el)
            last_joint = d.joint
            if d.kind not in DOF_KINDS:
                raise InputError(f"kind must be one of {DOF_KINDS}, got {d.kind!r}", source=source, element=el)
            axis = np.asarray(d.axis, dtype=np.float64)
            if axis.shape != (3,) or not np.all(np.isfinite(axis)) or abs(np.linalg.norm(axis) - 1) > 1e-6:
                raise InputError("axis must be a unit 3-vector", source=source, element=el)
            for label, value in (("lower", d.lower), ("upper", d.upper), ("rest", d.rest)):
                if value is None or not np.isfinite(value):
                    raise InputError(
                        f"{label} limit is missing or not finite: every DOF needs finite limits",
                        source=source,
                        element=el,
                    )
            if not d.lower < d.upper:
                raise InputError(f"lower limit {d.lower} is not below upper limit {d.upper}", source=source, element=el)
            if not (d.lower <= d.rest <= d.upper):
                raise InputError(
                    f"rest value {d.rest} lies outside its limits [{d.lower}, {d.upper}]",
                    source=source,
                    element=el,
                )
        from .coupling import DofCoupling

        coupling = DofCoupling.of_rig(self)
        rest = self.rest_pose
        for i in coupling.followers:
            want = coupling.multiplier[i] * rest[coupling.leader[i]] + coupling.offset[i]
            if abs(rest[i] - want) > 1e-6:
                raise InputError(f"rest value {rest[i]:.6g} breaks its coupling to {self.dofs[coupling.leader[i]].name!r} "
                                 f"(which gives {want:.6g})", source=source, element=f"DOF {self.dofs[i].name!r}")
        self.surface.validate(self.n_joints, source=source, element="surface")
        if self.visual is not None:
            self.visual.validate(self.n_joints, source=source, element="visual")
        if require_closed:
            report = self.surface.topology()
            if not (report.closed and report.manifold) or report.components != 1:
                raise InputError(
                    "the rig's surface must be a closed, connected 2-manifold, but it is "
                    + report.describe(),
                    source=source,
                    element="surface",
                )


#: A root joint whose rest is this close to the identity (m, and rotation entries) carries the
#: free root itself (float32 files write the identity with ~1e-7 of noise).
IDENTITY_ROOT_TOL = 1e-6
#: The free root's DOF names, in order (:func:`free_root`).
ROOT_DOF_NAMES = ["root_tx", "root_ty", "root_tz", "root_rx", "root_ry", "root_rz"]


def with_free_root(rig: Rig) -> Rig:
    """``rig`` with the standard free root (:func:`free_root`) at joint 0, wherever the hand sits
    and whatever its own root joint's rest transform: when the rig already starts with it, the
    rig itself; when joint 0 has an identity rest (within IDENTITY_ROOT_TOL) and no DOFs, the
    six DOFs on it; otherwise a
    new joint ``root`` (``root_1``, ... when taken) at the world origin, parent of the rig's own
    root joint, which keeps its rest transform and DOFs (skin indices shift by one)."""
    if rig.dof_names[:6] == ROOT_DOF_NAMES:
        return rig
    own_root = rig.joints[0]
    if not any(d.joint == 0 for d in rig.dofs) and np.abs(own_root.rest_local - np.eye(4)).max() <= IDENTITY_ROOT_TOL:
        _, dofs = free_root()
        # within float32 noise of the identity: exactly the identity, as the free root expects
        joints = [Joint(own_root.name, -1, np.eye(4))] + list(rig.joints[1:])
        return Rig(name=rig.name, joints=joints, dofs=dofs + list(rig.dofs), surface=rig.surface,
                   visual=rig.visual, metadata=dict(rig.metadata))
    taken = set(rig.joint_names)
    name, k = "root", 0
    while name in taken:
        k += 1
        name = f"root_{k}"
    joint, dofs = free_root()
    joints = [Joint(name, -1, joint.rest_local)] + [
        Joint(j.name, j.parent + 1, np.array(j.rest_local, float)) for j in rig.joints]
    shifted = [Dof(d.name, d.joint + 1, d.kind, np.array(d.axis, float), d.lower, d.upper, d.rest) for d in rig.dofs]

    def shift(mesh):
        if mesh is None:
            return None
        return SkinnedMesh(vertices=mesh.vertices.copy(), faces=mesh.faces.copy(),
                           joint_indices=mesh.joint_indices + 1, joint_weights=mesh.joint_weights.copy())

    return Rig(name=rig.name, joints=joints, dofs=dofs + shifted, surface=shift(rig.surface),
               visual=shift(rig.visual), metadata={**rig.metadata, "free_root_added": name})
