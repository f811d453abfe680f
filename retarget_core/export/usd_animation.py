"""The retargeting result as a USD layer (and as JSON for robot users).

Layout written by :func:`write_animation_usd` (stage metadata ``metersPerUnit`` and ``upAxis``
of the rig file it composes over, 1 and Z for the project's own rig files;
``timeCodesPerSecond = framesPerSecond = fps``, ``startTimeCode = 0``,
``endTimeCode = n_frames - 1``; time code = frame number, seconds = code / fps)::

    subLayers = [@<rig file, relative to the output folder>@]   (when ``rig_file`` is given;
                                                                  otherwise the rig itself is
                                                                  written into the layer)
    /<RigRoot>                 SkelRoot (from the rig)
      Skeleton                 over: SkelBindingAPI, skel:animationSource = </<RigRoot>/Animation>
      Animation                SkelAnimation: joints = the Skeleton's joint tokens; translations
                               (float3[]), rotations (quatf[]), scales (half3[]) of the LOCAL
                               joint transforms in that file's skeleton space (its units, up
                               axis and the Skeleton prim's placement), time-sampled at every
                               frame; a free root the reader added to a plain UsdSkel file is
                               not in its skeleton: its motion lands on the skeleton's root joint
      DofCurves                Scope: one ``double dof:<name>`` attribute per DOF carrying a
                               native Ts spline equal to the fitted cubic B-spline; customData
                               ``handretarget = {dofName, knots, coefficients, degree,
                               timeUnit = "seconds", fps, extrapolation}``
    /HandRetarget_wristTarget  Xform (a hand cut from a character's skeleton only): the world
                               transform of the hand's root joint per frame, in the file's units;
                               the character's other joints keep their rest in the Animation
    /Object                    Xform, xformOp:transform time-sampled per frame (when given), in
                               the file's units and up axis
      Mesh                     the object's mesh in its own frame

B-spline -> Ts spline: a Bezier knot at every breakpoint b (time code b * fps) with the
curve's value there, pre / post tangent slopes = the B-spline's left / right derivatives
(per time code, i.e. d/dt / fps) and tangent widths a third of the adjacent interval (in
time codes). A cubic Bezier whose time handles sit at thirds is the cubic polynomial itself,
so the Ts spline equals the B-spline up to rounding. Extrapolation: held (or linear, as the
curve says) on both sides.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import atomic_path
from ..fit.splines import BSplineCurve
from ..jsonio import to_jsonable
from ..rig.model import Rig

FORMAT_NAME = "handretarget.animation"
FORMAT_VERSION = 1
DOF_PREFIX = "dof:"
#: the Xform carrying the world motion of a hand cut from a larger skeleton (for the arm's IK)
WRIST_TARGET = "HandRetarget_wristTarget"
CUSTOM_KEY = "handretarget"
_USD_EXTENSIONS = (".usda", ".usdc", ".usd")


def _pxr():
    from pxr import Gf, Sdf, Tf, Ts, Usd, UsdGeom, UsdSkel, Vt  # noqa: F401

    return Gf, Sdf, Tf, Ts, Usd, UsdGeom, UsdSkel, Vt


# ---- B-spline -> Ts spline ---------------------------------------------------------------
def bspline_to_ts(curve: BSplineCurve, fps: float):
    """A ``Ts.Spline`` of value type double, in time codes (seconds * fps), equal to ``curve``."""
    Gf, Sdf, Tf, Ts, Usd, UsdGeom, UsdSkel, Vt = _pxr()
    fps = float(fps)
    segments = curve.to_bezier()  # (t0, t1, p0, p1, p2, p3) in seconds
    spline = Ts.Spline("double")  # curve type Bezier is the default
    n = len(segments)
    for i in range(n + 1):
        prev = segments[i - 1] if i > 0 else None
        nxt = segments[i] if i < n else None
        time_s = nxt[0] if nxt is not None else prev[1]
        # value: right limit (start of the next segment), or the end value at the last knot
        value = nxt[2] if nxt is not None else prev[5]
        knot = Ts.Knot(typeName="double", time=float(time_s * fps), value=float(value))
        if prev is not None:
            h = prev[1] - prev[0]
            slope_s = (prev[5] - prev[4]) * 3.0 / h  # f'(b-) from the Bezier handle
            knot.SetPreTanWidth(float(h * fps / 3.0))
            knot.SetPreTanSlope(float(slope_s / fps))
            if abs(prev[5] - value) > 0.0:  # a jump (only with full-multiplicity knots)
                knot.SetPreValue(float(prev[5]))
        if nxt is not None:
            h = nxt[1] - nxt[0]
            slope_s = (nxt[3] - nxt[2]) * 3.0 / h  # f'(b+)
            knot.SetPostTanWidth(float(h * fps / 3.0))
            knot.SetPostTanSlope(float(slope_s / fps))
            knot.SetNextInterpolation(Ts.InterpCurve)
        else:
            knot.SetNextInterpolation(Ts.InterpHeld)
        spline.SetKnot(knot)
    mode = Ts.ExtrapLinear if curve.extrapolation == "linear" else Ts.ExtrapHeld
    spline.SetPreExtrapolation(Ts.Extrapolation(mode))
    spline.SetPostExtrapolation(Ts.Extrapolation(mode))
    return spline


# ---- helpers -------------------------------------------------------------------------------
def _unique_tokens(names, make_valid, *, prefix=""):
    used, out = set(), []
    for name in names:
        base = make_valid(str(name)) or "dof"
        token, k = base, 2
        while token in used:
            token, k = f"{base}_{k}", k + 1
        used.add(token)
        out.append(prefix + token)
    return out


def local_joint_transforms(rig: Rig, q: np.ndarray) -> np.ndarray:
    """(J, 4, 4) local (parent-relative) joint transforms at DOF values q (D,), column vectors;
    the root's is its transform in the skeleton's space."""
    world = rig.kinematics().pose(np.asarray(q, dtype=np.float64)).world
    parents = np.array([j.parent for j in rig.joints])
    local = world.copy()
    child = parents >= 0
    local[child] = np.linalg.inv(world[parents[child]]) @ world[child]
    return local


def layers_over(rig: Rig, rig_file) -> bool:
    """Whether an animation layer for ``rig`` can compose over ``rig_file`` as it is: a USD
    file whose Skeleton has the rig's joints (by name; a free root the reader added may be
    missing from it), in any units, up axis and placement (:func:`_skeleton_target`)."""
    try:
        _skeleton_target(rig, Path(rig_file))
    except InputError:
        return False
    return True


class _SkeletonTarget:
    """The Skeleton of a rig file an animation layer composes over, and how the core's world
    (metres, Z-up) maps into its space: root prim name, skeleton path, joint tokens (T,),
    ``order`` (T,) the rig joint of each token (-1: a joint the rig does not have, e.g. the
    body around a hand cut out of a character, kept at ``rest_skel`` (T, 4, 4), its rest in
    skeleton space), ``parents`` (T,) token tree, and the file's metersPerUnit, upAxis and the
    Skeleton prim's placement (uniform scale, rigid)."""

    def __init__(self, root_name, skel_path, tokens, order, parents, meters_per_unit, up_axis, scale, placed,
                 rest_skel=None):
        self.root_name, self.skel_path, self.tokens = root_name, skel_path, tokens
        self.order, self.parents = np.asarray(order, dtype=np.int64), np.asarray(parents, dtype=np.int64)
        self.meters_per_unit, self.up_axis = meters_per_unit, up_axis
        from ..rig.usd_io import Y_UP_TO_Z_UP

        # world (m, Z-up) -> stage world (units, up axis): rotation, then units
        self.to_stage = (Y_UP_TO_Z_UP.T if up_axis == "Y" else np.eye(4)).copy()
        self.to_stage_scale = 1.0 / meters_per_unit
        self.placed = np.asarray(placed, dtype=np.float64)
        self.inv_placed = np.linalg.inv(self.placed)
        self.skel_scale = scale
        self.rest_skel = rest_skel

    @property
    def partial(self) -> bool:
        """Whether the file's skeleton has joints the rig does not (a hand cut from a body)."""
        return bool(np.any(self.order < 0))

    def stage_transform(self) -> np.ndarray:
        """(4, 4) world (m, Z-up) -> the file's stage space (units, up axis), scale included."""
        m = self.to_stage.copy()
        m[:3, :3] *= self.to_stage_scale
        return m

    def skel_space(self, world: np.ndarray) -> np.ndarray:
        """(N, 4, 4) rigid world transforms (m, Z-up) in the file's skeleton space."""
        k = np.einsum("ab,jbc->jac", self.to_stage, world)
        k[:, :3, 3] *= self.to_stage_scale
        k = np.einsum("ab,jbc->jac", self.inv_placed, k)
        k[:, :3, 3] /= self.skel_scale
        return k

    def stage_space(self, world: np.ndarray) -> np.ndarray:
        """(N, 4, 4) rigid world transforms (m, Z-up) in the file's stage world (its units)."""
        k = np.einsum("ab,jbc->jac", self.to_stage, world)
        k[:, :3, 3] *= self.to_stage_scale
        return k

    def local(self, world: np.ndarray) -> np.ndarray:
        """(T, 4, 4) the tokens' local transforms in the file's skeleton space from the rig's
        joint world transforms (J, 4, 4); joints the rig does not have keep their rest."""
        mine = self.order >= 0
        k = np.empty((len(self.order), 4, 4)) if self.rest_skel is None else self.rest_skel.copy()
        k[mine] = self.skel_space(world[self.order[mine]])
        out = k.copy()
        child = self.parents >= 0
        out[child] = np.linalg.inv(k[self.parents[child]]) @ k[child]
        return out


def _skeleton_target(rig: Rig, rig_file: Path) -> _SkeletonTarget:
    """The Skeleton of ``rig_file`` matched to ``rig`` by joint name (the reader's names:
    ``handretarget:jointNames``, else ``jointNames``, else the token's last element); every rig
    joint must be there except a free root the reader added (``free_root_added``)."""
    from ..rig.usd_io import _find_skeleton, _open_stage, _parents_from_paths, _prim_placement

    Gf, Sdf, Tf, Ts, Usd, UsdGeom, UsdSkel, Vt = _pxr()
    src = str(rig_file)
    stage = _open_stage(rig_file)
    mpu = float(UsdGeom.GetStageMetersPerUnit(stage))
    up = str(UsdGeom.GetStageUpAxis(stage))
    if up not in ("Y", "Z") or not np.isfinite(mpu) or mpu <= 0:
        raise InputError(f"the rig file has metersPerUnit {mpu}, upAxis {up}", source=src,
                         element="metersPerUnit/upAxis")
    skel = _find_skeleton(stage)
    if skel is None:
        raise InputError("no UsdSkel.Skeleton in the rig file", source=src, element="Skeleton")
    tokens = [str(t) for t in (skel.GetJointsAttr().Get() or [])]
    names_attr = skel.GetPrim().GetAttribute("handretarget:jointNames")
    names = names_attr.Get() if names_attr and names_attr.HasAuthoredValue() else None
    if names is None and skel.GetJointNamesAttr().HasAuthoredValue():
        names = skel.GetJointNamesAttr().Get()
    names = [str(n) for n in names] if names is not None else [t.rsplit("/", 1)[-1] for t in tokens]
    added = rig.metadata.get("free_root_added")
    cut = rig.metadata.get("hand_root")  # a hand cut out of a larger skeleton: the file has more joints
    if len(names) != len(tokens):
        raise InputError(f"the rig file's skeleton has {len(tokens)} joints and {len(names)} names", source=src,
                         element=f"{skel.GetPath()}.joints")
    index = {n: i for i, n in enumerate(rig.joint_names)}
    order = np.array([index.get(n, -1) for n in names], dtype=np.int64)
    # the free root the reader added is in a rig file written from the rig, not in the user's
    expected = set(range(rig.n_joints)) - ({index[added]} if added in index else set())
    missing = sorted(expected - set(order.tolist()))
    if missing or (np.any(order < 0) and not cut):
        raise InputError(
            f"the rig file's skeleton has {len(tokens)} joints, the rig {rig.n_joints}"
            + (f" (one of them the added free root {added!r})" if added else "")
            + (f"; not in the file: {', '.join(rig.joint_names[j] for j in missing[:5])}" if missing else ""),
            source=src,
            element=f"{skel.GetPath()}.joints",
        )
    parents = np.array(_parents_from_paths(tokens, src=src, element=f"{skel.GetPath()}.joints"), dtype=np.int64)
    # a rig file with the DOF spec is read in its Skeleton's space (rig/usd_io.read_rig_usd)
    spec = skel.GetPrim().GetAttribute("handretarget:specVersion")
    scale, placed = (1.0, np.eye(4)) if spec and spec.HasAuthoredValue() else _prim_placement(skel.GetPrim(), src=src)
    rest_skel = None
    if np.any(order < 0):
        rest_skel = _rest_in_skel_space(skel, parents)
    path = skel.GetPath()
    root = path.GetParentPath()
    while root.pathElementCount > 1:
        root = root.GetParentPath()
    return _SkeletonTarget(root.name, str(path), tokens, order, parents, mpu, up, scale, placed, rest_skel)


def _rest_in_skel_space(skel, parents: np.ndarray) -> np.ndarray:
    """(T, 4, 4) the file's rest pose in skeleton space (restTransforms, else bindTransforms)."""
    rest = skel.GetRestTransformsAttr()
    if rest.HasAuthoredValue():
        local = np.array(rest.Get(), dtype=np.float64).reshape(-1, 4, 4).transpose(0, 2, 1)
        out = np.empty_like(local)
        for j in range(len(local)):  # tokens list parents before children (UsdSkel requires it)
            out[j] = local[j] if parents[j] < 0 else out[parents[j]] @ local[j]
        return out
    return np.array(skel.GetBindTransformsAttr().Get(), dtype=np.float64).reshape(-1, 4, 4).transpose(0, 2, 1)


def _check_curves(rig: Rig, dof_curves, fps: float, n_frames: int):
    if not np.isfinite(fps) or fps <= 0:
        raise InputError(f"fps must be positive, got {fps}", element="fps")
    if int(n_frames) != n_frames or n_frames < 1:
        raise InputError(f"n_frames must be a positive integer, got {n_frames}", element="n_frames")
    if len(dof_curves) != rig.n_dofs:
        raise InputError(f"{len(dof_curves)} DOF curves for a rig with {rig.n_dofs} DOFs", element="dof_curves")
    for i, c in enumerate(dof_curves):
        if not isinstance(c, BSplineCurve):
            raise InputError(f"curve {i} is a {type(c).__name__}, not a BSplineCurve", element="dof_curves")
        if c.degree > 3:
            raise InputError(f"curve of DOF {rig.dofs[i].name!r} has degree {c.degree} > 3", element="dof_curves")


def _set_time_metadata(stage, fps: float, n_frames: int, meters_per_unit: float = 1.0, up_axis: str = "Z"):
    Gf, Sdf, Tf, Ts, Usd, UsdGeom, UsdSkel, Vt = _pxr()
    # the units and axes of the file the layer composes over (a root layer's metadata wins)
    UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if up_axis == "Y" else UsdGeom.Tokens.z)
    stage.SetTimeCodesPerSecond(float(fps))
    stage.SetFramesPerSecond(float(fps))
    stage.SetStartTimeCode(0.0)
    stage.SetEndTimeCode(float(n_frames - 1))


# ---- USD -------------------------------------------------------------------------------------
def write_animation_usd(
    path,
    *,
    rig: Rig,
    rig_file: str | None,
    dof_curves: list[BSplineCurve],
    fps: float,
    n_frames: int,
    object_vertices=None,
    object_faces=None,
    object_poses=None,
    metadata: dict | None = None,
    sublayer_path: str | None = None,
) -> None:
    """Write the result layer (.usda / .usdc / .usd) atomically; see the module docstring.

    sublayer_path: the asset path the layer sublayers, as written (e.g. the user's own file's
    name where the layer will sit beside it), instead of ``rig_file`` relative to the output
    folder; ``rig_file`` is still what the skeleton is read from.

    rig_file: the rig's USD file (written by ``write_rig_usd``), sublayered by a path relative
    to the output folder; None writes the rig itself into the layer. dof_curves: one curve per
    rig DOF (seconds). object_vertices (V, 3) metres in the object's frame, object_faces
    (F, 3), object_poses (n_frames, 4, 4) object-to-world per frame. metadata: JSON-able dict
    stored in the layer's customLayerData (``handretarget:metadata``, as JSON)."""
    Gf, Sdf, Tf, Ts, Usd, UsdGeom, UsdSkel, Vt = _pxr()
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in _USD_EXTENSIONS:
        raise InputError(f"USD file name must end in {', '.join(_USD_EXTENSIONS)}", source=str(path))
    fps = float(fps)
    _check_curves(rig, dof_curves, fps, n_frames)
    n_frames = int(n_frames)
    try:
        metadata_json = json.dumps(to_jsonable(metadata or {}), sort_keys=True)
    except (TypeError, ValueError) as exc:
        raise InputError(f"metadata is not JSON serialisable: {exc}", element="metadata") from exc

    # the scene graph: either the rig is sublayered, or written into this layer
    if rig_file is not None:
        rig_path = Path(rig_file)
        target = _skeleton_target(rig, rig_path)
        root_name, skel_path, tokens = target.root_name, target.skel_path, target.tokens
        stage = Usd.Stage.CreateInMemory()
        out_dir = path.resolve().parent
        sublayer = sublayer_path or os.path.relpath(rig_path.resolve(), out_dir).replace(os.sep, "/")
        skel_prim = stage.OverridePrim(skel_path)
        root_prim = stage.GetPrimAtPath(f"/{root_name}")
        stage.SetDefaultPrim(root_prim)
    else:
        from ..rig.usd_io import _build_stage

        stage = _build_stage(rig)
        root_prim = stage.GetDefaultPrim()
        root_name = root_prim.GetName()
        skel = UsdSkel.Skeleton(stage.GetPrimAtPath(f"/{root_name}/Skeleton"))
        skel_prim = skel.GetPrim()
        tokens = [str(t) for t in skel.GetJointsAttr().Get()]
        target = _SkeletonTarget(root_name, str(skel.GetPath()), tokens, np.arange(rig.n_joints),
                                 np.array([j.parent for j in rig.joints]), 1.0, "Z", 1.0, np.eye(4))
        sublayer = None
    _set_time_metadata(stage, fps, n_frames, target.meters_per_unit, target.up_axis)
    layer = stage.GetRootLayer()
    layer.customLayerData = {
        "handretarget:format": FORMAT_NAME,
        "handretarget:formatVersion": FORMAT_VERSION,
        "handretarget:metadata": metadata_json,
    }

    # baked skeletal animation
    anim_path = f"/{root_name}/Animation"
    anim = UsdSkel.Animation.Define(stage, anim_path)
    anim.CreateJointsAttr(Vt.TokenArray(tokens))
    frame_times = np.arange(n_frames, dtype=np.float64) / fps
    q = np.stack([np.asarray(c(frame_times), dtype=np.float64).reshape(n_frames) for c in dof_curves], axis=1) \
        if dof_curves else np.zeros((n_frames, 0))
    t_attr, r_attr, s_attr = anim.CreateTranslationsAttr(), anim.CreateRotationsAttr(), anim.CreateScalesAttr()
    wrist_op = None
    if target.partial:
        # a hand cut from a character: the rest of the body stays at rest, and the hand's root
        # joint's world motion is there for the arm's IK to follow
        wrist_op = UsdGeom.Xform.Define(stage, f"/{WRIST_TARGET}").AddTransformOp()
        hand_root = rig.joint_index(rig.metadata["hand_root"])
    for f in range(n_frames):
        world = rig.kinematics().pose(q[f]).world
        local = target.local(world)
        if wrist_op is not None:
            wrist_op.Set(Gf.Matrix4d(target.stage_space(world[hand_root][None])[0].T.tolist()), Usd.TimeCode(float(f)))
        mats = Vt.Matrix4dArray.FromNumpy(np.ascontiguousarray(local.transpose(0, 2, 1)))
        translations, rotations, scales = UsdSkel.DecomposeTransforms(mats)
        code = Usd.TimeCode(float(f))
        t_attr.Set(translations, code)
        r_attr.Set(rotations, code)
        s_attr.Set(scales, code)
    binding = UsdSkel.BindingAPI.Apply(skel_prim)
    binding.CreateAnimationSourceRel().SetTargets([Sdf.Path(anim_path)])

    # one native spline per DOF
    curves_prim = stage.DefinePrim(f"/{root_name}/DofCurves", "Scope")
    attr_names = _unique_tokens(rig.dof_names, Tf.MakeValidIdentifier, prefix=DOF_PREFIX)
    for dof, name, curve in zip(rig.dofs, attr_names, dof_curves):
        attr = curves_prim.CreateAttribute(name, Sdf.ValueTypeNames.Double, custom=True)
        attr.SetSpline(bspline_to_ts(curve, fps))
        attr.SetDocumentation(
            f"DOF {dof.name!r} ({'radians' if dof.kind == 'rotate' else 'metres'}) over time codes; "
            "a cubic B-spline in seconds (seconds = time code / fps), see customData"
        )
        attr.SetCustomDataByKey(CUSTOM_KEY, {
            "dofName": dof.name,
            "kind": dof.kind,
            "knots": Vt.DoubleArray([float(v) for v in curve.knots]),
            "coefficients": Vt.DoubleArray([float(v) for v in curve.coeffs]),
            "degree": int(curve.degree),
            "timeUnit": "seconds",
            "fps": fps,
            "extrapolation": curve.extrapolation,
        })

    if object_vertices is not None or object_faces is not None or object_poses is not None:
        _write_object(stage, object_vertices, object_faces, object_poses, n_frames, target.stage_transform())

    if sublayer is not None:
        # DefinePrim() made the rig's root a typeless "def" here; the rig file defines it
        layer.GetPrimAtPath(f"/{root_name}").specifier = Sdf.SpecifierOver
        # a detached copy takes the relative sublayer path: on the live in-memory stage it
        # would be resolved (and fail to load) relative to the working directory
        detached = Sdf.Layer.CreateAnonymous(ext)
        detached.TransferContent(layer)
        detached.subLayerPaths.append(sublayer)
        layer = detached
    with atomic_path(path, suffix=ext) as tmp:
        if not layer.Export(str(tmp)):
            raise OSError(f"USD could not write {path}")


def _write_object(stage, vertices, faces, poses, n_frames: int, stage_transform=None):
    """/Object: the mesh (metres, its own frame) under one time-sampled xformOp:transform,
    ``stage_transform`` (4, 4; the file's units and up axis, identity by default) @ pose."""
    Gf, Sdf, Tf, Ts, Usd, UsdGeom, UsdSkel, Vt = _pxr()
    if vertices is None or faces is None or poses is None:
        raise InputError("the object needs vertices, faces and poses together", element="object")
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    poses = np.asarray(poses, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0 or not np.all(np.isfinite(v)):
        raise InputError(f"object vertices must be finite with shape (V, 3), got {v.shape}", element="object_vertices")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or not np.issubdtype(f.dtype, np.integer) \
            or f.min() < 0 or f.max() >= len(v):
        raise InputError(f"object faces must be (F, 3) indices into {len(v)} vertices", element="object_faces")
    if poses.shape != (n_frames, 4, 4) or not np.all(np.isfinite(poses)):
        raise InputError(f"object poses must be finite with shape ({n_frames}, 4, 4), got {poses.shape}",
                         element="object_poses")
    xform = UsdGeom.Xform.Define(stage, "/Object")
    op = xform.AddTransformOp()
    to_stage = np.eye(4) if stage_transform is None else np.asarray(stage_transform, dtype=np.float64)
    for k in range(n_frames):
        op.Set(Gf.Matrix4d((to_stage @ poses[k]).T.tolist()), Usd.TimeCode(float(k)))
    mesh = UsdGeom.Mesh.Define(stage, "/Object/Mesh")
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(v, dtype=np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(f), 3, dtype=np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(f.reshape(-1), dtype=np.int32)))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    lo, hi = v.min(axis=0), v.max(axis=0)
    mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))


def _open_layer(path):
    """The USD stage at ``path``, or InputError naming the file."""
    Usd = _pxr()[4]
    path = Path(path)
    if not path.is_file():
        raise InputError("file not found", source=str(path))
    stage = Usd.Stage.Open(str(path))
    if stage is None:
        raise InputError("not a readable USD file", source=str(path))
    return stage


def read_dof_splines(path) -> dict:
    """{DOF name: Ts.Spline} of every ``dof:*`` attribute carrying a spline in the layer at
    ``path`` (time in time codes). The DOF name is the one in customData where present."""
    out = {}
    stage = _open_layer(path)  # held: prims expire with their stage
    # every prim, overs included: the curves are read from the layer even when the rig file it
    # sublayers (the user's own, by its name) is not beside it
    for prim in stage.TraverseAll():
        for attr in prim.GetAttributes():
            name = attr.GetName()
            if not name.startswith(DOF_PREFIX) or not attr.HasSpline():
                continue
            info = attr.GetCustomDataByKey(CUSTOM_KEY) or {}
            out[str(info.get("dofName", name[len(DOF_PREFIX):]))] = attr.GetSpline()
    return out


def read_dof_bsplines(path) -> dict:
    """{DOF name: BSplineCurve} rebuilt from the raw knots and coefficients in customData."""
    out = {}
    stage = _open_layer(path)  # held: prims expire with their stage
    # every prim, overs included: the curves are read from the layer even when the rig file it
    # sublayers (the user's own, by its name) is not beside it
    for prim in stage.TraverseAll():
        for attr in prim.GetAttributes():
            info = attr.GetCustomDataByKey(CUSTOM_KEY) if attr.GetName().startswith(DOF_PREFIX) else None
            if not info or "knots" not in info:
                continue
            out[str(info.get("dofName", attr.GetName()[len(DOF_PREFIX):]))] = BSplineCurve(
                knots=np.array(info["knots"], dtype=np.float64),
                coeffs=np.array(info["coefficients"], dtype=np.float64),
                degree=int(info.get("degree", 3)),
                extrapolation=str(info.get("extrapolation", "held")),
            )
    return out


# ---- JSON ------------------------------------------------------------------------------------
def write_animation_json(path, dof_names, times, values, extra: dict | None = None, robot: dict | None = None) -> None:
    """Per-frame DOF values for robot users, atomically::

        {"format": "handretarget.animation", "version": 1, "dof_names": [...D],
         "times": [...F seconds], "values": [[...D] x F], "extra": {...}, "robot": {...}}

    times: (F,); values: (F, D) radians / metres; ``robot`` (only for robot rigs): the joint
    commands in the robot file's terms (:func:`~retarget_core.export.robot_trajectory.robot_trajectory`)."""
    dof_names = [str(n) for n in dof_names]
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    values = np.asarray(values, dtype=np.float64)
    if values.shape != (len(times), len(dof_names)):
        raise InputError(f"values must have shape ({len(times)}, {len(dof_names)}), got {values.shape}",
                         element="values")
    if not np.all(np.isfinite(values)) or not np.all(np.isfinite(times)):
        raise InputError("times and values must be finite", element="values")
    doc = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "dof_names": dof_names,
        "times": times.tolist(),
        "values": values.tolist(),
        "extra": extra or {},
    }
    if robot is not None:
        doc["robot"] = robot
    try:
        text = json.dumps(to_jsonable(doc), indent=1)
    except (TypeError, ValueError) as exc:
        raise InputError(f"extra is not JSON serialisable: {exc}", element="extra") from exc
    path = Path(path)
    with atomic_path(path, suffix=".json.tmp") as tmp:
        tmp.write_text(text, encoding="utf-8")


def read_animation_json(path) -> dict:
    """The document written by :func:`write_animation_json`, with ``times`` (F,) and
    ``values`` (F, D) as numpy arrays."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise InputError(f"not a readable JSON file: {exc}", source=str(path)) from exc
    if not isinstance(doc, dict) or doc.get("format") != FORMAT_NAME:
        raise InputError(f"not a {FORMAT_NAME} document", source=str(path), element="format")
    if doc.get("version") != FORMAT_VERSION:
        raise InputError(f"unsupported version {doc.get('version')!r}", source=str(path), element="version")
    doc["times"] = np.asarray(doc.get("times", []), dtype=np.float64)
    doc["values"] = np.asarray(doc.get("values", []), dtype=np.float64).reshape(len(doc["times"]), -1)
    return doc
