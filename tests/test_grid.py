"""handretarget grid: one small cell row per method, the tables, the report, and resuming."""

import csv
import json

import pytest

from retarget_core.errors import InputError
from retarget_core.evaluate.grid import goals_missed, run_grid, write_grid_tables


@pytest.fixture(scope="module")
def grid(tmp_path_factory):
    out = tmp_path_factory.mktemp("grid")
    paths = run_grid(out, targets=["prosthetic_2dof"], clips=["box_pinch"], frames=40, workers=1, stride=10,
                     log=lambda *_: None)
    return out, paths


def test_grid_writes_every_cell_the_tables_and_the_report(grid):
    out, paths = grid
    rows = list(csv.DictReader(paths["grid.csv"].open()))
    assert [r["method"] for r in rows] == ["contacts", "fingertips", "keyvectors"]
    for r in rows:
        assert r["error"] == "" and float(r["contact_error_median_mm"]) >= 0
        cell = out / "cells" / "prosthetic_2dof" / "box_pinch" / r["method"]
        assert json.loads((cell / "metrics.json").read_text())["method"] == r["method"]
    page = paths["index.html"].read_text()
    for method in ("contacts", "fingertips", "keyvectors"):
        assert f"cells/prosthetic_2dof/box_pinch/{method}/intersection.png" in page
    assert "| prosthetic_2dof | box_pinch | contacts |" in paths["grid.md"].read_text()


def test_goals_are_judged_on_the_cells_figures():
    """Each goal at, just inside and just past its bound; the delivered curve against the solved
    frames' contact error; a figure that is absent is a missed goal, never a met one."""
    ok = {"hand_object_intersection_percent_median": 0.49, "penetration_mm_p95": 2.0,
          "self_intersection_percent_median": 0.0, "contact_error_median_mm": 3.3,
          "solved_contact_error_median_mm": 3.0}
    assert goals_missed(ok) == []
    assert goals_missed(None) is None
    assert goals_missed({**ok, "hand_object_intersection_percent_median": 0.5}) == ["hand-object < 0.5 % (0.5)"]
    assert goals_missed({**ok, "penetration_mm_p95": 2.01}) == ["penetration p95 <= 2 mm (2.01)"]
    assert goals_missed({**ok, "self_intersection_percent_median": 0.7}) == ["self < 0.5 % (0.7)"]
    assert goals_missed({**ok, "contact_error_median_mm": 3.31}) == ["delivered within 10 % of solved (3.31 vs 3)"]
    assert goals_missed({**ok, "contact_error_median_mm": 4.2, "solved_contact_error_median_mm": 4.1}) == \
        ["contact <= 4 mm (4.2)"]
    assert goals_missed({**ok, "penetration_mm_p95": None}) == ["penetration p95 <= 2 mm (unavailable)"]


def test_grid_reports_the_goals_of_our_cells(grid):
    out, paths = grid
    goals = json.loads(paths["goals.json"].read_text())
    summary = json.loads((out / "cells" / "prosthetic_2dof" / "box_pinch" / "contacts" / "metrics.json").read_text())
    missed = goals_missed(summary["summary"])
    assert goals["cells"] == 1 and goals["met"] == (1 if not missed else 0)
    assert goals["missed"] == ({} if not missed else {"prosthetic_2dof / box_pinch": missed})
    rows = {r["method"]: r for r in csv.DictReader(paths["grid.csv"].open())}
    assert rows["contacts"]["goals_missed"] == "; ".join(missed) and rows["keyvectors"]["goals_missed"] == ""
    assert f"{goals['met']} of 1 cells meet every one" in paths["grid.md"].read_text()


def test_grid_rerun_reuses_finished_cells(grid):
    out, _ = grid
    metrics = out / "cells" / "prosthetic_2dof" / "box_pinch" / "contacts" / "metrics.json"
    stamp = metrics.stat().st_mtime_ns
    said = []
    run_grid(out, targets=["prosthetic_2dof"], clips=["box_pinch"], frames=40, workers=1, stride=10, log=said.append)
    assert said == [] and metrics.stat().st_mtime_ns == stamp


def test_grid_table_marks_missing_cells_and_names_unknown_inputs(grid, tmp_path):
    out, _ = grid
    paths = write_grid_tables(out, ["prosthetic_2dof", "alien"], ["box_pinch"], ["contacts"])
    assert "| alien | box_pinch | contacts | n/a |" in paths["grid.md"].read_text()
    # a cell that never ran counts as missing its goals, not as meeting them
    assert "alien / box_pinch" in json.loads(paths["goals.json"].read_text())["missed"]
    with pytest.raises(InputError, match="unknown demo hand 'wizard'"):
        run_grid(tmp_path, targets=["wizard"])
    with pytest.raises(InputError, match="unknown method"):
        run_grid(tmp_path, targets=["alien"], methods=["telepathy"])


def test_compare_two_outputs_side_by_side(grid, tmp_path):
    from retarget_core.evaluate.compare import compare_outputs

    out, _ = grid
    cells = out / "cells" / "prosthetic_2dof" / "box_pinch"
    paths = compare_outputs(cells / "contacts", cells / "keyvectors", tmp_path / "cmp", worst=2)
    report = json.loads(paths["compare.json"].read_text())
    ours = json.loads((cells / "contacts" / "metrics.json").read_text())["summary"]
    assert report["summary"][report["names"][0]] == ours
    assert 1 <= len(report["worst_frames"]) <= 2
    for name in ("difference.png", "worst_frames.png"):
        assert paths[name].read_bytes()[:4] == b"\x89PNG"
    text = paths["compare.md"].read_text()
    assert "| contact_error_median_mm |" in text
    with pytest.raises(InputError, match="metrics.json"):
        compare_outputs(cells / "contacts", tmp_path, tmp_path / "cmp2")
