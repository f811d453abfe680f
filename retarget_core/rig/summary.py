"""Human-readable and JSON-ready summaries of a rig (used by ``handretarget rig info``)."""

from __future__ import annotations

import numpy as np

from .model import Rig


def rig_summary(rig: Rig) -> dict:
    """Plain-data description: joints with their DOFs and limits, mesh counts, topology."""
    report = rig.surface.topology()
    joints = []
    for index, joint in enumerate(rig.joints):
        dofs = [
            {
                "name": d.name,
                "kind": d.kind,
                "axis": [round(float(a), 6) for a in d.axis],
                "lower": float(d.lower),
                "upper": float(d.upper),
                "rest": float(d.rest),
            }
            for d in rig.dofs
            if d.joint == index
        ]
        joints.append({
            "name": joint.name,
            "parent": rig.joints[joint.parent].name if joint.parent >= 0 else None,
            "dofs": dofs,
        })
    summary = {
        "name": rig.name,
        "n_joints": rig.n_joints,
        "n_dofs": rig.n_dofs,
        "joints": joints,
        "surface": {
            "vertices": rig.surface.n_vertices,
            "faces": int(len(rig.surface.faces)),
            "topology": report.describe(),
            "closed": report.closed,
            "manifold": report.manifold,
            "components": report.components,
        },
        # the file-mesh ids of a cut surface are arrays for tools, not for reading: counted here
        "metadata": {k: (f"{len(v['vertices'])} vertices and {len(v['faces'])} triangles from the file's "
                         f"{v['file_vertices']} and {v['file_faces']}" if k == "surface_source" else v)
                     for k, v in rig.metadata.items()},
    }
    if rig.visual is not None:
        summary["visual"] = {"vertices": rig.visual.n_vertices, "faces": int(len(rig.visual.faces))}
    return summary


def format_rig_info(rig: Rig, source: str = "") -> str:
    """Multi-line text: header, one line per joint with its DOFs and limits, mesh facts."""
    s = rig_summary(rig)
    lines = [f"rig {s['name']}" + (f" ({source})" if source else "")]
    lines.append(f"  joints: {s['n_joints']}   DOFs: {s['n_dofs']}")
    if rig.metadata.get("dof_source"):
        lines.append(f"  DOFs: {rig.metadata['dof_source']}")
    for warning in rig.metadata.get("warnings", []):
        lines.append(f"  warning: {warning}")
    if rig.metadata.get("free_root_added"):
        lines.append(f"  free root: joint {rig.metadata['free_root_added']!r} added above the skeleton's own root")
    for joint in s["joints"]:
        parent = joint["parent"] or "-"
        lines.append(f"  joint {joint['name']} (parent {parent})")
        for d in joint["dofs"]:
            unit, scale = ("deg", 180 / np.pi) if d["kind"] == "rotate" else ("m", 1.0)
            lines.append(
                f"    {d['name']:<22} {d['kind']:<9} axis {tuple(d['axis'])}  "
                f"[{d['lower'] * scale:.4g}, {d['upper'] * scale:.4g}] {unit}"
            )
    surf = s["surface"]
    lines.append(f"  surface: {surf['vertices']} vertices, {surf['faces']} faces, {surf['topology']}")
    if "visual" in s:
        lines.append(f"  visual: {s['visual']['vertices']} vertices, {s['visual']['faces']} faces")
    return "\n".join(lines)
