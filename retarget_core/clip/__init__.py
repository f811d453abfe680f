"""Source clips: the clip format, the GRAB importer, the demonstration generator and the
source virtual markers (pipeline input)."""

from .format import CLIP_FORMAT, CLIP_VERSION, RIGHT_HAND_CONTACT_CODES, Clip, load_clip

__all__ = ["CLIP_FORMAT", "CLIP_VERSION", "RIGHT_HAND_CONTACT_CODES", "Clip", "load_clip"]
