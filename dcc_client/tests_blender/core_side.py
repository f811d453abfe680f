"""The core's side of the Blender tests, run with the service's Python (/work/main/.venv): the
bpy environment pins numpy < 2 and cannot import retarget_core, so files pass between the two.

    python core_side.py inputs OUT_DIR            demo rig USD + its DOF spec, a short demo clip
    python core_side.py rig RIG.usda POSE.json OUT.npy
                                                  read the rig, skin it at the DOF values in
                                                  POSE.json ({name: value}), print a summary
    python core_side.py grab OUT_DIR              GRAB sequence on a hand-shaped MANO model + meshes
    python core_side.py annotations FILE RIG.usda check an annotation file against the rig and
                                                  the demo source hand
    python core_side.py hand OUT_DIR              the demo target hand as arrays (hand.json: joints,
                                                  their rest origins, surface, skin weights) for a
                                                  test to build its own armature from, as
                                                  plain UsdSkel (demo_plain.usda), and a 120-frame
                                                  grasp window at real speed (grasp_clip.npz)
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

RESOLUTION = 0.006        # target hand: coarse keeps Blender and the solver fast
SOURCE_RESOLUTION = 0.004  # the demo source hand the clip and the proposer use


def inputs(out: Path) -> None:
    from retarget_core.clip.demo import make_demo_clip, source_rig
    from retarget_core.rig.demo_hands import demo_hand
    from retarget_core.rig.io import save_rig

    out.mkdir(parents=True, exist_ok=True)
    rig = demo_hand("human_alt", RESOLUTION)
    save_rig(rig, out / "demo_rig.usda")
    spec = [{"name": d.name, "joint": rig.joints[d.joint].name, "kind": d.kind, "axis": d.axis.tolist(),
             "lower": d.lower, "upper": d.upper} for d in rig.dofs]
    (out / "demo_spec.json").write_text(json.dumps(spec))
    clip = make_demo_clip("bottle_pick_place", time_scale=0.05, resolution=SOURCE_RESOLUTION,
                          rig=source_rig(SOURCE_RESOLUTION))
    clip.save(out / "clip.npz")
    print(json.dumps({"frames": int(clip.n_frames), "fps": float(clip.fps)}))


def grab(out: Path) -> None:
    """GRAB files on a hand-shaped MANO model (the core tests' generator, tests/grab_hand_sequence.py):
    a 60-frame bottle grasp, the MANO model, the object mesh and the subject's hand template."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))
    from grab_hand_sequence import write_known_sequence

    known = write_known_sequence(out, n_frames=60, lead=30)
    print(json.dumps({"sequence": str(known.path), "mano": str(known.mano),
                      "object_mesh": str(out / "tools/object_meshes/contact_meshes/bottle_pick_place.ply"),
                      "vtemp": str(out / "tools/subject_meshes/male/s1_rhand.ply"),
                      "contact_frames": int(known.contact_frames.sum())}))


def rig(path: str, pose_json: str, out_npy: str) -> None:
    from retarget_core.rig.usd_io import read_rig_usd

    r = read_rig_usd(path)
    values = json.loads(Path(pose_json).read_text())
    q = r.rest_pose.copy()
    for i, name in enumerate(r.dof_names):
        if name in values:
            q[i] = values[name]
    kin = r.kinematics()
    np.save(out_npy, np.stack([kin.skin(r.rest_pose), kin.skin(q)]))
    print(json.dumps({
        "name": r.name, "joints": r.joint_names, "dofs": r.dof_names, "kinds": [d.kind for d in r.dofs],
        "axes": [d.axis.tolist() for d in r.dofs], "lower": r.lower.tolist(), "upper": r.upper.tolist(),
        "rest": r.rest_pose.tolist(), "vertices": int(r.surface.n_vertices), "faces": r.surface.faces.tolist(),
        "world_at_pose": kin.pose(q).world.tolist(),
    }))


def annotations(path: str, rig_path: str) -> None:
    from retarget_core.clip.demo import source_rig
    from retarget_core.rig.usd_io import read_rig_usd
    from retarget_core.transfer.annotations import load_annotations

    a = load_annotations(path)  # schema and semantic checks
    target, source = read_rig_usd(rig_path), source_rig(SOURCE_RESOLUTION)
    a.check_meshes(source.surface.faces, source.surface.n_vertices, target.surface.faces, target.surface.n_vertices,
                   source=path)
    print(json.dumps({"markers": len(a.markers), "curves": len(a.curves)}))


def propose(rig_path: str, out: str) -> None:
    """Proposed annotations from the demo source hand onto the exported rig, with positions
    (format version 2)."""
    from retarget_core.clip.demo import source_rig
    from retarget_core.rig.usd_io import read_rig_usd
    from retarget_core.transfer.annotations import save_annotations, with_positions
    from retarget_core.transfer.propose import propose_annotations

    target, source = read_rig_usd(rig_path), source_rig(SOURCE_RESOLUTION)
    save_annotations(with_positions(propose_annotations(source, target), source, target), out)
    print(json.dumps({"faces": int(len(target.surface.faces)), "vertices": int(target.surface.n_vertices)}))


def hand(out: Path) -> None:
    """The target hand (the ``inputs`` one) as plain arrays and as plain UsdSkel: the same hand
    with DOFs by role, the reference a test's own armature is compared against."""
    from retarget_core.rig.demo_hands import demo_hand
    from retarget_core.rig.usd_io import write_rig_usd

    out.mkdir(parents=True, exist_ok=True)
    rig = demo_hand("human_alt", RESOLUTION)
    write_rig_usd(rig, out / "demo_plain.usda", dof_spec=False)
    s = rig.surface
    world = rig.kinematics().bind_world
    weights = [[[int(j), float(w)] for j, w in zip(s.joint_indices[v], s.joint_weights[v]) if w > 0]
               for v in range(s.n_vertices)]
    (out / "hand.json").write_text(json.dumps({
        "joints": rig.joint_names, "parents": [j.parent for j in rig.joints],
        "origins": world[:, :3, 3].tolist(), "vertices": s.vertices.tolist(), "faces": s.faces.tolist(),
        "weights": weights}))
    from retarget_core.clip.demo import grasp_window, make_demo_clip, source_rig

    # a real-speed window (the grasp, 1 s at 120 fps): its delivered curve is a figure worth comparing
    clip = grasp_window(make_demo_clip("bottle_pick_place", resolution=SOURCE_RESOLUTION,
                                       rig=source_rig(SOURCE_RESOLUTION)), 120)
    clip.save(out / "grasp_clip.npz")
    print(json.dumps({"joints": rig.n_joints, "vertices": int(s.n_vertices), "frames": int(clip.n_frames)}))


if __name__ == "__main__":
    cmd, args = sys.argv[1], sys.argv[2:]
    {"inputs": lambda: inputs(Path(args[0])), "grab": lambda: grab(Path(args[0])), "rig": lambda: rig(*args),
     "annotations": lambda: annotations(*args), "propose": lambda: propose(*args),
     "hand": lambda: hand(Path(args[0]))}[cmd]()
