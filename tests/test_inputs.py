"""Run inputs (retarget_core/inputs.py): frame ranges, the clip's own source-rig field (untrusted:
only a demo hand at a bounded resolution), content hashes and the executor's validation."""

import hashlib
import types

import numpy as np
import pytest

from retarget_core.errors import InputError
from retarget_core.execute import Executor
from retarget_core.inputs import clip_source_rig, content_sha256, file_sha256, frame_range, parse_frames


@pytest.mark.parametrize("text, expected", [("10:70", (10, 70)), (":70", (None, 70)), ("10:", (10, None)),
                                            (" 3 : 9 ", (3, 9))])
def test_parse_frames(text, expected):
    assert parse_frames(text) == expected


@pytest.mark.parametrize("text", ["10", "a:b", "-1:5", "1:2:3", ""])
def test_parse_frames_refuses(text):
    with pytest.raises(InputError, match="START:END") as err:
        parse_frames(text)
    assert err.value.element == "frames"


def test_frame_range_within_the_clip():
    assert frame_range(None, 50) == (0, 50)
    assert frame_range((None, 20), 50) == (0, 20)
    assert frame_range("5:", 50) == (5, 50)
    for bad in ((10, 10), (20, 10), (0, 51), (-1, 5), (1.5, 4), ("a", 3)):
        with pytest.raises(InputError) as err:
            frame_range(bad, 50)
        assert err.value.element == "frames", bad


@pytest.mark.parametrize("spec", ["/etc/passwd", "../rig.usda", "rig.usda", "file:///x.usda"])
def test_a_clip_may_not_name_a_file_as_its_source_rig(spec):
    with pytest.raises(InputError, match="--source-rig") as err:
        clip_source_rig(types.SimpleNamespace(source_rig=spec))
    assert err.value.element == "source_rig"


def test_a_clip_names_a_demo_hand_at_a_bounded_resolution():
    assert clip_source_rig(types.SimpleNamespace(source_rig="demo:source_human@0.004")) == "demo:source_human@0.004"
    assert clip_source_rig(types.SimpleNamespace(source_rig="")).startswith("demo:source_human")
    for res in ("0.00001", "5", "nan", "x"):
        with pytest.raises(InputError, match="resolution"):
            clip_source_rig(types.SimpleNamespace(source_rig=f"demo:source_human@{res}"))


def test_content_hash_sees_every_value_and_only_values():
    a = {"x": np.arange(6, dtype=np.float64).reshape(2, 3), "name": "hand"}
    b = {"name": "hand", "x": np.arange(6, dtype=np.float64).reshape(2, 3)}
    assert content_sha256(a) == content_sha256(b)  # key order does not matter
    c = dict(a, x=a["x"].copy())
    c["x"][1, 2] = np.nextafter(5.0, 6.0)
    assert content_sha256(c) != content_sha256(a)  # one ulp does
    assert content_sha256(dict(a, x=a["x"].reshape(3, 2))) != content_sha256(a)  # so does the shape
    assert content_sha256(dict(a, x=a["x"].astype(">f8"))) == content_sha256(a)  # byte order does not
    with pytest.raises(TypeError):
        content_sha256(object())


def test_file_sha256(tmp_path):
    path = tmp_path / "f.bin"
    path.write_bytes(b"hand" * 300_000)
    assert file_sha256(path) == hashlib.sha256(b"hand" * 300_000).hexdigest()


@pytest.mark.parametrize("kwargs, element", [(dict(workers=0), "executor.workers"),
                                             (dict(workers=True), "executor.workers"),
                                             (dict(blas_threads=0), "executor.blas_threads"),
                                             (dict(dask_scheduler="10.0.0.1:8786"), "executor.dask_scheduler"),
                                             (dict(dask_scheduler="tcp://h:99999"), "executor.dask_scheduler"),
                                             (dict(atlas_cache="a\0b"), "executor.atlas_cache")])
def test_executor_refuses_bad_options(kwargs, element):
    with pytest.raises(InputError) as err:
        Executor(**kwargs)
    assert err.value.element == element


def test_executor_describes_itself_without_the_progress_callback(tmp_path):
    ex = Executor(workers=3, atlas_cache=tmp_path, progress=print)
    assert ex.describe() == {"workers": 3, "dask_scheduler": "", "atlas_cache": str(tmp_path), "blas_threads": 1}


def test_in_memory_inputs_record_their_names_and_content_hashes(demo_rigs):
    from retarget_core.clip.demo import make_demo_clip
    from retarget_core.inputs import RunInputs
    from retarget_core.transfer.propose import propose_annotations

    source, target = demo_rigs["source_human"], demo_rigs["human_alt"]
    clip = make_demo_clip("box_pinch", time_scale=0.05, resolution=0.004, rig=source)
    ann = propose_annotations(source, target)
    inputs = RunInputs.of(clip, source, target, ann, frames=(0, 10), names={"target_rig": "demo:human_alt@0.004"})
    sources = inputs.provenance()
    assert set(sources) == {"clip", "source_rig", "target_rig", "annotations"}
    assert sources["target_rig"] == {"sha256": content_sha256(target), "spec": "demo:human_alt@0.004"}
    assert "spec" not in sources["clip"] and len(sources["clip"]["sha256"]) == 64
    assert sources["source_rig"]["sha256"] != sources["target_rig"]["sha256"]
