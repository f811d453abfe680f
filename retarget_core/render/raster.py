"""A small software renderer (numpy + Pillow only) for looking at results.

No OpenGL, no screen: triangles are rasterised with a z-buffer in vectorised numpy. Each
triangle's screen bounding box is expanded into candidate pixels (in chunks of bounded size),
an edge-function test keeps the covered pixel centres, and a scatter-min z-buffer resolves
visibility, so the result does not depend on drawing order. Shading is Lambert + ambient with
a headlight (a light at the camera, slightly above and to the left), two-sided (back faces are
lit as if they faced the viewer, so a mesh seen from inside still reads), with smooth normals
except across sharp creases, and optional thin outlines at silhouettes and depth jumps.

Conventions: world units are arbitrary (metres in this project); the image's row 0 is the top;
colours are RGB, either integers 0-255 or floats 0-1 (a float colour with any value > 1 is read
as 0-255).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import InputError
from ..mesh.geometry import face_normals, vertex_normals

BACKGROUND = (255, 255, 255)
SKIN = (226, 178, 146)
OBJECT_BLUE = (138, 156, 186)
CONTACT_RED = (220, 32, 32)
TABLE_WOOD = (222, 196, 150)

_VIEWS = {
    # view name: (direction from the target to the eye, camera up), world Z-up
    "front": ((0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
    "side": ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "top": ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0)),
    "three_quarter": ((0.7, -1.0, 0.75), (0.0, 0.0, 1.0)),
}

_CHUNK_FRAGMENTS = 1 << 21  # candidate pixels processed at once (bounds peak memory)


# ---- camera ------------------------------------------------------------------------------------
@dataclass
class Camera:
    """A look-at camera.

    ``projection`` is ``"perspective"`` (``fov``: vertical field of view in degrees) or
    ``"orthographic"`` (``ortho_height``: height of the visible region in world units; its width
    follows the image aspect ratio). ``near`` is the perspective near-plane distance."""

    eye: Sequence[float]
    target: Sequence[float]
    up: Sequence[float] = (0.0, 0.0, 1.0)
    projection: str = "perspective"
    fov: float = 30.0
    ortho_height: float = 1.0
    near: float = 1e-3

    def __post_init__(self):
        self.eye = np.asarray(self.eye, dtype=np.float64).reshape(3)
        self.target = np.asarray(self.target, dtype=np.float64).reshape(3)
        self.up = np.asarray(self.up, dtype=np.float64).reshape(3)
        if self.projection not in ("perspective", "orthographic"):
            raise InputError(f"must be 'perspective' or 'orthographic', got {self.projection!r}", element="projection")
        if not np.all(np.isfinite([*self.eye, *self.target, *self.up])):
            raise InputError("eye, target and up must be finite", element="camera")
        if np.linalg.norm(self.target - self.eye) < 1e-12:
            raise InputError("eye and target coincide", element="camera")
        if self.projection == "perspective" and not 0.0 < self.fov < 179.0:
            raise InputError(f"fov must be in (0, 179) degrees, got {self.fov}", element="fov")
        if self.projection == "orthographic" and not self.ortho_height > 0:
            raise InputError(f"ortho_height must be positive, got {self.ortho_height}", element="ortho_height")

    @property
    def orthographic(self) -> bool:
        return self.projection == "orthographic"

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(right, up, forward) orthonormal world vectors; forward points from eye to target."""
        forward = self.target - self.eye
        forward = forward / np.linalg.norm(forward)
        right = np.cross(forward, self.up)
        if np.linalg.norm(right) < 1e-9:  # up parallel to the view direction: pick any
            alt = np.array([0.0, 1.0, 0.0]) if abs(forward[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
            right = np.cross(forward, alt)
        right = right / np.linalg.norm(right)
        up = np.cross(right, forward)
        return right, up, forward

    def to_view(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) world points -> (N, 3) camera coordinates (x right, y up, z forward distance)."""
        right, up, forward = self.basis()
        rel = np.asarray(points, dtype=np.float64) - self.eye
        return np.stack([rel @ right, rel @ up, rel @ forward], axis=-1)

    def view_to_pixels(self, view: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """(N, 3) camera coordinates -> (N, 2) continuous pixel coordinates (x right, y down);
        pixel (i, j) covers [i, i+1) x [j, j+1) and its centre is (i + 0.5, j + 0.5)."""
        width, height = size
        if self.orthographic:
            half_h = 0.5 * self.ortho_height
            nx = view[:, 0] / (half_h * width / height)
            ny = view[:, 1] / half_h
        else:
            t = math.tan(math.radians(self.fov) / 2.0)
            z = np.maximum(view[:, 2], 1e-12)
            nx = view[:, 0] / (z * t * width / height)
            ny = view[:, 1] / (z * t)
        return np.stack([(nx + 1.0) * 0.5 * width, (1.0 - ny) * 0.5 * height], axis=-1)

    def project(self, points: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """(N, 3) world points -> (N, 2) pixel coordinates (see :meth:`view_to_pixels`)."""
        return self.view_to_pixels(self.to_view(points), size)


def frame_camera(
    points,
    view: str | Sequence[float] = "three_quarter",
    margin: float = 0.08,
    *,
    size: tuple[int, int] = (320, 320),
    projection: str = "perspective",
    fov: float = 30.0,
    up: Sequence[float] | None = None,
) -> Camera:
    """A camera looking at ``points`` (N, 3) from ``view`` so that they fill an image of ``size``
    with ``margin`` (a fraction of the framed extent) on each side. ``view`` is a name (``front`` =
    from -Y, ``side`` = from +X, ``top`` = from +Z, ``three_quarter`` = from front-right-above;
    world Z-up) or a direction (3,) from the points towards the eye; ``up`` (default: world +Z,
    +Y when looking along Z) overrides the camera's up."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) == 0:
        raise InputError("no finite points to frame", element="points")
    if isinstance(view, str):
        if view not in _VIEWS:
            raise InputError(f"unknown view {view!r} (choose from {', '.join(_VIEWS)})", element="view")
        direction, view_up = _VIEWS[view]
    else:
        direction = np.asarray(view, dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(direction)) and np.linalg.norm(direction) > 1e-12):
            raise InputError(f"a view direction must be a finite non-zero 3-vector, got {view!r}", element="view")
        along_z = abs(direction[2]) > 0.95 * np.linalg.norm(direction)
        view_up = (0.0, 1.0, 0.0) if along_z else (0.0, 0.0, 1.0)
    up = view_up if up is None else up
    direction = np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction)
    width, height = size
    aspect = width / height
    scale = 1.0 + 2.0 * max(float(margin), 0.0)

    lo, hi = pts.min(axis=0), pts.max(axis=0)
    centre = 0.5 * (lo + hi)
    diag = max(float(np.linalg.norm(hi - lo)), 1e-6)
    probe = Camera(eye=centre + direction * diag, target=centre, up=up, projection="orthographic")
    right, cam_up, forward = probe.basis()
    rel = pts - centre
    x, y = rel @ right, rel @ cam_up
    # re-centre the target on the middle of the points as seen along the view direction
    centre = centre + right * 0.5 * (x.min() + x.max()) + cam_up * 0.5 * (y.min() + y.max())
    rel = pts - centre
    x, y, z = rel @ right, rel @ cam_up, rel @ forward
    span = max(float(y.max() - y.min()), float(x.max() - x.min()) / aspect, 1e-6)

    if projection == "orthographic":
        distance = float(-z.min()) + diag + 1e-3  # any distance in front of every point
        return Camera(eye=centre - forward * distance, target=centre, up=cam_up,
                      projection="orthographic", ortho_height=span * scale)
    # perspective: the smallest distance that keeps every point inside the shrunken frustum
    tv = math.tan(math.radians(fov) / 2.0) / scale
    th = tv * aspect
    need = np.maximum(np.abs(x) / th, np.abs(y) / tv) - z
    distance = max(float(need.max()), float(-z.min()) + 1e-3 * diag, 1e-6)
    return Camera(eye=centre - forward * distance, target=centre, up=cam_up, projection="perspective", fov=fov,
                  near=max(1e-4 * distance, 1e-6))


# ---- rasteriser --------------------------------------------------------------------------------
def depth_buffer(meshes, camera: Camera, size: tuple[int, int] = (320, 320)) -> np.ndarray:
    """(H, W) distance along the view direction (world units) of the nearest surface of
    ``meshes`` (``(vertices (V, 3), faces (F, 3), ...)``) at each pixel centre, ``inf`` where none;
    ``size = (W, H)``. The same visibility as :func:`render_meshes` without shading."""
    width, height = int(size[0]), int(size[1])
    if width < 1 or height < 1:
        raise InputError(f"image size must be positive, got {size!r}", element="size")
    tris = []
    for mi, mesh in enumerate(meshes):
        verts = np.asarray(mesh[0], dtype=np.float64).reshape(-1, 3)
        faces = np.asarray(mesh[1]).reshape(-1, 3)
        if len(faces) == 0:
            continue
        if not np.issubdtype(faces.dtype, np.integer) or faces.min() < 0 or faces.max() >= len(verts):
            raise InputError(f"mesh {mi}: faces must be integer indices in [0, {len(verts)})", element="faces")
        corners = verts[faces.astype(np.int64)]
        tris.append(corners[np.all(np.isfinite(corners).reshape(len(faces), -1), axis=1)])
    if not tris:
        return np.full((height, width), np.inf)
    view = camera.to_view(np.concatenate(tris).reshape(-1, 3)).reshape(-1, 3, 3)
    if not camera.orthographic:
        view = _clip_near(view, camera.near)[0]
    if len(view) == 0:
        return np.full((height, width), np.inf)
    scr = camera.view_to_pixels(view.reshape(-1, 3), (width, height)).reshape(-1, 3, 2)
    key = view[..., 2] if camera.orthographic else -1.0 / view[..., 2]
    return _key_to_distance(_rasterise(scr, key, width, height)[0], camera)


def render_meshes(
    meshes,
    camera: Camera,
    size: tuple[int, int] = (320, 320),
    *,
    background=BACKGROUND,
    ambient: float = 0.35,
    diffuse: float = 0.65,
    smooth: bool = True,
    crease_deg: float = 40.0,
    outline: bool = True,
    supersample: int = 1,
    return_depth: bool = False,
):
    """Render ``meshes`` (a list of ``(vertices (V, 3), faces (F, 3), colour)``, where colour is one
    RGB triple or per-vertex colours (V, 3); a 2-tuple gets a neutral grey) seen by ``camera``.

    Returns an (H, W, 3) uint8 image, ``size = (W, H)``. ``smooth`` interpolates vertex normals
    except where a face bends more than ``crease_deg`` from its vertex normal (boxes stay flat);
    ``outline`` darkens silhouettes and depth jumps; ``supersample`` = k renders at k x k the
    resolution and averages down (anti-aliasing). ``return_depth``: return ``(image, depth)``, depth
    (H*k, W*k) the distance along the view direction of the visible surface (``inf`` where none), as
    :func:`depth_buffer`, at the supersampled resolution."""
    width, height = int(size[0]), int(size[1])
    if width < 1 or height < 1:
        raise InputError(f"image size must be positive, got {size!r}", element="size")
    k = max(int(supersample), 1)
    sw, sh = width * k, height * k
    bg = _as_rgb01(background).reshape(3)

    # gather every mesh into one triangle soup with per-corner normals and colours
    corner_pos, corner_nrm, corner_col, tri_mesh = [], [], [], []
    for mi, mesh in enumerate(meshes):
        verts = np.asarray(mesh[0], dtype=np.float64).reshape(-1, 3)
        faces = np.asarray(mesh[1]).reshape(-1, 3)
        if len(faces) == 0:
            continue
        if not np.issubdtype(faces.dtype, np.integer):
            raise InputError(f"mesh {mi}: faces must be integers", element="faces")
        faces = faces.astype(np.int64)
        if faces.min() < 0 or faces.max() >= len(verts):
            raise InputError(f"mesh {mi}: face index out of range [0, {len(verts)})", element="faces")
        colour = (0.7, 0.7, 0.7) if len(mesh) < 3 or mesh[2] is None else mesh[2]
        col = _as_rgb01(colour)
        if col.ndim == 1:
            col = np.broadcast_to(col, (len(verts), 3))
        elif col.shape != (len(verts), 3):
            raise InputError(f"mesh {mi}: per-vertex colours must have shape ({len(verts)}, 3), got {col.shape}",
                             element="colors")
        keep = np.all(np.isfinite(verts[faces]).reshape(len(faces), -1), axis=1)
        faces = faces[keep]
        fn, vn = face_normals(verts, faces), vertex_normals(verts, faces)
        if smooth:
            cn = vn[faces]  # (F, 3, 3) per-corner
            cos_crease = math.cos(math.radians(crease_deg))
            sharp = np.einsum("fcj,fj->fc", cn, fn) < cos_crease
            cn = np.where(sharp[..., None], fn[:, None, :], cn)
        else:
            cn = np.repeat(fn[:, None, :], 3, axis=1)
        corner_pos.append(verts[faces])
        corner_nrm.append(cn)
        corner_col.append(np.asarray(col, dtype=np.float64)[faces])
        tri_mesh.append(np.full(len(faces), mi, dtype=np.int32))

    image = np.broadcast_to(bg, (sh, sw, 3)).copy()
    if not corner_pos:
        return _finish(image, k, np.full((sh, sw), np.inf) if return_depth else None)
    pos = np.concatenate(corner_pos)  # (F, 3, 3) world corners
    nrm = np.concatenate(corner_nrm)
    col = np.concatenate(corner_col)
    mesh_of = np.concatenate(tri_mesh)

    view = camera.to_view(pos.reshape(-1, 3)).reshape(-1, 3, 3)
    # clip against the near plane (perspective only): new triangles remember, per corner, the
    # barycentric coordinates in their source triangle, so attributes are interpolated correctly
    if camera.orthographic:
        src = np.arange(len(view))
        bary_map = None
    else:
        view, src, bary_map = _clip_near(view, camera.near)
    if len(view) == 0:
        return _finish(image, k, np.full((sh, sw), np.inf) if return_depth else None)

    scr = camera.view_to_pixels(view.reshape(-1, 3), (sw, sh)).reshape(-1, 3, 2)
    depth = view[..., 2]  # distance along the view direction
    key = depth if camera.orthographic else -1.0 / depth  # affine in screen space; smaller = nearer
    zbuf, tri_buf, b1_buf, b2_buf = _rasterise(scr, key, sw, sh)

    hit = tri_buf >= 0
    if not hit.any():
        return _finish(image, k, _key_to_distance(zbuf, camera) if return_depth else None)
    pix = np.nonzero(hit.ravel())[0]
    t = tri_buf.ravel()[pix]
    b1 = b1_buf.ravel()[pix]
    b2 = b2_buf.ravel()[pix]
    bs = np.stack([1.0 - b1 - b2, b1, b2], axis=1)  # screen-space barycentrics of the clipped tri
    if not camera.orthographic:  # perspective-correct
        bs = bs / depth[t]
        bs /= bs.sum(axis=1, keepdims=True)
    s = src[t]
    if bary_map is not None:
        bs = np.einsum("pi,pij->pj", bs, bary_map[t])  # -> barycentrics in the source triangle
    n = np.einsum("pi,pij->pj", bs, nrm[s])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    c = np.einsum("pi,pij->pj", bs, col[s])

    right, up, forward = camera.basis()
    if camera.orthographic:
        to_eye = np.broadcast_to(-forward, n.shape)
    else:
        world = np.einsum("pi,pij->pj", bs, pos[s])
        to_eye = camera.eye - world
    flip = np.einsum("pj,pj->p", n, to_eye) < 0  # a back face: light it as if it faced us
    n[flip] *= -1.0
    light = -forward + 0.35 * up - 0.25 * right
    light /= np.linalg.norm(light)
    lambert = np.clip(n @ light, 0.0, 1.0)
    shade = ambient + diffuse * lambert
    rgb = np.clip(c * shade[:, None], 0.0, 1.0)
    flat = image.reshape(-1, 3)
    flat[pix] = rgb

    if outline:
        mesh_buf = np.full(sw * sh, -1, dtype=np.int64)
        mesh_buf[pix] = mesh_of[s]
        image[_edges(zbuf, mesh_buf.reshape(sh, sw), camera, sh, k)] *= 0.45
    return _finish(image, k, _key_to_distance(zbuf, camera) if return_depth else None)


def _finish(image: np.ndarray, k: int, depth: np.ndarray | None = None):
    if k > 1:
        h, w = image.shape[0] // k, image.shape[1] // k
        image = image.reshape(h, k, w, k, 3).mean(axis=(1, 3))
    image = np.clip(np.rint(image * 255.0), 0, 255).astype(np.uint8)
    return image if depth is None else (image, depth)


def _key_to_distance(key: np.ndarray, camera: Camera) -> np.ndarray:
    """The z-buffer's key (distance for orthographic, -1/distance for perspective) -> distance."""
    if camera.orthographic:
        return key
    with np.errstate(divide="ignore"):
        return np.where(np.isfinite(key), -1.0 / key, np.inf)


def _as_rgb01(colour) -> np.ndarray:
    c = np.asarray(colour)
    if c.shape[-1:] != (3,):
        raise InputError(f"a colour must be RGB (3 values), got shape {c.shape}", element="color")
    if np.issubdtype(c.dtype, np.integer) or (c.size and float(np.nanmax(c)) > 1.0):
        return c.astype(np.float64) / 255.0
    return c.astype(np.float64)


def _clip_near(view: np.ndarray, near: float):
    """Clip (F, 3, 3) camera-space triangles against z = near.

    Returns (triangles (G, 3, 3), source triangle per output (G,), and (G, 3, 3) maps taking an
    output triangle's barycentrics (row vector) to its source triangle's barycentrics)."""
    behind = view[..., 2] < near
    count = behind.sum(axis=1)
    eye3 = np.eye(3)
    keep = np.nonzero(count == 0)[0]
    out_v = [view[keep]]
    out_src = [keep]
    out_map = [np.broadcast_to(eye3, (len(keep), 3, 3))]

    def cut(a_idx, b_idx, f_idx):
        """Point where edge a->b crosses the near plane (in view space and as barycentrics)."""
        za = view[f_idx, a_idx, 2]
        zb = view[f_idx, b_idx, 2]
        s = (near - za) / (zb - za)
        p = view[f_idx, a_idx] + s[:, None] * (view[f_idx, b_idx] - view[f_idx, a_idx])
        bc = eye3[a_idx] + s[:, None] * (eye3[b_idx] - eye3[a_idx])
        return p, bc

    for n_behind in (1, 2):
        f = np.nonzero(count == n_behind)[0]
        if len(f) == 0:
            continue
        # rotate each triangle (keeping its winding) so corner 0 is the odd one out
        odd = behind[f] if n_behind == 1 else ~behind[f]
        first = np.argmax(odd, axis=1)
        i0, i1, i2 = first, (first + 1) % 3, (first + 2) % 3
        p0 = view[f, i0]
        if n_behind == 2:  # corner 0 in front: one smaller triangle
            q1, c1 = cut(i0, i1, f)
            q2, c2 = cut(i0, i2, f)
            out_v.append(np.stack([p0, q1, q2], axis=1))
            out_src.append(f)
            out_map.append(np.stack([eye3[i0], c1, c2], axis=1))
        else:  # corner 0 behind: a quad (q1, p1, p2, q2) -> two triangles
            p1, p2 = view[f, i1], view[f, i2]
            q1, c1 = cut(i0, i1, f)
            q2, c2 = cut(i0, i2, f)
            out_v += [np.stack([q1, p1, p2], axis=1), np.stack([q1, p2, q2], axis=1)]
            out_src += [f, f]
            out_map += [np.stack([c1, eye3[i1], eye3[i2]], axis=1), np.stack([c1, eye3[i2], c2], axis=1)]
    return np.concatenate(out_v), np.concatenate(out_src), np.concatenate(out_map)


def _rasterise(scr: np.ndarray, key: np.ndarray, width: int, height: int):
    """Z-buffer rasterisation of (F, 3, 2) pixel-space triangles with per-corner depth ``key``
    (affine in screen space, smaller = nearer). Returns the depth buffer, the winning triangle per
    pixel (-1 = none) and its barycentrics b1, b2 (b0 = 1 - b1 - b2), all (H, W)."""
    x, y = scr[..., 0], scr[..., 1]
    x0, y0 = x[:, 0], y[:, 0]
    e1x, e1y = x[:, 1] - x0, y[:, 1] - y0
    e2x, e2y = x[:, 2] - x0, y[:, 2] - y0
    area = e1x * e2y - e2x * e1y
    # covered pixel centres: ceil(min - 0.5) .. floor(max - 0.5), clipped to the image
    with np.errstate(invalid="ignore"):
        xmin = np.clip(np.ceil(x.min(axis=1) - 0.5), 0, width).astype(np.int64)
        xmax = np.clip(np.floor(x.max(axis=1) - 0.5), -1, width - 1).astype(np.int64)
        ymin = np.clip(np.ceil(y.min(axis=1) - 0.5), 0, height).astype(np.int64)
        ymax = np.clip(np.floor(y.max(axis=1) - 0.5), -1, height - 1).astype(np.int64)
    bw = np.maximum(xmax - xmin + 1, 0)
    bh = np.maximum(ymax - ymin + 1, 0)
    ok = (np.abs(area) > 1e-12) & np.all(np.isfinite(scr).reshape(len(scr), -1), axis=1) & np.isfinite(key).all(axis=1)
    tris = np.nonzero(ok & (bw > 0) & (bh > 0))[0]

    zbuf = np.full(width * height, np.inf)
    tri_buf = np.full(width * height, -1, dtype=np.int64)
    b1_buf = np.zeros(width * height)
    b2_buf = np.zeros(width * height)
    if len(tris) == 0:
        return (zbuf.reshape(height, width), tri_buf.reshape(height, width),
                b1_buf.reshape(height, width), b2_buf.reshape(height, width))

    inv_area = np.divide(1.0, area, out=np.zeros_like(area), where=area != 0)
    n_cand = bw[tris] * bh[tris]
    ends = np.cumsum(n_cand)
    start = 0
    while start < len(tris):
        base = ends[start - 1] if start else 0
        stop = int(np.searchsorted(ends, base + _CHUNK_FRAGMENTS, side="right"))
        stop = max(stop, start + 1)
        ids = tris[start:stop]
        counts = n_cand[start:stop]
        start = stop

        t = np.repeat(ids, counts)
        offsets = np.cumsum(counts) - counts
        local = np.arange(int(counts.sum()), dtype=np.int64) - np.repeat(offsets, counts)
        w = bw[t]
        px = xmin[t] + local % w
        py = ymin[t] + local // w
        dx = px + 0.5 - x0[t]
        dy = py + 0.5 - y0[t]
        ia = inv_area[t]
        b1 = (dx * e2y[t] - e2x[t] * dy) * ia
        b2 = (e1x[t] * dy - dx * e1y[t]) * ia
        eps = -1e-9
        inside = (b1 >= eps) & (b2 >= eps) & (b1 + b2 <= 1.0 - eps)
        if not inside.any():
            continue
        t, b1, b2 = t[inside], b1[inside], b2[inside]
        p = py[inside] * width + px[inside]
        kt = key[t]
        z = kt[:, 0] + b1 * (kt[:, 1] - kt[:, 0]) + b2 * (kt[:, 2] - kt[:, 0])
        np.minimum.at(zbuf, p, z)
        win = z <= zbuf[p]
        # ties between fragments at the same depth: any of them may win (order independent up to ties)
        tri_buf[p[win]] = t[win]
        b1_buf[p[win]] = b1[win]
        b2_buf[p[win]] = b2[win]
    return (zbuf.reshape(height, width), tri_buf.reshape(height, width),
            b1_buf.reshape(height, width), b2_buf.reshape(height, width))


def _edges(key: np.ndarray, mesh_buf: np.ndarray, camera: Camera, height: int, k: int) -> np.ndarray:
    """Outline pixels: a different mesh (or background) next door, or the near side of a depth
    jump. ``key`` is the z-buffer (affine in screen space on any plane: distance for orthographic,
    -1/distance for perspective), so its second difference vanishes on flat surfaces, even seen at
    grazing angles, and is large only across discontinuities."""
    covered = mesh_buf >= 0
    if camera.orthographic:
        thresh = np.full(key.shape, 4.0 * camera.ortho_height / height)
    else:
        dist = np.where(covered, -1.0 / np.where(covered, key, -1.0), 1.0)
        footprint = dist * 2.0 * math.tan(math.radians(camera.fov) / 2.0) / height
        thresh = 4.0 * footprint / dist**2  # a jump of 4 pixel footprints, in -1/distance units
    edge = np.zeros(key.shape, dtype=bool)
    for axis in (0, 1):
        for shift in range(1, max(k // 2, 1) + 1):
            for sign in (1, -1):
                edge |= covered & (_shift(mesh_buf, sign * shift, axis, -1) != mesh_buf)
        with np.errstate(invalid="ignore"):
            second = _shift(key, 1, axis, np.nan) + _shift(key, -1, axis, np.nan) - 2.0 * key
            edge |= covered & (second > thresh)  # > 0: a neighbour much farther, we are the near side
    return edge


def _shift(a: np.ndarray, by: int, axis: int, fill) -> np.ndarray:
    out = np.full_like(a, fill)
    src = [slice(None)] * a.ndim
    dst = [slice(None)] * a.ndim
    if by > 0:
        src[axis], dst[axis] = slice(0, -by), slice(by, None)
    else:
        src[axis], dst[axis] = slice(-by, None), slice(0, by)
    out[tuple(dst)] = a[tuple(src)]
    return out


# ---- clips -------------------------------------------------------------------------------------
def box_mesh(half_extents, pose=None) -> tuple[np.ndarray, np.ndarray]:
    """An axis-aligned box centred on its frame's origin (8 vertices, 12 outward triangles),
    optionally moved by a 4x4 world-from-box ``pose``."""
    hx, hy, hz = np.asarray(half_extents, dtype=np.float64).reshape(3)
    corners = np.array([[sx * hx, sy * hy, sz * hz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    faces = np.array([
        [0, 1, 3], [0, 3, 2],  # -x
        [4, 6, 7], [4, 7, 5],  # +x
        [0, 4, 5], [0, 5, 1],  # -y
        [2, 3, 7], [2, 7, 6],  # +y
        [0, 2, 6], [0, 6, 4],  # -z
        [1, 5, 7], [1, 7, 3],  # +z
    ], dtype=np.int64)
    if pose is not None:
        pose = np.asarray(pose, dtype=np.float64)
        corners = corners @ pose[:3, :3].T + pose[:3, 3]
    return corners, faces


def clip_frame_meshes(clip, frame: int, *, show_contacts: bool = True) -> list:
    """The meshes of one clip frame for :func:`render_meshes`: hand (skin), object at its pose
    (grey-blue, contact vertices red) and the table box if there is one."""
    hand = (np.asarray(clip.hand_vertices[frame], dtype=np.float64), clip.hand_faces, SKIN)
    obj_col = np.tile(np.asarray(OBJECT_BLUE, dtype=np.float64), (len(clip.object_vertices), 1))
    if show_contacts:
        obj_col[np.asarray(clip.contact_labels[frame]) != 0] = CONTACT_RED
    meshes = [hand, (clip.object_world_vertices(frame), clip.object_faces, obj_col / 255.0)]
    if clip.table_pose is not None and clip.table_half_extents is not None:
        verts, faces = box_mesh(clip.table_half_extents, clip.table_pose)
        meshes.append((verts, faces, TABLE_WOOD))
    return meshes


def render_clip_strip(
    clip,
    frames: list[int],
    path,
    *,
    size: tuple[int, int] = (320, 320),
    view: str = "three_quarter",
    show_contacts: bool = True,
    projection: str = "perspective",
    margin: float = 0.08,
    supersample: int = 2,
) -> Path:
    """Write a PNG with one row of panels, one per frame in ``frames``: hand, object (contacts in
    red when ``show_contacts``) and table, all panels seen by one camera framing the hand and
    object over the chosen frames, each captioned with its frame number. Returns the path."""
    from PIL import Image, ImageDraw

    frames = [int(f) for f in frames]
    if not frames:
        raise InputError("no frames to render", element="frames")
    n = clip.n_frames
    for f in frames:
        if not -n <= f < n:
            raise InputError(f"frame {f} is out of range [0, {n})", element="frames")
    frames = [f % n for f in frames]
    width, height = int(size[0]), int(size[1])

    pts = np.concatenate([np.concatenate([np.asarray(clip.hand_vertices[f], dtype=np.float64),
                                          clip.object_world_vertices(f)]) for f in frames])
    camera = frame_camera(pts, view=view, margin=margin, size=(width, height), projection=projection)

    strip = Image.new("RGB", (width * len(frames), height), BACKGROUND)
    draw = ImageDraw.Draw(strip)
    for i, f in enumerate(frames):
        panel = render_meshes(clip_frame_meshes(clip, f, show_contacts=show_contacts), camera, (width, height),
                              supersample=supersample)
        strip.paste(Image.fromarray(panel), (i * width, 0))
        draw.text((i * width + 6, 4), f"frame {f}", fill=(0, 0, 0))
        if i:
            draw.line([(i * width, 0), (i * width, height - 1)], fill=(200, 200, 200), width=1)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    strip.save(path)
    return path
