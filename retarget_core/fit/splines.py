"""Cubic B-spline fitting of DOF trajectories (the paper's "Spline Fitting" section).

One cubic B-spline per DOF, with the same number of control points for every DOF of a
motion. The fit is a least-squares fit (``scipy.interpolate.make_lsq_spline``) over the frames
that are kept (frames still violating the acceleration check are masked out), starting from
clamped uniform knots; optionally the interior knot locations are then moved to lower the
residual ("values and locations in time", as in the paper), never ending worse than the
uniform fit.

Conventions: time in seconds; a curve is defined on ``[knots[0], knots[-1]]`` (the clip's
first to last frame time) and extrapolated outside it as set by ``BSplineCurve.extrapolation``
("held": constant end values, the default; "linear": end values continued with the end
derivatives), matching the extrapolation written into USD splines.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.interpolate import BSpline, PPoly, make_lsq_spline

from ..errors import InputError, RetargetError

EXTRAPOLATIONS = ("held", "linear")


@dataclass(eq=False)
class BSplineCurve:
    """A scalar B-spline f(t), t in seconds.

    knots: (n + degree + 1,) non-decreasing knot vector; coeffs: (n,) control values;
    degree: 3 (cubic) for fitted curves; extrapolation: "held" or "linear" outside
    ``[knots[0], knots[-1]]``.
    """

    knots: np.ndarray
    coeffs: np.ndarray
    degree: int = 3
    extrapolation: str = "held"

    def __post_init__(self):
        self.knots = np.ascontiguousarray(self.knots, dtype=np.float64).reshape(-1)
        self.coeffs = np.ascontiguousarray(self.coeffs, dtype=np.float64).reshape(-1)
        self.degree = int(self.degree)
        if self.degree < 0:
            raise InputError(f"degree must be >= 0, got {self.degree}", element="B-spline")
        if len(self.knots) != len(self.coeffs) + self.degree + 1:
            raise InputError(
                f"{len(self.knots)} knots for {len(self.coeffs)} coefficients of degree {self.degree} "
                f"(need n + degree + 1 = {len(self.coeffs) + self.degree + 1})",
                element="B-spline knots",
            )
        if len(self.coeffs) < self.degree + 1:
            raise InputError(
                f"a degree-{self.degree} B-spline needs at least {self.degree + 1} coefficients",
                element="B-spline coefficients",
            )
        if not np.all(np.isfinite(self.knots)) or np.any(np.diff(self.knots) < 0):
            raise InputError("knots must be finite and non-decreasing", element="B-spline knots")
        if not self.knots[-1] > self.knots[0]:
            raise InputError("knots span an empty interval", element="B-spline knots")
        if self.extrapolation not in EXTRAPOLATIONS:
            raise InputError(
                f"extrapolation must be one of {EXTRAPOLATIONS}, got {self.extrapolation!r}",
                element="B-spline extrapolation",
            )
        self._spline = BSpline(self.knots, self.coeffs, self.degree, extrapolate=True)

    # ---- evaluation --------------------------------------------------------------------------
    @property
    def n_control(self) -> int:
        return len(self.coeffs)

    @property
    def domain(self) -> tuple[float, float]:
        """(start, end) seconds: the span of the knots, where the curve is a spline."""
        return float(self.knots[0]), float(self.knots[-1])

    def _split(self, t):
        t = np.asarray(t, dtype=np.float64)
        a, b = self.domain
        return t, np.clip(t, a, b), a, b

    def __call__(self, t):
        """f(t) at t (scalar or array, seconds); right-continuous at knots."""
        t, tc, a, b = self._split(t)
        value = self._spline(tc)
        if self.extrapolation == "linear":
            d_start = self._spline(a, nu=1)
            # left limit of the derivative at the end of the domain
            d_end = self._end_derivative(1)
            value = value + np.where(t < a, (t - a) * d_start, 0.0) + np.where(t > b, (t - b) * d_end, 0.0)
        return value[()] if value.ndim == 0 else value

    def derivative(self, t, order: int = 1):
        """d^order f / dt^order at t (seconds); inside the domain the right-hand derivative at
        knots, at the domain's end the left-hand one."""
        order = int(order)
        if order < 1:
            raise InputError("derivative order must be >= 1", element="B-spline derivative")
        t, tc, a, b = self._split(t)
        value = np.asarray(self._spline(tc, nu=order), dtype=np.float64)
        at_end = tc >= b
        if np.any(at_end):
            value = np.where(at_end, self._end_derivative(order), value)
        outside = (t < a) | (t > b)
        if np.any(outside):
            if self.extrapolation == "held" or order > 1:
                value = np.where(outside, 0.0, value)
            else:
                value = np.where(t < a, self._spline(a, nu=1), np.where(t > b, self._end_derivative(1), value))
        return value[()] if value.ndim == 0 else value

    def _end_derivative(self, order: int) -> float:
        """Left-hand derivative of the given order at the domain's end."""
        seg = self._segments()
        x, c = seg.x, seg.c
        h = x[-1] - x[-2]
        k = c.shape[0] - 1
        total = 0.0
        for i in range(c.shape[0]):  # c[i] multiplies s^(k - i)
            p = k - i
            if p >= order:
                coef = c[i, -1]
                for m in range(order):
                    coef *= p - m
                total += coef * h ** (p - order)
        return float(total)

    def _segments(self) -> PPoly:
        """The curve as a piecewise polynomial over its non-empty knot intervals."""
        cached = self.__dict__.get("_ppoly")
        if cached is None:
            pp = PPoly.from_spline(self._spline, extrapolate=False)
            keep = np.nonzero(np.diff(pp.x) > 0)[0]
            # PPoly.from_spline includes the empty intervals of repeated knots; drop them
            x = np.concatenate([pp.x[keep], [pp.x[keep[-1] + 1]]])
            cached = PPoly(pp.c[:, keep], x, extrapolate=False)
            self.__dict__["_ppoly"] = cached
        return cached

    def breakpoints(self) -> np.ndarray:
        """(B,) the distinct knot values, ascending (segment ends, including the domain ends)."""
        return np.unique(self.knots)

    def to_bezier(self) -> list[tuple[float, float, float, float, float, float]]:
        """The curve as cubic Bezier segments ``(t0, t1, p0, p1, p2, p3)``, one per non-empty
        knot interval, exactly: on [t0, t1] with u = (t - t0) / (t1 - t0),
        f(t) = (1-u)^3 p0 + 3 (1-u)^2 u p1 + 3 (1-u) u^2 p2 + u^3 p3.
        p0 / p3 are the segment's own end values (left / right limits at its breakpoints),
        p1 = p0 + h/3 f'(t0+), p2 = p3 - h/3 f'(t1-)."""
        if self.degree > 3:
            raise InputError("only curves of degree <= 3 have a cubic Bezier form", element="B-spline degree")
        seg = self._segments()
        x, c = seg.x, seg.c
        k = c.shape[0] - 1
        # power coefficients a0 + a1 s + a2 s^2 + a3 s^3 in s = t - t0, padded to cubic
        power = np.zeros((4, c.shape[1]))
        for i in range(k + 1):
            power[k - i] = c[i]
        out = []
        for j in range(c.shape[1]):
            t0, t1 = float(x[j]), float(x[j + 1])
            h = t1 - t0
            a0, a1, a2, a3 = power[:, j]
            p0 = a0
            p3 = a0 + h * (a1 + h * (a2 + h * a3))
            d0 = a1
            d1 = a1 + h * (2 * a2 + 3 * a3 * h)
            out.append((t0, t1, float(p0), float(p0 + h / 3 * d0), float(p3 - h / 3 * d1), float(p3)))
        return out


# ---- fitting ---------------------------------------------------------------------------------
def clamped_uniform_knots(start: float, end: float, n_control: int, degree: int = 3) -> np.ndarray:
    """(n_control + degree + 1,) clamped knot vector on [start, end] with uniform interior knots."""
    n_interior = n_control - degree - 1
    interior = np.linspace(start, end, n_interior + 2)[1:-1]
    return np.concatenate([np.full(degree + 1, start), interior, np.full(degree + 1, end)])


def schoenberg_whitney_ok(x: np.ndarray, knots: np.ndarray, degree: int = 3) -> bool:
    """True when the sorted, distinct sample sites ``x`` satisfy the Schoenberg-Whitney
    condition for ``knots``: each basis function j gets its own site x_j with
    knots[j] < x_j < knots[j + degree + 1] (inclusive at the clamped domain ends), so the
    least-squares system has full rank. Greedy matching, O(n + F)."""
    n = len(knots) - degree - 1
    a, b = knots[0], knots[-1]
    m = len(x)
    if m < n:
        return False
    lo, hi = knots[:n], knots[degree + 1 : degree + 1 + n]
    # first site strictly after lo (at or after a clamped start)
    first = np.where(lo == a, np.searchsorted(x, lo, side="left"), np.searchsorted(x, lo, side="right"))
    j = np.arange(n)
    # greedy assignment: i_j = max(first_j, i_{j-1} + 1)
    assigned = j + np.maximum.accumulate(first - j)
    if assigned[-1] >= m:
        return False
    site = x[assigned]
    return bool(np.all((site < hi) | ((hi == b) & (site <= b))))


def _check_samples(times, values, n_control, mask, degree):
    times = np.asarray(times, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    if times.ndim != 1 or len(times) < 2:
        raise InputError(f"times must have shape (F,) with F >= 2, got {times.shape}", element="times")
    if values.shape != times.shape:
        raise InputError(f"values must have shape {times.shape}, got {values.shape}", element="values")
    if not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0):
        raise InputError("times must be finite and strictly increasing", element="times")
    if int(n_control) != n_control or n_control < degree + 1:
        raise InputError(
            f"a cubic B-spline needs an integer number of control points >= {degree + 1}, got {n_control!r}",
            element="n_control",
        )
    if mask is None:
        use = np.ones(len(times), dtype=bool)
    else:
        use = np.asarray(mask)
        if use.shape != times.shape or use.dtype != bool:
            raise InputError(f"mask must be a bool array of shape {times.shape}", element="mask")
    bad = use & ~np.isfinite(values)
    if np.any(bad):
        raise InputError(
            f"value at frame {int(np.nonzero(bad)[0][0])} is NaN or infinite (mask the frame out to skip it)",
            element="values",
        )
    n_used = int(use.sum())
    if n_used < n_control:
        raise InputError(
            f"the clip is too short for {int(n_control)} control points: {n_used} usable frames "
            f"(of {len(times)}); use at most {n_used} control points",
            element="n_control",
        )
    return times, values, int(n_control), use


def _lsq(x, y, knots, degree):
    """(spline, sum of squared residuals), or None where the knots are unusable."""
    if not schoenberg_whitney_ok(x, knots, degree):
        return None
    try:
        spline = make_lsq_spline(x, y, knots, k=degree)
    except (ValueError, np.linalg.LinAlgError):
        return None
    if not np.all(np.isfinite(spline.c)):
        return None
    r = spline(x) - y
    return spline, float(r @ r)


def _data_knots(x: np.ndarray, start: float, end: float, n_control: int, degree: int) -> np.ndarray:
    """Clamped knots with interior knots at quantiles of the sample sites (always satisfy
    Schoenberg-Whitney for distinct sites, n_control <= len(x))."""
    n_interior = n_control - degree - 1
    if n_interior <= 0:
        return clamped_uniform_knots(start, end, n_control, degree)
    # averaging (de Boor) knot placement over the used sites
    idx = np.arange(1, n_interior + 1)
    pos = idx * (len(x) - 1) / (n_interior + 1)
    interior = np.interp(pos, np.arange(len(x)), x)
    return np.concatenate([np.full(degree + 1, start), interior, np.full(degree + 1, end)])


def fit_bspline(
    times,
    values,
    n_control: int,
    *,
    mask=None,
    optimize_knots: bool = True,
    min_gap: float | None = None,
    max_iter: int = 40,
    extrapolation: str = "held",
    bounds: tuple[float, float] | None = None,
    failures: list | None = None,
) -> BSplineCurve:
    """Least-squares clamped cubic B-spline with ``n_control`` control points.

    times: (F,) seconds, strictly increasing; values: (F,); mask: (F,) bool, frames to use
    (None = all); the curve spans [times[0], times[-1]] whatever the mask.
    With ``optimize_knots`` the interior knots are moved from their uniform positions to lower
    the residual (bounded L-BFGS-B over a sorted parametrisation with a minimum knot gap
    ``min_gap``, default a tenth of the uniform spacing; only knots meeting the
    Schoenberg-Whitney condition are accepted); the result is never worse than the uniform fit.

    ``bounds = (lower, upper)``: when the fitted curve leaves them (checked at the frames and
    four points per knot interval), the coefficients are re-fitted by bounded least squares
    within them, on the same knots; a B-spline lies in the convex hull of its coefficients, so
    the curve then stays within the bounds everywhere. A curve already inside is unchanged.

    ``failures``: a list that gets one message per knot optimisation that failed numerically
    (the uniform or best knots found are kept then); a failure is never silent.

    Raises InputError when fewer frames are usable than control points or a used value is NaN.
    """
    degree = 3
    times, values, n_control, use = _check_samples(times, values, n_control, mask, degree)
    x, y = times[use], values[use]
    start, end = float(times[0]), float(times[-1])

    knots = clamped_uniform_knots(start, end, n_control, degree)
    best = _lsq(x, y, knots, degree)
    if best is None:  # masked-out stretches leave some uniform interval empty
        knots = _data_knots(x, start, end, n_control, degree)
        best = _lsq(x, y, knots, degree)
        if best is None:
            raise InputError(
                f"cannot place {n_control} control points on the {len(x)} usable frames "
                "(too many masked frames in one stretch); use fewer control points",
                element="n_control",
            )
    best_knots = knots
    n_interior = n_control - degree - 1
    if optimize_knots and n_interior > 0 and best[1] > 0:
        best_knots, best, error = _optimize_knots(x, y, best_knots, best, start, end, degree, min_gap, max_iter)
        if error and failures is not None:
            failures.append(error)
    coeffs = np.asarray(best[0].c, dtype=np.float64)
    if bounds is not None:
        coeffs = _bounded(x, y, best_knots, coeffs, degree, times, bounds)
    return BSplineCurve(knots=best_knots, coeffs=coeffs, degree=degree, extrapolation=extrapolation)


def _bounded(x, y, knots, coeffs, degree, times, bounds) -> np.ndarray:
    """``coeffs`` refitted within ``bounds`` by bounded least squares when the curve leaves them."""
    lo, hi = float(bounds[0]), float(bounds[1])
    if not lo <= hi:
        raise InputError(f"bounds must satisfy lower <= upper, got ({lo}, {hi})", element="bounds")
    if coeffs.min() >= lo and coeffs.max() <= hi:
        return coeffs  # convex hull: the curve is inside
    breaks = np.unique(knots)
    probe = np.concatenate([times, (breaks[:-1, None] + np.diff(breaks)[:, None] * np.linspace(0, 1, 5)).ravel()])
    values = BSpline(knots, coeffs, degree)(probe)
    if values.min() >= lo and values.max() <= hi:
        return coeffs
    from scipy.optimize import lsq_linear

    design = BSpline.design_matrix(x, knots, degree).toarray()
    with np.errstate(divide="ignore", invalid="ignore"):
        fit = lsq_linear(design, y, bounds=(lo, hi), method="bvls")
    if fit.status <= 0 or not np.all(np.isfinite(fit.x)):
        # scipy's BVLS can stall with NaN steps (status 0) when long stretches of the data sit
        # exactly on a bound (a joint held at its limit for 400 frames did it): the
        # trust-region method solves the same convex problem without that failure
        fit = lsq_linear(design, y, bounds=(lo, hi), method="trf", lsq_solver="exact", tol=1e-12)
    if not np.all(np.isfinite(fit.x)):
        raise RetargetError(f"the bounded least-squares fit within [{lo:g}, {hi:g}] failed ({fit.message})")
    return np.clip(fit.x, lo, hi)


def _optimize_knots(x, y, knots, best, start, end, degree, min_gap, max_iter):
    """Move the interior knots to lower the least-squares residual; returns (knots, fit, error):
    the best knots seen and "" or, when the optimiser failed numerically, what happened."""
    from scipy.optimize import minimize

    n_interior = len(knots) - 2 * (degree + 1)
    length = end - start
    if min_gap is None:
        min_gap = 0.1 * length / (n_interior + 1)
    min_gap = float(min(min_gap, 0.5 * length / (n_interior + 1)))
    free = length - (n_interior + 1) * min_gap
    scale = float(np.mean(y * y)) + 1e-300  # keeps the objective O(1)

    def knots_of(z):
        # gaps = min_gap + softmax(z) * free: sorted interior knots with a minimum gap
        w = np.exp(z - z.max())
        gaps = min_gap + free * w / w.sum()
        interior = start + np.cumsum(gaps)[:-1]
        return np.concatenate([np.full(degree + 1, start), interior, np.full(degree + 1, end)])

    def z_of(kn):
        gaps = np.diff(np.concatenate([[start], kn[degree + 1 : -degree - 1], [end]]))
        w = np.maximum(gaps - min_gap, 1e-6 * free) / free
        return np.log(w)

    worst = best[1] / scale * 4.0 + 1.0
    state = {"knots": knots, "fit": best}

    def cost(z):
        kn = knots_of(z)
        fit = _lsq(x, y, kn, degree)
        if fit is None:
            return worst  # infeasible: worse than anything found
        if fit[1] < state["fit"][1]:
            state["knots"], state["fit"] = kn, fit
        return fit[1] / scale

    z0 = z_of(knots)
    error = ""
    try:
        minimize(cost, z0, method="L-BFGS-B", bounds=[(-12.0, 12.0)] * len(z0),
                 options={"maxiter": int(max_iter), "eps": 1e-6})
    except (ValueError, FloatingPointError, np.linalg.LinAlgError) as err:
        error = f"knot optimisation failed ({type(err).__name__}: {err}); kept the best knots seen"
    return state["knots"], state["fit"], error


def coupled_curves(curves: list[BSplineCurve], coupling) -> list[BSplineCurve]:
    """``curves`` (one per DOF) with each follower of ``coupling`` (a
    :class:`~retarget_core.rig.coupling.DofCoupling`) replaced by its leader's curve mapped
    affinely: knots shared, coefficients m c + o, so the follower's curve is m q_leader(t) + o
    at every t (B-spline bases sum to one), not only at the frames."""
    if coupling is None or coupling.empty:
        return list(curves)
    out = list(curves)
    for i in coupling.followers:
        lead = curves[coupling.leader[i]]
        out[i] = replace(lead, coeffs=coupling.multiplier[i] * lead.coeffs + coupling.offset[i])
    return out


def fit_trajectory(times, q, n_control: int, mask=None, optimize_knots: bool = True, limits=None,
                   report: dict | None = None, **kwargs) -> list[BSplineCurve]:
    """One cubic B-spline per DOF, the same control-point count for every DOF.

    times: (F,) seconds; q: (F, D) DOF values; mask: (F, D) bool frames to use per DOF, or
    None; limits: None or (lower (D,), upper (D,)): each curve kept within its DOF's limits
    (``bounds`` of :func:`fit_bspline`); report: a dict that gets ``failures`` [{dof, error}]
    (knot optimisations that failed). Extra keyword arguments go to :func:`fit_bspline`."""
    q = np.asarray(q, dtype=np.float64)
    times = np.asarray(times, dtype=np.float64)
    if q.ndim != 2 or q.shape[0] != times.shape[0]:
        raise InputError(f"q must have shape (F={times.shape[0]}, D), got {q.shape}", element="q")
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != q.shape or mask.dtype != bool:
            raise InputError(f"mask must be a bool array of shape {q.shape}", element="mask")
    curves, failures = [], []
    for d in range(q.shape[1]):
        errors = []
        try:
            curves.append(
                fit_bspline(times, q[:, d], n_control, mask=None if mask is None else mask[:, d],
                            optimize_knots=optimize_knots,
                            bounds=None if limits is None else (limits[0][d], limits[1][d]), failures=errors,
                            **kwargs)
            )
        except InputError as exc:
            raise InputError(str(exc), element=f"DOF {d}") from exc
        except RetargetError as exc:
            raise RetargetError(f"DOF {d}: {exc}") from exc
        if not np.all(np.isfinite(curves[-1].coeffs)):  # never a NaN curve handed on as a result
            raise RetargetError(f"DOF {d}: the fitted curve is not finite")
        failures += [{"dof": d, "error": e} for e in errors]
    if report is not None:
        report["failures"] = failures
    return curves


def evaluate_curves(curves: list[BSplineCurve], times) -> np.ndarray:
    """(F, D) the curves evaluated at times (F,) seconds."""
    times = np.asarray(times, dtype=np.float64)
    return np.stack([np.asarray(c(times), dtype=np.float64) for c in curves], axis=-1)
