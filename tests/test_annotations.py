"""Artist annotations (virtual markers, axial curves): format, schema, semantics, mesh checks."""

import copy
import json

import jsonschema
import numpy as np
import pytest

from retarget_core.errors import InputError
from retarget_core.transfer.annotations import (
    Annotations,
    AxialCurveAnnotation,
    CurveTarget,
    LambdaS,
    MarkerPair,
    MeshSignature,
    PointRef,
    annotations_from_dict,
    annotations_schema,
    annotations_to_dict,
    load_annotations,
    resolve_points,
    save_annotations,
)

EXAMPLE = {
    "format": "handretarget.annotations",
    "version": 1,
    "source": {"rig": "source_human", "vertices": 3784, "faces": 7564},
    "target": {"rig": "alien", "vertices": 9000, "faces": 17996},
    "landmark_spacing": 0.002,
    "markers": [
        {
            "name": "IndexTip",
            "source": [{"vertex": 316}],
            "target": [{"face": 10, "barycentric": [0.2, 0.3, 0.5]}, {"vertex": 77}],
        },
        {"name": "ThumbTip", "source": [{"vertex": 12}], "target": [{"vertex": 13}]},
        {
            "name": "Palm",
            "source": [{"vertex": 1}, {"vertex": 2}, {"vertex": 3}],
            "target": [{"vertex": 4}],
        },
        {
            "name": "Back",
            "source": [{"vertex": 5}, {"face": 6, "barycentric": [1.0, 0.0, 0.0]}],
            "target": [{"vertex": 7}, {"vertex": 8}],
        },
    ],
    "axial_curves": [
        {
            "name": "index",
            "source": {"start": {"vertex": 1}, "end": {"face": 4, "barycentric": [1, 0, 0]}},
            "target": {"start": {"vertex": 9}, "direction": {"vertex": 30}, "lambda_a": 1.27, "lambda_s": 1.5},
        },
        {"name": "ring", "source": {"start": {"vertex": 5}, "end": {"vertex": 6}}, "target": "discard"},
        {
            "name": "thumb",
            "source": {"points": [{"vertex": 1}, {"vertex": 2}, {"vertex": 3}]},
            "target": {
                "start": {"vertex": 9},
                "direction": {"vertex": 30},
                "lambda_a": 1.0,
                "lambda_s": {"angles_deg": [0, 90, 180, 270], "values": [1.0, 1.4, 1.0, 1.4]},
                "through": [{"vertex": 30}, {"face": 31, "barycentric": [0.5, 0.25, 0.25]}],
            },
        },
    ],
}


def example():
    return copy.deepcopy(EXAMPLE)


def grid_mesh(n_vertices: int) -> np.ndarray:
    """Faces (F, 3) of a triangle strip using every one of n_vertices vertices."""
    i = np.arange(n_vertices - 2)
    return np.column_stack([i, i + 1, i + 2])


def bad(data, match):
    with pytest.raises(InputError, match=match):
        annotations_from_dict(data, source="test.json")


# --- round trip ---------------------------------------------------------------------------------


def test_dict_round_trip():
    a = annotations_from_dict(example())
    assert annotations_to_dict(a) == EXAMPLE
    assert annotations_from_dict(annotations_to_dict(a)) == a
    assert a.source == MeshSignature("source_human", 3784, 7564)
    assert a.target.rig == "alien"
    assert a.landmark_spacing == 0.002
    assert [m.name for m in a.markers] == ["IndexTip", "ThumbTip", "Palm", "Back"]
    assert a.marker("IndexTip").target[0] == PointRef(face=10, barycentric=(0.2, 0.3, 0.5))
    index, ring, thumb = a.curves
    assert index.source_start == PointRef(vertex=1) and index.source_points is None
    assert index.target.lambda_a == 1.27 and index.target.lambda_s.uniform == 1.5
    assert ring.discard and ring.target is None
    assert not index.discard
    assert thumb.is_polyline and len(thumb.source_points) == 3
    assert thumb.target.lambda_s.uniform is None
    assert thumb.target.through == (PointRef(vertex=30), PointRef(face=31, barycentric=(0.5, 0.25, 0.25)))
    assert index.target.through is None and "through" not in annotations_to_dict(a)["axial_curves"][0]["target"]


def test_default_landmark_spacing():
    data = example()
    del data["landmark_spacing"]
    assert annotations_from_dict(data).landmark_spacing == 0.002


def test_file_round_trip(tmp_path):
    a = annotations_from_dict(example())
    path = tmp_path / "sub" / "pair.annotations.json"
    save_annotations(a, path)
    text = path.read_text()
    assert text.startswith("{\n  ")  # pretty
    assert json.loads(text) == EXAMPLE
    b = load_annotations(path)
    assert b == a
    # exact: saving again produces the same bytes
    save_annotations(b, tmp_path / "again.json")
    assert (tmp_path / "again.json").read_text() == text
    assert not [p for p in (tmp_path / "sub").iterdir() if p.name != "pair.annotations.json"]


def test_round_trip_of_constructed_annotations(tmp_path):
    a = Annotations(
        MeshSignature("s", 10, 8),
        MeshSignature("t", 10, 8),
        [MarkerPair("m", [PointRef(vertex=1)], [PointRef(face=2, barycentric=(0.1, 0.2, 0.7))])],
        [
            AxialCurveAnnotation(
                "c",
                source_points=[PointRef(vertex=0), PointRef(vertex=3)],
                target=CurveTarget(PointRef(vertex=1), PointRef(vertex=2), 0.9, LambdaS.piecewise([10.5, 200], [0.7, 1.3])),
            )
        ],
        landmark_spacing=0.0015,
    )
    save_annotations(a, tmp_path / "a.json")
    assert load_annotations(tmp_path / "a.json") == a


# --- markers ------------------------------------------------------------------------------------


def test_marker_kinds_and_pairs():
    v = [PointRef(vertex=i) for i in range(4)]
    one = MarkerPair("a", [v[0]], [v[1]])
    assert one.kind == "one-to-one" and one.pairs() == [(0, 0)]
    to_many = MarkerPair("b", [v[0]], v[1:4])
    assert to_many.kind == "one-to-many" and to_many.pairs() == [(0, 0), (0, 1), (0, 2)]
    from_many = MarkerPair("c", v[:3], [v[3]])
    assert from_many.kind == "many-to-one" and from_many.pairs() == [(0, 0), (1, 0), (2, 0)]
    area = MarkerPair("d", v[:2], v[2:4])
    assert area.kind == "area-to-area" and area.pairs() == [(0, 0), (1, 1)]
    a = annotations_from_dict(example())
    assert [m.kind for m in a.markers] == ["one-to-many", "one-to-one", "many-to-one", "area-to-area"]


def test_marker_2_and_3_points_is_an_error():
    with pytest.raises(InputError, match="2 source points and 3 target points"):
        MarkerPair("x", [PointRef(vertex=0)] * 2, [PointRef(vertex=1)] * 3)
    data = example()
    data["markers"][3]["target"].append({"vertex": 9})
    bad(data, r"markers\[3\].*'Back'.*2 source points and 3 target points")


# --- points -------------------------------------------------------------------------------------


def test_resolve_points_vertices_and_faces():
    faces = np.array([[0, 1, 2], [2, 1, 3], [3, 4, 2]])
    pts = resolve_points(
        [PointRef(vertex=3), PointRef(face=2, barycentric=(0.2, 0.3, 0.5)), PointRef(vertex=0)],
        faces, 5, what="marker 'm' target",
    )
    assert pts.faces.tolist() == [1, 2, 0]
    assert np.allclose(pts.barycentric, [[0, 0, 1], [0.2, 0.3, 0.5], [1, 0, 0]])
    verts = np.arange(15, dtype=float).reshape(5, 3)
    assert np.allclose(pts.positions(verts, faces)[0], verts[3])
    single = PointRef(vertex=4).to_surface_points(faces)
    assert single.faces.tolist() == [2] and np.allclose(single.barycentric, [[0, 1, 0]])


def test_resolve_points_errors_name_the_point():
    faces = grid_mesh(3784)
    pts = [PointRef(vertex=1), PointRef(vertex=2), PointRef(vertex=99999)]
    with pytest.raises(InputError, match=r"marker 'IndexTip' target point 2: vertex 99999 out of range \[0, 3784\)"):
        resolve_points(pts, faces, 3784, what="marker 'IndexTip' target")
    with pytest.raises(InputError, match=r"point 0: face 5000 out of range"):
        resolve_points([PointRef(face=5000, barycentric=(1, 0, 0))], faces, 3784, what="curve")
    with pytest.raises(InputError, match="used by no face"):
        resolve_points([PointRef(vertex=3)], np.array([[0, 1, 2]]), 4, what="curve")


def test_barycentric_not_summing_to_one():
    with pytest.raises(InputError, match="sums to"):
        PointRef(face=0, barycentric=(0.5, 0.5, 0.5))
    data = example()
    data["markers"][0]["target"][0]["barycentric"] = [0.2, 0.3, 0.4]
    bad(data, r"test\.json: markers\[0\]\.target\[0\]: .*sums to 0\.9")


def test_negative_barycentric_and_mixed_point():
    data = example()
    data["markers"][0]["target"][0]["barycentric"] = [-0.5, 1.0, 0.5]
    bad(data, r"markers\[0\]\.target\[0\]\.barycentric\[0\]")
    data = example()
    data["markers"][0]["source"][0] = {"vertex": 1, "face": 2}
    bad(data, r"markers\[0\]\.source\[0\]")


def test_integral_float_index_is_accepted():
    data = example()
    data["markers"][1]["target"][0]["vertex"] = 13.0
    assert annotations_from_dict(data).marker("ThumbTip").target[0] == PointRef(vertex=13)


def test_point_out_of_signature_range_at_load():
    data = example()
    data["markers"][1]["target"][0]["vertex"] = 9000
    bad(data, r"markers\[1\]\.target\[0\]: vertex 9000 out of range \[0, 9000\)")


# --- lambda_s -----------------------------------------------------------------------------------


def test_lambda_s_piecewise_interpolation():
    ls = LambdaS.piecewise([0, 90, 180, 270], [1.0, 1.4, 1.0, 1.4])
    assert ls.uniform is None
    assert np.allclose(ls.angles, np.deg2rad([0, 90, 180, 270]))
    assert ls.values.tolist() == [1.0, 1.4, 1.0, 1.4]
    deg = np.deg2rad
    # at knots
    assert np.allclose(ls(deg(np.array([0, 90, 180, 270]))), [1.0, 1.4, 1.0, 1.4])
    # between knots
    assert np.isclose(ls(deg(45.0)), 1.2)
    assert np.isclose(ls(deg(135.0)), 1.2)
    # periodic wrap between the last knot (270) and 360 == first knot (0)
    assert np.isclose(ls(deg(315.0)), 1.2)
    assert np.isclose(ls(deg(-45.0)), 1.2)
    assert np.isclose(ls(deg(360.0 + 90.0)), 1.4)
    # vectorised, shape preserved
    out = ls(deg(np.array([[0.0, 45.0], [315.0, 337.5]])))
    assert out.shape == (2, 2) and np.allclose(out, [[1.0, 1.2], [1.2, 1.1]])


def test_lambda_s_wrap_with_knots_not_at_zero():
    ls = LambdaS.piecewise([90, 300], [2.0, 4.0])
    # wrap interval 300 -> 450 (== 90): length 150 degrees
    assert np.isclose(ls(np.deg2rad(0.0)), 4.0 + (2.0 - 4.0) * 60 / 150)
    assert np.isclose(ls(np.deg2rad(30.0)), 4.0 + (2.0 - 4.0) * 90 / 150)
    assert np.isclose(ls(np.deg2rad(195.0)), 3.0)


def test_lambda_s_uniform_and_single_knot():
    ls = LambdaS.constant(1.5)
    assert ls.uniform == 1.5
    theta = np.linspace(-7, 7, 11)
    assert np.all(ls(theta) == 1.5) and ls(theta).shape == theta.shape
    one = LambdaS.piecewise([30], [0.8])
    assert np.allclose(one(theta), 0.8)


def test_lambda_s_from_file():
    a = annotations_from_dict(example())
    thumb = a.curve("thumb")
    assert np.isclose(thumb.target.lambda_s(np.deg2rad(45.0)), 1.2)


# --- schema -------------------------------------------------------------------------------------


def test_schema_is_published_and_valid(tmp_path):
    from importlib import resources

    schema = annotations_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    shipped = resources.files("retarget_core.transfer").joinpath("annotations.schema.json")
    assert json.loads(shipped.read_text()) == schema
    jsonschema.Draft202012Validator(schema).validate(EXAMPLE)
    # a copy each call
    schema["title"] = "changed"
    assert annotations_schema()["title"] != "changed"


# --- bad input ----------------------------------------------------------------------------------


def test_negative_lambda_a():
    data = example()
    data["axial_curves"][2]["target"]["lambda_a"] = -1
    bad(data, r"test\.json: axial_curves\[2\]\.target\.lambda_a: -1 ")
    with pytest.raises(InputError, match="lambda_a must be > 0"):
        CurveTarget(PointRef(vertex=0), PointRef(vertex=1), 0.0, LambdaS.constant(1))


def test_zero_lambda_s_value():
    data = example()
    data["axial_curves"][2]["target"]["lambda_s"]["values"][1] = 0
    bad(data, r"axial_curves\[2\]\.target\.lambda_s\.values\[1\]: 0 ")
    data = example()
    data["axial_curves"][0]["target"]["lambda_s"] = 0
    bad(data, r"axial_curves\[0\]\.target\.lambda_s: 0 ")
    with pytest.raises(InputError, match="must be > 0"):
        LambdaS.piecewise([0, 10], [1.0, 0.0])


def test_unsorted_angles():
    data = example()
    data["axial_curves"][2]["target"]["lambda_s"]["angles_deg"] = [0, 180, 90, 270]
    bad(data, r"axial_curves\[2\]\.target\.lambda_s: .*strictly increasing")
    data["axial_curves"][2]["target"]["lambda_s"]["angles_deg"] = [0, 90, 90, 270]
    bad(data, "strictly increasing")
    data["axial_curves"][2]["target"]["lambda_s"]["angles_deg"] = [0, 90, 180, 360]
    bad(data, r"angles_deg\[3\]")


def test_angles_and_values_of_different_length():
    data = example()
    data["axial_curves"][2]["target"]["lambda_s"]["values"] = [1.0, 1.2]
    bad(data, "4 angles but 2 values")


def test_unknown_target_string():
    data = example()
    data["axial_curves"][1]["target"] = "drop"
    bad(data, r"axial_curves\[1\]\.target: unknown target 'drop'.*discard")


def test_duplicate_names():
    data = example()
    data["axial_curves"][2]["name"] = "index"
    bad(data, r"axial_curves\[2\]\.name: duplicate axial curve name 'index'")
    data = example()
    data["markers"][1]["name"] = "IndexTip"
    bad(data, "duplicate marker name 'IndexTip'")
    a = annotations_from_dict(example())
    with pytest.raises(InputError, match="duplicate axial curve name"):
        Annotations(a.source, a.target, a.markers, a.curves + a.curves[:1])


def test_through_points_must_match_the_source_legs():
    data = example()
    data["axial_curves"][2]["target"]["through"].append({"vertex": 32})
    bad(data, "3 source points, so its target needs 2 'through' points, not 3")
    data = example()
    data["axial_curves"][0]["target"]["through"] = [{"vertex": 30}]
    bad(data, "'through' points need source points")
    data = example()
    data["axial_curves"][2]["target"]["through"][0] = {"vertex": 29}
    bad(data, "begin with the direction point")
    data = example()
    data["axial_curves"][2]["target"]["through"][1] = {"vertex": 99999}
    bad(data, r"through\[1\]")


def test_polyline_needs_two_points():
    data = example()
    data["axial_curves"][2]["source"]["points"] = [{"vertex": 1}]
    bad(data, r"axial_curves\[2\]\.source\.points")


def test_missing_field_and_unknown_field():
    data = example()
    del data["axial_curves"][0]["target"]["lambda_s"]
    bad(data, r"axial_curves\[0\]\.target: 'lambda_s' is a required property")
    data = example()
    data["markers"][0]["weight"] = 2
    bad(data, r"markers\[0\]: .*'weight'")


def test_wrong_format_and_version():
    data = example()
    data["format"] = "handretarget.clip"
    bad(data, r"test\.json: format: not an annotation file")
    data = example()
    data["version"] = 3
    bad(data, r"version: unsupported annotation format version 3")
    bad([1, 2], "JSON object")


def test_landmark_spacing_must_be_positive():
    data = example()
    data["landmark_spacing"] = 0
    bad(data, r"landmark_spacing: 0 ")


def test_invalid_json_and_missing_file(tmp_path):
    path = tmp_path / "broken.json"
    path.write_text('{"format": "handretarget.annotations", ')
    with pytest.raises(InputError, match=r"broken\.json: invalid JSON"):
        load_annotations(path)
    nan = tmp_path / "nan.json"
    nan.write_text(json.dumps(example()).replace("1.27", "NaN"))
    with pytest.raises(InputError, match=r"nan\.json: invalid JSON: NaN"):
        load_annotations(nan)
    with pytest.raises(InputError, match=r"missing\.json: annotation file not found"):
        load_annotations(tmp_path / "missing.json")


def test_schema_error_names_the_file(tmp_path):
    data = example()
    data["axial_curves"][1]["target"] = "drop"
    path = tmp_path / "pair.json"
    path.write_text(json.dumps(data))
    with pytest.raises(InputError, match=r"pair\.json: axial_curves\[1\]\.target") as info:
        load_annotations(path)
    assert info.value.source == str(path)
    assert info.value.element == "axial_curves[1].target"


# --- check_meshes -------------------------------------------------------------------------------


def small_annotations(marker_vertex=3, curve_vertex=4):
    return Annotations(
        MeshSignature("src", 100, 98),
        MeshSignature("tgt", 50, 48),
        [MarkerPair("IndexTip", [PointRef(vertex=1)], [PointRef(vertex=2), PointRef(vertex=marker_vertex)])],
        [
            AxialCurveAnnotation("index", source_start=PointRef(vertex=0), source_end=PointRef(vertex=90),
                                 target=CurveTarget(PointRef(vertex=curve_vertex), PointRef(vertex=5), 1.0, LambdaS.constant(1.0))),
            AxialCurveAnnotation("ring", source_points=[PointRef(vertex=5), PointRef(face=97, barycentric=(0, 0, 1))]),
        ],
    )


def test_check_meshes_ok():
    small_annotations().check_meshes(grid_mesh(100), 100, grid_mesh(50), 50, source="pair.json")


def test_check_meshes_vertex_out_of_range_names_the_element():
    # consistent counts but a point beyond them (constructed directly, not loaded)
    a = small_annotations(marker_vertex=77)
    with pytest.raises(InputError, match=r"pair\.json: marker 'IndexTip' target point 1: vertex 77 out of range \[0, 50\)"):
        a.check_meshes(grid_mesh(100), 100, grid_mesh(50), 50, source="pair.json")
    a = small_annotations(curve_vertex=60)
    with pytest.raises(InputError, match=r"axial curve 'index' target start: vertex 60 out of range \[0, 50\)"):
        a.check_meshes(grid_mesh(100), 100, grid_mesh(50), 50)


def test_check_meshes_vertex_used_by_no_face():
    faces = grid_mesh(50)[:-1]  # vertex 49 unused ... and keep the face count by duplicating one
    faces = np.vstack([faces, faces[:1]])
    a = Annotations(MeshSignature("s", 100, 98), MeshSignature("t", 50, 48),
                    [MarkerPair("Tip", [PointRef(vertex=0)], [PointRef(vertex=49)])])
    with pytest.raises(InputError, match=r"marker 'Tip' target point 0: vertex 49 is used by no face"):
        a.check_meshes(grid_mesh(100), 100, faces, 50)


def test_check_meshes_mismatched_counts_says_other_rig():
    a = annotations_from_dict(example())
    source_faces = np.resize(grid_mesh(3784), (7564, 3))  # the right counts for the source
    target_faces = np.resize(grid_mesh(9000), (17996, 3))
    a.check_meshes(source_faces, 3784, target_faces, 9000)
    with pytest.raises(InputError, match=r"annotations were made for rig 'alien' with 9000 vertices; this target has 3784") as info:
        a.check_meshes(source_faces, 3784, grid_mesh(3784), 3784)
    assert "another rig" in str(info.value)
    with pytest.raises(InputError, match=r"rig 'source_human' with 7564 faces; this source has 10"):
        a.check_meshes(grid_mesh(12), 3784, grid_mesh(9000), 9000)
