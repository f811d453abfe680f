"""GRAB sequences through the service: uploaded as files with the user's MANO model and the
meshes, imported by the core's restricted loader into a clip asset; a booby-trapped pickle is
refused with a 422 and never runs."""

from __future__ import annotations

import os

import numpy as np
import pytest

from dcc_client.client import ServiceError
from grab_fixtures import make_grab_sequence, make_mano_raw, write_grab_npz, write_mano_official


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


def test_grab_import_makes_a_clip_asset(service, grab_files, inputs):
    c = service.client("grace")
    ids = {k: c.upload("file", grab_files[k])["id"] for k in ("sequence", "mano", "object_mesh", "table_mesh", "vtemp")}
    clip = c.import_grab(**ids)
    assert clip["kind"] == "clip" and clip["info"]["frames"] == 6 and clip["info"]["hand_vertices"] == 778
    assert clip["info"]["imported_from"] == "grab"
    assert clip in c.assets("clip")
    # the clip names no demo source hand: a job needs the MANO hand as source_rig
    rig = c.upload("rig", inputs["rig"])
    ann = c.upload("annotations", inputs["annotations"])
    with pytest.raises(ServiceError) as err:
        c.submit(clip=clip["id"], rig=rig["id"], annotations=ann["id"])
    assert err.value.status == 422 and "source_rig" in err.value.detail


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
