"""Object substitution through the service (issue 21, item 6): a clip asset and a scanned
object uploaded as a ``file`` asset make a new clip asset, the scan registered onto the clip's
object in a memory-limited child; refusals are 422s naming the figure; the new clip runs."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from dcc_client.client import ServiceError


@pytest.fixture(scope="module")
def scan(inputs, tmp_path_factory):
    """The clip's bottle as a scan: decimated, centred at its centre of mass, turned, as PLY."""
    import fast_simplification

    from retarget_core.clip import load_clip

    clip = load_clip(inputs["clip"])
    v, f = fast_simplification.simplify(clip.object_vertices, clip.object_faces, target_reduction=0.6)
    v = v - trimesh.Trimesh(v, f, process=False).center_mass
    v = v @ Rotation.random(random_state=4).as_matrix().T
    path = tmp_path_factory.mktemp("scan") / "bottle_scan.ply"
    trimesh.Trimesh(v, f, process=False).export(path)
    return path


def test_a_scan_substituted_in_the_service_makes_a_clip_that_runs(service, inputs, scan, tmp_path):
    c = service.client("sally")
    clip = c.upload("clip", inputs["clip"])
    mesh = c.upload("file", scan)
    made = c.substitute_object(clip=clip["id"], object_mesh=mesh["id"], name="scan_clip.npz")
    info = made["info"]
    assert made["kind"] == "clip" and made in c.assets("clip") and made["id"] != clip["id"]
    assert info["frames"] == clip["info"]["frames"] and info["object"] == "bottle_scan"
    assert info["substituted_from"] == clip["id"] and info["object_mesh"] == mesh["id"]
    sub = info["substitution"]
    assert sub["share"] >= 0.95 and sub["residual_mm"] < 2.0 and sub["hand_depth_max_mm"] < 2.0
    assert np.asarray(sub["transform"]).shape == (4, 4)
    # the same request again gives the same asset (content addressed), not a second one
    assert c.substitute_object(clip=clip["id"], object_mesh=mesh["id"], name="scan_clip.npz")["id"] == made["id"]
    rig = c.upload("rig", inputs["rig"])
    annotations = c.upload("annotations", inputs["annotations"])
    job = c.submit(clip=made["id"], rig=rig["id"], annotations=annotations["id"], evaluate=False)
    done = c.wait(job["id"], timeout=900)
    assert done["state"] == "succeeded", done


def test_refused_substitutions_name_the_problem(service, inputs, scan, tmp_path):
    c = service.client("tariq")
    clip = c.upload("clip", inputs["clip"])
    mesh = c.upload("file", scan)
    identity = np.eye(4).ravel().tolist()
    with pytest.raises(ServiceError) as err:  # the scan as given: no contact reaches it
        c.substitute_object(clip=clip["id"], object_mesh=mesh["id"], transform=identity)
    assert err.value.status == 422 and "% of the contacts" in err.value.detail
    assert "/" not in err.value.detail.split("contacts")[0]  # no server path in the message
    with pytest.raises(ServiceError) as err:  # another owner's mesh is as unknown as a missing one
        service.client("ursula").substitute_object(clip=clip["id"], object_mesh=mesh["id"])
    assert err.value.status == 404 and "clip" in err.value.detail
    (tmp_path / "junk.ply").write_bytes(b"ply\nthis is not a mesh\n")
    junk = c.upload("file", tmp_path / "junk.ply")
    with pytest.raises(ServiceError) as err:
        c.substitute_object(clip=clip["id"], object_mesh=junk["id"])
    assert err.value.status == 422 and "mesh" in err.value.detail
    with pytest.raises(ServiceError) as err:  # a transform that is not 16 numbers
        c.substitute_object(clip=clip["id"], object_mesh=mesh["id"], transform=[1.0, 0.0])
    assert err.value.status == 422
    assert len(c.assets("clip")) == 1  # nothing stored by the refusals
