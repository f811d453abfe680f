"""handretarget grid: one small cell row per method, the tables, the report, and resuming."""

import csv
import json

import pytest

from retarget_core.errors import InputError
from retarget_core.evaluate.grid import run_grid, write_grid_tables


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
