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
        """Per grid, what every query needs: 1 / spacing (G,), the last cell index (G, 3),
        the C-order strides (G, 3) and the flat offsets of a cell's 8 corners (G, 8), x-major
        (dx * sx + dy * sy + dz). Built once per process (a query is called thousands of times
        per frame solve on a few points each: per-call work dominates)."""
        shapes = self.shapes.astype(np.int64)
        strides = np.stack([shapes[:, 1] * shapes[:, 2], shapes[:, 2], np.ones(len(shapes), np.int64)], axis=1)
        corners = np.stack([dx * strides[:, 0] + dy * strides[:, 1] + dz
                            for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)], axis=1)
        return 1.0 / self.spacing, (shapes - 2).astype(np.float64), strides, corners

    def _cells(self, p: np.ndarray, grid):
        """The grid ids (int or (P,)), the points (P, 3) in node units, their cells (P, 3) and
        the ids of the points inside their grid (the others read FAR)."""
        inv_h, last, _, _ = self._tables
        g = np.asarray(grid, dtype=np.int64)
        u = (p - self.origins[g]) * (inv_h[g][:, None] if g.ndim else inv_h[g])
        cell = np.floor(u)
        return g, u, cell, np.flatnonzero(((cell >= 0) & (cell <= last[g])).all(axis=1))

    def query(self, points: np.ndarray, grid: np.ndarray | int = 0):
        """Trilinear signed distance (P,) m and its gradient (P, 3) at points (P, 3) given in
        the frame of grid ``grid`` (an int or (P,) ids). Outside the grid: FAR and 0."""
        p = np.asarray(points, dtype=np.float64)
        d = np.full(len(p), FAR)
        grad = np.zeros((len(p), 3))
        if not len(p):
            return d, grad
        inv_h, _, strides, corners = self._tables
        g, u, cell, keep = self._cells(p, grid)
        if not len(keep):
            return d, grad
        c = cell[keep]
        if g.ndim:
            gk = g[keep]
            first = self.offsets[gk] + np.einsum("ka,ka->k", c.astype(np.int64), strides[gk])
            v = self.values[first[:, None] + corners[gk]]
            scale = inv_h[gk][:, None]
        else:
            first = self.offsets[g] + c.astype(np.int64) @ strides[g]
            v = self.values[first[:, None] + corners[g]]
            scale = inv_h[g]
        t = u[keep] - c
        v000, v001, v010, v011, v100, v101, v110, v111 = v.T
        tx, ty, tz = t.T
        # along x, then y, then z; the gradient is the interpolant's own (exact for it)
        dx00, dx10, dx01, dx11 = v100 - v000, v110 - v010, v101 - v001, v111 - v011
        x00, x10 = v000 + tx * dx00, v010 + tx * dx10
        x01, x11 = v001 + tx * dx01, v011 + tx * dx11
        y0, y1 = x00 + ty * (x10 - x00), x01 + ty * (x11 - x01)
        d[keep] = y0 + tz * (y1 - y0)
        gx0 = dx00 + ty * (dx10 - dx00)
        gx1 = dx01 + ty * (dx11 - dx01)
        out = np.empty((len(keep), 3))
        out[:, 0] = gx0 + tz * (gx1 - gx0)
        out[:, 1] = (1 - tz) * (x10 - x00) + tz * (x11 - x01)
        out[:, 2] = y1 - y0
        grad[keep] = out * scale
        return d, grad

    @cached_property
    def node_reach(self) -> np.ndarray:
        """Per grid (G,) m, how far :meth:`query` can read from :meth:`node_values` at the same
        point. With L the largest slope of the node values between any two corners of a cell
        (measured over the grid, about 1 for exact distances), a corner c differs from the
        nearest corner n by at most L |c - n|, and the trilinear weights, worst at a cell's
        centre, bound the mix by (3 + 3 sqrt 2 + sqrt 3) / 8 L h = 1.121 L h."""
        steps = [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, -1, 0), (1, 0, 1), (1, 0, -1),
                 (0, 1, 1), (0, 1, -1), (1, 1, 1), (1, 1, -1), (1, -1, 1), (-1, 1, 1)]
        reach = np.empty(self.n_grids)
        for g, (at, shape) in enumerate(zip(self.offsets, self.shapes)):
            v = self.values[at:at + int(np.prod(shape))].reshape(shape)
            slope = 0.0
            for step in steps:
                a = tuple(slice(max(0, -k), n - max(0, k)) for k, n in zip(step, v.shape))
                b = tuple(slice(max(0, k), n - max(0, -k)) for k, n in zip(step, v.shape))
                if v[a].size:
                    slope = max(slope, float(np.abs(v[b] - v[a]).max()) / float(np.linalg.norm(step)))
            reach[g] = (3 + 3 * 2 ** 0.5 + 3 ** 0.5) / 8 * slope  # slope is per node step: h is in it
        return reach

    def node_values(self, points: np.ndarray, grid: np.ndarray | int = 0) -> np.ndarray:
        """The value (P,) m at the grid node nearest each point (P, 3) in grid ``grid``'s frame
        (an int or (P,) ids); FAR where :meth:`query` reads FAR. One gather instead of eight:
        the cheap bound for culling (see :meth:`maybe_below`)."""
        p = np.asarray(points, dtype=np.float64)
        d = np.full(len(p), FAR)
        if not len(p):
            return d
        strides = self._tables[2]
        g, u, _, keep = self._cells(p, grid)
        if not len(keep):
            return d
        node = np.rint(u[keep]).astype(np.int64)  # a corner of the cell query() reads
        if g.ndim:
            gk = g[keep]
            d[keep] = self.values[self.offsets[gk] + np.einsum("ka,ka->k", node, strides[gk])]
        else:
            d[keep] = self.values[self.offsets[g] + node @ strides[g]]
        return d

    def maybe_below(self, points: np.ndarray, level: float, grid: np.ndarray | int = 0) -> np.ndarray:
        """Ids of the points (P, 3) where :meth:`query` may read below ``level`` (m); at every
        other point it reads ``level`` or more (by :attr:`node_reach`), so it need not be
        queried."""
        reach = self.node_reach[np.asarray(grid, dtype=np.int64)]
        return np.flatnonzero(self.node_values(points, grid) < level + reach)
