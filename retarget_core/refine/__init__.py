"""Trajectory refinement (paper appendix "Trajectory Refinement"): acceleration violations,
interpolation and iterative re-solving, plus the low-pass / peak-removal filtering pass; see
:mod:`retarget_core.refine.trajectory`."""

from .trajectory import (
    RefinementReport,
    ResolveFn,
    acceleration_violations,
    interpolate_violations,
    lowpass_and_remove_peaks,
    refine_trajectory,
)

__all__ = [
    "RefinementReport",
    "ResolveFn",
    "acceleration_violations",
    "interpolate_violations",
    "lowpass_and_remove_peaks",
    "refine_trajectory",
]
