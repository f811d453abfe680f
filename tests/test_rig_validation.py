"""Bad rigs are rejected with errors that name the element."""

import copy

import numpy as np
import pytest

from retarget_core.errors import InputError
from retarget_core.rig import parse_axis


@pytest.fixture
def rig(demo_rigs):
    return copy.deepcopy(demo_rigs["prosthetic_2dof"])


def test_valid_rig_passes(rig):
    rig.validate()


def test_unnormalised_skin_weights(rig):
    rig.surface.joint_weights[7] *= 1.5
    with pytest.raises(InputError, match="vertex 7.*sum to"):
        rig.validate(source="hand.usda")


def test_missing_skin_weights(rig):
    rig.surface.joint_weights[3] = 0.0
    with pytest.raises(InputError, match="vertex 3 has no skin weight"):
        rig.validate()


def test_joint_without_limits(rig):
    rig.dofs[8].lower = float("nan")
    with pytest.raises(InputError, match=rf"DOF '{rig.dofs[8].name}'.*limit"):
        rig.validate()


def test_rest_outside_limits(rig):
    rig.dofs[9].rest = rig.dofs[9].upper + 0.1
    with pytest.raises(InputError, match="outside its limits"):
        rig.validate()


def test_open_surface_is_rejected(rig):
    rig.surface.faces = rig.surface.faces[1:]
    with pytest.raises(InputError, match="closed.*boundary edges"):
        rig.validate(source="hand.usda")


def test_parent_after_child(rig):
    rig.joints[2].parent = 5
    with pytest.raises(InputError, match="earlier joint"):
        rig.validate()


def test_nan_vertex(rig):
    rig.surface.vertices[11, 1] = np.nan
    with pytest.raises(InputError, match="vertex 11 is NaN"):
        rig.validate()


def test_axis_names():
    np.testing.assert_array_equal(parse_axis("-y"), [0, -1, 0])
    np.testing.assert_allclose(parse_axis([0, 3, 4]), [0, 0.6, 0.8])
    with pytest.raises(InputError, match="unknown axis name 'w'"):
        parse_axis("w", element="DOF 'index1_flex'")
    with pytest.raises(InputError, match="zero length"):
        parse_axis([0, 0, 0])
