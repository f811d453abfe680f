"""Forward kinematics, skinning and analytic Jacobians against known answers and central
differences."""

import numpy as np
import pytest

from retarget_core.errors import InputError
from retarget_core.mesh import SurfacePoints
from retarget_core.rig import Dof, Joint, Rig, SkinnedMesh
from retarget_core.rig.demo_hands import DEMO_HANDS


def _random_points(rig, rng, n=120):
    faces = rng.integers(0, len(rig.surface.faces), n)
    return SurfacePoints(faces, rng.dirichlet([1.0, 1.0, 1.0], n))


def _central_differences(fn, q, h=1e-6):
    cols = []
    for d in range(len(q)):
        e = np.zeros_like(q)
        e[d] = h
        cols.append((fn(q + e) - fn(q - e)) / (2 * h))
    return np.stack(cols, axis=-1)


def _relative_error(analytic, numeric):
    return np.abs(analytic - numeric).max() / max(np.abs(numeric).max(), 1e-12)


@pytest.mark.parametrize("name", list(DEMO_HANDS))
def test_point_and_normal_jacobians_match_central_differences(demo_rigs, rng, name):
    rig = demo_rigs[name]
    kin = rig.kinematics()
    binding = kin.bind(_random_points(rig, rng))
    for _ in range(3):
        q = rig.random_pose(rng)
        x, jac = kin.points_jacobian(q, binding)
        n, jac_n = kin.normals_jacobian(q, binding)
        assert jac.shape == (binding.n_points, 3, rig.n_dofs)
        np.testing.assert_allclose(x, kin.points(q, binding), atol=1e-12)
        np.testing.assert_allclose(n, kin.normals(q, binding), atol=1e-12)
        assert _relative_error(jac, _central_differences(lambda v: kin.points(v, binding), q)) < 1e-5
        assert _relative_error(jac_n, _central_differences(lambda v: kin.normals(v, binding), q)) < 1e-5


def test_vector_jacobian_product_equals_transposed_jacobian(demo_rigs, rng):
    rig = demo_rigs["source_human"]
    kin = rig.kinematics()
    binding = kin.bind(_random_points(rig, rng, 300))
    q = rig.random_pose(rng)
    cotangent = rng.normal(size=(300, 3))
    _, jac = kin.points_jacobian(q, binding)
    np.testing.assert_allclose(kin.points_vjp(q, binding, cotangent), np.einsum("pa,pad->d", cotangent, jac), rtol=1e-10, atol=1e-12)


def test_normal_vector_jacobian_product_equals_transposed_jacobian(demo_rigs, rng):
    rig = demo_rigs["alien"]
    kin = rig.kinematics()
    binding = kin.bind(_random_points(rig, rng, 200))
    q = rig.random_pose(rng)
    cotangent = rng.normal(size=(200, 3))
    n, jac = kin.normals_jacobian(q, binding)
    n2, grad = kin.normals_vjp(q, binding, cotangent)
    np.testing.assert_allclose(n2, n, atol=1e-12)
    np.testing.assert_allclose(grad, np.einsum("pa,pad->d", cotangent, jac), rtol=1e-9, atol=1e-12)


def _two_link_rig():
    """A root that translates and spins about Z, and an elbow 1 m along X that bends about Z.
    A unit square of two triangles sits on the second link, rigidly skinned."""
    verts = np.array([[1.5, 0.0, 0.0], [2.0, 0.0, 0.0], [2.0, 0.5, 0.0], [1.5, 0.5, 0.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    elbow = np.eye(4)
    elbow[0, 3] = 1.0
    joints = [Joint("root", -1, np.eye(4)), Joint("elbow", 0, elbow)]
    dofs = [
        Dof("root_tx", 0, "translate", np.array([1.0, 0, 0]), -5, 5, 0.0),
        Dof("root_rz", 0, "rotate", np.array([0, 0, 1.0]), -4, 4, 0.0),
        Dof("elbow_rz", 1, "rotate", np.array([0, 0, 1.0]), -4, 4, 0.0),
    ]
    mesh = SkinnedMesh(verts, faces, np.ones((4, 1), dtype=int), np.ones((4, 1)))
    return Rig("two_link", joints, dofs, mesh)


def test_known_answers_on_a_two_link_chain():
    rig = _two_link_rig()
    rig.validate(require_closed=False)
    kin = rig.kinematics()
    # Elbow bent 90 degrees: the vertex 1 m past the elbow goes to (1, 1, 0).
    posed = kin.skin(np.array([0.0, 0.0, np.pi / 2]))
    np.testing.assert_allclose(posed[1], [1.0, 1.0, 0.0], atol=1e-12)
    # Root turned 90 degrees and moved 0.25 m along X (translation applies before the turn).
    posed = kin.skin(np.array([0.25, np.pi / 2, 0.0]))
    np.testing.assert_allclose(posed[1], [0.25, 2.0, 0.0], atol=1e-12)
    # d p / d elbow at rest for p = (2, 0, 0): z x (p - elbow) = (0, 1, 0); d p / d tx = (1, 0, 0).
    binding = kin.bind(SurfacePoints.from_vertices([1], rig.surface.faces))
    _, jac = kin.points_jacobian(np.zeros(3), binding)
    np.testing.assert_allclose(jac[0], [[1, 0, 0], [0, 2, 1], [0, 0, 0]], atol=1e-12)


def test_rest_pose_reproduces_bind_vertices_and_root_moves_rigidly(demo_rigs, rng):
    rig = demo_rigs["alien"]
    kin = rig.kinematics()
    np.testing.assert_allclose(kin.skin(rig.rest_pose), rig.surface.vertices, atol=1e-12)
    q = rig.rest_pose.copy()
    root = [i for i, d in enumerate(rig.dofs) if d.joint == 0]
    q[root] = rng.uniform(-1, 1, len(root))
    posed = kin.skin(q)
    i, j = rng.integers(0, len(posed), (2, 50))
    np.testing.assert_allclose(
        np.linalg.norm(posed[i] - posed[j], axis=1),
        np.linalg.norm(rig.surface.vertices[i] - rig.surface.vertices[j], axis=1),
        atol=1e-12,
    )


def test_surface_point_at_a_vertex_follows_that_vertex(demo_rigs, rng):
    rig = demo_rigs["witch"]
    kin = rig.kinematics()
    ids = rng.integers(0, rig.surface.n_vertices, 40)
    binding = kin.bind(SurfacePoints.from_vertices(ids, rig.surface.faces))
    q = rig.random_pose(rng)
    np.testing.assert_allclose(kin.points(q, binding), kin.skin(q)[ids], atol=1e-12)


def test_pose_of_wrong_shape_is_rejected(demo_rigs):
    kin = demo_rigs["robot4"].kinematics()
    with pytest.raises(InputError, match="shape"):
        kin.pose(np.zeros(5))


def test_the_compiled_pose_is_the_chain_of_joint_transforms(tmp_path):
    """Kinematics.pose (compiled, rig/forward_kernel.py) against the joint-by-joint NumPy chain
    the bind pose is computed with, at the rest pose and at random poses within the limits, on
    a human hand and a robot hand: world transforms within 1e-12 m. Reading a rig needs only the
    NumPy chain: loading one (what the service's upload validation does under its memory limit)
    does not import numba."""
    import subprocess
    import sys

    from retarget_core.rig.demo_hands import demo_hand
    from retarget_core.rig.io import save_rig

    rng = np.random.default_rng(11)
    for name in ("human_alt", "robot4"):
        rig = demo_hand(name, 0.006)
        kin = rig.kinematics()
        np.testing.assert_allclose(kin.pose(rig.rest_pose).world, kin.bind_world, rtol=0, atol=1e-12)
        for _ in range(5):
            q = rig.lower + (rig.upper - rig.lower) * rng.uniform(size=rig.n_dofs)
            np.testing.assert_allclose(kin.pose(q).world, kin._bind_world(q), rtol=0, atol=1e-12)
    save_rig(demo_hand("robot4", 0.006), tmp_path / "r.usda")
    code = ("import sys; from retarget_core.rig.io import load_rig; r = load_rig(sys.argv[1]); "
            "r.kinematics(); print('numba' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path / "r.usda")], capture_output=True, text=True,
                         timeout=300, check=True).stdout.split()
    assert out[-1] == "False"
