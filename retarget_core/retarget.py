"""One retargeting run, end to end (paper section "Motion Retargeting"): input checks, the passes
of :func:`~retarget_core.solve.pipeline.solve_trajectory`, one cubic B-spline per DOF, and the
figures that describe the result. Thin: every stage is a core function.

Files written by :meth:`RetargetResult.write` into one folder::

    animation.usda   USD layer over the rig file: baked SkelAnimation + one native spline per
                     DOF (:func:`~retarget_core.export.write_animation_usd`), object animation
    result.json      this result (format "handretarget.result", version 1); NaN -> null
    animation.json   per-frame DOF values for robot users (:func:`~retarget_core.export.write_animation_json`)
    rig.usda         the rig, when it was not given as a USD file
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from .clip.format import Clip
from .errors import InputError
from .files import atomic_path
from .fit.splines import BSplineCurve, evaluate_curves, fit_trajectory
from .mesh.surface_points import SurfacePoints
from .rig.model import Rig
from .solve.config import MIN_CONTROL_POINTS, RetargetConfig
from .transfer.annotations import Annotations

RESULT_FORMAT = "handretarget.result"
RESULT_VERSION = 1
MM = 1000.0

Progress = Callable[[str, int, int], None]


@dataclass
class RetargetResult:
    """The outcome of :func:`retarget`. Units: seconds, radians / metres (DOF values), mm
    (distances in the figures).

    dof_names, dof_kinds ("rotate" / "translate"), lower, upper (D,); fps; times (T,) frame
    times (frame / fps); q (T, D) the solved per-frame poses; curves: one cubic B-spline per
    DOF (None when the fit pass is off); unresolved (T, D) entries still violating the
    acceleration check (left out of the fit); timings {stage: seconds}; counts: evaluations
    per frame per pass, failed frames with their error, refinement report; contact_distance_mm
    (T,) median distance between the solved target contact points and their object points
    (NaN on frames without contacts); contact_count (T,); marker_error_mm (T,) mean distance of
    the target markers to the source markers (each marker counts once); summary: the figures
    above in short; config: ``RetargetConfig.to_dict()``. ``rig`` and the object mesh / poses
    are kept for :meth:`write` only (not in result.json)."""

    rig_name: str
    dof_names: list
    dof_kinds: list
    lower: np.ndarray
    upper: np.ndarray
    fps: float
    times: np.ndarray
    q: np.ndarray
    curves: list | None
    unresolved: np.ndarray
    timings: dict
    counts: dict
    contact_distance_mm: np.ndarray
    contact_count: np.ndarray
    marker_error_mm: np.ndarray
    summary: dict
    config: dict
    clip_source: str = ""
    rig_file: str = ""  # the rig file the output was written over (relative to it when inside)
    rig: Rig | None = field(default=None, repr=False)
    object_vertices: np.ndarray | None = field(default=None, repr=False)
    object_faces: np.ndarray | None = field(default=None, repr=False)
    object_poses: np.ndarray | None = field(default=None, repr=False)
    table_pose: np.ndarray | None = field(default=None, repr=False)
    table_half_extents: np.ndarray | None = field(default=None, repr=False)
    contacts: object | None = field(default=None, repr=False)  # ContactTargets
    source_contact_count: np.ndarray | None = field(default=None, repr=False)  # (T,) pairs before transfer
    source_hand: tuple | None = field(default=None, repr=False)  # (frames (K,), vertices (K, V, 3), faces (F, 3))

    @property
    def n_frames(self) -> int:
        return len(self.times)

    def sampled(self) -> np.ndarray:
        """(T, D) the curves at the frame times (the solved q when there are no curves)."""
        return evaluate_curves(self.curves, self.times) if self.curves else self.q

    def to_dict(self) -> dict:
        """The result.json document (JSON types; NaN as None)."""
        curves = None if self.curves is None else [
            {"knots": c.knots, "coefficients": c.coeffs, "degree": c.degree, "extrapolation": c.extrapolation}
            for c in self.curves]
        return _plain({
            "format": RESULT_FORMAT, "version": RESULT_VERSION, "rig": self.rig_name, "clip": self.clip_source,
            "rig_file": self.rig_file,
            "summary": self.summary, "timings": self.timings, "fps": self.fps, "dof_names": self.dof_names,
            "dof_kinds": self.dof_kinds, "lower": self.lower, "upper": self.upper, "times": self.times, "q": self.q,
            "curves": curves, "unresolved": self.unresolved,
            "counts": self.counts, "contact_distance_mm": self.contact_distance_mm,
            "contact_count": self.contact_count, "marker_error_mm": self.marker_error_mm, "config": self.config,
        })

    def write(self, out_dir, rig_path=None) -> dict:
        """Write animation.usda (over ``rig_path`` when it is a USD file, else over a rig.usda
        written here), result.json, animation.json and scene.npz (object mesh and poses, table,
        the frame's contact targets: what ``handretarget evaluate`` measures against) into
        ``out_dir``; returns {name: path}. Without curves (fit pass off) no animation.usda is
        written. result.json names the rig file (``rig_file``)."""
        from .export import write_animation_json, write_animation_usd
        from .rig.io import USD_SUFFIXES, load_rig, save_rig

        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        if self.rig is None and rig_path is None:
            raise InputError("writing a loaded result needs the rig file", element="rig_path")
        rig = self.rig if self.rig is not None else load_rig(rig_path)
        paths = {}
        if self.curves is not None:
            if rig_path is None or Path(str(rig_path)).suffix.lower() not in USD_SUFFIXES:
                rig_path = paths["rig.usda"] = out / "rig.usda"
                save_rig(rig, rig_path)
            paths["animation.usda"] = out / "animation.usda"
            write_animation_usd(paths["animation.usda"], rig=rig, rig_file=str(rig_path), dof_curves=self.curves,
                                fps=self.fps, n_frames=self.n_frames, object_vertices=self.object_vertices,
                                object_faces=self.object_faces, object_poses=self.object_poses,
                                metadata={"clip": self.clip_source, "summary": _plain(self.summary)})
        if "rig.usda" not in paths and (rig_path is None
                                         or Path(str(rig_path)).suffix.lower() not in USD_SUFFIXES):
            rig_path = paths["rig.usda"] = out / "rig.usda"
            save_rig(rig, rig_path)
        if self.object_vertices is not None:
            paths["scene.npz"] = out / "scene.npz"
            self._write_scene(paths["scene.npz"])
        paths["result.json"] = out / "result.json"
        rig_file = Path(str(rig_path)).resolve()
        self.rig_file = rig_file.name if rig_file.parent == out.resolve() else str(rig_file)
        text = json.dumps(self.to_dict(), indent=1, allow_nan=False)
        with atomic_path(paths["result.json"], suffix=".json.tmp") as tmp:
            tmp.write_text(text, encoding="utf-8")
        paths["animation.json"] = out / "animation.json"
        write_animation_json(paths["animation.json"], self.dof_names, self.times, self.sampled(), extra=_plain({
            "rig": self.rig_name, "fps": self.fps, "dof_kinds": self.dof_kinds, "lower": self.lower,
            "upper": self.upper, "values": "spline" if self.curves else "frames"}))
        return paths


    def _write_scene(self, path) -> None:
        c = self.contacts
        arrays = dict(object_vertices=self.object_vertices, object_faces=self.object_faces,
                      object_poses=self.object_poses)
        if self.table_pose is not None:
            arrays.update(table_pose=self.table_pose, table_half_extents=self.table_half_extents)
        if c is not None:
            arrays.update(contact_frame_offsets=c.frame_offsets, contact_target_faces=c.target_faces,
                          contact_target_barycentric=c.target_barycentric,
                          contact_surface_points=c.object_points - c.gap[:, None] * c.object_normals,
                          contact_object_normals=c.object_normals)
        if self.source_contact_count is not None:
            arrays["source_contact_count"] = self.source_contact_count
        if self.source_hand is not None:
            arrays.update(source_frames=self.source_hand[0], source_hand_vertices=self.source_hand[1],
                          source_hand_faces=self.source_hand[2])
        with atomic_path(path, suffix=".npz.tmp") as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, **arrays)


def _plain(obj):
    """JSON types: numpy -> lists / numbers, NaN and inf -> None, tuples -> lists."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def load_result(path) -> RetargetResult:
    """Read result.json (``path`` is the file or its folder) back into a :class:`RetargetResult`
    (without the rig and the object)."""
    path = Path(path)
    if path.is_dir():
        path = path / "result.json"
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError("no result.json here", source=str(path)) from None
    except (OSError, ValueError) as exc:
        raise InputError(f"not a readable JSON file: {exc}", source=str(path)) from None
    if not isinstance(doc, dict) or doc.get("format") != RESULT_FORMAT:
        raise InputError(f"not a {RESULT_FORMAT} document", source=str(path), element="format")
    if doc.get("version") != RESULT_VERSION:
        raise InputError(f"unsupported version {doc.get('version')!r} (this reader knows {RESULT_VERSION})",
                         source=str(path), element="version")

    def arr(key):  # (N,) floats, null -> NaN
        return np.array([np.nan if v is None else v for v in doc[key]], dtype=np.float64)

    try:
        n_dofs = len(doc["dof_names"])
        q = np.array(doc["q"], dtype=np.float64).reshape(-1, n_dofs)
        curves = None if doc["curves"] is None else [
            BSplineCurve(c["knots"], c["coefficients"], c["degree"], c["extrapolation"]) for c in doc["curves"]]
        return RetargetResult(
            rig_name=doc["rig"], dof_names=list(doc["dof_names"]), dof_kinds=list(doc["dof_kinds"]),
            lower=arr("lower"), upper=arr("upper"), fps=float(doc["fps"]), times=arr("times"), q=q, curves=curves,
            unresolved=np.array(doc["unresolved"], dtype=bool).reshape(q.shape), timings=doc["timings"],
            counts=doc["counts"], contact_distance_mm=arr("contact_distance_mm"),
            contact_count=np.array(doc["contact_count"], dtype=np.int64), marker_error_mm=arr("marker_error_mm"),
            summary=doc["summary"], config=doc["config"], clip_source=doc.get("clip", ""),
            rig_file=doc.get("rig_file", ""))
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"malformed result: {exc!r}", source=str(path)) from None


# ---- the run ------------------------------------------------------------------------------------
def check_inputs(clip: Clip, source: Rig, target: Rig, annotations: Annotations, config: RetargetConfig) -> int:
    """Raise InputError on inputs that cannot give a result; return the control-point count.
    Checks: both rigs (``Rig.validate``: limits that hold the rest pose, closed surface, ...),
    the annotations' mesh signatures against the rigs' surfaces, and a clip long enough for
    the spline (>= 4 frames and >= ``fit.control_points`` when fixed)."""
    source.validate(source=f"source rig {source.name!r}")
    target.validate(source=f"target rig {target.name!r}")
    annotations.check_meshes(source.surface.faces, source.surface.n_vertices, target.surface.faces,
                             target.surface.n_vertices, source="annotations")
    fixed = config.fit.control_points
    need = max(MIN_CONTROL_POINTS, fixed or 0)
    if config.passes.fit and clip.n_frames < need:
        why = f"fit.control_points = {fixed}" if fixed else f"a cubic B-spline has {MIN_CONTROL_POINTS} control points"
        raise InputError(f"the clip is too short for the spline fit: {clip.n_frames} frames, at least {need} needed "
                         f"({why})", source="clip", element="n_frames")
    return config.n_control_points(clip.n_frames, clip.fps)


def retarget(clip: Clip, source_rig: Rig, target_rig: Rig, annotations: Annotations, config: RetargetConfig, *,
             progress: Progress | None = None, pairs=None) -> RetargetResult:
    """Retarget ``clip`` (made with ``source_rig``) onto ``target_rig``: every pass of
    :func:`solve_trajectory`, then one cubic B-spline per DOF over the frame times (entries the
    refinement left unresolved are masked out). ``progress(stage, done, total)`` is called as
    stages advance; ``pairs``: the clip's contact pairs when already computed."""
    from .pairing.dense import pair_contacts
    from .solve.pipeline import solve_trajectory

    report = progress or (lambda stage, done, total: None)
    start = time.perf_counter()
    n_control = check_inputs(clip, source_rig, target_rig, annotations, config)
    timings = {"validation": time.perf_counter() - start}
    if pairs is None:
        report("pairing", 0, 1)
        t0 = time.perf_counter()
        pairs = pair_contacts(clip)
        timings["pairing"] = time.perf_counter() - t0
    report("transfer", 0, 1)
    trajectory = solve_trajectory(clip, source_rig, target_rig, annotations, config, progress=progress, pairs=pairs)
    timings.update({k: v for k, v in trajectory.timings.items() if k != "pairing"})

    times = np.arange(clip.n_frames) / clip.fps
    curves = None
    if config.passes.fit:
        report("spline fit", 0, 1)
        t0 = time.perf_counter()
        usable = int((~trajectory.unresolved).sum(axis=0).min())
        n_control = max(MIN_CONTROL_POINTS, min(n_control, usable))
        curves = fit_trajectory(times, trajectory.q, n_control, mask=~trajectory.unresolved,
                                optimize_knots=config.fit.optimize_knots,
                                limits=(target_rig.lower, target_rig.upper) if config.fit.respect_limits else None)
        timings["fit"] = time.perf_counter() - t0
        report("spline fit", 1, 1)

    t0 = time.perf_counter()
    distance, count, marker = solved_figures(target_rig, trajectory)
    timings["figures"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - start
    counts = run_counts(trajectory.reports)
    contact_frames = count > 0
    summary = {
        "frames": clip.n_frames, "dofs": target_rig.n_dofs, "control_points": n_control if curves else None,
        "contact_frames": int(contact_frames.sum()),
        "contact_distance_median_mm": float(np.median(distance[contact_frames])) if contact_frames.any() else None,
        "marker_error_median_mm": float(np.nanmedian(marker)) if np.isfinite(marker).any() else None,
        "failed_frames": len(counts["failed_frames"]), "unresolved_entries": int(trajectory.unresolved.sum()),
        "transferred_share": trajectory.transferred_share, "seconds": timings["total"],
    }
    return RetargetResult(
        rig_name=target_rig.name, dof_names=target_rig.dof_names, dof_kinds=[d.kind for d in target_rig.dofs],
        lower=target_rig.lower, upper=target_rig.upper, fps=float(clip.fps), times=times, q=trajectory.q,
        curves=curves, unresolved=trajectory.unresolved, timings=timings, counts=counts,
        contact_distance_mm=distance, contact_count=count, marker_error_mm=marker, summary=summary,
        config=config.to_dict(), clip_source=clip.source, rig=target_rig, object_vertices=clip.object_vertices,
        object_faces=clip.object_faces, object_poses=clip.object_poses, table_pose=clip.table_pose,
        table_half_extents=clip.table_half_extents, contacts=trajectory.contacts,
        source_contact_count=np.diff(trajectory.pairs.frame_offsets), source_hand=_source_snapshots(clip, count))


def _source_snapshots(clip: Clip, contact_count: np.ndarray, n: int = 4):
    """A few frames of the source hand for side-by-side renders: frames (K,) spread over the
    contact frames (over all frames without contact), vertices (K, V, 3) float32, faces."""
    pool = np.nonzero(contact_count > 0)[0]
    if len(pool) == 0:
        pool = np.arange(clip.n_frames)
    frames = np.unique(pool[np.linspace(0, len(pool) - 1, min(n, len(pool))).round().astype(int)])
    return frames, clip.hand_vertices[frames].astype(np.float32), clip.hand_faces


def solved_figures(rig: Rig, trajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame at the solved poses: median contact distance (T,) mm (NaN without contacts),
    contact count (T,), and marker error (T,) mm, the pair-weighted mean distance between the
    target marker points and the source markers."""
    kin = rig.kinematics()
    contacts, markers = trajectory.contacts, trajectory.markers
    n_frames = len(trajectory.q)
    distance, marker = np.full(n_frames, np.nan), np.full(n_frames, np.nan)
    count = np.array([contacts.count(f) for f in range(n_frames)], dtype=np.int64)
    marker_binding = kin.bind(SurfacePoints(markers.target_faces, markers.target_barycentric)) \
        if len(markers.pair_target) else None
    weight = markers.pair_weight / markers.pair_weight.sum() if marker_binding is not None else None
    for f in range(n_frames):
        pose = kin.pose(trajectory.q[f])
        if count[f]:
            points = contacts.frame(f)[0]  # the object's surface, not a kept source gap
            distance[f] = MM * np.median(np.linalg.norm(kin.points(pose, kin.bind(points)) - contacts.surface_points(f),
                                                        axis=1))
        if marker_binding is not None:
            x = kin.points(pose, marker_binding)[markers.pair_target]
            marker[f] = MM * float(weight @ np.linalg.norm(x - markers.source_positions[f], axis=1))
    return distance, count, marker


def run_counts(reports: dict) -> dict:
    """Evaluations per frame and failed frames of each pass (root, full, filter), the
    refinement report (``RefinementReport.to_dict``) and every failed frame once."""
    passes, failed = {}, {}
    for name, r in reports.items():
        if name == "refine":
            continue
        passes[name] = {"frames": r.frames, "evaluations": r.evaluations,
                        "evaluations_per_frame": r.evaluations / r.frames if r.frames else 0.0,
                        "failed": [{"frame": int(f), "error": str(e)} for f, e in r.failed]}
        for f, e in r.failed:
            failed.setdefault(int(f), str(e))
    return {"passes": passes, "refinement": reports["refine"].to_dict() if "refine" in reports else None,
            "failed_frames": [{"frame": f, "error": failed[f]} for f in sorted(failed)]}
