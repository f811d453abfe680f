"""The handretarget command: rig demo writes every demo hand, rig info describes each file, every
command has its --help, and the job service is imported only when serve or token runs."""

import argparse
import json
import os
import re
import subprocess
import sys
from pathlib import Path

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


@pytest.fixture(scope="module")
def clip_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("clips")
    assert main(["clip", "demo", "--out", str(out), "--clip", "box_pinch", "--time-scale", "0.1"]) == 0
    return out


def test_clip_demo_info_render_and_pair(clip_dir, capsys, tmp_path):
    path = clip_dir / "box_pinch.npz"
    assert path.is_file()
    assert main(["clip", "info", str(path)]) == 0
    assert "valid" in capsys.readouterr().out
    png = tmp_path / "strip.png"
    assert main(["clip", "render", str(path), "--out", str(png), "--count", "3", "--size", "160x120"]) == 0
    from PIL import Image

    assert Image.open(png).size == (3 * 160, 120)
    capsys.readouterr()
    assert main(["clip", "pair", str(path), "--out", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    assert re.search(r"box_pinch\.npz\s+\d+\s+\d+", text) and "worst discarded fraction" in text
    assert (tmp_path / "box_pinch.pairs.npz").is_file()


def test_unknown_demo_clip_is_a_clear_error(tmp_path, capsys):
    assert main(["clip", "demo", "--out", str(tmp_path), "--clip", "juggling"]) == 2
    assert "unknown demo clip 'juggling'" in capsys.readouterr().err


def test_import_grab_reports_a_missing_file(tmp_path, capsys):
    code = main(["import-grab", str(tmp_path / "seq.npz"), "--mano", str(tmp_path / "MANO_RIGHT.pkl"),
                 "--out", str(tmp_path / "c.npz")])
    assert code == 2
    assert "seq.npz" in capsys.readouterr().err


def test_import_grab_command_end_to_end(tmp_path, capsys):
    from grab_fixtures import make_grab_sequence, make_mano_raw, write_grab_npz, write_mano_official

    from retarget_core.clip import load_clip

    # a MANO-format file whose triangles are no hand surface: refused, saying why (no source rig)
    raw = make_mano_raw(0)
    mano = write_mano_official(tmp_path / "MANO_RIGHT.pkl", raw)
    seq = make_grab_sequence(tmp_path, raw)
    sequence = write_grab_npz(tmp_path / "grab" / "s1" / "apple_eat_1.npz", seq)
    out = tmp_path / "apple.npz"
    assert main(["import-grab", str(sequence), "--mano", str(mano), "--grab-root", str(tmp_path), "--out", str(out)]) == 2
    assert "do not form a hand surface" in capsys.readouterr().err and not out.exists()
    # the hand-shaped model: the clip and its MANO source rig beside it
    from mano_hand import make_hand_mano_raw

    raw = make_hand_mano_raw()
    (tmp_path / "hand").mkdir()
    mano = write_mano_official(tmp_path / "hand" / "MANO_RIGHT.pkl", raw)
    seq = make_grab_sequence(tmp_path / "hand", raw)
    sequence = write_grab_npz(tmp_path / "hand" / "grab" / "s1" / "apple_eat_1.npz", seq)
    assert main(["import-grab", str(sequence), "--mano", str(mano), "--grab-root", str(tmp_path / "hand"),
                 "--out", str(out)]) == 0
    assert f"wrote {out.with_name('apple.source_rig.usda')}" in capsys.readouterr().out
    clip = load_clip(out)
    assert clip.n_frames == 6 and clip.object_name == "apple" and len(clip.marker_names) == 25
    assert clip.source_rig == "apple.source_rig.usda" and len(clip.source_rig_sha256) == 64


def test_annotate_propose_and_transfer_commands(clip_dir, tmp_path, capsys):
    annotations = tmp_path / "alien.json"
    assert main(["annotate", "propose", "--source", "demo:source_human@0.004", "--target", "demo:alien@0.006",
                 "--out", str(annotations)]) == 0
    text = capsys.readouterr().out
    assert "discarded ring, pinky" in text
    assert main(["transfer", "--clip", str(clip_dir / "box_pinch.npz"), "--rig", "demo:alien@0.006",
                 "--annotations", str(annotations), "--out", str(tmp_path / "out")]) == 0
    text = capsys.readouterr().out
    assert re.search(r"box_pinch\s+\d+\s+[\d.]+%", text)
    report = json.loads((tmp_path / "out" / "box_pinch.transfer.json").read_text())
    assert report["contacts"] > 0 and 0.0 <= report["transferred_share"] <= 1.0
    assert (tmp_path / "out" / "box_pinch.transfer.png").is_file()
    # the paper preset's charts alone: each patch as the atlas sizes it; the default keeps the
    # source's patch size, so its spread is no further from the source's
    assert main(["transfer", "--clip", str(clip_dir / "box_pinch.npz"), "--rig", "demo:alien@0.006",
                 "--annotations", str(annotations), "--out", str(tmp_path / "paper"), "--preset", "paper"]) == 0
    paper = json.loads((tmp_path / "paper" / "box_pinch.transfer.json").read_text())
    assert paper["contacts"] == report["contacts"]
    assert abs(report["spread_ratio_median"] - 1) <= abs(paper["spread_ratio_median"] - 1) + 1e-9, (report, paper)


def test_transfer_with_annotations_for_another_rig_is_a_clear_error(clip_dir, tmp_path, capsys):
    annotations = tmp_path / "witch.json"
    assert main(["annotate", "propose", "--source", "demo:source_human@0.004", "--target", "demo:witch@0.006",
                 "--out", str(annotations)]) == 0
    capsys.readouterr()
    assert main(["transfer", "--clip", str(clip_dir / "box_pinch.npz"), "--rig", "demo:alien@0.006",
                 "--annotations", str(annotations)]) == 2
    assert "another rig" in capsys.readouterr().err


def test_a_control_rate_on_a_hand_that_is_no_robot_is_refused_before_the_run(clip_dir, tmp_path, capsys):
    annotations = tmp_path / "alien.json"
    assert main(["annotate", "propose", "--source", "demo:source_human@0.004", "--target", "demo:alien@0.006",
                 "--out", str(annotations)]) == 0
    capsys.readouterr()
    out = tmp_path / "out"
    assert main(["retarget", "--clip", str(clip_dir / "box_pinch.npz"), "--rig", "demo:alien@0.006",
                 "--annotations", str(annotations), "--out", str(out), "--rate", "100"]) == 2
    err = capsys.readouterr().err
    assert "--rate" in err and "not a URDF or MJCF robot" in err
    assert not out.exists()  # refused before anything ran or was written


# -- the command line as a package: every command registered, --help everywhere, the service
# -- imported only when serve/token run and a failed import shown

HANDRETARGET = Path(sys.executable).with_name("handretarget")
COMMANDS = ["demo", "rig", "clip", "import-grab", "annotate", "transfer", "transfer-demo", "retarget",
            "retarget-keypoints", "batch", "evaluate", "grid", "compare", "bench", "serve", "token"]


def _command_paths(parser=None, path=()):
    """Every (sub-)command of ``handretarget`` as a tuple of words, the bare command included."""
    from retarget_core.cli import build_parser

    parser = parser or build_parser()
    yield path
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                yield from _command_paths(child, path + (name,))


def _run(args, cwd, env=None):
    return subprocess.run(args, capture_output=True, text=True, check=False, cwd=cwd, timeout=120,
                          env={**os.environ, **(env or {})})


def test_help_lists_every_command_group(tmp_path):
    result = _run([str(HANDRETARGET), "--help"], tmp_path)
    assert result.returncode == 0, result.stderr
    listed = re.search(r"\{([^}]*)\}", result.stdout).group(1).split(",")
    assert listed == COMMANDS


@pytest.mark.parametrize("words", list(_command_paths()), ids=lambda w: " ".join(w) or "handretarget")
def test_every_sub_command_help_exits_0(words, tmp_path):
    result = _run([sys.executable, "-m", "retarget_core.cli", *words, "--help"], tmp_path)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith(f"usage: handretarget {' '.join(words)}".rstrip()), result.stdout


def _shadow_server(tmp_path, body: str) -> dict:
    """An environment whose ``server`` package is one whose __init__ runs ``body``."""
    (tmp_path / "shadow" / "server").mkdir(parents=True)
    (tmp_path / "shadow" / "server" / "__init__.py").write_text(body + "\n")
    return {"PYTHONPATH": str(tmp_path / "shadow")}


@pytest.mark.parametrize("words", [["serve"], ["token", "create", "alice"]])
def test_a_failed_service_import_is_shown_with_exit_2(words, tmp_path):
    env = _shadow_server(tmp_path, 'raise ImportError("boom")')
    result = _run([str(HANDRETARGET), *words, "--data-dir", str(tmp_path / "data")], tmp_path, env)
    assert result.returncode == 2, (result.stdout, result.stderr)
    assert result.stderr.startswith("handretarget: error: the job service needs its dependencies (")
    assert result.stderr.rstrip().endswith(": boom")
    assert not (tmp_path / "data").exists()


def test_another_exception_in_the_service_import_is_not_swallowed(tmp_path):
    env = _shadow_server(tmp_path, 'raise RuntimeError("kaboom")')
    result = _run([str(HANDRETARGET), "serve"], tmp_path, env)
    assert result.returncode == 1
    assert "Traceback" in result.stderr and "RuntimeError: kaboom" in result.stderr
    assert "needs its dependencies" not in result.stderr


def test_the_help_of_serve_needs_no_service(tmp_path):
    env = _shadow_server(tmp_path, 'raise ImportError("boom")')
    result = _run([str(HANDRETARGET), "serve", "--help"], tmp_path, env)
    assert result.returncode == 0 and "--atlas-cache-mb" in result.stdout, result.stderr


def test_importing_the_cli_imports_neither_the_service_nor_fastapi(tmp_path):
    code = ("import sys, retarget_core.cli as cli; cli.build_parser(); "
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'server', 'fastapi', 'uvicorn', 'numpy'}))")
    result = _run([sys.executable, "-c", code], tmp_path)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"


def test_bench_refuses_a_negative_speedup_frame_count(capsys):
    """``--speedup-frames 0`` skips the gradient speed-up (the bench prints "not measured");
    a negative count is refused by the parser with the reason, before any work."""
    from retarget_core.cli import build_parser

    assert build_parser().parse_args(["bench", "--speedup-frames", "0"]).speedup_frames == 0
    with pytest.raises(SystemExit) as stop:
        build_parser().parse_args(["bench", "--speedup-frames", "-2"])
    assert stop.value.code == 2
    assert "must be 0 or more, got -2" in capsys.readouterr().err


def test_demo_runs_every_stage_and_writes_each_hands_pictures(tmp_path, capsys):
    """The README's main job end to end (one hand, one short clip, coarse meshes): every stage
    runs through the command line's own parser, and the retarget summary links the pictures."""
    out = tmp_path / "demo"
    assert main(["demo", "--hand", "nobody", "--out", str(out)]) == 2
    assert "no demo hand nobody" in capsys.readouterr().err and not out.exists()
    assert main(["demo", "--out", str(out), "--clip", "box_pinch", "--time-scale", "0.1", "--resolution", "0.006",
                 "--hand", "prosthetic_1dof"]) == 0
    assert (out / "rigs" / "prosthetic_1dof.usda").is_file() and (out / "clips" / "box_pinch.png").is_file()
    assert (out / "annotations" / "prosthetic_1dof.json").is_file()
    assert any((out / "transfer" / "prosthetic_1dof").iterdir())
    hand = out / "retarget" / "prosthetic_1dof"
    for name in ("animation.usda", "result.json", "contact_sheet.png", "preview.gif", "pictures.json"):
        assert (hand / name).stat().st_size > 0, name
    summary = (out / "retarget" / "summary.md").read_text()
    assert "[contact sheet](prosthetic_1dof/contact_sheet.png), [preview](prosthetic_1dof/preview.gif)" in summary
    page = (out / "retarget" / "index.html").read_text()
    assert "src='prosthetic_1dof/contact_sheet.png'" in page and "src='prosthetic_1dof/preview.gif'" in page
