"""DOFs by anatomical role for rigs that carry none (a skeleton from a DCC has joints but no
limits): knuckle flexion and abduction, interphalangeal flexion, the thumb base and its joints,
the wrist, with default limits about the axes the hand model computed
(:mod:`retarget_core.rig.hand_model`), never about a bone's own local axes.

The limits are the normal active ranges of motion of the American Academy of Orthopaedic
Surgeons (AAOS, "Joint Motion: Method of Measuring and Recording", 1965; tabulated in Greene
and Heckman, "The Clinical Measurement of Joint Motion", AAOS 1994), in degrees, flexion toward
the palm positive:

============================  ===========================================================
wrist                          flexion 80, extension 70; radial deviation 20, ulnar 30
finger MCP (knuckle)           flexion 90, hyperextension 45; abduction +-20 (a common
                               clinical figure; AAOS gives no value)
finger PIP                     flexion 100, extension 0
finger DIP (and further)       flexion 90, extension 10
thumb CMC (base)               palmar abduction 70 toward the pad, 20 back; flexion 15 /
                               extension 20 in the palm plane (our abduction axis)
thumb MCP                      flexion 50, extension 0
thumb IP                       flexion 80, extension 20
metacarpals (rigs with them)   nearly fixed: +-5 (carpometacarpal play of fingers II-V)
============================  ===========================================================

The limits hold about the anatomical zero (a straight finger); a finger curled at rest starts
``rest_flexion`` into its range, so its DOF limits are shifted by that much. No twist DOFs on
finger joints; abduction only at the knuckles, the thumb base and the wrist. A joint that
already carries DOFs keeps them (a rig's own limits always win).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..errors import InputError
from .hand_model import HandMapping, HandModel, hand_model
from .model import ROOT_DOF_NAMES, Dof, Rig, with_free_root

#: role -> {dof: (lower, upper) in degrees about the anatomical zero}; see the module docstring.
ANATOMICAL_LIMITS_DEG = {
    "wrist": {"flex": (-70.0, 80.0), "abduct": (-30.0, 20.0)},
    "knuckle": {"abduct": (-20.0, 20.0), "flex": (-45.0, 90.0)},
    "pip": {"flex": (0.0, 100.0)},
    "dip": {"flex": (-10.0, 90.0)},
    "thumb_base": {"abduct": (-20.0, 15.0), "flex": (-20.0, 70.0)},
    "thumb_mcp": {"flex": (0.0, 50.0)},
    "thumb_ip": {"flex": (-20.0, 80.0)},
    "metacarpal": {"flex": (-5.0, 5.0)},
}



def joint_roles(model: HandModel) -> dict[int, tuple[str, int]]:
    """joint -> (role, finger segment index) for the first joint of every articulation, the
    metacarpals and the wrist (the palm joint, unless it is the rig's root)."""
    roles: dict[int, tuple[str, int]] = {}
    for finger in model.fingers:
        for k, seg in enumerate(finger.segments):
            if finger.is_thumb:
                role = ("thumb_base", "thumb_mcp")[k] if k < 2 else "thumb_ip"
            else:
                role = ("knuckle", "pip")[k] if k < 2 else "dip"
            roles[seg.joints[0]] = (role, k)
        for j in finger.metacarpals[:1]:
            roles[j] = ("metacarpal", -1)
    if model.palm_joint != 0:
        roles[model.palm_joint] = ("wrist", -1)
    return roles


def infer_dofs(rig: Rig, model: HandModel | None = None, *, mapping: HandMapping | None = None) -> Rig:
    """A copy of ``rig`` whose joints without DOFs get DOFs by role (see the module docstring);
    joints with DOFs keep theirs. The free root is added when the rig has none
    (:func:`~retarget_core.rig.model.with_free_root`: around the rig's own root joint). DOF names are
    ``<joint>_<flex|abduct>``; rest values are 0 (the bind pose)."""
    if rig.dof_names[:6] != ROOT_DOF_NAMES:
        rooted = with_free_root(rig)
        if rooted.n_joints != rig.n_joints:
            model = None  # a root joint was inserted: the joint ids moved
        rig = rooted
    model = model or hand_model(rig, mapping)
    world = rig.kinematics().bind_world
    has_dofs = {d.joint for d in rig.dofs}
    added: list[Dof] = []
    for joint, (role, k) in sorted(joint_roles(model).items()):
        if joint in has_dofs:
            continue
        if role == "wrist":
            flex_axis, abduct_axis, bend = _unit(np.cross(model.forward, model.palmar)), model.palmar, 0.0
        elif role == "metacarpal":
            finger = next(f for f in model.fingers if joint in f.metacarpals)
            flex_axis, abduct_axis, bend = finger.segments[0].flexion_axis, finger.segments[0].abduction_axis, 0.0
        else:
            finger = next(f for f in model.fingers if joint in f.segments[k].joints)
            seg = finger.segments[k]
            flex_axis, abduct_axis, bend = seg.flexion_axis, seg.abduction_axis, seg.rest_flexion
            if finger.is_thumb and k == 0:
                bend = 0.0  # the thumb base has no straight reference
        rotation = world[joint][:3, :3]
        name = rig.joints[joint].name
        for dof, (lo, hi) in ANATOMICAL_LIMITS_DEG[role].items():
            axis_world = flex_axis if dof == "flex" else abduct_axis
            shift = bend if dof == "flex" else 0.0
            lower, upper = np.radians(lo) - shift, np.radians(hi) - shift
            lower, upper = min(lower, 0.0), max(upper, 0.0)  # the bind pose stays reachable
            added.append(Dof(f"{name}_{dof}", joint, "rotate", _unit(rotation.T @ axis_world),
                             float(lower), float(upper), 0.0))
    existing = list(rig.dofs)
    dofs, rest = existing[:6], existing[6:]
    taken = {d.name for d in dofs + rest}
    for d in added:
        if d.name in taken:
            raise InputError(f"cannot name an inferred DOF {d.name!r}: the rig has a DOF of that name",
                             source=rig.name)
    # DOFs in joint order, as every reader of the rig expects parents before children.
    body = sorted(rest + added, key=lambda d: d.joint)
    out = replace(rig, dofs=dofs + body, metadata={**rig.metadata, "dofs_inferred": [d.name for d in added]})
    out.validate(source=f"{rig.name} with inferred DOFs")
    return out


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)
