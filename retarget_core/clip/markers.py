"""Source virtual markers.

MANO: the 25 single-point markers the paper's own runs place on fixed vertex ids of the right
MANO hand (778 vertices). Generated hands: the same names placed by the hand's geometry (see
:func:`retarget_core.rig.anatomy.source_markers`)."""

from __future__ import annotations

#: Marker name -> MANO (right hand, 778 vertices) vertex id.
MANO_MARKERS: dict[str, int] = {
    "PinkyTip": 650,
    "PinkyMiddle": 633,
    "PinkyBase": 616,
    "RingTip": 533,
    "RingMiddle": 476,
    "RingBase": 291,
    "MiddleTip": 423,
    "MiddleMiddle": 405,
    "MiddleBase": 399,
    "IndexTip": 316,
    "IndexMiddle": 86,
    "IndexBase": 274,
    "ThumbTip": 731,
    "ThumbMiddle": 250,
    "ThumbBase": 89,
    "BackRing": 181,
    "BackIndex": 158,
    "WristRight": 79,
    "WristLeft": 92,
    "PinkyFingertip": 671,
    "RingFingertip": 554,
    "MiddleFingertip": 443,
    "IndexFingertip": 320,
    "ThumbFingertip": 744,
    "PalmRoot": 24,
}

MANO_N_VERTICES = 778
