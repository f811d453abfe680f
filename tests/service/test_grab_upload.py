"""GRAB sequences through the service: uploaded as files with the user's MANO model and the
meshes, imported by the core's restricted loader into a clip asset and its MANO source rig (a
rig asset), a job run on the clip with no source_rig (the rig found by its hash among the
owner's assets, never by a path), the result imported; a booby-trapped pickle is refused with
a 422 and never runs."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from dcc_client.client import ServiceError
from grab_fixtures import make_grab_sequence, make_mano_raw, write_grab_npz, write_mano_official
from grab_hand_sequence import write_known_sequence


class _Evil:
    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.system, (f"echo pwned > {self.marker}",))


@pytest.fixture(scope="module")
def grab_files(tmp_path_factory):
    root = tmp_path_factory.mktemp("grab")
    raw = make_mano_raw(0, rigid=False)
    seq = make_grab_sequence(root, raw)
    mano = write_mano_official(root / "MANO_RIGHT.pkl", raw)
    path = write_grab_npz(root / "grab" / "s1" / "apple_eat_1.npz", seq)
    meshes = {k: root / v for k, v in (("object_mesh", "tools/object_meshes/contact_meshes/apple.ply"),
                                       ("table_mesh", "tools/object_meshes/contact_meshes/table.ply"),
                                       ("vtemp", "tools/subject_meshes/male/s1_rhand.ply"))}
    return dict(root=root, seq=seq, sequence=path, mano=mano, **meshes)


@pytest.fixture(scope="module")
def hand_files(tmp_path_factory):
    """A GRAB-format sequence on a hand-shaped MANO model (60 frames of a bottle grasp)."""
    root = tmp_path_factory.mktemp("grab_hand")
    known = write_known_sequence(root, n_frames=60, lead=30)
    return dict(sequence=known.path, mano=known.mano,
                object_mesh=root / "tools/object_meshes/contact_meshes/bottle_pick_place.ply",
                vtemp=root / "tools/subject_meshes/male/s1_rhand.ply")


def test_grab_import_to_an_imported_result(service, hand_files, tmp_path):
    c = service.client("grace")
    ids = {k: c.upload("file", hand_files[k])["id"] for k in ("sequence", "mano", "object_mesh", "vtemp")}
    clip = c.import_grab(**ids)
    assert clip["kind"] == "clip" and clip["info"]["frames"] == 60 and clip["info"]["hand_vertices"] == 778
    assert clip["info"]["imported_from"] == "grab" and clip["info"]["hand"] == "right"
    assert clip in c.assets("clip")
    # its MANO source rig is an asset too, and the clip records it by that asset's id
    (rig,) = [a for a in c.assets("rig") if a["id"] == clip["info"]["source_rig_asset"]]
    assert clip["info"]["source_rig_sha256"] == rig["id"] and rig["info"]["dofs"] == 51
    assert rig["info"]["hand_mesh"] == {"vertices": 778, "faces": clip["info"]["hand_faces"]}
    from retarget_core.rig.demo_hands import demo_hand
    from retarget_core.rig.io import save_rig

    save_rig(demo_hand("human_alt", 0.006), tmp_path / "human_alt.usda")
    target = c.upload("rig", tmp_path / "human_alt.usda")
    ann = c.propose_annotations(target_rig=target["id"], source_rig=rig["id"])
    assert ann["info"]["markers"] == 25
    job = c.submit(clip=clip["id"], rig=target["id"], annotations=ann["id"], evaluate=False)  # no source_rig
    done = c.wait(job["id"], timeout=900)
    assert done["state"] == "succeeded", done
    files = c.download_result(job["id"], tmp_path / "result")
    result = json.loads(files["result.json"].read_text())
    assert result["provenance"]["inputs"]["source_rig"]["asset"] == rig["id"]
    assert result["summary"]["contact_distance_median_mm"] < 5.0
    from retarget_core.export.usd_animation import read_dof_splines

    curves = read_dof_splines(files["animation.usda"])
    assert len(curves) == 54  # human_alt's DOFs, one spline each

    # another owner with the same clip bytes but not the rig: refused, naming what to upload
    other = service.client("olga")
    theirs = other.upload_bytes("clip", c.asset_content(clip["id"]), "copy.npz")
    t_rig = other.upload("rig", tmp_path / "human_alt.usda")
    t_ann = other.upload_bytes("annotations", c.asset_content(ann["id"]), "annotations.json")
    with pytest.raises(ServiceError) as err:
        other.submit(clip=theirs["id"], rig=t_rig["id"], annotations=t_ann["id"])
    assert err.value.status == 422 and rig["id"] in err.value.detail and "POST /v1/assets/rig" in err.value.detail


def test_a_mano_file_that_is_no_hand_is_refused(service, grab_files):
    c = service.client("grace2")
    ids = {k: c.upload("file", grab_files[k])["id"] for k in ("sequence", "mano", "object_mesh", "table_mesh", "vtemp")}
    with pytest.raises(ServiceError) as err:
        c.import_grab(**ids)
    assert err.value.status == 422 and "cannot build the MANO source rig" in err.value.detail
    assert c.assets("clip") == [] and c.assets("rig") == []


def test_booby_trapped_sequence_is_refused_and_never_runs(service, grab_files, tmp_path):
    c = service.client("heidi")
    marker = tmp_path / "pwned.txt"
    seq = {k: v for k, v in grab_files["seq"].items() if k != "_truth"}
    seq["rhand"] = dict(seq["rhand"], evil=_Evil(marker))
    evil = tmp_path / "evil.npz"
    np.savez(evil, **seq)
    ids = {k: c.upload("file", grab_files[k])["id"] for k in ("mano", "object_mesh")}
    bad = c.upload("file", evil)  # stored as bytes: nothing is unpickled on upload
    with pytest.raises(ServiceError) as err:
        c.import_grab(sequence=bad["id"], **ids)
    assert err.value.status == 422 and "refusing to unpickle" in err.value.detail
    assert "blobs" not in err.value.detail and not marker.exists()  # no server path in the message
    assert c.assets("clip") == []
    with pytest.raises(ServiceError) as err:  # the sequence must be the caller's own file asset
        service.client("ivan").import_grab(sequence=bad["id"], **ids)
    assert err.value.status == 404 and "sequence" in err.value.detail
