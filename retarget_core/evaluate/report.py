"""``handretarget evaluate DIR``: the metrics of one retarget output, as metrics.json and plots.

Reads what :meth:`~retarget_core.result.RetargetResult.write` left in DIR (result.json, the
rig file it names, scene.npz), poses the target hand at the spline samples of every frame and
measures: hand-object, self and table intersection (exact volumes, percent of the hand's volume)
and penetration depths (:mod:`.intersection`), contact error and coverage, marker error, smoothness
and DOF limit violations. Intersection figures in the summary are over the contact frames.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import atomic_path

METRICS_FORMAT = "handretarget.metrics"
#: 2: exact intersection volumes and depths, figures over the contact frames
METRICS_VERSION = 2
MM = 1000.0
#: penetration depth series (mm): both directions of hand-object, self and table
DEPTHS = ("hand_into_object", "object_into_hand", "self", "table")
COVERAGE_MM = 5.0


@dataclass
class Scene:
    """scene.npz: object mesh (V, 3) m / faces (F, 3) and poses (T, 4, 4); optional table pose
    (4, 4) and half extents (3,) m; contact targets split by frame offsets (T+1,)."""

    object_vertices: np.ndarray
    object_faces: np.ndarray
    object_poses: np.ndarray
    table_pose: np.ndarray | None
    table_half_extents: np.ndarray | None
    contact_frame_offsets: np.ndarray | None
    contact_target_faces: np.ndarray | None
    contact_target_barycentric: np.ndarray | None
    contact_surface_points: np.ndarray | None
    source_contact_count: np.ndarray | None


def load_scene(path) -> Scene:
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise InputError("no scene.npz here (written by handretarget retarget since result version 1 with "
                         "scene data; rerun the retarget)", source=str(path)) from None
    except (OSError, ValueError) as exc:
        raise InputError(f"not a readable scene file: {exc}", source=str(path)) from None
    for key in ("object_vertices", "object_faces", "object_poses"):
        if key not in data:
            raise InputError(f"missing array {key!r}", source=str(path), element=key)
    get = data.get
    return Scene(data["object_vertices"], data["object_faces"], data["object_poses"], get("table_pose"),
                 get("table_half_extents"), get("contact_frame_offsets"), get("contact_target_faces"),
                 get("contact_target_barycentric"), get("contact_surface_points"), get("source_contact_count"))


def load_output(folder):
    """(RetargetResult, Rig, Scene) of a retarget output folder; clear errors for a missing or
    foreign file."""
    from ..result import load_result
    from ..rig.io import load_rig

    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("not a folder", source=str(folder))
    result = load_result(folder)
    rig_file = result.rig_file
    if not rig_file:
        raise InputError("result.json names no rig_file (written by an older version: rerun the retarget)",
                         source=str(folder / "result.json"), element="rig_file")
    rig_path = Path(rig_file) if Path(rig_file).is_absolute() else folder / rig_file
    if not rig_path.exists():
        raise InputError("the rig file named by result.json is missing", source=str(rig_path))
    rig = load_rig(rig_path)
    if rig.dof_names != result.dof_names:
        raise InputError("the rig's DOFs differ from the result's", source=str(rig_path), element="dof_names")
    scene = load_scene(folder / "scene.npz")
    if len(scene.object_poses) != result.n_frames:
        raise InputError(f"scene.npz has {len(scene.object_poses)} frames, result.json {result.n_frames}",
                         source=str(folder / "scene.npz"), element="object_poses")
    return result, rig, scene


def scene_contacts(scene: Scene):
    """The scene's contact targets as a :class:`~retarget_core.solve.targets.ContactTargets`
    (object points already on the surface: no gap), None when scene.npz has none."""
    from ..solve.targets import ContactTargets

    if scene.contact_frame_offsets is None:
        return None
    points = np.asarray(scene.contact_surface_points, dtype=np.float64)
    return ContactTargets(scene.contact_frame_offsets, scene.contact_target_faces, scene.contact_target_barycentric,
                          points, np.zeros_like(points), np.zeros(len(points)))


def _scene_extras(path) -> dict:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in ("source_frames", "source_hand_vertices", "source_hand_faces") if k in z.files}


def evaluate_output(folder, *, stride: int = 1, self_intersection_stride: int | None = None) -> dict:
    """Per-frame metrics and their summary of the retarget output in ``folder`` (a dict ready
    for metrics.json). ``stride``: measure intersections every stride-th frame (the others are
    None); self intersection, the costliest, every ``self_intersection_stride``-th (default:
    ``stride``). Contact, marker, smoothness and limit figures cover every frame."""
    from ..rig.parts import rig_parts
    from .intersection import PosedHand, SceneObject, frame_intersections
    from .metrics import (
        contact_distances,
        coverage_per_frame,
        dof_limit_violations,
        dof_smoothness,
        median_per_frame_mm,
        summarize_series,
    )

    result, rig, scene = load_output(folder)
    kin = rig.kinematics()
    q = result.sampled()
    n = result.n_frames
    stride = max(1, int(stride))
    self_stride = max(1, int(self_intersection_stride or stride))
    faces = rig.surface.faces
    try:
        parts = rig_parts(rig)
        hand_volume = PosedHand(parts, kin.skin(rig.rest_pose), faces).volume  # the denominator: the rest hand
    except InputError:
        parts, hand_volume = None, None  # the frames say why the surface cannot be measured
    kinds = ("hand_object", "self", "table")
    percent = {k: np.full(n, np.nan) for k in kinds}
    depth_mm = {k: np.full(n, np.nan) for k in DEPTHS}
    reasons = {}
    contact_mm = np.full(n, np.nan)
    solved_contact_mm = np.full(n, np.nan)  # the same measure at the solved frames the curves were fitted to
    coverage = np.full(n, np.nan)
    contacts = scene_contacts(scene)
    if contacts is not None:
        distances = contact_distances(kin, q, contacts)
        contact_mm, _ = median_per_frame_mm(distances, contacts.frame_offsets)
        solved_contact_mm, _ = median_per_frame_mm(contact_distances(kin, result.q, contacts), contacts.frame_offsets)
        # the source contacts the transfer dropped count as not realised
        coverage = coverage_per_frame(distances, contacts.frame_offsets, scene.source_contact_count, COVERAGE_MM / MM)

    scene_object = SceneObject(scene.object_vertices, scene.object_faces)
    for f in range(0, n, stride):
        found = frame_intersections(
            kin.skin(q[f]), faces, parts=parts, scene_object=scene_object, object_pose=scene.object_poses[f],
            table_pose=scene.table_pose, table_half_extents=scene.table_half_extents, hand_volume_m3=hand_volume,
            kinds=kinds if f % self_stride == 0 else ("hand_object", "table"))
        for kind, r in found.items():
            if not r.available:
                reasons[kind] = r.reason
                continue
            percent[kind][f] = r.percent_of_hand
            if kind == "hand_object":
                depth_mm["hand_into_object"][f] = MM * r.hand_depth_m
                depth_mm["object_into_hand"][f] = MM * r.other_depth_m
            else:
                depth_mm[kind][f] = MM * r.max_depth_m
    penetration = np.fmax(depth_mm["hand_into_object"], depth_mm["object_into_hand"])
    # The intersection figures are taken over the frames with contacts (the grasp), not the approach.
    if scene.source_contact_count is not None and np.any(scene.source_contact_count > 0):
        grasp, over = np.asarray(scene.source_contact_count) > 0, "contact frames"
    elif np.isfinite(contact_mm).any():
        grasp, over = np.isfinite(contact_mm), "contact frames"
    else:
        grasp, over = np.ones(n, bool), "all frames"

    def at_grasp(values, prefix):
        s_ = summarize_series(np.where(grasp, values, np.nan))
        return {f"{prefix}_median": s_["median"], f"{prefix}_p95": s_["p95"], f"{prefix}_max": s_["max"]}

    measured = grasp & np.isfinite(penetration)
    smooth = dof_smoothness(q, result.fps, list(result.dof_kinds))
    limits = dof_limit_violations(q, result.lower, result.upper)
    per_frame = {"intersection_percent": {k: percent[k] for k in kinds}, "depth_mm": depth_mm,
                 "penetration_mm": penetration, "contact_error_median_mm": contact_mm,
                 "contact_coverage": coverage, "marker_error_mm": result.marker_error_mm}
    contact_frames = np.isfinite(contact_mm)
    summary = {
        "contact_frames": int(contact_frames.sum()),
        "contact_error_median_mm": float(np.median(contact_mm[contact_frames])) if contact_frames.any() else None,
        "solved_contact_error_median_mm": float(np.median(solved_contact_mm[contact_frames]))
        if contact_frames.any() else None,
        "contact_coverage_mean": float(np.mean(coverage[np.isfinite(coverage)])) if np.isfinite(coverage).any() else None,
        "marker_error_median_mm": summarize_series(result.marker_error_mm)["median"],
        "intersection_over": over,
        **{key: v for k in kinds for key, v in at_grasp(percent[k], f"{k}_intersection_percent").items()},
        **at_grasp(penetration, "penetration_mm"),
        **{key: v for k in DEPTHS for key, v in at_grasp(depth_mm[k], f"{k}_depth_mm").items()},
        "penetration_over_1mm_share": float(np.mean(penetration[measured] > 1.0)) if measured.any() else None,
        "accel_rms_median_deg_s2": float(np.nanmedian(smooth.accel_rms[smooth.rotation]))
        if smooth.rotation.any() and np.isfinite(smooth.accel_rms[smooth.rotation]).any() else None,
        "jerk_rms_median_deg_s3": float(np.nanmedian(smooth.jerk_rms[smooth.rotation]))
        if smooth.rotation.any() and np.isfinite(smooth.jerk_rms[smooth.rotation]).any() else None,
        "limit_violations": limits.count,
    }
    doc = {
        "format": METRICS_FORMAT, "version": METRICS_VERSION, "rig": result.rig_name, "clip": result.clip_source,
        "method": result.config.get("method", "contacts"), "fps": result.fps, "frames": n, "stride": stride,
        "self_intersection_stride": self_stride, "hand_volume_m3": hand_volume, "summary": summary,
        "per_frame": per_frame, "unavailable": reasons,
        "series": {name: summarize_series(v) for name, v in
                   [("contact_error_median_mm", contact_mm), ("contact_coverage", coverage),
                    ("marker_error_mm", result.marker_error_mm)]
                   + [(f"{k}_intersection_percent", percent[k]) for k in kinds]
                   + [("penetration_mm", penetration)]},
        "smoothness": smooth.to_dict(result.dof_names),
        "limits": limits.to_dict(result.dof_names),
    }
    return doc


def write_plots(doc: dict, out_dir) -> dict:
    """intersection.png (percent of the hand's volume over time per kind, like the paper's
    intersection figure, over the penetration depths in mm) and contact_error.png (median contact error and coverage over time)
    into ``out_dir``; returns {name: path}."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    n, fps = doc["frames"], doc["fps"]
    t = np.arange(n) / fps
    paths = {}

    def series(values):
        return np.array([np.nan if v is None else v for v in values], dtype=float)

    fig, (ax, ax_d) = plt.subplots(2, 1, figsize=(8, 5.6), dpi=110, sharex=True)
    labels = {"hand_object": "hand-object", "self": "self", "table": "table"}
    for kind, values in doc["per_frame"]["intersection_percent"].items():
        y = series(values)
        keep = np.isfinite(y)
        if keep.any():
            ax.plot(t[keep], y[keep], label=labels.get(kind, kind), lw=1.4)
    ax.set_ylabel("intersection (% of hand volume)")
    ax.set_title(f"{doc['rig']} ({doc['method']}): intersection (exact volumes)")
    ax.legend(loc="upper right")
    ax.grid(alpha=0.3)
    depth_labels = {"hand_into_object": "hand into object", "object_into_hand": "object into hand",
                    "self": "self", "table": "hand into table"}
    for kind, values in doc["per_frame"].get("depth_mm", {}).items():
        y = series(values)
        keep = np.isfinite(y)
        if keep.any() and np.any(y[keep] > 0):
            ax_d.plot(t[keep], y[keep], label=depth_labels.get(kind, kind), lw=1.2)
    ax_d.axhline(1.0, color="0.5", lw=0.8, ls=":")
    ax_d.axhline(2.0, color="0.5", lw=0.8, ls="--")
    ax_d.set_xlabel("time (s)")
    ax_d.set_ylabel("penetration depth (mm)")
    handles, _ = ax_d.get_legend_handles_labels()
    if handles:
        ax_d.legend(loc="upper right")
    ax_d.grid(alpha=0.3)
    fig.tight_layout()
    paths["intersection.png"] = out / "intersection.png"
    _save(fig, paths["intersection.png"])
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(8, 3.2), dpi=110)
    err = series(doc["per_frame"]["contact_error_median_mm"])
    keep = np.isfinite(err)
    ax.plot(t[keep], err[keep], ".", ms=3, color="C3", label="median contact error (mm)")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("contact error (mm)")
    ax2 = ax.twinx()
    cov = series(doc["per_frame"]["contact_coverage"])
    ax2.plot(t[np.isfinite(cov)], 100 * cov[np.isfinite(cov)], ".", ms=3, color="C0", label="coverage (%)")
    ax2.set_ylabel(f"coverage within {COVERAGE_MM:g} mm (%)")
    ax2.set_ylim(0, 105)
    ax.set_title(f"{doc['rig']} ({doc['method']}): contacts")
    ax.grid(alpha=0.3)
    fig.legend(loc="upper right")
    fig.tight_layout()
    paths["contact_error.png"] = out / "contact_error.png"
    _save(fig, paths["contact_error.png"])
    plt.close(fig)
    return paths


def _save(fig, path) -> None:
    with atomic_path(path, suffix=".png.tmp") as tmp:
        fig.savefig(tmp, format="png")


def write_output_pictures(folder) -> dict:
    """contact_sheet.png, preview.gif and pictures.json of the retarget output in ``folder``
    (:mod:`~retarget_core.render.preview`), from its result, rig and scene.npz; {name: path}."""
    from dataclasses import replace

    folder = Path(folder)
    result, rig, scene = load_output(folder)
    extras = _scene_extras(folder / "scene.npz")
    source_hand = ((extras["source_frames"], extras["source_hand_vertices"], extras["source_hand_faces"])
                   if "source_frames" in extras else None)
    result = replace(result, rig=rig, object_vertices=scene.object_vertices, object_faces=scene.object_faces,
                     object_poses=scene.object_poses, table_pose=scene.table_pose,
                     table_half_extents=scene.table_half_extents, contacts=scene_contacts(scene),
                     source_contact_count=scene.source_contact_count, source_hand=source_hand)
    return result.write_pictures(folder)


def write_evaluation(folder, *, stride: int = 1, self_intersection_stride: int | None = None,
                     render: bool = True) -> dict:
    """Evaluate the retarget output ``folder`` and write metrics.json, intersection.png,
    contact_error.png and (``render``) the pictures (contact_sheet.png, preview.gif,
    pictures.json: :func:`write_output_pictures`) into it; returns {name: path}."""
    from ..jsonio import to_jsonable

    folder = Path(folder)
    doc = evaluate_output(folder, stride=stride, self_intersection_stride=self_intersection_stride)
    paths = {"metrics.json": folder / "metrics.json"}
    text = json.dumps(to_jsonable(doc), indent=1, allow_nan=False)
    with atomic_path(paths["metrics.json"], suffix=".json.tmp") as tmp:
        tmp.write_text(text, encoding="utf-8")
    paths.update(write_plots(to_jsonable(doc), folder))
    if render:
        paths.update(write_output_pictures(folder))
    return paths
