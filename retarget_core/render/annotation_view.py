"""A picture of proposed annotations (issue 17 item 3): both hands side by side, source left and
target right, each at rest seen from its palmar side, with the axial curves and the virtual
markers drawn on it, so that a user checks a proposal at a glance.

Each panel's camera is built from the hand model's palm frame (looking along -palmar at the
palm, up = the hand's forward direction, orthographic, framed on the hand's own vertices), so
any hand in any world placement is shown the same way. A small inset shows the back of the hand
(markers on the dorsal side appear there). Source curves are the real geodesics the transfer
traces (:func:`retarget_core.transfer.axial_curves.build_source_curve`); target curves are
rebuilt as the transfer does (:func:`~retarget_core.transfer.axial_curves.reconstruct_curve`,
lambda_a times the source length), with the start point and an arrow to the direction point;
a curve that cannot be traced is drawn as a dashed straight line. Markers are black dots with
their names (a target marker's area vertices as small grey dots).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from .raster import SKIN, Camera, _rasterise, render_meshes

log = logging.getLogger(__name__)

BACKGROUND = (255, 255, 255)
MARKER = (15, 15, 15)
AREA = (95, 95, 95)
NON_HAND = (205, 205, 205)
CURVE_COLOURS = [
    (31, 119, 180), (214, 39, 40), (44, 160, 44), (148, 103, 189), (255, 127, 14),
    (23, 190, 207), (227, 119, 194), (140, 86, 75), (188, 189, 34), (127, 127, 127),
]
DISCARDED = (150, 150, 150)
TITLE_HEIGHT = 76
MARKER_RADIUS = 4
VISIBILITY_TOLERANCE = 0.003  # m: a point this far behind the visible surface is hidden


@dataclass
class PanelView:
    """Where one hand is drawn: its palmar-view camera, the view's top-left corner in the
    picture and size (px), the same for the back view, and the picture pixel of every marker
    dot drawn in each (a marker hidden from a view has no entry in its dict)."""

    side: str
    rig_name: str
    camera: Camera
    origin: tuple[int, int]
    size: tuple[int, int]
    back_camera: Camera
    back_origin: tuple[int, int]
    back_size: tuple[int, int]
    markers: dict[str, tuple[float, float]] = field(default_factory=dict)
    back_markers: dict[str, tuple[float, float]] = field(default_factory=dict)

    def project(self, points, *, back: bool = False) -> np.ndarray:
        """(N, 3) world points -> (N, 2) picture pixel coordinates in the palmar (or back) view."""
        camera, size, origin = ((self.back_camera, self.back_size, self.back_origin) if back
                                else (self.camera, self.size, self.origin))
        return camera.project(np.asarray(points, float).reshape(-1, 3), size) + np.asarray(origin, float)


@dataclass
class _View:
    camera: Camera
    origin: tuple[int, int]
    size: tuple[int, int]
    zbuf: np.ndarray | None = None
    markers: dict | None = None

    def project(self, points) -> np.ndarray:
        return self.camera.project(np.asarray(points, float).reshape(-1, 3), self.size) + np.asarray(self.origin, float)

    def visible(self, points) -> np.ndarray:
        return _visible(self.camera, self.zbuf, points)

    def behind(self, points) -> np.ndarray:
        return _behind(self.camera, self.zbuf, points)


@dataclass
class ProposalPicture:
    """What :func:`draw_proposal` wrote: the PNG path, its size and the two panels."""

    path: Path
    size: tuple[int, int]
    panels: list[PanelView]


# ---- geometry ------------------------------------------------------------------------------------
def palm_camera(model, points, size, *, margin: float = 0.06, back: bool = False) -> Camera:
    """Orthographic camera looking at the palm of ``model`` (along -palmar; ``back``: at the back,
    along +palmar), up = the hand's forward direction, framing ``points`` (N, 3) in ``size``."""
    frame = model.palm_frame()
    forward, dorsal = frame[:3, 1], frame[:3, 2]  # the palm frame: lateral, forward, dorsal axes
    look = dorsal if not back else -dorsal  # from the eye to the hand
    right = np.cross(look, forward)
    pts = np.asarray(points, float).reshape(-1, 3)
    rel = pts - frame[:3, 3]
    x, y, z = rel @ right, rel @ forward, rel @ look
    centre = frame[:3, 3] + right * 0.5 * (x.min() + x.max()) + forward * 0.5 * (y.min() + y.max())
    aspect = size[0] / size[1]
    span = max(float(y.max() - y.min()), float(x.max() - x.min()) / aspect, 1e-6) * (1.0 + 2.0 * margin)
    depth = float(np.abs(z).max()) + 0.05 * span + 1e-3
    return Camera(eye=centre - look * depth, target=centre, up=forward, projection="orthographic",
                  ortho_height=span)


def _depth_buffer(camera: Camera, vertices, faces, size) -> np.ndarray:
    """(H, W) distance along the view of the nearest surface per pixel (inf: background)."""
    view = camera.to_view(vertices[faces].reshape(-1, 3)).reshape(-1, 3, 3)
    scr = camera.view_to_pixels(view.reshape(-1, 3), size).reshape(-1, 3, 2)
    zbuf, _, _, _ = _rasterise(scr, view[..., 2], int(size[0]), int(size[1]))
    return zbuf


def _visible(camera: Camera, zbuf: np.ndarray, points) -> np.ndarray:
    """(N,) whether each world point is in front of (or on) the surface seen at its pixel."""
    return _behind(camera, zbuf, points) <= VISIBILITY_TOLERANCE


def _behind(camera: Camera, zbuf: np.ndarray, points) -> np.ndarray:
    """(N,) how far (m) each world point lies behind the surface seen around its pixel (<= 0:
    in front; inf: outside the view)."""
    pts = np.asarray(points, float).reshape(-1, 3)
    h, w = zbuf.shape
    xy = camera.project(pts, (w, h))
    depth = camera.to_view(pts)[:, 2]
    ix = np.clip(np.floor(xy[:, 0]).astype(int), 0, w - 1)
    iy = np.clip(np.floor(xy[:, 1]).astype(int), 0, h - 1)
    inside = (xy[:, 0] >= 0) & (xy[:, 0] < w) & (xy[:, 1] >= 0) & (xy[:, 1] < h)
    near = np.full(len(pts), np.inf)
    for dx in (-1, 0, 1):  # the nearest surface around the pixel: a point on a silhouette stays visible
        for dy in (-1, 0, 1):
            near = np.minimum(near, zbuf[np.clip(iy + dy, 0, h - 1), np.clip(ix + dx, 0, w - 1)])
    return np.where(inside, depth - np.minimum(near, depth), np.inf)


def _positions(points, rig) -> np.ndarray:
    from ..transfer.annotations import resolve_points

    surf = rig.surface
    sp = resolve_points(list(points), surf.faces, surf.n_vertices, what="point")
    return sp.positions(surf.vertices, surf.faces)


def _surface_points(point, rig, many: bool = False):
    """SurfacePoints of one annotation point (or, ``many``, of a list of them) on ``rig``."""
    from ..transfer.annotations import resolve_points

    return resolve_points(point if many else [point], rig.surface.faces, rig.surface.n_vertices, what="point")


@dataclass
class _CurveDrawing:
    name: str
    colour: tuple
    points: np.ndarray  # (K, 3) polyline
    traced: bool
    label: str
    start: np.ndarray | None = None  # target: start point and direction point
    toward: np.ndarray | None = None
    discarded: bool = False


def _geometry(rig, name):
    from ..transfer.geodesics import SurfaceGeometry

    try:
        return SurfaceGeometry(rig.surface.vertices, rig.surface.faces, name=name)
    except InputError as err:  # not a manifold: curves are drawn as straight lines
        log.warning("%s: curves drawn straight (%s)", name, err)
        return None


def _curves(annotations, source_rig, target_rig):
    """(source drawings, target drawings) of every axial curve."""
    from ..transfer.axial_curves import build_source_curve, reconstruct_curve

    sg, tg = _geometry(source_rig, "source surface"), _geometry(target_rig, "target surface")
    spacing = annotations.landmark_spacing
    src_out, tgt_out = [], []
    for i, c in enumerate(annotations.curves):
        colour = CURVE_COLOURS[i % len(CURVE_COLOURS)] if not c.discard else DISCARDED
        refs = c.source_points if c.is_polyline else (c.source_start, c.source_end)
        anchors = _positions(refs, source_rig)
        source_curve, traced = None, False
        if sg is not None:
            try:
                if c.is_polyline:
                    from ..transfer.annotations import resolve_points

                    pts = resolve_points(c.source_points, source_rig.surface.faces, source_rig.surface.n_vertices,
                                         what="point")
                    source_curve = build_source_curve(sg, c.name, points=pts, spacing=spacing)
                else:
                    source_curve = build_source_curve(sg, c.name, start=_surface_points(c.source_start, source_rig),
                                                      end=_surface_points(c.source_end, source_rig), spacing=spacing)
                traced = True
            except InputError as err:
                log.warning("axial curve %r: source curve not traced (%s)", c.name, err)
        src_pts = source_curve.positions if source_curve is not None else anchors
        length = float(np.linalg.norm(np.diff(src_pts, axis=0), axis=1).sum())
        if c.discard:
            label = f"{c.name} (discarded)"
        else:
            label = f"{c.name}  {1000 * length:.0f} mm"
        src_out.append(_CurveDrawing(c.name, colour, src_pts, traced, label, discarded=c.discard))
        if c.discard:
            continue
        t = c.target
        start, toward = _positions([t.start, t.direction], target_rig)
        tgt_pts, t_traced = np.vstack([start, toward]), False
        if tg is not None and source_curve is not None:
            try:
                through = None if t.through is None else _surface_points(list(t.through), target_rig, many=True)
                rebuilt = reconstruct_curve(tg, source_curve, _surface_points(t.start, target_rig),
                                            _surface_points(t.direction, target_rig), t.lambda_a, through=through)
                tgt_pts, t_traced = rebuilt.positions, True
            except InputError as err:
                log.warning("axial curve %r: target curve not traced (%s)", c.name, err)
        ls = t.lambda_s.uniform
        ls_text = f"{ls:g}" if ls is not None else "piecewise " + "/".join(f"{v:g}" for v in t.lambda_s.knot_values)
        label = f"{c.name}  \u03bba {t.lambda_a:g}  \u03bbs {ls_text}" + ("" if t_traced else " (not traced)")
        tgt_out.append(_CurveDrawing(c.name, colour, tgt_pts, t_traced, label, start=start, toward=toward))
    return src_out, tgt_out


# ---- drawing -------------------------------------------------------------------------------------
def _font(size: int, bold: bool = False):
    from PIL import ImageFont

    names = ["DejaVuSans-Bold.ttf", "DejaVuSans.ttf"] if bold else ["DejaVuSans.ttf"]
    for name in names:
        for folder in ("", "/usr/share/fonts/truetype/dejavu/"):
            try:
                return ImageFont.truetype(folder + name, size)
            except OSError:
                continue
    return ImageFont.load_default(size=size)


class _Labels:
    """Places text boxes near anchors without overlapping each other, dots or the view's edges."""

    def __init__(self, draw, bounds):
        self.draw = draw
        self.bounds = bounds  # (x0, y0, x1, y1)
        self.taken: list[tuple[float, float, float, float]] = []

    def block(self, x, y, r):
        self.taken.append((x - r, y - r, x + r, y + r))

    def _cost(self, box):
        x0, y0, x1, y1 = self.bounds
        cost = 0.0
        if box[0] < x0 or box[1] < y0 or box[2] > x1 or box[3] > y1:
            cost += 1e6
        for t in self.taken:
            w = min(box[2], t[2]) - max(box[0], t[0])
            h = min(box[3], t[3]) - max(box[1], t[1])
            if w > 0 and h > 0:
                cost += w * h
        return cost

    def place(self, text, anchors, font, fill, *, gap=6, leader=None):
        """Put ``text`` at the best of the offsets around the first anchors; draw it on a
        translucent white box. Returns the box."""
        l, t, r, b = self.draw.textbbox((0, 0), text, font=font)
        w, h = r - l + 6, b - t + 4
        best = None
        for k, (ax, ay) in enumerate(anchors):
            for dx, dy in ((gap, -h / 2), (-gap - w, -h / 2), (-w / 2, -gap - h), (-w / 2, gap),
                           (gap, -gap - h), (-gap - w, -gap - h), (gap, gap), (-gap - w, gap),
                           (2.5 * gap, -h / 2), (-2.5 * gap - w, -h / 2), (-w / 2, -3 * gap - h), (-w / 2, 3 * gap)):
                box = (ax + dx, ay + dy, ax + dx + w, ay + dy + h)
                cost = self._cost(box) + 0.5 * k + 0.01 * (abs(dx) + abs(dy))
                if best is None or cost < best[0]:
                    best = (cost, box, (ax, ay))
            if best[0] < 1.0:
                break
        _, box, (ax, ay) = best
        if leader is not None:
            cx = min(max(ax, box[0]), box[2])
            cy = min(max(ay, box[1]), box[3])
            if np.hypot(cx - ax, cy - ay) > gap + 2:
                self.draw.line([(ax, ay), (cx, cy)], fill=leader, width=1)
        self.draw.rectangle(box, fill=(255, 255, 255, 215))
        self.draw.text((box[0] + 3 - l, box[1] + 2 - t), text, font=font, fill=fill)
        self.taken.append(box)
        return box


def _dark(colour, f=0.65):
    return tuple(int(c * f) for c in colour)


def _runs(mask):
    """(start, stop) index ranges of consecutive True in mask."""
    out, start = [], None
    for i, m in enumerate(mask):
        if m and start is None:
            start = i
        if not m and start is not None:
            out.append((start, i))
            start = None
    if start is not None:
        out.append((start, len(mask)))
    return out


def _dashed(draw, xy, fill, width, dash=8.0):
    for a, b in zip(xy[:-1], xy[1:]):
        seg = np.linalg.norm(b - a)
        n = max(int(seg // dash), 1)
        for k in range(0, n, 2):
            p, q = a + (b - a) * k / n, a + (b - a) * min(k + 1, n) / n
            draw.line([tuple(p), tuple(q)], fill=fill, width=width)


def _arrow(draw, a, b, fill, width=2, head=11.0):
    a, b = np.asarray(a, float), np.asarray(b, float)
    d = b - a
    n = np.linalg.norm(d)
    if n < 1e-6:
        return
    d /= n
    draw.line([tuple(a), tuple(b)], fill=fill, width=width)
    side = np.array([-d[1], d[0]])
    p1, p2 = b - d * head + side * head * 0.45, b - d * head - side * head * 0.45
    draw.polygon([tuple(b), tuple(p1), tuple(p2)], fill=fill)


def _view_markers(draw, labels, view, markers, side, font, radius, forced=()):
    """Dots (and a target's area vertices) of the markers visible in ``view`` and of those named
    in ``forced`` (seen in no view, e.g. at the apex of a fingertip: drawn where they are least
    hidden), then their names; records each dot's picture pixel in ``view.markers``."""
    shown = []
    for name, centre, area in markers:
        if not view.visible(centre[None])[0] and name not in forced:
            continue
        xy = view.project(centre[None])[0]
        view.markers[name] = (float(xy[0]), float(xy[1]))
        shown.append((name, xy, area))
        labels.block(xy[0], xy[1], radius + 2)
    for name, xy, area in shown:
        if area is not None and len(area):
            for p in view.project(area[view.visible(area)]):
                draw.ellipse([p[0] - 1.5, p[1] - 1.5, p[0] + 1.5, p[1] + 1.5], fill=AREA)
    for name, xy, area in shown:
        labels.place(name, [xy], font, (25, 25, 25), gap=radius + 3, leader=(110, 110, 110))
    for name, xy, area in shown:  # last: no label or leader line covers a dot
        r = radius
        draw.ellipse([xy[0] - r - 1, xy[1] - r - 1, xy[0] + r + 1, xy[1] + r + 1], fill=(255, 255, 255))
        draw.ellipse([xy[0] - r, xy[1] - r, xy[0] + r, xy[1] + r], fill=MARKER)


def _view_curves(draw, labels, view, drawings, font, *, width=4, with_labels=True):
    """Each curve as a polyline (thick where visible in ``view``, thin where hidden; dashed when
    discarded or not traced), a target's start circle and arrow to its direction point, and the
    curve's label near its end."""
    for d in drawings:
        xy = view.project(d.points)
        vis = view.visible(d.points)
        if d.discarded or not d.traced:
            for a, b in _runs(vis):
                if b - a >= 2:
                    _dashed(draw, xy[a:b], fill=d.colour, width=max(width - 1, 1))
            continue
        draw.line([tuple(p) for p in xy], fill=d.colour + (110,), width=1)
        for a, b in _runs(vis):
            if b - a >= 2:
                draw.line([tuple(p) for p in xy[a:b]], fill=d.colour, width=width, joint="curve")
    for d in drawings:
        if d.start is None:
            s = view.project(d.points[:1])[0]
            if view.visible(d.points[:1])[0]:
                draw.ellipse([s[0] - 4, s[1] - 4, s[0] + 4, s[1] + 4], fill=d.colour)
            continue
        s, t = view.project(np.vstack([d.start, d.toward]))
        if view.visible(d.start[None])[0]:
            _arrow(draw, s, t, fill=_dark(d.colour, 0.5), width=1)
            r = 6
            draw.ellipse([s[0] - r, s[1] - r, s[0] + r, s[1] + r], outline=_dark(d.colour, 0.5), width=2)
            labels.block(s[0], s[1], r)
    if not with_labels:
        return
    for d in drawings:  # after every line: near the curve's end, else along it
        vis = view.visible(d.points)
        if not vis.any():
            continue
        xy = view.project(d.points)
        along = xy[-1] - xy[0]
        along = along / max(np.linalg.norm(along), 1e-9)
        anchors = [xy[-1] + along * 10] if vis[-1] else []
        anchors += [xy[i] for i in (int(k * (len(xy) - 1)) for k in (0.75, 0.5, 0.25, 0.0)) if vis[i]]
        labels.place(d.label, anchors or [xy[-1]], font, _dark(d.colour, 0.8), gap=7, leader=d.colour)


def _panel(image, draw, side, rig, model, drawings, markers, origin, panel_size, title_lines, fonts):
    """Draw one hand's panel at ``origin`` (x, y) of ``panel_size``: the title and legend on top,
    the palm view left and the back view right. Returns its PanelView."""
    from PIL import Image

    px, py = origin
    pw, ph = panel_size
    verts, faces = rig.surface.vertices, rig.surface.faces
    hand = np.asarray(model.hand_vertices, bool)
    colours = np.tile(np.asarray(NON_HAND, float) / 255.0, (len(verts), 1))
    colours[hand] = np.asarray(SKIN, float) / 255.0
    frame_pts = verts[hand] if hand.any() else verts
    mesh = [(verts, faces, colours)]

    title_h = int(TITLE_HEIGHT * ph / 800)
    view_h = ph - title_h
    palm_w = int(round(pw * 0.58))
    back_w = pw - palm_w
    palm = _View(palm_camera(model, frame_pts, (palm_w, view_h)), (px, py + title_h), (palm_w, view_h))
    back = _View(palm_camera(model, frame_pts, (back_w, view_h), back=True), (px + palm_w, py + title_h),
                 (back_w, view_h))
    for v in (palm, back):
        image.paste(Image.fromarray(render_meshes(mesh, v.camera, v.size, supersample=2)), v.origin)
        v.zbuf = _depth_buffer(v.camera, verts, faces, v.size)
    draw.line([(back.origin[0], back.origin[1] + 8), (back.origin[0], py + ph - 8)], fill=(215, 215, 215), width=1)
    for v, text in ((palm, "palm side"), (back, "back")):
        draw.text((v.origin[0] + 8, v.origin[1] + 4), text, font=fonts["label"], fill=(90, 90, 90))

    pv = PanelView(side, rig.name, palm.camera, palm.origin, palm.size, back.camera, back.origin, back.size)
    palm.markers, back.markers = pv.markers, pv.back_markers
    # a marker seen from neither side goes to the view where it is least hidden
    forced = {id(palm): set(), id(back): set()}
    for name, centre, area in markers:
        depth = [float(v.behind(centre[None])[0]) for v in (palm, back)]
        if min(depth) > VISIBILITY_TOLERANCE:
            forced[id(palm if depth[0] <= depth[1] else back)].add(name)
    for v, curve_width, with_labels in ((palm, 4, True), (back, 2, False)):
        labels = _Labels(draw, (v.origin[0] + 2, v.origin[1] + 24, v.origin[0] + v.size[0] - 2,
                                v.origin[1] + v.size[1] - 2))
        _view_curves(draw, labels, v, drawings, fonts["label"], width=curve_width, with_labels=with_labels)
        _view_markers(draw, labels, v, markers, side, fonts["small"], MARKER_RADIUS, forced[id(v)])

    # scale bar, title (left) and curve legend (right, two columns)
    bar = 0.05 * palm.size[1] / palm.camera.ortho_height
    bx, by = palm.origin[0] + 14, palm.origin[1] + view_h - 16
    draw.line([(bx, by), (bx + bar, by)], fill=(40, 40, 40), width=3)
    draw.text((bx, by - 18), "5 cm", font=fonts["small"], fill=(40, 40, 40))
    ty = py + 6
    for k, (text, colour) in enumerate(title_lines):
        draw.text((px + 10, ty), text, font=fonts["title"] if k == 0 else fonts["label"], fill=colour)
        ty += 26 if k == 0 else 20
    rows = max((len(drawings) + 1) // 2, 1)
    title_w = max(draw.textbbox((0, 0), text, font=fonts["title"] if k == 0 else fonts["label"])[2]
                  for k, (text, _) in enumerate(title_lines))
    lx0 = px + 10 + title_w + 24
    col_w = max((px + pw - 6 - lx0) // 2, 1)
    line_h = max(min((title_h - 10) // rows, 17), 12)
    for i, d in enumerate(drawings):
        lx, ly = lx0 + (i // rows) * col_w, py + 6 + (i % rows) * line_h
        draw.line([(lx, ly + 8), (lx + 16, ly + 8)], fill=d.colour, width=4)
        draw.text((lx + 21, ly), d.label, font=fonts["small"], fill=(30, 30, 30))
    return pv


def draw_proposal(proposal, path, *, source_rig=None, target_rig=None, size=(1600, 800)) -> ProposalPicture:
    """Write a PNG of ``size`` (W, H) showing proposed annotations on both hands: ``proposal``
    is a :class:`~retarget_core.transfer.propose.Proposal` (then ``source_rig`` and
    ``target_rig`` are the rigs it was proposed for) or a tuple ``(annotations, source_rig,
    target_rig, source_model, target_model)``. Returns what was drawn where."""
    from PIL import Image, ImageDraw

    if isinstance(proposal, tuple):
        if len(proposal) != 5:
            raise InputError("draw_proposal needs a Proposal or (annotations, source_rig, target_rig, "
                             "source_model, target_model)")
        annotations, source_rig, target_rig, sm, tm = proposal
        extra = [f.name for f in tm.fingers if sm.finger(f.name) is None]
    else:
        if source_rig is None or target_rig is None:
            raise InputError("draw_proposal(proposal, ...) needs source_rig and target_rig")
        annotations, sm, tm, extra = proposal.annotations, proposal.source_model, proposal.target_model, proposal.extra
    width, height = int(size[0]), int(size[1])
    if width < 400 or height < 300:
        raise InputError(f"the picture must be at least 400 x 300 pixels, got {width} x {height}", element="size")
    annotations.check_meshes(source_rig.surface.faces, source_rig.surface.n_vertices,
                             target_rig.surface.faces, target_rig.surface.n_vertices)

    src_curves, tgt_curves = _curves(annotations, source_rig, target_rig)
    src_markers, tgt_markers = [], []
    for m in annotations.markers:
        s = _positions(m.source, source_rig)
        t = _positions(m.target, target_rig)
        src_markers.append((m.name, s[0], s[1:] if len(s) > 1 else None))
        tgt_markers.append((m.name, t[0], t[1:] if len(t) > 1 else None))
    discarded = [c.name for c in annotations.curves if c.discard]

    image = Image.new("RGB", (width, height), BACKGROUND)
    draw = ImageDraw.Draw(image, "RGBA")
    scale = min(width / 1600, height / 800)
    fonts = {"title": _font(max(int(19 * scale), 11), bold=True), "label": _font(max(int(15 * scale), 10)),
             "small": _font(max(int(12 * scale), 9)), "tiny": _font(max(int(11 * scale), 8))}
    half = width // 2
    panels = []
    for side, rig, model, drawings, markers, origin, pw in (
            ("source", source_rig, sm, src_curves, src_markers, (0, 0), half),
            ("target", target_rig, tm, tgt_curves, tgt_markers, (half, 0), width - half)):
        title = [(f"{side}: {rig.name} \u2014 {model.handedness} hand", (0, 0, 0)),
                 (f"fingers: {', '.join(model.finger_names)}", (40, 40, 40))]
        notes = []
        if discarded:
            notes.append(f"discarded curves: {', '.join(discarded)}")
        if side == "target" and extra:
            notes.append(f"extra fingers (no contacts): {', '.join(extra)}")
        title.append(("; ".join(notes) if notes else "no curve discarded", (180, 30, 30) if notes else (40, 110, 40)))
        panels.append(_panel(image, draw, side, rig, model, drawings, markers, origin, (pw, height), title, fonts))
    draw.line([(half, 0), (half, height - 1)], fill=(170, 170, 170), width=1)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    image.save(path)
    return ProposalPicture(path, (width, height), panels)
