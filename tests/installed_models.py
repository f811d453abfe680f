"""The robot hand model files installed at set-up (retarget_core.rig.io.INSTALLED_MODELS), for
tests that skip without their wheels."""

from pathlib import Path

from retarget_core.errors import InputError
from retarget_core.rig.io import installed_model


def installed_or_none(name: str) -> Path | None:
    """The model file of ``installed:NAME``, or None when its wheel is not installed."""
    try:
        return installed_model(name)
    except InputError:
        return None
