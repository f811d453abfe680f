"""Rigs as USD files: a UsdSkel skeleton, skinned meshes and the DOF spec in one file.

Layout written by :func:`write_rig_usd` (stage metadata ``metersPerUnit = 1``,
``upAxis = "Z"``, ``defaultPrim`` = the SkelRoot)::

    /<RigName>            SkelRoot, kind = "component"
      Skeleton            UsdSkel.Skeleton: joints (paths "root", "root/wrist", ...),
                          jointNames, restTransforms (Joint.rest_local, i.e. local at q = 0),
                          bindTransforms (world at the rest pose), and the DOF spec in the
                          ``handretarget:`` namespace (see below)
      Surface             Mesh, purpose "default": the closed surface, skinned
                          (SkelBindingAPI: skel:skeleton, primvars:skel:jointIndices /
                          jointWeights, vertex interpolation, elementSize K,
                          geomBindTransform = identity), points at the rest pose
      Visual              Mesh, purpose "render" (only when ``rig.visual`` is set)

DOF spec attributes on the Skeleton prim (spec version 1)::

    int       handretarget:specVersion = 1
    string    handretarget:rigName
    string    handretarget:metadata        rig.metadata as JSON
    string[]  handretarget:jointNames      original joint names, skeleton joint order
    string[]  handretarget:dofNames
    int[]     handretarget:dofJoints       index into the skeleton's joints array
    token[]   handretarget:dofKinds        "rotate" | "translate"
    double3[] handretarget:dofAxes         unit axis in the joint frame
    double[]  handretarget:dofLower / dofUpper / dofRest

Units in the file are the stage's: rotations in radians, translations (transforms, points,
and the limits/rest of "translate" DOFs) in stage units, i.e. metres / metersPerUnit. The
reader converts to metres and to the core's Z-up convention.

USD stores matrices for row vectors; the core uses column vectors, so every matrix is
transposed on the way in and out.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import atomic_path
from ..jsonio import to_jsonable
from .model import DOF_KINDS, Dof, Joint, Rig, SkinnedMesh, orthonormalized, rigidity_error

SPEC_VERSION = 1
NAMESPACE = "handretarget"
_USD_EXTENSIONS = (".usda", ".usdc", ".usd")

#: Rotation taking a Y-up stage to the core's Z-up convention (+90 degrees about X).
Y_UP_TO_Z_UP = np.array(
    [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)


def _pxr():
    from pxr import Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt  # noqa: F401

    return Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt


def _attr_name(short: str) -> str:
    return f"{NAMESPACE}:{short}"


# ---- writing -------------------------------------------------------------------------------
def _unique_identifiers(names: list[str], make_valid) -> list[str]:
    """Valid, pairwise distinct prim-name tokens for ``names``."""
    used: set[str] = set()
    out = []
    for name in names:
        base = make_valid(name) or "joint"
        token, k = base, 2
        while token in used:
            token, k = f"{base}_{k}", k + 1
        used.add(token)
        out.append(token)
    return out


def _joint_paths(rig: Rig, tokens: list[str]) -> list[str]:
    paths: list[str] = []
    for i, joint in enumerate(rig.joints):
        paths.append(tokens[i] if joint.parent < 0 else f"{paths[joint.parent]}/{tokens[i]}")
    return paths


def _usd_matrices(mats: np.ndarray):
    """(N, 4, 4) column-vector transforms -> Vt.Matrix4dArray (row-vector convention)."""
    Vt = _pxr()[6]
    return Vt.Matrix4dArray.FromNumpy(np.ascontiguousarray(np.asarray(mats, dtype=np.float64).transpose(0, 2, 1)))


def _write_mesh(stage, path: str, mesh: SkinnedMesh, skeleton, *, purpose: str, role: str, double_sided: bool,
                dof_spec: bool = True):
    Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt = _pxr()
    geom = UsdGeom.Mesh.Define(stage, path)
    points = np.asarray(mesh.vertices, dtype=np.float64)
    geom.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(points, dtype=np.float32)))
    geom.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(mesh.faces), 3, dtype=np.int32)))
    geom.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(mesh.faces.reshape(-1), dtype=np.int32)))
    geom.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    geom.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    geom.CreateDoubleSidedAttr(bool(double_sided))
    lo, hi = points.min(axis=0), points.max(axis=0)
    geom.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
    geom.CreatePurposeAttr(purpose)
    if dof_spec:
        geom.GetPrim().CreateAttribute(_attr_name("role"), Sdf.ValueTypeNames.Token, custom=True).Set(role)

    binding = UsdSkel.BindingAPI.Apply(geom.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
    k = mesh.joint_indices.shape[1]
    binding.CreateJointIndicesPrimvar(False, k).Set(
        Vt.IntArray.FromNumpy(np.ascontiguousarray(mesh.joint_indices.reshape(-1), dtype=np.int32))
    )
    binding.CreateJointWeightsPrimvar(False, k).Set(
        Vt.FloatArray.FromNumpy(np.ascontiguousarray(mesh.joint_weights.reshape(-1), dtype=np.float32))
    )
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))
    return geom


def _build_stage(rig: Rig, dof_spec: bool = True):
    Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt = _pxr()
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)

    root_name = Tf.MakeValidIdentifier(rig.name or "") or "Rig"
    root = UsdSkel.Root.Define(stage, f"/{root_name}")
    stage.SetDefaultPrim(root.GetPrim())
    Usd.ModelAPI(root.GetPrim()).SetKind("component")

    skel = UsdSkel.Skeleton.Define(stage, f"/{root_name}/Skeleton")
    tokens = _unique_identifiers(rig.joint_names, Tf.MakeValidIdentifier)
    skel.CreateJointsAttr(Vt.TokenArray(_joint_paths(rig, tokens)))
    skel.CreateJointNamesAttr(Vt.TokenArray(rig.joint_names))
    rest_local = np.stack([np.asarray(j.rest_local, dtype=np.float64) for j in rig.joints])
    skel.CreateRestTransformsAttr(_usd_matrices(rest_local))
    skel.CreateBindTransformsAttr(_usd_matrices(rig.kinematics().bind_world))

    prim = skel.GetPrim()
    T = Sdf.ValueTypeNames

    def put(short, type_name, value, doc=""):
        attr = prim.CreateAttribute(_attr_name(short), type_name, custom=True)
        attr.Set(value)
        if doc:
            attr.SetDocumentation(doc)

    if not dof_spec:  # plain UsdSkel, as a DCC writes it
        _write_mesh(stage, f"/{root_name}/Surface", rig.surface, skel, purpose=UsdGeom.Tokens.default_,
                    role="surface", double_sided=False, dof_spec=False)
        return stage
    try:
        metadata_json = json.dumps(to_jsonable(rig.metadata), sort_keys=True)
    except (TypeError, ValueError) as exc:
        raise InputError(f"rig metadata is not JSON serialisable: {exc}", element="metadata") from exc
    put("specVersion", T.Int, SPEC_VERSION, "version of the handretarget DOF spec stored here")
    put("rigName", T.String, rig.name)
    put("metadata", T.String, metadata_json, "rig metadata as JSON")
    put("jointNames", T.StringArray, Vt.StringArray(rig.joint_names), "original joint names, skeleton order")
    put("dofNames", T.StringArray, Vt.StringArray(rig.dof_names))
    put("dofJoints", T.IntArray, Vt.IntArray([int(d.joint) for d in rig.dofs]), "index into the skeleton joints")
    put("dofKinds", T.TokenArray, Vt.TokenArray([d.kind for d in rig.dofs]), "rotate (radians) or translate (stage units)")
    put("dofAxes", T.Double3Array, Vt.Vec3dArray([Gf.Vec3d(*map(float, d.axis)) for d in rig.dofs]), "unit axis, joint frame")
    put("dofLower", T.DoubleArray, Vt.DoubleArray([float(d.lower) for d in rig.dofs]))
    put("dofUpper", T.DoubleArray, Vt.DoubleArray([float(d.upper) for d in rig.dofs]))
    put("dofRest", T.DoubleArray, Vt.DoubleArray([float(d.rest) for d in rig.dofs]), "DOF values of the bind pose")

    _write_mesh(stage, f"/{root_name}/Surface", rig.surface, skel, purpose=UsdGeom.Tokens.default_,
                role="surface", double_sided=False)
    if rig.visual is not None:
        _write_mesh(stage, f"/{root_name}/Visual", rig.visual, skel, purpose=UsdGeom.Tokens.render,
                    role="visual", double_sided=True)
    return stage


def write_rig_usd(rig: Rig, path, *, dof_spec: bool = True) -> None:
    """Write ``rig`` to a USD file (.usda text, .usdc or .usd crate), atomically: the file is
    written next to its destination under a temporary name and then moved into place.
    ``dof_spec=False`` writes plain UsdSkel (skeleton and skinned surface, no ``handretarget:``
    attribute, no visual mesh): what a DCC exporter writes, and what :func:`read_rig_usd`
    gives DOFs by role."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in _USD_EXTENSIONS:
        raise InputError(f"USD file name must end in {', '.join(_USD_EXTENSIONS)}", source=str(path))
    stage = _build_stage(rig, dof_spec=dof_spec)
    with atomic_path(path, suffix=ext) as tmp:
        if not stage.GetRootLayer().Export(str(tmp)):
            raise OSError(f"USD could not write {path}")


# ---- confinement ---------------------------------------------------------------------------
#: layer fields whose asset paths are composed (sublayers, references, payloads, value clips)
_ARC_FIELDS = {"subLayers": "subLayers", "references": "references", "payload": "payload", "clips": "clips",
               "clipSets": "clipSets"}


def _asset_paths(value):
    """Asset paths (as written) held by a layer field's value."""
    Sdf = _pxr()[1]
    if isinstance(value, Sdf.AssetPath):
        if value.path:
            yield value.path
    elif isinstance(value, (Sdf.Reference, Sdf.Payload)):
        if value.assetPath:
            yield value.assetPath
    elif isinstance(value, (Sdf.ReferenceListOp, Sdf.PayloadListOp)):
        for items in (value.explicitItems, value.addedItems, value.prependedItems, value.appendedItems,
                      value.deletedItems, value.orderedItems):
            for item in items:
                yield from _asset_paths(item)
    elif isinstance(value, dict):
        for v in value.values():
            yield from _asset_paths(v)
    elif isinstance(value, str):
        return
    elif hasattr(value, "__iter__") and not isinstance(value, (bytes, bytearray)):
        try:
            items = list(value)
        except TypeError:
            return
        for v in items:
            yield from _asset_paths(v)


def layer_asset_paths(layer) -> list[tuple[str, str, str, bool]]:
    """Every asset path a layer names: (spec path, field, asset path as written, is a
    composition arc). Sublayers, references, payloads and value clips are arcs; other asset
    paths (textures, asset-valued attributes and metadata) are not."""
    Sdf = _pxr()[1]
    found = []
    for sub in layer.subLayerPaths:
        found.append(("/", "subLayers", str(sub), True))
    specs = []
    layer.Traverse(Sdf.Path.absoluteRootPath, specs.append)
    for path in specs:
        spec = layer.GetObjectAtPath(path)
        if spec is None:
            continue
        for key in spec.ListInfoKeys():
            if key == "subLayers":
                continue
            try:
                value = spec.GetInfo(key)
            except Exception:  # noqa: BLE001 - an unreadable field is not an asset path
                continue
            for asset in _asset_paths(value):
                found.append((str(path), key, str(asset), key in _ARC_FIELDS))
    covered = {a for _, _, a, arc in found if arc}
    for dep in layer.GetCompositionAssetDependencies():  # whatever the walk above did not see
        if dep and dep not in covered:
            found.append(("/", "composition arc", str(dep), True))
    return found


def _arc_label(spec_path: str, field: str) -> str:
    return field if spec_path == "/" else f"{field} of <{spec_path}>"


def _open_layer(path: Path, *, src: str):
    Sdf = _pxr()[1]
    try:
        layer = Sdf.Layer.FindOrOpen(str(path))
        if layer is not None and not layer.dirty:
            layer.Reload()
    except Exception as exc:  # pxr.Tf.ErrorException
        raise InputError(f"not a readable USD file: {_scrub(str(exc), path)}", source=src) from exc
    if layer is None:
        raise InputError("not a readable USD file", source=src)
    return layer


def _scrub(text: str, path: Path) -> str:
    text = text.strip()
    for p in sorted({str(path), str(Path(path).resolve()), str(Path(path).parent), str(Path(path).resolve().parent)},
                    key=len, reverse=True):
        text = text.replace(p, Path(path).name if p.endswith(Path(path).name) else ".")
    return text


def check_confined_layers(path, confine_to) -> None:
    """Every composition arc of the USD layer at ``path``, and of the layers it reaches, must
    name an existing file inside the folder ``confine_to`` (or, when ``confine_to`` is the file
    itself, the layer may have no arc to another layer). Raises InputError naming the layer
    (relative to the folder), the arc and the asset path as written; nothing outside is opened."""
    from .robot_import import Confinement

    path = Path(path)
    confine_to = Path(confine_to)
    single = not confine_to.is_dir()
    conf = Confinement(confine_to.parent if single else confine_to)
    path = conf.check_file(path, source=path.name, what="USD file")
    seen, queue = {path}, [path]
    while queue:
        current = queue.pop()
        shown = conf.shown(current)
        layer = _open_layer(current, src=shown)
        for spec_path, field, asset, arc in layer_asset_paths(layer):
            if not arc:
                continue
            element = f"{_arc_label(spec_path, field)} @{asset}@"
            if single:
                raise InputError("a USD rig uploaded as one layer may not compose other layers; upload one "
                                 "flattened layer", source=shown, element=element)
            if "://" in asset or "[" in asset or ":" in asset[:3]:
                conf.refuse(asset, source=shown, element=element, what="asset path")
            target = conf.resolve(asset, [current.parent], source=shown, element=element, what="asset path")
            if not target.is_file():
                raise InputError(f"layer {asset!r} not found in the upload", source=shown, element=element)
            if target not in seen:
                seen.add(target)
                queue.append(target)


def flatten_confined(path, dest, *, confine_to=None) -> list[str]:
    """Write the USD rig at ``path`` to ``dest`` as one flattened, self-contained layer.

    Composition arcs must stay inside ``confine_to`` (a folder, e.g. an unpacked .usdz/zip
    package; None: the layer at ``path`` may compose nothing), see
    :func:`check_confined_layers`. Asset paths that are not arcs (textures, asset-valued
    attributes and metadata) are dropped before anything is composed, so they are never
    resolved. Returns a warning per dropped asset path."""
    Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt = _pxr()
    path = Path(path)
    check_confined_layers(path, confine_to if confine_to is not None else path)
    root = Path(confine_to) if confine_to is not None else path.parent
    warnings: list[str] = []
    layers = []
    stack = [path]
    opened = set()
    while stack:  # every layer reached (all inside the root, checked above); cleaned in memory
        current = stack.pop()
        if current in opened:
            continue
        opened.add(current)
        layer = _open_layer(current, src=current.name)
        layers.append(layer)
        for spec_path, field, asset, arc in layer_asset_paths(layer):
            if arc:
                stack.append(Path(os.path.normpath(current.parent / asset)))
    for layer in layers:
        shown = os.path.relpath(layer.realPath, os.path.realpath(root)) if confine_to is not None else path.name
        drops = [(sp, f, a) for sp, f, a, arc in layer_asset_paths(layer) if not arc]
        for spec_path, field, asset in drops:
            spec = layer.GetObjectAtPath(spec_path)
            if spec is None:
                continue
            if isinstance(spec, Sdf.AttributeSpec) and field in ("default", "timeSamples") and \
                    spec.typeName in (Sdf.ValueTypeNames.Asset, Sdf.ValueTypeNames.AssetArray):
                owner = spec.owner
                if owner is not None and spec in list(owner.properties):
                    owner.RemoveProperty(spec)
            elif spec.HasInfo(field):
                spec.ClearInfo(field)
            warnings.append(f"{shown}: {_arc_label(spec_path, field)}: asset path {asset!r} dropped (only the "
                            "rig's layers are kept; textures and other files are not resolved)")
    try:
        stage = Usd.Stage.Open(layers[0], Usd.Stage.LoadAll)
        flat = stage.Flatten()
        for layer in layers:  # the in-memory edits must not outlive this call
            layer.Reload(force=True)
    except Exception as exc:  # pxr.Tf.ErrorException
        raise InputError(f"USD cannot compose the rig: {_scrub(str(exc), path)}", source=path.name) from exc
    dest = Path(dest)
    for spec_path, field, asset, arc in layer_asset_paths(flat):
        raise InputError(f"the flattened rig still names {asset!r}", source=path.name,
                         element=_arc_label(spec_path, field))
    if not flat.Export(str(dest)):
        raise OSError(f"USD could not write {dest.name}")
    return sorted(set(warnings))


# ---- reading -------------------------------------------------------------------------------
def _open_stage(path: Path):
    Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt = _pxr()
    src = str(path)
    if not path.is_file():
        raise InputError("file not found", source=src)
    if path.suffix.lower() not in _USD_EXTENSIONS + (".usdz",):
        raise InputError(f"not a USD file (expected {', '.join(_USD_EXTENSIONS + ('.usdz',))})", source=src)
    try:
        layer = Sdf.Layer.Find(src)
        if layer is not None and not layer.dirty:
            layer.Reload()  # the file may have been replaced since it was last opened
        stage = Usd.Stage.Open(src, Usd.Stage.LoadAll)
    except Exception as exc:  # pxr.Tf.ErrorException and friends
        raise InputError(f"not a readable USD file: {str(exc).strip()}", source=src) from exc
    if stage is None:
        raise InputError("not a readable USD file", source=src)
    return stage


def _find_skeleton(stage):
    UsdSkel = _pxr()[5]
    first_any = None
    for prim in stage.Traverse():
        if prim.IsA(UsdSkel.Skeleton):
            parent = prim.GetParent()
            while parent and not parent.IsPseudoRoot():
                if parent.IsA(UsdSkel.Root):
                    return UsdSkel.Skeleton(prim)
                parent = parent.GetParent()
            if first_any is None:
                first_any = UsdSkel.Skeleton(prim)
    return first_any


def _matrices(value, n: int, *, src: str, element: str) -> np.ndarray:
    if value is None:
        raise InputError("attribute is missing", source=src, element=element)
    mats = np.array(value, dtype=np.float64).reshape(-1, 4, 4)
    if len(mats) != n:
        raise InputError(f"has {len(mats)} matrices for {n} joints", source=src, element=element)
    return mats.transpose(0, 2, 1)


def _parents_from_paths(paths: list[str], *, src: str, element: str) -> list[int]:
    index = {}
    for i, p in enumerate(paths):
        if not p or p in index:
            raise InputError(f"joint path {p!r} is empty or used twice", source=src, element=element)
        index[p] = i
    parents = []
    for p in paths:
        parent = -1
        parts = p.split("/")
        for cut in range(len(parts) - 1, 0, -1):
            anc = "/".join(parts[:cut])
            if anc in index:
                parent = index[anc]
                break
        parents.append(parent)
    roots = [paths[i] for i, par in enumerate(parents) if par < 0]
    if len(roots) != 1:
        raise InputError(
            f"the skeleton must have exactly one root joint, found {len(roots)}: {roots[:5]}",
            source=src,
            element=element,
        )
    return parents


def _parents_first_order(parents: list[int]) -> list[int]:
    """Joint order with every parent before its children, otherwise as in the file."""
    order: list[int] = []
    placed = [False] * len(parents)

    def place(i):
        chain = []
        while i >= 0 and not placed[i]:
            chain.append(i)
            i = parents[i]
        for j in reversed(chain):
            placed[j] = True
            order.append(j)

    for i in range(len(parents)):
        place(i)
    return order


def _get(prim, short: str, *, src: str, required: bool = True):
    attr = prim.GetAttribute(_attr_name(short))
    value = attr.Get() if attr and attr.IsValid() else None
    if value is None and required:
        raise InputError(
            f"attribute {_attr_name(short)} is missing (the rig's DOF spec is incomplete)",
            source=src,
            element=f"{prim.GetPath()}.{_attr_name(short)}",
        )
    return value


def _read_dofs(prim, n_joints: int, *, src: str):
    """The DOFs of the ``handretarget:`` spec, or None for a plain UsdSkel skeleton (no spec
    attribute at all: its DOFs are inferred by role, see :func:`read_rig_usd`)."""
    if all(_get(prim, short, src=src, required=False) is None for short in ("specVersion", "dofNames")):
        return None
    version = _get(prim, "specVersion", src=src)
    if int(version) != SPEC_VERSION:
        raise InputError(
            f"unsupported DOF spec version {version} (this reader knows version {SPEC_VERSION})",
            source=src,
            element=f"{prim.GetPath()}.{_attr_name('specVersion')}",
        )
    names = [str(s) for s in _get(prim, "dofNames", src=src)]
    n = len(names)
    columns = {}
    for short in ("dofJoints", "dofKinds", "dofAxes", "dofLower", "dofUpper", "dofRest"):
        value = list(_get(prim, short, src=src))
        if len(value) != n:
            raise InputError(
                f"attribute {_attr_name(short)} has {len(value)} entries but there are {n} DOFs "
                f"({_attr_name('dofNames')})",
                source=src,
                element=f"{prim.GetPath()}.{_attr_name(short)}",
            )
        columns[short] = value
    dofs = []
    for i, name in enumerate(names):
        joint = int(columns["dofJoints"][i])
        if not 0 <= joint < n_joints:
            raise InputError(
                f"joint index {joint} out of range [0, {n_joints})",
                source=src,
                element=f"DOF {name!r} ({_attr_name('dofJoints')})",
            )
        kind = str(columns["dofKinds"][i])
        if kind not in DOF_KINDS:
            raise InputError(
                f"unknown DOF kind {kind!r}; expected one of {DOF_KINDS}",
                source=src,
                element=f"DOF {name!r} ({_attr_name('dofKinds')})",
            )
        dofs.append(
            Dof(
                name=name,
                joint=joint,
                kind=kind,
                axis=np.array(columns["dofAxes"][i], dtype=np.float64),
                lower=float(columns["dofLower"][i]),
                upper=float(columns["dofUpper"][i]),
                rest=float(columns["dofRest"][i]),
            )
        )
    return dofs


def _find_meshes(stage, skel):
    """(surface, visual) Mesh prims bound to ``skel``; either may be None."""
    Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt = _pxr()
    scope = skel.GetPrim().GetParent()
    while scope and not scope.IsPseudoRoot() and not scope.IsA(UsdSkel.Root):
        scope = scope.GetParent()
    if not scope or scope.IsPseudoRoot():
        scope = stage.GetPseudoRoot()
    bound = []
    for prim in Usd.PrimRange(scope):
        if not prim.IsA(UsdGeom.Mesh):
            continue
        target = UsdSkel.BindingAPI(prim).GetInheritedSkeleton()
        if target and target.GetPath() == skel.GetPath():
            bound.append(prim)
    by_role: dict[str, object] = {}
    for prim in bound:
        attr = prim.GetAttribute(_attr_name("role"))
        role = str(attr.Get()) if attr and attr.HasAuthoredValue() else prim.GetName().lower()
        by_role.setdefault(role, prim)
    surface = by_role.get("surface")
    if surface is None and len(bound) == 1:
        surface = bound[0]
    return surface, by_role.get("visual"), bound


def _read_mesh(prim, skel_paths: list[str], *, src: str, element: str):
    """Points (V, 3) in stage units (after geomBindTransform), faces (F, 3), joint indices
    (V, K) into the skeleton's joint order, weights (V, K)."""
    Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt = _pxr()
    el = f"{element} mesh {prim.GetPath()}"
    geom = UsdGeom.Mesh(prim)
    points = geom.GetPointsAttr().Get()
    counts = geom.GetFaceVertexCountsAttr().Get()
    indices = geom.GetFaceVertexIndicesAttr().Get()
    if points is None or counts is None or indices is None:
        raise InputError("mesh needs points, faceVertexCounts and faceVertexIndices", source=src, element=el)
    points = np.array(points, dtype=np.float64).reshape(-1, 3)
    counts = np.array(counts, dtype=np.int64)
    indices = np.array(indices, dtype=np.int64)
    if counts.sum() != len(indices):
        raise InputError(
            f"faceVertexCounts sum to {counts.sum()} but there are {len(indices)} faceVertexIndices",
            source=src,
            element=el,
        )
    if len(counts) and counts.min() < 3:
        raise InputError(f"face {int(np.argmin(counts))} has fewer than 3 vertices", source=src, element=el)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    tris = []
    for n in np.unique(counts):  # fan-triangulate polygons, grouped by size
        sel = starts[counts == n]
        for k in range(1, int(n) - 1):
            tris.append(np.stack([sel, sel + k, sel + k + 1], axis=1))
    if tris:
        corner = np.concatenate(tris)
        # keep the faces in the file's order
        order = np.argsort(corner[:, 0], kind="stable")
        faces = indices[corner[order]]
    else:
        faces = np.zeros((0, 3), dtype=np.int64)
    if geom.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
        faces = faces[:, ::-1].copy()

    binding = UsdSkel.BindingAPI(prim)
    ji_pv, jw_pv = binding.GetJointIndicesPrimvar(), binding.GetJointWeightsPrimvar()
    if not ji_pv or not jw_pv or ji_pv.Get() is None or jw_pv.Get() is None:
        raise InputError(
            "skinned mesh needs primvars:skel:jointIndices and primvars:skel:jointWeights", source=src, element=el
        )
    ji = np.array(ji_pv.Get(), dtype=np.int64)
    jw = np.array(jw_pv.Get(), dtype=np.float64)
    k = ji_pv.GetElementSize()
    if k != jw_pv.GetElementSize() or len(ji) != len(jw) or k < 1 or len(ji) % k:
        raise InputError(
            f"jointIndices ({len(ji)} values, elementSize {ji_pv.GetElementSize()}) and jointWeights "
            f"({len(jw)} values, elementSize {jw_pv.GetElementSize()}) do not match",
            source=src,
            element=el + " skin weights",
        )
    ji, jw = ji.reshape(-1, k), jw.reshape(-1, k)
    if ji_pv.GetInterpolation() == UsdGeom.Tokens.constant and len(ji) == 1:
        ji, jw = np.repeat(ji, len(points), axis=0), np.repeat(jw, len(points), axis=0)
    if len(ji) != len(points):
        raise InputError(
            f"{len(ji)} skinning entries for {len(points)} points (need vertex interpolation)",
            source=src,
            element=el + " skin weights",
        )
    joints_attr = binding.GetJointsAttr()
    mesh_joints = joints_attr.Get() if joints_attr and joints_attr.HasAuthoredValue() else None
    if mesh_joints is not None:
        lookup = {p: i for i, p in enumerate(skel_paths)}
        unknown = [str(p) for p in mesh_joints if str(p) not in lookup]
        if unknown:
            raise InputError(
                f"skel:joints names joints the skeleton does not have: {unknown[:5]}",
                source=src,
                element=el + " skel:joints",
            )
        remap = np.array([lookup[str(p)] for p in mesh_joints], dtype=np.int64)
        if len(ji) and (ji.min() < 0 or ji.max() >= len(remap)):
            raise InputError(
                f"joint index out of range [0, {len(remap)}) of skel:joints", source=src, element=el + " skin weights"
            )
        ji = remap[ji] if len(remap) else ji
    geom_bind = binding.GetGeomBindTransformAttr().Get() if binding.GetGeomBindTransformAttr() else None
    if geom_bind is not None:
        g = np.array(geom_bind, dtype=np.float64).T
        if not np.allclose(g, np.eye(4)):
            points = points @ g[:3, :3].T + g[:3, 3]
    return points, faces, ji, jw


def read_rig_usd(path, *, confine_to=None, mapping=None, hand_root=None) -> Rig:
    """Read a skinned hand from USD: a rig written by :func:`write_rig_usd` (its
    ``handretarget:`` DOF spec), or a plain UsdSkel file as a DCC writes it (SkelRoot >
    Skeleton with joints, restTransforms, bindTransforms; a Mesh bound with jointIndices,
    jointWeights, geomBindTransform), whose DOFs are then inferred by role from the hand model
    (:func:`~retarget_core.rig.dof_roles.infer_dofs`, settled by ``mapping``, a
    :class:`~retarget_core.rig.hand_model.HandMapping`, when the hand model cannot tell) with a
    free root added around the skeleton's own root joint; a plain file may carry edited limits
    for those DOFs as TOML text (:mod:`~retarget_core.rig.dof_limits`) in the Skeleton's
    ``handretarget:dofLimits`` string. metersPerUnit and upAxis Y or Z are
    applied, and for a plain file the Skeleton prim's world transform (its ancestors' xformOps
    included; uniform scale allowed): the rig is in metres, Z-up, world (a file with the DOF
    spec stays in its Skeleton's space, where its free root is defined). A plain file whose skeleton is more than the
    hand (a character's body) gives its hand (:func:`~retarget_core.rig.hand_cut.cut_hand`:
    below ``hand_root``, or found where the fingers branch). Joint matrices must be rigid within
    |R^T R - I| <= 1e-5 and 1e-6 on the last row (float32 files pass) and are re-orthonormalised.
    Validated before returning.

    ``confine_to``: a folder every composed layer (sublayers, references, payloads, value
    clips) must lie in, or the file itself (then it may compose no other layer); checked on
    the layers before the stage is composed (:func:`check_confined_layers`). Errors then name
    the file relative to that folder."""
    path = Path(path)
    src = str(path)
    Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt = _pxr()
    if confine_to is not None:
        check_confined_layers(path, confine_to)
        root = Path(confine_to) if Path(confine_to).is_dir() else Path(confine_to).parent
        src = os.path.relpath(os.path.abspath(path), os.path.abspath(root))
        try:
            stage = _open_stage(path)
        except InputError as err:
            raise InputError(_scrub(str(err).replace(str(path), src), path)) from err
    else:
        stage = _open_stage(path)
    skel = _find_skeleton(stage)
    if skel is None:
        raise InputError("USD file without a skeleton (no UsdSkel.Skeleton prim)", source=src, element="Skeleton")
    prim = skel.GetPrim()
    skel_el = str(prim.GetPath())

    paths = [str(t) for t in (skel.GetJointsAttr().Get() or [])]
    if not paths:
        raise InputError("skeleton has no joints", source=src, element=f"{skel_el}.joints")
    n = len(paths)
    parents = _parents_from_paths(paths, src=src, element=f"{skel_el}.joints")
    names = _get(prim, "jointNames", src=src, required=False)
    if names is None:
        names = skel.GetJointNamesAttr().Get() if skel.GetJointNamesAttr().HasAuthoredValue() else None
    names = [str(s) for s in names] if names is not None else [p.rsplit("/", 1)[-1] for p in paths]
    if len(names) != n:
        raise InputError(
            f"{len(names)} joint names for {n} joints", source=src, element=f"{skel_el}.{_attr_name('jointNames')}"
        )
    bind_attr = skel.GetBindTransformsAttr()
    bind_usd = (
        _matrices(bind_attr.Get(), n, src=src, element=f"{skel_el}.bindTransforms")
        if bind_attr.HasAuthoredValue()
        else None
    )
    rest_attr = skel.GetRestTransformsAttr()
    if rest_attr.HasAuthoredValue() or bind_usd is None:
        rest_local = _matrices(rest_attr.Get(), n, src=src, element=f"{skel_el}.restTransforms")
    else:
        # no rest pose authored: UsdSkel falls back to the bind pose (joint-local from skel space)
        rest_local = np.array([bind_usd[j] if parents[j] < 0 else np.linalg.inv(bind_usd[parents[j]]) @ bind_usd[j]
                               for j in range(n)])
    for label, mats, attr in (("rest", rest_local, "restTransforms"), ("bind", bind_usd, "bindTransforms")):
        for i in range(n if mats is not None else 0):
            why = rigidity_error(mats[i])
            if why is not None:
                raise InputError(f"joint {paths[i]!r}: the {label} transform is not rigid: {why}",
                                 source=src, element=f"{skel_el}.{attr}")
    rest_local = orthonormalized(rest_local)  # float32 files (Blender) carry ~1e-7 of noise
    bind_usd = None if bind_usd is None else orthonormalized(bind_usd)
    dofs = _read_dofs(prim, n, src=src)
    plain = dofs is None
    if hand_root is not None and not plain:
        raise InputError("this rig file carries a handretarget DOF spec: it is a hand rig already, there is no "
                         "hand to cut out (drop --hand-root)", source=src, element="hand_root")
    dofs = dofs or []
    # A plain file is placed in its stage's world; a rig with the DOF spec is in its Skeleton's
    # space (the add-in writes the armature's object space and its free root there).
    placement = _prim_placement(prim, src=src) if plain else (1.0, np.eye(4))

    surface_prim, visual_prim, bound = _find_meshes(stage, skel)
    if surface_prim is None:
        raise InputError(
            "no skinned mesh for the rig's surface (expected a Mesh 'Surface' bound to the skeleton"
            + (f"; found {[str(p.GetPath()) for p in bound]}" if bound else "")
            + ")",
            source=src,
            element="Surface",
        )
    meshes = {"surface": _read_mesh(surface_prim, paths, src=src, element="surface")}
    if visual_prim is not None and visual_prim != surface_prim:
        meshes["visual"] = _read_mesh(visual_prim, paths, src=src, element="visual")

    # Parents-first joint order.
    order = _parents_first_order(parents)
    new_index = np.empty(n, dtype=np.int64)
    new_index[order] = np.arange(n)
    joints_rest = rest_local[order]
    parents_new = [int(new_index[parents[i]]) if parents[i] >= 0 else -1 for i in order]
    names = [names[i] for i in order]
    for d in dofs:
        d.joint = int(new_index[d.joint])
    dofs.sort(key=lambda d: d.joint)  # stable: DOF order within a joint is kept
    if bind_usd is not None:
        bind_usd = bind_usd[order]
    for key, (pts, faces, ji, jw) in meshes.items():
        meshes[key] = (pts, faces, new_index[ji] if ji.size else ji, jw)

    # The Skeleton prim's own world transform (its xformOps and every ancestor's: a SkelRoot
    # placed in a scene) carries the skeleton and, by UsdSkel's rules, the skinned points; the
    # bound Mesh's own transform does not take part in skinning (plain files only, see above).
    s_uniform, placed = placement
    if s_uniform != 1.0 or not np.allclose(placed, np.eye(4), atol=1e-12):
        root = parents_new.index(-1)
        joints_rest[:, :3, 3] *= s_uniform
        joints_rest[root] = placed @ joints_rest[root]
        if bind_usd is not None:
            bind_usd[:, :3, 3] *= s_uniform
            bind_usd = placed @ bind_usd
        for key, (pts, faces, ji, jw) in meshes.items():
            meshes[key] = ((pts * s_uniform) @ placed[:3, :3].T + placed[:3, 3], faces, ji, jw)

    # Units: stage units -> metres.
    scale = float(UsdGeom.GetStageMetersPerUnit(stage))
    if not np.isfinite(scale) or scale <= 0:
        raise InputError(f"metersPerUnit must be positive, got {scale}", source=src, element="metersPerUnit")
    if scale != 1.0:
        joints_rest[:, :3, 3] *= scale
        if bind_usd is not None:
            bind_usd[:, :3, 3] *= scale
        for key, (pts, faces, ji, jw) in meshes.items():
            meshes[key] = (pts * scale, faces, ji, jw)
        for d in dofs:
            if d.kind == "translate":
                d.lower, d.upper, d.rest = d.lower * scale, d.upper * scale, d.rest * scale

    # Up axis: the core is Z-up; a Y-up stage is turned +90 degrees about X.
    up = str(UsdGeom.GetStageUpAxis(stage))
    if up == "Y":
        root = parents_new.index(-1)
        joints_rest[root] = Y_UP_TO_Z_UP @ joints_rest[root]
        if bind_usd is not None:
            bind_usd = Y_UP_TO_Z_UP @ bind_usd
        r = Y_UP_TO_Z_UP[:3, :3]
        for key, (pts, faces, ji, jw) in meshes.items():
            meshes[key] = (pts @ r.T, faces, ji, jw)
    elif up != "Z":
        raise InputError(f"unsupported upAxis {up!r} (expected Y or Z)", source=src, element="upAxis")

    joints = [Joint(name=names[i], parent=parents_new[i], rest_local=joints_rest[i]) for i in range(n)]
    metadata_json = _get(prim, "metadata", src=src, required=False)
    try:
        metadata = json.loads(metadata_json) if metadata_json else {}
    except ValueError as exc:
        raise InputError(f"metadata is not valid JSON: {exc}", source=src, element=_attr_name("metadata")) from exc
    rig_name = _get(prim, "rigName", src=src, required=False) or prim.GetParent().GetName() or path.stem

    def skinned(key):
        pts, faces, ji, jw = meshes[key]
        return SkinnedMesh(vertices=pts, faces=faces, joint_indices=ji, joint_weights=jw)

    rig = Rig(
        name=str(rig_name),
        joints=joints,
        dofs=dofs,
        surface=skinned("surface"),
        visual=skinned("visual") if "visual" in meshes else None,
        metadata=metadata if isinstance(metadata, dict) else {"value": metadata},
    )
    # a plain file's mesh may be a whole character: closed only once the hand is cut out
    rig.validate(source=src, require_closed=not plain)

    # The core binds surfaces at the rest pose. If the file's bindTransforms differ from the
    # rest pose's world transforms, carry the points from the file's bind pose to the rest pose.
    if bind_usd is not None:
        bind_rest = rig.kinematics().bind_world
        if np.abs(bind_usd - bind_rest).max() > 1e-9:
            if not np.all(np.isfinite(bind_usd)) or np.any(np.abs(np.linalg.det(bind_usd)) < 1e-12):
                raise InputError("bind transforms are not invertible", source=src, element=f"{skel_el}.bindTransforms")
            skin = bind_rest @ np.linalg.inv(bind_usd)  # (J, 4, 4)
            for mesh in (rig.surface, rig.visual):
                if mesh is None:
                    continue
                dense = mesh.dense_weights(rig.n_joints)  # (V, J)
                homog = np.concatenate([mesh.vertices, np.ones((mesh.n_vertices, 1))], axis=1)
                moved = np.einsum("vj,jab,vb->va", dense, skin[:, :3, :], homog)
                mesh.vertices = moved
            rig.__dict__.pop("_kinematics", None)
            rig.validate(source=src, require_closed=not plain)
    if plain:
        # A skeleton from a DCC carries no DOFs: the hand cut out of a larger skeleton (hand_cut),
        # the free root around its own root joint and DOFs by role from the hand model
        # (dof_roles), which says what it cannot tell.
        from .dof_roles import infer_dofs
        from .hand_cut import cut_hand, keep_main_shell

        rig = keep_main_shell(cut_hand(rig, hand_root))
        rig.validate(source=src)

        try:
            rig = infer_dofs(rig, mapping=mapping)
        except InputError as err:
            raise InputError(f"{src}: no handretarget DOF spec, and DOFs by role could not be inferred: {err}") from err
        rig.metadata["dof_source"] = ("inferred by role (plain UsdSkel, no handretarget DOF spec); "
                                      "`handretarget rig import` writes them out for editing")
        # limits the user edited (the add-in's panel writes them here, as `rig import --limits` reads them)
        limits_text = _get(prim, "dofLimits", src=src, required=False)
        if limits_text:
            from .dof_limits import apply_limits_text

            rig = apply_limits_text(rig, str(limits_text), source=f"{src}: {skel_el}.{_attr_name('dofLimits')}",
                                    label=f"{_attr_name('dofLimits')} of {skel_el}")
    return rig


def _prim_placement(prim, *, src: str):
    """(uniform scale s, rigid (4, 4)) with the prim's local-to-world transform = rigid @ scale(s),
    column convention, stage units. A non-uniform scale, shear or mirror is an InputError."""
    Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt = _pxr()
    world = np.array(UsdGeom.Imageable(prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default()),
                     dtype=np.float64).T
    linear = world[:3, :3]
    det = float(np.linalg.det(linear))
    if not np.all(np.isfinite(world)) or det <= 0:
        raise InputError(f"the world transform of {prim.GetPath()} is singular or mirrors (determinant {det:.3g})",
                         source=src, element=str(prim.GetPath()))
    s = det ** (1.0 / 3.0)
    rigid = world.copy()
    rigid[:3, :3] = linear / s
    why = rigidity_error(rigid)
    if why is not None:
        raise InputError(f"the world transform of {prim.GetPath()} (its own and its ancestors' xformOps) is not "
                         f"a rotation, translation and uniform scale: {why}", source=src, element=str(prim.GetPath()))
    return s, orthonormalized(rigid)


# ---- compliance ----------------------------------------------------------------------------
def check_usd_compliance(path, *, include_warnings: bool = False) -> list[str]:
    """Run USD's own compliance checks on a file; return the problems found ([] = compliant).

    Runs ``pxr.UsdUtils.ComplianceChecker`` (default rules, not ARKit) where the installed USD
    has it (it was removed in USD 26; the project pins usd-core below 26 so it is there), and
    every validator of the newer UsdValidation framework where that exists (stage metadata,
    prim encapsulation, SkelBindingAPI application, missing references, ...). Errors and
    failed checks are returned; warnings too when ``include_warnings``."""
    path = Path(path)
    src = str(path)
    if not path.is_file():
        raise InputError("file not found", source=src)
    from pxr import UsdUtils

    problems: list[str] = []
    checker_cls = getattr(UsdUtils, "ComplianceChecker", None)
    if checker_cls is not None:
        checker = checker_cls(arkit=False, skipARKitRootLayerCheck=False, rootPackageOnly=False)
        checker.CheckCompliance(src)
        found = list(checker.GetErrors()) + list(checker.GetFailedChecks())
        if include_warnings:
            found += list(checker.GetWarnings())
        problems += [str(p) for p in found]

    try:
        from pxr import UsdValidation
    except ImportError:  # USD older than the validation framework
        UsdValidation = None
    if UsdValidation is not None:
        stage = _open_stage(path)
        registry = UsdValidation.ValidationRegistry()
        context = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators())
        wanted = {UsdValidation.ValidationErrorType.Error}
        if include_warnings:
            wanted.add(UsdValidation.ValidationErrorType.Warn)
        problems += [e.GetErrorAsString() for e in context.Validate(stage) if e.GetType() in wanted]
    if checker_cls is None and UsdValidation is None:
        raise RuntimeError("this USD build has neither ComplianceChecker nor UsdValidation")
    return problems
