"""The two contact-free baselines of the paper's comparison (section "Baseline Comparisons").

Both get what the paper gave them: the root comes from the project's own root pass (the
"ground truth root estimation"), every frame is solved independently, and the same filter,
acceleration refinement and spline fit follow. Only the finger DOFs are solved with their
objectives; the table term and the joint prior of :class:`FrameObjective` stay in both.

- ``fingertips``: fingertip keypoint tracking (Qin et al. 2022; the paper: its own objective with
  lambda_c = 0 and keypoints at the finger tips): the project's objective on the ``*Fingertip``
  markers only, contacts off.
- ``keyvectors``: functional pose equivalence, DexPilot's objective (Handa et al. 2020): task-space
  keyvectors between keypoints (palm -> each fingertip, thumb tip -> each other tip, between the
  other tips), each wanting the target's vector r_i(q) to equal f(d_i) * unit(v_i), v_i the
  source's vector and d_i = |v_i|:

      sum_i s_i |r_i(q) - f(d_i) v_i / d_i|^2   (mm^2)

  with f = beta d_i and s_i = 1 while d_i > epsilon; below epsilon, a thumb-finger vector is
  projected to eta_1 (pinch: the tips meet) with s_i = 200 and a finger-finger vector to eta_2
  (the tips kept apart) with s_i = 400. DexPilot's values: epsilon = 3 cm, eta_1 = 0.1 mm,
  eta_2 = 3 cm; its beta = 1.6 was the human-to-Allegro size ratio, so here beta is the target's
  palm-to-tip reach at rest over the source's longest over the clip.
"""

from __future__ import annotations

import copy

import numpy as np

from ..errors import InputError
from ..mesh.surface_points import SurfacePoints
from .objective import MM, FrameData, FrameObjective

KEYVECTOR_EPSILON = 0.03  # m: below it a keyvector switches to projection (DexPilot)
KEYVECTOR_ETA1 = 1e-4  # m: thumb-finger vectors projected to this length (pinch)
KEYVECTOR_ETA2 = 0.03  # m: finger-finger vectors projected to this length (kept apart)
KEYVECTOR_S1 = 200.0
KEYVECTOR_S2 = 400.0
TIP_SUFFIX = "Fingertip"
PALM_MARKER = "PalmRoot"


def _marker_groups(names: list) -> dict:
    """{marker name: (pair indices,)} in order of first appearance."""
    groups: dict = {}
    for i, n in enumerate(names):
        groups.setdefault(n, []).append(i)
    return {k: np.array(v, dtype=np.int64) for k, v in groups.items()}


def fingertip_subset(names: list) -> np.ndarray:
    """Indices (K,) of the marker pairs of the ``*Fingertip`` markers; an error if there are none."""
    subset = np.array([i for i, n in enumerate(names) if str(n).endswith(TIP_SUFFIX)], dtype=np.int64)
    if len(subset) < 2:
        raise InputError("the fingertip baselines need at least two '*Fingertip' markers in the annotations",
                         element="markers")
    return subset


class FingertipObjective(FrameObjective):
    """The project's objective restricted to the fingertip markers, contacts off (lambda_c = 0)."""

    def __init__(self, rig, config, marker_faces, marker_barycentric, pair_target, pair_weight, names, **kw):
        cfg = copy.deepcopy(config)
        cfg.weights.lambda_c = 0.0
        self.subset = fingertip_subset(names)
        tips = [names[i] for i in self.subset]
        weight = np.array([1.0 / tips.count(n) for n in tips])  # every tip marker counts once
        super().__init__(rig, cfg, marker_faces, marker_barycentric, np.asarray(pair_target)[self.subset],
                         weight, **kw)

    def set_frame(self, data: FrameData) -> None:
        super().set_frame(FrameData(data.markers[self.subset], data.contacts, data.object_points,
                                    data.object_normals, data.object_pose))


def keyvector_pairs(keypoints: list) -> tuple[list, list]:
    """Keyvectors over keypoint names (palm first): ((a, b) index pairs, set 0/1/2 per vector):
    0 palm -> tip, 1 thumb tip -> other tip, 2 between other tips."""
    tips = [k for k in range(1, len(keypoints))]
    thumb = [k for k in tips if keypoints[k].lower().startswith("thumb")]
    others = [k for k in tips if k not in thumb]
    pairs, sets = [], []
    for k in tips:
        pairs.append((0, k))
        sets.append(0)
    for t in thumb:
        for k in others:
            pairs.append((t, k))
            sets.append(1)
    for i, a in enumerate(others):
        for b in others[i + 1:]:
            pairs.append((a, b))
            sets.append(2)
    return pairs, sets


class KeyvectorObjective(FrameObjective):
    """DexPilot's keyvector objective (module docstring) plus the table term and joint prior.
    Keypoints: the palm marker and the fingertip markers; an area marker's keypoint is the mean
    of its target points, its source keypoint the marker's source point."""

    def __init__(self, rig, config, marker_faces, marker_barycentric, pair_target, pair_weight, names,
                 beta: float = 1.0, **kw):
        cfg = copy.deepcopy(config)
        cfg.weights.lambda_c = 0.0
        cfg.weights.lambda_m = 0.0
        super().__init__(rig, cfg, marker_faces, marker_barycentric, pair_target, pair_weight, **kw)
        groups = _marker_groups(list(names))
        if PALM_MARKER not in groups:
            raise InputError(f"the keyvector baseline needs a {PALM_MARKER!r} marker in the annotations",
                             element="markers")
        tip_names = [n for n in groups if str(n).endswith(TIP_SUFFIX)]
        if len(tip_names) < 2:
            raise InputError("the keyvector baseline needs at least two '*Fingertip' markers", element="markers")
        self.keypoints = [PALM_MARKER] + tip_names
        # averaging matrix (Kp, Mt): keypoint = mean of its marker's target points
        pair_target = np.asarray(pair_target)
        self.average = np.zeros((len(self.keypoints), len(marker_faces)))
        self.source_pair = np.zeros(len(self.keypoints), dtype=np.int64)
        for k, name in enumerate(self.keypoints):
            targets = np.unique(pair_target[groups[name]])
            self.average[k, targets] = 1.0 / len(targets)
            self.source_pair[k] = groups[name][0]
        pairs, sets = keyvector_pairs(self.keypoints)
        self.vec_a = np.array([p[0] for p in pairs])
        self.vec_b = np.array([p[1] for p in pairs])
        self.vec_set = np.array(sets)
        self.beta = float(beta)
        self.key_binding = self.kin.bind(SurfacePoints(np.asarray(marker_faces), np.asarray(marker_barycentric)))

    def source_keypoints(self, markers: np.ndarray) -> np.ndarray:
        """(Kp, 3) m: the source keypoints of a frame from its pair source positions (Np, 3)."""
        return markers[self.source_pair]

    def _aims(self):
        """Wanted target keyvectors (V, 3) mm and their weights s (V,) for the current frame."""
        src = self.source_keypoints(self.frame.markers)
        v = src[self.vec_b] - src[self.vec_a]
        d = np.linalg.norm(v, axis=1)
        unit = v / np.maximum(d, 1e-12)[:, None]
        length = self.beta * d
        weight = np.ones(len(d))
        close = (d < KEYVECTOR_EPSILON) & (self.vec_set > 0)
        s1 = close & (self.vec_set == 1)
        s2 = close & (self.vec_set == 2)
        length[s1], weight[s1] = KEYVECTOR_ETA1, KEYVECTOR_S1
        length[s2], weight[s2] = KEYVECTOR_ETA2, KEYVECTOR_S2
        return unit * (length * MM)[:, None], weight

    def value_and_grad(self, q: np.ndarray, want_grad: bool = True):
        value, grad = super().value_and_grad(q, want_grad)
        pose = self.kin.pose(q)
        keys = self.average @ self.kin.points(pose, self.key_binding)  # (Kp, 3) m
        aim, weight = self._aims()
        e = (keys[self.vec_b] - keys[self.vec_a]) * MM - aim  # (V, 3) mm
        value += float(np.sum(weight * np.einsum("ij,ij->i", e, e)))
        if want_grad:
            g = (2 * MM) * weight[:, None] * e
            cot_keys = np.zeros_like(keys)
            np.add.at(cot_keys, self.vec_b, g)
            np.add.at(cot_keys, self.vec_a, -g)
            grad = grad + self.kin.points_vjp(pose, self.key_binding, self.average.T @ cot_keys)
        return value, grad

    def _residual_blocks(self, pose, q: np.ndarray, jacobian: bool = True) -> list:
        blocks = super()._residual_blocks(pose, q, jacobian)
        x, jx = (self.kin.points_jacobian(pose, self.key_binding) if jacobian  # (Mt, 3), (Mt, 3, D)
                 else (self.kin.points(pose, self.key_binding), None))
        keys = self.average @ x
        aim, weight = self._aims()
        root = np.sqrt(weight)
        rk = ((keys[self.vec_b] - keys[self.vec_a]) * MM - aim) * root[:, None]
        jv = None
        if jx is not None:
            jk = np.einsum("km,dam->dak", self.average, jx.transpose(2, 1, 0))  # (D, 3, K)
            jv = ((jk[:, :, self.vec_b] - jk[:, :, self.vec_a]) * (MM * root)).reshape(len(q), -1)
        return blocks + [(rk.T.ravel(), jv)]


def keyvector_beta(target_rest_markers: np.ndarray, pair_target: np.ndarray, names: list,
                   source_positions: np.ndarray) -> float:
    """Size ratio beta: the target's mean palm-to-tip distance at rest over the source's
    longest (over the clip) mean palm-to-tip distance. target_rest_markers (Mt, 3) m,
    source_positions (T, Np, 3) m."""
    groups = _marker_groups(list(names))
    tips = [n for n in groups if str(n).endswith(TIP_SUFFIX)]
    if PALM_MARKER not in groups or not tips:
        return 1.0
    pair_target = np.asarray(pair_target)

    def target_point(name):
        return target_rest_markers[np.unique(pair_target[groups[name]])].mean(axis=0)

    palm_t = target_point(PALM_MARKER)
    reach_t = np.mean([np.linalg.norm(target_point(n) - palm_t) for n in tips])
    palm_s = source_positions[:, groups[PALM_MARKER][0]]
    reach_s = np.mean([np.linalg.norm(source_positions[:, groups[n][0]] - palm_s, axis=1) for n in tips], axis=0)
    return float(reach_t / max(float(reach_s.max()), 1e-9))
