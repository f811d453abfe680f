"""Cubic B-spline DOF curves -> Blender F-curve keyframes, standard library only (runs in
Blender's Python and in the client without numpy / scipy). See issue 8, item 5.

A B-spline of degree <= 3 is a polynomial of degree <= 3 between consecutive breakpoints
(distinct knots), and a polynomial piece on [t_i, t_i+1] (h = t_i+1 - t_i) is exactly the
cubic Bezier with control points

    P0 = f(t_i),  P1 = f(t_i) + f'(t_i+) h/3,  P2 = f(t_i+1) - f'(t_i+1 -) h/3,  P3 = f(t_i+1)

placed at times t_i, t_i + h/3, t_i+1 - h/3, t_i+1. Time handles at thirds make the Bezier's
x(u) linear in u, so its y is the polynomial itself: one keyframe per breakpoint with FREE
handles reproduces the B-spline exactly (up to rounding; Blender stores keyframes as 32-bit
floats). This is the same conversion the USD export uses for its Ts splines.

Units: B-spline time t in seconds; keyframe x in Blender frames,
``frame = start_frame + t * fps`` (a clip's frame 0 is t = 0); values as in the curve
(radians / metres).

    keys = bspline_to_keyframes(knots, coeffs, fps=30.0, start_frame=1.0)
    fcurve.extrapolation = keys.extrapolation          # "CONSTANT" for held curves
    for k in keys: ...  # k.frame, k.value, k.handle_left (x, y), k.handle_right (x, y)
"""

from __future__ import annotations

import bisect
import json
import math
from collections import namedtuple
from collections.abc import Mapping

RESULT_FORMAT = "handretarget.result"
RESULT_VERSION = 2
#: result.json versions this reader takes (2 added provenance, frames, unused_settings)
RESULT_VERSIONS = (1, 2)
# B-spline extrapolation (core / USD) -> Blender F-curve extrapolation
EXTRAPOLATION_TO_BLENDER = {"held": "CONSTANT", "linear": "LINEAR"}

Keyframe = namedtuple(
    "Keyframe",
    "frame value handle_left handle_right interpolation handle_left_type handle_right_type",
    defaults=("BEZIER", "FREE", "FREE"),
)
Keyframe.__doc__ = """One Blender keyframe: frame (frames), value, handle_left / handle_right
(frame, value) positions, interpolation of the segment that starts here ("BEZIER"), handle
types ("FREE": Blender keeps the positions as set)."""


class Keyframes(list):
    """A list of :data:`Keyframe` (ascending frames) with ``extrapolation``, the Blender
    F-curve extrapolation to use ("CONSTANT" or "LINEAR")."""

    def __init__(self, keys=(), extrapolation: str = "CONSTANT"):
        super().__init__(keys)
        self.extrapolation = extrapolation


class DofCurve(tuple):
    """(knots, coeffs) of one DOF's B-spline (knots in seconds), unpackable as a pair; also
    ``.knots``, ``.coeffs``, ``.degree`` and ``.extrapolation`` ("held" / "linear")."""

    def __new__(cls, knots, coeffs, degree: int = 3, extrapolation: str = "held"):
        self = super().__new__(cls, (knots, coeffs))
        self.degree, self.extrapolation = degree, extrapolation
        return self

    @property
    def knots(self):
        return self[0]

    @property
    def coeffs(self):
        return self[1]


# ---- checks --------------------------------------------------------------------------------
def _finite(x, what: str) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a number, got {x!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{what} must be finite, got {v}")
    return v


def _check_bspline(knots, coeffs, degree):
    """(knots, coeffs, degree) as lists of floats / int, or ValueError naming the problem."""
    if isinstance(degree, bool) or not isinstance(degree, (int, float)) or int(degree) != degree or degree < 0:
        raise ValueError(f"degree must be an integer >= 0, got {degree!r}")
    p = int(degree)
    try:
        knots = list(knots)
        coeffs = list(coeffs)
    except TypeError:
        raise ValueError("knots and coeffs must be sequences of numbers") from None
    knots = [_finite(k, f"knot {i}") for i, k in enumerate(knots)]
    coeffs = [_finite(c, f"coefficient {i}") for i, c in enumerate(coeffs)]
    n = len(coeffs)
    if n < p + 1:
        raise ValueError(f"a degree-{p} B-spline needs at least {p + 1} coefficients, got {n}")
    if len(knots) != n + p + 1:
        raise ValueError(f"wrong number of knots: {len(knots)} for {n} coefficients of degree {p} "
                         f"(need n + degree + 1 = {n + p + 1})")
    for i in range(1, len(knots)):
        if knots[i] < knots[i - 1]:
            raise ValueError(f"knots must be non-decreasing: knot {i} = {knots[i]} < knot {i - 1} = {knots[i - 1]}")
    if not knots[n] > knots[p]:
        raise ValueError(f"knots span an empty interval [{knots[p]}, {knots[n]}]")
    return knots, coeffs, p


# ---- de Boor ---------------------------------------------------------------------------------
def _span(knots, p, n, t, left: bool) -> int:
    """Index mu of the non-empty knot interval used at t: knots[mu] <= t < knots[mu + 1]
    (``left``: knots[mu] < t <= knots[mu + 1]), clamped to the base interval
    [knots[p], knots[n]] (outside it the end polynomial pieces continue)."""
    lo, hi = knots[p], knots[n]
    if t >= hi or (left and t > lo):
        mu = bisect.bisect_left(knots, min(t, hi)) - 1
    else:
        mu = bisect.bisect_right(knots, max(t, lo)) - 1
    return mu


def _eval_span(knots, coeffs, p, mu, t, m) -> float:
    """m-th derivative at t of the polynomial piece of span mu (de Boor on local control points)."""
    if m > p:
        return 0.0
    c = coeffs[mu - p: mu + 1]  # c[k] = coeffs[mu - p + k]
    for s in range(1, m + 1):  # derivative control points, degree p - s + 1 -> p - s
        q = p - s + 1
        c = [q * (c[k + 1] - c[k]) / (knots[mu - p + k + p + 1] - knots[mu - p + k + s]) for k in range(len(c) - 1)]
    q = p - m
    d = list(c)
    for r in range(1, q + 1):
        for j in range(q, r - 1, -1):
            i = j + mu - p
            a, b = knots[i + m], knots[i + p + 1 - r]
            alpha = (t - a) / (b - a)
            d[j] = (1.0 - alpha) * d[j - 1] + alpha * d[j]
    return d[q]


def bspline_eval(knots, coeffs, t, degree: int = 3, derivative: int = 0) -> float:
    """The B-spline (or its ``derivative``-th derivative) at t (seconds), by de Boor.

    knots: (n + degree + 1,) non-decreasing; coeffs: (n,). Right-continuous at knots; at the
    end of the base interval [knots[degree], knots[n]] (the last knot for clamped knots) the
    left limit. Outside the base interval the end polynomial pieces continue (as scipy's
    ``BSpline(..., extrapolate=True)``); held / linear extrapolation is the F-curve's job."""
    knots, coeffs, p = _check_bspline(knots, coeffs, degree)
    t = _finite(t, "t")
    if isinstance(derivative, bool) or int(derivative) != derivative or derivative < 0:
        raise ValueError(f"derivative must be an integer >= 0, got {derivative!r}")
    return _eval_span(knots, coeffs, p, _span(knots, p, len(coeffs), t, False), t, int(derivative))


# ---- keyframes -------------------------------------------------------------------------------
def bspline_to_keyframes(knots, coeffs, *, fps: float, start_frame: float = 0.0, degree: int = 3,
                         extrapolation: str = "held") -> Keyframes:
    """Blender keyframes equal to the clamped B-spline (knots in seconds, degree 1 to 3).

    One key per distinct knot (breakpoint) at ``frame = start_frame + t * fps`` with the
    curve's value there and FREE handles a third of the adjacent interval away, along the
    left / right derivative; the end keys' outer handles follow the end derivatives (what
    Blender's LINEAR extrapolation reads). ``extrapolation``: the curve's "held" / "linear"
    -> ``Keyframes.extrapolation`` "CONSTANT" / "LINEAR".

    Raises ValueError for bad input: wrong lengths, NaN, decreasing or unclamped knots, or an
    interior knot of multiplicity degree + 1 (the curve jumps there; an F-curve cannot)."""
    knots, coeffs, p = _check_bspline(knots, coeffs, degree)
    fps = _finite(fps, "fps")
    start_frame = _finite(start_frame, "start_frame")
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    if not 1 <= p <= 3:
        raise ValueError(f"only degrees 1 to 3 have a continuous cubic Bezier form, got degree {p}")
    if extrapolation not in EXTRAPOLATION_TO_BLENDER:
        raise ValueError(f"extrapolation must be one of {tuple(EXTRAPOLATION_TO_BLENDER)}, got {extrapolation!r}")
    n = len(coeffs)
    # distinct breakpoints with their multiplicities
    breaks, mult = [], []
    for k in knots:
        if breaks and k == breaks[-1]:
            mult[-1] += 1
        else:
            breaks.append(k)
            mult.append(1)
    if mult[0] != p + 1 or mult[-1] != p + 1:
        raise ValueError(f"knots must be clamped: the first and last {p + 1} knots equal (and no more); "
                         f"the start knot {breaks[0]} appears {mult[0]} times, the end knot {breaks[-1]} {mult[-1]}")
    for b, m in zip(breaks[1:-1], mult[1:-1]):
        if m > p:
            raise ValueError(f"interior knot {b} appears {m} times (at most {p} for degree {p}): the curve "
                             "jumps there, which an F-curve cannot represent")
    frames = [start_frame + b * fps for b in breaks]
    last = len(breaks) - 1
    keys = Keyframes(extrapolation=EXTRAPOLATION_TO_BLENDER[extrapolation])
    for i, b in enumerate(breaks):
        right = _span(knots, p, n, b, False)
        left = _span(knots, p, n, b, True)
        value = _eval_span(knots, coeffs, p, right if i < last else left, b, 0)
        d_right = _eval_span(knots, coeffs, p, right, b, 1) if i < last else None
        d_left = _eval_span(knots, coeffs, p, left, b, 1) if i > 0 else None
        # handle offsets: a third of the adjacent interval, in frames (x) and seconds (slope)
        if i > 0:
            hl_x, hl_t, hl_d = (frames[i] - frames[i - 1]) / 3.0, (b - breaks[i - 1]) / 3.0, d_left
        else:
            hl_x, hl_t, hl_d = (frames[1] - frames[0]) / 3.0, (breaks[1] - b) / 3.0, d_right
        if i < last:
            hr_x, hr_t, hr_d = (frames[i + 1] - frames[i]) / 3.0, (breaks[i + 1] - b) / 3.0, d_right
        else:
            hr_x, hr_t, hr_d = hl_x, hl_t, d_left
        keys.append(Keyframe(
            frame=frames[i], value=value,
            handle_left=(frames[i] - hl_x, value - hl_d * hl_t),
            handle_right=(frames[i] + hr_x, value + hr_d * hr_t),
        ))
    return keys


# ---- F-curve evaluation ----------------------------------------------------------------------
def _key_fields(key, i):
    """(frame, value, handle_left, handle_right, interpolation) of a Keyframe or a mapping."""
    if isinstance(key, Mapping):
        try:
            f, v, hl, hr = key["frame"], key["value"], key["handle_left"], key["handle_right"]
        except KeyError as exc:
            raise ValueError(f"keyframe {i} has no {exc.args[0]!r}") from None
        ipo = key.get("interpolation", "BEZIER")
    else:
        f, v, hl, hr, ipo = key.frame, key.value, key.handle_left, key.handle_right, \
            getattr(key, "interpolation", "BEZIER")
    try:
        hl = (_finite(hl[0], f"keyframe {i} handle_left x"), _finite(hl[1], f"keyframe {i} handle_left y"))
        hr = (_finite(hr[0], f"keyframe {i} handle_right x"), _finite(hr[1], f"keyframe {i} handle_right y"))
    except (TypeError, IndexError):
        raise ValueError(f"keyframe {i} handles must be (frame, value) pairs") from None
    return _finite(f, f"keyframe {i} frame"), _finite(v, f"keyframe {i} value"), hl, hr, str(ipo)


def _correct_bezpart(v1, v2, v3, v4):
    """Blender's BKE_fcurve_correct_bezpart: a handle longer in x than the segment is shortened
    (along itself) to the segment's length. Returns the corrected (v2, v3)."""
    length = v4[0] - v1[0]
    h1 = (v1[0] - v2[0], v1[1] - v2[1])
    h2 = (v4[0] - v3[0], v4[1] - v3[1])
    len1, len2 = abs(h1[0]), abs(h2[0])
    if len1 + len2 == 0.0:
        return v2, v3
    if len1 > length:
        fac = length / len1
        v2 = (v1[0] - fac * h1[0], v1[1] - fac * h1[1])
    if len2 > length:
        fac = length / len2
        v3 = (v4[0] - fac * h2[0], v4[1] - fac * h2[1])
    return v2, v3


def _bezier(p0, p1, p2, p3, u):
    s = 1.0 - u
    return s * s * s * p0 + 3.0 * s * s * u * p1 + 3.0 * s * u * u * p2 + u * u * u * p3


def _bezier_d(p0, p1, p2, p3, u):
    s = 1.0 - u
    return 3.0 * (s * s * (p1 - p0) + 2.0 * s * u * (p2 - p1) + u * u * (p3 - p2))


def _solve_x(x0, x1, x2, x3, x):
    """The first u in [0, 1] with Bezier x(u) = x: split [0, 1] where x(u) turns, then
    safeguarded Newton (bisection fallback) on the first piece bracketing x."""
    # x'(u) / 3 = a u^2 + b u + c
    a = (x1 - x0) - 2.0 * (x2 - x1) + (x3 - x2)
    b = 2.0 * ((x2 - x1) - (x1 - x0))
    c = x1 - x0
    turns = []
    if a != 0.0:
        disc = b * b - 4.0 * a * c
        if disc >= 0.0:
            r = math.sqrt(disc)
            q = -0.5 * (b + math.copysign(r, b))
            turns = [q / a] + ([c / q] if q != 0.0 else [])
    elif b != 0.0:
        turns = [-c / b]
    cuts = [0.0] + sorted(u for u in turns if 0.0 < u < 1.0) + [1.0]
    for lo, hi in zip(cuts[:-1], cuts[1:]):
        f_lo = _bezier(x0, x1, x2, x3, lo) - x
        f_hi = _bezier(x0, x1, x2, x3, hi) - x
        if f_lo == 0.0:
            return lo
        if f_hi == 0.0:
            return hi
        if (f_lo < 0.0) == (f_hi < 0.0):
            continue
        u = lo - f_lo * (hi - lo) / (f_hi - f_lo)  # secant start: exact when x(u) is linear
        for _ in range(200):
            f = _bezier(x0, x1, x2, x3, u) - x
            if f == 0.0:
                return u
            if (f < 0.0) == (f_lo < 0.0):
                lo, f_lo = u, f
            else:
                hi = u
            d = _bezier_d(x0, x1, x2, x3, u)
            nxt = u - f / d if d != 0.0 else 0.5 * (lo + hi)
            if not lo < nxt < hi:
                nxt = 0.5 * (lo + hi)
            if abs(nxt - u) <= 4e-16 * max(1.0, abs(u)) or hi - lo <= 4e-16:
                return nxt
            u = nxt
        return u
    # no crossing (x outside the segment's x range): the nearer end
    return 0.0 if abs(x0 - x) <= abs(x3 - x) else 1.0


def bezier_keyframes_eval(keys, frame, extrapolation: str | None = None):
    """The value at ``frame`` (frames; a list of values for a sequence of frames) of a Blender
    F-curve with these keyframes, evaluated as Blender does: Bezier segments (handles shortened
    by Blender's correction, x(u) = frame solved for u for arbitrary handles), "LINEAR" /
    "CONSTANT" segment interpolation, and extrapolation (``extrapolation``, else ``keys.extrapolation``, else "CONSTANT"): "LINEAR"
    continues along the first key's left / the last key's right handle.

    keys: Keyframe tuples or mappings with frame, value, handle_left, handle_right
    (optional interpolation), in strictly increasing frame order."""
    if extrapolation is None:
        extrapolation = getattr(keys, "extrapolation", "CONSTANT")
    if extrapolation not in ("CONSTANT", "LINEAR"):
        raise ValueError(f"extrapolation must be 'CONSTANT' or 'LINEAR', got {extrapolation!r}")
    keys = [_key_fields(k, i) for i, k in enumerate(keys)]
    if not keys:
        raise ValueError("no keyframes")
    frames = [k[0] for k in keys]
    for i in range(1, len(frames)):
        if not frames[i] > frames[i - 1]:
            raise ValueError(f"keyframe frames must increase: keyframe {i} at {frames[i]} after {frames[i - 1]}")
    if isinstance(frame, (str, bytes)) or not hasattr(frame, "__iter__"):
        return _eval_keys(keys, frames, _finite(frame, "frame"), extrapolation)
    return [_eval_keys(keys, frames, _finite(f, f"frame {i}"), extrapolation) for i, f in enumerate(frame)]


def _eval_keys(keys, frames, frame, extrapolation):
    first, last = keys[0], keys[-1]
    if frame <= first[0] or frame >= last[0]:
        # as Blender: the end key's own interpolation decides how its side is continued
        end, handle = (first, first[2]) if frame <= first[0] else (last, last[3])
        if extrapolation == "CONSTANT" or end[4] == "CONSTANT" or frame == end[0]:
            return end[1]
        if end[4] == "LINEAR":
            if len(keys) == 1:
                return end[1]
            other = keys[1] if end is first else keys[-2]
            return end[1] + (other[1] - end[1]) / (other[0] - end[0]) * (frame - end[0])
        dx = end[0] - handle[0]
        if dx == 0.0:
            return end[1]
        return end[1] - (end[1] - handle[1]) / dx * (end[0] - frame)
    i = bisect.bisect_right(frames, frame) - 1
    (f0, v0, _, hr, ipo), (f1, v1, hl, _, _) = keys[i], keys[i + 1]
    if frame == f0:
        return v0
    if ipo == "CONSTANT":
        return v0
    if ipo == "LINEAR":
        return v0 + (v1 - v0) * (frame - f0) / (f1 - f0)
    if ipo != "BEZIER":
        raise ValueError(f"keyframe {i} interpolation {ipo!r} is not BEZIER, LINEAR or CONSTANT")
    p1, p2 = _correct_bezpart((f0, v0), hr, hl, (f1, v1))
    u = _solve_x(f0, p1[0], p2[0], f1, frame)
    return _bezier(v0, p1[1], p2[1], v1, u)


# ---- result.json -----------------------------------------------------------------------------
def curves_from_result_json(doc) -> dict:
    """{DOF name: DofCurve (knots, coeffs)} from a result.json document (format
    "handretarget.result", version 1; the parsed dict, or its JSON text as str / bytes).
    Knots in seconds; each DofCurve also carries ``degree`` and ``extrapolation``.

    Raises ValueError naming the field when the document is not such a result, has no
    curves (the fit pass was off: use the baked animation) or a curve is malformed."""
    if isinstance(doc, (bytes, bytearray)):
        doc = doc.decode("utf-8")
    if isinstance(doc, str):
        try:
            doc = json.loads(doc)
        except ValueError as exc:
            raise ValueError(f"result.json is not valid JSON: {exc}") from None
    if not isinstance(doc, Mapping) or doc.get("format") != RESULT_FORMAT:
        raise ValueError(f"not a {RESULT_FORMAT} document (field 'format')")
    if doc.get("version") not in RESULT_VERSIONS:
        raise ValueError(f"unsupported result version {doc.get('version')!r} (field 'version'; "
                         f"this reader knows {', '.join(map(str, RESULT_VERSIONS))})")
    names, curves = doc.get("dof_names"), doc.get("curves")
    if not isinstance(names, list):
        raise ValueError("result has no list 'dof_names'")
    if curves is None:
        raise ValueError("result has no curves (field 'curves' is null: the fit pass was off; "
                         "use the baked animation)")
    if not isinstance(curves, list) or len(curves) != len(names):
        raise ValueError(f"field 'curves' must be a list of {len(names)} curves, one per DOF")
    out = {}
    for i, (name, c) in enumerate(zip(names, curves)):
        where = f"curves[{i}] (DOF {name!r})"
        if not isinstance(c, Mapping) or "knots" not in c or "coefficients" not in c:
            raise ValueError(f"{where} needs 'knots' and 'coefficients'")
        extrapolation = c.get("extrapolation", "held")
        if extrapolation not in EXTRAPOLATION_TO_BLENDER:
            raise ValueError(f"{where}: extrapolation {extrapolation!r} is not one of "
                             f"{tuple(EXTRAPOLATION_TO_BLENDER)}")
        try:
            knots, coeffs, p = _check_bspline(c["knots"] or [], c["coefficients"] or [], c.get("degree", 3))
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
        out[str(name)] = DofCurve(knots, coeffs, p, extrapolation)
    return out
