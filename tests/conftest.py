"""Shared fixtures: demo hands at a coarse resolution, built once per test session."""

import retarget_core  # noqa: F401  first, before numpy: it pins the numerical kernels (kernels.py)

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


@pytest.fixture(scope="session")
def solved_demo():
    """A short demo clip (46 frames of bottle_pick_place) onto human_alt at 6 mm cells, solved
    through the root and full passes with few evaluations: (problem, config, q (T, D))."""
    from retarget_core.clip.demo import make_demo_clip, source_rig
    from retarget_core.execute import Executor
    from retarget_core.pairing.dense import pair_contacts
    from retarget_core.pipeline import build_problem, root_pass, solve_pass
    from retarget_core.solve.config import load_config
    from retarget_core.transfer.propose import propose_annotations

    res = 0.006
    source, target = source_rig(res), demo_hand("human_alt", res)
    clip = make_demo_clip("bottle_pick_place", time_scale=0.05, resolution=res, rig=source)
    config = load_config(None, "default", {"solver.maxeval": 25, "solver.root_maxeval": 15})
    executor = Executor(workers=1)
    problem, _ = build_problem(clip, pair_contacts(clip), source, target, propose_annotations(source, target),
                               config, executor)
    with executor.frame_runner(problem) as runner:
        q, _ = root_pass(runner, problem, clip, config)
        q, _ = solve_pass(runner, np.arange(clip.n_frames), q, "full pass")
    return problem, config, q
