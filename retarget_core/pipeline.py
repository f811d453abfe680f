"""The retargeting pipeline of the paper, top to bottom (sections "Dense Contact Pairing",
"Hand Shape Matching", "Motion Retargeting" and the appendix "Motion Retargeting Details"):

    pairing -> transfer -> targets -> root pass -> full pass -> coherence -> filter -> refinement -> fit
    -> curve polish -> figures

:func:`retarget` is the one entry for one run: the command line, the demo, the grid, compare,
the benchmark and the service's job process all call it. What it computes depends on the
:class:`~retarget_core.inputs.RunInputs` and the :class:`~retarget_core.solve.config.RetargetConfig`
alone; the :class:`~retarget_core.execute.Executor` only says where the frame solves run, where
atlases are cached and who hears progress, so any worker count, locally or on Dask, gives the
same DOF values.
"""

from __future__ import annotations

import copy
import logging
import subprocess
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from . import __version__
from .clip.format import Clip
from .errors import InputError
from .evaluate.metrics import contact_distance_per_frame, marker_error_per_frame
from .execute import Executor, FrameRunner
from .fit.polish import polish_curves
from .fit.splines import coupled_curves, evaluate_curves, fit_trajectory
from .inputs import RunInputs, frame_range
from .kernels import kernel_provenance
from .mesh.geometry import rigid_fit
from .mesh.surface_points import SurfacePoints
from .pairing.dense import ContactPairs, pair_contacts
from .refine.branches import branch_jumps, branch_runs, choose_branch_path
from .refine.trajectory import lowpass_and_remove_peaks, refine_trajectory
from .result import RetargetResult
from .rig.anatomy import continuous_root_angles, set_root_transform
from .rig.hand_cut import surface_matches_hand
from .rig.model import Rig
from .solve.collision import collision_grids
from .solve.config import MIN_CONTROL_POINTS, RetargetConfig
from .solve.problem import Problem, method_objective, unused_settings
from .solve.targets import contact_targets, marker_targets, proportion_weights, scale_finger_markers
from .transfer.annotations import DEFAULT_MAX_DISPLACEMENT, remap_to_meshes
from .transfer.clip_transfer import transfer_clip

logger = logging.getLogger(__name__)

#: The root-only pass is seeded sequentially within runs of this many frames (half a second at
#: 120 fps), each run started from a rigid fit of the markers at its first frame; the runs are
#: solved in parallel. Cut by the data, never by the worker count, so the result does not depend
#: on the executor. 60 is also where two workers cut the 120-frame demo and grid windows before
#: the cut stopped depending on them, so the figures measured then still hold (a 64-frame cut
#: moved a baseline grid cell by 1.7 mm: the fingertip baselines keep the root pass's root).
ROOT_SEGMENT_FRAMES = 60


def retarget(inputs: RunInputs, config: RetargetConfig, executor: Executor | None = None, *,
             pairs: ContactPairs | None = None) -> RetargetResult:
    """Retarget ``inputs.clip`` (its ``inputs.frames`` range) onto ``inputs.target_rig``.
    ``pairs``: the contact pairs of that same range when already computed (a cache: they are
    what :func:`pair_contacts` would give)."""
    executor = executor or Executor()
    start = time.perf_counter()
    first, last = frame_range(inputs.frames, inputs.clip.n_frames)
    clip = inputs.clip if (first, last) == (0, inputs.clip.n_frames) else inputs.clip.slice(first, last)
    source, target = inputs.source_rig, inputs.target_rig
    n_control, annotations, remap = _check_inputs(clip, source, target, inputs.annotations, config,
                                                  inputs.annotation_max_displacement)
    if pairs is not None and len(pairs.frame_offsets) != clip.n_frames + 1:
        raise InputError(f"the given contact pairs have {len(pairs.frame_offsets) - 1} frames, the clip "
                         f"{clip.n_frames}", element="pairs")
    config, source_depth = collision_for_source_depth(clip, config)
    timings = {"validation": time.perf_counter() - start}
    client = executor.connect()  # an unreachable scheduler is reported before any work
    # one BLAS / OpenMP thread here and in the workers forked from here (see build_solver_state)
    limits = threadpool_limits(limits=executor.blas_threads)
    try:
        # 1. dense contact pairing: object contacts ray-cast onto the source hand
        t0 = time.perf_counter()
        if pairs is None:
            executor.report("pairing", 0, 1)
            pairs = pair_contacts(clip)
        timings["pairing"] = time.perf_counter() - t0

        # 2. contact transfer through the atlas of log-map charts; 3. per-frame targets
        t0 = time.perf_counter()
        executor.report("transfer", 0, 1)
        problem, transferred = build_problem(clip, pairs, source, target, annotations, config, executor)
        markers, contacts = problem.markers, problem.contacts
        timings["transfer"] = time.perf_counter() - t0

        reports = {}
        with executor.frame_runner(problem, client) as runner:
            client = None  # the runner owns it now
            # 4. root-only pass, seeded frame to frame
            q, reports["root"] = root_pass(runner, problem, clip, config)
            timings["root pass"] = reports["root"].seconds
            # 5. full-pose pass: independent frames seeded from the root estimate
            if config.passes.full:
                q, reports["full"] = solve_pass(runner, np.arange(clip.n_frames), q, "full pass")
                timings["full pass"] = reports["full"].seconds
            # 5b. coherence: frames that left their neighbours' branch, re-solved from it
            # (the contacts method only: a baseline keeps the root pass's root, see solve/baselines.py)
            coherent = config.passes.full and config.passes.coherence and clip.n_frames >= 2 and config.method == "contacts"
            if coherent:
                q, reports["coherence"] = coherence_pass(runner, problem, q)
                timings["coherence"] = reports["coherence"].seconds
            # the root's Euler angles continuous from frame to frame before anything filters them
            q = continuous_root_angles(target, q)
            # 6. low-pass and peak removal, re-solving the frames the filter moved
            if config.passes.filter and clip.n_frames >= 8:
                t0 = time.perf_counter()
                before = q
                q, report = filter_pass(runner, q, target, clip.fps, config)
                if report is not None:
                    reports["filter"] = report
                    if coherent:  # a re-solve from a filtered key can land on the other branch
                        q, report.held = hold_branches(problem, before, q)
                timings["filter"] = time.perf_counter() - t0
            # 7. acceleration refinement
            unresolved = np.zeros(q.shape, dtype=bool)
            if config.passes.refine and clip.n_frames >= 3:
                t0 = time.perf_counter()
                before = q
                q, reports["refine"] = refinement(runner, q, target, clip.fps, config)
                unresolved = reports["refine"].unresolved
                if coherent:
                    q, held = hold_branches(problem, before, q)
                    reports["refine"].held = held
                    unresolved[held] = False  # back to the solution the check passed before
                timings["refinement"] = time.perf_counter() - t0
            # 8. one cubic B-spline per DOF, polished on the frames' objective; coupled DOFs
            # (mimic joints) follow their leaders exactly, as every solve kept them
            coupling = target.coupling()
            q = coupling.apply(continuous_root_angles(target, q))  # the filter's frames that were not re-solved
            times = np.arange(clip.n_frames) / clip.fps
            curves, fit_report = None, None
            if config.passes.fit:
                executor.report("spline fit", 0, 1)
                t0 = time.perf_counter()
                usable = int((~unresolved).sum(axis=0).min())
                n_control = max(MIN_CONTROL_POINTS, min(n_control, usable))
                fit_report = {}
                curves = fit_trajectory(times, q, n_control, mask=~unresolved, optimize_knots=config.fit.optimize_knots,
                                        limits=coupling.bounds(target.lower, target.upper)
                                        if config.fit.respect_limits else None, report=fit_report)
                curves = coupled_curves(curves, coupling)  # a follower's curve is its leader's, mapped
                timings["fit"] = time.perf_counter() - t0
                executor.report("spline fit", 1, 1)
                if config.fit.polish_iterations > 0 and config.method == "contacts":
                    curves, polish = polish_curves(runner, curves, times, target.lower, target.upper,
                                                   iterations=config.fit.polish_iterations,
                                                   tolerance=config.fit.polish_tolerance,
                                                   patience=config.fit.polish_patience, coupling=coupling,
                                                   solved=q, within=config.fit.polish_within)
                    fit_report["polish"] = polish.to_dict()
                    timings["curve polish"] = polish.seconds
    finally:
        limits.restore_original_limits()
        if client is not None:
            client.close()

    # 9. figures at what the user gets: the curves at the frame times (the solved frames' kept,
    # labelled as such: a fit that cuts across a jump shows as the difference)
    t0 = time.perf_counter()
    kin = target.kinematics()
    delivered = evaluate_curves(curves, times) if curves else q
    distance, count = contact_distance_per_frame(kin, delivered, contacts)
    marker = marker_error_per_frame(kin, delivered, markers)
    if curves:
        solved_distance, _ = contact_distance_per_frame(kin, q, contacts)
        solved_marker = marker_error_per_frame(kin, q, markers)
    else:
        solved_distance, solved_marker = distance, marker
    timings["figures"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - start
    counts = run_counts(reports)
    counts["fit"] = fit_report
    if markers.proportion:
        counts["marker_weights"] = markers.proportion
    contact_frames = count > 0
    summary = {
        "frames": clip.n_frames, "dofs": target.n_dofs, "control_points": n_control if curves else None,
        "contact_frames": int(contact_frames.sum()),
        "figures_at": "delivered curves" if curves else "solved frames (no spline fit)",
        "contact_distance_median_mm": _median(distance[contact_frames]),
        "marker_error_median_mm": _median(marker),
        "solved_contact_distance_median_mm": _median(solved_distance[contact_frames]),
        "solved_marker_error_median_mm": _median(solved_marker),
        "failed_frames": len(counts["failed_frames"]), "unresolved_entries": int(unresolved.sum()),
        "fit_failures": len(fit_report["failures"]) if fit_report else 0,
        "transferred_share": (float(1 - transferred.contacts.dropped.mean())
                              if len(transferred.contacts.dropped) else 1.0),
        "unmapped_contacts": int(transferred.contacts.unmapped.sum()) if transferred.contacts.unmapped is not None else 0,
        "seconds": timings["total"],
        # the clip's own hand inside its object (contacts.source_depth_limit): None when not measured
        "source_depth_max_mm": None if source_depth is None else source_depth["max_mm"],
        "penetration_term": ("on" if config.weights.lambda_p > 0 else "off") if source_depth is None
        else source_depth["penetration_term"],
    }
    if summary["unmapped_contacts"]:
        logger.warning("%d of %d source contacts lie where no log-map chart of the source hand is one-to-one "
                       "(its mesh is too coarse there for geodesics): they were dropped, not guessed",
                       summary["unmapped_contacts"], len(transferred.contacts.dropped))
    provenance = {"version": __version__, "commit": _commit(), "inputs": inputs.provenance(),
                  "frames": [first, last], "config": config.to_dict(), "executor": executor.describe(),
                  "kernels": kernel_provenance()}
    if remap.changed:  # annotations carried onto edited meshes: how far their points moved
        provenance["annotation_remap"] = remap.to_dict() | {"lines": remap.lines()}
    return RetargetResult(
        rig_name=target.name, dof_names=target.dof_names, dof_kinds=[d.kind for d in target.dofs],
        lower=target.lower, upper=target.upper, fps=float(clip.fps), times=times, q=q, curves=curves,
        unresolved=unresolved, timings=timings, counts=counts, contact_distance_mm=distance, contact_count=count,
        marker_error_mm=marker, summary=summary, config=config.to_dict(), clip_source=clip.source,
        unused_settings=unused_settings(config), frames=(first, last), provenance=provenance, rig=target,
        object_vertices=clip.object_vertices, object_faces=clip.object_faces, object_poses=clip.object_poses,
        table_pose=clip.table_pose, table_half_extents=clip.table_half_extents, contacts=contacts,
        source_contact_count=np.diff(pairs.frame_offsets),
        source_hand=_source_snapshots(clip, np.diff(pairs.frame_offsets)))


def collision_for_source_depth(clip: Clip, config: RetargetConfig) -> tuple[RetargetConfig, dict | None]:
    """The run's configuration with the hand-object penetration term on when the clip's own
    hand lies deeper than ``contacts.source_depth_limit`` inside the object in some frame and
    ``weights.lambda_p`` is 0 (:class:`~retarget_core.solve.config.Contacts`); and what was
    measured: {"max_mm", "frames" (over the limit), "penetration_term"} (None when not measured)."""
    from .clip.substitute import hand_depth_per_frame
    from .solve.config import COLLISION_WEIGHTS

    limit = config.contacts.source_depth_limit_si
    if limit <= 0 or config.weights.lambda_p > 0 or clip.object_vertices is None:
        return config, None
    depth = hand_depth_per_frame(clip, clip.object_vertices, clip.object_faces)
    over = np.nonzero(depth > limit)[0]
    found = {"max_mm": float(1000.0 * depth.max()), "frames": int(len(over)), "penetration_term": "off"}
    if not len(over):
        return config, found
    effective = copy.deepcopy(config)
    effective.weights.lambda_p = COLLISION_WEIGHTS["lambda_p"]
    found["penetration_term"] = (
        f"on (weights.lambda_p = {effective.weights.lambda_p:g}): the clip's hand lies up to {found['max_mm']:.1f} mm "
        f"inside the object in {len(over)} frames (from frame {over[0]}), deeper than contacts.source_depth_limit = "
        f"{config.contacts.source_depth_limit:g} cm; set weights.lambda_p to choose the term yourself")
    logger.info("penetration term %s", found["penetration_term"])  # the summary and `retarget` say it
    return effective, found


def check_inputs(clip: Clip, source: Rig, target: Rig, annotations, config: RetargetConfig, *,
                 annotation_max_displacement: float = DEFAULT_MAX_DISPLACEMENT) -> int:
    """Raise InputError on inputs that cannot give a result; return the control-point count.
    Checks: both rigs (``Rig.validate``: limits that hold the rest pose, closed surface, ...),
    the clip's hand mesh against the source rig's surface, the annotations' mesh signatures
    against the rigs' surfaces (annotations with positions made for an earlier version of a mesh
    are carried onto it first, points moving at most ``annotation_max_displacement`` metres, see
    :func:`~retarget_core.transfer.annotations.remap_to_meshes`), and a clip long enough for
    the spline (>= 4 frames and >= ``fit.control_points`` when fixed)."""
    return _check_inputs(clip, source, target, annotations, config, annotation_max_displacement)[0]


def _check_inputs(clip, source, target, annotations, config, annotation_max_displacement):
    """:func:`check_inputs`; (control points, the annotations on the rigs' meshes, RemapReport)."""
    source.validate(source=f"source rig {source.name!r}")
    target.validate(source=f"target rig {target.name!r}")
    if not surface_matches_hand(source, clip.hand_faces, clip.hand_vertices.shape[1]):
        raise InputError(f"the clip's hand mesh ({clip.hand_vertices.shape[1]} vertices, {len(clip.hand_faces)} "
                         f"faces) is not the source rig {source.name!r}'s surface ({source.surface.n_vertices} "
                         f"vertices, {len(source.surface.faces)} faces): give the rig the clip was made with as the "
                         "source rig", source="clip", element="source_rig")
    annotations, remap = remap_to_meshes(annotations, source, target, max_displacement=annotation_max_displacement)
    if remap.changed:
        logger.warning("%s", remap)
    annotations.check_meshes(source.surface.faces, source.surface.n_vertices, target.surface.faces,
                             target.surface.n_vertices, source="annotations")
    fixed = config.fit.control_points
    need = max(MIN_CONTROL_POINTS, fixed or 0)
    if config.passes.fit and clip.n_frames < need:
        why = f"fit.control_points = {fixed}" if fixed else f"a cubic B-spline has {MIN_CONTROL_POINTS} control points"
        raise InputError(f"the clip is too short for the spline fit: {clip.n_frames} frames, at least {need} needed "
                         f"({why})", source="clip", element="n_frames")
    return config.n_control_points(clip.n_frames, clip.fps), annotations, remap


def build_problem(clip: Clip, pairs: ContactPairs, source: Rig, target: Rig, annotations, config: RetargetConfig,
                  executor: Executor):
    """Steps 2 and 3: the paired contacts carried onto ``target`` through the atlas, the marker
    and contact targets of every frame, and the per-frame problem the passes solve. Returns
    (problem, the clip transfer)."""
    transferred = transfer_clip(pairs, source, target, annotations, keep_patch_size=config.contacts.keep_patch_size,
                                workers=executor.workers, cache_dir=executor.cache_dir)
    markers = marker_targets(clip, source, target, annotations)
    if config.markers.scale_fingers:
        markers = scale_finger_markers(markers, source, target)
    if config.markers.proportion_width > 0:
        markers = proportion_weights(markers, source, target, config.markers.proportion_width_si)
    contacts = contact_targets(clip, pairs, transferred.contacts, keep_source_gap=config.contacts.keep_source_gap)
    if len(markers.pair_target) < 3:
        raise InputError("at least three marker pairs are needed to place the hand", element="markers")
    # the collision terms' grids once here, not once per worker and objective
    grids = collision_grids(target, clip.object_vertices, clip.object_faces, config)
    problem = Problem(target, config, markers, contacts, clip.object_poses, clip.table_pose,
                      clip.table_half_extents, clip.object_vertices, clip.object_faces, grids)
    method_objective(problem, "fingers")  # a baseline's missing markers are an input error, before any work
    return problem, transferred


# ---- the passes -------------------------------------------------------------------------------
class PassReport:
    """Frames solved, objective evaluations, failed frames [(frame, error)], seconds; held:
    frames given their earlier solution back (see :func:`hold_branches`)."""

    def __init__(self, frames: int = 0):
        self.frames, self.evaluations, self.failed, self.seconds = frames, 0, [], 0.0
        self.held = []


def root_segments(n_frames: int) -> list[np.ndarray]:
    """The root pass's runs of consecutive frames (:data:`ROOT_SEGMENT_FRAMES` each, the last
    shorter)."""
    return [np.arange(s, min(s + ROOT_SEGMENT_FRAMES, n_frames)) for s in range(0, n_frames, ROOT_SEGMENT_FRAMES)]


def root_pass(runner: FrameRunner, problem: Problem, clip: Clip, config: RetargetConfig):
    """Paper: "we first solve for only root joint position per frame while keeping the remaining
    joints fixed in their default positions", each frame seeded from the previous one. Each run
    of :func:`root_segments` starts from a rigid fit of the target markers at rest onto the
    source markers of its first frame. Returns q (T, D) and the pass's report (with
    ``passes.root`` off: the rigid-fit seeds, held over each run)."""
    t0 = time.perf_counter()
    target, markers = problem.rig, problem.markers
    rest = target.rest_pose
    kin = target.kinematics()
    rest_markers = kin.points(rest, kin.bind(SurfacePoints(markers.target_faces, markers.target_barycentric)))
    root_now = kin.pose(rest).world[0]
    segments = root_segments(clip.n_frames)
    seeds = [set_root_transform(target, rest, rigid_fit(rest_markers[markers.pair_target],
                                                     markers.source_positions[s[0]]) @ root_now) for s in segments]
    q = np.concatenate([np.repeat(seed[None], len(s), axis=0) for s, seed in zip(segments, seeds)])
    report = PassReport(clip.n_frames)
    if config.passes.root:
        for f, qf, evals, error in runner.solve_root_sequences(segments, seeds):
            report.evaluations += evals
            if error:
                report.failed.append((f, error))
            q[f] = qf
    report.seconds = time.perf_counter() - t0
    return q, report


def solve_pass(runner: FrameRunner, frames, seeds: np.ndarray, label: str, keyed: bool = False):
    """Solve ``frames`` of the finger objective independently from ``seeds`` (T, D) (all frames'
    seeds); returns the seeds with the solved frames replaced (a failed frame keeps its seed)
    and the report."""
    t0 = time.perf_counter()
    frames = np.asarray(frames, dtype=np.int64)
    out = seeds.copy()
    report = PassReport(len(frames))
    for f, qf, evals, error in runner.solve(frames, seeds[frames], stage="fingers", keyed=keyed, label=label):
        report.evaluations += evals
        if error:
            report.failed.append((f, error))
        else:
            out[f] = qf
    report.seconds = time.perf_counter() - t0
    return out, report


#: Rounds of the coherence pass: each traces the branches across the jumps its path still has.
COHERENCE_ROUNDS = 3


class CoherenceReport(PassReport):
    """A :class:`PassReport` with the jumps found before and left after the pass, the
    candidate solutions traced, and the frames whose solution was replaced."""

    def __init__(self, frames: int = 0):
        super().__init__(frames)
        self.jumps_before, self.jumps_after, self.candidates, self.replaced = 0, 0, 0, []


def target_marker_points(problem: Problem, q: np.ndarray) -> np.ndarray:
    """(T, Np, 3) the target side of every marker pair posed at q (T, D)."""
    kin = problem.rig.kinematics()
    m = problem.markers
    binding = kin.bind(SurfacePoints(m.target_faces, m.target_barycentric))
    return np.stack([kin.points(qf, binding)[m.pair_target] for qf in q])


def coherence_pass(runner: FrameRunner, problem: Problem, q: np.ndarray):
    """After the full pass, which solves every frame on its own: a step where the solved hand
    turns or moves far more than the source does (:func:`~retarget_core.refine.branches.branch_jumps`)
    is a frame that left its neighbours' branch. Each stretch between jumps is carried on
    across the clip, forward from its last frame and backward from its first, every frame
    re-solved seeded from the one before until the run rejoins the solution there; so a frame
    holds one candidate per branch. The path through the candidates with the fewest jumps, and
    among those the lowest summed objective, replaces the solutions
    (:func:`~retarget_core.refine.branches.choose_branch_path`); a new round traces from the
    jumps it still has (:data:`COHERENCE_ROUNDS` at most). A jump no branch avoids (the
    objective itself turns the hand there) is left. The runs are fixed before they start and
    each is sequential in one worker, so the result does not depend on the worker count."""
    t0 = time.perf_counter()
    source_points = problem.markers.source_positions
    own = q.copy()
    q = q.copy()
    report = CoherenceReport(0)
    jumps = branch_jumps(target_marker_points(problem, q), source_points)
    report.jumps_before = int(jumps.sum())
    # per frame: candidate poses and their objectives; the frame's own solution first
    poses = [[qf] for qf in q]
    values: list[list] = [[0.0] for _ in q]  # own values filled in where a trace brings a rival
    valued = np.zeros(len(q), dtype=bool)
    runner.executor.report("coherence", 0, COHERENCE_ROUNDS)  # a stage is announced even when it finds nothing
    for round_ in range(COHERENCE_ROUNDS):
        if not jumps.any():
            break
        if round_:
            runner.executor.report("coherence", round_, COHERENCE_ROUNDS)
        forward, backward = branch_runs(jumps, 1), branch_runs(jumps, -1)
        runs = forward + backward
        seeds = [q[r[0] - 1] for r in forward] + [q[r[0] + 1] for r in backward]
        for f, qf, value, own_value, evals, error in runner.trace_branches(runs, seeds, [q[r] for r in runs]):
            report.frames += 1
            report.evaluations += evals
            if error:
                report.failed.append((f, error))
                continue
            if not valued[f] and np.array_equal(q[f], own[f]):
                values[f][0], valued[f] = own_value, True
            poses[f].append(qf)
            values[f].append(value)
            report.candidates += 1
        for f in np.nonzero(~valued)[0]:  # a frame whose own value was not measured has no rival
            if len(poses[f]) > 1:
                raise RuntimeError(f"coherence: frame {f} has rivals but no value of its own solution")
        candidate_points = [target_marker_points(problem, np.array(p)) for p in poses]
        path, _ = choose_branch_path(candidate_points, values, source_points)
        new_q = np.array([poses[f][k] for f, k in enumerate(path)])
        if np.array_equal(new_q, q):
            break
        q = new_q
        jumps = branch_jumps(target_marker_points(problem, q), source_points)
    runner.executor.report("coherence", COHERENCE_ROUNDS, COHERENCE_ROUNDS)
    report.jumps_after = int(jumps.sum())
    report.replaced = [int(f) for f in np.nonzero(np.any(q != own, axis=1))[0]]
    report.seconds = time.perf_counter() - t0
    return q, report


def hold_branches(problem: Problem, before: np.ndarray, after: np.ndarray) -> tuple[np.ndarray, list]:
    """A pass after the coherence pass (filter, refinement) re-solves frames from filtered or
    interpolated keys, and a key between two poses can seed the other branch. A frame that
    pass changed and that now jumps against a neighbour (:func:`branch_jumps`) where it did not
    before (T, D) gets its earlier solution back. Returns q (T, D) and the frames held."""
    source_points = problem.markers.source_positions

    def jumps_at_frames(q):
        j = branch_jumps(target_marker_points(problem, q), source_points).astype(np.int64)
        count = np.zeros(len(q), dtype=np.int64)
        count[:-1] += j
        count[1:] += j
        return count

    had = jumps_at_frames(before)
    q, held = after.copy(), set()
    for _ in range(COHERENCE_ROUNDS):  # a frame held back can clear its neighbour's jump too
        bad = np.any(q != before, axis=1) & (jumps_at_frames(q) > had)
        if not bad.any():
            break
        q[bad] = before[bad]
        held.update(int(f) for f in np.nonzero(bad)[0])
    return q, sorted(held)


def filter_pass(runner: FrameRunner, q: np.ndarray, rig: Rig, fps: float, config: RetargetConfig):
    """Paper: "re-solve for the estimates after applying low-pass and peak removal filters".
    Only the frames the filter moved beyond the re-solve tolerances are re-solved, regularised
    toward the filtered key. Returns q and the report (None when no frame moved)."""
    ref = config.refinement
    rot = rig.kinematics().is_rotation
    filtered, changed = lowpass_and_remove_peaks(q, fps, ref.lowpass_cutoff_hz, ref.peak_thresholds(rot),
                                                 peak_window=ref.peak_window, order=ref.lowpass_order,
                                                 change_tolerance=ref.resolve_tolerances(rot))
    frames = np.nonzero(changed)[0]
    if not len(frames):
        return q, None
    resolved, report = solve_pass(runner, frames, filtered, "filter re-solve", keyed=True)
    q = q.copy()
    q[frames] = resolved[frames]
    return q, report


def refinement(runner: FrameRunner, q: np.ndarray, rig: Rig, fps: float, config: RetargetConfig):
    """Paper "Trajectory Refinement": frames violating E_acc are replaced per DOF by interpolation
    and re-solved toward it, until none is left or the iterations run out."""
    ref = config.refinement
    rounds = []

    def resolve(frames, seeds):
        out = np.array(seeds, dtype=np.float64)
        index = {int(f): i for i, f in enumerate(frames)}
        rounds.append(len(frames))
        # each round counts its own frames up: progress names the round after the first
        label = "refinement" if len(rounds) == 1 else f"refinement round {len(rounds)}"
        for f, qf, _, error in runner.solve(frames, seeds, stage="fingers", keyed=True, label=label):
            if not error:
                out[index[f]] = qf
        return out

    return refine_trajectory(q, fps, rig.kinematics().is_rotation, resolve, e_acc_angular=ref.e_acc_angular_si,
                             e_acc_linear=ref.e_acc_linear_si, max_iterations=ref.max_iterations,
                             patience=ref.patience)


# ---- reporting --------------------------------------------------------------------------------
def _median(values: np.ndarray) -> float | None:
    """The median of the finite values, None when there is none."""
    values = np.asarray(values, dtype=np.float64)
    values = values[np.isfinite(values)]
    return float(np.median(values)) if len(values) else None


def run_counts(reports: dict) -> dict:
    """Evaluations per frame and failed frames of each pass (root, full, filter), the
    refinement report (``RefinementReport.to_dict``) and every failed frame once."""
    passes, failed = {}, {}
    for name, r in reports.items():
        if name == "refine":
            continue
        passes[name] = {"frames": r.frames, "evaluations": r.evaluations,
                        "evaluations_per_frame": r.evaluations / r.frames if r.frames else 0.0,
                        "failed": [{"frame": int(f), "error": str(e)} for f, e in r.failed],
                        "held": [int(f) for f in r.held]}
        if isinstance(r, CoherenceReport):
            passes[name].update(jumps_before=r.jumps_before, jumps_after=r.jumps_after,
                                candidates=r.candidates, replaced=[int(f) for f in r.replaced])
        for f, e in r.failed:
            failed.setdefault(int(f), str(e))
    return {"passes": passes, "refinement": reports["refine"].to_dict() if "refine" in reports else None,
            "failed_frames": [{"frame": f, "error": failed[f]} for f in sorted(failed)]}


def _source_snapshots(clip: Clip, source_contact_count: np.ndarray):
    """The source hand at the frames the pictures show (:func:`~retarget_core.render.preview.picture_frames`:
    the contact sheet's and the preview's): frames (K,), vertices (K, V, 3) float32, faces."""
    from .render.preview import picture_frames

    sheet, preview = picture_frames(clip.n_frames, clip.fps, source_contact_count)
    frames = np.union1d(sheet, preview)
    return frames, clip.hand_vertices[frames].astype(np.float32), clip.hand_faces


def _commit() -> str | None:
    """The git commit of this checkout, when the package runs from one (else None)."""
    root = Path(__file__).resolve().parent.parent
    if not (root / ".git").exists():
        return None
    try:
        out = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                             timeout=5, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None

