"""Spline fitting of DOF trajectories: one cubic B-spline per DOF (paper, "Spline Fitting")."""

from .splines import (
    BSplineCurve,
    clamped_uniform_knots,
    evaluate_curves,
    fit_bspline,
    fit_trajectory,
    schoenberg_whitney_ok,
)

__all__ = [
    "BSplineCurve",
    "clamped_uniform_knots",
    "evaluate_curves",
    "fit_bspline",
    "fit_trajectory",
    "schoenberg_whitney_ok",
]
