"""The outcome of one retargeting run, and its files.

Files written by :meth:`RetargetResult.write` into one folder::

    animation.usda   USD layer over the rig file: baked SkelAnimation + one native spline per
                     DOF (:func:`~retarget_core.export.write_animation_usd`), object animation;
                     its customData carries the run's provenance
    result.json      this result (format "handretarget.result", version 2); NaN -> null
    animation.json   per-frame DOF values for robot users (:func:`~retarget_core.export.write_animation_json`)
    scene.npz        object mesh and poses, table, contact targets (what ``evaluate`` measures)
    rig.usda         the rig, when it was not given as a USD file
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import InputError
from .files import atomic_path
from .fit.splines import BSplineCurve, evaluate_curves
from .jsonio import to_jsonable
from .rig.model import Rig

logger = logging.getLogger(__name__)

RESULT_FORMAT = "handretarget.result"
RESULT_VERSION = 2


@dataclass
class RetargetResult:
    """The outcome of :func:`retarget`. Units: seconds, radians / metres (DOF values), mm
    (distances in the figures).

    dof_names, dof_kinds ("rotate" / "translate"), lower, upper (D,); fps; times (T,) frame
    times (frame / fps); q (T, D) the solved per-frame poses; curves: one cubic B-spline per
    DOF (None when the fit pass is off); unresolved (T, D) entries still violating the
    acceleration check (left out of the fit); timings {stage: seconds}; counts: evaluations
    per frame per pass, failed frames with their error, refinement report; contact_distance_mm
    (T,) median distance between the target contact points and their object points at the
    delivered curves (the solved frames without a fit; NaN on frames without contacts);
    contact_count (T,); marker_error_mm (T,) mean distance of the target markers to the source
    markers there (each marker counts once); summary: the figures above in short (``figures_at``
    says where), with the solved frames' medians as ``solved_*``; config: ``RetargetConfig.to_dict()``; unused_settings: the settings the
    method does not use ({key: {value, why}}); frames: [start, end) of the input clip that was
    retargeted (times count from its start); provenance: project version and commit, sha256 of
    every input, the run configuration and the executor. ``rig`` and the object mesh / poses
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
    unused_settings: dict = field(default_factory=dict)
    frames: tuple = (0, 0)
    provenance: dict = field(default_factory=dict)
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
        return to_jsonable({
            "format": RESULT_FORMAT, "version": RESULT_VERSION, "rig": self.rig_name, "clip": self.clip_source,
            "rig_file": self.rig_file,
            "summary": self.summary, "timings": self.timings, "fps": self.fps, "dof_names": self.dof_names,
            "dof_kinds": self.dof_kinds, "lower": self.lower, "upper": self.upper, "times": self.times, "q": self.q,
            "curves": curves, "unresolved": self.unresolved,
            "counts": self.counts, "contact_distance_mm": self.contact_distance_mm,
            "contact_count": self.contact_count, "marker_error_mm": self.marker_error_mm, "config": self.config,
            "unused_settings": self.unused_settings, "frames": list(self.frames), "provenance": self.provenance,
        })

    def write(self, out_dir, rig_path=None, *, rig_asset_path: str | None = None,
              control_rate_hz: float | None = None, pictures: bool = True) -> dict:
        """Write animation.usda (over ``rig_path`` when it is a rig file the layer composes over,
        :func:`~retarget_core.export.usd_animation.layers_over`; else over a rig.usda written here), result.json, animation.json and scene.npz (object mesh and poses, table,
        the frame's contact targets: what ``handretarget evaluate`` measures against) into
        ``out_dir``; returns {name: path}. Without curves (fit pass off) no animation.usda is
        written. result.json names the rig file (``rig_file``). ``rig_asset_path``: the layer
        sublayers this asset path as written (the user's own file, where the layer will sit)
        rather than ``rig_path``, which must then be a USD file it composes over; rig.usda is
        written here too (result.json names it). For a robot rig (URDF / MJCF) animation.json
        also holds the joint commands in the robot file's order at ``control_rate_hz`` (default:
        the clip's rate; :mod:`~retarget_core.export.robot_trajectory`). ``pictures`` (with the object
        known): contact_sheet.png, preview.gif and pictures.json of the delivered curve
        (:mod:`~retarget_core.render.preview`)."""
        from .export import write_animation_json, write_animation_usd
        from .export.robot_trajectory import is_robot, robot_trajectory
        from .export.usd_animation import layers_over
        from .rig.io import USD_SUFFIXES, load_rig, save_rig

        if self.rig is None and rig_path is None:
            raise InputError("writing a loaded result needs the rig file", element="rig_path")
        rig = self.rig if self.rig is not None else load_rig(rig_path)
        robot = None
        if control_rate_hz is not None and not (is_robot(rig) and self.curves):
            raise InputError("a control rate resamples a robot's joint commands from the delivered curves: this "
                             f"rig is {'not a URDF / MJCF robot' if not is_robot(rig) else 'without curves (fit off)'}",
                             element="rate")
        if is_robot(rig) and self.curves:  # before anything is written: a bad rate stores nothing
            robot = robot_trajectory(rig, self.curves, float(self.times[-1]) if len(self.times) else 0.0,
                                     control_rate_hz or self.fps, frame_times=self.times)
            if robot["velocity_exceeded"]:
                logger.warning("%s: the delivered curves exceed the file's velocity limits on %s (animation.json "
                               "robot.velocity lists when)", rig.name, ", ".join(robot["velocity_exceeded"]))
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        paths = {}
        usd_rig = rig_path is not None and Path(str(rig_path)).suffix.lower() in USD_SUFFIXES
        over = usd_rig and layers_over(rig, rig_path)
        if rig_asset_path is not None and not over:
            raise InputError("a rig asset path names the user's USD file the layer composes over; this rig "
                             "does not come from a USD file it can compose over", element="rig_asset_path")
        if usd_rig and not over:
            rig_path = None  # the layer goes over a rig.usda written here
        if self.curves is not None:
            if rig_path is None or Path(str(rig_path)).suffix.lower() not in USD_SUFFIXES:
                rig_path = paths["rig.usda"] = out / "rig.usda"
                save_rig(rig, rig_path)
            paths["animation.usda"] = out / "animation.usda"
            write_animation_usd(paths["animation.usda"], rig=rig, rig_file=str(rig_path), sublayer_path=rig_asset_path,
                                dof_curves=self.curves,
                                fps=self.fps, n_frames=self.n_frames, object_vertices=self.object_vertices,
                                object_faces=self.object_faces, object_poses=self.object_poses,
                                metadata={"clip": self.clip_source, "frames": list(self.frames),
                                          "summary": to_jsonable(self.summary),
                                          "provenance": to_jsonable(self.provenance)})
        if "rig.usda" not in paths and (rig_path is None or rig_asset_path is not None
                                         or Path(str(rig_path)).suffix.lower() not in USD_SUFFIXES):
            # with a rig asset path the layer names the user's file; the rig is kept here as well
            # (what ``evaluate`` reads, and the hand for a user without that file)
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
        if pictures and self.object_vertices is not None:
            paths.update(self.write_pictures(out, rig))
        paths["animation.json"] = out / "animation.json"
        write_animation_json(paths["animation.json"], self.dof_names, self.times, self.sampled(), extra=to_jsonable({
            "rig": self.rig_name, "fps": self.fps, "dof_kinds": self.dof_kinds, "lower": self.lower,
            "upper": self.upper, "values": "spline" if self.curves else "frames"}), robot=robot)
        return paths


    def write_pictures(self, out_dir, rig=None) -> dict:
        """The contact sheet and preview of the delivered curve on ``rig`` (default: the result's)
        into ``out_dir`` ({name: path})."""
        from .render.preview import result_scene, write_pictures

        source = self.provenance.get("inputs", {}).get("source_rig", {})
        source_name = source.get("name") or Path(str(source.get("spec") or source.get("path") or "source")).name
        scene = result_scene(
            rig if rig is not None else self.rig, self.sampled(), self.fps, object_vertices=self.object_vertices, object_faces=self.object_faces,
            object_poses=self.object_poses, contacts=self.contacts, contact_count=self.source_contact_count,
            source_hand=self.source_hand, table_pose=self.table_pose, table_half_extents=self.table_half_extents,
            title=f"{Path(self.clip_source).stem or 'clip'} -> {self.rig_name}, frames {self.frames[0]}:{self.frames[1]}",
            source_name=source_name)
        return write_pictures(scene, out_dir)

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
    if doc.get("version") not in (1, RESULT_VERSION):  # version 1: no provenance, frames or unused_settings
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
            unused_settings=doc.get("unused_settings", {}), frames=tuple(doc.get("frames", (0, len(q)))),
            provenance=doc.get("provenance", {}),
            rig_file=doc.get("rig_file", ""))
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"malformed result: {exc!r}", source=str(path)) from None


