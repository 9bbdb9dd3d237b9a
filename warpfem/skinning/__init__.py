"""Embedding a render surface in the volume mesh (barycentric / shape-function skinning), numpy and Warp."""

from .embedding import Embedding, barycentric_coordinates, embed_points, embed_points_in_mesh, point_tet_distance
from .skinner import SurfaceSkinner, resolve_precision
from .surface import SurfaceError, boundary_faces, load_surface, mesh_boundary_surface

__all__ = [
    "Embedding",
    "embed_points",
    "embed_points_in_mesh",
    "barycentric_coordinates",
    "point_tet_distance",
    "SurfaceSkinner",
    "resolve_precision",
    "boundary_faces",
    "mesh_boundary_surface",
    "load_surface",
    "SurfaceError",
]
