"""The per-frame objective of the paper (section "Motion Retargeting"), with analytic gradients.

    E(q) = lambda_m G_M + lambda_c (lambda_cd G_CD + lambda_cn G_CN) + lambda_t G_T + lambda_j G_J
           (+ lambda_p G_P + lambda_sc G_SC, beyond the paper)

- G_M: markers, sum over marker pairs of w * rho(|target point - source marker|) (a marker of
  K pairs has w = 1/K so every marker counts once), rho(d) = d^2 (mm^2) or, with
  ``markers.distance = "huber"``, the pseudo-Huber 2 delta (sqrt(d^2 + delta^2) - delta):
  d^2 within about delta, then growing like 2 delta d (a bounded pull);
- G_CD: contacts, sum of |target contact point - object point|^2 (mm^2);
- G_CN: contact normals, sum of (1 + n_object . n_hand): zero when exactly opposite;
- G_T: table, sum over hand sample points of max(0, -sdf_table) (mm), the box's analytic SDF;
- G_J: prior, smooth L1 deviation (radians) of the non-root DOFs from a reference pose;
- G_P: hand-object penetration, sum over hand sample points of max(0, -sdf_object)^2 (mm^2),
  and G_SC: self collision, the same between hand parts that do not share a surface edge
  (both beyond the paper, :mod:`.collision`; weights lambda_p and lambda_sc);
- G_R: root gauge, beyond the paper: a hand's root is three Euler angles, and near gimbal
  lock (the middle angle near +-90 deg) one combination of them barely turns the hand, so the
  data leave it free and the solves wander along it from frame to frame (measured: 20-180 deg
  jumps of root_rx and root_rz, which no refinement can smooth). G_R = (v . (theta -
  theta_seed))^2 (rad^2) along that combination v only, weighted up as lock nears
  (:meth:`FrameObjective.set_seed`); zero far from lock.

Distances are in millimetres so that the paper's weights (1, ..., lambda_j = 50) balance: data
terms dominate and the prior only settles what the data leave free. Gradients come from the
rig's vector-Jacobian products (one pass over the joints per term), never finite differences.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from ..mesh.geometry import box_inside, box_signed_distance
from ..mesh.surface_points import SurfacePoints
from ..rig.model import Rig
from .collision import CollisionGrids, ObjectCollision, ObjectInHand, SelfCollision
from .config import RetargetConfig

MM = 1000.0
#: The depth (mm) below which a point inside the table is modelled as this deep in the curve
#: polish's Gauss-Newton system (:meth:`FrameObjective.table_block`): the square root of a
#: hinge has unbounded slope at the surface.
TABLE_FLOOR_MM = 0.5
TABLE_MARGIN = 0.03  # metres: sample points farther above the table at the seed are skipped
PRIOR_EPS = 0.05  # radians
GAUGE_SIGMA = 0.3  # smallest singular value of the root's rotation axes below which G_R acts: the L1 prior is smoothed (quadratic) within about 3 degrees of zero


@dataclass
class FrameData:
    """Everything frame-specific: source marker positions (Np, 3) m; contact target points on
    the hand, object points (N, 3) m and object normals (N, 3); the object pose (4, 4)."""

    markers: np.ndarray
    contacts: SurfacePoints
    object_points: np.ndarray
    object_normals: np.ndarray
    object_pose: np.ndarray | None = None


class FrameObjective:
    """E(q) and dE/dq (D,) for one rig; frame data are swapped in with :meth:`set_frame`."""

    def __init__(self, rig: Rig, config: RetargetConfig, marker_faces: np.ndarray, marker_barycentric: np.ndarray,
                 pair_target: np.ndarray, pair_weight: np.ndarray, table_pose: np.ndarray | None = None,
                 table_half_extents: np.ndarray | None = None, object_vertices: np.ndarray | None = None,
                 object_faces: np.ndarray | None = None, reference: np.ndarray | None = None,
                 self_collision: bool = True, penetration_stride: int | None = None,
                 collision: CollisionGrids | None = None):
        self.rig = rig
        self.kin = rig.kinematics()
        self.config = config
        w = config.weights
        self.w = w
        self.marker_binding = self.kin.bind(SurfacePoints(marker_faces, marker_barycentric)) if len(marker_faces) else None
        self.pair_target = np.asarray(pair_target, dtype=np.int64)
        self.pair_weight = np.asarray(pair_weight, dtype=np.float64)
        self.marker_delta = (config.markers.huber_width_si * MM if config.markers.distance == "huber"
                             else None)  # mm; None = squared distances
        stride = max(1, int(config.sampling.table_sample_stride))
        samples = np.arange(0, rig.surface.n_vertices, stride)
        self.sample_vertices = samples
        self.all_samples = self.kin.bind(SurfacePoints.from_vertices(samples, rig.surface.faces))
        self.sample_binding = self.all_samples
        self.table = None if table_pose is None else (np.asarray(table_pose, float), np.asarray(table_half_extents, float))
        self.prior_mask = np.array([d.joint != 0 for d in rig.dofs])
        self.reference = rig.rest_pose if reference is None else np.asarray(reference, float)
        # root rotation DOFs, and the Euler direction gimbal lock leaves free at the seed
        self.root_rotation = np.array([d.joint == 0 and d.kind != "translate" for d in rig.dofs])
        self.root_reference = rig.rest_pose.copy()
        self.gauge_direction = np.zeros(int(self.root_rotation.sum()))
        self.gauge_weight = 0.0
        self.object_collision = self.object_in_hand = None  # the two halves of G_P
        if w.lambda_p > 0 and object_vertices is not None:
            self.object_collision = ObjectCollision(self.kin, object_vertices, object_faces,
                                                    penetration_stride or config.sampling.penetration_sample_stride,
                                                    grids=None if collision is None else collision.object)
            self.object_in_hand = ObjectInHand(self.kin, object_vertices,
                                               parts=None if collision is None else collision.parts,
                                               grids=None if collision is None else collision.part_grids)
        # ``self_collision`` False: a stage that moves the root only (the hand's own shape is fixed)
        self.self_collision = None
        if w.lambda_sc > 0 and self_collision:
            self.self_collision = SelfCollision(self.kin, config.sampling.self_collision_samples,
                                                parts=None if collision is None else collision.parts,
                                                grids=None if collision is None else collision.part_grids)
        self.frame: FrameData | None = None
        self.contact_binding = None
        self.evaluations = 0

    def set_frame(self, data: FrameData) -> None:
        self.frame = data
        self.contact_binding = self.kin.bind(data.contacts) if len(data.contacts) else None
        self.sample_binding = self.all_samples

    def set_seed(self, q: np.ndarray) -> None:
        """Anchor G_R at the seed q (D,): the root rotation DOFs' world axes at q form a (3, 3)
        matrix whose smallest singular value drops to 0 at gimbal lock; its right singular
        vector is the combination of Euler angles that barely turns the hand. Only that
        direction is held, and only near lock (weight lambda_r (1 - sigma / GAUGE_SIGMA)^2)."""
        self.root_reference = np.asarray(q, dtype=np.float64).copy()
        self.gauge_weight = 0.0
        if self.w.lambda_r <= 0 or self.root_rotation.sum() < 2:
            return
        axes = self.kin.pose(self.root_reference).dof_axis[self.root_rotation].T  # (3, k)
        _, sigma, vt = np.linalg.svd(axes)
        closeness = max(0.0, 1.0 - float(sigma[-1]) / GAUGE_SIGMA)
        self.gauge_direction = vt[-1]
        self.gauge_weight = self.w.lambda_r * closeness ** 2

    def focus_samples(self, q: np.ndarray, margin: float = TABLE_MARGIN, hand_object: bool = True) -> None:
        """Let the table term see only the sample points within ``margin`` (m) of the table at
        pose q (D,), and the collision terms only the points near the object or near another
        part: most of a hand is far from each, and skinning thousands of points per evaluation
        for nothing dominates the cost. Exact as long as the far points stay out;
        :meth:`unseen_collision` checks that at the solution. ``hand_object`` False leaves the
        hand-object term's sets as they are (a warm start that runs without it refocuses after)."""
        pose = self.kin.pose(q)
        if (hand_object and self.object_collision is not None and self.frame is not None
                and self.frame.object_pose is not None):
            self.object_collision.focus(pose, self.frame.object_pose)
            self.object_in_hand.focus(pose, self.frame.object_pose)
        if self.self_collision is not None:
            self.self_collision.focus(pose)
        if self.table is None:
            return
        s = self.kin.points(pose, self.all_samples)
        near = box_signed_distance(s, *self.table) < margin
        self.sample_binding = self.all_samples.subset(np.flatnonzero(near)) if near.any() else None

    def unseen_collision(self, q: np.ndarray) -> bool:
        """True when, at q (D,), a sample point left out by :meth:`focus_samples` is inside the
        table, the object or another part (the focused objective then differs from the whole one)."""
        pose = self.kin.pose(q)
        if (self.object_collision is not None and self.frame is not None and self.frame.object_pose is not None
                and (self.object_collision.missed(pose, self.frame.object_pose)
                     or self.object_in_hand.missed(pose, self.frame.object_pose))):
            return True
        if self.self_collision is not None and self.self_collision.missed(pose):
            return True
        if self.table is None or self.sample_binding is self.all_samples:
            return False
        inside_all = int((box_signed_distance(self.kin.points(pose, self.all_samples), *self.table) < 0).sum())
        if inside_all == 0 or self.sample_binding is None:
            return inside_all > 0
        return inside_all > int((box_signed_distance(self.kin.points(pose, self.sample_binding), *self.table) < 0).sum())

    def widen_self_focus(self, q: np.ndarray) -> bool:
        """Add to the self-collision rows the parts' points near another part at pose q (D,),
        keeping those focused; True when any was added (:meth:`SelfCollision.widen`)."""
        return self.self_collision is not None and self.self_collision.widen(self.kin.pose(q))

    def keep_object_out(self, q: np.ndarray) -> None:
        """Until the next :meth:`focus_samples`, the hand-object term costs only for the points
        (and object-point items) outside the object (the part) at pose q (D,): what is inside
        there moves freely, nothing else may go in (:meth:`ObjectCollision.keep_out`). The
        second warm start's form of the term (see
        :func:`~retarget_core.solve.frame_solver.warm_start`)."""
        if self.object_collision is not None and self.frame is not None and self.frame.object_pose is not None:
            pose = self.kin.pose(q)
            self.object_collision.keep_out(pose, self.frame.object_pose)
            self.object_in_hand.keep_out(pose, self.frame.object_pose)

    def object_depth(self, q: np.ndarray) -> float:
        """The deepest focused point of either half of G_P at pose q (D,), m (0: none inside)."""
        if self.object_collision is None or self.frame is None or self.frame.object_pose is None:
            return 0.0
        pose = self.kin.pose(q)
        return max(self.object_collision.deepest(pose, self.frame.object_pose),
                   self.object_in_hand.deepest(pose, self.frame.object_pose))

    def object_penetration(self, q: np.ndarray) -> float:
        """lambda_p * G_P (both halves) at pose q (D,) over the focused points: 0 when no point
        of the hand is in the object nor of the object in the hand (or the term is off)."""
        if self.object_collision is None or self.frame is None or self.frame.object_pose is None:
            return 0.0
        pose = self.kin.pose(q)
        return (self.object_collision.value_and_cot(pose, self.frame.object_pose, self.w.lambda_p)[0]
                + self.object_in_hand.value_and_grad(pose, self.frame.object_pose, self.w.lambda_p, False)[0])

    @contextmanager
    def hand_object_off(self):
        """Within the block the objective leaves out the hand-object term (both halves of G_P)."""
        held = self.object_collision, self.object_in_hand
        self.object_collision = self.object_in_hand = None
        try:
            yield self
        finally:
            self.object_collision, self.object_in_hand = held

    @contextmanager
    def collision_off(self):
        """Within the block the objective leaves out the collision terms (G_P, G_SC)."""
        with self.hand_object_off():
            held, self.self_collision = self.self_collision, None
            try:
                yield self
            finally:
                self.self_collision = held

    # ---- the terms -----------------------------------------------------------------------------
    def whole_value(self, q: np.ndarray) -> float:
        """E(q) over every sample point, as :meth:`focus_samples` at q then :meth:`value_and_grad`
        give it, without building the focused sets: for one-off values (a frame scored at a
        pose, the polish's trial steps), where the focus would cost as much as the value."""
        # every table sample point; the collision terms come after, over all their points
        focused, self.sample_binding = self.sample_binding, self.all_samples
        pose = self.kin.pose(q)
        try:
            with self.collision_off():
                value, _ = self.value_and_grad(q, want_grad=False, pose=pose)
        finally:
            self.sample_binding = focused
        if self.object_collision is not None and self.frame.object_pose is not None:
            value += self.object_collision.whole_value(pose, self.frame.object_pose, self.w.lambda_p)
            value += self.object_in_hand.whole_value(pose, self.frame.object_pose, self.w.lambda_p)
        if self.self_collision is not None:
            value += self.self_collision.whole_value(pose, self.w.lambda_sc)
        return value

    def value_and_grad(self, q: np.ndarray, want_grad: bool = True, pose=None):
        """(E, dE/dq (D,)) at q (D,) (``pose``: the kinematics' pose at q, when computed already)."""
        self.evaluations += 1
        w, kin, data = self.w, self.kin, self.frame
        pose = kin.pose(q) if pose is None else pose
        value = 0.0
        grad = np.zeros(len(q))

        if self.marker_binding is not None and w.lambda_m > 0 and len(self.pair_target):
            x = kin.points(pose, self.marker_binding)
            e = (x[self.pair_target] - data.markers) * MM  # (Np, 3) mm
            rho, slope = self._marker_penalty(np.einsum("ij,ij->i", e, e))
            value += w.lambda_m * float(np.sum(self.pair_weight * rho))
            if want_grad:
                cot = np.zeros_like(x)
                np.add.at(cot, self.pair_target, (2 * MM * w.lambda_m) * (self.pair_weight * slope)[:, None] * e)
                grad += kin.points_vjp(pose, self.marker_binding, cot)

        if self.contact_binding is not None and w.lambda_c > 0:
            x = kin.points(pose, self.contact_binding)
            e = (x - data.object_points) * MM
            value += w.lambda_c * w.lambda_cd * float(np.einsum("ij,ij->", e, e))
            if want_grad:
                grad += kin.points_vjp(pose, self.contact_binding, (2 * MM * w.lambda_c * w.lambda_cd) * e)
            if w.lambda_cn > 0:
                if want_grad:
                    n, g = kin.normals_vjp(pose, self.contact_binding, (w.lambda_c * w.lambda_cn) * data.object_normals)
                    grad += g
                else:
                    n = kin.normals(pose, self.contact_binding)
                value += w.lambda_c * w.lambda_cn * float(np.sum(1.0 + np.einsum("ij,ij->i", n, data.object_normals)))

        if self.sample_binding is not None and self.table is not None and w.lambda_t > 0:
            s = kin.points(pose, self.sample_binding)
            inside, sdf, dsdf = box_inside(s, *self.table)
            if len(inside):
                value += w.lambda_t * float(-sdf.sum() * MM)
                if want_grad:
                    cot = np.zeros_like(s)
                    cot[inside] -= (w.lambda_t * MM) * dsdf
                    grad += kin.points_vjp(pose, self.sample_binding, cot)

        if self.object_collision is not None and data.object_pose is not None:
            v, cot = self.object_collision.value_and_cot(pose, data.object_pose, w.lambda_p)
            value += v
            if want_grad and cot is not None:
                grad += kin.points_vjp(pose, self.object_collision.binding, cot)
            v, g = self.object_in_hand.value_and_grad(pose, data.object_pose, w.lambda_p, want_grad)
            value += v
            if g is not None:
                grad += g
        if self.self_collision is not None:
            v, g = self.self_collision.value_and_grad(pose, w.lambda_sc, want_grad)
            value += v
            if g is not None:
                grad += g

        if w.lambda_j > 0:
            d = (q - self.reference)[self.prior_mask]
            smooth = np.sqrt(d * d + PRIOR_EPS * PRIOR_EPS)
            value += w.lambda_j * float(np.sum(smooth - PRIOR_EPS))
            if want_grad:
                grad[self.prior_mask] += w.lambda_j * d / smooth
        if self.gauge_weight > 0:
            d = float(self.gauge_direction @ (q - self.root_reference)[self.root_rotation])
            value += self.gauge_weight * d * d
            if want_grad:
                grad[self.root_rotation] += 2 * self.gauge_weight * d * self.gauge_direction
        return value, grad

    def residuals(self, q: np.ndarray):
        """Least-squares form of the smooth terms: r (M,) and dr/dq (M, D) with sum(r**2) equal
        to the markers, contacts (distance and normal), collision (G_P, G_SC) and prior part of
        E(q). The table's linear hinge is left out (it is zero almost everywhere and MMA, which
        sees the whole objective, settles it; the curve polish, which has no MMA after it, adds
        it as :meth:`table_block`). The stacked, checkable form; the warm start uses
        :meth:`normal_equations` and :meth:`residual_cost`, built from the same blocks."""
        self.evaluations += 1
        blocks = self._residual_blocks(self.kin.pose(q), q)
        if not blocks:
            return np.zeros(0), np.zeros((0, len(q)))
        return np.concatenate([r for r, _ in blocks]), np.hstack([jt for _, jt in blocks]).T

    def normal_equations(self, q: np.ndarray, table: bool = False):
        """The Gauss-Newton system of :meth:`residuals` without forming the (M, D) Jacobian:
        (sum r^2, J^T r (D,), J^T J (D, D)). Summed block by block from each term's transposed
        Jacobian, which the kinematics hand out contiguous, so no large copy is made. ``table``:
        the table's hinge too, as :meth:`table_block` (the curve polish, which sees no MMA after it)."""
        self.evaluations += 1
        n = len(q)
        cost, g, h = 0.0, np.zeros(n), np.zeros((n, n))
        pose = self.kin.pose(q)
        blocks = self._residual_blocks(pose, q)
        if table:
            blocks.append(self.table_block(pose, n))
        for r, jt in blocks:
            cost += float(r @ r)
            g += jt @ r
            h += jt @ jt.T  # numpy hands A @ A.T to BLAS syrk
        return cost, g, h

    def residual_cost(self, q: np.ndarray) -> float:
        """sum(r**2) of :meth:`residuals` at q (D,) without any Jacobian, several times cheaper:
        all a Gauss-Newton trial step needs until it is accepted."""
        self.evaluations += 1
        return float(sum(r @ r for r, _ in self._residual_blocks(self.kin.pose(q), q, jacobian=False)))

    def table_block(self, pose, n: int):
        """G_T as residuals for a Gauss-Newton model: r_i = sqrt(lambda_t depth_i) (depth in mm)
        over the focused sample points inside the table, so sum r^2 is lambda_t G_T; dr/dq =
        lambda_t grad(depth) / (2 r) with r floored at TABLE_FLOOR_MM deep, so a point that has
        barely gone in does not dominate the system. Its J^T r is half the hinge's gradient, as
        for every least-squares term. (r (M,), transposed Jacobian (n, M)); empty when nothing
        is inside or the term is off."""
        w = self.w
        if self.sample_binding is None or self.table is None or w.lambda_t <= 0:
            return np.zeros(0), np.zeros((n, 0))
        inside, sdf, dsdf = box_inside(self.kin.points(pose, self.sample_binding), *self.table)
        if not len(inside):
            return np.zeros(0), np.zeros((n, 0))
        _, jx = self.kin.points_jacobian(pose, self.sample_binding.subset(inside))  # (I, 3, D)
        r = np.sqrt(w.lambda_t * MM * -sdf)
        floor = np.sqrt(w.lambda_t * TABLE_FLOOR_MM)
        # d depth / dq = -(d sdf / dx) . dx/dq, in mm per unit DOF
        ddepth = -MM * np.einsum("pa,pad->dp", dsdf, jx)
        return r, ddepth * (w.lambda_t / (2 * np.maximum(r, floor)))

    def _residual_blocks(self, pose, q: np.ndarray, jacobian: bool = True) -> list:
        """Per smooth term: (r (M_b,), transposed Jacobian dr/dq (D, M_b), None without
        ``jacobian``). Rows of a 3D term run axis-major (all x, then all y, then all z), the
        layout of the kinematics' (D, 3, P) Jacobians."""
        w, kin, data = self.w, self.kin, self.frame
        n = len(q)
        blocks = []
        if self.marker_binding is not None and w.lambda_m > 0 and len(self.pair_target):
            x, jx = (kin.points_jacobian(pose, self.marker_binding) if jacobian
                     else (kin.points(pose, self.marker_binding), None))
            e = (x[self.pair_target] - data.markers) * MM  # (Np, 3) mm
            # r = s(d^2) e with s^2 = lambda w rho / d^2, so |r|^2 = lambda w rho exactly;
            # dr = s de + e (ds/dd^2) 2 e.de
            d2 = np.einsum("ij,ij->i", e, e)
            if self.marker_delta is None:
                s, ds = np.sqrt(w.lambda_m * self.pair_weight), np.zeros(len(d2))
            else:
                root = np.sqrt(d2 + self.marker_delta ** 2)
                # rho / d^2 = 2 delta / (root + delta)
                s = np.sqrt(w.lambda_m * self.pair_weight * 2 * self.marker_delta / (root + self.marker_delta))
                ds = -s / (4 * root * (root + self.marker_delta))
            jm = None
            if jx is not None:
                je = jx.transpose(2, 1, 0)[:, :, self.pair_target] * MM  # (D, 3, Np) mm per unit DOF
                jm = je * s
                if self.marker_delta is not None:
                    jm += e.T[None] * (2 * ds * np.einsum("ap,dap->dp", e.T, je))[:, None, :]
                jm = jm.reshape(n, -1)
            blocks.append(((e * s[:, None]).T.ravel(), jm))
        if self.contact_binding is not None and w.lambda_c > 0:
            x, jx = (kin.points_jacobian(pose, self.contact_binding) if jacobian
                     else (kin.points(pose, self.contact_binding), None))
            s = np.sqrt(w.lambda_c * w.lambda_cd) * MM
            blocks.append((((x - data.object_points) * s).T.ravel(),
                           None if jx is None else jx.transpose(2, 1, 0).reshape(n, -1) * s))
            if w.lambda_cn > 0:
                # r = sqrt(k (1 + c)); dr = k dc / (2 r), floored where the normals are opposite
                normal, jn = (kin.normals_jacobian(pose, self.contact_binding) if jacobian
                              else (kin.normals(pose, self.contact_binding), None))
                k = w.lambda_c * w.lambda_cn
                c = np.einsum("ij,ij->i", normal, data.object_normals)
                r = np.sqrt(np.maximum(k * (1.0 + c), 1e-12))
                blocks.append((r, None if jn is None else
                               np.einsum("dap,pa->dp", jn.transpose(2, 1, 0), data.object_normals) * (k / (2 * r))))
        if self.object_collision is not None and data.object_pose is not None:
            for term in (self.object_collision, self.object_in_hand):
                block = term.residuals(pose, data.object_pose, w.lambda_p, jacobian)
                if block is not None:
                    blocks.append(block)
        if self.self_collision is not None:
            block = self.self_collision.residuals(pose, w.lambda_sc, jacobian)
            if block is not None:
                blocks.append(block)
        if w.lambda_j > 0:
            # signed r = sign(d) sqrt(lambda_j (smooth - eps)): smooth through d = 0
            d = (q - self.reference)[self.prior_mask]
            smooth = np.sqrt(d * d + PRIOR_EPS * PRIOR_EPS)
            r = np.sign(d) * np.sqrt(w.lambda_j * (smooth - PRIOR_EPS))
            jt = None
            if jacobian:
                slope = np.where(np.abs(r) > 1e-9, w.lambda_j * np.abs(d) / smooth / (2 * np.abs(r) + 1e-300),
                                 np.sqrt(w.lambda_j / (2 * PRIOR_EPS)))
                jt = np.zeros((n, len(d)))
                jt[np.nonzero(self.prior_mask)[0], np.arange(len(d))] = slope
            blocks.append((r, jt))
        if self.gauge_weight > 0:
            root = self.gauge_weight ** 0.5
            jt = None
            if jacobian:
                jt = np.zeros((n, 1))
                jt[self.root_rotation, 0] = root * self.gauge_direction
            blocks.append((np.array([root * float(self.gauge_direction @ (q - self.root_reference)[self.root_rotation])]), jt))
        return blocks

    def _marker_penalty(self, d2: np.ndarray):
        """rho and d rho / d(d^2) per marker pair (Np,) from the squared distances d2 (Np,) mm^2."""
        if self.marker_delta is None:
            return d2, np.ones_like(d2)
        delta = self.marker_delta
        root = np.sqrt(d2 + delta * delta)
        return 2 * delta * (root - delta), delta / root
