"""Dense contact pairing (paper section "Dense Contact Pairing"): every labelled object contact
vertex is traced along its normal to the source hand, giving a hand surface point paired 1:1
with it; see :mod:`retarget_core.pairing.dense`."""

from .dense import (
    DISCARD_REASONS,
    PAIRS_FORMAT,
    PAIRS_VERSION,
    ContactPairs,
    FramePairs,
    load_contact_pairs,
    pair_contacts,
)

__all__ = [
    "DISCARD_REASONS",
    "PAIRS_FORMAT",
    "PAIRS_VERSION",
    "ContactPairs",
    "FramePairs",
    "load_contact_pairs",
    "pair_contacts",
]
