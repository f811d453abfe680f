"""DOF couplings (URDF mimic joints, MJCF equalities and tendons) as constraints of the solve:
the affine map, its chain rule against finite differences, the narrowed limits, the import
from both robot formats, and a mimic-coupled LEAP finger retargeted end to end keeping its
ratio in the delivered curves and animation.json."""

import re

import numpy as np
import pytest

from installed_models import installed_or_none
from retarget_core.clip.demo import make_demo_clip, source_rig
from retarget_core.errors import InputError
from retarget_core.execute import Executor
from retarget_core.export import read_animation_json
from retarget_core.inputs import RunInputs
from retarget_core.pipeline import retarget
from retarget_core.export.robot_trajectory import robot_trajectory
from retarget_core.fit.splines import BSplineCurve, coupled_curves
from retarget_core.rig.coupling import Coupling, DofCoupling
from retarget_core.rig.io import resolve_rig
from retarget_core.solve.config import load_config
from retarget_core.transfer.propose import propose

NAMES = ["a", "b", "c", "d"]


def test_followers_are_affine_in_their_leaders_along_a_chain():
    # c follows b, b follows a: c = 2 (0.5 a + 0.1) - 0.3 = a - 0.1
    c = DofCoupling(NAMES, [Coupling("b", "a", 0.5, 0.1), Coupling("c", "b", 2.0, -0.3)])
    assert c.free.tolist() == [True, False, False, True]
    q = c.apply([0.4, 9.0, 9.0, -1.0])
    np.testing.assert_allclose(q, [0.4, 0.3, 0.3, -1.0], atol=1e-15)
    assert c.violation(q) == pytest.approx(0.0, abs=1e-15)
    assert c.violation([0.4, 0.3, 0.5, -1.0]) == pytest.approx(0.2)
    p = c.lift()
    z = np.array([0.4, 0.0, 0.0, -1.0])
    np.testing.assert_allclose(p @ z + c.offset, q, atol=1e-15)


def test_the_pulled_gradient_is_the_gradient_over_the_free_dofs():
    c = DofCoupling(NAMES, [Coupling("b", "a", -0.7, 0.2), Coupling("d", "a", 1.3, 0.0)])
    w = np.array([0.3, -1.1, 0.8, 0.5])

    def f(q):
        return float(np.sin(q) @ w + 0.5 * (q ** 2).sum())

    def grad(q):
        return np.cos(q) * w + q

    z = np.array([0.35, 0.0, -0.4, 0.0])
    analytic = c.pull_gradient(grad(c.apply(z)))
    h = 1e-6
    for i in np.nonzero(c.free)[0]:
        e = np.zeros(4)
        e[i] = h
        fd = (f(c.apply(z + e)) - f(c.apply(z - e))) / (2 * h)
        assert analytic[i] == pytest.approx(fd, rel=1e-7, abs=1e-9)
    assert analytic[~c.free].tolist() == [0.0, 0.0]


def test_a_leader_is_limited_so_that_its_followers_stay_within_theirs():
    c = DofCoupling(NAMES, [Coupling("b", "a", -2.0, 0.5)])
    lo, hi = c.bounds(np.array([-1.0, -1.0, 0, 0]), np.array([1.0, 1.0, 1, 1]))
    # b = -2 a + 0.5 in [-1, 1]  <=>  a in [-0.25, 0.75]
    np.testing.assert_allclose(lo[:2], [-0.25, -1.0])
    np.testing.assert_allclose(hi[:2], [0.75, 1.0])
    with pytest.raises(InputError, match="loop"):
        DofCoupling(NAMES, [Coupling("b", "a", 1, 0), Coupling("a", "b", 1, 0)])
    with pytest.raises(InputError, match="not a DOF"):
        DofCoupling(NAMES, [Coupling("e", "a", 1, 0)])
    with pytest.raises(InputError, match="multiplier"):
        DofCoupling(NAMES, [Coupling("b", "a", 0.0, 0)])


def test_shadow_distal_joints_follow_their_tendon_coupling():
    if installed_or_none("shadow") is None:
        pytest.skip("the Shadow hand's wheel is not installed")
    rig = resolve_rig("installed:shadow@0.005")
    couplings = {c["dof"]: c for c in rig.metadata["couplings"]}
    # the fixed tendon T_FFJ1c holds 0.00705 FFJ0 - 0.00805 FFJ1 within +-0.001
    ff = couplings["robot0:FFJ0"]
    assert ff["leader"] == "robot0:FFJ1"
    assert ff["multiplier"] == pytest.approx(0.00805 / 0.00705)
    assert sorted(couplings) == ["robot0:FFJ0", "robot0:LFJ0", "robot0:MFJ0", "robot0:RFJ0"]
    assert rig.metadata["unhonoured_constraints"] == []
    assert rig.metadata["joint_order"][:3] == ["robot0:WRJ1", "robot0:WRJ0", "robot0:FFJ3"]


# ---- a mimic-coupled URDF finger, end to end -----------------------------------------------------
MIMICS = {"id3": ("id2", 0.9, 0.02), "id7": ("id6", 1.0, 0.0)}
#: LEAP's moving joints in the order its URDF lists them (the file sorts them by name)
URDF_ORDER = ["id0", "id1", "id10", "id11", "id12", "id13", "id14", "id15", "id2", "id3", "id4", "id5", "id6", "id7",
              "id8", "id9"]


@pytest.fixture(scope="module")
def mimic_leap(tmp_path_factory):
    """The installed LEAP URDF with two distal joints made mimics of their middle joints, copied
    with its mesh references made absolute."""
    leap = installed_or_none("leap")
    if leap is None:
        pytest.skip("the LEAP hand's wheel is not installed")
    text = leap.read_text(encoding="utf-8")
    text = re.sub(r'filename="([^"]+)"', lambda m: f'filename="{(leap.parent / m.group(1)).resolve()}"', text)
    for joint, (leader, m, o) in MIMICS.items():
        pattern = rf'(<joint name="{joint}" type="revolute">)'
        assert re.search(pattern, text), joint
        text = re.sub(pattern, rf'\1<mimic joint="{leader}" multiplier="{m}" offset="{o}"/>', text)
    path = tmp_path_factory.mktemp("mimic") / "leap_mimic.urdf"
    path.write_text(text, encoding="utf-8")
    return resolve_rig(str(path), wrapper_resolution=0.005)


def test_urdf_mimic_tags_become_couplings(mimic_leap):
    rig = mimic_leap
    got = {c["dof"]: (c["leader"], c["multiplier"], c["offset"]) for c in rig.metadata["couplings"]}
    assert got == MIMICS
    rest = rig.rest_pose
    assert rest[rig.dof_index("id3")] == pytest.approx(0.9 * rest[rig.dof_index("id2")] + 0.02)
    # the leader's limits keep the follower within its own ([-1.745, 0.314]): 0.9 id2 + 0.02 <= 0.314
    lo, hi = rig.coupling().bounds(rig.lower, rig.upper)
    assert hi[rig.dof_index("id2")] == pytest.approx(min(0.314159, (0.314159 - 0.02) / 0.9))


def test_a_mimic_coupled_finger_keeps_its_ratio_in_the_result(mimic_leap, tmp_path):
    source = source_rig(0.005)
    clip = make_demo_clip("bottle_pick_place", time_scale=0.05, resolution=0.005, rig=source)
    proposal = propose(source, mimic_leap)
    result = retarget(RunInputs.of(clip, source, mimic_leap, proposal.annotations),
                      load_config(None, "default", {}), Executor(workers=1))
    rig = mimic_leap
    dense = np.linspace(result.times[0], result.times[-1], 5 * len(result.times))
    for follower, (leader, m, o) in MIMICS.items():
        i, j = rig.dof_index(follower), rig.dof_index(leader)
        # every solved frame, and the delivered curve at and between the frames
        np.testing.assert_allclose(result.q[:, i], m * result.q[:, j] + o, atol=1e-9)
        np.testing.assert_allclose(result.curves[i](dense), m * result.curves[j](dense) + o, atol=1e-9)
        assert np.ptp(result.q[:, j]) > 0.05, "the leader moved: the ratio was exercised"
    paths = result.write(tmp_path, control_rate_hz=50.0)
    doc = read_animation_json(paths["animation.json"])
    names = doc["dof_names"]
    values = doc["values"]
    for follower, (leader, m, o) in MIMICS.items():
        np.testing.assert_allclose(values[:, names.index(follower)], m * values[:, names.index(leader)] + o, atol=1e-9)
    # the robot's commands: the file's joints in its order, at the control rate, ratios kept
    robot = doc["robot"]
    assert robot["joints"] == URDF_ORDER
    positions = np.array(robot["positions"])
    assert positions.shape == (int(np.floor(result.times[-1] * 50 + 1e-9)) + 1, 16)
    for follower, (leader, m, o) in MIMICS.items():
        a, b = URDF_ORDER.index(follower), URDF_ORDER.index(leader)
        np.testing.assert_allclose(positions[:, a], m * positions[:, b] + o, atol=1e-9)
    assert {c["dof"] for c in robot["couplings"]} == set(MIMICS)
    # the coupled hand still reaches its contacts (uncoupled LEAP: 12.3 mm on these solved frames;
    # the 0.38 s clip's 4-control-point curve is far off for every hand, see test_foreign_retarget)
    assert result.summary["solved_contact_distance_median_mm"] < 15.0, result.summary


MJCF = """<mujoco>
  <compiler angle="radian"/>
  <worldbody>
    <body name="palm">
      <geom type="box" size="0.04 0.01 0.04"/>
      <body name="f1" pos="0 0 0.04">
        <joint name="j1" type="hinge" axis="1 0 0" range="-1 1" ref="0.1"/>
        <geom type="capsule" fromto="0 0 0 0 0 0.03" size="0.008"/>
        <body name="f2" pos="0 0 0.035">
          <joint name="j2" type="hinge" axis="1 0 0" range="-1 1"/>
          <geom type="capsule" fromto="0 0 0 0 0 0.025" size="0.007"/>
          <body name="f3" pos="0 0 0.03">
            <joint name="j3" type="hinge" axis="1 0 0" range="-1 1"/>
            <geom type="capsule" fromto="0 0 0 0 0 0.02" size="0.006"/>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
  <equality>
    <joint name="linear" joint1="j2" joint2="j1" polycoef="0.05 0.5 0 0 0"/>
    <joint name="curved" joint1="j3" joint2="j2" polycoef="0 0.5 0.2 0 0"/>
  </equality>
</mujoco>
"""


def test_mjcf_joint_equalities_are_couplings_at_the_models_reference(tmp_path):
    path = tmp_path / "finger.xml"
    path.write_text(MJCF, encoding="utf-8")
    rig = resolve_rig(str(path), wrapper_resolution=0.004)
    # MuJoCo: j2 - 0 = 0.05 + 0.5 (j1 - ref 0.1), so j2 = 0.5 j1 + 0.0
    (c,) = rig.metadata["couplings"]
    assert (c["dof"], c["leader"]) == ("j2", "j1")
    assert c["multiplier"] == pytest.approx(0.5) and c["offset"] == pytest.approx(0.0, abs=1e-12)
    # the quadratic one cannot be a linear coupling: it is reported, not silently dropped
    (u,) = rig.metadata["unhonoured_constraints"]
    assert "curved" in u["constraint"] and "polynomial" in u["why"]
    q = rig.coupling().apply(np.r_[np.zeros(6), 0.6, 0.0, 0.3])
    assert q[rig.dof_index("j2")] == pytest.approx(0.3)


def test_robot_commands_at_a_control_rate_with_velocity_limits_reported(mimic_leap):
    rig = mimic_leap
    d = rig.n_dofs
    curves = []
    ramp = rig.dof_index("id2")
    rest = rig.rest_pose
    for i in range(d):
        # id2 ramps at -2 rad/s over 0.5 s (LEAP's file allows 1 rad/s); the rest hold still,
        # the root turns a quarter turn about z
        c0, c1 = rest[i], rest[i]
        if i == ramp:
            c0, c1 = 0.2, -0.8
        if rig.dof_names[i] == "root_rz":
            c0, c1 = 0.0, np.pi / 2
        curves.append(BSplineCurve(np.array([0, 0, 0.5, 0.5]), np.array([c0, c1]), degree=1))
    curves = coupled_curves(curves, rig.coupling())
    robot = robot_trajectory(rig, curves, 0.5, 40.0, frame_times=np.linspace(0, 0.5, 7))
    times = np.array(robot["times"])
    np.testing.assert_allclose(times, np.arange(21) / 40.0, atol=1e-15)
    positions = np.array(robot["positions"])
    k = URDF_ORDER.index("id2")
    np.testing.assert_allclose(positions[:, k], 0.2 - 2.0 * times, atol=1e-12)
    np.testing.assert_allclose(positions[:, URDF_ORDER.index("id3")], 0.9 * (0.2 - 2.0 * times) + 0.02, atol=1e-12)
    v = robot["velocity"]
    assert v["id2"]["limit"] == 1.0 and v["id2"]["max"] == pytest.approx(2.0)
    assert v["id3"]["max"] == pytest.approx(1.8)
    assert set(robot["velocity_exceeded"]) == {"id2", "id3"} and v["id0"]["exceeded_at"] == []
    # the base turns a quarter turn about z: quaternion (cos, 0, 0, sin) of half the angle, unit
    quat = np.array(robot["base"]["quaternion_wxyz"])
    half = np.pi / 4 * times / 0.5
    np.testing.assert_allclose(np.abs(quat[:, 0]), np.cos(half), atol=1e-9)
    np.testing.assert_allclose(np.abs(quat[:, 3]), np.sin(half), atol=1e-9)
    assert np.all(np.sum(quat[1:] * quat[:-1], axis=1) > 0)  # no sign flips between samples
    with pytest.raises(InputError, match="control rate"):
        robot_trajectory(rig, curves, 0.5, 0.0)
