"""Signed distance fields of closed meshes sampled on regular grids, for the solver's collision
terms: one exact query per grid node at set-up (libigl, sign by winding number), then every
query during a solve is a trilinear interpolation with its exact gradient, over arrays.

Several grids live in one :class:`SdfGrids` (a robot's links, a hand's parts), so the points of
many pairs are queried in one vectorised call. Distances in metres, negative inside. A point
outside its grid reads :data:`FAR` (m) with a zero gradient: the grids reach ``margin`` beyond
their mesh, and the terms only act inside a mesh.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numba import njit


#: Distance read outside a grid (m): far enough that no penalty acts there.
FAR = 1.0


def centred_grid(lower: np.ndarray, upper: np.ndarray, spacing: float):
    """Nodes (N, 3) every ``spacing`` m covering [lower, upper] (3,) m, placed symmetrically about
    the box's centre: (points, shape (nx, ny, nz), origin (3,)). A mesh and its mirror image then
    get lattices that are mirror images too, so the interpolated distances of a mirrored hand or
    object are the mirror of the original's (a lattice starting at ``lower`` would not be)."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    shape = np.ceil((upper - lower) / spacing - 1e-9).astype(np.int64) + 1
    origin = 0.5 * (lower + upper) - 0.5 * (shape - 1) * spacing
    axes = [origin[i] + spacing * np.arange(shape[i]) for i in range(3)]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return points, tuple(int(n) for n in shape), origin


def mesh_sdf_samples(vertices: np.ndarray, faces: np.ndarray, spacing: float, margin: float):
    """Exact signed distances on a grid around a closed mesh: (values (nx, ny, nz), origin (3,)).
    vertices (V, 3) m, faces (F, 3); the grid covers the mesh's box grown by ``margin`` m."""
    v = np.asarray(vertices, dtype=np.float64)
    points, shape, origin = centred_grid(v.min(axis=0) - margin, v.max(axis=0) + margin, spacing)
    return signed_distances(vertices, faces, points).reshape(shape), origin


def signed_distances(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N,) exact signed distances (m, negative inside) from ``points`` (N, 3) to a closed mesh
    (V, 3) / (F, 3)."""
    import igl

    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    points = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    if not len(points):
        return np.zeros(0)
    # The magnitude is the exact closest-point distance and only the sign comes from the
    # (fast) winding number: igl.signed_distance in its fast-winding-number mode also
    # approximates the magnitude (0.34 mm off on the demo bottle at 3 mm nodes), and that error
    # is not mirror symmetric.
    squared, _, _ = igl.point_mesh_squared_distance(points, v, f)
    inside = np.asarray(igl.fast_winding_number(v, f, points)) > 0.5
    return np.sqrt(np.asarray(squared, dtype=np.float64)) * np.where(inside, -1.0, 1.0)


@dataclass(frozen=True)
class SdfGrids:
    """G grids in one flat array. ``values``: all nodes, grid g's at ``offsets[g]`` in C order
    of ``shapes[g]`` (3,); ``origins`` (G, 3) m; ``spacing`` (G,) m."""

    values: np.ndarray
    offsets: np.ndarray
    shapes: np.ndarray
    origins: np.ndarray
    spacing: np.ndarray

    @classmethod
    def of_meshes(cls, meshes, spacing: float, margin: float) -> "SdfGrids":
        """Grids of closed meshes [(vertices (V, 3), faces (F, 3)), ...], each in its own frame."""
        values, offsets, shapes, origins = [], [], [], []
        at = 0
        for v, f in meshes:
            d, origin = mesh_sdf_samples(v, f, spacing, margin)
            values.append(d.ravel())
            offsets.append(at)
            shapes.append(d.shape)
            origins.append(origin)
            at += d.size
        return cls(np.concatenate(values), np.array(offsets, dtype=np.int64), np.array(shapes, dtype=np.int64),
                   np.array(origins, dtype=np.float64), np.full(len(shapes), float(spacing)))

    @property
    def n_grids(self) -> int:
        return len(self.offsets)

    @cached_property
    def _tables(self):
        """What every query needs, as contiguous arrays for the compiled kernels: the values
        (N,), offsets (G,), shapes (G, 3) int64, origins (G, 3) m, 1 / spacing (G,)."""
        return (np.ascontiguousarray(self.values, dtype=np.float64), self.offsets.astype(np.int64),
                np.ascontiguousarray(self.shapes, dtype=np.int64), np.ascontiguousarray(self.origins, dtype=np.float64),
                1.0 / np.asarray(self.spacing, dtype=np.float64))

    def _grid_ids(self, grid, n: int) -> np.ndarray:
        g = np.asarray(grid, dtype=np.int64)
        return np.full(n, int(g)) if g.ndim == 0 else np.ascontiguousarray(g)

    def query(self, points: np.ndarray, grid: np.ndarray | int = 0):
        """Trilinear signed distance (P,) m and its gradient (P, 3) at points (P, 3) given in
        the frame of grid ``grid`` (an int or (P,) ids). Outside the grid: FAR and 0."""
        p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        return _query(*self._tables, _IDENTITY, p, self._grid_ids(grid, len(p)), True)

    def query_in(self, frames: np.ndarray, points: np.ndarray, grid: np.ndarray | int = 0, gradient: bool = True):
        """As :meth:`query` for points (P, 3) given in another frame: ``frames`` (G, 3, 4)
        per grid, the map [A | b] from that frame into the grid's (x_grid = A x + b). The
        gradient (P, 3) is in the points' frame (A^T of the grid's); None without
        ``gradient``. One compiled pass: no (P, 3) copy per frame."""
        p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        d, g = _query(*self._tables, _frames(frames), p, self._grid_ids(grid, len(p)), bool(gradient))
        return d, (g if gradient else None)

    def below_in(self, frames: np.ndarray, points: np.ndarray, grid: np.ndarray | int, level: float):
        """(ids (K,), distances (K,) m) of the points (P, 3) (in the frame ``frames`` maps from,
        see :meth:`query_in`) reading below ``level`` m, ids ascending."""
        d, _ = self.query_in(frames, points, grid, gradient=False)
        ids = np.flatnonzero(d < level)
        return ids, d[ids]

    def items_below(self, frames: np.ndarray, points: np.ndarray, item_point: np.ndarray, item_grid: np.ndarray,
                    item_owner: np.ndarray, owner_centres: np.ndarray, owner_radii: np.ndarray,
                    grid_centres: np.ndarray, grid_radii: np.ndarray, level: float, skip: np.ndarray | None = None):
        """(items (K,) ascending, distances (K,) m) of the items reading below ``level`` m. An
        item is point ``item_point[i]`` of ``points`` (N, 3) read in grid ``item_grid[i]``
        (``frames`` (G, 3, 4) map the points' frame into each grid's); it is read only where the
        sphere of its owner (``owner_centres`` (O, 3), ``owner_radii`` (O,), by ``item_owner``)
        meets its grid's (``grid_centres`` (G, 3), ``grid_radii`` (G,), in the points' frame),
        beyond which the grid reads FAR for every point of the owner; ``skip`` (I,) bool: items
        left out."""
        p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        skip = np.zeros(0, np.bool_) if skip is None else np.ascontiguousarray(skip, dtype=np.bool_)
        return _items_below(*self._tables, _frames(frames), p, item_point, item_grid, item_owner,
                            np.ascontiguousarray(owner_centres, dtype=np.float64),
                            np.ascontiguousarray(owner_radii, dtype=np.float64),
                            np.ascontiguousarray(grid_centres, dtype=np.float64),
                            np.ascontiguousarray(grid_radii, dtype=np.float64), skip, float(level))

    def pairs_below(self, frames: np.ndarray, points: np.ndarray, centres: np.ndarray, radii: np.ndarray,
                    level: float):
        """Every (point, grid) pair whose value is below ``level`` m: points (N, 3) in one frame,
        ``frames`` (G, 3, 4) from it into each grid's; ``centres`` (G, 3) and ``radii`` (G,) m
        bound each grid in the points' frame (beyond it a grid reads FAR). Returns (points (K,),
        grids (K,), distances (K,) m), grid by grid, points ascending within a grid. The points
        must be sorted by x (only the slab within a sphere's reach in x is visited)."""
        p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        return _pairs_below(*self._tables, _frames(frames), p, np.ascontiguousarray(centres, dtype=np.float64),
                            np.ascontiguousarray(radii, dtype=np.float64), float(level))


# ---- compiled kernels ---------------------------------------------------------------------------
# A solve queries a few hundred to a few tens of thousands of points per evaluation, tens of
# thousands of times per run: as NumPy array expressions each query cost ~20 small temporaries
# and their call overhead (the collision terms were 2.8x the run time, `handretarget bench
# --collision`), so the trilinear read is one compiled loop. Plain IEEE arithmetic in a fixed
# order (no fastmath): the same values on every machine and for any worker count.

_IDENTITY = np.zeros((1, 3, 4))
_IDENTITY[0, :, :3] = np.eye(3)


def _frames(frames: np.ndarray) -> np.ndarray:
    """(G, 3, 4) contiguous float64 maps from (G, 3, 4) or (G, 4, 4) transforms."""
    f = np.asarray(frames, dtype=np.float64)
    return np.ascontiguousarray(f[:, :3, :] if f.shape[-2] == 4 else f)


@njit(cache=True, inline="always")
def _trilinear(values, at, shape, origin, inv_h, x, y, z, out_g):
    """The grid's trilinear value at (x, y, z) in its frame (FAR outside the last cell), its
    gradient written to out_g (3,) when out_g has 3 entries (0 outside)."""
    ux = (x - origin[0]) * inv_h
    uy = (y - origin[1]) * inv_h
    uz = (z - origin[2]) * inv_h
    cx, cy, cz = np.floor(ux), np.floor(uy), np.floor(uz)
    grad = out_g.shape[0] == 3
    if (cx < 0.0 or cy < 0.0 or cz < 0.0 or cx > shape[0] - 2 or cy > shape[1] - 2 or cz > shape[2] - 2
            or not (ux == ux and uy == uy and uz == uz)):
        if grad:
            out_g[0] = out_g[1] = out_g[2] = 0.0
        return FAR
    sy = shape[2]
    sx = shape[1] * sy
    first = at + int(cx) * sx + int(cy) * sy + int(cz)
    v000, v001 = values[first], values[first + 1]
    v010, v011 = values[first + sy], values[first + sy + 1]
    v100, v101 = values[first + sx], values[first + sx + 1]
    v110, v111 = values[first + sx + sy], values[first + sx + sy + 1]
    tx, ty, tz = ux - cx, uy - cy, uz - cz
    # along x, then y, then z; the gradient is the interpolant's own (exact for it)
    dx00, dx10, dx01, dx11 = v100 - v000, v110 - v010, v101 - v001, v111 - v011
    x00, x10 = v000 + tx * dx00, v010 + tx * dx10
    x01, x11 = v001 + tx * dx01, v011 + tx * dx11
    y0, y1 = x00 + ty * (x10 - x00), x01 + ty * (x11 - x01)
    if grad:
        gx0 = dx00 + ty * (dx10 - dx00)
        gx1 = dx01 + ty * (dx11 - dx01)
        out_g[0] = (gx0 + tz * (gx1 - gx0)) * inv_h
        out_g[1] = ((1 - tz) * (x10 - x00) + tz * (x11 - x01)) * inv_h
        out_g[2] = (y1 - y0) * inv_h
    return y0 + tz * (y1 - y0)


@njit(cache=True)
def _query(values, offsets, shapes, origins, inv_h, frames, points, grid, want_grad):
    """Per point k: grid[k]'s value at frames[f] @ points[k] (f = grid[k], or 0 with one frame)
    and, with want_grad, the gradient in the points' frame."""
    n = points.shape[0]
    d = np.empty(n)
    g = np.zeros((n, 3))
    local = np.empty(3)
    scratch = np.empty(3 if want_grad else 0)
    one = frames.shape[0] == 1
    for k in range(n):
        gi = grid[k]
        a = frames[0] if one else frames[gi]
        px, py, pz = points[k, 0], points[k, 1], points[k, 2]
        for r in range(3):
            local[r] = a[r, 0] * px + a[r, 1] * py + a[r, 2] * pz + a[r, 3]
        d[k] = _trilinear(values, offsets[gi], shapes[gi], origins[gi], inv_h[gi], local[0], local[1], local[2],
                          scratch)
        if want_grad and d[k] < FAR:
            for c in range(3):  # A^T times the grid's gradient
                g[k, c] = a[0, c] * scratch[0] + a[1, c] * scratch[1] + a[2, c] * scratch[2]
    return d, g


@njit(cache=True)
def _pairs_below(values, offsets, shapes, origins, inv_h, frames, points, centres, radii, level):
    n_grids = frames.shape[0]
    cap = 1024
    out_p = np.empty(cap, np.int64)
    out_g = np.empty(cap, np.int64)
    out_d = np.empty(cap)
    count = 0
    none = np.empty(0)
    xs = points[:, 0].copy()
    for gi in range(n_grids):
        a = frames[gi]
        cx, cy, cz, r2 = centres[gi, 0], centres[gi, 1], centres[gi, 2], radii[gi] * radii[gi]
        for k in range(np.searchsorted(xs, cx - radii[gi]), np.searchsorted(xs, cx + radii[gi], side="right")):
            px, py, pz = points[k, 0], points[k, 1], points[k, 2]
            if (px - cx) ** 2 + (py - cy) ** 2 + (pz - cz) ** 2 > r2:
                continue
            lx = a[0, 0] * px + a[0, 1] * py + a[0, 2] * pz + a[0, 3]
            ly = a[1, 0] * px + a[1, 1] * py + a[1, 2] * pz + a[1, 3]
            lz = a[2, 0] * px + a[2, 1] * py + a[2, 2] * pz + a[2, 3]
            v = _trilinear(values, offsets[gi], shapes[gi], origins[gi], inv_h[gi], lx, ly, lz, none)
            if v < level:
                if count == cap:
                    cap *= 2
                    out_p = _grow_int(out_p, cap)
                    out_g = _grow_int(out_g, cap)
                    out_d = _grow_float(out_d, cap)
                out_p[count], out_g[count], out_d[count] = k, gi, v
                count += 1
    return out_p[:count].copy(), out_g[:count].copy(), out_d[:count].copy()


@njit(cache=True)
def _items_below(values, offsets, shapes, origins, inv_h, frames, points, item_point, item_grid, item_owner,
                 owner_centres, owner_radii, grid_centres, grid_radii, skip, level):
    n_owner, n_grids = owner_centres.shape[0], grid_centres.shape[0]
    meets = np.zeros((n_owner, n_grids), np.bool_)
    for o in range(n_owner):
        for gi in range(n_grids):
            dx = owner_centres[o, 0] - grid_centres[gi, 0]
            dy = owner_centres[o, 1] - grid_centres[gi, 1]
            dz = owner_centres[o, 2] - grid_centres[gi, 2]
            reach = owner_radii[o] + grid_radii[gi]
            meets[o, gi] = dx * dx + dy * dy + dz * dz <= reach * reach
    n = item_point.shape[0]
    use_skip = skip.shape[0] == n
    ids = np.empty(n, np.int64)
    out_d = np.empty(n)
    count = 0
    none = np.empty(0)
    for i in range(n):
        gi = item_grid[i]
        if not meets[item_owner[i], gi] or (use_skip and skip[i]):
            continue
        k = item_point[i]
        a = frames[gi]
        px, py, pz = points[k, 0], points[k, 1], points[k, 2]
        lx = a[0, 0] * px + a[0, 1] * py + a[0, 2] * pz + a[0, 3]
        ly = a[1, 0] * px + a[1, 1] * py + a[1, 2] * pz + a[1, 3]
        lz = a[2, 0] * px + a[2, 1] * py + a[2, 2] * pz + a[2, 3]
        v = _trilinear(values, offsets[gi], shapes[gi], origins[gi], inv_h[gi], lx, ly, lz, none)
        if v < level:
            ids[count], out_d[count] = i, v
            count += 1
    return ids[:count].copy(), out_d[:count].copy()


def owner_spheres(points: np.ndarray, owner: np.ndarray, n_owner: int):
    """The sphere around each owner's points: centres (O, 3) (the points' mean) and radii (O,)
    m of points (N, 3) owned by ``owner`` (N,) ids in [0, O); 0 and the origin for none."""
    return _owner_spheres(np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(owner, dtype=np.int64),
                          int(n_owner))


@njit(cache=True)
def _owner_spheres(points, owner, n_owner):
    centre = np.zeros((n_owner, 3))
    count = np.zeros(n_owner)
    for k in range(points.shape[0]):
        o = owner[k]
        count[o] += 1.0
        for c in range(3):
            centre[o, c] += points[k, c]
    for o in range(n_owner):
        if count[o] > 0:
            for c in range(3):
                centre[o, c] /= count[o]
    radius = np.zeros(n_owner)
    for k in range(points.shape[0]):
        o = owner[k]
        r = np.sqrt((points[k, 0] - centre[o, 0]) ** 2 + (points[k, 1] - centre[o, 1]) ** 2
                    + (points[k, 2] - centre[o, 2]) ** 2)
        if r > radius[o]:
            radius[o] = r
    return centre, radius


@njit(cache=True)
def _grow_int(a, cap):
    out = np.empty(cap, np.int64)
    out[:a.shape[0]] = a
    return out


@njit(cache=True)
def _grow_float(a, cap):
    out = np.empty(cap)
    out[:a.shape[0]] = a
    return out
