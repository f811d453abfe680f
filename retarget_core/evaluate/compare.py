"""``handretarget compare``: one clip onto two variants of a hand (the paper's extension
"visualising the impact of a DOF design choice", e.g. the prosthetic with 1-DOF and 2-DOF
knuckles): both retargets, their metrics side by side, a per-frame difference plot and the
frames where they differ most rendered side by side.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import atomic_path

#: per-frame series compared (metrics.json per_frame keys, label)
SERIES = (("contact_error_median_mm", "contact error (mm)"),
          ("hand_object", "hand-object intersection (%)"),
          ("penetration_mm", "hand-object penetration (mm)"),
          ("self", "self intersection (%)"),
          ("marker_error_mm", "marker error (mm)"))


def _series(doc: dict, key: str) -> np.ndarray:
    per = doc["per_frame"]
    values = per["intersection_percent"][key] if key in per["intersection_percent"] else per[key]
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def compare_outputs(a_dir, b_dir, out, *, worst: int = 3, size: int = 300) -> dict:
    """Compare two evaluated retarget outputs of the same clip (folders with metrics.json):
    writes compare.md, compare.json, difference.png and worst_frames.png into ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from PIL import Image

    from ..render.raster import frame_camera, render_meshes
    from .report import load_output

    a_dir, b_dir, out = Path(a_dir), Path(b_dir), Path(out)
    docs = []
    for d in (a_dir, b_dir):
        path = d / "metrics.json"
        if not path.is_file():
            raise InputError("no metrics.json here (run handretarget evaluate first)", source=str(d))
        docs.append(json.loads(path.read_text(encoding="utf-8")))
    if docs[0]["frames"] != docs[1]["frames"] or docs[0]["clip"] != docs[1]["clip"]:
        raise InputError("the two outputs are not of the same clip (frames or clip differ)", source=str(b_dir))
    names = [docs[0]["rig"], docs[1]["rig"]]
    if names[0] == names[1]:
        names = [f"{names[0]} ({a_dir.name})", f"{names[1]} ({b_dir.name})"]
    n, fps = docs[0]["frames"], docs[0]["fps"]
    out.mkdir(parents=True, exist_ok=True)

    rows = ["| metric | " + " | ".join(names) + " |", "|---|---:|---:|"]
    for key in docs[0]["summary"]:
        vals = [d["summary"].get(key) for d in docs]
        rows.append(f"| {key} | " + " | ".join("n/a" if v is None else v if isinstance(v, str) else f"{v:.4g}"
                                              for v in vals) + " |")
    diff = {key: _series(docs[1], key) - _series(docs[0], key) for key, _ in SERIES}
    contact = np.abs(diff["contact_error_median_mm"])
    order = np.argsort(-np.nan_to_num(contact, nan=-1.0))
    worst_frames = [int(f) for f in order[:worst] if np.isfinite(contact[f])]

    fig, axes = plt.subplots(len(SERIES), 1, figsize=(8, 1.9 * len(SERIES)), dpi=110, sharex=True)
    t = np.arange(n) / fps
    for ax, (key, label) in zip(axes, SERIES):
        for doc, name in zip(docs, names):
            y = _series(doc, key)
            keep = np.isfinite(y)
            ax.plot(t[keep], y[keep], lw=1.2, label=name)
        ax.set_ylabel(label, fontsize=8)
        ax.grid(alpha=0.3)
    for f in worst_frames:
        for ax in axes:
            ax.axvline(f / fps, color="k", lw=0.6, ls=":")
    axes[0].legend(fontsize=8)
    axes[-1].set_xlabel("time (s)")
    fig.tight_layout()
    paths = {"difference.png": out / "difference.png"}
    with atomic_path(paths["difference.png"], suffix=".png.tmp") as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)

    if worst_frames:
        loaded = [load_output(d) for d in (a_dir, b_dir)]
        tiles = []
        for f in worst_frames:
            row = []
            posed = []
            for result, rig, scene in loaded:
                pose = scene.object_poses[f]
                obj = scene.object_vertices @ pose[:3, :3].T + pose[:3, 3]
                posed.append((rig.kinematics().skin(result.sampled()[f]), rig.surface.faces, obj, scene.object_faces))
            camera = frame_camera(np.vstack([p[0] for p in posed] + [posed[0][2]]), size=(size, size))
            for hand, faces, obj, obj_faces in posed:
                row.append(np.asarray(render_meshes([(hand, faces, (0.85, 0.68, 0.58)),
                                                     (obj, obj_faces, (0.55, 0.7, 0.85))], camera, (size, size))))
            tiles.append(np.concatenate(row, axis=1))
        paths["worst_frames.png"] = out / "worst_frames.png"
        with atomic_path(paths["worst_frames.png"], suffix=".png.tmp") as tmp:
            Image.fromarray(np.concatenate(tiles, axis=0).astype(np.uint8)).save(tmp, format="PNG")

    report = {"a": str(a_dir), "b": str(b_dir), "names": names, "worst_frames": worst_frames,
              "summary": {names[0]: docs[0]["summary"], names[1]: docs[1]["summary"]},
              "mean_abs_difference": {key: float(np.nanmean(np.abs(v))) if np.isfinite(v).any() else None
                                      for key, v in diff.items()}}
    rows += ["", "Frames where the contact error differs most (rendered in worst_frames.png, "
             f"{names[0]} left): " + ", ".join(map(str, worst_frames)), ""]
    paths["compare.md"] = out / "compare.md"
    paths["compare.json"] = out / "compare.json"
    with atomic_path(paths["compare.md"]) as tmp:
        tmp.write_text("\n".join(rows) + "\n", encoding="utf-8")
    with atomic_path(paths["compare.json"]) as tmp:
        tmp.write_text(json.dumps(report, indent=1), encoding="utf-8")
    return paths


def run_compare(clip_path, rigs, out, *, annotations=None, workers=None, stride: int = 4, frames: int | None = None,
                overrides: dict | None = None, log=print) -> dict:
    """Retarget ``clip_path`` onto each of two ``rigs`` (files or demo:NAME[@RES]), with the
    given annotation files or proposed ones, evaluate both under ``out/<rig>`` and compare them
    into ``out``."""
    from ..clip import load_clip
    from ..clip.demo import grasp_window
    from ..execute import Executor, default_workers
    from ..inputs import RunInputs, clip_source_rig, file_sha256, resolve_rig_source
    from ..pairing import pair_contacts
    from ..pipeline import retarget
    from ..solve.config import load_config
    from ..transfer.annotations import load_annotations
    from ..transfer.propose import propose_annotations
    from .report import write_evaluation

    if len(rigs) != 2:
        raise InputError(f"compare needs exactly two rigs, got {len(rigs)}", element="rig")
    if annotations and len(annotations) != 2:
        raise InputError("give one --annotations per --rig (or none to use proposed ones)", element="annotations")
    out = Path(out)
    clip = load_clip(clip_path)
    if frames:
        clip = grasp_window(clip, frames)
    source, source_entry = resolve_rig_source(clip_source_rig(clip, clip_path))
    pairs = pair_contacts(clip)
    config = load_config(None, "default", overrides)
    executor = Executor(workers=default_workers() if workers is None else workers)
    folders = []
    for k, spec in enumerate(rigs):
        target, target_entry = resolve_rig_source(spec)
        ann = load_annotations(annotations[k]) if annotations else propose_annotations(source, target)
        folder = out / f"{k + 1}_{target.name}"
        inputs = RunInputs.of(clip, source, target, ann)
        inputs.sources.update(source_rig=source_entry, target_rig=target_entry)
        inputs.sources["clip"].update(path=str(Path(clip_path).resolve()), file_sha256=file_sha256(clip_path),
                                      window=frames)
        result = retarget(inputs, config, executor, pairs=pairs)
        rig_path = None if str(spec).startswith("demo:") else spec
        result.write(folder, rig_path)
        write_evaluation(folder, stride=stride, render=False)  # the write drew the pictures
        log(f"{target.name}: median contact distance {result.summary['contact_distance_median_mm']}")
        folders.append(folder)
    return compare_outputs(folders[0], folders[1], out)
