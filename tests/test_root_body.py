"""``--root-body`` picks the hand inside an MJCF model on every command that reads a target
(rig info, annotate propose, retarget), never silently: a root body for a file that is not
MJCF, or for a demo hand, is an error naming it."""

import json

import pytest

from installed_models import installed_or_none
from retarget_core.cli import main
from retarget_core.clip.demo import make_demo_clip, source_rig
from retarget_core.errors import InputError
from retarget_core.rig.io import resolve_rig

RES = 0.004
SHADOW = "installed:shadow@0.004"
SOURCE = f"demo:source_human@{RES}"

pytestmark = pytest.mark.skipif(installed_or_none("shadow") is None, reason="the Shadow hand wheel is not installed")


def test_propose_and_retarget_cut_the_shadow_hand_at_its_wrist(tmp_path):
    whole = resolve_rig(SHADOW)
    cut = resolve_rig(SHADOW, root_body="robot0:wrist")
    # the forearm and its mount carry no joints: the cut leaves the DOFs and drops their surface
    assert cut.dof_names == whole.dof_names
    assert cut.surface.n_vertices < 0.8 * whole.surface.n_vertices
    annotations = tmp_path / "shadow.json"
    assert main(["annotate", "propose", "--source", SOURCE, "--target", SHADOW, "--root-body", "robot0:wrist",
                 "--out", str(annotations)]) == 0
    clip = make_demo_clip("bottle_pick_place", time_scale=0.05, resolution=RES, rig=source_rig(RES))
    clip.save(tmp_path / "clip.npz")
    assert main(["retarget", "--clip", str(tmp_path / "clip.npz"), "--rig", SHADOW, "--root-body", "robot0:wrist",
                 "--annotations", str(annotations), "--source-rig", SOURCE, "--out", str(tmp_path / "out"),
                 "--workers", "1"]) == 0
    doc = json.loads((tmp_path / "out" / "result.json").read_text())
    assert doc["dof_names"] == cut.dof_names


def test_a_root_body_for_a_file_that_is_not_mjcf_is_an_error(tmp_path):
    leap = installed_or_none("leap")
    if leap is not None:
        with pytest.raises(InputError, match="not MJCF"):
            resolve_rig(str(leap), root_body="palm_lower")
    with pytest.raises(InputError, match="demo hand takes no rig options"):
        resolve_rig("demo:human_alt@0.005", root_body="wrist")
