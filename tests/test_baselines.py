"""The contact-free baselines: their objectives' gradients and the pipeline running them."""

import dataclasses

import numpy as np
import pytest

from retarget_core.clip.demo import build_demo_timeline, clip_from_timeline, source_rig
from retarget_core.errors import InputError
from retarget_core.execute import Executor
from retarget_core.inputs import RunInputs
from retarget_core.pairing.dense import pair_contacts
from retarget_core.pipeline import retarget
from retarget_core.solve.baselines import KEYVECTOR_ETA1, KeyvectorObjective, keyvector_pairs
from retarget_core.solve.config import RetargetConfig
from retarget_core.solve.problem import Problem, method_objective
from retarget_core.solve.targets import contact_targets, marker_targets
from retarget_core.transfer.clip_transfer import transfer_clip
from retarget_core.transfer.propose import propose_annotations


@pytest.fixture(scope="module")
def setup():
    rig = source_rig()
    obj, timeline = build_demo_timeline("bottle_pick_place", time_scale=0.15, rig=rig)
    clip = clip_from_timeline("bottle_pick_place", obj, timeline, rig, 0.004)
    annotations = propose_annotations(rig, rig)
    pairs = pair_contacts(clip)
    transferred = transfer_clip(pairs, rig, rig, annotations)
    return rig, clip, annotations, pairs, transferred


def _problem(setup, method):
    rig, clip, annotations, pairs, transferred = setup
    cfg = RetargetConfig.preset("default")
    cfg.method = method
    cfg.weights.lambda_t = 0.0
    markers = marker_targets(clip, rig, rig, annotations)
    contacts = contact_targets(clip, pairs, transferred.contacts, keep_source_gap=True)
    return Problem(rig, cfg, markers, contacts, clip.object_poses, clip.table_pose, clip.table_half_extents,
                   clip.object_vertices, clip.object_faces)


def _fd(fun, q, h=1e-6):
    return np.array([(fun(q + h * e) - fun(q - h * e)) / (2 * h) for e in np.eye(len(q))])


@pytest.mark.parametrize("method", ["fingertips", "keyvectors"])
def test_baseline_gradient_and_residual_form(setup, method):
    problem = _problem(setup, method)
    objective = method_objective(problem, "fingers")
    f = int(np.argmax(np.diff(problem.contacts.frame_offsets)))
    objective.set_frame(problem.frame_data(f))
    q = setup[1].dof_values[f] + np.random.default_rng(4).normal(scale=0.1, size=problem.rig.n_dofs)
    value, grad = objective.value_and_grad(q)
    fd = _fd(lambda x: objective.value_and_grad(x, want_grad=False)[0], q)
    assert value > 0 and np.abs(fd).max() > 0
    assert np.abs(grad - fd).max() <= 1e-5 * np.abs(fd).max()
    r, jac = objective.residuals(q)
    assert np.isclose(r @ r, value, rtol=1e-9)
    fd_r = _fd(lambda x: objective.residuals(x)[0], q).T
    assert np.abs(jac - fd_r).max() <= 1e-5 * np.abs(fd_r).max()
    # the Gauss-Newton forms see the baseline's key vectors too
    cost, g, h = objective.normal_equations(q)
    assert np.isclose(cost, r @ r, rtol=1e-12) and np.isclose(objective.residual_cost(q), r @ r, rtol=1e-12)
    assert np.allclose(g, jac.T @ r, rtol=1e-10, atol=1e-10 * np.abs(g).max())
    assert np.allclose(h, jac.T @ jac, rtol=1e-10, atol=1e-10 * np.abs(h).max())


def test_keyvector_sets_and_pinch_projection(setup):
    """Palm -> 5 tips, thumb -> 4 tips, 6 between the 4 other tips; when the source thumb and
    index tips touch, the target's thumb-index vector is aimed at eta_1 with weight 200."""
    pairs, sets = keyvector_pairs(["PalmRoot", "ThumbFingertip", "IndexFingertip", "MiddleFingertip",
                                   "RingFingertip", "PinkyFingertip"])
    assert sets.count(0) == 5 and sets.count(1) == 4 and sets.count(2) == 6
    problem = _problem(setup, "keyvectors")
    objective = method_objective(problem, "fingers")
    assert isinstance(objective, KeyvectorObjective)
    data = problem.frame_data(0)
    markers = data.markers.copy()
    thumb, index = (objective.source_pair[objective.keypoints.index(n)] for n in ("ThumbFingertip", "IndexFingertip"))
    markers[index] = markers[thumb] + [0.005, 0.0, 0.0]  # 5 mm apart: a pinch
    data.markers = markers
    objective.set_frame(data)
    aim, weight = objective._aims()
    k = [i for i, (a, b) in enumerate(zip(objective.vec_a, objective.vec_b))
         if objective.keypoints[a] == "ThumbFingertip" and objective.keypoints[b] == "IndexFingertip"][0]
    assert weight[k] == 200.0
    assert np.isclose(np.linalg.norm(aim[k]), KEYVECTOR_ETA1 * 1000.0)
    palm = [i for i, s in enumerate(objective.vec_set) if s == 0][0]
    assert weight[palm] == 1.0


def test_baseline_without_tip_markers_is_an_input_error(setup):
    rig, clip, annotations, pairs, _ = setup
    reduced = dataclasses.replace(annotations, markers=[m for m in annotations.markers
                                                         if not m.name.endswith("Fingertip")])
    cfg = RetargetConfig.preset("default")
    cfg.method = "keyvectors"
    with pytest.raises(InputError, match="Fingertip"):
        retarget(RunInputs.of(clip, rig, rig, reduced), cfg, pairs=pairs)


def test_baselines_keep_the_root_of_the_root_pass_and_solve_the_fingers(setup):
    rig, clip, annotations, pairs, _ = setup
    cfg = RetargetConfig.preset("default")
    cfg.passes.filter = cfg.passes.refine = cfg.passes.fit = False  # the root and full passes only
    root = np.array([d.joint == 0 for d in rig.dofs])
    runs = {}
    for method, full in (("contacts", False), ("contacts", True), ("fingertips", True), ("keyvectors", True)):
        cfg.method, cfg.passes.full = method, full
        runs[method, full] = retarget(RunInputs.of(clip, rig, rig, annotations), cfg, Executor(workers=1),
                                      pairs=pairs).q
    root_pass = runs["contacts", False]
    for method in ("fingertips", "keyvectors"):
        q = runs[method, True]
        assert np.array_equal(q[:, root], root_pass[:, root])  # the root pass's root, untouched
        assert np.abs(q[:, ~root] - rig.rest_pose[~root]).max() > np.radians(20)  # fingers were solved
    # identity retarget: the contacts pin the fingers better than five tip markers do
    contact = np.diff(pairs.frame_offsets) > 0
    rmse = {m: np.degrees(np.sqrt(np.mean((runs[m, True] - clip.dof_values)[contact][:, ~root] ** 2)))
            for m in ("contacts", "fingertips")}
    assert rmse["contacts"] < rmse["fingertips"], rmse
