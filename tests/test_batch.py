"""``handretarget batch`` (issue 19): a GRAB folder of three generated sequences onto two hands,
killed after its first result and restarted, finishes every output exactly once; manifests and
GRAB folder layouts."""

from __future__ import annotations

import csv
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from grab_hand_sequence import write_known_sequence
from retarget_core.batch import grab_sequences, read_manifest
from retarget_core.errors import InputError

HANDS = ("demo:human_alt@0.006", "demo:robot4@0.006")


@pytest.fixture(scope="module")
def grab_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("GRAB")
    known = [write_known_sequence(root, subject=subject, lead=lead, n_frames=40, name=f"bottle_{i}")
             for i, (subject, lead) in enumerate([("s1", 20), ("s1", 10), ("s2", 25)])]
    return root, known[0].mano


def _batch_command(root, mano, out) -> list[str]:
    cmd = [sys.executable, "-m", "retarget_core.cli", "batch", "--grab-root", str(root), "--mano", str(mano),
           "--out", str(out), "--workers", "1"]
    for hand in HANDS:
        cmd += ["--rig", hand]
    return cmd


def test_interrupted_batch_finishes_each_output_once(grab_root, tmp_path):
    root, mano = grab_root
    out = tmp_path / "batch"
    results = out / "results"
    first = subprocess.Popen(_batch_command(root, mano, out), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                             cwd=Path(__file__).resolve().parents[1])
    deadline = time.monotonic() + 600
    while time.monotonic() < deadline and first.poll() is None:
        done = [p for p in results.glob("*") if p.is_dir() and not p.name.endswith(".partial")] if results.is_dir() else []
        if done:
            break
        time.sleep(0.2)
    assert first.poll() is None, f"the batch ended before it could be interrupted: {first.stdout.read().decode()}"
    first.send_signal(signal.SIGKILL)
    first.wait()
    finished = {p.name: (p / "result.json").stat().st_mtime_ns
                for p in results.iterdir() if p.is_dir() and not p.name.endswith(".partial")}
    assert finished and all((results / name / "animation.usda").is_file() for name in finished)
    assert len(finished) < 6

    second = subprocess.run(_batch_command(root, mano, out), capture_output=True, text=True,
                            cwd=Path(__file__).resolve().parents[1], timeout=1200)
    assert second.returncode == 0, second.stdout + second.stderr
    assert f"{6 - len(finished)} made, {len(finished)} already finished, 0 failed" in second.stdout
    names = sorted(p.name for p in results.iterdir())
    assert len(names) == 6 and not any(n.endswith(".partial") for n in names)  # the killed one's scratch is gone
    for name, mtime in finished.items():  # finished before the kill: not redone
        assert (results / name / "result.json").stat().st_mtime_ns == mtime
    with open(out / "summary.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert sorted((r["clip"], r["hand"]) for r in rows) == sorted(
        (f"{s}_bottle_{i}", h) for i, s in ((0, "s1"), (1, "s1"), (2, "s2")) for h in ("human_alt", "robot4"))
    assert all(r["status"] == "ok" and float(r["contact_distance_median_mm"]) < 10 for r in rows), rows
    # three clips converted once, each with its MANO source rig; one proposal per (source rig, hand)
    assert len(list((out / "clips").glob("*.npz"))) == 3
    assert len(list((out / "clips").glob("*.source_rig.usda"))) == 3
    assert len(list((out / "annotations").glob("*.json"))) == 2

    third = subprocess.run(_batch_command(root, mano, out), capture_output=True, text=True,
                           cwd=Path(__file__).resolve().parents[1], timeout=600)
    assert "0 made, 6 already finished, 0 failed" in third.stdout


def test_grab_layouts_and_manifests(tmp_path):
    tree = tmp_path / "GRAB"
    for rel in ("grab/s1/a.npz", "grab/s2/b.npz", "tools/object_meshes/x.npz"):
        (tree / rel).parent.mkdir(parents=True, exist_ok=True)
        (tree / rel).write_bytes(b"")
    assert [n for n, _ in grab_sequences(tree)] == ["s1_a", "s2_b"]
    flat = tmp_path / "flat"
    flat.mkdir()
    (flat / "c.npz").write_bytes(b"")
    assert [n for n, _ in grab_sequences(flat)] == ["c"]
    with pytest.raises(InputError, match="grab/<subject>/<sequence>.npz"):
        grab_sequences(_empty(tmp_path))
    with pytest.raises(InputError, match="not a folder"):
        grab_sequences(tmp_path / "nowhere")

    manifest = tmp_path / "list.txt"
    manifest.write_text("# clips\nflat/c.npz\n\n")
    assert read_manifest(manifest) == [tmp_path / "flat" / "c.npz"]
    (tmp_path / "list.json").write_text('["flat/c.npz", "flat/missing.npz"]')
    with pytest.raises(InputError, match="missing.npz"):
        read_manifest(tmp_path / "list.json")


def _empty(tmp_path):
    folder = tmp_path / "empty"
    folder.mkdir()
    return folder
