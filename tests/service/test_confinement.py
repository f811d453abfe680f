"""Issue 16, Build 1 (confinement), against a real ``handretarget serve`` on 127.0.0.1.

Finding (High) "a URDF or MJCF rig bundle may name meshes anywhere on the host": every file a
bundle names must resolve inside the unpacked bundle; anything else is a 422 naming the element
and the path as written, the same whether the outside file exists or not, with no server path in
the text and no foreign geometry stored.

Finding (High) "a .usda upload with subLayers / references / payload pointing at an absolute
path is composed": a single-layer USD upload may compose no other layer (422 naming the arc and
the asset path as written); other asset paths are dropped with a warning; the stored asset is the
flattened layer.

Every hostile input is built here, in the test; nothing hostile is committed as a file.
"""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np
import pytest

from dcc_client.client import ServiceError

from .conftest import Service

# ---- inputs built in the test ----------------------------------------------------------------
def _box_stl(size=(0.02, 0.02, 0.05), offset=(0.0, 0.0, 0.025)) -> bytes:
    import trimesh

    mesh = trimesh.creation.box(extents=size)
    mesh.apply_translation(offset)
    return mesh.export(file_type="stl")


def _urdf(mesh_filename: str) -> str:
    """A two-link hand: a box palm and a finger whose visual is the mesh ``mesh_filename``."""
    return f"""<?xml version="1.0"?>
<robot name="probe_hand">
  <link name="palm"><visual><geometry><box size="0.06 0.06 0.02"/></geometry></visual></link>
  <link name="finger"><visual><geometry><mesh filename="{mesh_filename}"/></geometry></visual></link>
  <joint name="knuckle" type="revolute">
    <parent link="palm"/><child link="finger"/><origin xyz="0 0 0.01"/>
    <axis xyz="1 0 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/>
  </joint>
</robot>
"""


def _zip(files: dict[str, bytes | str]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, data in files.items():
            zf.writestr(name, data.encode() if isinstance(data, str) else data)
    return buf.getvalue()


def _mjcf(meshdir: str, mesh_file: str = "finger.stl") -> str:
    return f"""<mujoco model="probe_hand">
  <compiler angle="radian" meshdir="{meshdir}" autolimits="true"/>
  <asset><mesh name="finger" file="{mesh_file}"/></asset>
  <worldbody>
    <body name="palm">
      <geom type="box" size="0.03 0.03 0.01"/>
      <body name="finger" pos="0 0 0.01">
        <joint name="knuckle" type="hinge" axis="1 0 0" range="-1 1"/>
        <geom type="mesh" mesh="finger"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.fixture(scope="module")
def svc(tmp_path_factory):
    service = Service(tmp_path_factory.mktemp("confine") / "data", "--job-slots", "1").start()
    yield service
    service.stop()


@pytest.fixture(scope="module")
def foreign(tmp_path_factory) -> Path:
    """A mesh on the host, outside the service's data dir: the geometry that must never be read.
    Its 602-vertex sphere is easy to recognise in a stored rig."""
    import trimesh

    folder = tmp_path_factory.mktemp("host_files")
    path = folder / "secret.stl"
    trimesh.creation.icosphere(subdivisions=3, radius=0.03).export(path)
    return path


def _refused(client, kind: str, data: bytes, name: str) -> str:
    with pytest.raises(ServiceError) as info:
        client.upload_bytes(kind, data, name)
    assert info.value.status == 422, info.value
    return info.value.detail


def _no_server_path(detail: str, svc: Service, *extra: Path) -> None:
    data_dir = str(svc.data_dir)
    assert data_dir not in detail and str(svc.data_dir.resolve()) not in detail, detail
    assert "/tmp" not in detail and "bundle/" not in detail, detail
    for p in extra:
        assert str(p.parent) not in detail, detail


# ---- finding: URDF / MJCF bundles name files anywhere on the host -----------------------------
def test_urdf_bundle_inside_loads(svc):
    # Positive control: the same bundle with the mesh inside it (relative, package://, file://
    # relative) is accepted; the refusals below are about where the mesh is, not its format.
    client = svc.client("confine-ok")
    for i, ref in enumerate(["meshes/finger.stl", "package://probe_hand/meshes/finger.stl",
                             "./meshes/../meshes/finger.stl"]):
        asset = client.upload_bytes("rig", _zip({"probe.urdf": _urdf(ref) + f"<!-- {i} -->",
                                                 "meshes/finger.stl": _box_stl()}), f"ok{i}.zip")
        assert asset["info"]["dofs"] == 7 and asset["info"]["imported_from"] == "probe.urdf"


@pytest.mark.parametrize("form", ["absolute", "file_uri", "dotdot", "package_dotdot", "package_abs"])
def test_urdf_mesh_outside_the_bundle_is_refused(svc, foreign, form):
    # Finding: "a URDF ... bundle may name meshes anywhere on the host (absolute path, file://,
    # ../, package://)". On 328eb67 the absolute and file:// forms were imported (201) with the
    # foreign sphere's 602 vertices; the ../ forms climbed out of <data>/tmp/<id>/bundle.
    client = svc.client(f"confine-urdf-{form}")
    climb = "../" * (len(Path(svc.data_dir).resolve().parts) + 6)
    ref = {"absolute": str(foreign), "file_uri": f"file://{foreign}",
           "dotdot": climb + str(foreign).lstrip("/"),
           "package_dotdot": "package://probe_hand/" + climb + str(foreign).lstrip("/"),
           "package_abs": f"package://probe_hand/{foreign}"}[form]
    bundle = _zip({"probe.urdf": _urdf(ref), "meshes/finger.stl": _box_stl()})
    detail = _refused(client, "rig", bundle, f"{form}.zip")
    assert "<mesh filename=" in detail and repr(ref) in detail, detail  # names the element, as written
    assert "link 'finger'" in detail and "probe.urdf" in detail, detail
    assert client.assets("rig") == []  # no foreign geometry stored
    # the only host path in the text is the one the uploader wrote
    _no_server_path(detail.replace(repr(ref), "<REF>"), svc, foreign)


def test_urdf_existence_probe_gives_one_answer(svc, tmp_path):
    # Finding: "the same path is a file-existence oracle (file:///etc/shadow -> 'file_type not
    # supported', missing -> 'not found')". Now both are refused before any stat, identically.
    client = svc.client("confine-probe")
    missing = tmp_path / "no" / "such" / "file.stl"
    answers = []
    for target in ("/etc/passwd", str(missing)):
        ref = f"file://{target}"
        detail = _refused(client, "rig", _zip({"probe.urdf": _urdf(ref)}), "probe.zip")
        answers.append(detail.replace(ref, "<REF>"))
    assert answers[0] == answers[1], answers
    assert "not found" not in answers[0] and "not supported" not in answers[0]


def test_urdf_missing_mesh_inside_names_no_server_path(svc):
    # Finding: "error texts disclose server paths ('searched relative to <data dir>/tmp/<id>/bundle')".
    client = svc.client("confine-missing")
    detail = _refused(client, "rig", _zip({"probe.urdf": _urdf("meshes/absent.stl")}), "missing.zip")
    assert "'meshes/absent.stl'" in detail and "not found" in detail, detail
    _no_server_path(detail, svc)


@pytest.mark.parametrize("meshdir, mesh_file", [("/", None), ("../..", "finger.stl"), ("meshes", None)])
def test_mjcf_asset_folder_outside_the_bundle_is_refused(svc, foreign, meshdir, mesh_file):
    # Finding: "... MuJoCo meshdir": meshdir="/" with the host path as the mesh file, meshdir
    # climbing out, and a mesh file that is absolute under an inside meshdir. On 328eb67 MuJoCo
    # loaded the foreign file (meshdir="/") or answered with the server's path.
    client = svc.client(f"confine-mjcf-{meshdir.replace('/', 's').replace('.', 'd')}")
    mesh_file = mesh_file or (str(foreign).lstrip("/") if meshdir == "/" else str(foreign))
    bundle = _zip({"hand.xml": _mjcf(meshdir, mesh_file), "meshes/finger.stl": _box_stl()})
    detail = _refused(client, "rig", bundle, "mjcf.zip")
    if meshdir == "meshes":
        assert f"<mesh file={mesh_file!r}>" in detail, detail
    else:
        assert f"<compiler meshdir={meshdir!r}>" in detail, detail
    assert client.assets("rig") == []
    assert str(svc.data_dir) not in detail and "/tmp/" not in detail.replace(str(foreign), ""), detail


def test_mjcf_include_outside_the_bundle_is_refused(svc, foreign):
    # Finding: bundles name files anywhere (an MJCF <include> is read by MuJoCo's compiler).
    client = svc.client("confine-mjcf-include")
    xml = _mjcf("meshes").replace("<worldbody>", f'<include file="../../{foreign.name}"/><worldbody>')
    detail = _refused(client, "rig", _zip({"hand.xml": xml, "meshes/finger.stl": _box_stl()}), "inc.zip")
    assert f"<include file='../../{foreign.name}'>" in detail, detail
    _no_server_path(detail, svc)


def test_mjcf_bundle_inside_loads(svc):
    # Positive control for the MJCF refusals above.
    asset = svc.client("confine-mjcf-ok").upload_bytes(
        "rig", _zip({"hand.xml": _mjcf("meshes"), "meshes/finger.stl": _box_stl()}), "mjcf_ok.zip")
    assert asset["info"]["dofs"] == 7 and asset["info"]["imported_from"] == "hand.xml"


# ---- finding: USD composition arcs pointing at any file --------------------------------------
def _blob_of(svc: Service, sha: str) -> Path:
    found = [p for p in (svc.data_dir / "blobs").rglob(f"{sha}*") if p.is_file()]
    assert found, sha
    return found[0]


def _referencing_layer(arc: str, target: str) -> bytes:
    if arc == "subLayers":
        return f'#usda 1.0\n(\n    subLayers = [@{target}@]\n)\n'.encode()
    if arc == "references":
        return f'#usda 1.0\n(\n    defaultPrim = "Hand"\n)\ndef "Hand" (\n    references = @{target}@\n)\n{{\n}}\n'.encode()
    if arc == "payload":
        return f'#usda 1.0\n(\n    defaultPrim = "Hand"\n)\ndef "Hand" (\n    payload = @{target}@\n)\n{{\n}}\n'.encode()
    # a reference inside a variant: composed only when the variant is selected
    return (f'#usda 1.0\ndef "Hand" (\n    variants = {{\n        string v = "a"\n    }}\n'
            f'    prepend variantSets = "v"\n)\n{{\n    variantSet "v" = {{\n        "a" (\n'
            f'            references = @{target}@\n        ) {{\n        }}\n    }}\n}}\n').encode()


@pytest.mark.parametrize("arc", ["subLayers", "references", "payload", "variant_reference"])
def test_usd_layer_composing_another_owners_blob_is_refused(svc, inputs, arc):
    # Finding: "a 76-byte .usda upload with subLayers, references or payload pointing at an
    # absolute path is composed at upload and at every job; with the blob path of another
    # owner's private rig, the job's rig.usda artifact returned that owner's whole rig". On
    # 328eb67 this upload was accepted (201) as a rig with the victim's DOFs and surface.
    victim = svc.client("confine-victim")
    private = victim.upload("rig", inputs["rig"], name="private.usda")
    blob = _blob_of(svc, private["id"])
    attacker = svc.client(f"confine-usd-{arc}")
    data = _referencing_layer(arc, str(blob))
    detail = _refused(attacker, "rig", data, "tiny.usda")
    label = {"subLayers": "subLayers", "references": "references of </Hand>", "payload": "payload of </Hand>",
             "variant_reference": "references of </Hand{v=a}>"}[arc]
    assert label in detail and f"@{blob}@" in detail, detail  # the arc and the asset path as written
    assert attacker.assets("rig") == []  # nothing of the victim's stored under the attacker
    assert "Skeleton" not in detail and private["info"]["name"] not in detail
    # the text names the upload's own element; the only path in it is the one the uploader wrote
    _no_server_path(detail.replace(str(blob), "<written>"), svc)


@pytest.mark.parametrize("arc", ["subLayers", "references", "payload"])
def test_usd_layer_arc_to_a_missing_or_relative_file_is_refused_alike(svc, arc, tmp_path):
    # Finding (same): no existence oracle through composition: /etc/passwd, a missing absolute
    # path and a relative sibling all answer the same 422 (none of them is opened), and it names
    # the arc with the path as written (328eb67 answered USD's own "cannot open" text instead).
    client = svc.client(f"confine-usd-probe-{arc}")
    answers = []
    for target in ("/etc/passwd", str(tmp_path / "missing.usda"), "./sibling.usda"):
        detail = _refused(client, "rig", _referencing_layer(arc, target), "probe.usda")
        answers.append(detail.replace(target, "<REF>"))
    assert answers[0] == answers[1] == answers[2], answers
    label = {"subLayers": "subLayers", "references": "references of </Hand>", "payload": "payload of </Hand>"}[arc]
    assert f"probe.usda: {label} @<REF>@" in answers[0], answers[0]
    _no_server_path(answers[0], svc)


def test_usd_texture_paths_are_dropped_and_the_stored_layer_is_flat(svc, inputs):
    # Finding (same): other asset paths are never resolved: a rig with an asset-valued attribute
    # naming a host file is accepted with a warning, and the stored (downloaded) layer is the
    # flattened one without that path and without any composition arc.
    from pxr import Sdf

    layer = Sdf.Layer.FindOrOpen(str(inputs["rig"]))
    copy = Sdf.Layer.CreateAnonymous(".usda")
    copy.TransferContent(layer)
    root = copy.GetPrimAtPath(copy.defaultPrim)
    attr = Sdf.AttributeSpec(root, "tex", Sdf.ValueTypeNames.Asset)
    attr.default = Sdf.AssetPath("/etc/hostname")
    # an internal reference (no other layer) is fine and flattened away
    Sdf.PrimSpec(copy.pseudoRoot, "Extra", Sdf.SpecifierDef).referenceList.Prepend(Sdf.Reference(primPath=root.path))
    client = svc.client("confine-texture")
    asset = client.upload_bytes("rig", copy.ExportToString().encode(), "textured.usda")
    assert asset["info"]["dofs"] == inputs["target"].n_dofs
    assert any("'/etc/hostname'" in w and "dropped" in w for w in asset["info"]["warnings"]), asset["info"]
    assert all(w.startswith("textured.usda: ") for w in asset["info"]["warnings"]), asset["info"]
    stored = client.asset_content(asset["id"]).decode()
    assert "/etc/hostname" not in stored and "references" not in stored


def test_usdz_package_is_flattened_inside_the_package(svc, inputs, foreign, tmp_path):
    # Finding (same), packages: a zip USD package composes its own layers (confined to it) and is
    # stored flattened; one whose layer references a file outside the package is refused.
    from pxr import Sdf

    rig_text = Path(inputs["rig"]).read_text()
    root_layer = ('#usda 1.0\n(\n    defaultPrim = "Hand"\n    metersPerUnit = 1\n    upAxis = "Z"\n)\n'
                  'def "Hand" (\n    references = @./parts/rig.usda@\n)\n{\n}\n')
    client = svc.client("confine-usdz")
    asset = client.upload_bytes("rig", _zip({"hand.usda": root_layer, "parts/rig.usda": rig_text}), "hand.usdz")
    assert asset["info"]["dofs"] == inputs["target"].n_dofs
    assert asset["info"]["imported_from"] == "hand.usda"
    (tmp_path / "stored.usdc").write_bytes(client.asset_content(asset["id"]))
    stored = Sdf.Layer.OpenAsAnonymous(str(tmp_path / "stored.usdc"))
    assert stored.GetCompositionAssetDependencies() in ([], [""]) or not any(stored.GetCompositionAssetDependencies())
    assert stored.GetPrimAtPath("/Hand/Skeleton") is not None  # the referenced layer's content, flattened
    outside = root_layer.replace("./parts/rig.usda", "../" * 12 + str(foreign).lstrip("/"))
    detail = _refused(client, "rig", _zip({"hand.usda": outside}), "evil.usdz")
    assert "references of </Hand>" in detail, detail
    _no_server_path(detail.replace(str(foreign).lstrip("/"), ""), svc)


def test_foreign_mesh_vertices_never_stored(svc, foreign):
    # Finding: "the downloaded rig holds the foreign geometry verbatim (602 of 602 vertices)".
    # Whatever form the reference takes, no stored rig of this owner holds the foreign sphere.
    import trimesh

    client = svc.client("confine-geometry")
    sphere = np.asarray(trimesh.load(foreign, force="mesh").vertices)
    for ref in (str(foreign), f"file://{foreign}", "package://probe_hand/../" + "../" * 20 + str(foreign)[1:]):
        with pytest.raises(ServiceError):
            client.upload_bytes("rig", _zip({"probe.urdf": _urdf(ref)}), "geo.zip")
    assert len(sphere) > 600 and client.assets("rig") == []


def test_job_refuses_a_stored_layer_that_composes_another(svc, inputs):
    # Finding: "... is composed at upload and at every job; ... the job's rig.usda artifact
    # returned that owner's whole rig". A rig stored before uploads were flattened (simulated by
    # rewriting the attacker's own blob in the store) is refused by the job before composing.
    from .conftest import FAST

    victim = svc.client("confine-job-victim")
    private = victim.upload("rig", inputs["rig"], name="private3.usda")
    attacker = svc.client("confine-job-attacker")
    ids = {k: attacker.upload(kind, inputs[k])["id"]
           for k, kind in (("clip", "clip"), ("rig", "rig"), ("annotations", "annotations"))}
    own_blob = _blob_of(svc, ids["rig"])
    own_blob.write_bytes(_referencing_layer("references", str(_blob_of(svc, private["id"]))))
    # (the store's integrity check may refuse the rewritten blob at submission already: fine too;
    # the job's own check, usd_io.check_confined_layers in server/job_process.py, covers a layer
    # stored raw before this fix, whose recorded hash still matches)
    try:
        job = attacker.submit(clip=ids["clip"], rig=ids["rig"], annotations=ids["annotations"], overrides=FAST)
    except ServiceError as err:
        assert err.status in (409, 410, 422) and "Skeleton" not in err.detail, err
        return
    done = attacker.wait(job["id"], timeout=300)
    assert done["state"] == "failed", done
    assert "may not compose other layers" in done["error"] and str(svc.data_dir) not in done["error"], done
    with pytest.raises(ServiceError):
        attacker.artifact(job["id"], "rig.usda")
