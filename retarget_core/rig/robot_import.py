"""Robot hands from URDF (yourdfpy) and MJCF (MuJoCo) files as :class:`Rig` objects.

Both loaders produce the same layout:

- joint 0 is an added ``root`` joint with six DOFs (``root_tx/ty/tz`` translations within
  +-2 m, then ``root_rx/ry/rz`` rotations within +-2 pi, all about world axes, rest 0), the
  parent of the robot's base link / root body, exactly like the procedural hands;
- world coordinates are those of the source file (root DOFs at 0 = the file's placement);
- ``Rig.visual`` is the robot's own display geometry concatenated, rigidly skinned (weight 1
  to the joint that carries it), world coordinates at the rest pose;
- ``Rig.surface`` is a closed, connected, manifold wrapper generated around that same display
  geometry by :func:`retarget_core.rig.wrapper.build_wrapper` (robot meshes are rarely
  watertight, so they cannot be the surface themselves);
- every DOF has finite limits; its rest value is 0 clipped into its limits; geometry is
  authored at that rest pose.

Choices specific to each format are described in :func:`load_urdf` and :func:`load_mjcf`.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from pathlib import Path, PurePosixPath

import logging

import numpy as np

from ..errors import InputError
from .coupling import MIN_MULTIPLIER, Coupling, couple_rest, tendon_coupling
from .model import Dof, Joint, Rig, SkinnedMesh, free_root
from .wrapper import build_wrapper

logger = logging.getLogger(__name__)

WRAPPER_OFFSET = 0.0015


# ---- shared helpers ------------------------------------------------------------------------
def _unique_names(joints) -> dict[str, str]:
    """Rename robot joints whose name clashes with an earlier one (the added ``root`` first)
    by appending ``_link`` (then ``_link2``...). Returns {new name: original name}."""
    seen = set()
    renamed = {}
    for jt in joints:
        name, k = jt.name, 1
        while name in seen:
            name = f"{jt.name}_link" + (str(k) if k > 1 else "")
            k += 1
        if name != jt.name:
            renamed[name] = jt.name
            jt.name = name
        seen.add(name)
    return renamed


def _unit_axis(axis, *, source, element) -> np.ndarray:
    vec = np.asarray(axis, dtype=np.float64).reshape(-1)
    if vec.shape != (3,) or not np.all(np.isfinite(vec)) or np.linalg.norm(vec) < 1e-12:
        raise InputError(f"joint axis must be a non-zero 3-vector, got {axis!r}", source=source, element=element)
    return vec / np.linalg.norm(vec)


def _check_limits(lower, upper, *, source, element) -> tuple[float, float]:
    if lower is None or upper is None or not (np.isfinite(lower) and np.isfinite(upper)):
        raise InputError(
            "joint has no finite limits (lower and upper are required for every actuated joint)",
            source=source,
            element=element,
        )
    if not lower < upper:
        raise InputError(f"lower limit {lower} is not below upper limit {upper}", source=source, element=element)
    return float(lower), float(upper)


def _transform_points(m: np.ndarray, v: np.ndarray) -> np.ndarray:
    return v @ m[:3, :3].T + m[:3, 3]


def _rest_frames(joints, dofs) -> tuple[np.ndarray, np.ndarray]:
    """World joint frames at q = 0 and at the rest pose, (J, 4, 4) each."""
    from .kinematics import Kinematics

    probe = Rig(name="probe", joints=joints, dofs=dofs, surface=None)
    kin = Kinematics(probe)
    zero = kin.pose(np.zeros(len(dofs))).world
    return zero, kin.bind_world


def _finish(name, joints, dofs, pieces, source, metadata, wrapper_resolution) -> Rig:
    """pieces: (joint, vertices world at q = 0, faces). Moves them to the rest pose, builds
    the visual and the wrapper, validates."""
    if not pieces:
        raise InputError("the robot has no visual or collision geometry to build a surface from", source=source)
    zero, rest = _rest_frames(joints, dofs)
    carry = rest @ np.linalg.inv(zero)
    posed = [(j, _transform_points(carry[j], v), f) for j, v, f in pieces]
    verts, faces, owner = [], [], []
    base = 0
    for j, v, f in posed:
        verts.append(v)
        faces.append(f + base)
        owner.append(np.full(len(v), j, dtype=np.int64))
        base += len(v)
    visual = SkinnedMesh(
        np.concatenate(verts), np.concatenate(faces), np.concatenate(owner)[:, None], np.ones((base, 1))
    )
    surface = build_wrapper(
        posed,
        resolution=wrapper_resolution,
        offset=WRAPPER_OFFSET,
        parents=[jt.parent for jt in joints],
        link_names={i: jt.name for i, jt in enumerate(joints)},
    )
    rig = Rig(name=name, joints=joints, dofs=dofs, surface=surface, visual=visual, metadata=metadata)
    rig.validate(source=source)
    return rig


def _primitive(kind: str, size) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and faces of a primitive centred at the origin (capsules/cylinders along z)."""
    import trimesh

    if kind == "box":
        m = trimesh.creation.box(extents=np.asarray(size, float))
    elif kind == "sphere":
        m = trimesh.creation.icosphere(subdivisions=3, radius=float(size[0]))
    elif kind == "ellipsoid":
        m = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
        m = trimesh.Trimesh(m.vertices * np.asarray(size, float)[:3], m.faces, process=False)
    elif kind == "cylinder":  # size = (radius, full length)
        m = trimesh.creation.cylinder(radius=float(size[0]), height=float(size[1]), sections=32)
    elif kind == "capsule":  # size = (radius, full length of the cylindrical part)
        m = trimesh.creation.capsule(height=float(size[1]), radius=float(size[0]), count=[24, 24])
    else:  # pragma: no cover - callers filter kinds
        raise ValueError(kind)
    return np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)



# ---- confinement ---------------------------------------------------------------------------
class Confinement:
    """Every file a rig refers to must lie inside ``root`` (an unpacked upload).

    Checks are lexical first: a reference that is absolute, or whose ``..`` climbs above the
    root, is refused before anything is opened or stat-ed, so the refusal is the same whether
    the file outside exists or not. A reference inside the root that resolves (through a
    symbolic link) outside it is refused too. Errors name the file inside the root and the
    reference as written, never a path of the host."""

    def __init__(self, root):
        self.root = Path(os.path.abspath(root))
        self.real = Path(os.path.realpath(self.root))

    def shown(self, path: Path) -> str:
        """``path`` (inside the root) as the upload names it."""
        try:
            return Path(os.path.abspath(path)).relative_to(self.root).as_posix()
        except ValueError:
            return Path(path).name

    def scrub(self, text: str) -> str:
        """``text`` with the root's host paths removed."""
        for r in sorted({str(self.real), str(self.root)}, key=len, reverse=True):
            text = text.replace(r + os.sep, "").replace(r, ".")
        return text

    def _inside(self, p: Path, base: Path) -> bool:
        return p == base or base in p.parents

    def resolve(self, written: str, bases, *, source, element, what="file") -> Path:
        """The path ``written`` names, relative to each of ``bases`` (absolute folders inside
        the root); refused unless every interpretation stays inside the root. Returns the
        first interpretation (not checked for existence)."""
        if not written or "\\" in written or "\0" in written or PurePosixPath(written).is_absolute() or (
                len(written) > 1 and written[1] == ":"):
            self.refuse(written, source=source, element=element, what=what)
        out = None
        for base in bases:
            cand = Path(os.path.normpath(os.path.join(base, written)))
            if not self._inside(cand, self.root):
                self.refuse(written, source=source, element=element, what=what)
            # as normalised (what this module opens) and as joined (what MuJoCo opens)
            for real in (os.path.realpath(cand), os.path.realpath(os.path.join(base, written))):
                if not self._inside(Path(real), self.real):
                    self.refuse(written, source=source, element=element, what=what)
            out = cand if out is None else out
        return out

    def check_file(self, path: Path, *, source, element=None, what="file") -> Path:
        """``path`` itself (the file being loaded) must lie inside the root."""
        p = Path(os.path.abspath(path))
        if not self._inside(p, self.root) or not self._inside(Path(os.path.realpath(p)), self.real):
            raise InputError(f"{what} is outside the folder it is confined to", source=p.name, element=element)
        return p

    @staticmethod
    def refuse(written: str, *, source, element, what="file"):
        raise InputError(
            f"{what} {written!r} is outside the rig's own folder (absolute paths, file:// URIs, '..' above the "
            "folder, package:// outside it and links out of it are refused); it was not opened",
            source=source, element=element)


def _no_doctype(path: Path, *, source):
    """A confined XML file may not declare a DTD (entities could hide what the parsers see)."""
    head = path.read_bytes()
    if b"<!DOCTYPE" in head.upper() or b"<!ENTITY" in head.upper():
        raise InputError("XML with a DOCTYPE or entity declarations is not accepted", source=source)


# ---- URDF ----------------------------------------------------------------------------------
def _resolve_mesh_path(filename: str, urdf_dir: Path) -> Path | None:
    """Absolute path of a URDF mesh reference, or None when no candidate exists.

    Relative paths are relative to the URDF's folder; ``file://`` URIs are taken literally;
    ``package://pkg/rest`` is searched in the URDF's folder and each ancestor folder, both as
    ``<ancestor>/pkg/rest`` and, when the ancestor itself is named ``pkg``, ``<ancestor>/rest``."""
    if filename.startswith("file://"):
        p = Path(filename[len("file://") :])
        return p if p.is_file() else None
    if filename.startswith("package://"):
        rest = filename[len("package://") :]
        package, _, inner = rest.partition("/")
        for folder in [urdf_dir, *urdf_dir.parents]:
            for candidate in (folder / package / inner, folder / inner if folder.name == package else None):
                if candidate is not None and candidate.is_file():
                    return candidate
        return None
    p = Path(filename)
    if not p.is_absolute():
        p = urdf_dir / p
    return p if p.is_file() else None


def _resolve_mesh_confined(filename: str, urdf_dir: Path, conf: Confinement, *, source, element) -> Path | None:
    """:func:`_resolve_mesh_path` inside ``conf.root`` only: ``package://PKG/rest`` is looked
    for from the URDF's folder up to the root (``<folder>/PKG/rest``, ``<folder>/rest`` when
    the folder is named PKG) and finally as ``<root>/rest`` (the bundle is the package);
    ``file://`` URIs must name a relative path; anything resolving outside is refused unopened."""
    what = "mesh filename"
    if filename.startswith("file://"):
        inner = filename[len("file://"):]
        if not inner or inner.startswith("/"):
            conf.refuse(filename, source=source, element=element, what=what)
        p = conf.resolve(inner, [urdf_dir], source=source, element=element, what=what)
        return p if p.is_file() else None
    if filename.startswith("package://"):
        rest = filename[len("package://"):]
        package, _, inner = rest.partition("/")
        parts = PurePosixPath(inner).parts
        if (package in ("", ".", "..") or not inner or PurePosixPath(inner).is_absolute() or ".." in parts
                or "\\" in rest):
            conf.refuse(filename, source=source, element=element, what=what)
        folders, folder = [], Path(os.path.abspath(urdf_dir))
        while True:
            folders.append(folder)
            if folder == conf.root or conf.root not in folder.parents:
                break
            folder = folder.parent
        candidates = []
        for folder in folders:
            candidates.append(folder / package / inner)
            if folder.name == package:
                candidates.append(folder / inner)
        candidates.append(conf.root / inner)
        for cand in candidates:
            try:
                p = conf.resolve(os.path.relpath(cand, urdf_dir), [urdf_dir], source=source, element=element)
            except InputError:
                conf.refuse(filename, source=source, element=element, what=what)
            if p.is_file():
                return p
        return None
    if "://" in filename:
        conf.refuse(filename, source=source, element=element, what=what)
    p = conf.resolve(filename, [urdf_dir], source=source, element=element, what=what)
    return p if p.is_file() else None


def _load_mesh_file(path: Path, *, source, element, shown=None) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    try:
        mesh = trimesh.load(str(path), force="mesh")
    except Exception as exc:  # trimesh raises many kinds
        if shown is not None:
            raise InputError(f"cannot read mesh file {shown!r}: {str(exc).replace(str(path), shown)}",
                             source=source, element=element) from exc
        raise InputError(f"cannot read mesh file {path}: {exc}", source=source, element=element) from exc
    v = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), float)
    f = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), np.int64)
    if len(v) == 0 or len(f) == 0:
        raise InputError(f"mesh file {shown if shown is not None else path} has no triangles", source=source,
                         element=element)
    return v, f


def _urdf_geometry(geometry, urdf_dir: Path, *, source, element, conf: Confinement | None = None):
    """(vertices, faces) in the geometry's own frame, or None for an empty geometry."""
    if geometry is None:
        return None
    if geometry.mesh is not None:
        filename = str(geometry.mesh.filename)
        if conf is not None:
            element = f"{element} <mesh filename={filename!r}>"
            path = _resolve_mesh_confined(filename, urdf_dir, conf, source=source, element=element)
            if path is None:
                raise InputError(f"mesh file {filename!r} not found in the rig's folder", source=source,
                                 element=element)
            v, f = _load_mesh_file(path, source=source, element=element, shown=filename)
        else:
            path = _resolve_mesh_path(filename, urdf_dir)
            if path is None:
                raise InputError(
                    f"mesh file {filename!r} not found (searched relative to {urdf_dir})",
                    source=source,
                    element=element,
                )
            v, f = _load_mesh_file(path, source=source, element=element)
        scale = geometry.mesh.scale
        if scale is not None:
            v = v * np.broadcast_to(np.asarray(scale, float), (3,))
        return v, f
    if geometry.box is not None:
        return _primitive("box", geometry.box.size)
    if geometry.cylinder is not None:
        return _primitive("cylinder", (geometry.cylinder.radius, geometry.cylinder.length))
    if geometry.sphere is not None:
        return _primitive("sphere", (geometry.sphere.radius,))
    return None



def _model_file(path, confine_to, what: str):
    """(path, Confinement or None, the name errors show) of a robot model file, checked to lie
    inside ``confine_to`` when given, and to exist."""
    path = Path(path)
    conf = Confinement(confine_to) if confine_to is not None else None
    if conf is not None:
        path = conf.check_file(path, source=path.name, what=what)
        source = conf.shown(path)
    else:
        source = str(path)
    if not path.is_file():
        raise InputError(f"{what} not found", source=source)
    return path, conf, source

def load_urdf(path, *, wrapper_resolution: float = 0.002, confine_to=None) -> Rig:
    """Load a robot hand from a URDF file.

    - Each non-fixed URDF joint becomes a rig joint named after its child link, with one DOF
      named after the URDF joint: ``revolute`` -> "rotate" about the (unit-normalised) joint
      axis, ``prismatic`` -> "translate" along it, ``continuous`` -> "rotate" with limits
      [-pi, pi] (continuous joints have none in the file). Revolute/prismatic joints without
      ``<limit lower upper>`` raise InputError naming the joint. A ``<mimic joint multiplier
      offset>`` joint becomes a coupled DOF (``metadata["couplings"]``, see
      :mod:`retarget_core.rig.coupling`): the solve moves its leader and keeps
      q = multiplier * q_leader + offset exactly. Floating/planar joints raise InputError.
    - **Fixed joints are merged** into the nearest non-fixed ancestor: their link's geometry is
      carried by that ancestor's rig joint. ``metadata["link_frames"]`` maps every URDF link
      name to ``[rig joint name, 4x4 offset as nested lists]`` so that its world frame is
      ``world[joint] @ offset``.
    - The base link becomes the rig joint named after it, child of the 6-DOF ``root``.
    - Geometry: each link's ``<visual>`` elements (meshes with scale and origin, boxes,
      cylinders, spheres); a link without visuals contributes its ``<collision>`` elements.
      It is both ``Rig.visual`` and the input of the wrapper surface.
    - Mesh references: relative paths (to the URDF folder), ``file://`` and ``package://``
      (searched upward from the URDF folder); a missing file raises InputError naming the
      URDF, the link and the mesh.
    - ``confine_to`` (a folder holding the URDF, e.g. an unpacked upload): every mesh must lie
      inside it (``package://PKG/rest`` is searched only up to it, and as ``<folder>/rest``);
      a reference outside (absolute, ``file:///...``, ``..`` above it, a link out) raises
      InputError naming the element and the reference as written, without opening or
      stat-ing anything outside; errors and ``metadata["source_file"]`` name the URDF relative
      to the folder.
    """
    import yourdfpy

    path, conf, source = _model_file(path, confine_to, "URDF file")
    if conf is not None:
        _no_doctype(path, source=source)
    try:
        ET.parse(path)  # yourdfpy recovers from malformed XML silently; be strict first
    except ET.ParseError as exc:
        raise InputError(f"malformed XML: {exc if conf is None else conf.scrub(str(exc))}", source=source) from exc
    try:
        urdf = yourdfpy.URDF.load(
            str(path), load_meshes=False, build_scene_graph=False, build_collision_scene_graph=False,
            load_collision_meshes=False,
        )
    except Exception as exc:
        text = str(exc) if conf is None else conf.scrub(str(exc).replace(str(path), source))
        raise InputError(f"yourdfpy cannot parse the URDF: {text}", source=source) from exc
    robot = urdf.robot
    if robot is None or not robot.links:
        raise InputError("the URDF has no links", source=source)
    links = {link.name: link for link in robot.links}
    if len(links) != len(robot.links):
        raise InputError("a link name is used twice", source=source)
    child_joint = {}
    children: dict[str, list] = {name: [] for name in links}
    for j in robot.joints:
        el = f"joint {j.name!r}"
        if j.parent not in links or j.child not in links:
            raise InputError(f"joint connects unknown links {j.parent!r} -> {j.child!r}", source=source, element=el)
        if j.child in child_joint:
            raise InputError(f"link {j.child!r} is the child of two joints", source=source, element=el)
        child_joint[j.child] = j
        children[j.parent].append(j)
    roots = [name for name in links if name not in child_joint]
    if len(roots) != 1:
        raise InputError(
            f"the URDF must form one tree with one base link, found base links {roots}", source=source
        )
    base = roots[0]

    root_joint, dofs = free_root()
    joints = [root_joint]
    joints.append(Joint(base, 0, np.eye(4)))
    # link -> (rig joint index, offset from that joint's frame to the link frame)
    link_frame: dict[str, tuple[int, np.ndarray]] = {base: (1, np.eye(4))}
    stack = [base]
    velocity_limits = {}  # DOF name -> rad/s or m/s, from <limit velocity>
    visited = {base}
    order = [base]
    while stack:
        parent_link = stack.pop()
        owner, offset = link_frame[parent_link]
        for j in reversed(children[parent_link]):
            el = f"joint {j.name!r}"
            if j.child in visited:
                raise InputError("the joint graph has a loop", source=source, element=el)
            visited.add(j.child)
            order.append(j.child)
            origin = np.eye(4) if j.origin is None else np.asarray(j.origin, float)
            if j.type == "fixed":
                link_frame[j.child] = (owner, offset @ origin)
            elif j.type in ("revolute", "continuous", "prismatic"):
                axis = _unit_axis(j.axis if j.axis is not None else (1.0, 0.0, 0.0), source=source, element=el)
                if j.type == "continuous":
                    lower, upper = -np.pi, np.pi
                else:
                    limit = j.limit
                    lower, upper = _check_limits(
                        None if limit is None else limit.lower,
                        None if limit is None else limit.upper,
                        source=source,
                        element=el,
                    )
                if j.limit is not None and j.limit.velocity is not None and float(j.limit.velocity) > 0:
                    velocity_limits[j.name] = float(j.limit.velocity)
                joints.append(Joint(j.child, owner, offset @ origin))
                index = len(joints) - 1
                kind = "translate" if j.type == "prismatic" else "rotate"
                dofs.append(Dof(j.name, index, kind, axis, lower, upper, float(np.clip(0.0, lower, upper))))
                link_frame[j.child] = (index, np.eye(4))
            else:
                raise InputError(
                    f"joint type {j.type!r} is not supported (use revolute, continuous, prismatic or fixed)",
                    source=source,
                    element=el,
                )
            stack.append(j.child)
    # Joints were appended depth-first, so parents come first; DOFs follow joint order.
    couplings = _urdf_mimics(robot.joints, {d.name for d in dofs}, source)
    couple_rest(dofs, couplings)

    zero, _ = _rest_frames(joints, dofs)
    urdf_dir = path.parent
    pieces = []
    for link_name in order:
        link = links[link_name]
        owner, offset = link_frame[link_name]
        link_world = zero[owner] @ offset
        elements = list(link.visuals) or list(link.collisions)
        for k, element in enumerate(elements):
            geom = _urdf_geometry(element.geometry, urdf_dir, source=source, element=f"link {link_name!r}", conf=conf)
            if geom is None:
                continue
            v, f = geom
            origin = np.eye(4) if element.origin is None else np.asarray(element.origin, float)
            pieces.append((owner, _transform_points(link_world @ origin, v), f))

    renamed = _unique_names(joints)
    metadata = {
        "renamed_joints": renamed,
        "source_format": "urdf",
        "source_file": source,
        "robot_name": robot.name,
        "base_link": base,
        "link_frames": {name: [joints[o].name, off.tolist()] for name, (o, off) in link_frame.items()},
        "wrapper_resolution": wrapper_resolution,
        "wrapper_offset": WRAPPER_OFFSET,
        "couplings": [c.to_dict() for c in couplings],
        "joint_order": [j.name for j in robot.joints if j.type != "fixed"],
        "velocity_limits": velocity_limits,
    }
    return _finish(robot.name or path.stem, joints, dofs, pieces, source, metadata, wrapper_resolution)


def _urdf_mimics(urdf_joints, dof_names: set, source) -> list[Coupling]:
    """The ``<mimic>`` tags of the moving joints as couplings (multiplier 1 and offset 0 when
    not written, as URDF specifies)."""
    out = []
    for j in urdf_joints:
        mimic = getattr(j, "mimic", None)
        if mimic is None or j.type == "fixed":
            continue
        el = f"joint {j.name!r} <mimic>"
        if mimic.joint not in dof_names:
            raise InputError(f"mimics {mimic.joint!r}, which is not a moving joint of the URDF", source=source,
                             element=el)
        m = 1.0 if mimic.multiplier is None else float(mimic.multiplier)
        o = 0.0 if mimic.offset is None else float(mimic.offset)
        if not (np.isfinite(m) and np.isfinite(o)) or abs(m) < MIN_MULTIPLIER:
            raise InputError(f"multiplier {m!r} and offset {o!r} must be finite, the multiplier not zero",
                             source=source, element=el)
        out.append(Coupling(j.name, mimic.joint, m, o, "urdf mimic"))
    return out


def _mjcf_constraints(model, mujoco, dof_of_joint: dict[int, str], dofs, source) -> tuple[list, list]:
    """(couplings, not honoured) from the model's joint equalities and fixed tendons among the
    hand's joints. A linear ``<equality><joint>`` (MuJoCo: q1 - q1_ref = c0 + c1 (q2 - q2_ref))
    is a coupling; a limited fixed tendon over one joint narrows that joint's limits (in place
    on ``dofs``), over two joints with a narrow band it is a coupling
    (:func:`~retarget_core.rig.coupling.tendon_coupling`); anything else (polynomial
    equalities, wide or longer tendons) is listed as not honoured, with the reason."""
    couplings, unhonoured = [], []
    by_name = {d.name: d for d in dofs}
    ranges = {d.name: (d.lower, d.upper) for d in dofs}
    qpos0 = model.qpos0
    for e in range(model.neq):
        if int(model.eq_type[e]) != int(mujoco.mjtEq.mjEQ_JOINT):
            continue
        j1, j2 = int(model.eq_obj1id[e]), int(model.eq_obj2id[e])
        if j1 not in dof_of_joint or (j2 >= 0 and j2 not in dof_of_joint):
            continue  # not between two of the hand's hinge / slide joints
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_EQUALITY, e) or f"equality{e}"
        poly = np.asarray(model.eq_data[e][:5], float)
        if j2 < 0 or np.any(np.abs(poly[2:]) > 0) or abs(poly[1]) < MIN_MULTIPLIER:
            unhonoured.append({"constraint": f"mjcf equality {name!r}", "why": (
                "a polynomial or constant joint equality is not a linear coupling; the joints move freely "
                "within their limits")})
            continue
        r1, r2 = qpos0[model.jnt_qposadr[j1]], qpos0[model.jnt_qposadr[j2]]
        couplings.append(Coupling(dof_of_joint[j1], dof_of_joint[j2], float(poly[1]),
                                  float(r1 + poly[0] - poly[1] * r2), f"mjcf equality {name!r}"))
    order = {d.name: i for i, d in enumerate(dofs)}
    for t in range(model.ntendon):
        if not model.tendon_limited[t]:
            continue
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_TENDON, t) or f"tendon{t}"
        adr, num = model.tendon_adr[t], model.tendon_num[t]
        types = [int(model.wrap_type[w]) for w in range(adr, adr + num)]
        if any(k != int(mujoco.mjtWrap.mjWRAP_JOINT) for k in types):
            continue  # a spatial tendon: its length is no linear function of the joints
        members = [(int(model.wrap_objid[w]), float(model.wrap_prm[w])) for w in range(adr, adr + num)]
        if not all(j in dof_of_joint for j, _ in members):
            continue
        joints = sorted(((dof_of_joint[j], c) for j, c in members), key=lambda m: order[m[0]])
        lo, hi = (float(x) for x in model.tendon_range[t])
        if len(joints) == 1:
            (dof, c), = joints
            a, b = sorted((lo / c, hi / c))
            d = by_name[dof]
            if a > d.lower or b < d.upper:
                if max(a, d.lower) >= min(b, d.upper):
                    raise InputError(f"tendon {name!r} leaves joint {dof!r} no range", source=source)
                d.lower, d.upper = max(a, d.lower), min(b, d.upper)
                d.rest = float(np.clip(d.rest, d.lower, d.upper))
            continue
        # a limit the joints' own limits never let the tendon reach is no constraint at all
        reach = [sorted((c * ranges[n][0], c * ranges[n][1])) for n, c in joints]
        if sum(r[0] for r in reach) >= lo and sum(r[1] for r in reach) <= hi:
            continue
        coupling = tendon_coupling(name, joints, (lo, hi), ranges)
        if coupling is not None and coupling.dof not in {c.dof for c in couplings}:
            couplings.append(coupling)
        else:
            unhonoured.append({"constraint": f"mjcf tendon {name!r}", "why": (
                f"a limit on {' + '.join(f'{c:g} {n}' for n, c in joints)} in [{lo:g}, {hi:g}] is not one of "
                "the constraints the solve keeps (a coupling of two joints with a narrow band, or one joint's "
                "limits)")})
    return couplings, unhonoured


# ---- MJCF ----------------------------------------------------------------------------------
def _quat_to_matrix(q) -> np.ndarray:
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _axis_angle(axis, angle) -> np.ndarray:
    axis = np.asarray(axis, float)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def _check_mjcf_files(path: Path, conf: Confinement, *, source) -> None:
    """Refuse an MJCF whose includes, ``meshdir``/``texturedir``/``assetdir`` or ``file*``
    attributes (mesh, texture incl. cube faces, hfield, skin, include) could resolve outside
    ``conf.root``, before MuJoCo opens anything. Each reference is checked against every base
    MuJoCo might use (the main file's folder, the including file's folder, and each asset
    folder), so it is refused if any reading of it escapes. Sub-models (``<model file>``) are
    refused."""
    model_dir = path.parent
    files, queue, elements = {path}, [path], []
    while queue:
        xml = queue.pop()
        shown = conf.shown(xml)
        _no_doctype(xml, source=shown)
        try:
            tree = ET.parse(xml)
        except ET.ParseError as exc:
            raise InputError(f"malformed XML: {exc}", source=shown) from exc
        for el in tree.iter():
            tag = str(el.tag).rsplit("}", 1)[-1]
            if tag == "model":
                raise InputError("sub-models (<model file=...>) are not accepted in a rig bundle", source=shown,
                                 element=f"<{tag}>")
            elements.append((xml, tag, el))
            if tag == "include" and "file" in el.attrib:
                written = el.attrib["file"]
                element = f"<include file={written!r}>"
                inc = conf.resolve(written, [model_dir, xml.parent], source=shown, element=element, what="file")
                if not inc.is_file():
                    raise InputError(f"included file {written!r} not found in the rig's folder", source=shown,
                                     element=element)
                if inc not in files:
                    files.add(inc)
                    queue.append(inc)
    dirs = []
    for xml, tag, el in elements:
        for attr, written in el.attrib.items():
            name = attr.rsplit("}", 1)[-1]
            if name in ("meshdir", "texturedir", "assetdir"):
                dirs.append(conf.resolve(written or ".", [model_dir, xml.parent], source=conf.shown(xml),
                                         element=f"<{tag} {name}={written!r}>", what=name))
    bases = [model_dir, *dirs]
    for xml, tag, el in elements:
        for attr, written in el.attrib.items():
            name = attr.rsplit("}", 1)[-1]
            if name.startswith("file") and tag != "include":
                conf.resolve(written, [*bases, xml.parent], source=conf.shown(xml),
                             element=f"<{tag} {name}={written!r}>", what="file")


def load_mjcf(path, *, root_body: str | None = None, wrapper_resolution: float = 0.002, confine_to=None) -> Rig:
    """Load a robot hand from a MuJoCo MJCF file (compiled by ``mujoco.MjModel``).

    - The hand is the body subtree under ``root_body``; when None, the single child of the
      world body whose subtree holds hinge/slide/ball joints (several -> InputError asking for
      ``root_body``).
    - One rig joint per MuJoCo joint, at the joint's anchor with the body's orientation (at
      qpos = 0; a hinge/slide ``ref`` is folded into the frame so that our DOF value equals
      MuJoCo's qpos). A body with several joints becomes a chain of rig joints, one per MuJoCo
      joint in order (named ``<body>/<joint>``; a single-joint body's rig joint is named after
      the body). Bodies without joints are **merged** into their parent's last rig joint, except
      the root body, which becomes a DOF-less rig joint (child of the 6-DOF ``root``).
      ``metadata["body_offsets"]`` maps every body of the hand to ``[rig joint name, 4x4
      offset]`` (world frame of the body = ``world[joint] @ offset``).
    - hinge -> "rotate" about ``jnt_axis``, slide -> "translate"; DOF named after the MuJoCo
      joint. ball -> three "rotate" DOFs ``<name>_x/_y/_z`` about the joint frame's x, y, z
      with limits [-range, range] (an Euler-angle stand-in for the ball). A free joint on the
      root body is skipped (the 6-DOF root replaces it); elsewhere it raises InputError.
      Limits come from ``jnt_range`` when ``jnt_limited`` (MuJoCo's ``autolimits`` sets it when
      a range is given); an unlimited hinge/slide/ball raises InputError naming the joint.
    - Geometry: mesh geoms (MuJoCo's compiled, re-centred ``mesh_vert``/``mesh_face`` placed by
      the geom's compiled frame, so the re-centring is accounted for) and box, sphere, capsule,
      cylinder, ellipsoid primitives; planes, height fields and SDFs are skipped. When the
      subtree has pure visual geoms (contype = conaffinity = 0) only those are used (they are the
      robot's looks; the colliding geoms duplicate them coarsely); otherwise all geoms. The same
      geometry is ``Rig.visual`` and the wrapper's input.
    - Constraints between joints: a linear ``<equality><joint>`` and a limited fixed tendon over
      two joints with a narrow band become couplings the solve keeps exactly
      (``metadata["couplings"]``); a fixed tendon over one joint narrows its limits; any other
      constraint the joints' limits let bind is listed in ``metadata["unhonoured_constraints"]``
      and logged as a warning.
    - ``confine_to`` (a folder holding the MJCF, e.g. an unpacked upload): every file the model
      names (includes, meshes, textures, height fields, skins, and the asset folders
      ``meshdir``/``texturedir``/``assetdir``) must lie inside it; anything else raises
      InputError naming the element and the value as written, before MuJoCo opens a file.
      Errors and ``metadata["source_file"]`` name the file relative to the folder.
    """
    import mujoco

    path, conf, source = _model_file(path, confine_to, "MJCF file")
    if conf is not None:
        _check_mjcf_files(path, conf, source=source)
    try:
        model = mujoco.MjModel.from_xml_path(str(path))
    except Exception as exc:  # mujoco raises ValueError with the compiler's message
        text = str(exc) if conf is None else conf.scrub(str(exc))
        raise InputError(f"MuJoCo cannot load the model: {text}", source=source) from exc

    def name_of(obj, i):
        n = mujoco.mj_id2name(model, obj, i)
        return n if n else f"{'body' if obj == mujoco.mjtObj.mjOBJ_BODY else 'joint'}{i}"

    body_name = lambda b: name_of(mujoco.mjtObj.mjOBJ_BODY, b)  # noqa: E731
    joint_name = lambda j: name_of(mujoco.mjtObj.mjOBJ_JOINT, j)  # noqa: E731
    parent = model.body_parentid

    def subtree(b):
        out = [b]
        members = {b}
        for c in range(b + 1, model.nbody):  # bodies are ordered parents first
            if parent[c] in members:
                out.append(c)
                members.add(c)
        return out

    articulated = {int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE), int(mujoco.mjtJoint.mjJNT_BALL)}
    if root_body is None:
        candidates = []
        for b in range(1, model.nbody):
            if parent[b] != 0:
                continue
            if any(int(model.jnt_type[j]) in articulated for j in range(model.njnt) if model.jnt_bodyid[j] in subtree(b)):
                candidates.append(b)
        if len(candidates) != 1:
            names = [body_name(b) for b in candidates]
            raise InputError(
                f"cannot tell which body is the hand: {len(candidates)} world children have joints "
                f"({names}); pass root_body",
                source=source,
            )
        root = candidates[0]
    else:
        root = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, root_body)
        if root < 0:
            raise InputError(f"no body named {root_body!r}", source=source, element="root_body")
        if root == 0:
            raise InputError("root_body must not be the world body", source=source, element="root_body")
    bodies = subtree(root)

    # Kinematics at qpos = 0 (hinge/slide), identity quaternions (ball, free).
    data = mujoco.MjData(model)
    qpos = np.zeros(model.nq)
    for j in range(model.njnt):
        adr = model.jnt_qposadr[j]
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_BALL:
            qpos[adr : adr + 4] = (1, 0, 0, 0)
        elif model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            qpos[adr : adr + 7] = model.qpos0[adr : adr + 7]
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)

    root_joint, dofs = free_root()
    joints = [root_joint]
    dof_of_joint = {}  # MuJoCo hinge / slide joint id -> DOF name
    owner = {}  # body -> rig joint carrying it
    body_offset = {}  # body -> world frame at q = 0 (4x4)
    world0 = [np.eye(4)]  # rig joint world frames at q = 0
    for b in bodies:
        bw = np.eye(4)
        bw[:3, :3] = data.xmat[b].reshape(3, 3)
        bw[:3, 3] = data.xpos[b]
        body_offset[b] = bw
        jnts = list(range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b]))
        if any(model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE for j in jnts):
            if b != root:
                raise InputError(
                    "free joints are only supported on the hand's root body",
                    source=source,
                    element=f"joint {joint_name(jnts[0])!r}",
                )
            jnts = [j for j in jnts if model.jnt_type[j] != mujoco.mjtJoint.mjJNT_FREE]
        parent_joint = 0 if b == root else owner[parent[b]]
        if not jnts:
            if b == root:
                joints.append(Joint(body_name(b), 0, bw.copy()))
                world0.append(bw.copy())
                owner[b] = len(joints) - 1
            else:
                owner[b] = parent_joint
            continue
        # Orientation just after each joint at q = 0, peeled back from the body's final frame.
        rot_after = {}
        r = bw[:3, :3].copy()
        for j in reversed(jnts):
            rot_after[j] = r.copy()
            if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE:
                r = r @ _axis_angle(model.jnt_axis[j] / np.linalg.norm(model.jnt_axis[j]), -model.qpos0[model.jnt_qposadr[j]]).T
        for j in jnts:
            jname = joint_name(j)
            el = f"joint {jname!r}"
            jtype = model.jnt_type[j]
            if not model.jnt_limited[j]:
                raise InputError(
                    "joint has no range (set range=..., and limited=\"true\" when autolimits is off)",
                    source=source,
                    element=el,
                )
            lo, hi = (float(x) for x in model.jnt_range[j])
            frame = np.eye(4)
            frame[:3, :3] = rot_after[j]
            frame[:3, 3] = data.xanchor[j]
            ref = model.qpos0[model.jnt_qposadr[j]]
            if jtype == mujoco.mjtJoint.mjJNT_SLIDE:
                frame[:3, 3] = data.xanchor[j] - data.xaxis[j] * ref
            index = len(joints)
            rest_local = np.linalg.inv(world0[parent_joint]) @ frame
            rig_name = body_name(b) if len(jnts) == 1 else f"{body_name(b)}/{jname}"
            joints.append(Joint(rig_name, parent_joint, rest_local))
            world0.append(frame)
            if jtype == mujoco.mjtJoint.mjJNT_BALL:
                lo, hi = _check_limits(-hi, hi, source=source, element=el)
                for axis_name, axis in (("x", (1, 0, 0)), ("y", (0, 1, 0)), ("z", (0, 0, 1))):
                    dofs.append(Dof(f"{jname}_{axis_name}", index, "rotate", np.array(axis, float), lo, hi, 0.0))
            else:
                lo, hi = _check_limits(lo, hi, source=source, element=el)
                axis = _unit_axis(model.jnt_axis[j], source=source, element=el)
                kind = "rotate" if jtype == mujoco.mjtJoint.mjJNT_HINGE else "translate"
                dofs.append(Dof(jname, index, kind, axis, lo, hi, float(np.clip(0.0, lo, hi))))
                dof_of_joint[j] = jname
            parent_joint = index
        owner[b] = parent_joint

    couplings, unhonoured = _mjcf_constraints(model, mujoco, dof_of_joint, dofs, source)
    couple_rest(dofs, couplings)
    for u in unhonoured:
        logger.warning("%s: %s is not honoured: %s", source, u["constraint"], u["why"])

    # Geometry at q = 0.
    geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] in owner]
    visual_only = [g for g in geoms if model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0]
    use = visual_only or geoms
    pieces = []
    gt = mujoco.mjtGeom
    for g in use:
        kind = model.geom_type[g]
        if kind == gt.mjGEOM_MESH:
            m = model.geom_dataid[g]
            va, vn = model.mesh_vertadr[m], model.mesh_vertnum[m]
            fa, fn = model.mesh_faceadr[m], model.mesh_facenum[m]
            v = np.asarray(model.mesh_vert[va : va + vn], float)
            f = np.asarray(model.mesh_face[fa : fa + fn], np.int64)
        elif kind == gt.mjGEOM_BOX:
            v, f = _primitive("box", 2 * model.geom_size[g])
        elif kind == gt.mjGEOM_SPHERE:
            v, f = _primitive("sphere", model.geom_size[g])
        elif kind == gt.mjGEOM_ELLIPSOID:
            v, f = _primitive("ellipsoid", model.geom_size[g])
        elif kind == gt.mjGEOM_CAPSULE:
            v, f = _primitive("capsule", (model.geom_size[g][0], 2 * model.geom_size[g][1]))
        elif kind == gt.mjGEOM_CYLINDER:
            v, f = _primitive("cylinder", (model.geom_size[g][0], 2 * model.geom_size[g][1]))
        else:  # plane, hfield, sdf
            continue
        gw = np.eye(4)
        gw[:3, :3] = data.geom_xmat[g].reshape(3, 3)
        gw[:3, 3] = data.geom_xpos[g]
        # The geom moves with its body's rig joint; place it at q = 0 of our rig (identical to
        # MuJoCo's frames at qpos = 0 computed above).
        pieces.append((owner[model.geom_bodyid[g]], _transform_points(gw, v), f))

    renamed = _unique_names(joints)
    metadata = {
        "renamed_joints": renamed,
        "source_format": "mjcf",
        "source_file": source,
        "root_body": body_name(root),
        "body_joints": {body_name(b): joints[o].name for b, o in owner.items()},
        "body_offsets": {
            body_name(b): [joints[o].name, (np.linalg.inv(world0[o]) @ body_offset[b]).tolist()]
            for b, o in owner.items()
        },
        "geometry": "visual geoms (contype=conaffinity=0)" if visual_only else "all geoms",
        "couplings": [c.to_dict() for c in couplings],
        "unhonoured_constraints": unhonoured,
        "joint_order": [joint_name(j) for j in range(model.njnt) if j in dof_of_joint
                        or (int(model.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_BALL)
                            and model.jnt_bodyid[j] in owner)],
        "wrapper_resolution": wrapper_resolution,
        "wrapper_offset": WRAPPER_OFFSET,
    }
    name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, root) or path.stem
    return _finish(name, joints, dofs, pieces, source, metadata, wrapper_resolution)
