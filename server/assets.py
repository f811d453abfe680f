"""Validating uploaded assets with the core's own readers, before anything is recorded.

Kinds: ``rig`` (one USD layer, a .usdz / zip USD package, or a zip of a URDF / MJCF robot hand
with its meshes; every file a rig names must lie inside the upload, and what is stored is the
rig as one self-contained USD layer), ``annotations``
(JSON), ``clip`` (native npz, read with ``allow_pickle=False``) and ``file`` (raw inputs of the
GRAB importer: a sequence, the user's MANO model, meshes; they are only ever opened by the
restricted GRAB loader in :func:`import_grab_clip`).
"""

from __future__ import annotations

import shutil
import stat
import zipfile
from pathlib import Path, PurePosixPath
from typing import get_args

from retarget_core.errors import InputError

from .schemas import AssetKind

KINDS = get_args(AssetKind)
FILE_SUFFIXES = (".npz", ".pkl", ".ply", ".obj", ".stl", ".off")
ROBOT_SUFFIXES = (".urdf", ".xml", ".mjcf")
USD_SUFFIXES = (".usd", ".usda", ".usdc")
MAX_BUNDLE_MEMBERS = 2000


class UploadError(ValueError):
    """An upload that is not a valid asset of its kind (HTTP 422)."""


def sniff_rig(head: bytes) -> str:
    """The rig upload's container from its first bytes: '.usda', '.usdc' or '.zip'."""
    if head.startswith(b"PK\x03\x04"):
        return ".zip"
    if head.startswith(b"PXR-USDC"):
        return ".usdc"
    if head.lstrip().startswith(b"#usda"):
        return ".usda"
    raise UploadError("a rig must be a USD file (usda or usdc) or a zip of a URDF or MJCF robot hand with its meshes")


def rig_info(rig) -> dict:
    """What a client shows of a stored rig: counts, and each DOF's joint, kind and limits
    (radians / metres; the add-in's panel lists them for editing) and where they came from."""
    surface = rig.surface
    limits = [{"name": d.name, "joint": rig.joints[d.joint].name, "kind": d.kind, "lower": float(d.lower),
               "upper": float(d.upper), "rest": float(d.rest)} for d in rig.dofs]
    meta = rig.metadata
    return {"name": rig.name, "dofs": rig.n_dofs, "dof_names": list(rig.dof_names),
            "vertices": int(surface.n_vertices), "faces": int(len(surface.faces)), "dof_limits": limits,
            # the mesh a clip made with this hand carries (the surface before caps closed it)
            "hand_mesh": _hand_mesh(rig),
            "dof_source": str(meta.get("dof_source", "the rig's DOF spec")),
            "free_root_added": meta.get("free_root_added") or None,  # the joint name, when one was added
            "rig_warnings": [str(w) for w in meta.get("warnings", [])]} | (
        # a surface cut from the uploaded mesh: where its vertices and triangles are in that mesh
        {"surface_source": meta["surface_source"]} if meta.get("surface_source") else {})


def _hand_mesh(rig) -> dict:
    from retarget_core.rig.hand_cut import SURFACE_SOURCE, uncapped_faces

    n_faces = uncapped_faces(rig)
    centres = 0
    if n_faces < len(rig.surface.faces):
        centres = sum(1 for v in (rig.metadata.get(SURFACE_SOURCE) or {}).get("vertices", []) if v < 0)
    return {"vertices": int(rig.surface.n_vertices - centres), "faces": int(n_faces)}


def clip_info(clip) -> dict:
    return {"frames": clip.n_frames, "fps": float(clip.fps), "source_rig": clip.source_rig,
            "source_rig_sha256": clip.source_rig_sha256, "hand": clip.hand or "right",
            "object": clip.object_name, "hand_vertices": int(clip.hand_vertices.shape[1]),
            "hand_faces": int(len(clip.hand_faces)), "motion": clip.motion}


def recorded_source_rig(store, owner: str, clip_asset):
    """The owner's rig asset a clip records as its source rig by content (a GRAB import's MANO
    hand: ``source_rig_sha256`` is that rig's asset id); None when the clip records none.
    Raises InputError when it records one the owner does not have. A path a clip records is
    never opened here: only the hash is used, and only among the owner's own assets."""
    sha = clip_asset.info.get("source_rig_sha256") or ""
    if not sha:
        return None
    asset = store.asset(owner, sha, "rig")
    if asset is None:
        raise InputError(f"the clip records its source rig by content (rig {sha}), and you have no such rig asset: "
                         "upload the rig the clip was made with (POST /v1/assets/rig) or pass source_rig",
                         source="clip", element="source_rig")
    return asset


def annotations_info(ann) -> dict:
    return {"source": ann.source.to_dict(), "target": ann.target.to_dict(), "markers": len(ann.markers),
            "curves": len(ann.curves)}


def stored_rig_options(info: dict) -> dict:
    """The loader options a stored rig is read with at every use (``hand_root`` of a USD rig,
    kept in its info as ``load_options``; a robot bundle's ``root_body`` was applied at import)."""
    return dict(info.get("load_options") or {})


def validate_upload(kind: str, tmp: Path, filename: str, *, scratch: Path, bundle_bytes: int,
                    rig_options: dict | None = None) -> tuple[Path, str, dict]:
    """Check the upload at ``tmp`` (no suffix) as a ``kind`` asset. Returns (path to move to the
    content address, its suffix, info). ``rig_options``: ``root_body`` (an MJCF hand in a
    bundle) and ``hand_root`` (a hand inside a USD character), None values left out. Raises
    :class:`UploadError` naming the problem; the caller removes what is left under ``scratch``."""
    options = {k: v for k, v in (rig_options or {}).items() if v is not None}
    if options and kind != "rig":
        raise UploadError(f"{', '.join(sorted(options))} only apply to rig uploads")
    head = tmp.open("rb").read(16)
    if kind == "annotations":
        from retarget_core.transfer.annotations import load_annotations

        path = tmp.rename(tmp.with_suffix(".json"))
        return path, ".json", annotations_info(_core(load_annotations, path))
    if kind == "clip":
        from retarget_core.clip import load_clip

        if not head.startswith(b"PK\x03\x04"):
            raise UploadError("a clip must be a native clip .npz (a zip archive); convert GRAB sequences with "
                              "POST /v1/clips/import-grab")
        path = tmp.rename(tmp.with_suffix(".npz"))
        return path, ".npz", clip_info(_core(load_clip, path))
    if kind == "file":
        suffix = Path(filename).suffix.lower()
        if suffix not in FILE_SUFFIXES:
            raise UploadError(f"a file upload needs a name ending in one of {', '.join(FILE_SUFFIXES)} "
                              f"(got {filename!r})")
        path = tmp.rename(tmp.with_suffix(suffix))
        return path, suffix, {"suffix": suffix}
    if kind == "rig":
        from retarget_core.rig.io import load_rig, save_rig
        from retarget_core.rig.usd_io import flatten_confined

        suffix = sniff_rig(head)
        if suffix != ".zip":
            # One USD layer: it may compose no other layer (refused, naming the arc); other asset
            # paths are dropped; the flattened layer is what is stored and what jobs open.
            path = tmp.rename(tmp.with_suffix(suffix))
            flat = scratch / f"rig{suffix}"
            warnings = _core(lambda p: flatten_confined(p, flat), path, scratch=scratch, name=filename)
            info = rig_info(_core(lambda p: load_rig(p, confine_to=p, **options), flat, scratch=scratch, name=filename))
            tmp.with_suffix(suffix).unlink(missing_ok=True)
            warnings = [w.replace(path.name, filename) for w in warnings]
            return flat, suffix, info | ({"warnings": warnings} if warnings else {}) | (
                {"load_options": options} if options else {})
        folder = scratch / "bundle"
        entry = _unpack_bundle(tmp, folder, bundle_bytes)
        shown = entry.relative_to(folder).as_posix()
        tmp.unlink()
        if entry.suffix.lower() in USD_SUFFIXES:
            # A .usdz / zip USD package: composed with every layer confined to the package.
            flat = scratch / "rig.usdc"
            warnings = _core(lambda p: flatten_confined(p, flat, confine_to=folder), entry, scratch=scratch)
            info = rig_info(_core(lambda p: load_rig(p, confine_to=p, **options), flat, scratch=scratch, name=filename))
            return flat, ".usdc", info | {"imported_from": shown} | ({"warnings": warnings} if warnings else {}) | (
                {"load_options": options} if options else {})
        # A robot bundle: unpacked safely, imported with every file it names confined to the
        # bundle (wrapper surface built once, here), and kept as the USD rig the jobs read, so
        # every job sees the same surface the annotations name.
        rig = _core(lambda p: load_rig(p, confine_to=folder, **options), entry, scratch=scratch)
        usd = scratch / "rig.usda"
        save_rig(rig, usd)
        return usd, ".usda", rig_info(rig) | {"imported_from": shown} | ({"import_options": options} if options else {})
    raise UploadError(f"unknown asset kind {kind!r} (known: {', '.join(KINDS)})")


def _core(fn, path, *, scratch: Path | None = None, name: str | None = None):
    try:
        return fn(path)
    except InputError as err:
        message = _without_path(str(err), path, scratch)
        if name is not None:  # the server's file name of a single-file upload is the client's name
            message = message.replace(path.name, name)
        raise UploadError(message) from err


def _without_path(message: str, path: Path, scratch: Path | None = None) -> str:
    """Core errors name the file; the client never sees the server's paths."""
    message = message.replace(str(path), path.suffix.lstrip(".") + " upload").replace(str(path.parent) + "/", "")
    if scratch is not None:
        for folder in sorted({str(scratch / "bundle"), str(scratch), str(scratch.resolve())}, key=len, reverse=True):
            message = message.replace(folder + "/", "").replace(folder, "upload")
    return message


def _unpack_bundle(archive: Path, folder: Path, limit: int) -> Path:
    """Extract a robot bundle zip into ``folder`` refusing absolute paths, '..', links and more
    than ``limit`` bytes unpacked; return the one URDF / MJCF file at its top level."""
    try:
        zf = zipfile.ZipFile(archive)
    except zipfile.BadZipFile as err:
        raise UploadError("the rig zip is not a readable zip archive") from err
    with zf:
        members = zf.infolist()
        if len(members) > MAX_BUNDLE_MEMBERS:
            raise UploadError(f"the rig zip holds {len(members)} entries (at most {MAX_BUNDLE_MEMBERS})")
        if sum(m.file_size for m in members) > limit:
            raise UploadError(f"the rig zip unpacks to more than {limit} bytes")
        for m in members:
            name = PurePosixPath(m.filename)
            if name.is_absolute() or ".." in name.parts or "\\" in m.filename:
                raise UploadError(f"the rig zip has an unsafe path {m.filename!r}")
            if stat.S_ISLNK(m.external_attr >> 16):
                raise UploadError(f"the rig zip has a symbolic link {m.filename!r}")
        folder.mkdir(parents=True)
        for m in members:
            dest = folder / PurePosixPath(m.filename)
            if m.is_dir():
                dest.mkdir(parents=True, exist_ok=True)
                continue
            dest.parent.mkdir(parents=True, exist_ok=True)
            with zf.open(m) as src, dest.open("wb") as out:
                shutil.copyfileobj(src, out)
    entries = sorted(p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in ROBOT_SUFFIXES
                     and len(p.relative_to(folder).parts) <= 2)
    if entries and any(p.suffix.lower() == ".urdf" for p in entries):
        entries = [p for p in entries if p.suffix.lower() == ".urdf"]
    if not entries:  # a .usdz / zip USD package: its first entry, or its one top-level layer
        first = next((PurePosixPath(m.filename) for m in members if not m.is_dir()), None)
        if first is not None and first.suffix.lower() in USD_SUFFIXES:
            return folder / first
        entries = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in USD_SUFFIXES)
        if len(entries) == 1:
            return entries[0]
    if len(entries) != 1:
        names = ", ".join(str(p.relative_to(folder)) for p in entries) or "none"
        raise UploadError("the rig zip must hold exactly one URDF or MJCF file at its top level, or be a USD "
                          f"package (.usdz) whose first entry is its root layer (found: {names})")
    return entries[0]


def import_grab_clip(sequence: Path, mano: Path, object_mesh: Path, table_mesh: Path | None, vtemp: Path | None,
                     hand: str = "right"):
    """One hand of uploaded GRAB files as a :class:`~retarget_core.clip.grab.GrabHand` (the
    clip and what its MANO source rig is built from), by the core's restricted loader: nothing
    outside numpy's array types is ever unpickled."""
    from retarget_core.clip.grab import import_grab_hand

    try:
        return import_grab_hand(sequence, mano, hand=hand, object_mesh=object_mesh, table_mesh=table_mesh, vtemp=vtemp)
    except InputError as err:
        message = str(err)
        for p in (sequence, mano, object_mesh, table_mesh, vtemp):
            if p is not None:
                message = message.replace(str(p), p.name[:12] + "…" + p.suffix)
        raise UploadError(message) from err
