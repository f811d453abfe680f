"""Annotations that survive a mesh edit (issue 17 item 5): rest positions on points (format
version 2), a surface hash on the signatures, remapping onto an edited mesh by closest surface
point with the largest displacement reported and bounded, the ``annotate remap`` command and the
pipeline carrying annotations onto an edited rig."""

import contextlib
import dataclasses
import io
import json
import re

import igl
import jsonschema
import numpy as np
import pytest

from retarget_core.cli import main
from retarget_core.errors import InputError
from retarget_core.rig.demo_hands import demo_hand
from retarget_core.transfer.annotations import (
    annotations_schema,
    load_annotations,
    remap_to_meshes,
    resolve_points,
    save_annotations,
    surface_sha256,
    with_positions,
)
from retarget_core.transfer.propose import propose_annotations

RES, EDIT_RES = 0.005, 0.0045
TARGET = "human_alt"


@pytest.fixture(scope="module")
def hands():
    src, tgt = demo_hand("source_human", resolution=RES), demo_hand(TARGET, resolution=RES)
    src2, tgt2 = demo_hand("source_human", resolution=EDIT_RES), demo_hand(TARGET, resolution=EDIT_RES)
    plain = propose_annotations(src, tgt)
    return dict(src=src, tgt=tgt, src2=src2, tgt2=tgt2, plain=plain, placed=with_positions(plain, src, tgt))


def sites(a, side):
    return [(element, p) for s, element, p in a._point_sites() if s == side]


def geometry(a, side, rig):
    """(N, 3) positions of a side's points computed from their indices on ``rig`` (not from the
    stored positions)."""
    pts = resolve_points([p for _, p in sites(a, side)], rig.surface.faces, rig.surface.n_vertices, what=side)
    return pts.positions(rig.surface.vertices, rig.surface.faces)


def stored(a, side):
    return np.array([p.position for _, p in sites(a, side)], dtype=float)


def edited(rig, vertices):
    """``rig`` with its surface's vertices replaced (same faces, same counts)."""
    return dataclasses.replace(rig, surface=dataclasses.replace(rig.surface, vertices=vertices))


def validate(doc):
    jsonschema.Draft202012Validator(annotations_schema()).validate(doc)


# --- positions ----------------------------------------------------------------------------------
def test_with_positions_are_the_points_on_the_rigs(hands):
    placed, src, tgt = hands["placed"], hands["src"], hands["tgt"]
    for side, rig in (("source", src), ("target", tgt)):
        assert all(p.position is not None for _, p in sites(placed, side))
        assert np.abs(stored(placed, side) - geometry(hands["plain"], side, rig)).max() < 1e-12
        sig = getattr(placed, side)
        assert sig.surface_sha256 == surface_sha256(rig.surface.vertices, rig.surface.faces)
        assert (sig.vertices, sig.faces) == (rig.surface.n_vertices, len(rig.surface.faces))
    # a face point's position is its barycentric blend of the face's corners
    name, p = sites(hands["plain"], "source")[0]
    q = dict(sites(placed, "source"))[name]
    corners = src.surface.vertices[src.surface.faces[p.face]]
    assert np.allclose(q.position, np.asarray(p.barycentric) @ corners, atol=1e-15)
    assert q.face == p.face and q.barycentric == p.barycentric
    # the rigs the indices refer to: another mesh is refused
    with pytest.raises(InputError, match="annotations were made for rig"):
        with_positions(hands["plain"], hands["src2"], tgt)


def test_surface_hash_notices_a_same_count_edit(hands):
    src = hands["src"]
    v = src.surface.vertices.copy()
    h = surface_sha256(v, src.surface.faces)
    assert h == surface_sha256(v.copy(), src.surface.faces.copy())
    v[7, 2] += 1e-6
    assert surface_sha256(v, src.surface.faces) != h
    assert hands["placed"].source.matches(src.surface.vertices, src.surface.faces)
    assert not hands["placed"].source.matches(v, src.surface.faces)


# --- remapping ----------------------------------------------------------------------------------
def test_unchanged_meshes_are_kept(hands):
    a, report = remap_to_meshes(hands["placed"], hands["src"], hands["tgt"])
    assert a is hands["placed"] and not report.changed
    assert not report.source.remapped and report.source.moved == 0
    # without positions too: nothing to remap
    b, report = remap_to_meshes(hands["plain"], hands["src"], hands["tgt"])
    assert b is hands["plain"] and not report.changed


def test_remap_onto_a_rebuilt_mesh(hands):
    placed, src2, tgt2 = hands["placed"], hands["src2"], hands["tgt2"]
    assert src2.surface.n_vertices != hands["src"].surface.n_vertices  # really another mesh
    remapped, report = remap_to_meshes(placed, src2, tgt2)
    assert report.changed
    remapped.check_meshes(src2.surface.faces, src2.surface.n_vertices, tgt2.surface.faces, tgt2.surface.n_vertices)
    for side, rig in (("source", src2), ("target", tgt2)):
        side_report = getattr(report, side)
        old = stored(placed, side)
        new = geometry(remapped, side, rig)  # where the new indices really are
        moved = np.linalg.norm(new - old, axis=1) * 1e3
        assert side_report.remapped and side_report.points == len(old) == side_report.moved
        assert moved.max() <= side_report.max_displacement_mm + 1e-9  # every point within the reported max
        assert abs(moved.max() - side_report.max_displacement_mm) < 1e-9  # the report's max is the measured one
        assert side_report.worst == sites(placed, side)[int(np.argmax(moved))][0]
        assert 0.05 < side_report.max_displacement_mm < 1.5  # the same shape within ~1 mm
        assert np.abs(stored(remapped, side) - new).max() < 1e-12  # positions now on the new mesh
        assert all(not p.is_vertex for _, p in sites(remapped, side))
        sig = getattr(remapped, side)
        assert sig.surface_sha256 == surface_sha256(rig.surface.vertices, rig.surface.faces)
        # each new point is the closest surface point: no point of the new surface is nearer
        d2, _, _ = igl.point_mesh_squared_distance(old, rig.surface.vertices, rig.surface.faces)
        assert np.allclose(np.sqrt(d2) * 1e3, moved, atol=1e-9)
    text = "\n".join(report.lines())
    assert f"{report.source.max_displacement_mm:.3f} mm" in text and report.source.worst in text
    # remapping again onto the same meshes changes nothing
    again, report2 = remap_to_meshes(remapped, src2, tgt2)
    assert again is remapped and not report2.changed


def test_same_count_edit_of_half_a_millimetre(hands):
    placed, src, tgt = hands["placed"], hands["src"], hands["tgt"]
    normals = tgt.surface.vertex_normals()
    old = stored(placed, "target")
    # push the vertices within 15 mm of the first target point out by 0.5 mm along their normals
    near = np.linalg.norm(tgt.surface.vertices - old[0], axis=1) < 0.015
    assert 3 < near.sum() < 0.5 * tgt.surface.n_vertices
    vertices = tgt.surface.vertices + 0.0005 * normals * near[:, None]
    tgt_edit = edited(tgt, vertices)
    remapped, report = remap_to_meshes(placed, src, tgt_edit)
    assert report.target.remapped and not report.source.remapped
    new = geometry(remapped, "target", tgt_edit)
    moved = np.linalg.norm(new - old, axis=1) * 1e3
    assert abs(moved.max() - report.target.max_displacement_mm) < 1e-9
    assert 0.1 < report.target.max_displacement_mm <= 0.5 + 1e-6
    assert 0 < report.target.moved < report.target.points  # points far from the edit stay put
    assert report.target.moved == int((moved > 1e-6).sum())
    # a hash but a point without its position: refused, saying why
    unplaced = placed.map_points(lambda side, element, p: p.with_position(None) if element.endswith("target point 0")
                                 else p)
    with pytest.raises(InputError, match=r"surface_sha256 differs.*target point 0 has no position.*annotate remap"):
        remap_to_meshes(unplaced, src, tgt_edit)
    # a signature without the hash cannot see a same-count edit: kept as it is
    blind = dataclasses.replace(placed, target=dataclasses.replace(placed.target, surface_sha256=None))
    kept, report = remap_to_meshes(blind, src, tgt_edit)
    assert kept is blind and not report.changed


def test_five_millimetre_edit_is_refused_naming_the_point(hands):
    placed, src, tgt = hands["placed"], hands["src"], hands["tgt"]
    old = stored(placed, "target")
    names = [e for e, _ in sites(placed, "target")]
    k = next(i for i, e in enumerate(names) if e.startswith("marker"))
    near = np.linalg.norm(tgt.surface.vertices - old[k], axis=1) < 0.012
    vertices = tgt.surface.vertices + 0.005 * tgt.surface.vertex_normals() * near[:, None]
    tgt_edit = edited(tgt, vertices)
    d = np.sqrt(igl.point_mesh_squared_distance(old, tgt_edit.surface.vertices, tgt_edit.surface.faces)[0])
    worst = names[int(np.argmax(d))]
    assert d.max() > 0.003
    with pytest.raises(InputError) as info:
        remap_to_meshes(placed, src, tgt_edit)
    message = str(info.value)
    assert worst in message
    assert f"{d.max() * 1e3:.3f} mm" in message
    assert "3 mm allowed" in message and "--max-annotation-displacement-mm" in message
    assert "--max-displacement-mm" in message
    # a raised limit lets it through, reporting that displacement
    _, report = remap_to_meshes(placed, src, tgt_edit, max_displacement=0.006)
    assert abs(report.target.max_displacement_mm - d.max() * 1e3) < 1e-9 and report.target.worst == worst


def test_mismatch_without_positions_stays_an_error(hands, tmp_path):
    plain = hands["plain"]
    path = tmp_path / "v1.json"
    save_annotations(plain, path)
    doc = json.loads(path.read_text())
    assert doc["version"] == 1 and "surface_sha256" not in doc["source"]
    assert "position" not in json.dumps(doc)
    validate(doc)
    v1 = load_annotations(path)
    assert v1 == plain
    with pytest.raises(InputError, match=r"annotations were made for rig 'source_human'.*"
                                         r"handretarget annotate remap ANNOTATIONS --source RIG") as info:
        remap_to_meshes(v1, hands["src2"], hands["tgt2"])
    assert "survive mesh edits" in str(info.value)
    with pytest.raises(InputError, match=r"another rig\?; if the rig's mesh was edited, re-save"):
        v1.check_meshes(hands["src2"].surface.faces, hands["src2"].surface.n_vertices,
                        hands["tgt"].surface.faces, hands["tgt"].surface.n_vertices)


def test_round_trip_keeps_positions_and_validates(hands, tmp_path):
    placed = hands["placed"]
    path = tmp_path / "v2.json"
    save_annotations(placed, path)
    doc = json.loads(path.read_text())
    assert doc["version"] == 2
    assert re.fullmatch("[0-9a-f]{64}", doc["target"]["surface_sha256"])
    assert len(doc["markers"][0]["source"][0]["position"]) == 3
    validate(doc)
    back = load_annotations(path)
    assert back == placed
    assert np.array_equal(stored(back, "target"), stored(placed, "target"))
    remapped, _ = remap_to_meshes(placed, hands["src2"], hands["tgt2"])
    save_annotations(remapped, tmp_path / "remapped.json")
    validate(json.loads((tmp_path / "remapped.json").read_text()))
    assert load_annotations(tmp_path / "remapped.json") == remapped
    # the schema checks the new fields
    bad = json.loads(json.dumps(doc))
    bad["markers"][0]["source"][0]["position"] = [0.0, 1.0]
    with pytest.raises(jsonschema.ValidationError):
        validate(bad)
    bad = json.loads(json.dumps(doc))
    bad["source"]["surface_sha256"] = "xyz"
    with pytest.raises(jsonschema.ValidationError):
        validate(bad)
    with pytest.raises(InputError, match="surface_sha256"):
        from retarget_core.transfer.annotations import annotations_from_dict
        annotations_from_dict(bad)


# --- the command and the pipeline ---------------------------------------------------------------
def run_cli(argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


def test_annotate_remap_command(hands, tmp_path):
    old = tmp_path / "old.json"
    save_annotations(hands["plain"], old)  # version 1, no positions
    # against the rigs they were made for: positions added
    placed = tmp_path / "placed.json"
    code, out, err = run_cli(["annotate", "remap", str(old), "--source", f"demo:source_human@{RES}",
                              "--target", f"demo:{TARGET}@{RES}", "--out", str(placed)])
    assert code == 0, err
    assert "positions added" in out and load_annotations(placed) == hands["placed"]
    # onto the rebuilt meshes: remapped, the report printed
    new = tmp_path / "new.json"
    code, out, err = run_cli(["annotate", "remap", str(placed), "--source", f"demo:source_human@{EDIT_RES}",
                              "--target", f"demo:{TARGET}@{EDIT_RES}", "--out", str(new)])
    assert code == 0, err
    expected, report = remap_to_meshes(hands["placed"], hands["src2"], hands["tgt2"])
    assert load_annotations(new) == expected
    assert f"largest displacement {report.target.max_displacement_mm:.3f} mm" in out
    # a tight limit refuses, naming the option
    code, out, err = run_cli(["annotate", "remap", str(placed), "--source", f"demo:source_human@{EDIT_RES}",
                              "--target", f"demo:{TARGET}@{EDIT_RES}", "--out", str(tmp_path / "x.json"),
                              "--max-displacement-mm", "0.01"])
    assert code != 0 and "0.01 mm allowed" in err and not (tmp_path / "x.json").exists()


def test_retarget_runs_on_an_edited_target_mesh(tmp_path):
    from retarget_core.clip.demo import make_demo_clip, source_rig

    target_name = "prosthetic_1dof"
    source = source_rig(RES)
    clip = make_demo_clip("bottle_pick_place", time_scale=0.05, resolution=RES, rig=source)
    clip.save(tmp_path / "clip.npz")
    target = demo_hand(target_name, RES)
    save_annotations(with_positions(propose_annotations(source, target), source, target), tmp_path / "a.json")
    edited_spec = f"demo:{target_name}@{EDIT_RES}"
    assert demo_hand(target_name, EDIT_RES).surface.n_vertices != target.surface.n_vertices
    argv = ["retarget", "--clip", str(tmp_path / "clip.npz"), "--rig", edited_spec, "--annotations",
            str(tmp_path / "a.json"), "--source-rig", f"demo:source_human@{RES}", "--out", str(tmp_path / "out"),
            "--frames", "0:8", "--set", "solver.maxeval=5", "--set", "solver.root_maxeval=5",
            "--set", "refinement.max_iterations=0", "--workers", "1"]
    code, out, err = run_cli(argv)
    assert code == 0, err
    assert re.search(r"annotations: target: mesh of rig '.*' changed .* largest displacement \d+\.\d{3} mm", out)
    doc = json.loads((tmp_path / "out" / "result.json").read_text())
    remap = doc["provenance"]["annotation_remap"]
    assert remap["target"]["remapped"] and not remap["source"]["remapped"]
    assert 0 < remap["target"]["max_displacement_mm"] < 3
    # a limit below the move is refused before any work, naming the option
    code, out, err = run_cli(argv + ["--max-annotation-displacement-mm", "0.001"])
    assert code != 0 and "--max-annotation-displacement-mm" in err
