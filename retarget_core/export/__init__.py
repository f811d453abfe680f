"""Result export: the USD animation layer (baked UsdSkel animation + native DOF splines) and
per-frame JSON for robot users."""

from .usd_animation import (
    bspline_to_ts,
    local_joint_transforms,
    read_animation_json,
    read_dof_bsplines,
    read_dof_splines,
    write_animation_json,
    write_animation_usd,
)

__all__ = [
    "bspline_to_ts",
    "local_joint_transforms",
    "read_animation_json",
    "read_dof_bsplines",
    "read_dof_splines",
    "write_animation_json",
    "write_animation_usd",
]
