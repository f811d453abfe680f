"""The per-frame problem of the passes (paper Eq. "optframe"), as plain data a worker can
receive, and the functions that solve frames of it.

:class:`Problem` holds the target rig, the run configuration and the per-frame targets
(markers, contacts, object, table). :func:`build_solver_state` turns it into the stateful solver
objects of one worker (nlopt and potpourri3d objects do not pickle, so every worker builds its
own); :func:`solve_frames` and :func:`solve_root_sequence` solve frames with them. Which
objective a method solves, and which DOFs it moves, is decided in one place:
:func:`method_objective` and :func:`active_dofs`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from threadpoolctl import threadpool_limits

from ..mesh.surface_points import SurfacePoints
from ..refine.branches import JUMP_MIN_SHIFT
from ..rig.model import Rig
from .baselines import FingertipObjective, KeyvectorObjective, keyvector_beta
from .collision import CollisionGrids
from .config import RetargetConfig
from .frame_solver import solve_frame
from .objective import FrameData, FrameObjective
from .targets import ContactTargets, MarkerTargets

#: Settings each contact-free baseline does not use in its finger passes (the root pass, which
#: every method shares, still uses them), with the reason; recorded in result.json.
_UNUSED_BY_METHOD = {
    "contacts": {},
    "fingertips": {
        "weights.lambda_c": "the fingertips baseline tracks fingertip markers only (lambda_c = 0 in its finger passes)",
        "weights.lambda_cd": "no contact term in the fingertips baseline's finger passes",
        "weights.lambda_cn": "no contact term in the fingertips baseline's finger passes",
    },
    "keyvectors": {
        "weights.lambda_m": "the keyvectors baseline matches keyvectors, not markers, in its finger passes",
        "weights.lambda_c": "no contact term in the keyvectors baseline's finger passes",
        "weights.lambda_cd": "no contact term in the keyvectors baseline's finger passes",
        "weights.lambda_cn": "no contact term in the keyvectors baseline's finger passes",
        "markers.distance": "the keyvectors baseline has no marker term in its finger passes",
        "markers.huber_width": "the keyvectors baseline has no marker term in its finger passes",
    },
}


def unused_settings(config: RetargetConfig) -> dict[str, dict]:
    """{dotted key: {"value": v, "why": text}} of the settings ``config.method`` does not use in
    its finger passes (empty for the paper's method)."""
    out = {}
    for key, why in _UNUSED_BY_METHOD[config.method].items():
        section, name = key.split(".")
        out[key] = {"value": getattr(getattr(config, section), name), "why": why}
    return out


@dataclass
class Problem:
    """Everything a worker needs to solve any frame of a run, as plain data. Arrays: the
    object's poses (T, 4, 4), vertices (Vo, 3) m and faces (Fo, 3); the table's pose (4, 4) and
    half extents (3,) m, or None; ``collision``: the collision terms' grids, built once
    (:func:`~retarget_core.solve.collision.collision_grids`; None: each objective builds its own)."""

    rig: Rig
    config: RetargetConfig
    markers: MarkerTargets
    contacts: ContactTargets
    object_poses: np.ndarray
    table_pose: np.ndarray | None
    table_half_extents: np.ndarray | None
    object_vertices: np.ndarray
    object_faces: np.ndarray
    collision: CollisionGrids | None = None

    def frame_data(self, f: int) -> FrameData:
        points, obj_p, obj_n = self.contacts.frame(f)
        return FrameData(self.markers.source_positions[f], points, obj_p, obj_n, self.object_poses[f])


#: The root pass samples the hand this many times more sparsely for the penetration term.
ROOT_PENETRATION_STRIDE = 4


def method_objective(problem: Problem, stage: str) -> FrameObjective:
    """The objective of ``stage`` ("root" or "fingers") for ``problem.config.method``. The root
    pass always solves the paper's objective; the finger passes (full pass, filter re-solves,
    refinement) solve the method's. The one place the method is switched on."""
    m, cfg = problem.markers, problem.config
    common = dict(table_pose=problem.table_pose, table_half_extents=problem.table_half_extents,
                  object_vertices=problem.object_vertices, object_faces=problem.object_faces,
                  collision=problem.collision)
    if stage == "root":
        # the root moves the hand as a whole: its self collision cannot change, and a quarter of
        # the penetration samples keep a rigid hand out of the object
        return FrameObjective(problem.rig, cfg, m.target_faces, m.target_barycentric, m.pair_target,
                              m.pair_weight, self_collision=False,
                              penetration_stride=ROOT_PENETRATION_STRIDE * cfg.sampling.penetration_sample_stride,
                              **common)
    if cfg.method == "contacts":
        return FrameObjective(problem.rig, cfg, m.target_faces, m.target_barycentric, m.pair_target,
                              m.pair_weight, **common)
    if cfg.method == "fingertips":
        return FingertipObjective(problem.rig, cfg, m.target_faces, m.target_barycentric, m.pair_target,
                                  m.pair_weight, m.names, **common)
    if cfg.method == "keyvectors":
        kin = problem.rig.kinematics()
        rest_markers = kin.points(problem.rig.rest_pose,
                                  kin.bind(SurfacePoints(m.target_faces, m.target_barycentric)))
        beta = keyvector_beta(rest_markers, m.pair_target, m.names, m.source_positions)
        return KeyvectorObjective(problem.rig, cfg, m.target_faces, m.target_barycentric, m.pair_target,
                                  m.pair_weight, m.names, beta=beta, **common)
    raise ValueError(f"unknown method {cfg.method!r}")  # validated in RetargetConfig


def active_dofs(rig: Rig, method: str, stage: str) -> np.ndarray:
    """Bool (D,): the DOFs ``stage`` solves. The root pass moves the root only; the paper's
    method then moves every DOF, a baseline only the fingers (it keeps the root of the root
    pass: the paper's "ground truth root")."""
    root = np.array([d.joint == 0 for d in rig.dofs])
    if stage == "root":
        return root
    return ~root if method != "contacts" else np.ones(rig.n_dofs, dtype=bool)


def build_solver_state(problem: Problem, blas_threads: int = 1) -> dict:
    """The solver objects of one worker: {"problem", "root" objective, "fingers" objective}.
    Pins BLAS / OpenMP to ``blas_threads`` in this process: the solver's matrices are small
    (54 x a few thousand at most) and a second thread per worker only fights the other workers
    for the cores (measured: whole bench 44 s with one thread per worker, 80 s with two)."""
    threadpool_limits(limits=blas_threads)
    # two objectives even for the paper's method: the root pass leaves out self collision and
    # samples the penetration term more sparsely
    return {"problem": problem, "root": method_objective(problem, "root"), "fingers": method_objective(problem, "fingers")}


def solve_root_sequence(state: dict, frames, seed) -> list:
    """Root-only solves of consecutive ``frames``, each seeded from the previous solution (the
    paper's root pass; a failed frame keeps its seed and passes it on). Returns
    [(frame, q (D,), evaluations, error)]."""
    out = []
    for f in frames:
        (_, q, evals, error), = solve_frames(state, [f], [seed], "root")
        if not error:
            seed = q
        out.append((int(f), seed, evals, error))
    return out


def solve_frames(state: dict, frames, seeds, stage: str, keyed: bool = False) -> list:
    """Solve ``frames`` independently from ``seeds`` (F, D) with ``state``'s objective of
    ``stage`` ("root" or "fingers"). ``keyed``: the prior pulls toward the seed (the paper's
    "previously existing keyed value at frame f": the filtered or interpolated value in the
    later passes) instead of the rest pose, so a re-solve stays near the smooth key where the
    data allow it rather than returning to the same spike. Returns
    [(frame, q (D,), evaluations, error)]; a numerically failed frame has a non-empty error and
    keeps its seed."""
    problem: Problem = state["problem"]
    objective: FrameObjective = state[stage]
    cfg = problem.config.solver
    rig = problem.rig
    lower, upper = rig.lower, rig.upper
    active = active_dofs(rig, problem.config.method, stage)
    root_only = stage == "root"
    settings = dict(maxeval=cfg.root_maxeval if root_only else cfg.maxeval, xtol_rel=cfg.xtol_rel,
                    ftol_rel=cfg.ftol_rel, gradient=cfg.gradient, fd_step=cfg.fd_step,
                    kinds=[d.kind for d in rig.dofs], root_mask=[d.joint == 0 for d in rig.dofs],
                    algorithm=cfg.algorithm, coupling=rig.coupling())
    rest = rig.rest_pose
    out = []
    for f, seed in zip(frames, seeds):
        objective.set_frame(problem.frame_data(int(f)))
        objective.reference = np.asarray(seed, dtype=np.float64) if keyed else rest
        warm = 0 if root_only else cfg.warm_start_iterations
        # the warm start runs without the hand-object term and solve_frame refocuses it after
        objective.focus_samples(seed, hand_object=warm == 0)
        # the root pass starts from the previous frame's root: MMA alone is enough there
        sol = solve_frame(objective, seed, lower, upper, active, warm_start_iterations=warm, **settings)
        evaluations = sol.evaluations
        if sol.ok and objective.unseen_collision(sol.q):
            # a point that was far from the table, object or another part at the seed ended inside: polish with it
            objective.focus_samples(sol.q)
            polished = solve_frame(objective, sol.q, lower, upper, active, **settings)
            evaluations += polished.evaluations
            if polished.ok:
                sol = polished
        out.append((int(f), sol.q, evaluations, sol.error))
    return out


def frame_value(state: dict, frame: int, q: np.ndarray, stage: str = "fingers") -> float:
    """The objective of ``stage`` at pose ``q`` (D,) of ``frame``, with the prior toward the
    rest pose as in the full pass and the root gauge anchored at ``q`` itself (zero there), so
    values from different seeds compare and nothing a worker solved before leaks in."""
    objective = _frame_at(state, frame, q, stage)
    return float(objective.whole_value(np.asarray(q, dtype=np.float64)))


def _frame_at(state: dict, frame: int, q: np.ndarray, stage: str = "fingers") -> FrameObjective:
    """``stage``'s objective set to ``frame``, the prior toward the rest pose, the root gauge
    anchored at q (see :func:`frame_value`)."""
    problem: Problem = state["problem"]
    objective: FrameObjective = state[stage]
    objective.set_frame(problem.frame_data(int(frame)))
    objective.reference = problem.rig.rest_pose
    objective.set_seed(np.asarray(q, dtype=np.float64))
    return objective


def trace_branch(state: dict, frames, seed, current, gap: float = JUMP_MIN_SHIFT) -> list:
    """Carry a branch along the run ``frames`` (in order): each frame re-solved seeded from the
    solution before it (the first from ``seed`` (D,)). The run ends where it rejoins the
    frame's ``current`` solution (F, D) (every marker point within ``gap`` metres of it: the
    same branch from there on) or a solve fails. Returns [(frame, q, value, current value,
    evaluations, error)] for the frames visited (values: :func:`frame_value`)."""
    problem: Problem = state["problem"]
    kin = problem.rig.kinematics()
    m = problem.markers
    binding = kin.bind(SurfacePoints(m.target_faces, m.target_barycentric))
    out = []
    for f, mine in zip(frames, current):
        mine = np.asarray(mine, dtype=np.float64)
        (_, q, evals, error), = solve_frames(state, [f], [seed], "fingers")
        value = np.inf if error else frame_value(state, f, q)
        out.append((int(f), q, value, frame_value(state, f, mine), evals, error))
        if error or np.linalg.norm(kin.points(q, binding) - kin.points(mine, binding), axis=1).max() <= gap:
            break
        seed = q
    return out


def frame_systems(state: dict, frames, qs) -> list:
    """At pose ``qs[i]`` (F, D) of each frame: (frame, then the Gauss-Newton system of its
    least-squares form: sum r^2, J^T r (D,), J^T J (D, D)), with the prior toward the rest
    pose as in the full pass, and the table's hinge in the system too (nothing settles it
    after the polish). What the polish of the delivered curves (fit/polish.py) sums over
    frames; the objective's value there is :func:`frame_values`' (the polish already has it
    from the step it kept)."""
    out = []
    for f, q in zip(frames, qs):
        q = np.asarray(q, dtype=np.float64)
        objective = _frame_at(state, f, q)
        objective.focus_samples(q)  # the collision and table rows are those of the focused sets
        cost, g, h = objective.normal_equations(q, table=True)
        out.append((int(f), cost, g, h))
    return out


def frame_values(state: dict, frames, qs) -> list:
    """[(frame, full objective value at qs[i])] (see :func:`frame_value`)."""
    return [(int(f), frame_value(state, int(f), q)) for f, q in zip(frames, qs)]
