"""``confine_to`` of the rig loaders (issue 16, Build 1): every file a URDF / MJCF / USD rig
names must resolve inside a given folder; anything else is an InputError naming the element and
the reference as written, raised before the file outside is opened or stat-ed.

Covers the High findings "a URDF or MJCF rig bundle may name meshes anywhere on the host" and
"a .usda upload with subLayers / references / payload pointing at an absolute path is composed"
at the core level (the service tests are in tests/service/test_confinement.py). Each test uses
``confine_to``, which the loaders of 328eb67 do not take (TypeError), or checks a behaviour they
lacked. Hostile inputs are built here, in tmp_path.
"""

from __future__ import annotations

import os
import re

import pytest

from installed_models import installed_or_none
from retarget_core.errors import InputError
from retarget_core.rig.io import load_rig
from retarget_core.rig.robot_import import load_mjcf, load_urdf



LEAP = installed_or_none("leap")
SHADOW = installed_or_none("shadow")

RES = 0.006  # coarse wrapper: these tests are about which files are read, not the surface


def _box_stl(path):
    import trimesh

    path.parent.mkdir(parents=True, exist_ok=True)
    trimesh.creation.box(extents=(0.02, 0.02, 0.05)).export(path)
    return path


def _urdf(path, mesh_filename):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"""<?xml version="1.0"?>
<robot name="probe_hand">
  <link name="palm"><visual><geometry><box size="0.06 0.06 0.02"/></geometry></visual></link>
  <link name="finger"><visual><geometry><mesh filename="{mesh_filename}"/></geometry></visual></link>
  <joint name="knuckle" type="revolute">
    <parent link="palm"/><child link="finger"/><origin xyz="0 0 0.01"/>
    <axis xyz="1 0 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/>
  </joint>
</robot>
""")
    return path


def _mjcf(path, *, compiler='meshdir="meshes"', extra_asset="", extra_world="", mesh_file="finger.stl"):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"""<mujoco model="probe_hand">
  <compiler angle="radian" {compiler} autolimits="true"/>
  <asset><mesh name="finger" file="{mesh_file}"/>{extra_asset}</asset>
  <worldbody>{extra_world}
    <body name="palm">
      <geom type="box" size="0.03 0.03 0.01"/>
      <body name="finger" pos="0 0 0.01">
        <joint name="knuckle" type="hinge" axis="1 0 0" range="-1 1"/>
        <geom type="mesh" mesh="finger"/>
      </body>
    </body>
  </worldbody>
</mujoco>
""")
    return path


# ---- the robot model wheels still load when confined to their own folders --------------------
@pytest.mark.skipif(LEAP is None, reason="ghand wheel (LEAP hand URDF) not installed")
def test_ghand_urdf_loads_confined_to_its_models_folder():
    # finding 1 (URDF bundles): a real bundle whose meshes are '../meshes/*.ply' relative to
    # urdf/ still loads confined to its own folder, and names itself relative to it
    models = LEAP.parent.parent
    rig = load_rig(LEAP, confine_to=models, wrapper_resolution=RES)
    assert rig.n_dofs == 6 + 16
    assert rig.metadata["source_file"] == "urdf/ghand_right.urdf"


@pytest.mark.skipif(LEAP is None, reason="ghand wheel (LEAP hand URDF) not installed")
def test_ghand_urdf_confined_to_its_urdf_folder_is_refused():
    # finding 1: '..' above the confining folder is refused, naming the element as written
    with pytest.raises(InputError) as info:
        load_urdf(LEAP, confine_to=LEAP.parent, wrapper_resolution=RES)
    text = str(info.value)
    assert re.search(r"<mesh filename='\.\./meshes/[^']+\.ply'>", text), text
    assert str(LEAP.parent) not in text and text.startswith("ghand_right.urdf: link ")


@pytest.mark.skipif(SHADOW is None, reason="gymnasium-robotics wheel (Shadow hand MJCF) not installed")
def test_shadow_mjcf_loads_confined_to_its_assets_folder():
    # finding 1 (MJCF bundles): meshdir="../stls/hand" and the includes stay inside envs/assets
    assets = SHADOW.parent.parent
    rig = load_rig(SHADOW, confine_to=assets, wrapper_resolution=RES)
    assert rig.n_dofs == 6 + 24
    assert rig.metadata["source_file"] == "hand/reach.xml"
    with pytest.raises(InputError, match=r"<compiler meshdir='\.\./stls/hand'>"):
        load_mjcf(SHADOW, confine_to=SHADOW.parent, wrapper_resolution=RES)


# ---- URDF --------------------------------------------------------------------------------------
@pytest.mark.parametrize("form", ["absolute", "file_uri", "dotdot", "package_dotdot", "http"])
def test_urdf_reference_outside_is_refused_unopened(tmp_path, monkeypatch, form):
    # finding 1: absolute, file://, '..', package:// escaping (and other URI schemes) are refused;
    # the outside file is neither opened nor stat-ed (the check is lexical)
    outside = _box_stl(tmp_path / "host" / "secret.stl")
    root = tmp_path / "bundle"
    ref = {"absolute": str(outside), "file_uri": f"file://{outside}", "dotdot": "../host/secret.stl",
           "package_dotdot": "package://probe_hand/../../host/secret.stl", "http": "http://example.com/m.stl"}[form]
    urdf = _urdf(root / "probe.urdf", ref)
    touched = []
    real_stat = os.stat

    def spy(p, *a, **k):
        if "host" in str(p):
            touched.append(str(p))
        return real_stat(p, *a, **k)

    monkeypatch.setattr(os, "stat", spy)
    with pytest.raises(InputError) as info:
        load_urdf(urdf, confine_to=root, wrapper_resolution=RES)
    monkeypatch.undo()
    assert touched == []
    text = str(info.value)
    assert f"<mesh filename={ref!r}>" in text and "link 'finger'" in text, text
    assert text.startswith("probe.urdf: ") and str(root) not in text


def test_urdf_outside_existing_and_missing_answer_alike(tmp_path):
    # finding 1, the existence oracle: the same message whether the file outside exists or not
    root = tmp_path / "bundle"
    answers = []
    for target in ("/etc/passwd", str(tmp_path / "missing" / "x.stl")):
        urdf = _urdf(root / "probe.urdf", f"file://{target}")
        with pytest.raises(InputError) as info:
            load_urdf(urdf, confine_to=root, wrapper_resolution=RES)
        answers.append(str(info.value).replace(target, "<T>"))
    assert answers[0] == answers[1]


def test_urdf_symlink_out_of_the_folder_is_refused(tmp_path):
    # finding 1: a link inside the folder pointing outside it
    outside = _box_stl(tmp_path / "host" / "secret.stl")
    root = tmp_path / "bundle"
    (root / "meshes").mkdir(parents=True)
    (root / "meshes" / "finger.stl").symlink_to(outside)
    urdf = _urdf(root / "probe.urdf", "meshes/finger.stl")
    with pytest.raises(InputError, match="outside the rig's own folder"):
        load_urdf(urdf, confine_to=root, wrapper_resolution=RES)


def test_urdf_package_search_stops_at_the_folder(tmp_path):
    # finding 1: "package:// searched upward through every ancestor": unconfined (the command
    # line) it still finds <ancestor>/PKG/...; confined it looks only inside the folder
    _box_stl(tmp_path / "probe_hand" / "meshes" / "finger.stl")
    root = tmp_path / "site" / "bundle"
    urdf = _urdf(root / "urdf" / "probe.urdf", "package://probe_hand/meshes/finger.stl")
    assert load_urdf(urdf, wrapper_resolution=RES).n_dofs == 7  # the CLI's behaviour is kept
    with pytest.raises(InputError) as info:
        load_urdf(urdf, confine_to=root, wrapper_resolution=RES)
    text = str(info.value)
    assert "'package://probe_hand/meshes/finger.stl' not found in the rig's folder" in text, text
    assert text.startswith("urdf/probe.urdf: ") and str(tmp_path) not in text


def test_urdf_package_inside_the_folder_loads(tmp_path):
    # finding 1: package:// maps to the bundle root (the bundle is the package) and to a folder
    # named after the package inside it
    root = tmp_path / "bundle"
    _box_stl(root / "meshes" / "finger.stl")
    urdf = _urdf(root / "urdf" / "probe.urdf", "package://probe_hand/meshes/finger.stl")
    assert load_rig(urdf, confine_to=root, wrapper_resolution=RES).n_dofs == 7
    root2 = tmp_path / "bundle2"
    _box_stl(root2 / "probe_hand" / "meshes" / "finger.stl")
    urdf2 = _urdf(root2 / "probe_hand" / "probe.urdf", "package://probe_hand/meshes/finger.stl")
    assert load_rig(urdf2, confine_to=root2, wrapper_resolution=RES).n_dofs == 7


def test_urdf_unconfined_keeps_absolute_paths(tmp_path):
    # the command line loads local files as before (no confinement)
    mesh = _box_stl(tmp_path / "elsewhere" / "finger.stl")
    urdf = _urdf(tmp_path / "robot" / "probe.urdf", str(mesh))
    assert load_rig(urdf, wrapper_resolution=RES).n_dofs == 7
    with pytest.raises(InputError):
        load_rig(urdf, confine_to=urdf.parent, wrapper_resolution=RES)


# ---- MJCF --------------------------------------------------------------------------------------
@pytest.mark.parametrize("case", ["meshdir_root", "meshdir_up", "assetdir_abs", "mesh_abs", "include_up",
                                  "texture_cube", "doctype"])
def test_mjcf_reference_outside_is_refused(tmp_path, case):
    # finding 1 (MuJoCo meshdir): asset folders, mesh / texture / include files outside the
    # folder are refused before MuJoCo opens anything
    outside = _box_stl(tmp_path / "host" / "secret.stl")
    root = tmp_path / "bundle"
    _box_stl(root / "meshes" / "finger.stl")
    kw, expect = {
        "meshdir_root": ({"compiler": 'meshdir="/"', "mesh_file": str(outside).lstrip("/")},
                         "<compiler meshdir='/'>"),
        "meshdir_up": ({"compiler": 'meshdir="../host"', "mesh_file": "secret.stl"}, "<compiler meshdir='../host'>"),
        "assetdir_abs": ({"compiler": f'assetdir="{outside.parent}"', "mesh_file": "secret.stl"},
                         f"<compiler assetdir={str(outside.parent)!r}>"),
        "mesh_abs": ({"mesh_file": str(outside)}, f"<mesh file={str(outside)!r}>"),
        "include_up": ({"extra_world": '<include file="../host/part.xml"/>'}, "<include file='../host/part.xml'>"),
        "texture_cube": ({"extra_asset": '<texture name="t" type="cube" fileright="../../x.png"/>'},
                         "<texture fileright='../../x.png'>"),
        "doctype": ({}, "DOCTYPE"),
    }[case]
    xml = _mjcf(root / "hand.xml", **kw)
    if case == "doctype":
        xml.write_text('<?xml version="1.0"?><!DOCTYPE mujoco [<!ENTITY d "meshes">]>' + xml.read_text())
    with pytest.raises(InputError) as info:
        load_mjcf(xml, confine_to=root, wrapper_resolution=RES)
    text = str(info.value)
    assert expect in text and text.startswith("hand.xml: "), text
    assert str(root) not in text


def test_mjcf_inside_loads_and_errors_name_no_host_path(tmp_path):
    root = tmp_path / "bundle"
    _box_stl(root / "meshes" / "finger.stl")
    assert load_rig(_mjcf(root / "hand.xml"), confine_to=root, wrapper_resolution=RES).n_dofs == 7
    # a missing mesh inside: MuJoCo's own message, without the host folder
    with pytest.raises(InputError) as info:
        load_mjcf(_mjcf(root / "hand.xml", mesh_file="absent.stl"), confine_to=root, wrapper_resolution=RES)
    assert str(root) not in str(info.value) and str(tmp_path) not in str(info.value)


# ---- USD ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def rig_layer(tmp_path_factory):
    from retarget_core.rig.demo_hands import demo_hand
    from retarget_core.rig.io import save_rig

    path = tmp_path_factory.mktemp("usd") / "hand.usda"
    save_rig(demo_hand("human_alt", 0.006), path)
    return path


def _layer(path, arc, target):
    body = {"subLayers": f'(\n    subLayers = [@{target}@]\n)\n',
            "references": f'(\n    defaultPrim = "Hand"\n)\ndef "Hand" (\n    references = @{target}@\n)\n{{\n}}\n',
            "payload": f'(\n    defaultPrim = "Hand"\n)\ndef "Hand" (\n    payload = @{target}@\n)\n{{\n}}\n'}[arc]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("#usda 1.0\n" + body)
    return path


@pytest.mark.parametrize("arc", ["subLayers", "references", "payload"])
def test_usd_arcs_outside_the_folder_are_refused(tmp_path, rig_layer, arc):
    # finding 2: a layer composing a file outside the folder (here: a real rig) is refused,
    # naming the arc and the asset path as written; inside the folder it composes
    root = tmp_path / "upload"
    layer = _layer(root / "main.usda", arc, str(rig_layer))
    with pytest.raises(InputError) as info:
        load_rig(layer, confine_to=root)
    text = str(info.value)
    assert f"@{rig_layer}@" in text and arc in text and text.startswith("main.usda: "), text
    (root / "parts").mkdir()
    (root / "parts" / "rig.usda").write_bytes(rig_layer.read_bytes())
    inside = _layer(root / "ok.usda", arc, "./parts/rig.usda")
    if arc != "subLayers":  # a sublayer's prims keep their own path; the rig is found either way
        assert load_rig(inside, confine_to=root).n_dofs == load_rig(rig_layer).n_dofs
    else:
        assert load_rig(inside, confine_to=root).n_dofs == load_rig(rig_layer).n_dofs


def test_usd_single_layer_composes_nothing(tmp_path, rig_layer):
    # finding 2: confined to the file itself, a layer may compose no other layer at all, not
    # even a sibling; unconfined (the command line) it composes as before
    (tmp_path / "rig.usda").write_bytes(rig_layer.read_bytes())
    layer = _layer(tmp_path / "main.usda", "references", "./rig.usda")
    assert load_rig(layer).n_dofs == load_rig(rig_layer).n_dofs
    with pytest.raises(InputError, match=r"references of </Hand> @\./rig\.usda@: a USD rig uploaded as one layer"):
        load_rig(layer, confine_to=layer)


def test_usd_flatten_drops_texture_paths(tmp_path, rig_layer):
    # finding 2: asset paths that are not arcs are dropped with a warning, and the flattened
    # layer is self-contained
    from pxr import Sdf

    from retarget_core.rig.usd_io import flatten_confined, layer_asset_paths

    src = Sdf.Layer.FindOrOpen(str(rig_layer))
    copy = Sdf.Layer.CreateAnonymous(".usda")
    copy.TransferContent(src)
    attr = Sdf.AttributeSpec(copy.GetPrimAtPath(copy.defaultPrim), "tex", Sdf.ValueTypeNames.Asset)
    attr.default = Sdf.AssetPath("/etc/hostname")
    (tmp_path / "in.usda").write_text(copy.ExportToString())
    warnings = flatten_confined(tmp_path / "in.usda", tmp_path / "flat.usda")
    assert len(warnings) == 1 and "'/etc/hostname'" in warnings[0]
    flat = Sdf.Layer.FindOrOpen(str(tmp_path / "flat.usda"))
    assert layer_asset_paths(flat) == []
    assert load_rig(tmp_path / "flat.usda", confine_to=tmp_path / "flat.usda").n_dofs == load_rig(rig_layer).n_dofs


def test_usd_value_clips_outside_are_refused(tmp_path, rig_layer):
    # finding 2: value clips open other layers when values are read, like a reference does
    root = tmp_path / "upload"
    root.mkdir()
    layer = root / "clips.usda"
    layer.write_text('#usda 1.0\ndef "Hand" (\n    clips = {\n        dictionary default = {\n'
                     f'            asset[] assetPaths = [@{rig_layer}@]\n'
                     '            string primPath = "/human_alt"\n        }\n    }\n)\n{\n}\n')
    with pytest.raises(InputError, match=r"clips of </Hand> @" + re.escape(str(rig_layer)) + "@"):
        load_rig(layer, confine_to=root)
    with pytest.raises(InputError, match="may not compose other layers"):
        load_rig(layer, confine_to=layer)
