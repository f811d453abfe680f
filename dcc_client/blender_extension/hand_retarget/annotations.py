"""Annotation authoring on the target mesh, and the core's annotation JSON
(retarget_core/transfer/annotations.py, annotations.schema.json).

The add-on edits the *target* side only:

- a virtual marker is a vertex group named like the marker ("IndexTip"): one vertex is a point,
  several an area (vertices with weight > 0, ascending ids);
- an axial curve is an item of the mesh's ``hand_retarget.curves`` list: start vertex,
  direction vertex, lambda_a, lambda_s (or "discard"); the anatomy points a proposed finger
  curve passes through (``through``, the first being the direction point) are kept from the
  file and written back, the first following a re-picked direction.

The *source* side (points on the source hand, its mesh signature, landmark spacing) cannot be
authored on the target mesh: it is kept, per marker / curve name, from the last proposal or
loaded file (``hand_retarget.source_json``). Points are written as (face, barycentric) on the
core's triangles of the exported mesh (:func:`rig_export.core_triangles`).

A target point is never snapped to a corner vertex: the (face, barycentric) points of a loaded
file or proposal are kept as they are (``hand_retarget.target_json``, with their rest
positions when they have one) as long as the marker's vertex group / the curve's vertex still
shows them, and a point picked at the 3D cursor (:func:`surface_point`) is the cursor's closest
point on the mesh, as barycentric coordinates in that core triangle. Only a vertex the artist
puts in a group or picks is a vertex point (weight 1 on one corner).
"""

from __future__ import annotations

import json

from .rig_export import core_triangles

FORMAT = "handretarget.annotations"
VERSION = 1
#: Versions read; version 2 adds optional rest positions to points and a surface hash to the
#: mesh signatures (written when the document carries either).
VERSIONS = (1, 2)
DEFAULT_SPACING = 0.002


class AnnotationError(ValueError):
    """The annotations cannot be used or built (the message says why)."""


def _first_slots(tris, n_vertices):
    """Per vertex, (face, corner) of its first use in ``tris`` (None if unused)."""
    first = [None] * n_vertices
    for f, tri in enumerate(tris):
        for k, v in enumerate(tri):
            if first[v] is None:
                first[v] = (f, k)
    return first


def vertex_point(v: int, first) -> dict:
    """{"face", "barycentric"} of vertex ``v`` (weight 1 on its corner of its first triangle)."""
    slot = first[v] if 0 <= v < len(first) else None
    if slot is None:
        raise AnnotationError(f"vertex {v} is used by no face")
    bary = [0.0, 0.0, 0.0]
    bary[slot[1]] = 1.0
    return {"face": slot[0], "barycentric": bary}


def point_vertex(point: dict, tris, n_vertices: int, what: str) -> int:
    """The mesh vertex of an annotated point: its vertex, or the corner of its face with the
    largest barycentric weight."""
    if "vertex" in point:
        v = int(point["vertex"])
    else:
        face, bary = int(point["face"]), list(point["barycentric"])
        if not 0 <= face < len(tris):
            raise AnnotationError(f"{what}: face {face} out of range [0, {len(tris)})")
        v = tris[face][max(range(3), key=lambda k: bary[k])]
    if not 0 <= v < n_vertices:
        raise AnnotationError(f"{what}: vertex {v} out of range [0, {n_vertices})")
    return v


def _barycentric(a, b, c, x):
    """Barycentric coordinates of the point of triangle (a, b, c) closest to ``x`` (3-sequences)."""
    sub = lambda u, v: [u[i] - v[i] for i in range(3)]  # noqa: E731
    dot = lambda u, v: sum(u[i] * v[i] for i in range(3))  # noqa: E731
    ab, ac, ax = sub(b, a), sub(c, a), sub(x, a)
    d1, d2 = dot(ab, ax), dot(ac, ax)
    if d1 <= 0 and d2 <= 0:
        return [1.0, 0.0, 0.0]
    bx = sub(x, b)
    d3, d4 = dot(ab, bx), dot(ac, bx)
    if d3 >= 0 and d4 <= d3:
        return [0.0, 1.0, 0.0]
    vc = d1 * d4 - d3 * d2
    if vc <= 0 and d1 >= 0 and d3 <= 0:
        t = d1 / (d1 - d3)
        return [1.0 - t, t, 0.0]
    cx = sub(x, c)
    d5, d6 = dot(ab, cx), dot(ac, cx)
    if d6 >= 0 and d5 <= d6:
        return [0.0, 0.0, 1.0]
    vb = d5 * d2 - d1 * d6
    if vb <= 0 and d2 >= 0 and d6 <= 0:
        t = d2 / (d2 - d6)
        return [1.0 - t, 0.0, t]
    va = d3 * d6 - d5 * d4
    if va <= 0 and (d4 - d3) >= 0 and (d5 - d6) >= 0:
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return [0.0, 1.0 - t, t]
    denom = 1.0 / (va + vb + vc)
    v, w = vb * denom, vc * denom
    return [1.0 - v - w, v, w]


def _blend(bary, corners):
    return [sum(bary[k] * corners[k][i] for k in range(3)) for i in range(3)]


def surface_point(me, co) -> tuple[dict, int]:
    """The point of mesh ``me`` closest to ``co`` (mesh coordinates) as the core's point
    ``{"face", "barycentric"}`` on :func:`rig_export.core_triangles` (an n-gon is split as the
    export splits it, and the point lies in the fan triangle nearest to ``co``), and the corner
    vertex nearest to it (for display)."""
    from mathutils.bvhtree import BVHTree

    verts = [tuple(v.co) for v in me.vertices]
    polys = [tuple(p.vertices) for p in me.polygons]
    if not polys:
        raise AnnotationError("the mesh has no faces")
    _, _, poly, _ = BVHTree.FromPolygons(verts, polys).find_nearest(tuple(co))
    if poly is None:
        raise AnnotationError("no face of the mesh is near the 3D cursor")
    base = sum(len(q) - 2 for q in polys[:poly])
    vs = polys[poly]
    best = None
    for k in range(1, len(vs) - 1):
        corners = [verts[vs[0]], verts[vs[k]], verts[vs[k + 1]]]
        bary = _barycentric(*corners, tuple(co))
        at = _blend(bary, corners)
        d = sum((at[i] - co[i]) ** 2 for i in range(3))
        if best is None or d < best[0]:
            best = (d, base + k - 1, bary, (vs[0], vs[k], vs[k + 1]))
    _, face, bary, tri = best
    total = sum(bary)
    bary = [b / total for b in bary]
    return {"face": face, "barycentric": bary}, tri[max(range(3), key=lambda k: bary[k])]


def _as_face_point(point: dict, first) -> dict:
    """A kept point as written: a vertex point becomes (face, barycentric) on its first
    triangle (the same point), keeping its position; a face point is unchanged."""
    if "vertex" not in point:
        return point
    out = vertex_point(int(point["vertex"]), first)
    if "position" in point:
        out["position"] = point["position"]
    return out


def kept_targets(mesh_obj) -> dict:
    """The target points kept from the last file, proposal or cursor pick:
    {"markers": {name: {"points", "vertices"}}, "curves": {name: {"start", "start_vertex",
    "direction", "direction_vertex", "through" (optional)}}}."""
    text = mesh_obj.hand_retarget.target_json
    kept = json.loads(text) if text else {}
    return {"markers": kept.get("markers", {}), "curves": kept.get("curves", {})}


def keep_target(mesh_obj, kind: str, name: str, entry: dict) -> None:
    """Remember target points of marker / curve ``name`` (``kind`` "markers" or "curves")."""
    kept = kept_targets(mesh_obj)
    kept[kind].setdefault(name, {}).update(entry)
    mesh_obj.hand_retarget.target_json = json.dumps(kept)


def forget_target(mesh_obj, kind: str, name: str, which: str | None = None) -> None:
    """Drop the kept target points of ``name`` (only ``which``, e.g. "start", when given)."""
    kept = kept_targets(mesh_obj)
    entry = kept[kind].get(name)
    if entry is None:
        return
    if which is None:
        del kept[kind][name]
    else:
        entry.pop(which, None)
        entry.pop(f"{which}_vertex", None)
    mesh_obj.hand_retarget.target_json = json.dumps(kept)


def signature(arm, mesh_obj) -> dict:
    """The target mesh signature the service checks: vertex and (core) triangle counts."""
    me = mesh_obj.data
    return {"rig": arm.name, "vertices": len(me.vertices), "faces": len(core_triangles(me))}


def bone_names(arm) -> set:
    return {b.name for b in arm.data.bones} if arm is not None else set()


# ---- the service's surface and this mesh -----------------------------------------------------------
def surface_map(arm) -> dict | None:
    """Where the service's hand surface is in the exported mesh, when they differ (a hand cut
    from a body mesh, a mesh in several pieces): {"vertices", "faces": ids in this mesh, -1 for
    the cap the service closed the cut with}; None when they are the same."""
    text = arm.hand_retarget.surface_map_json if arm is not None else ""
    return json.loads(text) if text else None


def _target_points(doc):
    """(owner, key, what) of every target point of a document: owner[key] is a point dict."""
    for m in doc.get("markers", []):
        for j in range(len(m["target"])):
            yield m["target"], j, f"marker {m['name']!r}"
    for c in doc.get("axial_curves", []):
        if isinstance(c.get("target"), dict):
            for which in ("start", "direction"):
                yield c["target"], which, f"curve {c['name']!r} {which}"
            for j in range(len(c["target"].get("through") or ())):
                yield c["target"]["through"], j, f"curve {c['name']!r} through point {j}"


def to_mesh(doc: dict, smap: dict, mesh_signature: dict) -> tuple[dict, list[str]]:
    """A document on the service's surface carried onto this mesh's triangles (the kept
    triangles keep their corners, so barycentrics carry over); points on the cap are dropped
    (a marker left with none is left out, a curve is discarded), with warnings."""
    doc = json.loads(json.dumps(doc))
    warnings, dropped = [], set()
    for owner, key, what in list(_target_points(doc)):
        field = "vertex" if "vertex" in owner[key] else "face"
        ids = smap["vertices" if field == "vertex" else "faces"]
        i = owner[key].get(field)
        if not isinstance(i, int) or not 0 <= i < len(ids):
            raise AnnotationError(f"{what}: {field} {i} is not one of the service's surface ({len(ids)})")
        if ids[i] < 0:
            dropped.add((id(owner), key))
            warnings.append(f"{what}: a point on the cap that closes the cut hand; left out")
        else:
            owner[key] = {**owner[key], field: ids[i]}
    for m in doc.get("markers", []):
        m["target"] = [p for j, p in enumerate(m["target"]) if (id(m["target"]), j) not in dropped]
    doc["markers"] = [m for m in doc.get("markers", []) if m["target"]]
    for c in doc.get("axial_curves", []):
        if isinstance(c.get("target"), dict) and (
                any((id(c["target"]), k) in dropped for k in ("start", "direction"))
                or any((id(c["target"].get("through")), j) in dropped for j in range(len(c["target"].get("through") or ())))):
            c["target"] = "discard"
    doc["target"] = {**(doc.get("target") or {}), **mesh_signature}
    doc["target"].pop("surface_sha256", None)  # the hash is of the service's surface
    return doc, warnings


def to_service(doc: dict, smap: dict, rig_name: str) -> dict:
    """A document on this mesh's triangles carried onto the service's surface; a point on a
    part the service left out (the body, a separate piece) is an error naming it."""
    doc = json.loads(json.dumps(doc))
    inverse = {field: {g: i for i, g in enumerate(smap[key]) if g >= 0}
               for field, key in (("vertex", "vertices"), ("face", "faces"))}
    for owner, key, what in list(_target_points(doc)):
        field = "vertex" if "vertex" in owner[key] else "face"
        i = inverse[field].get(owner[key][field])
        if i is None:
            raise AnnotationError(f"{what}: on a part of the mesh that is not the hand the service retargets (the "
                                  "rest of the body, or a separate piece); move it onto the hand")
        owner[key] = {**owner[key], field: i}
    doc["target"] = {"rig": rig_name, "vertices": len(smap["vertices"]), "faces": len(smap["faces"])}
    return doc


# ---- JSON -> Blender ------------------------------------------------------------------------------
def load_document(doc, arm, mesh_obj) -> dict:
    """Fill ``mesh_obj``'s marker vertex groups and curve list from an annotation document (a
    dict, or JSON text / bytes) and keep its source side. Returns {"markers": n, "curves": n}."""
    if isinstance(doc, (bytes, bytearray)):
        doc = doc.decode("utf-8")
    if isinstance(doc, str):
        try:
            doc = json.loads(doc)
        except ValueError as exc:
            raise AnnotationError(f"not JSON: {exc}") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or doc.get("version") not in VERSIONS:
        raise AnnotationError(f"not a {FORMAT} document of version {' or '.join(map(str, VERSIONS))}")
    me = mesh_obj.data
    tris = core_triangles(me)
    smap, warnings = surface_map(arm), []
    if smap is not None and (doc.get("target") or {}).get("faces") == len(smap["faces"]):
        doc, warnings = to_mesh(doc, smap, signature(arm, mesh_obj))
    target = doc.get("target") or {}
    if (target.get("vertices"), target.get("faces")) != (len(me.vertices), len(tris)):
        raise AnnotationError(
            f"the annotations were made for a target of {target.get('vertices')} vertices and "
            f"{target.get('faces')} triangles; {mesh_obj.name!r} has {len(me.vertices)} and {len(tris)}")
    bones = bone_names(arm)
    clashes = [m["name"] for m in doc.get("markers", []) if m["name"] in bones]
    if clashes:
        raise AnnotationError(f"marker names equal bone names (their vertex groups would skin): {clashes[:5]}")
    n = len(me.vertices)
    markers, kept = {}, {"markers": {}, "curves": {}}
    for i, m in enumerate(doc.get("markers", [])):
        verts = sorted({point_vertex(p, tris, n, f"marker {m['name']!r} target point {j}")
                        for j, p in enumerate(m["target"])})
        markers[m["name"]] = verts
        # the group shows the points' nearest corners; the points themselves are kept
        kept["markers"][m["name"]] = {"points": m["target"], "vertices": verts}
    curves = []
    for c in doc.get("axial_curves", []):
        tgt = c["target"]
        item = {"name": c["name"], "discard": tgt == "discard"}
        if tgt != "discard":
            item["start"] = point_vertex(tgt["start"], tris, n, f"curve {c['name']!r} start")
            item["direction"] = point_vertex(tgt["direction"], tris, n, f"curve {c['name']!r} direction")
            kept["curves"][c["name"]] = {"start": tgt["start"], "start_vertex": item["start"],
                                         "direction": tgt["direction"], "direction_vertex": item["direction"]}
            if tgt.get("through"):
                for j, p in enumerate(tgt["through"]):  # checked here; shown by the curve's overlay only
                    point_vertex(p, tris, n, f"curve {c['name']!r} through point {j}")
                kept["curves"][c["name"]]["through"] = tgt["through"]
            item["lambda_a"] = float(tgt["lambda_a"])
            ls = tgt["lambda_s"]
            item["lambda_s"] = float(ls) if isinstance(ls, (int, float)) else 1.0
            item["lambda_s_json"] = "" if isinstance(ls, (int, float)) else json.dumps(ls)
        curves.append(item)

    # everything checked: now change the mesh
    for name, verts in markers.items():
        group = mesh_obj.vertex_groups.get(name)
        if group is not None:
            mesh_obj.vertex_groups.remove(group)
        group = mesh_obj.vertex_groups.new(name=name)
        group.add(verts, 1.0, 'REPLACE')
    settings = mesh_obj.hand_retarget
    settings.curves.clear()
    for item in curves:
        c = settings.curves.add()
        c.name, c.discard = item["name"], item["discard"]
        if not item["discard"]:
            c.start_vertex, c.direction_vertex = item["start"], item["direction"]
            c.lambda_a, c.lambda_s, c.lambda_s_json = item["lambda_a"], item["lambda_s"], item["lambda_s_json"]
    settings.curve_index = 0
    settings.target_json = json.dumps(kept)
    settings.source_json = json.dumps({
        "source": doc["source"],
        "landmark_spacing": doc.get("landmark_spacing", DEFAULT_SPACING),
        "markers": {m["name"]: m["source"] for m in doc.get("markers", [])},
        "curves": {c["name"]: c["source"] for c in doc.get("axial_curves", [])},
    })
    return {"markers": len(markers), "curves": len(curves), "warnings": warnings}


# ---- Blender -> JSON ------------------------------------------------------------------------------
def marker_vertices(mesh_obj, exclude=()) -> dict:
    """{group name: [vertex ids with weight > 0]} of the mesh's vertex groups, except ``exclude``."""
    groups = {g.index: g.name for g in mesh_obj.vertex_groups if g.name not in exclude}
    out = {name: [] for name in groups.values()}
    for v in mesh_obj.data.vertices:
        for ge in v.groups:
            name = groups.get(ge.group)
            if name is not None and ge.weight > 0.0:
                out[name].append(v.index)
    return out


def source_side(mesh_obj) -> dict | None:
    text = mesh_obj.hand_retarget.source_json
    return json.loads(text) if text else None


def build_document(arm, mesh_obj) -> tuple[dict, list[str]]:
    """The annotation document of the current markers and curves, and warnings (markers or
    curves left out). Raises AnnotationError when it cannot be built."""
    src = source_side(mesh_obj)
    if src is None:
        raise AnnotationError("no source side yet: propose annotations or load an annotation file first")
    me = mesh_obj.data
    tris = core_triangles(me)
    first = _first_slots(tris, len(me.vertices))
    warnings = []
    kept = kept_targets(mesh_obj)
    groups = marker_vertices(mesh_obj, exclude=bone_names(arm))
    markers = []
    for name, source_points in src["markers"].items():
        verts = groups.pop(name, None)
        if not verts:
            warnings.append(f"marker {name}: no vertex group (or an empty one) on the target; left out")
            continue
        if len(source_points) > 1 and len(verts) > 1 and len(verts) != len(source_points):
            raise AnnotationError(f"marker {name}: {len(source_points)} source points but {len(verts)} target "
                                  "vertices; an area needs the same number on both sides (or 1 on one side)")
        keep = kept["markers"].get(name)
        if keep is not None and sorted(keep["vertices"]) == sorted(verts):  # group unchanged: the exact points
            target_points = [_as_face_point(p, first) for p in keep["points"]]
        else:
            target_points = [vertex_point(v, first) for v in verts]
        markers.append({"name": name, "source": source_points, "target": target_points})
    for name in groups:
        warnings.append(f"vertex group {name}: no marker of that name on the source side; ignored")
    curves = []
    for item in mesh_obj.hand_retarget.curves:
        if item.name not in src["curves"]:
            warnings.append(f"curve {item.name}: no source axis of that name; left out")
            continue
        if item.discard:
            target = "discard"
        else:
            if item.lambda_a <= 0 or item.lambda_s <= 0:
                raise AnnotationError(f"curve {item.name}: lambda_a and lambda_s must be positive")
            lambda_s = json.loads(item.lambda_s_json) if item.lambda_s_json else float(item.lambda_s)
            keep = kept["curves"].get(item.name, {})

            def point(which, vertex):  # the kept point while the curve still shows its vertex
                if which in keep and keep.get(f"{which}_vertex") == vertex:
                    return _as_face_point(keep[which], first)
                return vertex_point(vertex, first)

            target = {"start": point("start", item.start_vertex),
                      "direction": point("direction", item.direction_vertex),
                      "lambda_a": float(item.lambda_a), "lambda_s": lambda_s}
            if keep.get("through"):
                # the curve passes through the anatomy points it was loaded with; the first is the
                # direction point, so a re-picked direction moves the first leg's end with it
                target["through"] = [target["direction"]] + [_as_face_point(p, first) for p in keep["through"][1:]]
        curves.append({"name": item.name, "source": src["curves"][item.name], "target": target})
    doc = {"format": FORMAT, "version": VERSION, "source": src["source"], "target": signature(arm, mesh_obj),
           "landmark_spacing": src.get("landmark_spacing", DEFAULT_SPACING),
           "markers": markers, "axial_curves": curves}
    smap = surface_map(arm)
    if smap is not None:
        doc = to_service(doc, smap, arm.name)
    if _has_v2_fields(doc):
        doc["version"] = 2
    return doc, warnings


def _has_v2_fields(doc) -> bool:
    """True when a document carries a point position or a surface hash (format version 2)."""
    if any("surface_sha256" in (doc.get(side) or {}) for side in ("source", "target")):
        return True
    stack = [doc.get("markers"), doc.get("axial_curves")]
    while stack:
        x = stack.pop()
        if isinstance(x, dict):
            if "position" in x:
                return True
            stack.extend(x.values())
        elif isinstance(x, list):
            stack.extend(x)
    return False
