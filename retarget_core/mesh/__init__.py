"""Surface utilities shared by all pipeline stages."""

from .topology import MeshTopologyReport, check_closed_manifold, require_closed_manifold
from .surface_points import SurfacePoints

__all__ = ["MeshTopologyReport", "check_closed_manifold", "require_closed_manifold", "SurfacePoints"]
