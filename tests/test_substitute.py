"""Object substitution: contacts traced onto a new object, then the normal pipeline."""

import contextlib
import io

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from retarget_core.cli import main
from retarget_core.clip import load_clip
from retarget_core.clip.demo import make_demo_clip, source_rig
from retarget_core.clip.objects import make_object
from retarget_core.clip.substitute import substitute_object, trace_onto
from retarget_core.errors import InputError
from retarget_core.mesh.registration import register_surface, surface_moments
from retarget_core.pairing import pair_contacts


@pytest.fixture(scope="module")
def clip():
    return make_demo_clip("bottle_pick_place", time_scale=0.05, resolution=0.004, rig=source_rig(0.004))


def test_trace_onto_a_concentric_sphere_lands_straight_out():
    """Points on a unit-ish sphere traced along their normals onto a sphere 5 mm larger land on
    the new vertex nearest the radial hit; beyond max_distance nothing is found."""
    small = trimesh.creation.icosphere(subdivisions=3, radius=0.03)
    big = trimesh.creation.icosphere(subdivisions=4, radius=0.035)
    hit, face, bary = trace_onto(small.vertices, small.vertex_normals, big.vertices, big.faces, max_distance=0.01)
    assert np.all(hit >= 0)
    radial = small.vertices / np.linalg.norm(small.vertices, axis=1, keepdims=True) * 0.035
    assert np.linalg.norm(big.vertices[hit] - radial, axis=1).max() < 0.004  # within a mesh edge
    # the surface point itself is the radial hit, to the sphere's faceting (not a vertex away)
    point = np.einsum("nk,nkd->nd", bary, big.vertices[big.faces[face]])
    assert np.linalg.norm(point - radial, axis=1).max() < 3e-4
    assert np.all(trace_onto(small.vertices, small.vertex_normals, big.vertices, big.faces, max_distance=0.004)[0] < 0)
    inner = trace_onto(big.vertices, big.vertex_normals, small.vertices, small.faces, max_distance=0.01)[0]
    assert np.all(inner >= 0)  # inward when nothing is outward


def test_substituting_the_same_object_keeps_every_label(clip):
    same, report = substitute_object(clip, clip.object_vertices, clip.object_faces, name="bottle")
    assert report["dropped"] == 0 and report["traced"] == report["labelled_vertices"] > 0
    assert np.array_equal(same.contact_labels, clip.contact_labels)
    assert np.array_equal(same.hand_vertices, clip.hand_vertices)


def test_a_wider_object_gets_the_contacts_and_pairs_with_the_hand(clip):
    wide = clip.object_vertices * [1.1, 1.1, 1.0]
    new, report = substitute_object(clip, wide, clip.object_faces, name="wide bottle", allow_intersection=True)
    assert report["dropped"] == 0 and new.object_name == "wide bottle"
    frames = (clip.contact_labels > 0).any(axis=1)
    assert np.array_equal((new.contact_labels > 0).any(axis=1), frames)
    pairs = pair_contacts(new)
    assert np.diff(pairs.frame_offsets)[frames].sum() > 0.8 * np.diff(pair_contacts(clip).frame_offsets)[frames].sum()


def test_bad_new_objects_are_named(clip, tmp_path):
    box = trimesh.creation.box([0.05, 0.05, 0.2])
    with pytest.raises(InputError, match="closed manifold"):
        substitute_object(clip, box.vertices, box.faces[:-1], repair=False)
    # two boxes side by side: not a stray piece, refused rather than one of them kept
    two = np.concatenate([box.vertices, box.vertices + [0.1, 0, 0]])
    with pytest.raises(InputError, match="2 separate pieces"):
        substitute_object(clip, two, np.concatenate([box.faces, box.faces + 8]))
    with pytest.raises(InputError, match="finite"):
        substitute_object(clip, np.full((8, 3), np.nan), box.faces)
    clip.save(tmp_path / "c.npz")
    (tmp_path / "junk.obj").write_text("this is not a mesh\n")
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = main(["clip", "substitute", str(tmp_path / "c.npz"), "--object", "demo:teapot", "--out",
                     str(tmp_path / "n.npz")])
    assert code == 2 and "teapot" in err.getvalue() and not (tmp_path / "n.npz").exists()


def test_cli_substitute_writes_a_valid_clip(clip, tmp_path):
    clip.save(tmp_path / "c.npz")
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(["clip", "substitute", str(tmp_path / "c.npz"), "--object", "demo:bottle", "--scale", "1.1,1.1,1",
                     "--out", str(tmp_path / "n.npz")])
    assert code == 0
    new = load_clip(tmp_path / "n.npz")
    assert new.object_name == "bottle" and (new.contact_labels > 0).any()
    assert "traced" in out.getvalue() and "registered the new object" in out.getvalue()


def _turned(vertices, seed):
    """``vertices`` re-centred at their surface centroid (as a scan comes), turned by a random
    rotation and moved; and that rigid motion (4, 4)."""
    rotation = Rotation.random(random_state=seed).as_matrix()
    m = np.eye(4)
    m[:3, :3] = rotation
    m[:3, 3] = [0.31, -0.17, 0.08]
    return vertices @ rotation.T + m[:3, 3], m


def _scan_like(vertices, faces, edge=0.005, seed=0):
    """The demo object as a scan comes: decimated to about ``edge`` metre edges with
    fast-simplification, centred at its centre of mass, turned."""
    import fast_simplification

    mean_edge = np.linalg.norm(vertices[faces[:, 0]] - vertices[faces[:, 1]], axis=1).mean()
    reduction = float(np.clip(1.0 - (mean_edge / edge) ** 2, 0.0, 0.95))
    v, f = fast_simplification.simplify(vertices, faces, target_reduction=reduction)
    v = v - trimesh.Trimesh(v, f, process=False).center_mass
    turned, _ = _turned(v, seed)
    return turned, np.asarray(f, dtype=np.int64)


@pytest.mark.parametrize("name", ["mug", "hammer", "bottle"])
def test_registration_undoes_a_turn_and_a_move(name):
    """A demo object turned by a random rotation and moved is placed back onto itself: the
    surfaces meet to 1 um; the mug (no symmetry) to the vertex, symmetric objects up to their
    symmetry (any such placement is the same surface)."""
    obj = make_object(name, 0.004)
    centroid, _ = surface_moments(obj.vertices, obj.faces)
    moved, m = _turned(obj.vertices - centroid, seed=11)
    fit = register_surface(obj.vertices, obj.faces, moved, obj.faces)
    assert fit.surface_rms < 1e-6 and fit.rms < 1e-6
    back = fit.apply(moved)
    if name == "mug":
        assert np.abs(back - obj.vertices).max() < 1e-6
    np.testing.assert_allclose(fit.transform[:3, :3] @ fit.transform[:3, :3].T, np.eye(3), atol=1e-9)
    assert np.linalg.det(fit.transform[:3, :3]) > 0  # a rotation, never a mirror image


def test_a_scan_like_object_is_registered_and_keeps_the_contacts(clip):
    """The clip's bottle as a scan (decimated to 5 mm edges, centred at its centre of mass,
    turned): as given, no contact reaches it and the substitution is refused naming the share;
    registered, >= 95 % of the contacts carry over with an RMS residual under 2 mm, and the
    reported transform is the one that places it."""
    scan, faces = _scan_like(clip.object_vertices, clip.object_faces)
    assert len(faces) < 0.7 * len(clip.object_faces)
    with pytest.raises(InputError, match=r"only \d+\.\d % of the contacts"):
        substitute_object(clip, scan, faces, name="scan")
    new, report = substitute_object(clip, scan, faces, name="scan", register=True)
    assert report["share"] >= 0.95 and report["residual_mm"] < 2.0
    m = np.array(report["transform"])
    np.testing.assert_allclose(new.object_vertices, scan @ m[:3, :3].T + m[:3, 3], atol=1e-12)
    # the placed scan lies on the original surface
    closest, distance, _ = trimesh.proximity.closest_point(
        trimesh.Trimesh(clip.object_vertices, clip.object_faces, process=False), new.object_vertices)
    assert np.median(distance) < 1e-3
    frames = (clip.contact_labels > 0).any(axis=1)
    assert np.array_equal((new.contact_labels > 0).any(axis=1), frames)


def test_a_new_object_that_cuts_through_the_hand_is_refused_with_its_frames(clip):
    """A bottle 30 % wider in the same place puts the captured fingers inside it: refused,
    naming the frames; with allow_intersection it is written and the depths are reported."""
    wide = clip.object_vertices * [1.3, 1.3, 1.0]
    with pytest.raises(InputError, match=r"inside the new object in \d+ of 46 frames \(frames \d+") as err:
        substitute_object(clip, wide, clip.object_faces, transform=np.eye(4))
    new, report = substitute_object(clip, wide, clip.object_faces, transform=np.eye(4), allow_intersection=True)
    depth = np.array(report["hand_depth_mm"])
    deep = np.flatnonzero(depth > 2.0)
    assert len(deep) and f"in {len(deep)} of 46 frames" in str(err.value)
    assert ", ".join(str(f) for f in deep[:3]) in str(err.value)
    # the same object in the same place: the hand touches it but is not inside it
    _, same = substitute_object(clip, clip.object_vertices, clip.object_faces, transform=np.eye(4))
    assert max(same["hand_depth_mm"]) < 2.0


def test_cli_substitute_places_refuses_and_explains(clip, tmp_path):
    """The CLI registers a scan by default and prints the residual and the transform;
    --transform identity takes it as given (refused: the share); a bad --transform is a usage
    error, as is mixing it with --rotate."""
    clip.save(tmp_path / "c.npz")
    scan, faces = _scan_like(clip.object_vertices, clip.object_faces, seed=5)
    trimesh.Trimesh(scan, faces, process=False).export(tmp_path / "scan.ply")

    def run(*extra):
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main(["clip", "substitute", str(tmp_path / "c.npz"), "--object", str(tmp_path / "scan.ply"),
                         "--out", str(tmp_path / "n.npz"), *extra])
        return code, out.getvalue(), err.getvalue()

    code, out, _ = run()
    assert code == 0 and "RMS" in out and "placement" in out and (tmp_path / "n.npz").exists()
    (tmp_path / "n.npz").unlink()
    code, _, err = run("--transform", "identity")
    assert code == 2 and "% of the contacts" in err and not (tmp_path / "n.npz").exists()
    code, _, err = run("--transform", "1,0,0")
    assert code == 2 and "--transform" in err
    code, _, err = run("--rotate", "0,0,0", "--transform", "identity")
    assert code == 2 and "not both" in err


def test_a_scan_with_a_hole_and_a_stray_piece_is_repaired_and_registered(clip):
    """The scan-like bottle with a hole cut in its side (away from the grasp), a stray speck
    beside it and its triangles written unwelded (STL-style): welded, the speck dropped, the
    hole closed, then registered as before; the repairs are listed."""
    scan, faces = _scan_like(clip.object_vertices, clip.object_faces, seed=2)
    centroid = scan.mean(axis=0)
    # a hole: the faces around the scan's lowest vertex (the bottle's base, no contact there)
    down = Rotation.random(random_state=2).as_matrix() @ [0.0, 0.0, -1.0]  # the bottle's base, turned
    low = scan[np.argmax(scan @ down)]
    cut = np.linalg.norm(scan[faces].mean(axis=1) - low, axis=1) < 0.01
    assert 3 <= cut.sum() < 0.05 * len(faces)
    holed = faces[~cut]
    speck = trimesh.creation.icosphere(subdivisions=1, radius=0.002)
    v = np.concatenate([scan, speck.vertices + centroid + [0.2, 0, 0]])
    f = np.concatenate([holed, speck.faces + len(scan)])
    soup_v = v[f].reshape(-1, 3)  # every triangle with its own three vertices
    soup_f = np.arange(len(soup_v)).reshape(-1, 3)
    new, report = substitute_object(clip, soup_v, soup_f, name="holed scan", register=True)
    text = "; ".join(report["repairs"])
    assert "welded" in text and "1 stray piece" in text and "closed 1 hole" in text, text
    assert report["share"] >= 0.95 and report["residual_mm"] < 2.0
    with pytest.raises(InputError, match="closed manifold"):
        substitute_object(clip, soup_v, soup_f, register=True, repair=False)


def test_a_registered_scan_retargets_like_the_original_object(clip):
    """Done-when of the substitution: the clip with its bottle replaced by the registered
    scan-like bottle retargets onto the prosthetic with a delivered contact error within 1 mm
    of the original clip's (the clip is 20x sped up, so the curve gets 60 control points a
    second to follow it)."""
    from retarget_core.inputs import RunInputs
    from retarget_core.pipeline import retarget
    from retarget_core.rig.demo_hands import demo_hand
    from retarget_core.solve.config import load_config
    from retarget_core.transfer.propose import propose_annotations

    source, target = source_rig(0.004), demo_hand("prosthetic_1dof", 0.004)
    annotations = propose_annotations(source, target)
    scan, faces = _scan_like(clip.object_vertices, clip.object_faces)
    new, report = substitute_object(clip, scan, faces, register=True)
    config = load_config(None, "default", {"fit.control_points_per_second": 60})
    error = {name: retarget(RunInputs.of(c, source, target, annotations), config).summary["contact_distance_median_mm"]
             for name, c in (("original", clip), ("scan", new))}
    assert np.isfinite(error["original"]) and abs(error["scan"] - error["original"]) < 1.0, error


def test_substituted_contacts_are_the_traced_surface_points_not_vertices(clip, tmp_path):
    """The substituted clip (format 2) keeps each traced contact where it landed: on the
    registered scan, the points lie on the original bottle's surface (where its contacts
    were) to well under the scan's 5 mm edges, while the nearest vertices are millimetres off;
    the points survive saving, and pairing uses them."""
    scan, faces = _scan_like(clip.object_vertices, clip.object_faces)
    new, report = substitute_object(clip, scan, faces, register=True)
    assert new.contact_offsets is not None and new.contact_offsets[-1] == len(new.contact_faces)
    corners = new.object_faces[new.contact_faces]
    points = np.einsum("nk,nkd->nd", new.contact_barycentric, new.object_vertices[corners])
    nearest = new.object_vertices[corners[np.arange(len(corners)), np.argmax(new.contact_barycentric, axis=1)]]
    original = trimesh.Trimesh(clip.object_vertices, clip.object_faces, process=False)
    on_surface = trimesh.proximity.closest_point(original, points)[1]
    snapped = trimesh.proximity.closest_point(original, nearest)[1]
    # where the original contact vertices were: each point is within its trace of one
    frame_of = np.repeat(np.arange(new.n_frames), np.diff(new.contact_offsets))
    assert np.median(on_surface) < 0.3e-3 and np.median(np.linalg.norm(nearest - points, axis=1)) > 1e-3
    assert np.median(snapped) >= np.median(on_surface)
    assert np.array_equal(np.unique(frame_of), np.flatnonzero((clip.contact_labels > 0).any(axis=1)))
    new.save(tmp_path / "v2.npz")
    back = load_clip(tmp_path / "v2.npz")
    np.testing.assert_array_equal(back.contact_offsets, new.contact_offsets)
    np.testing.assert_allclose(back.contact_barycentric, new.contact_barycentric)
    pairs = pair_contacts(back)
    # pairing uses the surface points: the paired object points are those points
    kept = np.flatnonzero(pairs.gap >= 0)
    assert len(kept) > 0.8 * len(points)
    assert set(map(tuple, np.round(pairs.object_barycentric, 9))) <= set(map(tuple, np.round(back.contact_barycentric, 9)))
