"""The foreign-hand fixture builders (tests/foreign_hands.py) themselves: every variant is a valid
rig, keeps (or provably changes) the kinematics and surface as documented, and carries its truth."""

import numpy as np
import pytest

from retarget_core.mesh.geometry import signed_volume
from tests.foreign_hands import (
    FINGERS, curl_at_rest, drop_fingers, foreign_demo, insert_metacarpals, mirror, move, posed_vertices, rename,
    reroll, rigid, rot_x, rot_y, rot_z, rotate_thumb_at_rest, hinge_offsets, slide_hinges, strip_dofs, truth_of, variant_q,
)
from retarget_core.rig.demo_hands import DEMO_HANDS

RES = 0.005
ATOL = 1e-9
MOVE = rigid(rot_z(35.0) @ rot_x(-120.0) @ rot_y(20.0), (0.3, -0.15, 0.42))
FLIP = np.diag([-1.0, 1.0, 1.0])


@pytest.fixture(scope="module")
def hands():
    return {name: foreign_demo(name, RES) for name in ("source_human", "robot4", "alien", "prosthetic_2dof")}


def _q(rig, seed, root=True):
    q = rig.random_pose(np.random.default_rng(seed))
    if not root:
        q[[i for i, d in enumerate(rig.dofs) if d.joint == 0]] = 0.0
    return q


def _check_truth(rig, truth):
    """The truth names real joints, its palmar directions are unit, chains are parent-linked."""
    names = set(rig.joint_names)
    assert truth.palm in names
    assert set(truth.palmar) <= names and set(truth.original) <= names
    for finger, chain in truth.fingers.items():
        assert finger in FINGERS and chain and set(chain) <= names
        first = rig.joint_index(chain[0])
        parent = rig.joints[first].parent
        expected = truth.metacarpals.get(finger, truth.palm)
        assert rig.joints[parent].name == expected
        for a, b in zip(chain, chain[1:]):
            assert rig.joints[rig.joint_index(b)].parent == rig.joint_index(a)
    for direction in truth.palmar.values():
        assert abs(np.linalg.norm(direction) - 1) < 1e-9
    assert set(truth.dof_original) <= set(rig.dof_names)
    assert truth.handedness in ("right", "left")


# ---- the unmodified truth -----------------------------------------------------------------------
@pytest.mark.parametrize("name", list(DEMO_HANDS))
def test_truth_of_demo_hand(name):
    rig, truth = foreign_demo(name, RES)
    _check_truth(rig, truth)
    bind = rig.kinematics().bind_world
    assert set(truth.palmar) == set(rig.joint_names)
    for i, joint in enumerate(rig.joint_names):
        assert np.allclose(truth.palmar[joint], -bind[i][:3, 2], atol=1e-12)
    assert truth.palm == ("wrist" if "wrist" in rig.joint_names else "root")
    n_joints = sum(len(c) for c in truth.fingers.values())
    assert n_joints == rig.n_joints - (2 if "wrist" in rig.joint_names else 1)
    assert truth.fingers["thumb"][0] == "thumb1"
    # the fingers' palmar side faces the palm side (-Z) of the demo hand frame
    for f in ("index", "middle"):
        assert truth.palmar[truth.fingers[f][0]] @ np.array([0, 0, -1.0]) > 0.9


# ---- 1. rename ----------------------------------------------------------------------------------
@pytest.mark.parametrize("style", ["rigify", "mixamo", "unreal", "ids"])
def test_rename_keeps_posed_surface(hands, style):
    rig, truth = hands["source_human"]
    out, t = rename(rig, truth, style)
    out.validate()
    _check_truth(out, t)
    q = _q(rig, 1)
    assert np.allclose(posed_vertices(out, variant_q(rig, out, t, q)), posed_vertices(rig, q), atol=ATOL)
    old = {n for n in rig.joint_names if n != "root"}
    assert not old & set(out.joint_names)
    assert set(t.original.values()) == set(rig.joint_names)
    for f, chain in t.fingers.items():
        assert [t.original[j] for j in chain] == truth.fingers[f]
    expected_palm = {"rigify": "hand.R", "mixamo": "RightHand", "unreal": "hand_r"}
    if style in expected_palm:
        assert t.palm == expected_palm[style]
    else:
        # shuffled joint order, parents first, meaningless DOF names except the free root's
        assert [t.original[n] for n in out.joint_names] != rig.joint_names
        assert all(n.startswith("d") for n, d in zip(out.dof_names, out.dofs) if d.joint != 0)
        assert out.dof_names[:6] == rig.dof_names[:6]


def test_rename_styles_spell_names(hands):
    rig, truth = hands["source_human"]
    assert rename(rig, truth, "rigify")[1].fingers["index"][0] == "f_index.01.R"
    assert rename(rig, truth, "rigify")[1].fingers["thumb"][0] == "thumb.01.R"
    assert rename(rig, truth, "mixamo")[1].fingers["index"][0] == "RightHandIndex1"
    assert rename(rig, truth, "unreal")[1].fingers["index"][0] == "index_01_r"
    left = rename(*mirror(rig, truth), "unreal")[1]
    assert left.palm == "hand_l" and left.fingers["pinky"][2] == "pinky_03_l"
    out, t = rename(rig, truth, "mixamo")
    assert "RightHandIndex1_flex" in out.dof_names


# ---- 2. reroll ----------------------------------------------------------------------------------
@pytest.mark.parametrize("degrees", [90, 180])
@pytest.mark.parametrize("name", ["source_human", "robot4"])
def test_reroll_keeps_kinematics(hands, name, degrees):
    rig, truth = hands[name]
    out, t = reroll(rig, truth, degrees)
    _check_truth(out, t)
    for seed in (2, 3):
        q = _q(rig, seed)
        assert np.allclose(posed_vertices(out, q), posed_vertices(rig, q), atol=ATOL)
        world, world0 = out.kinematics().pose(q).world, rig.kinematics().pose(q).world
        assert np.allclose(world[:, :3, 3], world0[:, :3, 3], atol=ATOL)
        assert np.allclose(world[:, :3, 1], world0[:, :3, 1], atol=ATOL)  # the bone axis is kept
    bind = out.kinematics().bind_world
    dots = [truth.palmar[n] @ -bind[i][:3, 2] for i, n in enumerate(out.joint_names) if i > 0]
    # the palmar truth no longer is the frame's -Z: the roll really happened
    assert np.allclose(dots, 0.0 if degrees == 90 else -1.0, atol=1e-9)
    assert all(np.array_equal(t.palmar[k], truth.palmar[k]) for k in truth.palmar)


def test_reroll_chosen_joints(hands):
    rig, truth = hands["source_human"]
    out, _ = reroll(rig, truth, 90, joints=["index2"])
    changed = [j.name for j, j0 in zip(out.joints, rig.joints) if not np.allclose(j.rest_local, j0.rest_local)]
    assert changed == ["index2", "index3"]
    q = _q(rig, 4)
    assert np.allclose(posed_vertices(out, q), posed_vertices(rig, q), atol=ATOL)


# ---- 2b. hinges slid along their axes ----------------------------------------------------------
@pytest.mark.parametrize("name", ["robot4", "prosthetic_2dof"])
def test_slide_hinges_keeps_kinematics(hands, name):
    rig, truth = hands[name]
    offsets = hinge_offsets(rig)
    assert len(offsets) >= 10
    out, t = slide_hinges(rig, truth, offsets)
    _check_truth(out, t)
    moved = out.kinematics().bind_world[:, :3, 3] - rig.kinematics().bind_world[:, :3, 3]
    for joint, s in offsets.items():
        # the joint really moved, along its own axis
        assert np.linalg.norm(moved[rig.joint_index(joint)]) == pytest.approx(abs(s), abs=1e-12)
    for seed in (2, 3):
        q = _q(rig, seed)
        assert np.allclose(posed_vertices(out, q), posed_vertices(rig, q), atol=ATOL)


# ---- 3. move ------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["source_human", "robot4"])
def test_move(hands, name):
    rig, truth = hands[name]
    out, t = move(rig, truth, MOVE)
    _check_truth(out, t)
    assert np.array_equal(out.joints[0].rest_local, np.eye(4))
    r, p = MOVE[:3, :3], MOVE[:3, 3]
    assert np.allclose(out.surface.vertices, rig.surface.vertices @ r.T + p, atol=ATOL)
    q = _q(rig, 5, root=False)
    assert np.allclose(posed_vertices(out, q), posed_vertices(rig, q) @ r.T + p, atol=ATOL)
    # with the root posed too: root(q) @ MOVE @ root(q)^-1 applied to the original's posed surface
    q = _q(rig, 6)
    root = rig.kinematics().pose(q).world[0]
    m = root @ MOVE @ np.linalg.inv(root)
    assert np.allclose(posed_vertices(out, q), posed_vertices(rig, q) @ m[:3, :3].T + m[:3, 3], atol=ATOL)
    for k in truth.palmar:
        assert np.allclose(t.palmar[k], r @ truth.palmar[k])
    assert np.allclose(t.to_variant, MOVE)
    assert np.allclose(t.palm_origin, p)
    palm = out.kinematics().bind_world[out.joint_index(t.palm)][:3, 3]
    assert np.allclose(palm, 0.0 if t.palm == out.joint_names[0] else p)  # a root palm stays at the origin
    with pytest.raises(ValueError):
        move(rig, truth, np.diag([-1.0, 1, 1, 1]))


# ---- 4. mirror ----------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["source_human", "robot4", "alien"])
def test_mirror(hands, name):
    rig, truth = hands[name]
    out, t = mirror(rig, truth)
    _check_truth(out, t)
    assert t.handedness == "left"
    for j in out.joints:
        assert np.linalg.det(j.rest_local[:3, :3]) > 0
    assert signed_volume(rig.surface.vertices, rig.surface.faces) > 0
    assert signed_volume(out.surface.vertices, out.surface.faces) > 0
    for seed in (7, 8):
        q = _q(rig, seed)
        qm = variant_q(rig, out, t, q)
        assert np.allclose(posed_vertices(out, qm), posed_vertices(rig, q) @ FLIP, atol=ATOL)
    # the thumb is now on the +X side (it was on -X)
    thumb_tip = out.kinematics().bind_world[out.joint_index(t.fingers["thumb"][-1])][:3, 3]
    assert thumb_tip[0] > 0.02
    bind = out.kinematics().bind_world
    for i, n in enumerate(out.joint_names):
        assert np.allclose(t.palmar[n], FLIP @ truth.palmar[n])
        assert np.allclose(t.palmar[n], -bind[i][:3, 2], atol=1e-9)  # mirror keeps -Z palmar (D leaves Z)
    # the free root stays the standard free root
    assert out.dof_names[:6] == rig.dof_names[:6]
    for d, d0 in zip(out.dofs[:6], rig.dofs[:6]):
        assert np.array_equal(d.axis, d0.axis)
    back, bt = mirror(out, t)
    assert bt.handedness == "right"
    for j, j0 in zip(back.joints, rig.joints):
        assert np.allclose(j.rest_local, j0.rest_local, atol=1e-15)
    assert np.allclose(back.surface.vertices, rig.surface.vertices)


# ---- 5. drop fingers ----------------------------------------------------------------------------
@pytest.mark.parametrize("drop", [("pinky",), ("ring", "pinky")])
def test_drop_fingers(hands, drop):
    rig, truth = hands["source_human"]
    out, t = drop_fingers(rig, truth, drop)
    out.validate()
    _check_truth(out, t)
    assert set(t.fingers) == set(FINGERS) - set(drop)
    assert not any(n.startswith(f) for n in out.joint_names for f in drop)
    assert out.n_dofs == rig.n_dofs - 9 * len(drop)
    assert out.surface.n_vertices < rig.surface.n_vertices
    # the remaining fingers are where they were
    for f in t.fingers:
        for joint in t.fingers[f]:
            a = out.kinematics().bind_world[out.joint_index(joint)]
            b = rig.kinematics().bind_world[rig.joint_index(joint)]
            assert np.allclose(a, b)
    with pytest.raises(ValueError):
        drop_fingers(*reroll(rig, truth, 90), drop)


def test_drop_robot_finger(hands):
    out, t = drop_fingers(*hands["robot4"], ["ring"])
    assert set(t.fingers) == {"thumb", "index", "middle"} and t.palm == "root"
    assert out.n_dofs == 22 - 4


# ---- 6. metacarpals -----------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["source_human", "robot4", "prosthetic_2dof"])
def test_insert_metacarpals(hands, name):
    rig, truth = hands[name]
    out, t = insert_metacarpals(rig, truth)
    _check_truth(out, t)
    non_thumb = [f for f in t.fingers if f != "thumb"]
    assert set(t.metacarpals) == set(non_thumb)
    assert t.fingers == truth.fingers
    assert out.n_joints == rig.n_joints + len(non_thumb)
    assert out.n_dofs == rig.n_dofs + len(non_thumb)
    kin, kin0 = out.kinematics(), rig.kinematics()
    palm = out.joint_index(t.palm)
    assert out.joints[out.joint_index(t.fingers["thumb"][0])].parent == palm
    for joint in rig.joint_names:
        assert np.allclose(kin.bind_world[out.joint_index(joint)], kin0.bind_world[rig.joint_index(joint)], atol=1e-12)
    weights = out.surface.dense_weights(out.n_joints)
    for f, m in t.metacarpals.items():
        mi = out.joint_index(m)
        assert out.joints[mi].parent == palm
        start, knuckle = kin.bind_world[palm][:3, 3], kin.bind_world[out.joint_index(t.fingers[f][0])][:3, 3]
        assert np.allclose(start, t.palm_origin)
        assert np.allclose(kin.bind_world[mi][:3, 3], start + 0.2 * (knuckle - start))
        assert np.allclose(kin.bind_world[mi][:3, 1], (knuckle - start) / np.linalg.norm(knuckle - start))
        assert (weights[:, mi] > 0.5).sum() > 10  # it owns palm skin
    # the palm keeps the skin near the wrist
    assert (weights[:, palm] > 0.5).sum() > 0
    # metacarpal DOFs at 0: exactly the original; flexed: the palm skin moves
    q = _q(rig, 9)
    qv = variant_q(rig, out, t, q)
    assert np.allclose(posed_vertices(out, qv), posed_vertices(rig, q), atol=ATOL)
    meta_dofs = [i for i, d in enumerate(out.dofs) if out.joint_names[d.joint] in t.metacarpals.values()]
    assert all(abs(out.dofs[i].upper - np.radians(5)) < 1e-12 for i in meta_dofs)
    qv[meta_dofs] = np.radians(5)
    moved = np.linalg.norm(posed_vertices(out, qv) - posed_vertices(rig, q), axis=1)
    assert moved.max() > 1e-3


# ---- 7./8. bind-pose bakes ----------------------------------------------------------------------
def _check_bake(rig, truth, out, t, offsets):
    """offsets: original DOF name -> baked offset (radians)."""
    _check_truth(out, t)
    o = np.zeros(rig.n_dofs)
    for name, value in offsets.items():
        o[rig.dof_index(name)] = value
    assert np.count_nonzero(o) == len(offsets) > 0
    kin0 = rig.kinematics()
    # the bind surface is the original posed at the bake
    assert np.allclose(out.surface.vertices, posed_vertices(rig, rig.rest_pose + o), atol=ATOL)
    assert np.allclose(out.kinematics().bind_world, kin0.pose(rig.rest_pose + o).world, atol=1e-12)
    assert not np.allclose(out.surface.vertices, rig.surface.vertices, atol=1e-3)
    # the reachable set is unchanged: limits map back to the original's
    for d in out.dofs:
        orig, scale, offset = t.dof_original[d.name]
        d0 = rig.dofs[rig.dof_index(orig)]
        assert scale == 1.0
        assert np.isclose(d.lower - offset, d0.lower) and np.isclose(d.upper - offset, d0.upper)
        assert np.isclose(offset, -o[rig.dof_index(orig)])
    # the kinematics are the original's, shifted by the offsets: joint frames exactly; the skin
    # exactly where one joint owns a vertex (re-binding a blended, posed LBS surface is not
    # exact where joints share a vertex), and within millimetres elsewhere
    motion = out.kinematics().bind_world @ kin0.inv_bind  # how the bake moved each joint
    ji, jw = out.surface.joint_indices, out.surface.joint_weights
    spread = np.abs(motion[ji] - motion[ji[:, :1]]).max(axis=(2, 3))
    single = np.all((spread < 1e-12) | (jw == 0), axis=1)  # its joints moved together
    assert single.sum() > 100 and (~single).sum() > 100
    for seed in (10, 11):
        q = _q(rig, seed)
        qv = variant_q(rig, out, t, q)
        assert np.allclose(out.kinematics().pose(qv).world, kin0.pose(q).world, atol=1e-12)
        posed, posed0 = posed_vertices(out, qv), posed_vertices(rig, q)
        assert np.allclose(posed[single], posed0[single], atol=ATOL)
        assert np.abs(posed - posed0).max() < 0.01
    # q = 0 is the baked pose when the original rests at 0
    if not np.any(rig.rest_pose):
        assert not np.any(out.rest_pose)
    # palmar truth is carried by each joint's rotation: still -Z of the (curled) bind frames
    bind = out.kinematics().bind_world
    for i, n in enumerate(out.joint_names):
        assert np.allclose(t.palmar[n], -bind[i][:3, 2], atol=1e-9)


@pytest.mark.parametrize("degrees", [20, 40])
@pytest.mark.parametrize("name", ["source_human", "robot4"])
def test_curl_at_rest(hands, name, degrees):
    rig, truth = hands[name]
    out, t = curl_at_rest(rig, truth, degrees)
    offsets = {d.name: np.radians(degrees) for d in rig.dofs
               if d.name.endswith("_flex") and truth.finger_of(rig.joint_names[d.joint]) not in (None, "thumb")}
    assert len(offsets) == (9 if name == "robot4" else 12)
    _check_bake(rig, truth, out, t, offsets)
    # a curled finger: the fingertip is closer to the palm's palmar side
    tip = out.joint_index(t.fingers["index"][-1])
    tip0 = rig.joint_index(truth.fingers["index"][-1])
    drop = (out.kinematics().bind_world[tip][:3, 3] - rig.kinematics().bind_world[tip0][:3, 3]) @ np.array([0, 0, -1.0])
    assert drop > 0.01


@pytest.mark.parametrize("name,dof,degrees", [("source_human", "thumb1_twist", 25), ("robot4", "thumb1_twist", 40),
                                              ("prosthetic_2dof", "thumb1_abduct", 15)])
def test_rotate_thumb_at_rest(hands, name, dof, degrees):
    rig, truth = hands[name]
    out, t = rotate_thumb_at_rest(rig, truth, degrees)
    _check_bake(rig, truth, out, t, {dof: np.radians(degrees)})
    with pytest.raises(ValueError):
        rotate_thumb_at_rest(rig, truth, 120)  # beyond the limits


def test_curl_on_mirrored_rerolled_hand(hands):
    rig, truth = hands["source_human"]
    mid, mt = mirror(*reroll(*rename(rig, truth, "ids"), 90))
    out, t = curl_at_rest(mid, mt, 30)
    _check_truth(out, t)
    q = _q(rig, 12)
    world = out.kinematics().pose(variant_q(rig, out, t, q)).world
    world0 = rig.kinematics().pose(q).world
    order = [rig.joint_index(t.original[n]) for n in out.joint_names]
    assert np.allclose(world[:, :3, 3], world0[order, :3, 3] @ FLIP, atol=1e-12)
    # the bind surface is the mirrored original curled by 30 degrees
    curled = curl_at_rest(rig, truth, 30)[0]
    assert np.allclose(out.surface.vertices, curled.surface.vertices @ FLIP, atol=ATOL)


# ---- 9. strip DOFs ------------------------------------------------------------------------------
def test_strip_dofs(hands):
    rig, truth = hands["source_human"]
    out, t = strip_dofs(*rename(rig, truth, "unreal"))
    out.validate()
    assert out.dof_names == ["root_tx", "root_ty", "root_tz", "root_rx", "root_ry", "root_rz"]
    assert len(t.stripped_dofs) == rig.n_dofs - 6
    assert t.stripped_dofs[0].name == "hand_r_abduct"
    assert np.allclose(out.kinematics().bind_world, rig.kinematics().bind_world)
    assert np.array_equal(out.surface.vertices, rig.surface.vertices)
    q = _q(rig, 13)
    qs = variant_q(rig, out, t, q)
    assert np.array_equal(qs, q[:6])


# ---- compositions -------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["source_human", "robot4", "alien"])
def test_composition_mixamo_reroll_move_mirror(hands, name):
    rig, truth = hands[name]
    out, t = mirror(*move(*reroll(*rename(rig, truth, "mixamo"), 90), MOVE))
    out.validate()
    _check_truth(out, t)
    # names given before the mirror keep saying "Right": only the geometry tells
    assert t.handedness == "left" and t.palm == "RightHand"
    assert t.steps == ["rename(mixamo)", "reroll(90)", "move", "mirror"]
    m = FLIP @ MOVE[:3, :3]
    assert np.allclose(t.to_variant[:3, :3], m)
    q = _q(rig, 14, root=False)
    expected = posed_vertices(rig, q) @ t.to_variant[:3, :3].T + t.to_variant[:3, 3]
    assert np.allclose(posed_vertices(out, variant_q(rig, out, t, q)), expected, atol=ATOL)
    for joint, original in t.original.items():
        assert np.allclose(t.palmar[joint], m @ truth.palmar[original])
    for f, chain in t.fingers.items():
        assert [t.original[j] for j in chain] == truth.fingers[f]
    assert signed_volume(out.surface.vertices, out.surface.faces) > 0


def test_everything_composes(hands):
    rig, truth = hands["robot4"]
    steps = [
        lambda r, t: insert_metacarpals(r, t),
        lambda r, t: rename(r, t, "rigify"),
        lambda r, t: curl_at_rest(r, t, 25),
        lambda r, t: rotate_thumb_at_rest(r, t, 20),
        lambda r, t: reroll(r, t, 180),
        lambda r, t: mirror(r, t),
        lambda r, t: move(r, t, MOVE),
        lambda r, t: rename(r, t, "ids", seed=3),
    ]
    out, t = rig, truth
    for step in steps:
        out, t = step(out, t)
        out.validate()
        _check_truth(out, t)
    assert len(t.metacarpals) == 3 and t.handedness == "left"
    q = _q(rig, 15, root=False)
    qv = variant_q(rig, out, t, q)
    a, b = t.to_variant[:3, :3], t.to_variant[:3, 3]
    # joints exactly where the original's are (through the world map); the surface within the
    # re-binding error of the two bakes
    world, world0 = out.kinematics().pose(qv).world, rig.kinematics().pose(q).world
    for n, original in t.original.items():
        if n == out.joint_names[0]:
            continue  # the free root stays at the identity (move puts the transform below it)
        assert np.allclose(world[out.joint_index(n)][:3, 3], a @ world0[rig.joint_index(original)][:3, 3] + b, atol=1e-12)
    assert len(t.original) == rig.n_joints
    expected = posed_vertices(rig, q) @ a.T + b
    assert np.abs(posed_vertices(out, qv) - expected).max() < 0.01
    out, t = strip_dofs(out, t)
    assert out.n_dofs == 6 and len(t.stripped_dofs) == 22 - 6 + 3


def test_builders_do_not_modify_their_input(hands):
    rig, truth = hands["source_human"]
    before = [j.rest_local.copy() for j in rig.joints], [d.axis.copy() for d in rig.dofs], rig.surface.vertices.copy()
    palmar = {k: v.copy() for k, v in truth.palmar.items()}
    for fn in (lambda: reroll(rig, truth, 90), lambda: mirror(rig, truth), lambda: move(rig, truth, MOVE),
               lambda: curl_at_rest(rig, truth, 30), lambda: insert_metacarpals(rig, truth),
               lambda: rename(rig, truth, "ids"), lambda: strip_dofs(rig, truth)):
        fn()
    assert all(np.array_equal(a, j.rest_local) for a, j in zip(before[0], rig.joints))
    assert all(np.array_equal(a, d.axis) for a, d in zip(before[1], rig.dofs))
    assert np.array_equal(before[2], rig.surface.vertices)
    assert all(np.array_equal(palmar[k], truth.palmar[k]) for k in palmar) and truth.steps == []
    assert truth_of(rig).fingers == truth.fingers


def test_metacarpals_after_move_and_mirror(hands):
    rig, truth = hands["prosthetic_2dof"]
    base, bt = drop_fingers(rig, truth, ["pinky"])
    moved, mt = mirror(*move(base, bt, MOVE))
    out, t = insert_metacarpals(moved, mt, flex_deg=None)
    _check_truth(out, t)
    assert out.n_dofs == moved.n_dofs and len(t.metacarpals) == 3
    q = _q(base, 16)
    assert np.allclose(posed_vertices(out, variant_q(base, out, t, q)),
                       posed_vertices(moved, variant_q(base, moved, mt, q)), atol=ATOL)
    bind = out.kinematics().bind_world
    for f, m in t.metacarpals.items():
        i = out.joint_index(m)
        assert np.allclose(t.palmar[m], -bind[i][:3, 2])
        # the metacarpal sits on the moved, mirrored palm and its palmar side agrees with its knuckle's
        knuckle = bind[out.joint_index(t.fingers[f][0])][:3, 3]
        assert np.allclose(bind[i][:3, 3], t.palm_origin + 0.2 * (knuckle - t.palm_origin))
        assert np.linalg.norm(t.palm_origin - MOVE[:3, 3] * [-1, 1, 1]) < 1e-12
        assert t.palmar[m] @ t.palmar[t.fingers[f][0]] > 0.9
