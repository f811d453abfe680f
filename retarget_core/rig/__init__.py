"""Target hand rigs: the joint tree, DOFs with limits, skinned surfaces, and analytic
kinematics (see :mod:`.model` and :mod:`.kinematics`)."""

from .model import Dof, Joint, Rig, SkinnedMesh, parse_axis
from .kinematics import Kinematics, Pose, SurfaceBinding

__all__ = ["Dof", "Joint", "Rig", "SkinnedMesh", "parse_axis", "Kinematics", "Pose", "SurfaceBinding"]
