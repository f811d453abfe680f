"""Hand Retarget core: contact-aware kinematic retargeting of hand-object manipulation.

One run: ``retarget_core.pipeline.retarget(inputs, config, executor)`` with
``inputs = retarget_core.inputs.load_inputs(clip, rig, annotations)`` (or ``RunInputs.of``),
``config = retarget_core.solve.config.load_config(...)`` (what changes the result) and
``executor = retarget_core.execute.Executor(workers=...)`` (how it runs). Pipeline stages live
in their own subpackages (see DESIGN.md beside the repo):

- ``retarget_core.rig``   target hand rigs: joint tree, DOFs with limits, skinning,
                          analytic kinematics and Jacobians, USD / URDF / MJCF I/O,
                          the procedural hand generator and the demo library.
- ``retarget_core.mesh``  surface utilities shared by every stage (topology checks,
                          closed-surface extraction, surface points).

Everything is SI: metres, radians, seconds. Nothing in the core prints.
"""

__version__ = "0.1.0"

from .kernels import pin_kernels as _pin_kernels

_pin_kernels()  # before anything loads numpy: one kernel set on every machine (see kernels.py)
