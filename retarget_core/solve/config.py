"""Run configuration: everything that describes one retargeting run, in one dataclass.

:class:`RetargetConfig` groups the settings of the pipeline stages of the paper's appendix
"Motion Retargeting Details" / "Parameter Values":

- :class:`Weights`        the objective's lambda coefficients (paper table "Optimization
                          weighting coefficients": all 1.0 except lambda_j = 50) plus the
                          collision weights beyond the paper: hand-object penetration
                          lambda_p and self collision lambda_sc (0 = off, as in both presets).
- :class:`SolverSettings` the per-frame optimiser (nlopt LD_MMA, 100 evaluations,
                          xtol_rel 1e-4 in the paper's code).
- :class:`Refinement`     the acceleration threshold E_acc (500 deg/s^2 and 500 cm/s^2), the
                          iteration cap (20) and the low-pass / peak-removal filtering pass.
- :class:`Fit`            the cubic B-spline fit: a fixed control-point count or a rate.
- :class:`Passes`         which stages run.
- :class:`Contacts`       how contact targets are placed (on the object, or keeping the
                          source's gap).
- :class:`Markers`        how a marker pair's distance is penalised (squared, or
                          pseudo-Huber: squared near, linear far).
- :class:`Sampling`       vertex sub-sampling for the table and collision terms.

User-facing units follow the paper: angles in degrees, lengths in centimetres; every such
field has an SI property (``*_si``) or helper returning radians / metres, which is what the
core uses internally.

Configurations are built from a preset (:meth:`RetargetConfig.preset`) with an optional TOML
file and an optional override dict applied on top (:func:`load_config`). The TOML tables and
keys mirror the dataclasses::

    method = "contacts"

    [weights]
    lambda_j = 20.0

    [solver]
    maxeval = 60

    [refinement]
    e_acc_angular = 500.0   # deg/s^2

    [fit]
    control_points = 60     # replaces the preset's control_points_per_second

Every numeric key has a lower and an upper bound (:data:`BOUNDS`; "(" excludes the low end):

====================================== ================== ===================================
key                                    allowed            unit
====================================== ================== ===================================
weights.* (every lambda)               [0, 1e6]
solver.maxeval, solver.root_maxeval    [1, 10000]         objective evaluations per frame
solver.xtol_rel, solver.ftol_rel       [0, 1]
solver.fd_step                         (0, 1]
solver.warm_start_iterations           [0, 200]           Gauss-Newton steps per frame
markers.huber_width                    (0, 100]           cm
markers.proportion_width               [0, 100]           cm (0 = off)
contacts.source_depth_limit            [0, 100]           cm (0 = never)
refinement.e_acc_angular               (0, 1e7]           deg/s^2
refinement.e_acc_linear                (0, 1e7]           cm/s^2
refinement.max_iterations              [0, 200]           rounds
refinement.patience                    [0, 200]           rounds
refinement.lowpass_cutoff_hz           (0, 1000]          Hz
refinement.lowpass_order               [1, 10]
refinement.peak_threshold_angular      (0, 360]           deg
refinement.peak_threshold_linear       (0, 1000]          cm
refinement.peak_window                 [3, 101], odd      frames
refinement.resolve_tolerance_angular   [0, 360]           deg
refinement.resolve_tolerance_linear    [0, 1000]          cm
fit.control_points                     [4, 10000]
fit.control_points_per_second          (0, 120]           per second of clip
fit.polish_iterations                  [0, 100]           Levenberg-Marquardt steps
fit.polish_tolerance                   [0, 1]             stop on a smaller share of the gap
fit.polish_patience                    [1, 100]           kept steps that must close it together
fit.polish_within                      [0, 100]           done this share above the solved frames
sampling.*_sample_stride               [1, 1000]          vertices
====================================== ================== ===================================

Unknown keys, wrong types and out-of-range values raise :class:`~retarget_core.errors.InputError`
whose ``element`` is the dotted key path (``"solver.maxevals: unknown key"``).

The configuration holds only what changes the result. How a run executes (worker count, Dask
scheduler, atlas cache, progress, BLAS threads) is an :class:`~retarget_core.execute.Executor`
passed beside it; the old top-level keys ``workers``, ``dask_scheduler`` and ``atlas_cache``
are refused with the executor option that replaces them.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from retarget_core.errors import InputError

__all__ = [
    "GRADIENT_MODES",
    "MARKER_DISTANCES",
    "METHODS",
    "PRESETS",
    "SUPPORTED_ALGORITHMS",
    "Contacts",
    "Fit",
    "Markers",
    "Passes",
    "Refinement",
    "RetargetConfig",
    "Sampling",
    "SolverSettings",
    "Weights",
    "BOUNDS",
    "load_config",
    "n_control_points",
]

#: Optimiser names accepted in ``solver.algorithm`` (nlopt spelling; gradient-based only).
SUPPORTED_ALGORITHMS = ("LD_MMA", "LD_CCSAQ", "LD_SLSQP", "LD_LBFGS")
#: ``solver.gradient`` values: ``"analytic"`` (the core's Jacobians) or ``"forward"`` (forward
#: differences with ``fd_step``, one skinning pass per DOF; kept only to measure the speed-up).
GRADIENT_MODES = ("analytic", "forward")
#: ``method`` values: the paper's contact-based objective and the two contact-free baselines.
METHODS = ("contacts", "fingertips", "keyvectors")
#: ``markers.distance`` values (see :class:`Markers`).
MARKER_DISTANCES = ("squared", "huber")

#: Collision weights measured on robot and prosthetic hands (see the default preset's note 9):
#: what ``--set weights.lambda_p=10 --set weights.lambda_sc=10`` turns on.
COLLISION_WEIGHTS = {"lambda_p": 10.0, "lambda_sc": 10.0}

#: Smallest control-point count of a cubic B-spline.
MIN_CONTROL_POINTS = 4

#: The allowed range of every numeric field: {dotted key: (low, high, low excluded)}. Values are
#: checked by :meth:`RetargetConfig.validate` (an out-of-range value is an InputError naming the
#: key and this range). The upper bounds keep a run's work finite: each is far above what a run
#: needs (the presets use 30-100 evaluations, 20 warm-start steps, 20 refinement rounds, order-4
#: filters, 7-frame peak windows, 10 control points per second) and below what would make one
#: frame, or the whole clip, take unbounded time or memory (an nlopt evaluation cap of 2^31 is
#: not representable at all).
BOUNDS: dict[str, tuple[float, float, bool]] = {
    **{f"weights.{name}": (0.0, 1e6, False) for name in
       ("lambda_m", "lambda_cd", "lambda_cn", "lambda_c", "lambda_t", "lambda_j", "lambda_p", "lambda_sc",
        "lambda_r")},
    "solver.maxeval": (1, 10_000, False),
    "solver.root_maxeval": (1, 10_000, False),
    "solver.xtol_rel": (0.0, 1.0, False),
    "solver.ftol_rel": (0.0, 1.0, False),
    "solver.fd_step": (0.0, 1.0, True),
    "solver.warm_start_iterations": (0, 200, False),
    "markers.huber_width": (0.0, 100.0, True),              # cm
    "markers.proportion_width": (0.0, 100.0, False),        # cm, 0 = off
    "contacts.source_depth_limit": (0.0, 100.0, False),     # cm, 0 = never
    "refinement.e_acc_angular": (0.0, 1e7, True),           # deg/s^2
    "refinement.e_acc_linear": (0.0, 1e7, True),            # cm/s^2
    "refinement.max_iterations": (0, 200, False),
    "refinement.patience": (0, 200, False),
    "refinement.lowpass_cutoff_hz": (0.0, 1000.0, True),
    "refinement.lowpass_order": (1, 10, False),
    "refinement.peak_threshold_angular": (0.0, 360.0, True),  # deg
    "refinement.peak_threshold_linear": (0.0, 1000.0, True),  # cm
    "refinement.peak_window": (3, 101, False),                # odd
    "refinement.resolve_tolerance_angular": (0.0, 360.0, False),
    "refinement.resolve_tolerance_linear": (0.0, 1000.0, False),
    "fit.control_points": (MIN_CONTROL_POINTS, 10_000, False),
    "fit.control_points_per_second": (0.0, 120.0, True),
    "fit.polish_iterations": (0, 100, False),
    "fit.polish_tolerance": (0.0, 1.0, False),
    "fit.polish_patience": (1, 100, False),
    "fit.polish_within": (0.0, 100.0, False),
    "sampling.table_sample_stride": (1, 1000, False),
    "sampling.penetration_sample_stride": (1, 1000, False),
    "sampling.self_collision_samples": (1, 100_000, False),
}


def _range_text(lo, hi, open_lo: bool) -> str:
    """``[1, 10000]`` / ``(0, 1]``."""
    def num(x) -> str:
        return str(int(x)) if float(x).is_integer() else f"{x:g}"

    return f"{'(' if open_lo else '['}{num(lo)}, {num(hi)}]"


#: ``dask_scheduler`` values: ``tcp://HOST:PORT`` (HOST a name, an IPv4 address or a bracketed
#: IPv6 address).
_DASK_ADDRESS = re.compile(r"tcp://(?:[A-Za-z0-9](?:[A-Za-z0-9.-]*[A-Za-z0-9])?|\[[0-9A-Fa-f:.]+\]):(\d{1,5})")


@dataclass
class Weights:
    """Objective weights (paper table "Optimization weighting coefficients")."""

    lambda_m: float = 1.0   # marker alignment
    lambda_cd: float = 1.0  # contact distance
    lambda_cn: float = 1.0  # contact normal (1 + n_obj . n_hand)
    lambda_c: float = 1.0   # contact term (scales lambda_cd and lambda_cn)
    lambda_t: float = 1.0   # table
    lambda_j: float = 50.0  # joint prior (L1 deviation of non-root DOFs)
    lambda_p: float = 0.0   # hand-object penetration, squared hinge in mm^2; 0 = off (not in the paper)
    lambda_sc: float = 0.0  # self collision between non-adjacent hand parts, mm^2; 0 = off (not in the paper)
    lambda_r: float = 0.0   # root gauge near Euler gimbal lock (rad^2, see objective); not in the paper


@dataclass
class SolverSettings:
    """Per-frame optimiser. ``maxeval`` bounds objective evaluations per frame in the full
    pass, ``root_maxeval`` per frame in the root-only pass. ``ftol_rel = 0`` disables the
    relative-objective stop (nlopt convention). ``fd_step`` is only used with
    ``gradient = "forward"``. ``warm_start_iterations`` > 0 runs that many bounded
    Gauss-Newton (Levenberg-Marquardt) steps on the least-squares form of the objective before
    the optimiser in the full-pose solves (0 = the paper: the optimiser alone, from the seed)."""

    algorithm: str = "LD_MMA"
    maxeval: int = 100
    root_maxeval: int = 100
    xtol_rel: float = 1e-4
    ftol_rel: float = 0.0
    gradient: str = "analytic"
    fd_step: float = 1e-3
    warm_start_iterations: int = 0


@dataclass
class Contacts:
    """Contact targets. ``keep_source_gap = False`` aims each target contact point at its object
    point (the paper); ``True`` moves the object point out along the object normal by the gap
    the source pair had there (captured contacts are "within a threshold", often 1-4 mm open;
    closing that gap bends the fingers a few degrees past the capture). ``keep_patch_size =
    False`` takes the contacts on the target hand where the atlas puts them (the paper: a patch
    grows with lambda_s); ``True`` then gives each contact patch the size it had on the source
    hand (:func:`~retarget_core.transfer.clip_transfer.size_patches`): its points are paired
    with the same object points, so only a patch of the object's size can meet them.

    ``source_depth_limit`` (cm; 0 = never, the paper preset; 0.2 in the default preset): when
    the clip's own hand lies deeper than this inside the object in some frame, and
    ``weights.lambda_p`` is 0, the run turns the hand-object penetration term on at
    :data:`COLLISION_WEIGHTS` (the result's summary says so and why). Markers and the prior follow
    the source hand's closure, so a target follows the source into the object where nothing else
    pushes it out: an object substituted by a wider or thicker one (``clip substitute
    --allow-intersection``), a capture whose hand sank into a scan. Measured (bottle_pick_place,
    120 frames, the bottle 1.15x wider, source hand up to 5.1 mm inside it, onto human_alt,
    default preset): penetration p95 2.89 mm, hand-object intersection median 0.43 % with the
    term off (the palm, 43 mm from any contact, followed the source's); 0.74 mm and 0.005 % on,
    contact error 0.90 -> 0.86 mm. The demo clips' hands stay within 0.4 mm of their objects."""

    keep_source_gap: bool = False
    keep_patch_size: bool = False
    source_depth_limit: float = 0.0

    @property
    def source_depth_limit_si(self) -> float:
        """``source_depth_limit`` in metres (0 = never)."""
        return self.source_depth_limit / 100.0


@dataclass
class Markers:
    """How far a marker pair is penalised.

    ``distance = "squared"`` (paper preset): |d|^2 (mm^2) per pair. ``"huber"`` (default preset,
    ``huber_width`` 0.2 cm): the
    pseudo-Huber penalty 2 delta (sqrt(|d|^2 + delta^2) - delta) with delta = ``huber_width``
    (cm): |d|^2 within about delta, then growing like 2 delta |d| (with the default 0.05 cm,
    beyond a millimetre a pair costs its distance in mm, the paper's "L2 distance"), so a
    marker that cannot be met pulls with a bounded force. Measured (natural-speed bottle
    grasp, proposed annotations, on the earlier witch whose thumb was 1.55x the source's): the
    witch's markers cannot all be met (median 15-17 mm off) and "huber" lowered its median
    contact distance from 3.40 to 2.86 mm, but on the identity retarget the weaker pull near
    the markers lets the prior open the fingers: finger RMSE 4.3 deg instead of 1.2-1.5.
    The default preset uses "huber" with a 2 mm width since stop 25: quadratic where a hand can
    meet its markers (the identity retarget, within 2-3 mm), a pull capped at 4 mm-equivalent
    where it cannot (a hand of other proportions). Measured (``handretarget grid --clip
    bottle_pick_place --method contacts``, 120 frames, proposed annotations, contact error median
    at the delivered spline, squared -> huber 0.2): LEAP 12.9 -> 8.99 mm (solved frames 4.5),
    Shadow 1.84 -> 1.84, source_human 1.49 -> 1.48, human_alt 1.66 -> 1.66, witch 2.29 -> 1.97,
    alien 2.07 -> 1.67, prosthetic_1dof 2.59 -> 2.16, prosthetic_2dof 2.00 -> 1.76, robot4
    5.44 -> 4.45. A 0.5 mm width took LEAP's solved frames to 3.6 mm but opens the identity
    retarget's fingers (above).
    Either way a marker of K pairs (area, many-to-one) weighs each pair 1/K, so every marker
    counts once.

    ``scale_fingers`` (off in both presets): re-place the source markers of each finger for
    the target's link lengths (:func:`retarget_core.solve.targets.scale_finger_markers`), so
    the markers ask for the source's joint angles rather than the source's marker positions.
    Measured on that witch (same run as above): markers met to 3.6 mm instead of 15 mm, but the
    median contact distance rose from 3.40 to 3.95 mm: the contacts carried through the atlas
    (stretched by lambda_a = 1.5 along each finger) want a different pose from the source's
    angles. With the markers off altogether (lambda_m = 0) the contacts alone reached 2.71 mm.

    ``proportion_width`` (cm; 0 = off): weigh each marker by how well the target's proportions
    can meet it (:func:`retarget_core.solve.targets.proportion_weights`): d, the marker's
    distance from the source's after a rigid fit of the target's markers at rest onto the
    source's, gives the weight 1 / (1 + (d / width)^2), the weights rescaled to keep their sum.
    A hand of the source's proportions keeps nearly even weights; on a hand with a larger palm
    or longer fingers the markers it cannot meet pull less. Off in both presets: measured
    (``handretarget grid --clip bottle_pick_place --method contacts``, 120 frames, default
    preset, contact error median at the delivered curve, off -> width 1 cm -> 3 cm): robot4
    3.50 -> 3.85 -> 3.66 mm (penetration p95 31.4 -> 18.6 -> 23.8 mm, self intersection 1.66 ->
    2.65 -> 3.06 %), LEAP 4.54 -> 5.12 -> 4.79, prosthetic_1dof 2.13 -> 2.16 (1 cm), human_alt
    1.61 -> 1.61. The pseudo-Huber marker penalty already caps the pull of a marker a hand
    cannot meet; taking weight off some markers hands the pose to the others and to the prior.
    Both hands' rest poses are compared, so a target whose rest pose curls its fingers reads
    as a mismatch of its finger markers."""

    distance: str = "squared"
    huber_width: float = 0.05
    scale_fingers: bool = False
    proportion_width: float = 0.0

    @property
    def huber_width_si(self) -> float:
        """``huber_width`` in metres."""
        return self.huber_width / 100.0

    @property
    def proportion_width_si(self) -> float:
        """``proportion_width`` in metres (0 = off)."""
        return self.proportion_width / 100.0


@dataclass
class Refinement:
    """Trajectory refinement (paper "Trajectory Refinement").

    ``e_acc_angular`` (deg/s^2) and ``e_acc_linear`` (cm/s^2) are compared with
    ``|(q[f+1]-q[f]) - (q[f]-q[f-1])| / dt`` — divided by ``dt`` once, as in the paper's code
    (see :func:`retarget_core.refine.acceleration_violations`). ``max_iterations`` caps the
    violation / re-solve loop; ``patience`` > 0 ends it earlier once that many rounds in a row
    did not lower the violation count (0 = the paper: always up to the cap).

    The filtering pass (run before refinement) removes peaks — samples deviating from a running
    median over ``peak_window`` frames by more than ``peak_threshold_angular`` (deg) /
    ``peak_threshold_linear`` (cm) — then applies a zero-phase Butterworth low-pass of order
    ``lowpass_order`` at ``lowpass_cutoff_hz``. Frames the filter moved by more than
    ``resolve_tolerance_angular`` (deg) / ``resolve_tolerance_linear`` (cm) in some DOF are
    re-solved (0 = every frame the filter moved). The paper gives no values for the filter;
    these defaults are the project's choice."""

    e_acc_angular: float = 500.0
    e_acc_linear: float = 500.0
    max_iterations: int = 20
    patience: int = 0
    lowpass_cutoff_hz: float = 10.0
    lowpass_order: int = 4
    peak_threshold_angular: float = 10.0
    peak_threshold_linear: float = 2.0
    peak_window: int = 7
    resolve_tolerance_angular: float = 0.0
    resolve_tolerance_linear: float = 0.0

    @property
    def e_acc_angular_si(self) -> float:
        """E_acc for rotational DOFs in rad/s^2."""
        return math.radians(self.e_acc_angular)

    @property
    def e_acc_linear_si(self) -> float:
        """E_acc for translational DOFs in m/s^2."""
        return self.e_acc_linear / 100.0

    @property
    def peak_threshold_angular_si(self) -> float:
        return math.radians(self.peak_threshold_angular)

    @property
    def peak_threshold_linear_si(self) -> float:
        return self.peak_threshold_linear / 100.0

    def peak_thresholds(self, is_rotation) -> np.ndarray:
        """Per-DOF peak threshold in SI (rad for rotations, m otherwise), shape (D,)."""
        rot = np.asarray(is_rotation, dtype=bool)
        return np.where(rot, self.peak_threshold_angular_si, self.peak_threshold_linear_si)

    def resolve_tolerances(self, is_rotation) -> np.ndarray:
        """Per-DOF filter change tolerance in SI (rad / m), shape (D,)."""
        rot = np.asarray(is_rotation, dtype=bool)
        return np.where(rot, math.radians(self.resolve_tolerance_angular),
                        self.resolve_tolerance_linear / 100.0)


@dataclass
class Fit:
    """Spline fit (paper "Spline Fitting"): one cubic B-spline per DOF with the same number of
    control points for every DOF. Give exactly one of ``control_points`` (a fixed count) or
    ``control_points_per_second`` (scaled with the clip's duration). ``optimize_knots = False``
    uses clamped uniform knots (the paper's code); ``True`` also solves for knot locations
    (the paper's text). ``respect_limits`` (default preset; off in ``paper``): a curve that
    would leave its DOF's limits between or at the frames is re-fitted with its coefficients
    bounded by the limits, so it stays within them (a robot can play it back); the
    unconstrained least-squares fit overshot the limits on fast clips."""

    control_points: int | None = None
    control_points_per_second: float | None = 10.0
    optimize_knots: bool = False
    respect_limits: bool = True
    #: Levenberg-Marquardt iterations polishing the fitted coefficients on the frames' own
    #: objective (fit/polish.py; 0: the least-squares fit is delivered as it is)
    polish_iterations: int = 0
    #: the polish stops once the last ``polish_patience`` kept steps together closed less than
    #: this share of the gap to the solved frames' summed objective left before them (0: all
    #: ``polish_iterations`` run while steps are kept and a gap is left)
    polish_tolerance: float = 0.0
    #: ... the kept steps that window counts (1: each step on its own)
    polish_patience: int = 1
    #: ... or once the curve scores within this share above the solved frames' objective (0:
    #: at or below it)
    polish_within: float = 0.0

    def n_control_points(self, n_frames: int, fps: float) -> int:
        """Control points for a clip of ``n_frames`` at ``fps``: the fixed count, or
        ``round(rate * n_frames / fps)``; clamped to ``[4, n_frames]`` (at least a cubic
        segment, never more unknowns than samples; fewer than 4 frames gives ``n_frames``)."""
        if int(n_frames) != n_frames or n_frames < 1:
            raise InputError(f"n_frames must be a positive integer, got {n_frames!r}",
                             element="n_frames")
        if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
            raise InputError(f"fps must be positive, got {fps!r}", element="fps")
        n_frames = int(n_frames)
        if self.control_points is not None:
            n = int(self.control_points)
        else:
            n = int(round(float(self.control_points_per_second) * n_frames / float(fps)))
        return min(max(n, MIN_CONTROL_POINTS), n_frames)


@dataclass
class Passes:
    """Which pipeline stages run: root-only pass, full-pose pass, coherence pass (each
    stretch between jumps traced across the clip, one branch kept per frame by the path with
    the fewest jumps; pipeline.coherence_pass), filtering pass,
    acceleration refinement, spline fit."""

    root: bool = True
    full: bool = True
    coherence: bool = True
    filter: bool = True
    refine: bool = True
    fit: bool = True


@dataclass
class Sampling:
    """Vertex sub-sampling for the per-frame terms: the table term and the penetration term use
    every ``table_sample_stride``-th / ``penetration_sample_stride``-th hand vertex
    (1 = all vertices); the self collision term at most ``self_collision_samples`` vertices per
    hand part, spread evenly over its surface (one per cube: :data:`~retarget_core.solve.collision.PART_POINT_SPACING`).
    128 since stop 49 (32 before, picked by vertex id: robot4's fingertip links went 11 mm into
    each other between the points)."""

    table_sample_stride: int = 1
    penetration_sample_stride: int = 1
    self_collision_samples: int = 128


#: Keys that moved out of the run configuration into the executor: {key: what replaces it}.
EXECUTOR_KEYS = {
    "workers": "the executor's worker count (--workers on the command line, Executor(workers=N), "
               "the service's --workers)",
    "dask_scheduler": "the executor's Dask scheduler (--dask-scheduler on the command line, "
                      "Executor(dask_scheduler=...), the service's --dask-scheduler)",
    "atlas_cache": "the executor's atlas cache (--atlas-cache on the command line, "
                   "Executor(atlas_cache=...); the service keeps its own)",
}


def check_dask_address(address: str, element: str) -> None:
    """InputError naming ``element`` unless ``address`` is "" or ``tcp://HOST:PORT``."""
    if not isinstance(address, str):
        raise InputError(f"expected a string, got {address!r}", element=element)
    if address:
        m = _DASK_ADDRESS.fullmatch(address)
        if m is None or not 1 <= int(m.group(1)) <= 65535:
            raise InputError(f"expected \"\" or a scheduler address tcp://HOST:PORT, got {address!r}",
                             element=element)


@dataclass
class RetargetConfig:
    """Settings of one retargeting run. Build one with :meth:`preset` or :func:`load_config`.

    Presets (see :data:`PRESETS`):

    ``"paper"``
        The paper's settings: weights from its table (lambda_j = 50, others 1, no
        penetration term), LD_MMA with 100 evaluations per frame in both passes,
        xtol_rel 1e-4, E_acc 500 deg/s^2 and 500 cm/s^2, 20 refinement iterations, clamped
        uniform knots, and 10 control points per second (the paper's table averages ~10/s at
        120 fps, e.g. 60 for the 703-frame apple clip). The paper's code used forward
        differences only because it had no analytic gradients; the gradient mode does not
        change the optimum, so ``gradient`` stays ``"analytic"`` in every preset
        (``"forward"`` exists only to measure the speed-up).
    ``"default"``
        The project's choice: the paper's settings, except
        (1) every full-pose solve starts with up to 20 bounded Gauss-Newton steps before MMA:
        from rest fingers MMA needs far more than 100 evaluations to close a hand onto a few
        hundred contacts (identity retarget of bottle_pick_place: finger RMSE 6.6 deg with MMA
        alone at 100 evaluations, 1.2 deg with the warm start, in a third of the time);
        (2) contact targets keep the source's gap (:class:`Contacts`);
        (3) MMA then polishes with at most 30 evaluations (after the warm start, 100 lower the
        objective by only another 0.2 % at 1.4x the time); the root-only pass, which starts
        from the previous frame's root, uses MMA alone with 30;
        (4) near gimbal lock of the root's Euler angles, the one combination of them that
        barely turns the hand is held at the seed (lambda_r = 100 per rad^2, see
        :class:`~retarget_core.solve.objective.FrameObjective`);
        (5) the table term samples a third of the hand's vertices;
        (6) after filtering, only frames the filter moved by more than 0.5 deg / 0.5 mm in some
        DOF are re-solved;
        (7) refinement stops after 3 rounds in a row without fewer violations
        (``Refinement.patience``) and keeps the best round;
        (8) the prior weighs 20 instead of 50 (``weights.lambda_j``): at 50 it held the distal
        finger joints short of the captured bend where only a few contacts and one marker
        constrain them (GRAB-format MANO -> MANO identity, 200 frames, tests/
        test_grab_end_to_end.py: finger rotation RMSE 3.04 deg at 50, 1.38 at 20; the
        prior's L1 force is a constant 50 per radian against a fingertip's few mm); the grid
        (``handretarget grid ... --clip bottle_pick_place --method contacts``) kept every
        contact median within 0.1 mm (LEAP 4.69 -> 4.65 mm, alien 1.71 -> 1.62, witch 1.94 ->
        1.98), LEAP's self intersection rose from 8.2 to 10.7 %, robot4's fell from 4.6 to 4.0 %;
        (9) the collision terms are built but off (``weights.lambda_p``, ``weights.lambda_sc``;
        :data:`COLLISION_WEIGHTS` turns them on: every 4th vertex for the hand-into-object half,
        the object's points every 2 mm for the other, 32 sample vertices per hand part for self
        collision). On, robot4 on bottle_pick_place (120 frames, exact measures over the
        contact frames) goes from 31.4 mm p95 penetration and 1.65 % median self intersection
        to 1.74 mm and 0.0006 % (contact error 3.50 -> 3.94 mm); the README's grid table has
        every hand. What keeps them off is the mirror test (tests/test_grab_both_hands.py: the
        left hand against the mirrored right within 1 mm per frame and 2 mm per vertex): the
        frame solve has two minima at some frames of that clip (frame 100: the middle finger's
        distal joints 42 deg apart between the two hands, with the terms on and off alike, from
        inputs that agree to rounding), and whether filtering, refinement and the curve polish
        bring the two hands back within the bounds changes with any change to the objective
        (terms on: 2.3-4.4 mm, per-frame mean 0.4-1.6 mm, as the warm start changed). Off, it
        depends on the machine: at 21a7f49 the same run gives 0.99 mm with OpenBLAS's SkylakeX
        kernels and 2.60 mm with its Haswell kernels (``OPENBLAS_CORETYPE``, same AMD EPYC
        host; the test fails there); and their cost: 1.59x the solving stages at stop 55
        (3.16x at stop 39, 2.78x before stop 55 compiled the grid reads and the kinematics;
        ``handretarget bench --collision``, the goal is 1.5x; the README's "What they cost" has
        where it goes).

    Top-level key ``method``: ``"contacts"`` (the paper) or a contact-free baseline
    (:data:`METHODS`); the settings a baseline does not use in its finger passes are listed in
    result.json (:func:`~retarget_core.solve.problem.unused_settings`).

    Every numeric field has a range (:data:`BOUNDS`, tabled in the module docstring), checked by
    :meth:`validate`: e.g. ``solver.maxeval`` 1-10000, ``refinement.max_iterations`` 0-200,
    ``refinement.lowpass_order`` 1-10; beyond it is an InputError naming the dotted key and the
    range, so no configuration (nor a service job's overrides) asks for unbounded work.
    """

    weights: Weights = field(default_factory=Weights)
    solver: SolverSettings = field(default_factory=SolverSettings)
    refinement: Refinement = field(default_factory=Refinement)
    fit: Fit = field(default_factory=Fit)
    passes: Passes = field(default_factory=Passes)
    contacts: Contacts = field(default_factory=Contacts)
    markers: Markers = field(default_factory=Markers)
    sampling: Sampling = field(default_factory=Sampling)
    #: the per-frame objective of the finger passes: "contacts" (the paper's method) or one of
    #: the contact-free baselines "fingertips" / "keyvectors" (:mod:`~retarget_core.solve.baselines`)
    method: str = "contacts"

    @classmethod
    def preset(cls, name: str = "default") -> "RetargetConfig":
        """A fresh configuration for preset ``name`` (``"paper"`` or ``"default"``)."""
        try:
            make = _PRESET_BUILDERS[name]
        except (KeyError, TypeError):
            raise InputError(f"unknown preset {name!r} (expected one of {', '.join(PRESETS)})",
                             element="preset") from None
        cfg = make()
        cfg.validate()
        return cfg

    def n_control_points(self, n_frames: int, fps: float) -> int:
        """See :meth:`Fit.n_control_points`."""
        return self.fit.n_control_points(n_frames, fps)

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (TOML/JSON friendly except ``None`` for the unused control-point
        option), for reports."""
        return dataclasses.asdict(self)

    def validate(self, source: str | None = None) -> None:
        """Raise :class:`InputError` (``element`` = dotted key, ``source`` as given) on a wrong
        type or out-of-range value."""
        _check_types(self, "", source)

        def fail(msg: str, key: str):
            raise InputError(msg, source=source, element=key)

        for key, (lo, hi, open_lo) in BOUNDS.items():
            section, _, name = key.partition(".")
            obj = getattr(self, section)
            v = getattr(obj, name)
            if v is None:  # fit.control_points / control_points_per_second: the unused one
                continue
            if not math.isfinite(v) or v > hi or (v <= lo if open_lo else v < lo):
                fail(f"must be in {_range_text(lo, hi, open_lo)}, got {v!r}", key)
        s = self.solver
        if s.algorithm not in SUPPORTED_ALGORITHMS:
            fail(f"unsupported algorithm {s.algorithm!r} (expected one of "
                 f"{', '.join(SUPPORTED_ALGORITHMS)})", "solver.algorithm")
        if s.gradient not in GRADIENT_MODES:
            fail(f"must be one of {', '.join(GRADIENT_MODES)}, got {s.gradient!r}",
                 "solver.gradient")
        if self.markers.distance not in MARKER_DISTANCES:
            fail(f"must be one of {', '.join(MARKER_DISTANCES)}, got {self.markers.distance!r}",
                 "markers.distance")
        r = self.refinement
        if r.peak_window % 2 == 0:
            fail(f"must be an odd integer in {_range_text(*BOUNDS['refinement.peak_window'])}, "
                 f"got {r.peak_window!r}", "refinement.peak_window")
        fit = self.fit
        if (fit.control_points is None) == (fit.control_points_per_second is None):
            fail("give exactly one of fit.control_points and fit.control_points_per_second",
                 "fit")
        if self.method not in METHODS:
            fail(f"must be one of {', '.join(METHODS)}, got {self.method!r}", "method")


# --------------------------------------------------------------------------------------------
# presets


def _paper() -> RetargetConfig:
    return RetargetConfig(
        weights=Weights(),
        solver=SolverSettings(algorithm="LD_MMA", maxeval=100, root_maxeval=100,
                              xtol_rel=1e-4, ftol_rel=0.0, gradient="analytic", fd_step=1e-3),
        refinement=Refinement(e_acc_angular=500.0, e_acc_linear=500.0, max_iterations=20),
        fit=Fit(control_points=None, control_points_per_second=10.0, optimize_knots=False, respect_limits=False),
        passes=Passes(coherence=False),  # the paper's frames stay independent to the end
        contacts=Contacts(keep_source_gap=False),
        markers=Markers(distance="squared"),
        sampling=Sampling(),
    )


def _default() -> RetargetConfig:
    cfg = _paper()
    cfg.weights.lambda_r = 100.0  # pins the Euler direction gimbal lock leaves free
    cfg.weights.lambda_j = 20.0  # the prior settles what the data leave free, not a fingertip's bend
    cfg.solver.maxeval = 30  # after the warm start MMA only polishes (measured: 2 % of the value)
    cfg.solver.root_maxeval = 30
    cfg.solver.warm_start_iterations = 20
    cfg.contacts.keep_source_gap = True
    # each contact patch keeps its source size (transfer/clip_transfer.py size_patches): the
    # atlas made robot4's index-tip patch in box_pinch 2.6x the object's, 8.32 -> 2.16 mm
    # delivered contact error (README "Stop 47"; Shadow 4.04 -> 1.62, human_alt 2.07 -> 1.59)
    cfg.contacts.keep_patch_size = True
    # a source hand more than 2 mm inside its object (a substituted, thicker object) switches the
    # penetration term on for that run (Contacts.source_depth_limit)
    cfg.contacts.source_depth_limit = 0.2
    cfg.refinement.patience = 3  # measured: rounds after the third stale one never helped
    cfg.refinement.resolve_tolerance_angular = 0.5  # re-solve only frames the filter really moved
    cfg.refinement.resolve_tolerance_linear = 0.05
    cfg.sampling.table_sample_stride = 3  # a third of the hand's vertices feel the table
    # collision terms (objective, collision.py): off (see note 9);
    # the sampling is what --set weights.lambda_p=10 --set weights.lambda_sc=10 then uses
    cfg.sampling.penetration_sample_stride = 4
    cfg.fit.respect_limits = True  # curves a rig (or a robot) can play back
    # the delivered curve scored on what the frames were solved on, until it scores about as
    # well as the solved frames or stops gaining on them
    # (4 fixed steps until stop 37 left Shadow's and the witch's apple curves 10-15 % above
    # their solved frames' contact error and 3-6 mm into the apple, with the objective still
    # falling 25 % a step; see the README's "Issue 20's goals")
    # (12 steps left Shadow's apple_handoff at 3.55 mm against 2.83 solved; 40 reach 2.88;
    # a curve near its solved frames still stops after a step or two; at stop 52 Shadow's
    # apple_rotate needed 60 to reach its solved frames' objective: 40 left it at 1.20x,
    # delivered 2.58 mm against 2.46 solved and 2.27 mm p95 penetration, 60 gave 2.13 mm, 1.78)
    cfg.fit.polish_iterations = 80
    # progress comes in bursts (small steps while the damping settles, then large ones), so the
    # gain is judged over ten kept steps: they must close 10 % of the gap together. Step by step
    # (three in a row each < 1 %, stops 40-52) Shadow's apple curves stalled at 1.39x (delivered
    # 3.14 mm against 2.46 solved) five steps before a burst that reached the solved frames'
    # objective after 60 steps; and a curve that cannot follow its frames (a clip sped up past
    # its control points) ran all 80 steps gaining 0.01 % each
    cfg.fit.polish_tolerance = 0.1
    cfg.fit.polish_patience = 10
    # fit.polish_within stays 0 (done only at the solved frames' objective): at 1 % robot4's
    # box_pinch curve stopped at 1.007x with a delivered contact error of 3.02 mm against 2.11
    # solved (one more step reached 1.0x and 2.11 mm); the contacts are a small part of the sum
    # a bounded marker pull: markers a hand of other proportions cannot meet stop fighting the contacts
    cfg.markers.distance = "huber"
    cfg.markers.huber_width = 0.2
    # the solved frames' path through the root branches with the fewest jumps (pipeline.coherence_pass)
    cfg.passes.coherence = True
    return cfg


_PRESET_BUILDERS = {"paper": _paper, "default": _default}
#: Preset names accepted by :meth:`RetargetConfig.preset` and :func:`load_config`.
PRESETS = tuple(_PRESET_BUILDERS)


def n_control_points(n_frames: int, fps: float, config: RetargetConfig | None = None) -> int:
    """Control points for a clip under ``config`` (default preset when ``None``)."""
    cfg = config if config is not None else RetargetConfig.preset("default")
    return cfg.n_control_points(n_frames, fps)


# --------------------------------------------------------------------------------------------
# loading / overrides

# Pairs of mutually exclusive fields: setting one in a layer clears the other.
_EXCLUSIVE = {("fit", "control_points"): "control_points_per_second",
              ("fit", "control_points_per_second"): "control_points"}


def _type_name(tp) -> str:
    if tp is float:
        return "a number"
    if tp is int:
        return "an integer"
    if tp is bool:
        return "a boolean"
    if tp is str:
        return "a string"
    return str(tp)


def _coerce(value, tp, key: str, source: str | None):
    """Check ``value`` against the annotation ``tp``; return it (ints widened to float)."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _coerce(value, args[0], key, source)
    ok = False
    if tp is bool:
        ok = isinstance(value, bool)
    elif tp is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif tp is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        if ok:
            value = float(value)
    elif tp is str:
        ok = isinstance(value, str)
    if not ok:
        raise InputError(f"expected {_type_name(tp)}, got {type(value).__name__} {value!r}",
                         source=source, element=key)
    return value


def _check_types(obj, prefix: str, source: str | None = None) -> None:
    hints = typing.get_type_hints(type(obj))
    for f in dataclasses.fields(obj):
        key = f"{prefix}{f.name}"
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(hints[f.name]):
            _check_types(v, key + ".", source)
        else:
            _coerce(v, hints[f.name], key, source)


def _expand_dotted(overrides: Mapping[str, Any]) -> dict[str, Any]:
    """``{"solver.maxeval": 50}`` -> ``{"solver": {"maxeval": 50}}`` (nested dicts pass)."""
    out: dict[str, Any] = {}
    for k, v in overrides.items():
        if not isinstance(k, str):
            raise InputError(f"override keys must be strings, got {k!r}", element=str(k))
        parts = k.split(".")
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise InputError("conflicting overrides", element=k)
        if isinstance(v, Mapping):
            v = _expand_dotted(v)
            existing = node.setdefault(parts[-1], {})
            if not isinstance(existing, dict):
                raise InputError("conflicting overrides", element=k)
            existing.update(v)
        else:
            node[parts[-1]] = v
    return out


def _apply(obj, data: Mapping[str, Any], prefix: str, source: str | None) -> None:
    if not isinstance(data, Mapping):
        raise InputError(f"expected a table, got {type(data).__name__}", source=source,
                         element=prefix.rstrip(".") or "<root>")
    hints = typing.get_type_hints(type(obj))
    names = {f.name for f in dataclasses.fields(obj)}
    section = prefix.rstrip(".")
    for k, v in data.items():
        key = f"{prefix}{k}"
        if not prefix and k in EXECUTOR_KEYS:
            raise InputError(f"no longer part of the run configuration (it does not change the result): "
                             f"use {EXECUTOR_KEYS[k]}", source=source, element=key)
        if k not in names:
            raise InputError("unknown key", source=source, element=key)
        tp = hints[k]
        if dataclasses.is_dataclass(tp):
            _apply(getattr(obj, k), v, key + ".", source)
            continue
        if isinstance(v, Mapping):
            raise InputError(f"expected {_type_name(tp)}, got a table", source=source,
                             element=key)
        setattr(obj, k, _coerce(v, tp, key, source))
        other = _EXCLUSIVE.get((section, k))
        if other is not None:
            if other in data:
                raise InputError(f"give only one of {section}.{k} and {section}.{other}",
                                 source=source, element=key)
            setattr(obj, other, None)


def load_config(path: str | os.PathLike | None = None, preset: str = "default",
                overrides: Mapping[str, Any] | None = None) -> RetargetConfig:
    """Build a configuration: preset ``preset``, then the TOML file at ``path`` (if any), then
    ``overrides`` (nested dicts mirroring the TOML tables, or dotted keys such as
    ``{"solver.maxeval": 50}``). Setting ``fit.control_points`` in a layer clears the
    preset's ``fit.control_points_per_second`` and vice versa. Raises :class:`InputError`
    naming the file and dotted key on an unreadable file, unknown key, wrong type or
    out-of-range value."""
    cfg = RetargetConfig.preset(preset)
    source = None
    if path is not None:
        source = str(path)
        try:
            with Path(path).open("rb") as fh:
                data = tomllib.load(fh)
        except FileNotFoundError:
            raise InputError("configuration file not found", source=source) from None
        except OSError as exc:
            raise InputError(f"cannot read configuration file: {exc}", source=source) from None
        except tomllib.TOMLDecodeError as exc:
            raise InputError(f"invalid TOML: {exc}", source=source) from None
        _apply(cfg, data, "", source)
        cfg.validate(source)
    if overrides:
        _apply(cfg, _expand_dotted(overrides), "", "overrides")
        cfg.validate("overrides")
    return cfg

