"""Linear couplings between DOFs: a follower DOF that is a fixed affine function of a leader,
``q[follower] = multiplier * q[leader] + offset`` (URDF ``<mimic>``, MJCF ``<equality><joint>``
with a linear polynomial).

A coupling is a constraint of the solve, not a correction after it: the solver moves only the
free DOFs (leaders and uncoupled DOFs), the followers are computed from their leaders
(:meth:`DofCoupling.apply`), and the gradient with respect to a follower is carried to its
leader (:meth:`DofCoupling.pull_gradient`), so every pose the solver visits satisfies the
coupling exactly. A leader's limits are narrowed so that each of its followers stays within
its own (:meth:`DofCoupling.bounds`).

The couplings live in ``rig.metadata["couplings"]`` as
``[{"dof": follower name, "leader": leader name, "multiplier": m, "offset": o (rad or m),
"source": where it came from}]``: by name, so they survive DOFs being renumbered (a free root
added in front, a rig written to USD and read back).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError

#: A coupling's multiplier smaller than this in magnitude makes the follower a constant: refused
#: (a joint that never moves is a fixed joint, not a coupling).
MIN_MULTIPLIER = 1e-9


@dataclass(frozen=True)
class Coupling:
    """q[dof] = multiplier * q[leader] + offset; ``dof`` and ``leader`` are DOF names."""

    dof: str
    leader: str
    multiplier: float
    offset: float
    source: str = ""

    def to_dict(self) -> dict:
        return {"dof": self.dof, "leader": self.leader, "multiplier": float(self.multiplier),
                "offset": float(self.offset), "source": self.source}


class DofCoupling:
    """The couplings of one rig over its DOF vector (D,).

    ``leader`` (D,) int: the free DOF each DOF follows (itself when free); ``multiplier`` (D,)
    and ``offset`` (D,): the affine map from that leader (1 and 0 for a free DOF); ``free``
    (D,) bool. Chains (a follower of a follower) are resolved to the free DOF at their end."""

    def __init__(self, dof_names: list[str], couplings: list[Coupling] = ()):
        names = self.names = list(dof_names)
        index = {n: i for i, n in enumerate(names)}
        d = len(names)
        self.leader = np.arange(d)
        self.multiplier = np.ones(d)
        self.offset = np.zeros(d)
        self.couplings = tuple(couplings)
        direct = {}
        for c in self.couplings:
            el = f"coupling of DOF {c.dof!r}"
            if c.dof not in index:
                raise InputError(f"the coupled DOF {c.dof!r} is not a DOF of the rig", element=el)
            if c.leader not in index:
                raise InputError(f"its leader {c.leader!r} is not a DOF of the rig", element=el)
            if c.dof in direct:
                raise InputError("the DOF is coupled twice (one leader per DOF)", element=el)
            if c.dof == c.leader:
                raise InputError("the DOF is coupled to itself", element=el)
            if not (np.isfinite(c.multiplier) and np.isfinite(c.offset)) or abs(c.multiplier) < MIN_MULTIPLIER:
                raise InputError(f"multiplier {c.multiplier!r} and offset {c.offset!r} must be finite, the "
                                 "multiplier not zero", element=el)
            direct[c.dof] = c
        for name, c in direct.items():
            m, o, at, seen = 1.0, 0.0, name, {name}
            while at in direct:  # compose along the chain: q = m1 (m2 q_l + o2) + o1
                link = direct[at]
                m, o = m * link.multiplier, m * link.offset + o
                at = link.leader
                if at in seen:
                    raise InputError(f"the couplings form a loop through {sorted(seen)}",
                                     element=f"coupling of DOF {name!r}")
                seen.add(at)
            i = index[name]
            self.leader[i], self.multiplier[i], self.offset[i] = index[at], m, o
        self.free = self.leader == np.arange(d)

    @classmethod
    def identity(cls, n_dofs: int) -> "DofCoupling":
        """No couplings over ``n_dofs`` DOFs."""
        return cls([f"dof{i}" for i in range(n_dofs)])

    @classmethod
    def of_rig(cls, rig) -> "DofCoupling":
        """The rig's couplings (``rig.metadata["couplings"]``; none: the identity)."""
        raw = rig.metadata.get("couplings") or []
        try:
            couplings = [Coupling(str(c["dof"]), str(c["leader"]), float(c["multiplier"]),
                                  float(c.get("offset", 0.0)), str(c.get("source", ""))) for c in raw]
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"each coupling needs dof, leader, multiplier and offset: {exc}",
                             element="metadata couplings") from exc
        return cls(rig.dof_names, couplings)

    @property
    def empty(self) -> bool:
        return bool(self.free.all())

    @property
    def followers(self) -> np.ndarray:
        return np.nonzero(~self.free)[0]

    def apply(self, q: np.ndarray) -> np.ndarray:
        """(..., D) poses (or B-spline coefficients of curves sharing their knots, which a
        partition of unity makes exact) with every follower set from its leader."""
        q = np.array(q, dtype=np.float64)
        if self.empty:
            return q
        f = self.followers
        q[..., f] = self.multiplier[f] * q[..., self.leader[f]] + self.offset[f]
        return q

    def pull_gradient(self, g: np.ndarray) -> np.ndarray:
        """(D,) or (..., D) gradient with respect to the free DOFs (the chain rule through
        :meth:`apply`): each follower's part added to its leader's, zero at the followers."""
        g = np.array(g, dtype=np.float64)
        if self.empty:
            return g
        f = self.followers
        for i in f:  # a leader may have several followers: accumulate one by one
            g[..., self.leader[i]] += self.multiplier[i] * g[..., i]
        g[..., f] = 0.0
        return g

    def lift(self) -> np.ndarray:
        """(D, D) P with q = P q_free + offset: column j holds d q / d q_j for a free j
        (zero columns at the followers). Carries Gauss-Newton systems: P^T J^T r, P^T J^T J P."""
        d = len(self.free)
        p = np.zeros((d, d))
        p[np.arange(d), self.leader] = self.multiplier
        return p

    def bounds(self, lower: np.ndarray, upper: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(D,), (D,): the limits narrowed so that a leader within its own keeps every follower
        within the follower's; the followers' then those its leader reaches. Raises InputError
        when a follower's limits cannot be met at all."""
        lo, hi = np.array(lower, dtype=np.float64), np.array(upper, dtype=np.float64)
        if self.empty:
            return lo, hi
        for i in self.followers:
            j, m, o = self.leader[i], self.multiplier[i], self.offset[i]
            a, b = sorted(((lower[i] - o) / m, (upper[i] - o) / m))
            lo[j], hi[j] = max(lo[j], a), min(hi[j], b)
        for i in self.followers:
            j = self.leader[i]
            if not lo[j] <= hi[j]:
                raise InputError(f"no value of DOF {self.names[j]!r} keeps the DOFs coupled to it within their "
                                 "limits", element="couplings")
        f = self.followers
        ends = np.stack([self.multiplier[f] * lo[self.leader[f]], self.multiplier[f] * hi[self.leader[f]]])
        lo[f] = ends.min(axis=0) + self.offset[f]
        hi[f] = ends.max(axis=0) + self.offset[f]
        return lo, hi

    def violation(self, q: np.ndarray) -> float:
        """Largest |q[follower] - (m q[leader] + o)| over (..., D) poses (0 without couplings)."""
        if self.empty:
            return 0.0
        q = np.asarray(q, dtype=np.float64)
        return float(np.abs(self.apply(q) - q).max(initial=0.0))

    def to_list(self) -> list[dict]:
        return [c.to_dict() for c in self.couplings]


#: A fixed tendon over two joints whose allowed band, measured on its follower joint, is at most
#: this share of that joint's range is a coupling (held at the band's middle); a wider one is
#: left to the limits and reported as not honoured.
TENDON_COUPLING_SHARE = 0.25


def tendon_coupling(name: str, joints: list[tuple[str, float]], band: tuple[float, float],
                    ranges: dict[str, tuple[float, float]]) -> Coupling | None:
    """The coupling a limited fixed tendon ``sum coef_i q_i in band`` over two joints
    ``joints`` [(DOF name, coef)] (in DOF order) stands for, or None when its band is too wide
    (:data:`TENDON_COUPLING_SHARE` of the follower's range in ``ranges``) to be one. The later
    DOF follows the earlier: q_b = (mid - c_a q_a) / c_b."""
    if len(joints) != 2:
        return None
    (a, ca), (b, cb) = joints
    if abs(cb) < MIN_MULTIPLIER or abs(ca) < MIN_MULTIPLIER:
        return None
    lo, hi = band
    width = (hi - lo) / abs(cb)
    span = ranges[b][1] - ranges[b][0]
    if not (span > 0 and width <= TENDON_COUPLING_SHARE * span):
        return None
    mid = 0.5 * (lo + hi)
    return Coupling(b, a, -ca / cb, mid / cb,
                    f"mjcf tendon {name!r}: {ca:g} {a} + {cb:g} {b} in [{lo:g}, {hi:g}], held at its middle")


def couple_rest(dofs, couplings: list[Coupling]) -> None:
    """Set each follower's rest value (``Dof.rest``, in place) from its leader's, the leader's
    first moved within the limits its followers allow."""
    if not couplings:
        return
    c = DofCoupling([d.name for d in dofs], couplings)
    lo, hi = c.bounds(np.array([d.lower for d in dofs]), np.array([d.upper for d in dofs]))
    rest = np.clip([d.rest for d in dofs], lo, hi)
    rest = c.apply(rest)
    for d, r in zip(dofs, rest):
        d.rest = float(np.clip(r, d.lower, d.upper))
