"""The demo hand library: the paper's cast of target hands, built with the procedural generator.

DOF counts follow the paper's table where it gives them (each including the 6-DOF root):
human and witch 54 (forearm root, 3-DOF wrist, 15 finger joints of 3 DOFs), alien 42
(forearm root, wrist, a 3-joint thumb and two 4-joint fingers), prosthetic 26 (wrist root;
per finger a 2-DOF knuckle and two 1-DOF joints; the 1-DOF-knuckle variant has 21), and the
Allegro-like robot hand 22 (wrist root, four fingers of four 1-DOF revolute joints).
"""

from __future__ import annotations

from dataclasses import replace

from .handgen import FingerSpec, HandSpec, JointSpec, PalmSpec, build_hand
from .model import Rig

# Limits in degrees.
_WRIST = JointSpec(("abduct", "flex", "twist"), {"abduct": (-25, 35), "flex": (-75, 75), "twist": (-30, 30)})
_MCP = JointSpec(("abduct", "flex", "twist"), {"abduct": (-25, 25), "flex": (-25, 95), "twist": (-20, 20)})
_PIP = JointSpec(("abduct", "flex", "twist"), {"abduct": (-10, 10), "flex": (-5, 110), "twist": (-10, 10)})
_DIP = JointSpec(("abduct", "flex", "twist"), {"abduct": (-10, 10), "flex": (-10, 90), "twist": (-10, 10)})
_CMC = JointSpec(("abduct", "flex", "twist"), {"abduct": (-40, 40), "flex": (-30, 65), "twist": (-45, 45)})
_THUMB_MCP = JointSpec(("abduct", "flex", "twist"), {"abduct": (-15, 15), "flex": (-15, 75), "twist": (-20, 20)})
_THUMB_IP = JointSpec(("abduct", "flex", "twist"), {"abduct": (-10, 10), "flex": (-15, 90), "twist": (-10, 10)})

#: The witch's thumb over the source's, from the paper's table of lambda coefficients (witch:
#: lambda_A 1.15 on the thumb, 1.55 on the other fingers); the README's motion synthesis
#: figures show what a 1.55x thumb does to the contact distance.
WITCH_THUMB_LENGTH_SCALE = 1.15

# Thumb: rests out to the -X side and a little below the palm, curls across the palm.
_THUMB_DIRECTION = (-0.72, 0.62, -0.30)
_THUMB_CURL = (0.75, 0.15, -0.65)


def _human_fingers(length_scale=1.0, girth_scale=1.0, spread=1.0, palm_width=0.084, thumb_length_scale=None):
    """Five fingers of a human-like right hand (MANO-like proportions at scale 1); the thumb's
    links scale by ``thumb_length_scale`` (default: ``length_scale``)."""
    s, g = length_scale, girth_scale
    ts = s if thumb_length_scale is None else thumb_length_scale
    half = palm_width / 2
    xs = (-0.36 * half * 2, -0.12 * half * 2, 0.12 * half * 2, 0.35 * half * 2)
    ys = (0.090, 0.093, 0.089, 0.081)
    angles = (-7.0, 0.0, 7.0, 14.0)
    lengths = ((0.040, 0.024, 0.020), (0.045, 0.028, 0.021), (0.042, 0.027, 0.021), (0.033, 0.020, 0.019))
    radii = ((0.0088, 0.0080, 0.0071, 0.0060), (0.0090, 0.0082, 0.0073, 0.0062),
             (0.0085, 0.0077, 0.0069, 0.0058), (0.0078, 0.0070, 0.0062, 0.0053))
    import math

    fingers = [
        FingerSpec(
            "thumb",
            base=(-0.020 * palm_width / 0.084, 0.020, -0.006),
            direction=_THUMB_DIRECTION,
            lengths=tuple(l * ts for l in (0.042, 0.032, 0.028)),
            radii=tuple(r * g for r in (0.0125, 0.0102, 0.0092, 0.0078)),
            joints=(_CMC, _THUMB_MCP, _THUMB_IP),
            curl_toward=_THUMB_CURL,
        )
    ]
    for name, x, y, angle, lens, rads in zip(("index", "middle", "ring", "pinky"), xs, ys, angles, lengths, radii):
        a = math.radians(angle * spread)
        fingers.append(
            FingerSpec(
                name,
                base=(x, y, 0.0),
                direction=(math.sin(a), math.cos(a), 0.0),
                lengths=tuple(l * s for l in lens),
                radii=tuple(r * g for r in rads),
                joints=(_MCP, _PIP, _DIP),
            )
        )
    return tuple(fingers)


def source_human_spec(resolution: float = 0.002) -> HandSpec:
    """The source human hand (MANO-like proportions) that the demo clips are made with."""
    return HandSpec(
        name="source_human",
        palm=PalmSpec(width=0.084, length=0.094, thickness=0.026, start=-0.004, rounding=0.011),
        fingers=_human_fingers(),
        wrist=_WRIST,
        forearm_length=0.03,
        forearm_radius=0.018,
        resolution=resolution,
        metadata={"kind": "human", "root": "forearm"},
    )


def human_alt_spec(resolution: float = 0.002) -> HandSpec:
    """A second human hand: broader palm, shorter and thicker fingers."""
    return HandSpec(
        name="human_alt",
        palm=PalmSpec(width=0.094, length=0.088, thickness=0.030, start=-0.004, rounding=0.012),
        fingers=_human_fingers(length_scale=0.88, girth_scale=1.12, spread=1.1, palm_width=0.094),
        wrist=_WRIST,
        forearm_length=0.03,
        forearm_radius=0.020,
        resolution=resolution,
        metadata={"kind": "human", "root": "forearm"},
    )


def witch_spec(resolution: float = 0.002) -> HandSpec:
    """Long thin fingers on a narrow palm (the paper's witch hand). Finger lengths follow the
    paper's lambda_A for its witch ("a satisfactory lambda_A extended the axis along the full
    length of the target finger"): 1.55 on index to pinky, 1.15 on the thumb."""
    return HandSpec(
        name="witch",
        palm=PalmSpec(width=0.078, length=0.100, thickness=0.022, start=-0.004, rounding=0.009),
        fingers=_human_fingers(length_scale=1.55, girth_scale=0.78, spread=1.2, palm_width=0.078,
                               thumb_length_scale=WITCH_THUMB_LENGTH_SCALE),
        wrist=_WRIST,
        forearm_length=0.03,
        forearm_radius=0.016,
        resolution=resolution,
        metadata={"kind": "human-like", "root": "forearm"},
    )


def alien_spec(resolution: float = 0.002) -> HandSpec:
    """Three thick fingers: a 3-joint thumb and two 4-joint fingers (42 DOFs)."""
    import math

    finger_radii = (0.0135, 0.0125, 0.0115, 0.0105, 0.0092)
    fingers = [
        FingerSpec(
            "thumb",
            base=(-0.024, 0.022, -0.008),
            direction=_THUMB_DIRECTION,
            lengths=(0.046, 0.036, 0.030),
            radii=(0.0155, 0.0140, 0.0128, 0.0112),
            joints=(_CMC, _THUMB_MCP, _THUMB_IP),
            curl_toward=_THUMB_CURL,
        )
    ]
    for name, x, angle in (("index", -0.017, -6.0), ("middle", 0.019, 8.0)):
        a = math.radians(angle)
        fingers.append(
            FingerSpec(
                name,
                base=(x, 0.092, 0.0),
                direction=(math.sin(a), math.cos(a), 0.0),
                lengths=(0.034, 0.028, 0.024, 0.020),
                radii=finger_radii,
                joints=(_MCP, _PIP, _PIP, _DIP),
            )
        )
    return HandSpec(
        name="alien",
        palm=PalmSpec(width=0.086, length=0.096, thickness=0.034, start=-0.004, rounding=0.012),
        fingers=tuple(fingers),
        wrist=_WRIST,
        forearm_length=0.03,
        forearm_radius=0.022,
        resolution=resolution,
        metadata={"kind": "creature", "root": "forearm"},
    )


def _flex(lo, hi):
    return JointSpec(("flex",), {"flex": (lo, hi)})


def prosthetic_spec(knuckle_dofs: int = 2, resolution: float = 0.002) -> HandSpec:
    """A thin prosthetic hand; its root is the wrist. ``knuckle_dofs`` = 2 gives abduction and
    flexion at each knuckle (26 DOFs), 1 gives flexion only (21 DOFs)."""
    if knuckle_dofs == 2:
        knuckle = JointSpec(("abduct", "flex"), {"abduct": (-20, 20), "flex": (-10, 90)})
    elif knuckle_dofs == 1:
        knuckle = _flex(-10, 90)
    else:
        raise ValueError("knuckle_dofs must be 1 or 2")
    fingers = []
    for f in _human_fingers(length_scale=0.92, girth_scale=0.82, spread=1.0, palm_width=0.080):
        fingers.append(replace(f, joints=(knuckle, _flex(-5, 100), _flex(-5, 80))))
    return HandSpec(
        name=f"prosthetic_{knuckle_dofs}dof",
        palm=PalmSpec(width=0.080, length=0.090, thickness=0.022, start=0.004, rounding=0.006),
        fingers=tuple(fingers),
        wrist=None,
        forearm_length=0.0,
        style="robot",
        blend=0.003,
        resolution=resolution,
        metadata={"kind": "prosthetic", "root": "wrist", "knuckle_dofs": knuckle_dofs},
    )


def robot4_spec(resolution: float = 0.002) -> HandSpec:
    """A large four-fingered robot-like hand with 1-DOF revolute joints (Allegro-like, 22 DOFs)."""
    import math

    abduct = JointSpec(("abduct",), {"abduct": (-27, 27)})
    finger_joints = (abduct, _flex(-17, 92), _flex(-17, 98), _flex(-13, 95))
    fingers = []
    for name, x, angle in (("index", -0.0455, -4.0), ("middle", 0.0, 0.0), ("ring", 0.0455, 4.0)):
        a = math.radians(angle)
        fingers.append(
            FingerSpec(
                name,
                base=(x, 0.100, 0.0),
                direction=(math.sin(a), math.cos(a), 0.0),
                lengths=(0.016, 0.054, 0.038, 0.040),
                radii=(0.0140, 0.0140, 0.0140, 0.0140, 0.0140),
                joints=finger_joints,
            )
        )
    thumb_joints = (
        JointSpec(("twist",), {"twist": (-20, 80)}),
        JointSpec(("abduct",), {"abduct": (-60, 60)}),
        _flex(-10, 100),
        _flex(-10, 95),
    )
    fingers.insert(
        0,
        FingerSpec(
            "thumb",
            base=(-0.035, 0.020, -0.012),
            direction=(-0.80, 0.55, -0.25),
            lengths=(0.018, 0.028, 0.051, 0.046),
            radii=(0.0140, 0.0140, 0.0140, 0.0140, 0.0140),
            joints=thumb_joints,
            curl_toward=_THUMB_CURL,
        ),
    )
    return HandSpec(
        name="robot4",
        palm=PalmSpec(width=0.122, length=0.106, thickness=0.030, start=0.0, rounding=0.008),
        fingers=tuple(fingers),
        wrist=None,
        forearm_length=0.0,
        style="robot",
        blend=0.002,
        resolution=resolution,
        metadata={"kind": "robot", "root": "wrist"},
    )


#: name -> (spec factory, expected DOF count)
DEMO_HANDS = {
    "source_human": (source_human_spec, 54),
    "human_alt": (human_alt_spec, 54),
    "witch": (witch_spec, 54),
    "alien": (alien_spec, 42),
    "prosthetic_1dof": (lambda resolution=0.002: prosthetic_spec(1, resolution), 21),
    "prosthetic_2dof": (lambda resolution=0.002: prosthetic_spec(2, resolution), 26),
    "robot4": (robot4_spec, 22),
}


def demo_hand(name: str, resolution: float = 0.002) -> Rig:
    """Build one demo hand by name (see :data:`DEMO_HANDS`); ``resolution`` in metres."""
    if name not in DEMO_HANDS:
        raise KeyError(f"unknown demo hand {name!r}; known: {', '.join(DEMO_HANDS)}")
    factory, _ = DEMO_HANDS[name]
    return build_hand(factory(resolution=resolution))


def demo_library(resolution: float = 0.002) -> dict[str, Rig]:
    """Every demo hand, by name."""
    return {name: demo_hand(name, resolution) for name in DEMO_HANDS}
