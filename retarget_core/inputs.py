"""The inputs of one retargeting run: the clip, the source and target rigs, the annotations and
the frame range, each with the sha256 of what it was read from (provenance).

:func:`load_inputs` reads them from files or demo names (what the command line, the service's
job process and the tools call); :meth:`RunInputs.of` wraps objects already in memory (the
demo, the grid, tests). A clip's own ``source_rig`` field names a demo hand or a rig file beside
the clip whose sha256 it records (:func:`clip_source_rig`); no other path stored inside an
untrusted clip is ever opened.
"""

from __future__ import annotations

import hashlib
import math
import re
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path

import numpy as np

from .clip.format import Clip, load_clip
from .errors import InputError
from .rig.model import Rig
from .transfer.annotations import DEFAULT_MAX_DISPLACEMENT, Annotations, load_annotations

#: The demo hand the demonstration clips are made with, when a clip names no source rig.
DEFAULT_SOURCE_RIG = "demo:source_human@0.004"
#: Mesh cell sizes (m) a clip may ask its demo source hand to be built at: a clip is untrusted,
#: and a tiny cell size would build an enormous hand (the same range as every ``demo:NAME@R``,
#: :data:`~retarget_core.rig.io.DEMO_RESOLUTION_RANGE`).
CLIP_DEMO_RESOLUTIONS = (0.001, 0.02)


def file_sha256(path) -> str:
    """Hex sha256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def content_sha256(obj) -> str:
    """Hex sha256 of an in-memory input (dataclasses, arrays, numbers, strings, containers),
    independent of the machine: arrays hash their dtype, shape and little-endian bytes."""
    digest = hashlib.sha256()
    _feed(digest, obj)
    return digest.hexdigest()


def _feed(digest, obj) -> None:
    if is_dataclass(obj) and not isinstance(obj, type):
        digest.update(f"<{type(obj).__name__}>".encode())
        for f in fields(obj):
            digest.update(f.name.encode())
            _feed(digest, getattr(obj, f.name))
    elif isinstance(obj, np.ndarray):
        a = np.ascontiguousarray(obj)
        a = a.astype(a.dtype.newbyteorder("<")) if a.dtype.byteorder == ">" else a
        digest.update(f"array{a.dtype.str}{a.shape}".encode())
        digest.update(a.tobytes())
    elif isinstance(obj, dict):
        digest.update(b"{")
        for k in sorted(obj, key=str):
            digest.update(str(k).encode())
            _feed(digest, obj[k])
        digest.update(b"}")
    elif isinstance(obj, (list, tuple)):
        digest.update(f"[{len(obj)}".encode())
        for v in obj:
            _feed(digest, v)
    elif isinstance(obj, (bool, int, float, str, type(None), np.generic)):
        digest.update(repr(obj.item() if isinstance(obj, np.generic) else obj).encode())
    else:
        raise TypeError(f"cannot hash {type(obj).__name__} as a run input")


_FRAMES = re.compile(r"\s*(\d*)\s*:\s*(\d*)\s*")


def parse_frames(text: str) -> tuple[int | None, int | None]:
    """``"START:END"`` (either side may be empty) -> (start, end); a clear error otherwise."""
    m = _FRAMES.fullmatch(str(text))
    if m is None:
        raise InputError(f"expected START:END (frame numbers, end excluded, either may be empty), got {text!r}",
                         element="frames")
    return (int(m.group(1)) if m.group(1) else None, int(m.group(2)) if m.group(2) else None)


def frame_range(frames, n_frames: int) -> tuple[int, int]:
    """Check a frame range (start, end) — None / missing ends mean the clip's — against a clip
    of ``n_frames``; returns (start, end) with 0 <= start < end <= n_frames."""
    if frames is None:
        return 0, n_frames
    if isinstance(frames, str):
        frames = parse_frames(frames)
    try:
        start, end = frames
    except (TypeError, ValueError):
        raise InputError(f"expected a (start, end) pair, got {frames!r}", element="frames") from None
    start = 0 if start is None else start
    end = n_frames if end is None else end
    for v in (start, end):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
            raise InputError(f"frame numbers must be integers, got {v!r}", element="frames")
    if not 0 <= start < end <= n_frames:
        raise InputError(f"frames {start}:{end} are not a non-empty range within the clip's 0:{n_frames}",
                         element="frames")
    return int(start), int(end)


@dataclass
class RunInputs:
    """What one run reads. ``frames``: [start, end) of ``clip`` to retarget (None = all).
    ``sources``: {input name: {"sha256", and "path" or "spec" when read from one}}.
    ``annotation_max_displacement``: how far (metres) an annotated point may move when the
    annotations are carried onto an edited rig mesh
    (:func:`~retarget_core.transfer.annotations.remap_to_meshes`)."""

    clip: Clip
    source_rig: Rig
    target_rig: Rig
    annotations: Annotations
    frames: tuple | None = None
    sources: dict = field(default_factory=dict)
    annotation_max_displacement: float = DEFAULT_MAX_DISPLACEMENT

    @classmethod
    def of(cls, clip: Clip, source_rig: Rig, target_rig: Rig, annotations: Annotations, frames=None, *,
           names: dict | None = None,
           annotation_max_displacement: float = DEFAULT_MAX_DISPLACEMENT) -> "RunInputs":
        """Inputs already in memory; their sha256 is taken from their content. ``names``:
        optional {input name: where it came from} (e.g. ``{"target_rig": "demo:witch@0.003"}``)."""
        sources = names or {}
        described = {}
        for name, obj in (("clip", clip), ("source_rig", source_rig), ("target_rig", target_rig),
                          ("annotations", annotations)):
            described[name] = {"sha256": content_sha256(obj)}
            if name in sources:
                described[name]["spec"] = str(sources[name])
        return cls(clip, source_rig, target_rig, annotations, frames, described, annotation_max_displacement)

    def provenance(self) -> dict:
        return {name: dict(v) for name, v in self.sources.items()}


def resolve_rig_source(spec: str, **load_options) -> tuple[Rig, dict]:
    """A rig from a file path, ``demo:NAME[@RES]`` or ``installed:NAME[@RES]``, with its
    provenance entry."""
    from .rig.io import installed_model, resolve_rig

    rig = resolve_rig(spec, **load_options)
    spec = str(spec)
    if spec.startswith("demo:"):
        return rig, {"spec": spec, "sha256": content_sha256(rig)}
    if spec.startswith("installed:"):
        model = installed_model(spec[len("installed:"):].partition("@")[0])
        return rig, {"spec": spec, "path": str(model), "sha256": file_sha256(model)}
    return rig, {"path": str(Path(spec).resolve()), "sha256": file_sha256(spec)}


def clip_source_rig(clip: Clip, clip_path=None) -> str:
    """The source rig a clip records: a demo hand (``DEFAULT_SOURCE_RIG`` when it names none), or
    the rig file an import wrote beside it (a GRAB clip's MANO rig), returned as its path.

    A clip is untrusted input, so a recorded file is used only when ``clip_path`` (where the clip
    was read from) is given, the recorded path is relative and stays inside the clip's folder, and
    the file's sha256 is the one the clip records; anything else is refused, never opened. The
    service passes no path: it resolves a recorded rig by its hash among the owner's assets."""
    spec = clip.source_rig or DEFAULT_SOURCE_RIG
    if not str(spec).startswith("demo:"):
        return _recorded_rig_file(clip, spec, clip_path)
    name, _, res = spec.partition("@")
    lo, hi = CLIP_DEMO_RESOLUTIONS
    try:
        value = float(res) if res else None
    except ValueError:
        value = float("nan")
    if value is not None and not (math.isfinite(value) and lo <= value <= hi):
        raise InputError(f"the clip asks for its demo source hand at resolution {res!r}; a clip may ask for "
                         f"{lo:g} to {hi:g} m", source="clip", element="source_rig")
    from .rig.demo_hands import DEMO_HANDS

    if name[len("demo:"):] not in DEMO_HANDS:
        raise InputError(f"the clip names an unknown demo hand {name[len('demo:'):]!r} (known: {', '.join(DEMO_HANDS)})",
                         source="clip", element="source_rig")
    return spec


def _recorded_rig_file(clip: Clip, spec: str, clip_path) -> str:
    from .rig.io import USD_SUFFIXES

    settle = "or give the source rig explicitly (--source-rig on the command line, source_rig in a job request)"
    if clip_path is None or not clip.source_rig_sha256:
        raise InputError(f"the clip names its source rig {spec!r}, which is not a demo hand; a clip may name a rig "
                         f"file only beside itself with the file's sha256 (as import-grab writes it): {settle}",
                         source="clip", element="source_rig")
    relative = Path(spec)
    if relative.is_absolute() or ".." in relative.parts or relative.suffix.lower() not in USD_SUFFIXES:
        raise InputError(f"the clip names its source rig {spec!r}: a recorded rig must be a USD file in the clip's "
                         f"own folder (a relative path without '..'); {settle}", source=str(clip_path),
                         element="source_rig")
    path = Path(clip_path).resolve().parent / relative
    if not path.is_file():
        raise InputError(f"the clip's source rig {spec!r} is not beside the clip (looked for {path}): keep the rig "
                         f"import-grab wrote with the clip, {settle}", source=str(clip_path), element="source_rig")
    digest = file_sha256(path)
    if digest != clip.source_rig_sha256:
        raise InputError(f"the clip's source rig {path} has changed since the clip was made (sha256 {digest[:12]}..., "
                         f"the clip records {clip.source_rig_sha256[:12]}...): re-run import-grab, {settle}",
                         source=str(clip_path), element="source_rig")
    return str(path)


def load_inputs(clip, rig, annotations, *, source_rig=None, frames=None,
                annotation_max_displacement: float = DEFAULT_MAX_DISPLACEMENT, target_options: dict | None = None,
                clip_rig_files: bool = True, **rig_options) -> RunInputs:
    """Read a run's inputs: ``clip`` and ``annotations`` file paths, ``rig`` and ``source_rig``
    file paths or ``demo:NAME[@RES]`` (``source_rig`` None: the demo hand the clip names, see
    :func:`clip_source_rig`), ``frames`` (start, end), ``"START:END"`` or None.
    Annotations made for an earlier version of a rig's mesh are carried onto the current one by
    the run (points within ``annotation_max_displacement`` metres, see :class:`RunInputs`); a
    mismatch they cannot survive is reported here, before any work. ``rig_options`` go to both
    rigs' loaders (:func:`~retarget_core.rig.io.load_rig`), ``target_options`` to the target's
    only (``root_body`` of an MJCF hand, ``mapping`` for a plain UsdSkel hand's DOFs).
    ``clip_rig_files``: a rig file the clip records beside itself may be used (the command line);
    False (the service) takes only a demo hand the clip names."""
    loaded = load_clip(clip)
    sources = {"clip": {"path": str(Path(clip).resolve()), "sha256": file_sha256(clip)}}
    source, sources["source_rig"] = resolve_rig_source(
        source_rig or clip_source_rig(loaded, clip if clip_rig_files else None), **rig_options)
    target, sources["target_rig"] = resolve_rig_source(rig, **(rig_options | {k: v for k, v in (target_options or {}).items()
                                                                             if v is not None}))
    ann = load_annotations(annotations)
    sources["annotations"] = {"path": str(Path(annotations).resolve()), "sha256": file_sha256(annotations)}
    frame_range(frames, loaded.n_frames)  # a bad range is reported before any work
    from .transfer.annotations import remap_to_meshes

    # a mesh the annotations cannot be carried onto is reported before any work (the run
    # remaps again, from the annotations as read, and records the report)
    remap_to_meshes(ann, source, target, max_displacement=annotation_max_displacement, source=str(annotations))
    return RunInputs(loaded, source, target, ann, frames, sources, annotation_max_displacement)
