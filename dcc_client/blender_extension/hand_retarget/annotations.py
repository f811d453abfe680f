"""Annotation authoring on the target mesh, and the core's annotation JSON
(retarget_core/transfer/annotations.py, annotations.schema.json).

The add-on edits the *target* side only:

- a virtual marker is a vertex group named like the marker ("IndexTip"): one vertex is a point,
  several an area (vertices with weight > 0, ascending ids);
- an axial curve is an item of the mesh's ``hand_retarget.curves`` list: start vertex,
  direction vertex, lambda_a, lambda_s (or "discard").

The *source* side (points on the source hand, its mesh signature, landmark spacing) cannot be
authored on the target mesh: it is kept, per marker / curve name, from the last proposal or
loaded file (``hand_retarget.source_json``). Points are written as (face, barycentric) on the
core's triangles of the exported mesh (:func:`rig_export.core_triangles`).
"""

from __future__ import annotations

import json

from .rig_export import core_triangles

FORMAT = "handretarget.annotations"
VERSION = 1
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


def signature(arm, mesh_obj) -> dict:
    """The target mesh signature the service checks: vertex and (core) triangle counts."""
    me = mesh_obj.data
    return {"rig": arm.name, "vertices": len(me.vertices), "faces": len(core_triangles(me))}


def bone_names(arm) -> set:
    return {b.name for b in arm.data.bones} if arm is not None else set()


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
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or doc.get("version") != VERSION:
        raise AnnotationError(f"not a {FORMAT} version {VERSION} document")
    me = mesh_obj.data
    tris = core_triangles(me)
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
    markers = {}
    for i, m in enumerate(doc.get("markers", [])):
        verts = sorted({point_vertex(p, tris, n, f"marker {m['name']!r} target point {j}")
                        for j, p in enumerate(m["target"])})
        markers[m["name"]] = verts
    curves = []
    for c in doc.get("axial_curves", []):
        tgt = c["target"]
        item = {"name": c["name"], "discard": tgt == "discard"}
        if tgt != "discard":
            item["start"] = point_vertex(tgt["start"], tris, n, f"curve {c['name']!r} start")
            item["direction"] = point_vertex(tgt["direction"], tris, n, f"curve {c['name']!r} direction")
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
    settings.source_json = json.dumps({
        "source": doc["source"],
        "landmark_spacing": doc.get("landmark_spacing", DEFAULT_SPACING),
        "markers": {m["name"]: m["source"] for m in doc.get("markers", [])},
        "curves": {c["name"]: c["source"] for c in doc.get("axial_curves", [])},
    })
    return {"markers": len(markers), "curves": len(curves)}


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
        markers.append({"name": name, "source": source_points,
                        "target": [vertex_point(v, first) for v in verts]})
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
            target = {"start": vertex_point(item.start_vertex, first),
                      "direction": vertex_point(item.direction_vertex, first),
                      "lambda_a": float(item.lambda_a), "lambda_s": lambda_s}
        curves.append({"name": item.name, "source": src["curves"][item.name], "target": target})
    doc = {"format": FORMAT, "version": VERSION, "source": src["source"], "target": signature(arm, mesh_obj),
           "landmark_spacing": src.get("landmark_spacing", DEFAULT_SPACING),
           "markers": markers, "axial_curves": curves}
    return doc, warnings
