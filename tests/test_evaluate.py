"""handretarget evaluate: metrics.json and plots of a retarget output, and its bad inputs."""

import contextlib
import io
import json
import shutil

import numpy as np
import pytest

from retarget_core.cli import main
from retarget_core.clip.demo import make_demo_clip, source_rig
from retarget_core.rig.demo_hands import demo_hand
from retarget_core.transfer.annotations import save_annotations
from retarget_core.transfer.propose import propose_annotations

RES = 0.004
TARGET = "prosthetic_2dof"
FAST = ["--set", "solver.maxeval=15", "--set", "solver.root_maxeval=10", "--set", "refinement.max_iterations=2",
        "--workers", "1"]


def run_cli(argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def outputs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("evaluate")
    source = source_rig(RES)
    target = demo_hand(TARGET, RES)
    make_demo_clip("bottle_pick_place", time_scale=0.05, resolution=RES, rig=source).save(folder / "clip.npz")
    save_annotations(propose_annotations(source, target), folder / "annotations.json")
    runs = {}
    for name, extra in (("splines", []), ("frames", ["--set", "passes.fit=false"]),
                        ("keyvectors", ["--set", "method=keyvectors"])):
        out = folder / name
        code, _, err = run_cli(["retarget", "--clip", str(folder / "clip.npz"), "--rig", f"demo:{TARGET}@{RES}",
                                "--annotations", str(folder / "annotations.json"), "--out", str(out), *FAST, *extra])
        assert code == 0, err
        runs[name] = out
    return runs


def test_evaluate_writes_metrics_and_plots(outputs):
    out = outputs["splines"]
    code, text, err = run_cli(["evaluate", str(out)])
    assert code == 0, err
    for name in ("metrics.json", "intersection.png", "contact_error.png", "contact_sheet.png", "preview.gif"):
        assert (out / name).stat().st_size > 0 and f"wrote {out / name}" in text
        if name.endswith(".png"):
            assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["format"] == "handretarget.metrics" and doc["method"] == "contacts"
    n = doc["frames"]
    assert n == 46
    for kind in ("hand_object", "self", "table"):
        series = doc["per_frame"]["intersection_percent"][kind]
        assert len(series) == n and all(v is None or v >= 0 for v in series)
    coverage = [v for v in doc["per_frame"]["contact_coverage"] if v is not None]
    assert coverage and all(0.0 <= v <= 1.0 for v in coverage)
    assert doc["summary"]["contact_frames"] > 0
    assert doc["hand_volume_m3"] > 0
    assert doc["version"] == 2


def test_intersection_figures_are_over_the_contact_frames(outputs):
    out = outputs["splines"]
    code, _, err = run_cli(["evaluate", str(out), "--no-render", "--stride", "3"])
    assert code == 0, err
    doc = json.loads((out / "metrics.json").read_text())
    s, per = doc["summary"], doc["per_frame"]
    assert s["intersection_over"] == "contact frames"
    with np.load(out / "scene.npz") as z:
        grasp = z["source_contact_count"] > 0
    assert 0 < grasp.sum() < doc["frames"]  # the approach has no contacts
    for key, values in (("hand_object_intersection_percent", per["intersection_percent"]["hand_object"]),
                        ("penetration_mm", per["penetration_mm"])):
        x = np.array([np.nan if v is None else v for v in values])
        at = x[grasp & np.isfinite(x)]
        assert len(at) > 3
        assert s[f"{key}_median"] == pytest.approx(np.median(at), abs=1e-12)
        assert s[f"{key}_max"] == pytest.approx(at.max(), abs=1e-12)
        assert s[f"{key}_median"] <= s[f"{key}_p95"] <= s[f"{key}_max"]
    depth = per["depth_mm"]
    both = [max(a, b) for a, b in zip(depth["hand_into_object"], depth["object_into_hand"]) if a is not None]
    assert both == [v for v in per["penetration_mm"] if v is not None]
    x = np.array([np.nan if v is None else v for v in per["penetration_mm"]])
    at = x[grasp & np.isfinite(x)]
    assert s["penetration_over_1mm_share"] == pytest.approx(np.mean(at > 1.0))


def test_contact_error_matches_the_retargets_own_figures_on_solved_frames(outputs):
    """Without a spline fit the evaluated motion is the solved frames, so evaluate's median
    contact error per frame must equal the one retarget reported for them."""
    out = outputs["frames"]
    code, _, err = run_cli(["evaluate", str(out), "--no-render", "--stride", "5"])
    assert code == 0, err
    doc = json.loads((out / "metrics.json").read_text())
    result = json.loads((out / "result.json").read_text())
    ours = np.array([np.nan if v is None else v for v in doc["per_frame"]["contact_error_median_mm"]])
    theirs = np.array([np.nan if v is None else v for v in result["contact_distance_mm"]])
    assert np.isfinite(ours).sum() > 10
    assert np.allclose(ours, theirs, equal_nan=True, rtol=0, atol=1e-5)  # mm
    inter = doc["per_frame"]["intersection_percent"]["hand_object"]
    assert all(v is None for i, v in enumerate(inter) if i % 5)  # stride: only every 5th frame measured
    assert all(v is not None for i, v in enumerate(inter) if i % 5 == 0)


def test_solved_frames_contact_error_is_the_retargets_own(outputs):
    """metrics.json keeps the solved frames' contact error beside the delivered curve's: the
    figure retarget printed for the frames the curves were fitted to (and, without a fit, the
    delivered figure itself)."""
    for name in ("splines", "frames"):
        out = outputs[name]
        code, _, err = run_cli(["evaluate", str(out), "--no-render", "--stride", "7"])
        assert code == 0, err
        s = json.loads((out / "metrics.json").read_text())["summary"]
        r = json.loads((out / "result.json").read_text())["summary"]
        # mm; the curves are evaluated again from result.json's knots and coefficients (1e-6 mm apart)
        assert s["solved_contact_error_median_mm"] == pytest.approx(r["solved_contact_distance_median_mm"], abs=1e-4)
        assert s["contact_error_median_mm"] == pytest.approx(r["contact_distance_median_mm"], abs=1e-4)
        if name == "frames":
            assert s["solved_contact_error_median_mm"] == pytest.approx(s["contact_error_median_mm"], abs=1e-9)


def test_baseline_output_is_evaluated_as_such(outputs):
    code, _, err = run_cli(["evaluate", str(outputs["keyvectors"]), "--no-render", "--stride", "9"])
    assert code == 0, err
    assert json.loads((outputs["keyvectors"] / "metrics.json").read_text())["method"] == "keyvectors"


@pytest.mark.parametrize("damage, message", [
    ("scene", "scene.npz"),
    ("version", "unsupported version"),
    ("rig", "rig file"),
    ("result", "no result.json"),
])
def test_bad_output_folders_are_named_errors(outputs, tmp_path, damage, message):
    out = tmp_path / "copy"
    shutil.copytree(outputs["frames"], out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    if damage == "scene":
        (out / "scene.npz").unlink()
    elif damage == "version":
        doc = json.loads((out / "result.json").read_text())
        doc["version"] = 99
        (out / "result.json").write_text(json.dumps(doc))
    elif damage == "rig":
        (out / "rig.usda").unlink()
    else:
        (out / "result.json").unlink()
    code, _, err = run_cli(["evaluate", str(out)])
    assert code == 2 and message in err, err
    assert {p.name for p in out.iterdir()} <= set(before)  # nothing new, no temporary files
    for p in out.iterdir():  # nothing that was there is changed
        if p.name in before and not (damage == "version" and p.name == "result.json"):
            assert p.read_bytes() == before[p.name]
