"""The handretarget command: rig demo writes every demo hand, rig info describes each file."""

import json
import re
import subprocess
import sys

import pytest

from retarget_core.cli import main
from retarget_core.rig.demo_hands import DEMO_HANDS


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("rigs")
    assert main(["rig", "demo", "--out", str(out), "--resolution", "0.005"]) == 0
    return out


def test_rig_demo_writes_every_demo_hand(demo_dir):
    assert sorted(p.stem for p in demo_dir.glob("*.usda")) == sorted(DEMO_HANDS)


@pytest.mark.parametrize("name", list(DEMO_HANDS))
def test_rig_info_prints_dof_count_and_closed_manifold(demo_dir, capsys, name):
    assert main(["rig", "info", str(demo_dir / f"{name}.usda")]) == 0
    text = capsys.readouterr().out
    assert re.search(rf"DOFs: {DEMO_HANDS[name][1]}\b", text)
    assert re.search(r"surface: \d+ vertices, \d+ faces, closed, manifold", text)


def test_rig_info_json(demo_dir, capsys):
    assert main(["rig", "info", "--json", str(demo_dir / "alien.usda")]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["n_dofs"] == 42 and info["surface"]["closed"] and info["surface"]["manifold"]


def test_rig_info_on_a_missing_file_is_a_clear_error(tmp_path, capsys):
    assert main(["rig", "info", str(tmp_path / "nope.usda")]) == 2
    assert "nope.usda: no such file" in capsys.readouterr().err


def test_console_script_runs_as_a_real_process(demo_dir):
    result = subprocess.run(
        [sys.executable, "-m", "retarget_core.cli", "rig", "info", str(demo_dir / "robot4.usda")],
        capture_output=True, text=True, check=False,
    )
    assert result.returncode == 0, result.stderr
    assert "DOFs: 22" in result.stdout


def test_every_demo_hand_file_passes_usd_compliance(demo_dir):
    from retarget_core.rig.usd_io import check_usd_compliance

    for path in sorted(demo_dir.glob("*.usda")):
        assert check_usd_compliance(path) == [], path.name
