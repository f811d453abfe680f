"""The picture of proposed annotations (retarget_core/render/annotation_view.py) and
``handretarget annotate propose --png``."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from retarget_core.cli import main
from retarget_core.render.annotation_view import MARKER, draw_proposal
from retarget_core.rig.demo_hands import demo_hand
from retarget_core.transfer.annotations import resolve_points
from retarget_core.transfer.propose import propose
from tests.foreign_hands import foreign_demo, move, rigid, rot_x, rot_z

SIZE = (1400, 700)


@pytest.fixture(scope="module")
def target():
    return demo_hand("robot4", resolution=0.005)


@pytest.fixture(scope="module")
def drawn(tmp_path_factory, target):
    source = demo_hand("source_human", resolution=0.005)
    proposal = propose(source, target)
    path = tmp_path_factory.mktemp("view") / "proposal.png"
    picture = draw_proposal(proposal, path, source_rig=source, target_rig=target, size=SIZE)
    return proposal, source, picture, np.asarray(Image.open(path).convert("RGB"), dtype=np.float64)


def _halves(image):
    w = image.shape[1] // 2
    return image[:, :w], image[:, w:2 * w]


def test_png_has_the_requested_size_and_is_not_blank(drawn):
    _, _, picture, image = drawn
    assert picture.path.is_file()
    assert Image.open(picture.path).size == SIZE
    assert image.shape == (SIZE[1], SIZE[0], 3)
    assert image.std() > 20.0  # a blank (or single-colour) picture has ~0
    skin = (np.abs(image - np.array([226, 178, 146]) * 0.9).max(axis=2) < 40).mean()
    assert skin > 0.05  # the hands are shaded surfaces, not just lines


def test_the_two_panels_differ(drawn):
    left, right = _halves(drawn[3])
    assert np.abs(left - right).mean() > 10.0


def test_panels_look_at_the_palm_with_the_fingers_up(drawn):
    proposal, _, picture, _ = drawn
    for panel, model in zip(picture.panels, (proposal.source_model, proposal.target_model)):
        right, up, forward = panel.camera.basis()
        assert forward @ -model.palmar > 0.999  # looking along -palmar: at the palm
        assert up @ model.forward > 0.999
        _, _, back_forward = panel.back_camera.basis()
        assert back_forward @ model.palmar > 0.999


def test_marker_dots_are_drawn_at_their_projected_positions(drawn, target):
    proposal, source, picture, image = drawn
    background = image[5, SIZE[0] // 2 - 5]  # top right corner of the source panel
    assert np.abs(background - 255).max() < 1
    checked = 0
    for panel, rig, side in zip(picture.panels, (source, target), ("source", "target")):
        # every marker is drawn, from the palm or from the back
        assert set(panel.markers) | set(panel.back_markers) == {m.name for m in proposal.annotations.markers}
        for m in proposal.annotations.markers:
            point = getattr(m, side)[0]
            xyz = resolve_points([point], rig.surface.faces, rig.surface.n_vertices, what="m").positions(
                rig.surface.vertices, rig.surface.faces)
            for back, dots in ((False, panel.markers), (True, panel.back_markers)):
                if m.name not in dots:
                    continue
                expected = panel.project(xyz, back=back)[0]
                assert np.allclose(dots[m.name], expected, atol=0.5)
                x, y = int(expected[0]), int(expected[1])
                pixel = image[y, x]
                assert np.abs(pixel - MARKER).max() < 40, (side, m.name, back, pixel)
                assert np.abs(pixel - background).max() > 150
                checked += 1
    assert checked >= 30


def test_a_moved_hand_is_drawn_from_its_palm_side_too(tmp_path, drawn, target):
    rig, truth = foreign_demo("human_alt", 0.005)
    moved, _ = move(rig, truth, rigid(rot_z(110.0) @ rot_x(-65.0), [0.3, -0.2, 0.5]))
    images = []
    for i, source in enumerate((rig, moved)):
        p = propose(source, target)
        path = tmp_path / f"{i}.png"
        draw_proposal((p.annotations, source, target, p.source_model, p.target_model), path, size=SIZE)
        images.append(_halves(np.asarray(Image.open(path).convert("RGB"), dtype=np.float64))[0])
    same = np.abs(images[0] - images[1]).mean()
    other = np.abs(images[0] - _halves(drawn[3])[0]).mean()  # another hand (source_human), same layout
    assert other > 4.0
    assert same < 0.25 * other and same < 1.5, (same, other)


def test_cli_propose_png_writes_the_picture_next_to_the_json(tmp_path, capsys):
    out = tmp_path / "pair" / "annotations.json"
    assert main(["annotate", "propose", "--source", "demo:source_human@0.005", "--target", "demo:robot4@0.005",
                 "--out", str(out), "--png"]) == 0
    png = out.with_suffix(".png")
    assert out.is_file() and png.is_file()
    assert Image.open(png).size == (1600, 800)
    assert f"wrote {png}" in capsys.readouterr().out
