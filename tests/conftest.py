"""Shared fixtures: demo hands at a coarse resolution, built once per test session."""

import numpy as np
import pytest

from retarget_core.rig.demo_hands import DEMO_HANDS, demo_hand

COARSE = 0.004  # metres; coarse meshes keep the suite fast


@pytest.fixture(scope="session")
def demo_rigs():
    return {name: demo_hand(name, resolution=COARSE) for name in DEMO_HANDS}


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
