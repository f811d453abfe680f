"""Plain UsdSkel hands written with pxr alone, as a DCC's exporter writes them: SkelRoot >
Skeleton (joints, jointNames, bindTransforms, restTransforms) and a Mesh bound with
SkelBindingAPI (jointIndices / jointWeights primvars, geomBindTransform), stage metadata
metersPerUnit and upAxis, optional xformOps on the SkelRoot and on the Mesh (which UsdSkel
ignores for skinned points). No ``handretarget:`` attribute and no project code: the writer
takes plain arrays (it is the "other tool" of issue 18's tests).

All inputs are in metres, Z-up, world; the writer converts them into the file's units, up axis
and the Skeleton's space, so the file composes back to the same world hand."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Gf, Usd, UsdGeom, UsdSkel, Vt

#: Z-up world -> Y-up stage: -90 degrees about X ((x, y, z) -> (x, z, -y)).
Z_UP_TO_Y_UP = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])


def _gf(m: np.ndarray, float32: bool) -> Gf.Matrix4d:
    m = np.asarray(m, dtype=np.float32 if float32 else np.float64).astype(np.float64)
    return Gf.Matrix4d(*m.T.ravel().tolist())  # USD is row-vector: store the transpose


def _scaled(m: np.ndarray, s: float) -> np.ndarray:
    out = np.array(m, dtype=np.float64)
    out[..., :3, 3] *= s
    return out


def write_plain_usdskel(path, *, joint_names, parents, bind_world, vertices, faces, joint_indices,
                        joint_weights, meters_per_unit: float = 1.0, up_axis: str = "Z",
                        skel_root_transform=None, skel_root_scale: float = 1.0, mesh_transform=None,
                        geom_bind=None, float32: bool = False, root_name: str = "Hand") -> Path:
    """Write a plain UsdSkel hand.

    joint_names (J,), parents (J,) (-1 for the root, parents before children); bind_world
    (J, 4, 4) rigid world transforms at the bind pose (m, Z-up), also the rest pose; vertices
    (V, 3) world m at the bind pose; faces (F, 3); joint_indices, joint_weights (V, K).
    skel_root_transform: (4, 4) rigid, stage units, authored on the SkelRoot (with
    ``skel_root_scale`` as a uniform scale op); the skeleton is written in the space that puts
    the world hand back where it was. mesh_transform: (4, 4) authored on the Mesh (ignored by
    skinning). geom_bind: (4, 4) geomBindTransform; the mesh points are stored in the space it
    maps from. float32: matrices rounded through float32 (Blender writes them so)."""
    path = Path(path)
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if up_axis == "Y" else UsdGeom.Tokens.z)

    # world (m, Z-up) -> stage world (units, up axis) -> skeleton space
    axis = Z_UP_TO_Y_UP if up_axis == "Y" else np.eye(4)
    unit = 1.0 / meters_per_unit
    placed = np.eye(4) if skel_root_transform is None else np.asarray(skel_root_transform, float)
    to_skel = np.linalg.inv(placed)
    s = float(skel_root_scale)
    bind_stage = np.einsum("ab,jbc->jac", axis, _scaled(bind_world, unit))
    bind_skel = _scaled(np.einsum("ab,jbc->jac", to_skel, bind_stage), 1.0 / s)
    points_stage = (np.asarray(vertices, float) @ axis[:3, :3].T) * unit
    points_skel = (points_stage @ to_skel[:3, :3].T + to_skel[:3, 3]) / s
    parents = [int(p) for p in parents]
    rest_local = np.array([bind_skel[j] if p < 0 else np.linalg.inv(bind_skel[p]) @ bind_skel[j]
                           for j, p in enumerate(parents)])

    root = UsdSkel.Root.Define(stage, f"/{root_name}")
    stage.SetDefaultPrim(root.GetPrim())
    xf = UsdGeom.Xformable(root)
    if skel_root_transform is not None:
        xf.AddTransformOp().Set(_gf(placed, float32))
    if s != 1.0:
        xf.AddScaleOp().Set(Gf.Vec3f(s, s, s))

    tokens = []
    for j, name in enumerate(joint_names):
        tokens.append(name if parents[j] < 0 else f"{tokens[parents[j]]}/{name}")
    skel = UsdSkel.Skeleton.Define(stage, f"/{root_name}/Skeleton")
    skel.CreateJointsAttr(Vt.TokenArray(tokens))
    skel.CreateJointNamesAttr(Vt.TokenArray(list(joint_names)))
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray([_gf(m, float32) for m in bind_skel]))
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray([_gf(m, float32) for m in rest_local]))

    mesh = UsdGeom.Mesh.Define(stage, f"/{root_name}/HandMesh")
    g = np.eye(4) if geom_bind is None else np.asarray(geom_bind, float)
    local = points_skel @ np.linalg.inv(g)[:3, :3].T + np.linalg.inv(g)[:3, 3]
    dtype = np.float32
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(local.astype(dtype)))
    faces = np.asarray(faces, dtype=np.int32)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(faces)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(faces.ravel().tolist()))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    lo, hi = local.min(axis=0), local.max(axis=0)
    mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*lo.tolist()), Gf.Vec3f(*hi.tolist())]))
    if mesh_transform is not None:
        UsdGeom.Xformable(mesh).AddTransformOp().Set(_gf(mesh_transform, float32))
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
    ji = np.asarray(joint_indices, dtype=np.int32)
    jw = np.asarray(joint_weights, dtype=np.float32)
    k = ji.shape[1]
    binding.CreateJointIndicesPrimvar(False, k).Set(Vt.IntArray(ji.ravel().tolist()))
    binding.CreateJointWeightsPrimvar(False, k).Set(Vt.FloatArray(jw.ravel().tolist()))
    binding.CreateGeomBindTransformAttr().Set(_gf(g, float32))
    stage.GetRootLayer().Save()
    return path


def skinned_world_points(path, time=None) -> np.ndarray:
    """(V, 3) the file's mesh skinned by UsdSkel itself (pxr's skinning query) at time code
    ``time`` (None: the default time, the rest pose without an animation), in the stage's world
    space and units (no project code)."""
    stage = Usd.Stage.Open(str(path))
    cache = UsdSkel.Cache()
    root = next(UsdSkel.Root(p) for p in stage.Traverse() if p.IsA(UsdSkel.Root))
    cache.Populate(root, Usd.TraverseInstanceProxies())
    binding = cache.ComputeSkelBindings(root, Usd.TraverseInstanceProxies())[0]
    skel_query = cache.GetSkelQuery(binding.GetSkeleton())
    query = binding.GetSkinningTargets()[0]
    mesh = UsdGeom.Mesh(query.GetPrim())
    points = mesh.GetPointsAttr().Get()
    code = Usd.TimeCode.Default() if time is None else Usd.TimeCode(float(time))
    xforms = skel_query.ComputeSkinningTransforms(code)
    query.ComputeSkinnedPoints(xforms, points, code)
    skel_to_world = UsdGeom.Imageable(binding.GetSkeleton().GetPrim()).ComputeLocalToWorldTransform(code)
    return np.array([skel_to_world.Transform(Gf.Vec3d(*p)) for p in points], dtype=np.float64)
