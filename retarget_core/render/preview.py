"""Pictures of a retarget: a labelled contact sheet and an animated preview of the delivered curve.

``contact_sheet.png``: a few contact frames, one row each, the captured source hand and the target
hand posed by the delivered curves side by side, the object drawn translucent, the contacts as
dots (source: where the source hand touches the object; target: the target hand's contact points,
coloured by their distance to the object point they should reach). ``preview.gif``: the same
views over the whole clip at about :data:`PREVIEW_RATE_HZ`, playing in real time.
``pictures.json``: the frames, the views and the share of contacts they show.

The views are chosen per clip (:func:`choose_views`): of :data:`VIEW_DIRECTIONS` (the 26
directions to the faces, edges and corners of a cube around the scene), the one that shows the
most of the target's contact points unoccluded in the depth buffer of the opaque scene (hand and table; the object
is translucent, so the contacts between it and the hand can be seen through it) over the sheet's
frames (the target's contacts: what the user gets); a second one when the first shows under
:data:`VISIBLE_GOAL` of them. A top-down grasp is
seen from the side or below, not from the back of the hand; a wrap grasp from both sides.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import atomic_path
from ..mesh.surface_points import SurfacePoints
from .raster import (
    BACKGROUND,
    OBJECT_BLUE,
    SKIN,
    TABLE_WOOD,
    Camera,
    box_mesh,
    depth_buffer,
    frame_camera,
    render_meshes,
)

#: the preview's frame rate (Hz) when the clip's allows it, and its most frames (longer clips play
#: at a lower rate, still in real time)
PREVIEW_RATE_HZ = 24.0
PREVIEW_MAX_FRAMES = 60
SHEET_ROWS = 4
#: the share of the contact points the pictures should show unoccluded (issue 21); a second view
#: is added when one shows fewer
VISIBLE_GOAL = 0.7
SECOND_VIEW_GAIN = 0.1
#: contact error colour scale (mm): green at 0, yellow at half, red at and beyond the end
ERROR_SCALE_MM = 10.0
#: a contact point is unoccluded when no opaque surface lies nearer than its own depth minus
#: this much (metres) plus one pixel footprint (the depth buffer's sampling error on surfaces
#: sloped up to 45 degrees; steeper ones near silhouettes count as hidden: the share errs low)
VISIBILITY_TOLERANCE_M = 1.0e-3
SOURCE_DOT = (250, 250, 250)
GHOST_ALPHA = 0.45
_THREE_QUARTER = np.array([0.7, -1.0, 0.75]) / np.linalg.norm([0.7, -1.0, 0.75])


def _cube_directions() -> np.ndarray:
    d = np.array([(x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1) if (x, y, z) != (0, 0, 0)],
                 dtype=np.float64)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


#: (26, 3) unit directions from the scene towards the candidate eyes
VIEW_DIRECTIONS = _cube_directions()


@dataclass
class PictureScene:
    """What the pictures show, all world metres, frames of the result.

    target_vertices(f) -> (V, 3): the target hand at the delivered curve; target_faces (F, 3);
    target_contacts(f) -> ((N_f, 3) hand contact points, (N_f, 3) object points they should meet);
    source_frames (K,) with source_vertices (K, V_s, 3) and source_faces (F_s, 3), or None;
    object mesh (V_o, 3) / (F_o, 3) and poses (T, 4, 4); optional table pose and half extents;
    contact_count (T,) source contacts per frame (picks the sheet's frames)."""

    n_frames: int
    fps: float
    target_vertices: object
    target_faces: np.ndarray
    target_contacts: object
    object_vertices: np.ndarray
    object_faces: np.ndarray
    object_poses: np.ndarray
    contact_count: np.ndarray | None = None
    source_frames: np.ndarray | None = None
    source_vertices: np.ndarray | None = None
    source_faces: np.ndarray | None = None
    table_pose: np.ndarray | None = None
    table_half_extents: np.ndarray | None = None
    title: str = ""
    source_label: str = "source (captured)"
    target_label: str = "target (delivered curve)"

    def object_at(self, f: int) -> np.ndarray:
        pose = np.asarray(self.object_poses[f], dtype=np.float64)
        return np.asarray(self.object_vertices, dtype=np.float64) @ pose[:3, :3].T + pose[:3, 3]

    def source_at(self, f: int) -> np.ndarray | None:
        if self.source_frames is None:
            return None
        hit = np.nonzero(np.asarray(self.source_frames) == f)[0]
        return None if len(hit) == 0 else np.asarray(self.source_vertices[hit[0]], dtype=np.float64)

    def table_mesh(self, near=None, margin: float = 0.05):
        """The table box, cut in its own x and y to ``margin`` metres around the points ``near``
        (N, 3) when given (a table top reaching far beyond the hand only costs pixels), or None."""
        if self.table_pose is None or self.table_half_extents is None:
            return None
        pose = np.asarray(self.table_pose, dtype=np.float64)
        half = np.asarray(self.table_half_extents, dtype=np.float64).reshape(3).copy()
        centre = np.zeros(3)
        if near is not None and len(near):
            local = (np.asarray(near, dtype=np.float64) - pose[:3, 3]) @ pose[:3, :3]
            lo = np.maximum(local.min(axis=0) - margin, -half)
            hi = np.minimum(local.max(axis=0) + margin, half)
            if np.all(hi[:2] > lo[:2]):
                centre[:2], half[:2] = 0.5 * (lo[:2] + hi[:2]), 0.5 * (hi[:2] - lo[:2])
        box = pose.copy()
        box[:3, 3] = pose[:3, 3] + pose[:3, :3] @ centre
        verts, faces = box_mesh(half, box)
        return verts, faces, TABLE_WOOD


def picture_frames(n_frames: int, fps: float, contact_count=None) -> tuple[np.ndarray, np.ndarray]:
    """(sheet frames (<= SHEET_ROWS,), preview frames (<= PREVIEW_MAX_FRAMES,)): the sheet's spread
    evenly over the contact frames (over all frames when none has contacts), the preview's every
    k-th frame, k the clip's rate over :data:`PREVIEW_RATE_HZ` (rounded), raised until at most
    :data:`PREVIEW_MAX_FRAMES` remain."""
    n = int(n_frames)
    if n < 1:
        raise InputError("no frames to picture", element="frames")
    count = np.zeros(n) if contact_count is None else np.asarray(contact_count).reshape(-1)[:n]
    pool = np.nonzero(count > 0)[0]
    if len(pool) == 0:
        pool = np.arange(n)
    sheet = np.unique(pool[np.linspace(0, len(pool) - 1, min(SHEET_ROWS, len(pool))).round().astype(int)])
    step = max(1, int(round(float(fps) / PREVIEW_RATE_HZ))) if fps and np.isfinite(fps) else 1
    step = max(step, int(math.ceil(n / PREVIEW_MAX_FRAMES)))
    return sheet, np.arange(0, n, step)


# ---- visibility --------------------------------------------------------------------------------
def unoccluded(points, depth: np.ndarray, camera: Camera, tolerance: float = VISIBILITY_TOLERANCE_M) -> np.ndarray:
    """(N,) bool: which ``points`` (N, 3) world lie inside the image of ``depth`` (H, W; from
    :func:`~retarget_core.render.raster.depth_buffer` with ``camera``) with no surface nearer than
    their own distance less ``tolerance`` plus one pixel footprint."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    height, width = depth.shape
    view = camera.to_view(pts)
    pix = camera.view_to_pixels(view, (width, height))
    col, row = np.floor(pix[:, 0]).astype(np.int64), np.floor(pix[:, 1]).astype(np.int64)
    inside = (view[:, 2] > camera.near) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
    out = np.zeros(len(pts), dtype=bool)
    if not inside.any():
        return out
    d = view[inside, 2]
    if camera.orthographic:
        footprint = np.full(len(d), camera.ortho_height / height)
    else:
        footprint = d * 2.0 * math.tan(math.radians(camera.fov) / 2.0) / height
    nearest = depth[row[inside], col[inside]]
    out[inside] = nearest >= d - tolerance - footprint
    return out


def _frame_layers(scene: PictureScene, f: int, table=None) -> dict:
    """One frame's sides: {side: (opaque meshes, contact points (N, 3), object points (N, 3))}
    for the source (when stored) and the target, with ``table`` (a mesh or None). The source's
    contacts are the object points it touches; the target's are its hand's contact points."""
    hand_points, object_points = scene.target_contacts(f)
    extra = [table] if table else []
    layers = {}
    source = scene.source_at(f)
    if source is not None:
        layers["source"] = ([(source, scene.source_faces, SKIN)] + extra, object_points, object_points)
    layers["target"] = ([(scene.target_vertices(f), scene.target_faces, SKIN)] + extra, hand_points, object_points)
    return layers


def choose_views(scene: PictureScene, frames, size: int = 96) -> tuple[list, dict]:
    """The view directions ((3,) each, of :data:`VIEW_DIRECTIONS`) the pictures use, and what
    they show. The first shows the most of the target's contact points at ``frames`` unoccluded
    (what the user gets; the source's are reported, not chosen on: a source hand sunk into a
    substituted, thicker object hides its own); when that is under :data:`VISIBLE_GOAL`, a second
    view, the one adding the most of the rest, if it adds at least :data:`SECOND_VIEW_GAIN` of
    them (a wrap grasp hides the near fingers' pads from any one view). Shares within a percent
    are a tie, which goes to the direction nearest the usual three-quarter view (a rasterisation
    difference between machines must not pick another view). Info: {"share", "target_share"
    (the chosen views together), "source_share" (the same views; None without a stored source
    hand), "view_shares" (each view alone), "contacts" (the target's), "cameras" (framing
    ``frames`` at ``size`` pixels: the cameras that measured it)}."""
    framing = _framing_points(scene, frames)
    table = scene.table_mesh(framing)
    layers = [(opaque, points, side) for f in frames
              for side, (opaque, points, _) in _frame_layers(scene, f, table).items() if len(points)]
    cameras = [frame_camera(framing, view=direction, size=(size, size)) for direction in VIEW_DIRECTIONS]

    def seen_from(camera, side):  # (contacts,) bool: the side's contact points this camera sees
        return np.concatenate([np.zeros(0, bool)] + [
            unoccluded(points, depth_buffer(opaque, camera, (size, size)), camera)
            for opaque, points, s in layers if s == side])

    target = np.array([seen_from(camera, "target") for camera in cameras])  # (directions, contacts)
    closeness = VIEW_DIRECTIONS @ _THREE_QUARTER

    def share(mask):
        return float(mask.mean(axis=-1)) if mask.shape[-1] else None

    def best(masks):
        score = np.round(masks.mean(axis=1), 2) if masks.shape[1] else np.zeros(len(masks))
        return int(np.lexsort((closeness, score))[-1])  # the highest share, then the nearest

    chosen = [best(target)]
    if target.shape[1] and target[chosen[0]].mean() < VISIBLE_GOAL:
        second = best(target | target[chosen[0]])
        if (target[second] & ~target[chosen[0]]).mean() >= SECOND_VIEW_GAIN:
            chosen.append(second)
    source = np.array([seen_from(cameras[c], "source") for c in chosen])  # reported only
    info = {"target_share": share(np.any(target[chosen], axis=0)),
            "source_share": share(np.any(source, axis=0)),
            "view_shares": [share(target[c]) for c in chosen],
            "contacts": int(target.shape[1]), "cameras": [cameras[c] for c in chosen]}
    info["share"] = info["target_share"] or 0.0
    return [VIEW_DIRECTIONS[c] for c in chosen], info


# ---- drawing -----------------------------------------------------------------------------------
def error_colour(error_mm) -> np.ndarray:
    """(N,) mm -> (N, 3) uint8: green at 0, yellow at ERROR_SCALE_MM / 2, red at ERROR_SCALE_MM and beyond."""
    t = np.clip(np.nan_to_num(np.asarray(error_mm, dtype=np.float64), nan=ERROR_SCALE_MM) / ERROR_SCALE_MM, 0, 1)
    stops = np.array([[40, 170, 70], [240, 200, 40], [215, 40, 30]], dtype=np.float64)
    low = np.clip((t * 2).astype(int), 0, 1)
    s = t * 2 - low
    return np.rint(stops[low] + (stops[low + 1] - stops[low]) * s[:, None]).astype(np.uint8)


def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: the fixed bitmap font
        return ImageFont.load_default()


def _ghost(scene: PictureScene, f: int, camera: Camera, size: int, supersample: int):
    """The translucent object of frame ``f``: (image, depth) at the supersampled resolution, drawn
    once per frame and view for both sides."""
    k = max(int(supersample), 1)
    obj = (scene.object_at(f), scene.object_faces, OBJECT_BLUE)
    return render_meshes([obj], camera, (size * k, size * k), return_depth=True)


def _tile(opaque, ghost, camera: Camera, size: int, supersample: int):
    """One view: the opaque meshes with the ghost (:func:`_ghost`) blended over where it is nearer.
    Returns (H, W, 3) uint8 and the opaque depth (H*k, W*k) at the supersampled resolution."""
    k = max(int(supersample), 1)
    big = (size * k, size * k)
    image, depth = render_meshes(opaque, camera, big, return_depth=True)
    over, ghost_depth = ghost
    image = image.astype(np.float64)
    front = ghost_depth < depth
    image[front] = (1.0 - GHOST_ALPHA) * image[front] + GHOST_ALPHA * over[front]
    if k > 1:
        image = image.reshape(size, k, size, k, 3).mean(axis=(1, 3))
    return np.clip(np.rint(image), 0, 255).astype(np.uint8), depth


def _render_side(layers: dict, ghost, side: str, camera: Camera, size: int, supersample: int, dot: int):
    """A PIL image of one side of a frame (``layers``: :func:`_frame_layers` of that frame,
    ``ghost``: its object, :func:`_ghost`) with its visible contacts drawn; (image, errors (N,) mm
    of the target's contacts or None)."""
    from PIL import Image, ImageDraw

    if side not in layers:
        tile = Image.new("RGB", (size, size), (240, 240, 240))
        ImageDraw.Draw(tile).text((8, size // 2 - 8), "source hand not stored", fill=(90, 90, 90), font=_font(12))
        return tile, None
    opaque, points, goals = layers[side]
    pixels, depth = _tile(opaque, ghost, camera, size, supersample)
    tile = Image.fromarray(pixels)
    errors = None
    if len(points):
        k = max(int(supersample), 1)
        visible = unoccluded(points, depth, camera)
        if side == "target":
            errors = 1000.0 * np.linalg.norm(points - goals, axis=1)
            colours = error_colour(errors)
        else:
            colours = np.tile(np.array(SOURCE_DOT, dtype=np.uint8), (len(points), 1))
        xy = camera.project(points, (size * k, size * k)) / k
        draw = ImageDraw.Draw(tile)
        for (x, y), c in zip(xy[visible], colours[visible]):
            # an outline only where the dot is big enough to keep its colour inside it
            draw.ellipse([x - dot, y - dot, x + dot, y + dot], fill=tuple(int(v) for v in c),
                         outline=(30, 30, 30) if dot >= 4 else None)
    return tile, errors


def _framing_points(scene: PictureScene, frames) -> np.ndarray:
    """(N, 3): the object and both hands at ``frames``, what a camera must keep in view."""
    pts = [scene.object_at(int(f)) for f in frames] + [scene.target_vertices(int(f)) for f in frames]
    pts += [s for s in (scene.source_at(int(f)) for f in frames) if s is not None]
    return np.concatenate(pts)


def write_contact_sheet(scene: PictureScene, path, frames, directions, *, tile: int = 240,
                        supersample: int = 2) -> Path:
    """contact_sheet.png: one row per frame in ``frames`` (frame number, time, the target's median
    contact error), the source and target side by side seen along each of ``directions``, a
    colour key."""
    from PIL import Image, ImageDraw

    framing = _framing_points(scene, frames)
    cameras = [frame_camera(framing, view=d, size=(tile, tile)) for d in directions]
    table = scene.table_mesh(framing)
    label_w, head_h, col_h, foot_h = 120, 34, 22, 46
    width = label_w + 2 * tile * len(cameras)
    sheet = Image.new("RGB", (width, head_h + col_h + tile * len(frames) + foot_h), BACKGROUND)
    draw = ImageDraw.Draw(sheet)
    draw.text((8, 8), scene.title, fill=(0, 0, 0), font=_font(15))
    for v in range(len(cameras)):
        for i, label in enumerate((scene.source_label, scene.target_label)):
            prefix = f"view {v + 1}: " if len(cameras) > 1 else ""
            draw.text((label_w + (2 * v + i) * tile + 6, head_h + 3), prefix + label, fill=(40, 40, 40), font=_font(13))
    for r, f in enumerate(frames):
        top = head_h + col_h + r * tile
        errors = None
        layers = _frame_layers(scene, int(f), table)
        for v, camera in enumerate(cameras):
            ghost = _ghost(scene, int(f), camera, tile, supersample)
            for i, side in enumerate(("source", "target")):
                image, e = _render_side(layers, ghost, side, camera, tile, supersample, dot=4)
                sheet.paste(image, (label_w + (2 * v + i) * tile, top))
                errors = e if e is not None else errors
        lines = [f"frame {int(f)}", f"{f / scene.fps:.2f} s"]
        lines.append(f"contact error\nmedian {np.median(errors):.1f} mm" if errors is not None and len(errors)
                     else "no contacts")
        draw.multiline_text((8, top + 8), "\n".join(lines), fill=(0, 0, 0), font=_font(13), spacing=4)
        draw.line([(0, top), (width, top)], fill=(200, 200, 200))
    bottom = head_h + col_h + tile * len(frames)
    for c in range(1, 2 * len(cameras)):
        x = label_w + c * tile
        draw.line([(x, head_h + col_h), (x, bottom)], fill=(120, 120, 120) if c % 2 == 0 else (200, 200, 200),
                  width=3 if c % 2 == 0 else 1)
    _draw_key(draw, 8, bottom + 8, width - 16)
    return _save_png(sheet, path)


def _draw_key(draw, x: int, y: int, width: int) -> None:
    bar_w = min(240, width // 2)
    ramp = error_colour(np.linspace(0, ERROR_SCALE_MM, bar_w))
    for i, c in enumerate(ramp):
        draw.line([(x + i, y), (x + i, y + 10)], fill=tuple(int(v) for v in c))
    font = _font(11)
    draw.text((x, y + 13), "0", fill=(0, 0, 0), font=font)
    draw.text((x + bar_w - 40, y + 13), f">= {ERROR_SCALE_MM:g} mm", fill=(0, 0, 0), font=font)
    draw.text((x + bar_w + 12, y - 1), "target contact: distance to its object point\n"
              "white: where the source touches; object translucent", fill=(40, 40, 40), font=font, spacing=2)


def write_preview(scene: PictureScene, path, frames, directions, *, tile: int = 180) -> Path:
    """preview.gif: source and target side by side over ``frames``, one row per view direction,
    looping, in real time (each picture lasts the time to the next frame shown)."""
    import imageio.v3 as iio
    from PIL import Image, ImageDraw

    frames = [int(f) for f in frames]
    framing = _framing_points(scene, frames)
    cameras = [frame_camera(framing, view=d, size=(tile, tile)) for d in directions]
    table = scene.table_mesh(framing)
    band = 20
    pictures = []
    for f in frames:
        canvas = Image.new("RGB", (2 * tile, band + tile * len(cameras)), BACKGROUND)
        layers = _frame_layers(scene, f, table)
        for v, camera in enumerate(cameras):
            ghost = _ghost(scene, f, camera, tile, 1)
            for i, side in enumerate(("source", "target")):
                image, _ = _render_side(layers, ghost, side, camera, tile, 1, dot=3)
                canvas.paste(image, (i * tile, band + v * tile))
        draw = ImageDraw.Draw(canvas)
        draw.text((6, 3), f"source   frame {f}  {f / scene.fps:.2f} s", fill=(0, 0, 0), font=_font(12))
        draw.text((tile + 6, 3), "target (delivered curve)", fill=(0, 0, 0), font=_font(12))
        draw.line([(tile, band), (tile, band + tile * len(cameras))], fill=(200, 200, 200))
        for v in range(1, len(cameras)):
            draw.line([(0, band + v * tile), (2 * tile, band + v * tile)], fill=(120, 120, 120), width=2)
        pictures.append(np.asarray(canvas))
    step = frames[1] - frames[0] if len(frames) > 1 else 1
    duration_ms = max(20, int(round(1000.0 * step / scene.fps)))
    path = Path(path)
    with atomic_path(path, suffix=".gif.tmp") as tmp:
        iio.imwrite(tmp, np.stack(pictures), extension=".gif", duration=duration_ms, loop=0)
    return path


def _save_png(image, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path, suffix=".png.tmp") as tmp:
        image.save(tmp, format="PNG")
    return path


def write_pictures(scene: PictureScene, out_dir) -> dict:
    """contact_sheet.png, preview.gif and pictures.json (frames, the chosen view and the share of
    contacts it shows unoccluded) into ``out_dir``; returns {name: path}."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sheet_frames, preview_frames = picture_frames(scene.n_frames, scene.fps, scene.contact_count)
    directions, seen = choose_views(scene, sheet_frames)
    paths = {"contact_sheet.png": write_contact_sheet(scene, out / "contact_sheet.png", sheet_frames, directions),
             "preview.gif": write_preview(scene, out / "preview.gif", preview_frames, directions)}
    doc = {"sheet_frames": sheet_frames.tolist(), "preview_frames": preview_frames.tolist(),
           "preview_frame_seconds": float((preview_frames[1] - preview_frames[0]) / scene.fps)
           if len(preview_frames) > 1 else None,
           "views": [{"direction": [round(float(v), 6) for v in d], "unoccluded_share": share,
                      "camera": {"eye": cam.eye.tolist(), "target": cam.target.tolist(), "up": cam.up.tolist(),
                                 "fov_deg": cam.fov}}
                     for d, share, cam in zip(directions, seen["view_shares"], seen["cameras"])],
           "contacts_unoccluded_share": seen["target_share"], "source_contacts_unoccluded_share": seen["source_share"],
           "contacts_in_sheet": seen["contacts"],
           "visible_goal": VISIBLE_GOAL, "visibility_tolerance_m": VISIBILITY_TOLERANCE_M,
           "object": "translucent (not an occluder)"}
    paths["pictures.json"] = out / "pictures.json"
    with atomic_path(paths["pictures.json"], suffix=".json.tmp") as tmp:
        tmp.write_text(json.dumps(doc, indent=1), encoding="utf-8")
    return paths


def result_scene(rig, q, fps: float, *, object_vertices, object_faces, object_poses, contacts=None,
                 contact_count=None, source_hand=None, table_pose=None, table_half_extents=None,
                 title: str = "", source_name: str = "source") -> PictureScene:
    """A :class:`PictureScene` of a retarget: ``rig`` posed by ``q`` (T, D) (the delivered curve
    sampled at the frames); ``contacts`` a ContactTargets-like (``frame_offsets``, ``target_faces``,
    ``target_barycentric``, ``surface_points(f)``) or None; ``source_hand`` (frames (K,), vertices
    (K, V, 3), faces (F, 3)) or None."""
    kin = rig.kinematics()
    q = np.asarray(q, dtype=np.float64)

    def target_vertices(f):
        return kin.skin(q[f])

    def target_contacts(f):
        if contacts is None:
            return np.zeros((0, 3)), np.zeros((0, 3))
        sl = slice(int(contacts.frame_offsets[f]), int(contacts.frame_offsets[f + 1]))
        if sl.stop <= sl.start:
            return np.zeros((0, 3)), np.zeros((0, 3))
        points = SurfacePoints(contacts.target_faces[sl], contacts.target_barycentric[sl])
        return kin.points(kin.pose(q[f]), kin.bind(points)), np.asarray(contacts.surface_points(f), dtype=np.float64)

    frames, verts, faces = (None, None, None) if source_hand is None else source_hand
    return PictureScene(
        n_frames=len(q), fps=float(fps), target_vertices=target_vertices, target_faces=rig.surface.faces,
        target_contacts=target_contacts, object_vertices=object_vertices, object_faces=object_faces,
        object_poses=object_poses, contact_count=contact_count, source_frames=frames, source_vertices=verts,
        source_faces=faces, table_pose=table_pose, table_half_extents=table_half_extents, title=title,
        source_label=f"source: {source_name}", target_label=f"target: {rig.name} (delivered)")
