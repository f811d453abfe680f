"""GRAB importer: GRAB sequence (.npz of pickled dicts) + MANO right-hand model -> :class:`Clip`.

Nothing here ever calls ``np.load(allow_pickle=True)`` or ``pickle.load`` on user files: both the
GRAB archives and the MANO model pickles are read with restricted unpicklers that admit only the
globals numpy arrays, plain containers, chumpy ``Ch`` and scipy ``csc_matrix`` need (the last two
are mapped to inert stand-ins that merely capture their state). Anything else raises
:class:`InputError` naming the refused ``module.global``.

Conventions (see :func:`import_grab`):

* MANO: 16 joints (wrist, then index, middle, pinky, ring, thumb with 3 joints each), pose
  blend-shape feature ``(R_i - I)`` for joints 1..15, linear blend skinning relative to the rest
  joints, then ``transl``. GRAB's PCA ``hand_pose`` is expanded with the *flat* hand mean.
* GRAB objects/tables: world vertices = ``v @ R + transl`` with ``R = rodrigues(global_orient)``
  (row vectors times R), so the clip's world-from-object pose is ``[[R^T, transl], [0, 1]]``.
"""

from __future__ import annotations

import importlib
import io
import math
import pickle
import re
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.lib.format as npformat

from ..errors import InputError
from ..mesh.io import load_mesh_file
from ..mesh.surface_points import SurfacePoints
from .format import RIGHT_HAND_CONTACT_CODES, Clip
from .markers import MANO_MARKERS, MANO_N_VERTICES

__all__ = [
    "ManoModel",
    "load_grab_sequence",
    "load_mano_model",
    "mano_forward",
    "finger_pose_from_pca",
    "rodrigues",
    "import_grab",
    "import_grab_hand",
    "GrabHand",
    "MANO_N_JOINTS",
]

MANO_N_JOINTS = 16
_ROOT_PARENT_SENTINELS = (2**32 - 1, -1)


# =============================================================================================
# Restricted unpickling
# =============================================================================================

def _numpy_core_module(sub: str):
    """numpy's internal module ``sub`` (``multiarray``/``numeric``) under numpy 2 or 1 naming."""
    for name in (f"numpy._core.{sub}", f"numpy.core.{sub}"):
        try:
            return importlib.import_module(name)
        except ImportError:  # pragma: no cover - depends on numpy version
            continue
    raise ImportError(f"numpy {sub} module not found")  # pragma: no cover


def _safe_codecs_encode(text, encoding="utf-8", errors="strict"):
    """``_codecs.encode`` as Python-3 protocol<3 pickles use it for bytes: text codecs only."""
    if not isinstance(text, str) or str(encoding).lower().replace("_", "-") not in ("latin1", "latin-1", "iso-8859-1", "utf-8", "utf8", "ascii"):
        raise pickle.UnpicklingError(f"refusing _codecs.encode with encoding {encoding!r}")
    return text.encode(encoding, errors)


def _numpy_globals() -> dict[tuple[str, str], object]:
    multiarray = _numpy_core_module("multiarray")
    numeric = _numpy_core_module("numeric")
    allowed: dict[tuple[str, str], object] = {}
    for mod in ("numpy.core.multiarray", "numpy._core.multiarray"):
        allowed[(mod, "_reconstruct")] = multiarray._reconstruct
        allowed[(mod, "scalar")] = multiarray.scalar
        allowed[(mod, "ndarray")] = np.ndarray
        allowed[(mod, "dtype")] = np.dtype
    for mod in ("numpy.core.numeric", "numpy._core.numeric"):
        if hasattr(numeric, "_frombuffer"):
            allowed[(mod, "_frombuffer")] = numeric._frombuffer
    allowed[("numpy", "ndarray")] = np.ndarray
    allowed[("numpy", "dtype")] = np.dtype
    for builtins_name in ("builtins", "__builtin__"):
        for name, obj in (("object", object), ("set", set), ("frozenset", frozenset), ("slice", slice),
                          ("complex", complex), ("bytes", bytes), ("bytearray", bytearray)):
            allowed[(builtins_name, name)] = obj
    for copyreg_name in ("copyreg", "copy_reg"):
        import copyreg

        allowed[(copyreg_name, "_reconstructor")] = copyreg._reconstructor
    allowed[("_codecs", "encode")] = _safe_codecs_encode
    return allowed


class _RefusedGlobal(pickle.UnpicklingError):
    def __init__(self, module: str, name: str):
        self.qualified = f"{module}.{name}"
        super().__init__(f"refusing to unpickle {self.qualified}")


class _RestrictedUnpickler(pickle.Unpickler):
    """Unpickler admitting only an explicit table of (module, name) -> object."""

    def __init__(self, file, allowed: dict[tuple[str, str], object], **kwargs):
        super().__init__(file, **kwargs)
        self._allowed = allowed

    def find_class(self, module, name):  # noqa: D401 - pickle API
        try:
            return self._allowed[(module, name)]
        except KeyError:
            raise _RefusedGlobal(module, name) from None

    def persistent_load(self, pid):
        raise pickle.UnpicklingError("persistent ids are not supported")


def _restricted_loads(payload: bytes, allowed, *, source: str, element: str, encoding: str = "ASCII"):
    try:
        return _RestrictedUnpickler(io.BytesIO(payload), allowed, encoding=encoding).load()
    except _RefusedGlobal as err:
        raise InputError(str(err), source=source, element=element) from None
    except InputError:
        raise
    except Exception as err:  # truncated/corrupt pickles raise many types
        raise InputError(f"cannot unpickle ({type(err).__name__}: {err})", source=source, element=element) from None


# =============================================================================================
# GRAB sequences
# =============================================================================================

def _plain(value):
    """Turn unpickled values into plain dicts / numpy arrays / str / numbers."""
    if isinstance(value, dict):
        out = {}
        for k, v in value.items():
            key = k.decode("latin1") if isinstance(k, bytes) else str(k)
            out[key] = _plain(v)
        return out
    if isinstance(value, np.ndarray):
        if value.dtype.hasobject:
            if value.ndim == 0:
                return _plain(value.item())
            return value
        if value.ndim == 0:
            return value.item()
        return value
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, bytes):
        return value.decode("latin1")
    if isinstance(value, (list, tuple)):
        return type(value)(_plain(v) for v in value)
    return value


def _read_npy_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, allowed, source: str, element: str):
    try:
        with zf.open(info) as handle:
            raw = handle.read()
    except (zipfile.BadZipFile, OSError, EOFError, RuntimeError, ValueError) as err:
        raise InputError(f"cannot read archive member ({err})", source=source, element=element) from None
    fp = io.BytesIO(raw)
    try:
        version = npformat.read_magic(fp)
        if version == (1, 0):
            shape, fortran, dtype = npformat.read_array_header_1_0(fp)
        elif version == (2, 0):
            shape, fortran, dtype = npformat.read_array_header_2_0(fp)
        elif version == (3, 0) and hasattr(npformat, "_read_array_header"):
            shape, fortran, dtype = npformat._read_array_header(fp, version)
        else:
            raise ValueError(f"unsupported .npy version {version}")
    except Exception as err:
        raise InputError(f"not a valid .npy member ({err})", source=source, element=element) from None
    if dtype.hasobject:
        value = _restricted_loads(fp.read(), allowed, source=source, element=element)
        if isinstance(value, np.ndarray) and value.ndim == 0:
            value = value.item()
        return _plain(value)
    count = math.prod(int(n) for n in shape)
    nbytes = count * dtype.itemsize
    data = fp.read()
    if count < 0 or len(data) < nbytes:
        raise InputError(f"truncated array data ({len(data)} of {nbytes} bytes)", source=source, element=element)
    array = np.frombuffer(data[:nbytes], dtype=dtype, count=count)
    array = array.reshape(shape[::-1]).transpose() if fortran else array.reshape(shape)
    return _plain(array.copy())


def _merge(target: dict, key_path: list[str], value, source: str, element: str) -> None:
    node = target
    for part in key_path[:-1]:
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise InputError("member conflicts with a non-dict value of the same name", source=source, element=element)
        node = child
    last = key_path[-1]
    if isinstance(value, dict) and isinstance(node.get(last), dict):
        for k, v in value.items():
            _merge(node[last], [k], v, source, element)
    elif last in node:
        raise InputError("key occurs twice in the archive", source=source, element=element)
    else:
        node[last] = value


def load_grab_sequence(path) -> dict:
    """Read a GRAB sequence ``.npz`` safely into nested plain dicts.

    Members that are 0-d object arrays (GRAB's pickled dicts) are unpickled with a restricted
    unpickler; members named with dots (``rhand.params.transl``) are nested into dicts."""
    path = Path(path)
    src = str(path)
    if not path.is_file():
        raise InputError("no such file", source=src)
    allowed = _numpy_globals()
    result: dict = {}
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError, ValueError) as err:
        raise InputError(f"not an .npz (zip) archive ({err})", source=src) from None
    with zf:
        for info in zf.infolist():
            if info.is_dir():
                continue
            name = info.filename
            key = name[:-4] if name.endswith(".npy") else name
            value = _read_npy_member(zf, info, allowed, src, key)
            parts = [p for p in key.split(".") if p]
            if not parts:
                raise InputError("empty member name", source=src, element=name)
            _merge(result, parts, value, src, key)
    return result


# =============================================================================================
# MANO model
# =============================================================================================

class _ChStandIn:
    """Inert stand-in for ``chumpy.ch.Ch``: keeps the pickled state (its array is ``state['x']``)."""

    def __init__(self, *args, **kwargs):
        self.state = None

    def __setstate__(self, state):
        self.state = state

    def to_array(self, key: str, source: str) -> np.ndarray:
        state = self.state
        if isinstance(state, tuple) and len(state) == 2 and isinstance(state[0], dict):
            state = state[0]
        if not isinstance(state, dict) or "x" not in state:
            raise InputError("chumpy object without an 'x' array", source=source, element=key)
        return np.asarray(state["x"])


class _CscStandIn:
    """Inert stand-in for ``scipy.sparse.csc_matrix``: keeps data/indices/indptr/shape."""

    def __init__(self, *args, **kwargs):
        self.state = None

    def __setstate__(self, state):
        self.state = state

    def to_dense(self, key: str, source: str) -> np.ndarray:
        state = self.state if isinstance(self.state, dict) else {}
        try:
            data = np.asarray(state["data"], dtype=np.float64).reshape(-1)
            indices = np.asarray(state["indices"], dtype=np.int64).reshape(-1)
            indptr = np.asarray(state["indptr"], dtype=np.int64).reshape(-1)
            shape = tuple(int(s) for s in state.get("_shape", state.get("shape")))
        except (KeyError, TypeError, ValueError) as err:
            raise InputError(f"sparse matrix state is incomplete ({err})", source=source, element=key) from None
        n_rows, n_cols = shape
        if (len(indptr) != n_cols + 1 or indptr[0] != 0 or np.any(np.diff(indptr) < 0) or indptr[-1] != len(data)
                or len(indices) != len(data) or (len(indices) and (indices.min() < 0 or indices.max() >= n_rows))):
            raise InputError("inconsistent sparse (csc) matrix", source=source, element=key)
        dense = np.zeros(shape, dtype=np.float64)
        cols = np.repeat(np.arange(n_cols), np.diff(indptr))
        np.add.at(dense, (indices, cols), data)
        return dense


def _mano_globals():
    allowed = _numpy_globals()
    allowed[("chumpy.ch", "Ch")] = _ChStandIn
    for mod in ("scipy.sparse.csc", "scipy.sparse._csc"):
        allowed[(mod, "csc_matrix")] = _CscStandIn
    return allowed


@dataclass
class ManoModel:
    """A MANO hand model as dense numpy arrays (one hand: ``handedness``)."""

    v_template: np.ndarray  # (778, 3)
    shapedirs: np.ndarray  # (778, 3, S)
    posedirs: np.ndarray  # (778, 3, 135)
    J_regressor: np.ndarray  # (16, 778)
    weights: np.ndarray  # (778, 16)
    parents: np.ndarray  # (16,), parents[0] = -1
    faces: np.ndarray  # (F, 3) int64
    hands_components: np.ndarray  # (k, 45)
    hands_mean: np.ndarray  # (45,)
    source: str = ""
    handedness: str = "right"


def _mano_array(raw: dict, key: str, src: str, *, required: bool = True):
    if key not in raw:
        if required:
            raise InputError("MANO model: required key is missing", source=src, element=key)
        return None
    value = raw[key]
    if isinstance(value, _ChStandIn):
        value = value.to_array(key, src)
    elif isinstance(value, _CscStandIn):
        value = value.to_dense(key, src)
    try:
        array = np.asarray(value)
        if array.dtype.hasobject:
            raise TypeError("holds Python objects")
        return array
    except (TypeError, ValueError) as err:
        raise InputError(f"MANO model: not a numeric array ({err})", source=src, element=key) from None


def _check_shape(array: np.ndarray, expected: tuple, key: str, src: str) -> None:
    ok = array.ndim == len(expected) and all(e is None or e == s for e, s in zip(expected, array.shape))
    if not ok:
        shown = "(" + ", ".join("S" if e is None else str(e) for e in expected) + ("," if len(expected) == 1 else "") + ")"
        raise InputError(f"MANO model: {key} has shape {tuple(array.shape)}, expected {shown}", source=src, element=key)
    if np.issubdtype(array.dtype, np.number) and not np.all(np.isfinite(array)):
        raise InputError(f"MANO model: {key} contains NaN or inf", source=src, element=key)


def _side_from_name(stem: str) -> str | None:
    for side in ("left", "right"):
        if re.search(rf"(^|[^a-z]){side}([^a-z]|$)", stem, re.IGNORECASE):
            return side
    return None


def _side_from_data(raw: dict, src: str) -> str | None:
    """The side a MANO pickle states (``is_rhand`` / ``is_right`` flags, ``hand``/``side`` text)."""
    for flag in ("is_rhand", "is_right"):
        if flag in raw:
            value = raw[flag]
            if isinstance(value, (np.ndarray, np.generic)):
                value = np.asarray(value).reshape(-1)[0] if np.size(value) else True
            return "right" if bool(value) else "left"
    for flag in ("hand", "side", "hand_type"):
        if flag in raw and isinstance(raw[flag], (str, bytes)):
            text = (raw[flag].decode("latin1") if isinstance(raw[flag], bytes) else raw[flag]).strip().lower()
            if text in ("left", "l", "lhand", "left_hand"):
                return "left"
            if text in ("right", "r", "rhand", "right_hand"):
                return "right"
    return None


def _outward(vertices: np.ndarray, faces: np.ndarray, src: str) -> np.ndarray:
    """``faces`` wound so the surface (its openings closed by fans) encloses a positive volume:
    MANO_LEFT files carry the right hand's winding on mirrored vertices."""
    from ..rig.hand_cut import cap_openings

    try:
        v, f, _ = cap_openings(vertices, faces, np.zeros((len(vertices), 1)), what=f"{src} (MANO mesh)")
    except InputError:  # not a hand surface with simple openings: left as written (no rig can be built)
        return faces
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    volume = float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum()) / 6.0
    return faces if volume >= 0 else faces[:, [0, 2, 1]].copy()


def load_mano_model(path, hand: str = "right") -> ManoModel:
    """Read a MANO model pickle (official Python-2 chumpy style or plain numpy arrays) of the
    ``hand`` ("right": MANO_RIGHT.pkl, "left": MANO_LEFT.pkl). A file whose name or data says
    it is the other hand is refused, naming what to pass instead. Triangles are returned wound
    outward (a left model's are flipped when its file keeps the right's winding)."""
    if hand not in ("right", "left"):
        raise InputError(f"hand must be 'right' or 'left', got {hand!r}", element="hand")
    path = Path(path)
    src = str(path)
    if not path.is_file():
        raise InputError("no such file", source=src)
    other = "left" if hand == "right" else "right"
    remedy = ("pass it as the left hand's model (--mano-left)" if other == "left"
              else "pass it as the right hand's model (--mano)")
    if _side_from_name(path.stem) == other:
        raise InputError(f"this looks like a {other}-hand MANO model (MANO_{other.upper()}), but the {hand} hand's "
                         f"model is asked for: {remedy}", source=src)
    raw = _restricted_loads(path.read_bytes(), _mano_globals(), source=src, element="MANO model", encoding="latin1")
    if not isinstance(raw, dict):
        raise InputError(f"MANO model: expected a dict, got {type(raw).__name__}", source=src)
    raw = {(k.decode("latin1") if isinstance(k, bytes) else str(k)): v for k, v in raw.items()}
    if _side_from_data(raw, src) == other:
        raise InputError(f"MANO model is a {other} hand, but the {hand} hand's model is asked for: {remedy}",
                         source=src, element="is_rhand")

    v_template = _mano_array(raw, "v_template", src).astype(np.float64)
    _check_shape(v_template, (None, 3), "v_template", src)
    if len(v_template) != MANO_N_VERTICES:
        raise InputError(f"MANO model: v_template has {len(v_template)} vertices, expected {MANO_N_VERTICES}", source=src, element="v_template")
    n_v = MANO_N_VERTICES
    shapedirs = _mano_array(raw, "shapedirs", src).astype(np.float64)
    _check_shape(shapedirs, (n_v, 3, None), "shapedirs", src)
    posedirs = _mano_array(raw, "posedirs", src).astype(np.float64)
    _check_shape(posedirs, (n_v, 3, 9 * (MANO_N_JOINTS - 1)), "posedirs", src)
    j_reg = _mano_array(raw, "J_regressor", src).astype(np.float64)
    _check_shape(j_reg, (MANO_N_JOINTS, n_v), "J_regressor", src)
    weights = _mano_array(raw, "weights", src).astype(np.float64)
    _check_shape(weights, (n_v, MANO_N_JOINTS), "weights", src)
    row_sums = weights.sum(axis=1)
    bad = np.nonzero(np.abs(row_sums - 1.0) > 1e-4)[0]
    if len(bad):
        raise InputError(f"MANO model: weights of vertex {int(bad[0])} sum to {row_sums[bad[0]]:.6g}, expected 1", source=src, element="weights")

    kintree = _mano_array(raw, "kintree_table", src)
    _check_shape(kintree, (2, MANO_N_JOINTS), "kintree_table", src)
    kintree = kintree.astype(np.int64)
    ids = kintree[1]
    if sorted(ids.tolist()) != list(range(MANO_N_JOINTS)):
        raise InputError(f"MANO model: kintree_table row 1 must list joints 0..{MANO_N_JOINTS - 1}", source=src, element="kintree_table")
    parents = np.full(MANO_N_JOINTS, -2, dtype=np.int64)
    for parent, child in zip(kintree[0], ids):
        parents[child] = -1 if parent in _ROOT_PARENT_SENTINELS else parent
    if parents[0] != -1 or any(not (0 <= parents[i] < i) for i in range(1, MANO_N_JOINTS)):
        raise InputError(f"MANO model: kintree_table must have joint 0 as root and every parent before its child, got parents {parents.tolist()}", source=src, element="kintree_table")

    faces = _mano_array(raw, "f", src)
    _check_shape(faces, (None, 3), "f", src)
    if not np.issubdtype(faces.dtype, np.integer):
        if not np.all(np.equal(np.mod(faces, 1), 0)):
            raise InputError("MANO model: f must hold integer vertex ids", source=src, element="f")
    faces = faces.astype(np.int64)
    if len(faces) == 0 or faces.min() < 0 or faces.max() >= n_v:
        raise InputError(f"MANO model: f must index vertices in [0, {n_v})", source=src, element="f")

    comps = _mano_array(raw, "hands_components", src, required=False)
    if comps is None:
        comps = np.eye(45)
    comps = comps.astype(np.float64)
    _check_shape(comps, (None, 45), "hands_components", src)
    if not 1 <= len(comps) <= 45:
        raise InputError(f"MANO model: hands_components has {len(comps)} rows, expected 1..45", source=src, element="hands_components")
    mean = _mano_array(raw, "hands_mean", src, required=False)
    mean = np.zeros(45) if mean is None else mean.astype(np.float64).reshape(-1)
    _check_shape(mean, (45,), "hands_mean", src)

    return ManoModel(v_template=v_template, shapedirs=shapedirs, posedirs=posedirs, J_regressor=j_reg,
                     weights=weights, parents=parents, faces=_outward(v_template, faces, src), hands_components=comps,
                     hands_mean=mean, source=src, handedness=hand)


# =============================================================================================
# MANO forward kinematics
# =============================================================================================

def rodrigues(axis_angle: np.ndarray) -> np.ndarray:
    """(..., 3) axis-angle vectors -> (..., 3, 3) rotation matrices."""
    aa = np.asarray(axis_angle, dtype=np.float64)
    angle = np.linalg.norm(aa, axis=-1)
    small = angle < 1e-12
    safe = np.where(small, 1.0, angle)
    axis = aa / safe[..., None]
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    zero = np.zeros_like(x)
    k = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=-1).reshape(aa.shape[:-1] + (3, 3))
    s = np.where(small, 0.0, np.sin(angle))[..., None, None]
    c = np.where(small, 0.0, 1.0 - np.cos(angle))[..., None, None]
    return np.eye(3) + s * k + c * (k @ k)


def finger_pose_from_pca(model: ManoModel, hand_pose: np.ndarray, flat_hand_mean: bool = True) -> np.ndarray:
    """(T, k) PCA coefficients -> (T, 45) finger axis-angles: ``hand_pose @ hands_components[:k]``
    plus ``hands_mean`` unless ``flat_hand_mean`` (GRAB uses the flat mean)."""
    hand_pose = np.asarray(hand_pose, dtype=np.float64)
    if hand_pose.ndim != 2 or hand_pose.shape[1] > len(model.hands_components) or hand_pose.shape[1] < 1:
        raise InputError(
            f"hand_pose must have shape (T, k) with 1 <= k <= {len(model.hands_components)}, got {hand_pose.shape}",
            element="hand_pose",
        )
    pose = hand_pose @ model.hands_components[: hand_pose.shape[1]]
    if not flat_hand_mean:
        pose = pose + model.hands_mean
    return pose


def mano_forward(model: ManoModel, global_orient, finger_pose, transl, betas=None, v_template=None,
                 *, chunk: int = 256) -> np.ndarray:
    """MANO vertices (T, 778, 3) for per-frame root axis-angle (T, 3), finger axis-angles (T, 45)
    in MANO joint order and translation (T, 3). ``v_template`` (778, 3) replaces the model's
    template (GRAB's subject ``vtemp``); ``betas`` (S',) or (T, S') adds shape blend shapes."""
    global_orient = np.asarray(global_orient, dtype=np.float64).reshape(-1, 3)
    n_frames = len(global_orient)
    finger_pose = np.asarray(finger_pose, dtype=np.float64).reshape(n_frames, -1)
    if finger_pose.shape[1] != 45:
        raise InputError(f"finger pose must have 45 values per frame, got {finger_pose.shape[1]}", element="finger_pose")
    transl = np.asarray(transl, dtype=np.float64).reshape(n_frames, 3)
    base = model.v_template if v_template is None else np.asarray(v_template, dtype=np.float64)
    if base.shape != model.v_template.shape:
        raise InputError(f"template must have shape {model.v_template.shape}, got {base.shape}", element="v_template")
    weights, posedirs, parents = model.weights, model.posedirs, model.parents
    n_joints = len(parents)
    out = np.empty((n_frames, len(base), 3), dtype=np.float64)

    per_frame_betas = betas is not None and np.ndim(betas) == 2
    if betas is not None and not per_frame_betas:
        b = np.asarray(betas, dtype=np.float64).reshape(-1)
        base = base + model.shapedirs[:, :, : len(b)] @ b

    for start in range(0, n_frames, chunk):
        sl = slice(start, min(start + chunk, n_frames))
        m = sl.stop - sl.start
        if per_frame_betas:
            b = np.asarray(betas, dtype=np.float64)[sl]
            v_shaped = base[None] + np.einsum("vcs,ts->tvc", model.shapedirs[:, :, : b.shape[1]], b)
        else:
            v_shaped = np.broadcast_to(base, (m,) + base.shape)
        joints = np.einsum("jv,tvc->tjc", model.J_regressor, v_shaped)  # (m, 16, 3)
        pose = np.concatenate([global_orient[sl], finger_pose[sl]], axis=1).reshape(m, n_joints, 3)
        rot = rodrigues(pose)  # (m, 16, 3, 3)
        feature = (rot[:, 1:] - np.eye(3)).reshape(m, -1)  # (m, 135)
        v_posed = v_shaped + np.einsum("vcp,tp->tvc", posedirs, feature)

        world_r = np.empty_like(rot)
        world_t = np.empty((m, n_joints, 3))
        world_r[:, 0] = rot[:, 0]
        world_t[:, 0] = joints[:, 0]
        for j in range(1, n_joints):
            p = parents[j]
            world_r[:, j] = world_r[:, p] @ rot[:, j]
            world_t[:, j] = world_t[:, p] + np.einsum("tab,tb->ta", world_r[:, p], joints[:, j] - joints[:, p])
        # Transforms relative to the rest pose: x -> R (x - J_rest) + t.
        rel_t = world_t - np.einsum("tjab,tjb->tja", world_r, joints)
        blend_r = np.einsum("vj,tjab->tvab", weights, world_r)
        blend_t = np.einsum("vj,tja->tva", weights, rel_t)
        out[sl] = np.einsum("tvab,tvb->tva", blend_r, v_posed) + blend_t + transl[sl, None]
    return out


# =============================================================================================
# Import
# =============================================================================================

def _get(seq: dict, key: str, src: str, *, required: bool = True):
    node = seq
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            if required:
                raise InputError("required key is missing from the GRAB sequence", source=src, element=key)
            return None
        node = node[part]
    return node


def _frames_array(seq: dict, key: str, src: str, width: int | None, *, required: bool = True):
    value = _get(seq, key, src, required=required)
    if value is None:
        return None
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise InputError(f"not a numeric array ({err})", source=src, element=key) from None
    if array.ndim == 1 and width is not None and array.size % width == 0 and array.size == width:
        array = array[None]
    if array.ndim != 2 or (width is not None and array.shape[1] != width) or len(array) == 0:
        expected = f"(T, {width})" if width is not None else "(T, k)"
        raise InputError(f"has shape {array.shape}, expected {expected}", source=src, element=key)
    return array


def _check_nan(array: np.ndarray, key: str, src: str) -> None:
    finite = np.isfinite(array).reshape(len(array), -1).all(axis=1)
    if not finite.all():
        frame = int(np.nonzero(~finite)[0][0])
        raise InputError(f"frame {frame} contains NaN or inf", source=src, element=key)


def _text(value) -> str:
    if value is None:
        return ""
    if isinstance(value, np.ndarray):
        value = value.item() if value.size == 1 else value.tolist()
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    return str(value)


def _resolve(explicit, stored, grab_root, what: str, src: str, element: str):
    """An explicit path must exist; a stored one is tried as-is (if absolute) or under grab_root."""
    if explicit is not None:
        p = Path(explicit)
        if not p.is_file():
            raise InputError(f"{what} file not found: {p}", source=src, element=element)
        return p
    stored_text = _text(stored)
    if not stored_text:
        return None
    p = Path(stored_text)
    candidates = []
    if p.is_absolute():
        candidates.append(p)
    if grab_root is not None:
        root = Path(grab_root)
        rel = Path(*p.parts[1:]) if p.is_absolute() else p
        candidates.append(root / rel)
        # GRAB paths usually start with 'tools/...' or the dataset folder name; try without it too.
        if len(rel.parts) > 1:
            candidates.append(root / Path(*rel.parts[1:]))
    for c in candidates:
        if c.is_file():
            return c
    return None


def _grab_pose(orient: np.ndarray, transl: np.ndarray) -> np.ndarray:
    """GRAB object/table params -> (T, 4, 4) world-from-local (world = v @ R + t)."""
    rot = rodrigues(orient)
    poses = np.zeros((len(orient), 4, 4))
    poses[:, :3, :3] = np.swapaxes(rot, -1, -2)
    poses[:, :3, 3] = transl
    poses[:, 3, 3] = 1.0
    return poses


#: GRAB's contact codes are SMPL-X joint indices plus one: 22 = right wrist (the palm), 41-55 = the
#: right hand's 15 finger joints in MANO's order; 21 and 26-40 are the left hand's.
LEFT_HAND_CODE_SHIFT = {21: 22, **{c: c + 15 for c in range(26, 41)}}
HAND_KEYS = {"right": "rhand", "left": "lhand"}


@dataclass
class GrabHand:
    """One hand of an imported GRAB sequence: the clip, the MANO model it was posed with and the
    subject's hand template (None: the model's mean template). :meth:`rig` is its source rig."""

    clip: Clip
    model: ManoModel
    template: np.ndarray | None

    def rig(self, name: str | None = None):
        """The MANO source rig of this hand (:func:`retarget_core.rig.mano.mano_rig`)."""
        from ..rig.mano import mano_rig

        return mano_rig(self.model, self.template, name=name)


def import_grab(sequence_path, mano_path, *, object_mesh=None, table_mesh=None, vtemp=None, grab_root=None) -> Clip:
    """The right hand of :func:`import_grab_hand` as a clip."""
    return import_grab_hand(sequence_path, mano_path, object_mesh=object_mesh, table_mesh=table_mesh, vtemp=vtemp,
                            grab_root=grab_root).clip


def import_grab_hand(sequence_path, mano_path, *, hand: str = "right", object_mesh=None, table_mesh=None, vtemp=None,
                     grab_root=None) -> GrabHand:
    """Import one GRAB sequence's ``hand`` ("right" or "left") and object into a validated
    :class:`Clip`, with what its source rig is built from.

    ``mano_path``: that hand's MANO model pickle (MANO_RIGHT.pkl / MANO_LEFT.pkl). Meshes (object,
    table, subject hand template ``vtemp``) come from the explicit arguments or from the relative
    paths stored in the sequence, resolved under ``grab_root`` (the GRAB dataset folder). A left
    hand's contact codes are stored in the clip's right-hand numbering (``hand`` = "left")."""
    seq_path = Path(sequence_path)
    src = str(seq_path)
    seq = load_grab_sequence(seq_path)
    model = load_mano_model(mano_path, hand)
    hand_key = HAND_KEYS[hand]
    other_key = HAND_KEYS["left" if hand == "right" else "right"]
    fps_value = _get(seq, "framerate", src)
    try:
        fps = float(np.asarray(fps_value, dtype=np.float64).reshape(-1)[0])
    except (TypeError, ValueError, IndexError):
        raise InputError(f"not a number: {fps_value!r}", source=src, element="framerate") from None
    if not np.isfinite(fps) or fps <= 0:
        raise InputError(f"must be a positive number, got {fps}", source=src, element="framerate")

    if not isinstance(seq.get(hand_key), dict):
        if isinstance(seq.get(other_key), dict):
            raise InputError(f"the sequence holds no {hand}-hand data (only {other_key!r}): import the other hand "
                             f"(--hand {'left' if hand == 'right' else 'right'})", source=src, element=hand_key)
        raise InputError(f"required key is missing from the GRAB sequence (GRAB keeps each hand's MANO "
                         f"parameters under '{hand_key}.params')", source=src, element=hand_key)

    # ---- per-frame arrays ------------------------------------------------------------------
    arrays: dict[str, np.ndarray] = {}
    arrays[f"{hand_key}.params.global_orient"] = _frames_array(seq, f"{hand_key}.params.global_orient", src, 3)
    arrays[f"{hand_key}.params.transl"] = _frames_array(seq, f"{hand_key}.params.transl", src, 3)
    hand_pose = _frames_array(seq, f"{hand_key}.params.hand_pose", src, None, required=False)
    fullpose = None
    if hand_pose is not None:
        arrays[f"{hand_key}.params.hand_pose"] = hand_pose
        k = hand_pose.shape[1]
        if k > len(model.hands_components):
            raise InputError(f"has {k} PCA coefficients but the MANO model has {len(model.hands_components)} components",
                             source=src, element=f"{hand_key}.params.hand_pose")
    else:
        fullpose = _frames_array(seq, f"{hand_key}.params.fullpose", src, 45, required=False)
        if fullpose is None:
            raise InputError("required key is missing from the GRAB sequence (neither hand_pose nor fullpose)",
                             source=src, element=f"{hand_key}.params.hand_pose")
        arrays[f"{hand_key}.params.fullpose"] = fullpose
    arrays["object.params.global_orient"] = _frames_array(seq, "object.params.global_orient", src, 3)
    arrays["object.params.transl"] = _frames_array(seq, "object.params.transl", src, 3)
    contact_raw = _get(seq, "contact.object", src)
    contact = np.asarray(contact_raw)
    if contact.ndim != 2 or not (np.issubdtype(contact.dtype, np.integer) or np.issubdtype(contact.dtype, np.floating)):
        raise InputError(f"must be a (T, Vo) array of contact codes, got shape {contact.shape} dtype {contact.dtype}",
                         source=src, element="contact.object")

    # ---- meshes (resolved before the table arrays are required) ------------------------------
    stored_obj = _text(_get(seq, "object.object_mesh", src, required=False))
    obj_path = _resolve(object_mesh, stored_obj, grab_root, "object mesh", src, "object_mesh")
    if obj_path is None:
        names = f"the sequence names {stored_obj!r}" if stored_obj else "the sequence names no object mesh"
        where = (f"it is not under the GRAB root {grab_root}" if grab_root is not None
                 else "no --grab-root was given to look under")
        raise InputError(f"object mesh not found: {names} and {where}; GRAB keeps object meshes in "
                         "<GRAB root>/tools/object_meshes/contact_meshes/<object>.ply: pass --grab-root (the folder "
                         "holding grab/ and tools/) or the mesh itself with --object-mesh",
                         source=src, element="object.object_mesh")
    table_path = _resolve(table_mesh, _get(seq, "table.table_mesh", src, required=False), grab_root, "table mesh", src, "table_mesh")
    if table_path is not None:
        arrays["table.params.global_orient"] = _frames_array(seq, "table.params.global_orient", src, 3)
        arrays["table.params.transl"] = _frames_array(seq, "table.params.transl", src, 3)

    # ---- frame counts and NaNs -------------------------------------------------------------
    n_frames_value = _get(seq, "n_frames", src, required=False)
    if n_frames_value is not None:
        try:
            ref_key, ref_n = "n_frames", int(np.asarray(n_frames_value).reshape(-1)[0])
        except (TypeError, ValueError, IndexError):
            raise InputError(f"not an integer: {n_frames_value!r}", source=src, element="n_frames") from None
    else:
        ref_key, ref_n = f"{hand_key}.params.transl", len(arrays[f"{hand_key}.params.transl"])
    for key, array in [*arrays.items(), ("contact.object", contact)]:
        if len(array) != ref_n:
            raise InputError(f"has {len(array)} frames but {ref_key} says {ref_n}", source=src, element=key)
    for key, array in arrays.items():
        _check_nan(array, key, src)
    if np.issubdtype(contact.dtype, np.floating):
        _check_nan(contact, "contact.object", src)

    # ---- hand -------------------------------------------------------------------------------
    source = f"grab:{seq_path.stem}"
    sbj = _text(seq.get("sbj_id"))
    if sbj and re.fullmatch(r"[\w-]+", sbj):
        source = f"grab:{sbj}/{seq_path.stem}"
    if hand == "left":
        source += " (left hand)"
    vtemp_path = _resolve(vtemp, _get(seq, f"{hand_key}.vtemp", src, required=False), grab_root, "hand template (vtemp)", src, "vtemp")
    template = None
    if vtemp_path is not None:
        template, _ = load_mesh_file(vtemp_path, "hand template (vtemp)", "vtemp")
        if template.shape != (MANO_N_VERTICES, 3):
            raise InputError(f"hand template has {len(template)} vertices, expected {MANO_N_VERTICES} (a MANO mesh)",
                             source=str(vtemp_path), element="vtemp")
    else:
        # a fit to another subject's hand: said in the clip's provenance, and by import-grab
        source += " (MANO mean template: subject vtemp not found)"

    if hand_pose is not None:
        finger = finger_pose_from_pca(model, hand_pose, flat_hand_mean=True)
    else:
        finger = fullpose
    hand_vertices = mano_forward(model, arrays[f"{hand_key}.params.global_orient"], finger, arrays[f"{hand_key}.params.transl"],
                                 v_template=template)

    # ---- object ----------------------------------------------------------------------------
    obj_vertices, obj_faces = load_mesh_file(obj_path, "object", "object_mesh")
    if contact.shape[1] != len(obj_vertices):
        raise InputError(f"has {contact.shape[1]} vertices per frame but the object mesh {obj_path} has {len(obj_vertices)}",
                         source=src, element="contact.object")
    object_poses = _grab_pose(arrays["object.params.global_orient"], arrays["object.params.transl"])
    codes = np.rint(contact).astype(np.int64) if np.issubdtype(contact.dtype, np.floating) else contact.astype(np.int64)
    if hand == "left":
        shifted = np.zeros_like(codes)
        for code, right in LEFT_HAND_CODE_SHIFT.items():
            shifted[codes == code] = right
        codes = shifted
    keep = np.isin(codes, sorted(RIGHT_HAND_CONTACT_CODES))
    contact_labels = np.where(keep, codes, 0).astype(np.uint8)

    # ---- table -----------------------------------------------------------------------------
    table_pose = table_half = None
    if table_path is not None:
        t_vertices, _ = load_mesh_file(table_path, "table", "table_mesh")
        lo, hi = t_vertices.min(axis=0), t_vertices.max(axis=0)
        centre = (lo + hi) / 2
        table_half = np.maximum((hi - lo) / 2, 1e-4)
        pose0 = _grab_pose(arrays["table.params.global_orient"][:1], arrays["table.params.transl"][:1])[0]
        table_pose = pose0.copy()
        table_pose[:3, 3] = pose0[:3, :3] @ centre + pose0[:3, 3]

    # ---- markers ---------------------------------------------------------------------------
    names = list(MANO_MARKERS)
    points = SurfacePoints.from_vertices(np.array([MANO_MARKERS[n] for n in names]), model.faces)

    clip = Clip(
        fps=fps,
        hand_faces=model.faces.copy(),
        hand_vertices=hand_vertices.astype(np.float32),
        object_vertices=obj_vertices,
        object_faces=obj_faces,
        object_poses=object_poses,
        contact_labels=contact_labels,
        table_pose=table_pose,
        table_half_extents=table_half,
        marker_names=names,
        marker_faces=points.faces,
        marker_barycentric=points.barycentric,
        object_name=_text(seq.get("obj_name")),
        motion=_text(seq.get("motion_intent")),
        source=source,
        hand=hand,
    )
    clip.validate(source=src)
    return GrabHand(clip, model, template)


def save_grab_hand(hand: GrabHand, clip_path) -> tuple[Path, Path]:
    """Write ``hand``'s clip to ``clip_path`` and its MANO source rig beside it
    (``<clip stem>.source_rig.usda``), the clip recording the rig's file name and sha256 so that
    ``retarget``, ``transfer`` and ``annotate propose --source CLIP`` find it. Returns both paths."""
    from dataclasses import replace as _replace

    from ..inputs import file_sha256
    from ..rig.io import save_rig

    clip_path = Path(clip_path)
    rig_path = clip_path.with_name(clip_path.name.removesuffix(".npz") + ".source_rig.usda")
    save_rig(hand.rig(), rig_path)
    clip = _replace(hand.clip, source_rig=rig_path.name, source_rig_sha256=file_sha256(rig_path))
    clip.save(clip_path)
    return clip_path, rig_path

