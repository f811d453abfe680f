"""The compiled forward kinematics of :class:`~retarget_core.rig.kinematics.Kinematics` (numba).

Its own module so that numba is imported only when a pose is first evaluated: reading a rig
(the service's upload validation runs under a memory limit) needs only the bind pose, which
Kinematics computes in NumPy."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _mul4(a, b, out):
    for r in range(4):
        for c in range(4):
            out[r, c] = a[r, 0] * b[0, c] + a[r, 1] * b[1, c] + a[r, 2] * b[2, c] + a[r, 3] * b[3, c]


@njit(cache=True)
def forward(q, order, parent, dof_joint, k, k2, t, rest_local, inv_bind, axes):
    """Forward kinematics at q (D,): world (J, 4, 4), skin = world @ inv_bind (J, 4, 4), and per
    DOF its world axis (D, 3) and pivot (D, 3). Each joint's local transform is its rest local
    transform times its DOFs' A(q) = I + sin q K + (1 - cos q) K^2 + q T, in DOF order;
    ``order`` lists the joints parents first. Compiled: as batched NumPy products per chain level
    this was ~0.1-0.2 ms a pose, evaluated tens of thousands of times a run."""
    n_joints, n_dofs = rest_local.shape[0], q.shape[0]
    local = rest_local.copy()
    before = np.empty((n_dofs, 4, 4))
    a = np.empty((4, 4))
    tmp = np.empty((4, 4))
    for d in range(n_dofs):
        j = dof_joint[d]
        before[d] = local[j]
        s, c, v = np.sin(q[d]), 1.0 - np.cos(q[d]), q[d]
        for r in range(4):
            for col in range(4):
                a[r, col] = (1.0 if r == col else 0.0) + s * k[d, r, col] + c * k2[d, r, col] + v * t[d, r, col]
        _mul4(before[d], a, tmp)
        local[j] = tmp
    world = np.empty((n_joints, 4, 4))
    for j in order:
        if parent[j] < 0:
            world[j] = local[j]
        else:
            _mul4(world[parent[j]], local[j], tmp)
            world[j] = tmp
    skin = np.empty((n_joints, 4, 4))
    for j in range(n_joints):
        _mul4(world[j], inv_bind[j], tmp)
        skin[j] = tmp
    dof_axis = np.empty((n_dofs, 3))
    dof_origin = np.empty((n_dofs, 3))
    for d in range(n_dofs):
        pj = parent[dof_joint[d]]
        if pj < 0:
            frame = before[d]
        else:
            _mul4(world[pj], before[d], tmp)
            frame = tmp
        for r in range(3):
            dof_axis[d, r] = frame[r, 0] * axes[d, 0] + frame[r, 1] * axes[d, 1] + frame[r, 2] * axes[d, 2]
            dof_origin[d, r] = frame[r, 3]
    return world, skin, dof_axis, dof_origin
