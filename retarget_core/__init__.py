"""Hand Retarget core: contact-aware kinematic retargeting of hand-object manipulation.

Pipeline stages live in their own subpackages (see DESIGN.md beside the repo):

- ``retarget_core.rig``   target hand rigs: joint tree, DOFs with limits, skinning,
                          analytic kinematics and Jacobians, USD / URDF / MJCF I/O,
                          the procedural hand generator and the demo library.
- ``retarget_core.mesh``  surface utilities shared by every stage (topology checks,
                          closed-surface extraction, surface points).

Everything is SI: metres, radians, seconds. Nothing in the core prints.
"""

__version__ = "0.1.0"
