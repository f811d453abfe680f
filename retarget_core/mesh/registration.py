"""Rigid registration of one object's surface onto another's: a scan of an object, in whatever
frame its tool wrote it (centre of mass at the origin, another up axis, turned), placed where
the clip's object is.

Start poses from the surfaces' moments: the area-weighted centroids matched, and every proper
rotation taking the new object's principal axes onto the old one's (the 24 signed axis
permutations: an axis's sign is not fixed by its moments, and near-equal moments (a cylinder,
a sphere, a cube) do not fix which axis is which). From each start, point-to-surface ICP of
samples of the old surface against the new one (the starts screened by a few point-to-point
Kabsch steps against dense samples of the new surface; the start that ends with the smallest
RMS distance then converges by point-to-plane steps on exact closest points), then the same on
the fitting region alone (the contact region: where the captured grip has to fit). All lengths in metres."""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from .geometry import face_areas, rigid_fit

#: ICP stops when an iteration changes the RMS distance by less than this (metres)
ICP_TOLERANCE = 1e-9
#: ICP iterations from every start pose (then the best start runs on to convergence)
SCREEN_ITERATIONS = 8
#: ... on this many of the old surface's samples (a random subset: the samples are random)
SCREEN_POINTS = 500
#: screened starts within this factor of the best RMS, plus SCREEN_TIE_M metres, fit equally
#: well (the screening's nearest-sample distances have a floor of about the sample spacing)
SCREEN_TIE = 1.1
SCREEN_TIE_M = 2e-4


def _turn(transform: np.ndarray) -> float:
    """The rotation angle (radians) of a rigid transform (4, 4)."""
    return float(np.arccos(np.clip((np.trace(transform[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))


@dataclass
class Registration:
    """``transform`` (4, 4) maps the new object's coordinates into the old object's frame;
    ``rms`` metres: RMS distance from the fitting region's points to the registered new
    surface; ``surface_rms`` the same over samples of the whole old surface; ``starts``: the
    screened RMS of every start pose tried (for a report)."""

    transform: np.ndarray
    rms: float
    surface_rms: float
    iterations: int
    starts: list = field(default_factory=list)

    def residual(self, points: np.ndarray, surface: "_Surface") -> float:
        """RMS distance (metres) from ``points`` (N, 3, old frame) to the registered surface."""
        inverse = np.linalg.inv(self.transform)
        local = np.asarray(points, dtype=np.float64) @ inverse[:3, :3].T + inverse[:3, 3]
        return float(np.sqrt(np.mean(np.sum((surface.closest(local) - local) ** 2, axis=1))))

    def apply(self, vertices: np.ndarray) -> np.ndarray:
        """(N, 3) points of the new object in the old object's frame."""
        return np.asarray(vertices, dtype=np.float64) @ self.transform[:3, :3].T + self.transform[:3, 3]


def surface_moments(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The area-weighted centroid (3,) of a triangle surface and its principal axes (3, 3)
    (columns, largest second moment first), from the exact second moments of the triangles.
    Surface moments, not volume ones: they hold for open scans and survive decimation."""
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]  # (F, 3, 3)
    area = face_areas(vertices, faces)
    total = float(area.sum())
    if not total > 0:
        raise InputError("the surface has no area", element="object mesh")
    centroid = (area[:, None] * tri.mean(axis=1)).sum(axis=0) / total
    local = tri - centroid
    # the second moment of a triangle with corners a, b, c over its area A:
    # A / 12 (sum_i v_i v_i^T + (sum_i v_i)(sum_i v_i)^T)
    s = local.sum(axis=1)
    second = np.einsum("f,fki,fkj->ij", area, local, local) + np.einsum("f,fi,fj->ij", area, s, s)
    second /= 12.0 * total
    values, axes = np.linalg.eigh(second)
    return centroid, axes[:, np.argsort(values)[::-1]]


def signed_axis_maps() -> list[np.ndarray]:
    """The 48 matrices (3, 3) that permute and flip the coordinate axes (half of them
    reflections: which half gives a rotation depends on the handedness of the eigenvectors)."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            m = np.zeros((3, 3))
            m[np.arange(3), perm] = signs
            out.append(m)
    return out


class _Surface:
    """Exact closest-point queries on one triangle surface, its AABB tree built once."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        import igl

        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        self.tree = igl.AABB()
        self.tree.init(self.vertices, self.faces)

        e1 = self.vertices[self.faces[:, 1]] - self.vertices[self.faces[:, 0]]
        e2 = self.vertices[self.faces[:, 2]] - self.vertices[self.faces[:, 0]]
        n = np.cross(e1, e2)
        self.normals = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)

    def closest(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) the surface points closest to ``points`` (N, 3)."""
        return self.closest_with_normals(points)[0]

    def closest_with_normals(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) closest surface points and (N, 3) the unit normals of their faces."""
        _, face, closest = self.tree.squared_distance(self.vertices, self.faces,
                                                      np.ascontiguousarray(points, dtype=np.float64))
        return closest, self.normals[np.asarray(face, dtype=np.int64)]


class _Samples:
    """Nearest-sample queries on dense samples of a surface (approximate closest points, a
    fraction of the exact query's cost): what screening the start poses needs."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, count: int):
        from scipy.spatial import cKDTree

        self.points = sample_surface(vertices, faces, count, seed=1)
        self.tree = cKDTree(self.points)

    def closest(self, points: np.ndarray) -> np.ndarray:
        return self.points[self.tree.query(points)[1]]


def _point_to_plane(points: np.ndarray, surface: _Surface, transform: np.ndarray,
                    iterations: int) -> tuple[np.ndarray, int]:
    """Point-to-plane ICP (linearised rotation, Gauss-Newton on the distances along the closest
    faces' normals): converges in a few steps from close by, where point-to-point creeps.
    (transform new -> old, iterations run)."""
    rms_before = np.inf
    for it in range(iterations):
        inverse = np.linalg.inv(transform)
        local = points @ inverse[:3, :3].T + inverse[:3, 3]
        closest, normal = surface.closest_with_normals(local)
        rms = float(np.sqrt(np.mean(np.sum((closest - local) ** 2, axis=1))))
        if rms_before - rms < ICP_TOLERANCE:
            return transform, it + 1
        rms_before = rms
        # a small motion (w, t) of the new surface, in its own frame: the moved closest point
        # q + w x q + t should meet the point along the face normal n
        a = np.hstack([np.cross(closest, normal), normal])  # (N, 6)
        b = np.einsum("ij,ij->i", local - closest, normal)
        step, *_ = np.linalg.lstsq(a, b, rcond=None)
        motion = np.eye(4)
        motion[:3, :3] = _rotation(step[:3])
        motion[:3, 3] = step[3:]
        transform = transform @ motion
    return transform, iterations


def _rotation(w: np.ndarray) -> np.ndarray:
    """The rotation matrix (3, 3) of the rotation vector ``w`` (3,) (Rodrigues)."""
    angle = float(np.linalg.norm(w))
    if angle < 1e-15:
        return np.eye(3)
    k = w / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * kx @ kx


def _icp(points: np.ndarray, surface: _Surface, transform: np.ndarray, iterations: int) -> tuple[np.ndarray, float, int]:
    """Point-to-surface ICP moving the new surface onto ``points`` (N, 3) (old frame) from
    ``transform`` (new -> old); (transform, RMS metres, iterations run)."""
    rms_before = np.inf
    rms = np.inf
    for it in range(iterations):
        inverse = np.linalg.inv(transform)
        local = points @ inverse[:3, :3].T + inverse[:3, 3]  # the points in the new object's frame
        closest = surface.closest(local)
        rms = float(np.sqrt(np.mean(np.sum((closest - local) ** 2, axis=1))))
        if rms_before - rms < ICP_TOLERANCE:
            return transform, rms, it + 1
        rms_before = rms
        transform = rigid_fit(closest, points)
    return transform, rms, iterations


def sample_surface(vertices: np.ndarray, faces: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """``count`` (N, 3) points spread over the surface by area, reproducibly."""
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    area = face_areas(vertices, faces)
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(tri), size=count, p=area / area.sum())
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    t = tri[pick]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])


def register_surface(old_vertices: np.ndarray, old_faces: np.ndarray, new_vertices: np.ndarray,
                     new_faces: np.ndarray, region: np.ndarray | None = None, *, samples: int = 2000,
                     iterations: int = 60) -> Registration:
    """The rigid transform placing the new surface (Vn, 3) / (Fn, 3) onto the old one (see the
    module docstring). ``region``: indices of old vertices the final fit is made on (the
    contact region; default every vertex)."""
    old_vertices = np.asarray(old_vertices, dtype=np.float64)
    new_vertices = np.asarray(new_vertices, dtype=np.float64)
    new_faces = np.asarray(new_faces, dtype=np.int64)
    c_old, a_old = surface_moments(old_vertices, old_faces)
    c_new, a_new = surface_moments(new_vertices, new_faces)
    cloud = sample_surface(old_vertices, old_faces, samples)
    surface = _Surface(new_vertices, new_faces)
    dense = _Samples(new_vertices, new_faces, 10 * samples)
    screened = []
    for m in signed_axis_maps():
        rotation = a_old @ m @ a_new.T
        if np.linalg.det(rotation) < 0:  # the 24 proper ones
            continue
        start = np.eye(4)
        start[:3, :3] = rotation
        start[:3, 3] = c_old - rotation @ c_new
        transform, rms, _ = _icp(cloud[:SCREEN_POINTS], dense, start, SCREEN_ITERATIONS)
        screened.append((rms, len(screened), transform))
    # a symmetric object fits equally well from several starts: of those that fit about as well
    # as the best, the smallest turn (so noise in the last digits never picks another one)
    best = min(s[0] for s in screened)
    near = [s for s in screened if s[0] <= SCREEN_TIE * best + SCREEN_TIE_M]
    chosen = min(near, key=lambda s: (round(_turn(s[2]), 6), s[1]))
    transform, used = _point_to_plane(cloud, surface, chosen[2], iterations)
    points = old_vertices if region is None or len(region) == 0 else old_vertices[np.asarray(region)]
    transform, more = _point_to_plane(points, surface, transform, iterations)
    registration = Registration(transform=transform, rms=0.0, surface_rms=0.0, iterations=used + more,
                                starts=[float(s[0]) for s in sorted(screened, key=lambda s: s[1])])
    registration.rms = registration.residual(points, surface)
    registration.surface_rms = registration.residual(cloud, surface)
    return registration
