"""Whole-pipeline benchmark (issue budgets of DESIGN.md): a ~1000-frame demo clip onto a 54-DOF
hand, wall time per stage on the configured workers, peak memory of the process tree, and the
per-frame speed-up of analytic over forward-difference gradients on the same frames."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import numpy as np

from ..clip.demo import SOURCE_RESOLUTION, build_demo_timeline, clip_from_timeline, source_rig
from ..pairing.dense import pair_contacts
from ..procmem import tree_memory_bytes
from ..rig.demo_hands import demo_hand
from ..solve.collision import clear_grid_cache
from ..solve.config import COLLISION_WEIGHTS, RetargetConfig
from ..solve.frame_solver import solve_frame
from ..solve.problem import Problem, method_objective
from ..solve.targets import contact_targets, marker_targets
from ..transfer.atlas import clear_memory_cache
from ..transfer.clip_transfer import transfer_clip
from ..transfer.propose import propose_annotations


class PeakMemory:
    """Samples the memory (PSS) of this process and its children every ``interval`` s. A sample
    walks every page table of the tree (/proc/PID/smaps_rollup: about 7 ms for a 150 MB parent
    and two workers, more for the bench's 1.3 GiB), so sampling costs the run it measures some
    CPU: the runs compared in one bench are all sampled alike."""

    def __init__(self, interval: float = 0.2):
        self.interval = interval
        self.peak = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self.available = Path("/proc/self/stat").exists()

    def _run(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, tree_memory_bytes(os.getpid()))
            self._stop.wait(self.interval)

    def __enter__(self):
        if self.available:
            self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        if self.available:
            self._thread.join()
            self.peak = max(self.peak, tree_memory_bytes(os.getpid()))


def benchmark_clip(name: str = "bottle_pick_place", n_frames: int = 1000):
    """The demo clip ``name`` stretched to about ``n_frames`` frames (the source rig is
    returned with it)."""
    rig = source_rig()
    _, nominal = build_demo_timeline(name, time_scale=1.0, rig=rig)
    scale = n_frames / nominal.nominal_frames
    obj, timeline = build_demo_timeline(name, time_scale=scale, rig=rig)
    return clip_from_timeline(name, obj, timeline, rig, SOURCE_RESOLUTION), rig


def gradient_speedup(clip, source, target, annotations, config: RetargetConfig, n_frames: int = 8) -> dict:
    """Per-frame solve time with analytic vs forward-difference gradients, same frames, same
    MMA settings (the paper's solve: no warm start, ``maxeval`` evaluations from the rest
    fingers) on ``n_frames`` contact frames spread over the clip."""
    pairs = pair_contacts(clip)
    transferred = transfer_clip(pairs, source, target, annotations, keep_patch_size=config.contacts.keep_patch_size)
    markers = marker_targets(clip, source, target, annotations)
    contacts = contact_targets(clip, pairs, transferred.contacts, keep_source_gap=config.contacts.keep_source_gap)
    problem = Problem(target, config, markers, contacts, clip.object_poses, clip.table_pose, clip.table_half_extents,
                      clip.object_vertices, clip.object_faces)
    objective = method_objective(problem, "root")  # the paper's objective, every DOF free below
    counts = np.diff(contacts.frame_offsets)
    with_contacts = np.nonzero(counts > 0)[0]
    frames = with_contacts[np.linspace(0, len(with_contacts) - 1, n_frames).astype(int)]
    kinds = [d.kind for d in target.dofs]
    root = [d.joint == 0 for d in target.dofs]
    out = {}
    for mode in ("analytic", "forward"):
        seconds, values, evals = [], [], []
        for f in frames:
            objective.set_frame(problem.frame_data(int(f)))
            seed = target.rest_pose.copy()
            seed[:6] = clip.dof_values[f, :6]  # every rig starts with the same free root (demo clips)
            t0 = time.perf_counter()
            sol = solve_frame(objective, seed, target.lower, target.upper, np.ones(target.n_dofs, bool),
                              maxeval=config.solver.maxeval, xtol_rel=config.solver.xtol_rel, gradient=mode,
                              fd_step=config.solver.fd_step, kinds=kinds, root_mask=root,
                              algorithm=config.solver.algorithm, coupling=target.coupling())
            seconds.append(time.perf_counter() - t0)
            values.append(sol.value)
            evals.append(sol.evaluations)
        out[mode] = {"ms_per_frame": 1000 * float(np.mean(seconds)), "objective_evaluations": float(np.mean(evals)),
                     "median_value": float(np.median(values))}
    out["frames"] = [int(f) for f in frames]
    out["speedup"] = out["forward"]["ms_per_frame"] / out["analytic"]["ms_per_frame"]
    return out


def run_retarget_benchmark(n_frames: int = 1000, target: str = "human_alt", workers: int = 2,
                           preset: str = "default", speedup_frames: int = 8, collision_off: bool = True,
                           collision: bool = False) -> dict:
    """Time every stage of :func:`retarget_core.pipeline.retarget` on a ~``n_frames`` demo clip
    onto the demo hand ``target``, twice: from scratch (the in-memory atlas and collision grids
    cleared, no disk cache; ``scratch``) and then with them cached (``timings``); peak memory
    (PSS) of the process tree over both;
    then the gradient speed-up on ``speedup_frames`` contact frames of the same clip (0: not
    measured, ``gradient`` None). With
    ``collision_off`` (and the collision terms on in the preset, or ``collision``: on with
    :data:`~retarget_core.solve.config.COLLISION_WEIGHTS`) the same run again without them
    (lambda_p = lambda_sc = 0): what the terms cost."""
    from ..execute import Executor
    from ..inputs import RunInputs
    from ..pipeline import retarget

    t0 = time.perf_counter()
    clip, source = benchmark_clip(n_frames=n_frames)
    target_rig = demo_hand(target)
    annotations = propose_annotations(source, target_rig)
    setup_seconds = time.perf_counter() - t0
    config = RetargetConfig.preset(preset)
    if collision:
        for name, value in COLLISION_WEIGHTS.items():
            setattr(config.weights, name, value)
    inputs = RunInputs.of(clip, source, target_rig, annotations, names={"target_rig": f"demo:{target}"})
    # from scratch: nothing of this hand pair kept in memory, and no disk cache (the executor's
    # default), as a first run on a new hand pair; then the same run with the atlas cached
    clear_memory_cache()
    clear_grid_cache()
    with PeakMemory() as memory_scratch:
        scratch = retarget(inputs, config, Executor(workers=int(workers)))
    with PeakMemory() as memory:
        result = retarget(inputs, config, Executor(workers=int(workers)))
    off = None
    if collision_off and (config.weights.lambda_p > 0 or config.weights.lambda_sc > 0):
        plain = RetargetConfig.preset(preset)
        plain.weights.lambda_p = plain.weights.lambda_sc = 0.0
        with PeakMemory() as memory_off:  # timed under the same sampling as the run it is compared with
            without = retarget(inputs, plain, Executor(workers=int(workers)))
        off = {"timings": without.timings, "summary": without.summary, "counts": without.counts,
               "peak_memory_bytes": memory_off.peak}
    speed = None  # speedup_frames = 0: not measured
    if speedup_frames > 0:
        speed = gradient_speedup(clip, source, target_rig, annotations, RetargetConfig.preset("paper"),
                                 n_frames=speedup_frames)
    return {
        "frames": clip.n_frames, "fps": float(clip.fps), "target": target, "dofs": target_rig.n_dofs,
        "target_vertices": int(target_rig.surface.n_vertices), "workers": int(workers), "preset": preset,
        "duration_seconds": clip.n_frames / float(clip.fps),
        "scratch": {"timings": scratch.timings, "peak_memory_bytes": memory_scratch.peak,
                    "summary": scratch.summary},
        "setup_seconds": setup_seconds, "timings": result.timings, "peak_memory_bytes": max(memory.peak, memory_scratch.peak),
        "peak_memory_measured": memory.available, "summary": result.summary, "counts": result.counts,
        "gradient": speed, "collision_off": off,
    }
