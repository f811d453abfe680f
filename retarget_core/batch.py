"""Many clips onto one or more hands: a GRAB dataset (or a manifest of clips) retargeted as a batch,
resumable, with one summary table of every result's figures.

Layout of a batch folder (``out``)::

    clips/<name>.npz, clips/<name>.source_rig.usda    converted GRAB sequences (when converting)
    annotations/<source rig>-<sha>__<hand>.json       proposed once per source rig (content) and hand
    results/<clip>__<hand>/                           one retarget's files (RetargetResult.write)
    summary.csv, summary.md                           one row per (clip, hand)

Every output is written beside its final name and renamed into place when complete, so an
interrupted batch leaves no half-written output, and a restarted one skips what is finished.
What a run computes (clips, hands, annotations, configuration) is the caller's; how it executes
(workers, a Dask cluster, the atlas cache, by default ``out/atlas_cache``) is the executor's."""

from __future__ import annotations

import csv
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from .errors import InputError

SUMMARY_FIELDS = ("clip", "hand", "status", "frames", "contact_frames", "contact_distance_median_mm",
                  "marker_error_median_mm", "solved_contact_distance_median_mm", "transferred_share",
                  "unmapped_contacts", "seconds", "result", "error")


# ---- GRAB datasets ---------------------------------------------------------------------------
def grab_sequences(root) -> list[tuple[str, Path]]:
    """(name, path) of every GRAB sequence under ``root``: the released tree
    (``root/grab/<subject>/<sequence>.npz``), subject folders (``root/<subject>/*.npz``) or flat
    files (``root/*.npz``); names are ``<subject>_<sequence>`` where there is a subject folder.
    GRAB's ``tools`` folder (meshes) is never searched."""
    root = Path(root)
    if not root.is_dir():
        raise InputError("not a folder (the GRAB root: its 'grab/<subject>/' sequences and 'tools/' meshes)",
                         source=str(root))
    base = root / "grab" if (root / "grab").is_dir() else root
    found = []
    for path in sorted(base.rglob("*.npz")):
        rel = path.relative_to(base)
        if rel.parts[0] == "tools" or any(p.startswith(".") for p in rel.parts):
            continue
        name = "_".join([*rel.parts[:-1], path.stem]) if len(rel.parts) > 1 else path.stem
        found.append((name, path))
    if not found:
        raise InputError("no GRAB sequences (*.npz) found: GRAB's released layout keeps them in "
                         "grab/<subject>/<sequence>.npz under the GRAB root", source=str(root))
    return found


def convert_grab(root, out_clips, mano: dict, *, hands=("right",), log=print) -> list[Path]:
    """Convert every sequence of :func:`grab_sequences` (``mano``: {hand: MANO model path}) into
    ``out_clips/<name>.npz`` (``<name>_left.npz`` for a left hand) with its source rig beside it;
    a clip already converted is kept. Returns the clip paths, in order."""
    from .clip.grab import import_grab_hand, save_grab_hand

    out_clips = Path(out_clips)
    out_clips.mkdir(parents=True, exist_ok=True)
    clips = []
    for name, path in grab_sequences(root):
        for hand in hands:
            clip_path = out_clips / f"{name}{'' if hand == 'right' else '_left'}.npz"
            rig_path = clip_path.with_name(clip_path.name.removesuffix(".npz") + ".source_rig.usda")
            if clip_path.is_file() and rig_path.is_file():
                clips.append(clip_path)
                continue
            imported = import_grab_hand(path, mano[hand], hand=hand, grab_root=root)
            save_grab_hand(imported, clip_path)
            log(f"converted {path} ({hand} hand) -> {clip_path}")
            clips.append(clip_path)
    return clips


def read_manifest(path) -> list[Path]:
    """Clip paths listed in a manifest: one per line (``#`` comments, blank lines skipped) or a
    JSON list; relative paths are relative to the manifest's folder."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(f"cannot read the manifest: {exc}", source=str(path)) from None
    if text.lstrip().startswith("["):
        try:
            entries = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InputError(f"the manifest is not valid JSON: {exc}", source=str(path)) from None
        if not all(isinstance(e, str) for e in entries):
            raise InputError("a JSON manifest is a list of clip paths (strings)", source=str(path))
    else:
        entries = [line.strip() for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")]
    clips = [(path.parent / e) if not Path(e).is_absolute() else Path(e) for e in entries]
    missing = [str(c) for c in clips if not c.is_file()]
    if missing:
        raise InputError(f"the manifest lists clips that do not exist: {', '.join(missing[:5])}", source=str(path))
    if not clips:
        raise InputError("the manifest lists no clips", source=str(path))
    return clips


# ---- the batch ---------------------------------------------------------------------------------
@dataclass
class BatchReport:
    """What :func:`run_batch` did: rows (one dict per (clip, hand), :data:`SUMMARY_FIELDS`),
    counts of results made now, skipped (finished before) and failed, and the summary files."""

    rows: list
    made: int
    skipped: int
    failed: int
    summary_csv: Path
    summary_md: Path


def _label(spec: str, rig) -> str:
    text = str(spec)
    if text.startswith(("demo:", "installed:")):
        return rig.name
    return Path(text).stem


def run_batch(clips, hands, out, *, config, executor, annotations=None, log=print) -> BatchReport:
    """Retarget every clip (paths; each names its source rig, :func:`~retarget_core.inputs.clip_source_rig`)
    onto every hand in ``hands`` (rig specs: files, ``demo:NAME``, ``installed:NAME``) into
    ``out/results``; ``annotations``: one annotation file for every clip and hand, or None to
    propose them once per (source rig, hand). A result folder that exists is finished and is
    skipped; a failed item is recorded in the summary and the batch goes on."""
    from .clip import load_clip
    from .inputs import clip_source_rig, load_inputs, resolve_rig_source
    from .pipeline import retarget
    from .transfer.annotations import save_annotations, with_positions
    from .transfer.propose import propose

    out = Path(out)
    results, proposed = out / "results", out / "annotations"
    results.mkdir(parents=True, exist_ok=True)
    if executor.cache_dir is None:  # one atlas per (source rig, hand, annotations), kept across restarts
        executor.atlas_cache = out / "atlas_cache"
    targets = []
    for spec in hands:
        rig, _ = resolve_rig_source(spec)
        targets.append((str(spec), rig, _label(spec, rig)))
    labels = [t[2] for t in targets]
    if len(set(labels)) != len(labels):
        raise InputError(f"two hands share the output name {labels}: give rig files distinct names", element="rig")
    sources: dict[str, object] = {}
    rows, made, skipped, failed = [], 0, 0, 0
    for clip_path in clips:
        clip_path = Path(clip_path)
        for spec, target, label in targets:
            name = f"{clip_path.stem}__{label}"
            final = results / name
            row = {"clip": clip_path.stem, "hand": label, "result": str(final.relative_to(out))}
            if final.is_dir():
                skipped += 1
                rows.append(row | _figures(final))
                continue
            partial = results / f"{name}.partial"
            shutil.rmtree(partial, ignore_errors=True)
            try:
                clip = load_clip(clip_path)
                source_spec = clip_source_rig(clip, clip_path)
                if source_spec not in sources:
                    sources[source_spec] = resolve_rig_source(source_spec)
                source, entry = sources[source_spec]
                # one proposal per source rig content (a subject's clips share their MANO hand)
                ann_path = (Path(annotations) if annotations
                            else proposed / f"{source.name}-{entry['sha256'][:12]}__{label}.json")
                if not annotations and not ann_path.is_file():
                    proposed.mkdir(parents=True, exist_ok=True)
                    proposal = propose(source, target)
                    save_annotations(with_positions(proposal.annotations, source, target), ann_path)
                inputs = load_inputs(clip_path, spec, ann_path, source_rig=source_spec)
                result = retarget(inputs, config, executor)
                rig_path = None if spec.startswith(("demo:", "installed:")) else spec
                result.write(partial, rig_path)
                os.replace(partial, final)
            except InputError as err:
                shutil.rmtree(partial, ignore_errors=True)
                failed += 1
                rows.append(row | {"status": "failed", "error": str(err)})
                log(f"{name}: failed: {err}")
                continue
            made += 1
            rows.append(row | _figures(final))
            log(f"{name}: contact distance {rows[-1]['contact_distance_median_mm']} mm "
                f"({rows[-1]['seconds']} s)")
    summary_csv, summary_md = _write_summary(out, rows)
    return BatchReport(rows, made, skipped, failed, summary_csv, summary_md)


def _figures(folder: Path) -> dict:
    """The summary figures of a finished result folder (its result.json)."""
    try:
        summary = json.loads((folder / "result.json").read_text(encoding="utf-8"))["summary"]
    except (OSError, ValueError, KeyError) as exc:
        return {"status": "failed", "error": f"unreadable result.json ({exc}): delete the folder to redo it"}
    row = {"status": "ok"}
    for key in SUMMARY_FIELDS:
        if key in summary:
            value = summary[key]
            row[key] = round(value, 3) if isinstance(value, float) else value
    return row


def _write_summary(out: Path, rows: list) -> tuple[Path, Path]:
    from .files import atomic_path

    csv_path, md_path = out / "summary.csv", out / "summary.md"
    with atomic_path(csv_path, suffix=".csv") as tmp:
        with open(tmp, "w", newline="", encoding="utf-8") as fh:
            writer = csv.DictWriter(fh, fieldnames=SUMMARY_FIELDS)
            writer.writeheader()
            for row in rows:
                writer.writerow({k: row.get(k, "") for k in SUMMARY_FIELDS})
    shown = ("clip", "hand", "status", "frames", "contact_frames", "contact_distance_median_mm",
             "marker_error_median_mm", "seconds")
    lines = ["| " + " | ".join(shown) + " |", "|" + "---|" * len(shown)]
    for row in rows:
        lines.append("| " + " | ".join(str(row.get(k, "")) for k in shown) + " |")
    ok = [r["contact_distance_median_mm"] for r in rows if r.get("status") == "ok"
          and isinstance(r.get("contact_distance_median_mm"), (int, float))]
    if ok:
        ok.sort()
        lines.append(f"\n{len(ok)} results; median of the contact distance medians {ok[len(ok) // 2]:.2f} mm")
    with atomic_path(md_path, suffix=".md") as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n", encoding="utf-8")
    return csv_path, md_path
