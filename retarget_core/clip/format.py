"""The source clip: one captured (or generated) hand-object demonstration.

Stored as an ``.npz`` read with ``allow_pickle=False`` (so a clip file can never run code).
Every array has a fixed name, dtype and shape; :meth:`Clip.validate` names the first bad field
(and frame). Units: metres, seconds; world frame is Z-up. Version 2 (written since stop 53)
adds the optional contact surface points; version 1 files (without them) still read. Fields:

==================== ============ ===============================================================
field                shape        meaning
==================== ============ ===============================================================
format               ()           the string "handretarget.clip"
version              ()           2 (1: no contact surface points)
fps                  ()           frames per second (float64), 1 to 10000
hand_faces           (Fh, 3)      source hand triangles (int32)
hand_vertices        (T, Vh, 3)   source hand vertices per frame, world (float32)
object_vertices      (Vo, 3)      object mesh in its own frame (float64)
object_faces         (Fo, 3)      object triangles (int32)
object_poses         (T, 4, 4)    rigid world-from-object transform per frame (float64)
contact_labels       (T, Vo)      per-frame contact code of each object vertex, GRAB's
                                  convention: 0 = none, 22 = right palm, 41-55 = right fingers
                                  (uint8)
contact_offsets      (T + 1,)     optional (version 2): frame f's contact surface points are rows
                                  contact_offsets[f]:contact_offsets[f + 1] of the next three;
                                  when present, pairing uses them instead of contact_labels
                                  (which then mark each point's nearest vertex, for display)
contact_faces        (N,)         ... object face of each point (int32)
contact_barycentric  (N, 3)       ... its barycentric coordinates in that face (float64)
contact_codes        (N,)         ... its contact code, as contact_labels (uint8)
table_pose           (4, 4)       optional: world-from-table-box transform; the box is centred on
                                  its frame's origin, so its top is at +table_half_extents[2]
table_half_extents   (3,)         optional, with table_pose
marker_names         (M,)         optional source virtual markers: names (unicode)
marker_faces         (M,)         ... on the source hand mesh: face index (int32)
marker_barycentric   (M, 3)       ... and barycentric coordinates (float64)
dof_names            (D,)         optional ground truth of a generated clip: source rig DOFs
dof_values           (T, D)       ... their values per frame (float64)
source_rig           ()           optional: which rig made the clip: a demo hand
                                  ("demo:source_human@0.005") or a rig file's path relative to
                                  the clip's folder (a GRAB import's MANO rig)
source_rig_sha256    ()           optional, with a file source_rig: the sha256 of that file (the
                                  file is used only when its bytes match)
hand                 ()           optional: "right" (default) or "left"; contact codes use the
                                  right-hand numbering either way (a left GRAB hand's 21, 26-40 are
                                  stored as 22, 41-55)
object_name          ()           e.g. "bottle"
motion               ()           e.g. "pick_place"
source               ()           provenance, e.g. "demo" or "grab:s1/apple_eat_1"
==================== ============ ===============================================================

Reading is bounded: :func:`load_clip` first reads every member's npy header (never its data) and
refuses, naming the member, a pickled dtype, a malformed header, a declared array larger than the
member holds, a scalar field that is not a scalar of its kind (fps of shape (2,), version "one",
string faces) and a clip whose members add up to more than ``max_bytes`` uncompressed
(:data:`MAX_CLIP_BYTES`, 2 GiB, by default): a 1 MB upload can no longer decompress into gigabytes.
"""

from __future__ import annotations

import zipfile
import zlib
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import save_npz_atomic

CLIP_FORMAT = "handretarget.clip"
#: Frame rates a clip may have (capture systems record 30-240 Hz; the bounds keep the spline's
#: control-point count and the filter's cutoff finite).
FPS_RANGE = (1.0, 10_000.0)
#: Default limit of a clip's uncompressed size (the sum of its members) in :func:`load_clip`.
MAX_CLIP_BYTES = 2 * 1024 ** 3
#: Largest npy header read (numpy's own default).
_MAX_HEADER = 10_000
CLIP_VERSION = 2
#: Versions :func:`load_clip` reads (1: without contact surface points).
READABLE_VERSIONS = (1, 2)

#: GRAB's right-hand contact codes (22 = palm/hand, 41-55 = the 15 finger segments).
RIGHT_HAND_CONTACT_CODES = frozenset([22, *range(41, 56)])


@dataclass
class Clip:
    """An in-memory clip; see the module docstring for every field."""

    fps: float
    hand_faces: np.ndarray
    hand_vertices: np.ndarray
    object_vertices: np.ndarray
    object_faces: np.ndarray
    object_poses: np.ndarray
    contact_labels: np.ndarray
    contact_offsets: np.ndarray | None = None
    contact_faces: np.ndarray | None = None
    contact_barycentric: np.ndarray | None = None
    contact_codes: np.ndarray | None = None
    table_pose: np.ndarray | None = None
    table_half_extents: np.ndarray | None = None
    marker_names: list[str] = field(default_factory=list)
    marker_faces: np.ndarray | None = None
    marker_barycentric: np.ndarray | None = None
    dof_names: list[str] = field(default_factory=list)
    dof_values: np.ndarray | None = None
    source_rig: str = ""
    object_name: str = ""
    source_rig_sha256: str = ""
    hand: str = ""
    motion: str = ""
    source: str = ""

    @property
    def n_frames(self) -> int:
        return int(self.hand_vertices.shape[0])

    @property
    def duration(self) -> float:
        """Seconds."""
        return self.n_frames / float(self.fps)

    @property
    def has_table(self) -> bool:
        return self.table_pose is not None

    def object_world_vertices(self, frame: int) -> np.ndarray:
        """(Vo, 3) object vertices in world coordinates at ``frame``."""
        pose = self.object_poses[frame]
        return self.object_vertices @ pose[:3, :3].T + pose[:3, 3]

    def contact_vertex_ids(self, frame: int) -> np.ndarray:
        """Object vertex ids labelled as contact at ``frame``."""
        return np.nonzero(self.contact_labels[frame])[0]

    def markers(self) -> dict[str, tuple[int, np.ndarray]]:
        """{marker name: (face, barycentric (3,))} on the source hand."""
        if self.marker_faces is None:
            return {}
        return {n: (int(f), self.marker_barycentric[i]) for i, (n, f) in enumerate(zip(self.marker_names, self.marker_faces))}

    def slice(self, start: int, stop: int) -> "Clip":
        """Frames [start, stop) as a new clip."""
        sub = {f.name: getattr(self, f.name) for f in fields(self)}
        for name in ("hand_vertices", "object_poses", "contact_labels", "dof_values"):
            if sub[name] is not None:
                sub[name] = sub[name][start:stop]
        if self.contact_offsets is not None:
            start, stop, _ = slice(start, stop).indices(self.n_frames)
            lo, hi = int(self.contact_offsets[start]), int(self.contact_offsets[max(start, stop)])
            sub["contact_offsets"] = self.contact_offsets[start:max(start, stop) + 1] - lo
            for name in ("contact_faces", "contact_barycentric", "contact_codes"):
                sub[name] = getattr(self, name)[lo:hi]
        return Clip(**sub)

    # ---- validation --------------------------------------------------------------------------
    def validate(self, *, source: str = "") -> None:
        """Raise InputError naming the field (and frame) of the first problem found."""
        src = source

        def bad(field_name: str, message: str):
            raise InputError(message, source=src, element=field_name)

        try:
            fps = float(self.fps) if np.ndim(self.fps) == 0 else float("nan")
        except (TypeError, ValueError):
            fps = float("nan")
        lo, hi = FPS_RANGE
        if not np.isfinite(fps) or fps <= 0:
            bad("fps", f"must be a positive number, got {self.fps!r}")
        if not lo <= fps <= hi:
            bad("fps", f"must be within {lo:g} to {hi:g} frames per second, got {fps!r}")

        hv = self.hand_vertices
        if not isinstance(hv, np.ndarray) or hv.ndim != 3 or hv.shape[2] != 3 or hv.shape[0] < 1:
            bad("hand_vertices", f"must have shape (T, Vh, 3), got {getattr(hv, 'shape', None)}")
        n_frames, n_hand = hv.shape[0], hv.shape[1]
        _check_faces(self.hand_faces, n_hand, "hand_faces", src)
        _check_finite_frames(hv, "hand_vertices", src)

        ov = self.object_vertices
        if not isinstance(ov, np.ndarray) or ov.ndim != 2 or ov.shape[1] != 3 or len(ov) < 4:
            bad("object_vertices", f"must have shape (Vo, 3) with Vo >= 4, got {getattr(ov, 'shape', None)}")
        if not np.all(np.isfinite(ov)):
            bad("object_vertices", "contains NaN or inf")
        _check_faces(self.object_faces, len(ov), "object_faces", src)

        poses = self.object_poses
        if not isinstance(poses, np.ndarray) or poses.shape != (n_frames, 4, 4):
            bad("object_poses", f"must have shape (T={n_frames}, 4, 4) like hand_vertices, got {getattr(poses, 'shape', None)}")
        _check_finite_frames(poses, "object_poses", src)
        _check_rigid(poses, "object_poses", src)

        labels = self.contact_labels
        if not isinstance(labels, np.ndarray) or labels.shape != (n_frames, len(ov)):
            bad("contact_labels", f"must have shape (T={n_frames}, Vo={len(ov)}), got {getattr(labels, 'shape', None)}")
        if not np.issubdtype(labels.dtype, np.integer):
            bad("contact_labels", f"must be integers, got dtype {labels.dtype}")
        codes = np.unique(labels)
        unknown = [int(c) for c in codes if c != 0 and int(c) not in RIGHT_HAND_CONTACT_CODES]
        if unknown:
            frame = int(np.nonzero(np.isin(labels, unknown).any(axis=1))[0][0])
            bad("contact_labels", f"frame {frame}: code {unknown[0]} is not a right-hand contact code (0, 22, 41-55)")

        surface = (self.contact_offsets, self.contact_faces, self.contact_barycentric, self.contact_codes)
        if any(a is not None for a in surface):
            off, cf, cb, cc = (np.asarray(a) if a is not None else None for a in surface)
            if any(a is None for a in (off, cf, cb, cc)):
                bad("contact_offsets", "contact_offsets, contact_faces, contact_barycentric and contact_codes go together")
            if off.shape != (n_frames + 1,) or not np.issubdtype(off.dtype, np.integer) or off[0] != 0 \
                    or np.any(np.diff(off) < 0):
                bad("contact_offsets", f"must be (T + 1 = {n_frames + 1},) non-decreasing integers from 0, "
                                       f"got shape {off.shape}")
            n = int(off[-1])
            if cf.shape != (n,) or cb.shape != (n, 3) or cc.shape != (n,):
                bad("contact_faces", f"contact_faces (N,), contact_barycentric (N, 3) and contact_codes (N,) must "
                                     f"have N = contact_offsets[-1] = {n} rows")
            if n and (cf.min() < 0 or cf.max() >= len(self.object_faces)):
                bad("contact_faces", f"face index out of range [0, {len(self.object_faces)})")
            if n and (not np.all(np.isfinite(cb)) or np.abs(cb.sum(axis=1) - 1).max() > 1e-6 or cb.min() < -1e-6):
                bad("contact_barycentric", "rows must be non-negative and sum to 1")
            odd = [int(c) for c in np.unique(cc) if int(c) not in RIGHT_HAND_CONTACT_CODES]
            if odd:
                bad("contact_codes", f"code {odd[0]} is not a right-hand contact code (22, 41-55)")

        if self.hand not in ("", "right", "left"):
            bad("hand", f"must be 'right' or 'left', got {self.hand!r}")
        if self.source_rig_sha256 and not (len(self.source_rig_sha256) == 64
                                           and all(c in "0123456789abcdef" for c in self.source_rig_sha256)):
            bad("source_rig_sha256", "must be 64 lowercase hex digits")

        if (self.table_pose is None) != (self.table_half_extents is None):
            bad("table_pose", "table_pose and table_half_extents go together")
        if self.table_pose is not None:
            tp = np.asarray(self.table_pose)
            if tp.shape != (4, 4) or not np.all(np.isfinite(tp)):
                bad("table_pose", f"must be a finite 4x4 matrix, got shape {tp.shape}")
            _check_rigid(tp[None], "table_pose", src, per_frame=False)
            he = np.asarray(self.table_half_extents)
            if he.shape != (3,) or not np.all(np.isfinite(he)) or np.any(he <= 0):
                bad("table_half_extents", f"must be 3 positive numbers, got {he!r}")

        if self.marker_faces is not None or self.marker_names:
            mf, mb = self.marker_faces, self.marker_barycentric
            m = len(self.marker_names)
            if mf is None or mb is None or np.shape(mf) != (m,) or np.shape(mb) != (m, 3):
                bad("marker_faces", f"marker_names, marker_faces (M,) and marker_barycentric (M, 3) must agree (M={m})")
            if len(set(self.marker_names)) != m:
                bad("marker_names", "a marker name is used twice")
            if m and (mf.min() < 0 or mf.max() >= len(self.hand_faces)):
                bad("marker_faces", f"face index out of range [0, {len(self.hand_faces)})")
            if m and (not np.all(np.isfinite(mb)) or np.abs(mb.sum(axis=1) - 1).max() > 1e-6 or mb.min() < -1e-6):
                bad("marker_barycentric", "rows must be non-negative and sum to 1")

        if self.dof_values is not None or self.dof_names:
            dv = self.dof_values
            if dv is None or dv.shape != (n_frames, len(self.dof_names)):
                bad("dof_values", f"must have shape (T={n_frames}, D={len(self.dof_names)}), got {getattr(dv, 'shape', None)}")
            _check_finite_frames(dv, "dof_values", src)

    # ---- files ---------------------------------------------------------------------------------
    def save(self, path) -> None:
        """Write an .npz (compressed) atomically: a temp file in the same folder, then rename."""
        self.validate(source=str(path))
        path = Path(path)
        arrays = {
            "format": np.array(CLIP_FORMAT),
            "version": np.array(CLIP_VERSION),
            "fps": np.array(float(self.fps)),
            "hand_faces": np.asarray(self.hand_faces, dtype=np.int32),
            "hand_vertices": np.asarray(self.hand_vertices, dtype=np.float32),
            "object_vertices": np.asarray(self.object_vertices, dtype=np.float64),
            "object_faces": np.asarray(self.object_faces, dtype=np.int32),
            "object_poses": np.asarray(self.object_poses, dtype=np.float64),
            "contact_labels": np.asarray(self.contact_labels, dtype=np.uint8),
            "source_rig": np.array(self.source_rig),
            "source_rig_sha256": np.array(self.source_rig_sha256),
            "hand": np.array(self.hand),
            "object_name": np.array(self.object_name),
            "motion": np.array(self.motion),
            "source": np.array(self.source),
        }
        if self.contact_offsets is not None:
            arrays["contact_offsets"] = np.asarray(self.contact_offsets, dtype=np.int64)
            arrays["contact_faces"] = np.asarray(self.contact_faces, dtype=np.int32)
            arrays["contact_barycentric"] = np.asarray(self.contact_barycentric, dtype=np.float64)
            arrays["contact_codes"] = np.asarray(self.contact_codes, dtype=np.uint8)
        if self.table_pose is not None:
            arrays["table_pose"] = np.asarray(self.table_pose, dtype=np.float64)
            arrays["table_half_extents"] = np.asarray(self.table_half_extents, dtype=np.float64)
        if self.marker_faces is not None:
            arrays["marker_names"] = np.array(self.marker_names, dtype=np.str_)
            arrays["marker_faces"] = np.asarray(self.marker_faces, dtype=np.int32)
            arrays["marker_barycentric"] = np.asarray(self.marker_barycentric, dtype=np.float64)
        if self.dof_values is not None:
            arrays["dof_names"] = np.array(self.dof_names, dtype=np.str_)
            arrays["dof_values"] = np.asarray(self.dof_values, dtype=np.float64)
        save_npz_atomic(path, arrays)


_REQUIRED = ("format", "version", "fps", "hand_faces", "hand_vertices", "object_vertices", "object_faces",
             "object_poses", "contact_labels")


#: What each field must be, checked from its npy header before it is read: (ndim or None for
#: any, allowed dtype kinds). Unlisted members are ignored (never read).
_FIELD_SPECS = {
    "format": (0, "U"), "version": (0, "iu"), "fps": (0, "iuf"),
    "hand_faces": (None, "iu"), "hand_vertices": (None, "iuf"), "object_vertices": (None, "iuf"),
    "object_faces": (None, "iu"), "object_poses": (None, "iuf"), "contact_labels": (None, "biu"),
    "contact_offsets": (1, "iu"), "contact_faces": (1, "iu"), "contact_barycentric": (2, "iuf"),
    "contact_codes": (1, "biu"),
    "table_pose": (None, "iuf"), "table_half_extents": (None, "iuf"),
    "marker_names": (1, "U"), "marker_faces": (None, "iu"), "marker_barycentric": (None, "iuf"),
    "dof_names": (1, "U"), "dof_values": (None, "iuf"),
    "source_rig": (0, "U"), "source_rig_sha256": (0, "U"), "hand": (0, "U"), "object_name": (0, "U"), "motion": (0, "U"), "source": (0, "U"),
}
_KIND_NAMES = {"U": "a string", "iu": "an integer", "iuf": "a number", "biu": "an integer"}


def check_npz_members(path, *, max_bytes: int = MAX_CLIP_BYTES, source: str = "") -> dict[str, tuple]:
    """Read only the npy headers of the clip archive at ``path``: {field: (shape, dtype)}.
    Raises InputError naming the member when a header is malformed or pickled, declares more
    data than the member holds, does not match its field (:data:`_FIELD_SPECS`), or when the
    members add up to more than ``max_bytes`` uncompressed (checked on the zip's own sizes
    before any member is decompressed)."""
    from numpy.lib import format as npformat

    src = source or str(path)
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as err:
        raise InputError(f"not a clip .npz file ({err})", source=src) from err
    out = {}
    with zf:
        members = zf.infolist()
        total = sum(info.file_size for info in members)
        if total > max_bytes:
            biggest = max(members, key=lambda info: info.file_size)
            raise InputError(f"the clip decompresses to {total} bytes, over the limit of {max_bytes} bytes "
                             f"(largest member: {biggest.file_size} bytes)", source=src,
                             element=biggest.filename.removesuffix(".npy"))
        declared_total = 0
        for info in members:
            name = info.filename.removesuffix(".npy")
            if not info.filename.endswith(".npy") or name not in _FIELD_SPECS:
                continue
            try:
                with zf.open(info) as fh:
                    version = npformat.read_magic(fh)
                    if version == (1, 0):
                        shape, fortran, dtype = npformat.read_array_header_1_0(fh, max_header_size=_MAX_HEADER)
                    elif version in ((2, 0), (3, 0)):
                        shape, fortran, dtype = npformat.read_array_header_2_0(fh, max_header_size=_MAX_HEADER)
                    else:
                        raise ValueError(f"npy format version {version} is not supported")
                    offset = fh.tell()
            except (ValueError, TypeError, OverflowError, SyntaxError, EOFError, zipfile.BadZipFile, OSError,
                    RuntimeError, NotImplementedError, zlib.error) as err:
                raise InputError(f"not a readable array (bad npy header: {err})", source=src, element=name) from err
            if dtype.hasobject:
                raise InputError("field holds Python objects, which clips never do (it would need pickle)",
                                 source=src, element=name)
            count = 1
            for n in shape:
                count *= int(n)
            declared = count * dtype.itemsize
            declared_total += declared
            if declared > info.file_size - offset:
                raise InputError(f"the header declares an array of shape {shape} ({dtype}, {declared} bytes) but "
                                 f"the member holds {info.file_size - offset} bytes", source=src, element=name)
            if declared_total > max_bytes:
                raise InputError(f"the clip's arrays add up to more than the limit of {max_bytes} bytes",
                                 source=src, element=name)
            ndim, kinds = _FIELD_SPECS[name]
            if dtype.kind not in kinds:
                raise InputError(f"must be {_KIND_NAMES[kinds]} array, got dtype {dtype}", source=src, element=name)
            if ndim is not None and len(shape) != ndim:
                what = "a single value (shape ())" if ndim == 0 else f"a {ndim}-d array"
                raise InputError(f"must be {what}, got shape {shape}", source=src, element=name)
            out[name] = (shape, dtype)
    return out


def load_clip(path, *, validate: bool = True, max_bytes: int = MAX_CLIP_BYTES) -> Clip:
    """Read a clip .npz (never unpickling anything) and validate it. Every member's header is
    checked first (:func:`check_npz_members`, at most ``max_bytes`` uncompressed)."""
    path = Path(path)
    src = str(path)
    if not path.is_file():
        raise InputError("no such file", source=src)
    present = check_npz_members(path, max_bytes=max_bytes, source=src)
    missing = [k for k in _REQUIRED if k not in present]
    if missing:
        raise InputError("required field is missing", source=src, element=missing[0])
    try:
        data = np.load(path, allow_pickle=False)
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as err:
        raise InputError(f"not a clip .npz file ({err})", source=src) from err
    with data:
        def get(key):
            try:
                return data[key]
            except ValueError as err:  # object arrays need pickle: refuse them
                raise InputError(f"field holds Python objects, which clips never do ({err})", source=src, element=key) from err
            except (zipfile.BadZipFile, OSError, EOFError, zlib.error) as err:  # a damaged member (bad CRC, truncated)
                raise InputError(f"the member cannot be read ({err})", source=src, element=key) from err

        fmt = str(get("format"))
        if fmt != CLIP_FORMAT:
            raise InputError(f"not a Hand Retarget clip (format {fmt!r})", source=src, element="format")
        version = int(get("version"))
        if version not in READABLE_VERSIONS:
            raise InputError(f"clip version {version} is not supported (this build reads "
                             f"{', '.join(map(str, READABLE_VERSIONS))})", source=src, element="version")

        def has(key):
            return key in present

        def text(key):
            return str(get(key)) if has(key) else ""

        clip = Clip(
            fps=float(get("fps")),
            hand_faces=get("hand_faces").astype(np.int64),
            hand_vertices=get("hand_vertices"),
            object_vertices=get("object_vertices").astype(np.float64),
            object_faces=get("object_faces").astype(np.int64),
            object_poses=get("object_poses").astype(np.float64),
            contact_labels=get("contact_labels"),
            contact_offsets=get("contact_offsets").astype(np.int64) if has("contact_offsets") else None,
            contact_faces=get("contact_faces").astype(np.int64) if has("contact_faces") else None,
            contact_barycentric=get("contact_barycentric").astype(np.float64) if has("contact_barycentric") else None,
            contact_codes=get("contact_codes") if has("contact_codes") else None,
            table_pose=get("table_pose") if has("table_pose") else None,
            table_half_extents=get("table_half_extents") if has("table_half_extents") else None,
            marker_names=[str(s) for s in get("marker_names")] if has("marker_names") else [],
            marker_faces=get("marker_faces").astype(np.int64) if has("marker_faces") else None,
            marker_barycentric=get("marker_barycentric") if has("marker_barycentric") else None,
            dof_names=[str(s) for s in get("dof_names")] if has("dof_names") else [],
            dof_values=get("dof_values") if has("dof_values") else None,
            source_rig=text("source_rig"),
            source_rig_sha256=text("source_rig_sha256"),
            hand=text("hand"),
            object_name=text("object_name"),
            motion=text("motion"),
            source=text("source"),
        )
    if validate:
        clip.validate(source=src)
    return clip


def _check_faces(faces, n_vertices: int, name: str, src: str) -> None:
    if not isinstance(faces, np.ndarray) or faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise InputError(f"must have shape (F, 3), got {getattr(faces, 'shape', None)}", source=src, element=name)
    if not np.issubdtype(faces.dtype, np.integer):
        raise InputError(f"must be integers, got dtype {faces.dtype}", source=src, element=name)
    if faces.min() < 0 or faces.max() >= n_vertices:
        row = int(np.nonzero((faces < 0).any(axis=1) | (faces >= n_vertices).any(axis=1))[0][0])
        raise InputError(
            f"face {row} has vertex index {faces[row].tolist()} out of range [0, {n_vertices})", source=src, element=name
        )


def _check_finite_frames(array: np.ndarray, name: str, src: str) -> None:
    finite = np.isfinite(array).reshape(len(array), -1).all(axis=1)
    if not finite.all():
        frame = int(np.nonzero(~finite)[0][0])
        raise InputError(f"frame {frame} contains NaN or inf", source=src, element=name)


def _check_rigid(poses: np.ndarray, name: str, src: str, *, per_frame: bool = True, tol: float = 1e-5) -> None:
    rot = poses[:, :3, :3]
    ortho = np.abs(np.einsum("fji,fjk->fik", rot, rot) - np.eye(3)).reshape(len(poses), -1).max(axis=1)
    det = np.linalg.det(rot)
    bottom = np.abs(poses[:, 3] - [0, 0, 0, 1]).max(axis=1)
    bad = (ortho > tol) | (det < 0) | (bottom > 1e-9)
    if bad.any():
        i = int(np.nonzero(bad)[0][0])
        where = f"frame {i}: " if per_frame else ""
        raise InputError(
            f"{where}not a rigid transform (rotation part off orthonormal by {ortho[i]:.2g}, det {det[i]:.3g})",
            source=src,
            element=name,
        )
