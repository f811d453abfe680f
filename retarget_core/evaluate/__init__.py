"""Evaluation of a retargeted motion: the paper's intersection metrics (hand-object, self and
table, as convex-hull volumes of penetrating vertex clusters relative to the hand's volume)
and per-frame / per-clip quality metrics (contact error and coverage, marker error,
smoothness, DOF limit violations, series summaries)."""

from .intersection import (
    KINDS,
    IntersectionResult,
    clip_intersections,
    hand_object_intersection,
    points_inside_mesh,
    self_intersection,
    table_intersection,
)
from .metrics import (
    DEFAULT_COVERAGE_THRESHOLD,
    DEFAULT_LIMIT_TOLERANCE,
    ContactCoverage,
    LimitViolations,
    Smoothness,
    contact_coverage,
    contact_distance_per_frame,
    contact_distances,
    coverage_per_frame,
    dof_derivatives,
    dof_limit_violations,
    dof_smoothness,
    marker_error_per_frame,
    median_per_frame_mm,
    summarize_series,
)

__all__ = [
    "KINDS",
    "IntersectionResult",
    "clip_intersections",
    "hand_object_intersection",
    "points_inside_mesh",
    "self_intersection",
    "table_intersection",
    "DEFAULT_COVERAGE_THRESHOLD",
    "DEFAULT_LIMIT_TOLERANCE",
    "ContactCoverage",
    "LimitViolations",
    "Smoothness",
    "contact_coverage",
    "contact_distance_per_frame",
    "contact_distances",
    "coverage_per_frame",
    "dof_derivatives",
    "dof_limit_violations",
    "dof_smoothness",
    "marker_error_per_frame",
    "median_per_frame_mm",
    "summarize_series",
]
