"""On-disk atlas cache (``get_atlas(..., cache_dir=...)``): a loaded atlas transfers exactly as
the built one without computing a log map, the key follows the annotations, bad files are
rebuilt and replaced, and the files hold plain arrays only."""

import dataclasses
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from retarget_core.clip.demo import source_rig
from retarget_core.errors import InputError
from retarget_core.execute import Executor
from retarget_core.mesh.surface_points import SurfacePoints
from retarget_core.rig.demo_hands import demo_hand
from retarget_core.solve.config import load_config
from retarget_core.transfer import atlas as atlas_module
from retarget_core.transfer.atlas import ATLAS_CACHE_VERSION, atlas_key, get_atlas
from retarget_core.transfer.clip_transfer import atlas_for
from retarget_core.transfer.geodesics import SurfaceGeometry
from retarget_core.transfer.propose import propose_annotations


class BuildCalled(RuntimeError):
    pass


@pytest.fixture(scope="module")
def hands():
    """The demo source hand and the three-fingered alien (two discarded curves), 4 mm."""
    source = source_rig()
    target = demo_hand("alien", resolution=0.004)
    return source, target, propose_annotations(source, target)


def surfaces(source, target):
    return source.surface.vertices, source.surface.faces, target.surface.vertices, target.surface.faces


@pytest.fixture(autouse=True)
def empty_memory_cache():
    atlas_module._CACHE.clear()
    yield
    atlas_module._CACHE.clear()


@pytest.fixture(scope="module")
def built(hands, tmp_path_factory):
    """The atlas built once with a cache folder: (atlas, folder, cache file, seconds)."""
    source, target, annotations = hands
    folder = tmp_path_factory.mktemp("atlas_cache")
    atlas_module._CACHE.clear()
    start = time.perf_counter()
    atlas = get_atlas(*surfaces(source, target), annotations, cache_dir=folder)
    seconds = time.perf_counter() - start
    atlas_module._CACHE.clear()
    path = folder / f"{atlas_key(*surfaces(source, target), annotations)}.npz"
    return atlas, folder, path, seconds


@pytest.fixture
def no_build(monkeypatch):
    """Computing any log map (or chart) raises BuildCalled."""
    def boom(*args, **kwargs):
        raise BuildCalled("the atlas was rebuilt")

    monkeypatch.setattr(atlas_module, "chart_fields", boom)
    monkeypatch.setattr(SurfaceGeometry, "log_map", boom)


def contacts(source, n=6000, seed=7) -> SurfacePoints:
    """n random surface points (N,) over every face of the source hand."""
    rng = np.random.default_rng(seed)
    return SurfacePoints(rng.integers(0, len(source.surface.faces), n), rng.dirichlet([1, 1, 1], n))


def assert_same_transfer(a, b, points):
    ra, rb = a.transfer(points), b.transfer(points)
    for name in ("face", "barycentric", "dropped", "landmark", "curve", "radius", "angle"):
        assert np.array_equal(getattr(ra, name), getattr(rb, name)), name
    return ra


def test_loaded_atlas_transfers_exactly_as_the_built_one(hands, built, no_build):
    source, target, annotations = hands
    atlas, folder, path, build_seconds = built
    assert path.is_file() and sorted(p.name for p in folder.iterdir()) == [path.name]  # no temp file left
    start = time.perf_counter()
    loaded = get_atlas(*surfaces(source, target), annotations, cache_dir=folder)
    load_seconds = time.perf_counter() - start
    print(f"\natlas of the 4 mm demo hands ({atlas.n_landmarks} landmarks, {path.stat().st_size / 1e6:.1f} MB): "
          f"build {build_seconds:.2f} s, load {load_seconds:.2f} s")
    assert loaded is not atlas
    assert get_atlas(*surfaces(source, target), annotations, cache_dir=folder) is loaded  # then from memory
    result = assert_same_transfer(atlas, loaded, contacts(source))
    assert result.dropped.any() and not result.dropped.all()  # the alien's discarded curves
    ours, theirs = atlas.to_arrays(), loaded.to_arrays()
    assert ours.keys() == theirs.keys()
    for name in ours:
        assert ours[name].dtype == theirs[name].dtype and np.array_equal(ours[name], theirs[name]), name
    assert [t is None for t in loaded.target_curves] == [c.discard for c in annotations.curves]


def test_atlas_for_passes_the_folder_and_saves_an_atlas_held_in_memory(hands, built, tmp_path, no_build):
    source, target, annotations = hands
    atlas, folder, path, _ = built
    loaded = atlas_for(source, target, annotations, cache_dir=folder)
    again = atlas_for(source, target, annotations, cache_dir=tmp_path / "other")  # memory hit, file missing there
    assert again is loaded
    assert (tmp_path / "other" / path.name).is_file()


def test_other_annotations_or_options_give_another_key(hands, built, no_build):
    source, target, annotations = hands
    _, folder, path, _ = built
    key = atlas_key(*surfaces(source, target), annotations)
    assert path.name == f"{key}.npz" and len(key) == 64
    # same content in other arrays (faces as int32) and objects: same key
    v1, f1, v2, f2 = surfaces(source, target)
    assert atlas_key(v1.copy(), f1.astype(np.int32), v2.copy(), f2.copy(),
                     dataclasses.replace(annotations)) == key
    i = next(i for i, c in enumerate(annotations.curves) if not c.discard)
    curve = annotations.curves[i]
    changed_curve = dataclasses.replace(curve, target=dataclasses.replace(curve.target,
                                                                          lambda_a=curve.target.lambda_a * 1.05))
    changed = dataclasses.replace(annotations, curves=annotations.curves[:i] + (changed_curve,) + annotations.curves[i + 1:])
    others = {
        atlas_key(*surfaces(source, target), changed),
        atlas_key(*surfaces(source, target), dataclasses.replace(annotations, landmark_spacing=0.003)),
        atlas_key(*surfaces(source, target), annotations, chart_radius=0.05),
        atlas_key(*surfaces(source, target), annotations, reconstruction="trace"),
        atlas_key(v1 + 1e-9, f1, v2, f2, annotations),
    }
    assert len(others) == 5 and key not in others
    # the changed annotations do not pick up the cached file: they need a build of their own
    with pytest.raises(BuildCalled):
        get_atlas(*surfaces(source, target), changed, cache_dir=folder)


@pytest.mark.parametrize("damage", ["garbage", "truncated", "pickled", "other_version", "other_key", "wrong_shape"])
def test_bad_cache_files_are_ignored(hands, built, tmp_path, damage, no_build, caplog):
    """Each damaged file is not used (the build is asked for instead), raises nothing else, is
    reported as a warning naming it and is removed."""
    source, target, annotations = hands
    _, _, path, _ = built
    bad = tmp_path / path.name
    good = dict(np.load(path, allow_pickle=False))
    if damage == "garbage":
        bad.write_bytes(b"not an npz file at all" * 100)
    elif damage == "truncated":
        bad.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    else:
        if damage == "pickled":
            good["source_coords"] = np.array([{"a": 1}], dtype=object)
        elif damage == "other_version":
            good["cache_version"] = np.array(ATLAS_CACHE_VERSION + 1)
        elif damage == "other_key":
            good["cache_key"] = np.array("0" * 64)
        else:
            good["vertex_landmark"] = good["vertex_landmark"][:-1]
        with open(bad, "wb") as handle:
            np.savez(handle, **good)
    with caplog.at_level("WARNING", logger=atlas_module.log.name), pytest.raises(BuildCalled):
        get_atlas(*surfaces(source, target), annotations, cache_dir=tmp_path)
    warned = [r for r in caplog.records if r.levelname == "WARNING" and str(bad) in r.getMessage()]
    assert warned and "corrupt atlas cache file" in warned[0].getMessage()
    assert not bad.exists()


def test_a_truncated_cache_file_is_rebuilt_and_replaced(hands, built, tmp_path, monkeypatch):
    source, target, annotations = hands
    atlas, _, path, _ = built
    bad = tmp_path / path.name
    bad.write_bytes(path.read_bytes()[:100_000])
    rebuilt = get_atlas(*surfaces(source, target), annotations, cache_dir=tmp_path)  # no error
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]
    assert bad.stat().st_size == path.stat().st_size
    with np.load(bad, allow_pickle=False) as data:
        assert str(data["cache_key"]) == path.stem
    atlas_module._CACHE.clear()
    monkeypatch.setattr(atlas_module, "chart_fields", lambda *a, **k: (_ for _ in ()).throw(BuildCalled()))
    loaded = get_atlas(*surfaces(source, target), annotations, cache_dir=tmp_path)
    points = contacts(source, n=2000, seed=3)
    assert_same_transfer(atlas, rebuilt, points)
    assert_same_transfer(atlas, loaded, points)


def test_cache_file_holds_plain_arrays_only(built):
    _, _, path, _ = built
    with zipfile.ZipFile(path) as archive:
        names = archive.namelist()
    assert names and all(n.endswith(".npy") for n in names)
    with np.load(path, allow_pickle=False) as data:
        assert len(data.files) == len(names)
        for name in data.files:
            array = data[name]  # raises for an object array when pickles are not allowed
            assert array.dtype.kind in "biufU", (name, array.dtype)
        assert int(data["cache_version"]) == ATLAS_CACHE_VERSION


def test_unwritable_cache_folder_only_costs_the_saving(hands, built, tmp_path):
    source, target, annotations = hands
    atlas, _, _, _ = built
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    atlas_module._CACHE[atlas_key(*surfaces(source, target), annotations)] = atlas
    assert get_atlas(*surfaces(source, target), annotations, cache_dir=blocker / "cache") is atlas


def test_executor_option():
    """The cache folder is how a run executes, not what it computes: an Executor option now
    (formerly the run configuration's ``atlas_cache`` key, which is refused, naming it)."""
    assert Executor().cache_dir is None and Executor().describe()["atlas_cache"] == ""
    assert Executor(atlas_cache="/tmp/atlases").cache_dir == Path("/tmp/atlases")
    assert Executor(atlas_cache="/tmp/atlases").describe()["atlas_cache"] == "/tmp/atlases"
    with pytest.raises(InputError, match="--atlas-cache") as info:
        load_config(None, "default", {"atlas_cache": "/tmp/atlases"})
    assert info.value.element == "atlas_cache"
    with pytest.raises(InputError, match="atlas_cache") as info:
        Executor(atlas_cache=3)
    assert info.value.element == "executor.atlas_cache"
    with pytest.raises(InputError, match="atlas_cache") as info:
        Executor(atlas_cache="a\0b")
    assert info.value.element == "executor.atlas_cache"


def test_prune_keeps_the_most_recently_used_files_within_the_budget(tmp_path):
    import os
    import time

    from retarget_core.transfer.atlas import prune_atlas_cache

    now = time.time()
    sizes = {"a": 400, "b": 300, "c": 200, "d": 100}  # a oldest ... d newest
    for age, (name, size) in enumerate(sizes.items()):
        path = tmp_path / f"{name}.npz"
        path.write_bytes(b"x" * size)
        os.utime(path, (now - 100 * (4 - age), now - 100 * (4 - age)))
    old_tmp = tmp_path / ".e.npz.tmp"
    old_tmp.write_bytes(b"x" * 50)
    os.utime(old_tmp, (now - 7200, now - 7200))
    fresh_tmp = tmp_path / ".f.npz.tmp"  # a save in progress: kept
    fresh_tmp.write_bytes(b"x" * 50)
    (tmp_path / "notes.txt").write_text("not an atlas")
    assert prune_atlas_cache(tmp_path, 350) == (3, 750)  # a and b go, then c+d = 300 fit
    assert sorted(p.name for p in tmp_path.iterdir()) == [".f.npz.tmp", "c.npz", "d.npz", "notes.txt"]
    assert prune_atlas_cache(tmp_path, 350) == (0, 0)
    assert prune_atlas_cache(tmp_path / "missing", 0) == (0, 0)


def test_loading_a_cached_atlas_marks_it_recently_used(hands, built, no_build):
    import os

    source, target, annotations = hands
    path = built[2]
    os.utime(path, (1_000_000, 1_000_000))
    get_atlas(*surfaces(source, target), annotations, cache_dir=path.parent)  # loaded, not rebuilt
    assert path.stat().st_mtime > 1_000_000 + 3600
