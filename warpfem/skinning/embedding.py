"""Embedding of render-surface points into a simulation mesh of any element type.

The point location itself (tet search, barycentric coordinates) is :mod:`warpfem.mesh.locate`;
this module picks the element-type path (reference coordinates by Newton on the isoparametric map,
:func:`warpfem.mesh.locate.embed_points_in_elements`, for elements other than the linear tet).
"""

from __future__ import annotations

import numpy as np

from warpfem.mesh.element_types import get_element
from warpfem.mesh.locate import (INSIDE_TOL, Embedding, barycentric_coordinates, embed_points, embed_points_in_elements,
                                 point_tet_distance)

__all__ = ["Embedding", "embed_points", "embed_points_in_mesh", "barycentric_coordinates", "point_tet_distance",
           "INSIDE_TOL"]


def embed_points_in_mesh(points, mesh) -> Embedding:
    """Embed points (p, 3) in a volume mesh of any element type (``warpfem.mesh.VolumeMesh``).

    Linear tets (Tet4): :func:`embed_points` (barycentric coordinates, k = 4). Tet10 / Hex8 / Hex27: the point's
    element and reference coordinates from :func:`warpfem.mesh.locate.embed_points_in_elements`
    (corner-tet search, then Newton on the isoparametric map), weights = the element's k shape
    functions there (k = 10, 8, 27), so x = sum_a N_a(xi) x_a reproduces every deformation the
    element represents (affine ones exactly). ``distances`` / ``outside`` come from the corner-tet
    search: the distance of an outside point to the mesh's straight-sided corner tets.
    """
    etype = mesh.element_type
    if get_element(etype).is_linear_tet:
        return embed_points(points, mesh.vertices, np.asarray(mesh.elements))
    corner = embed_points(points, mesh.vertices, mesh.corner_tets())
    ids, weights, elem = embed_points_in_elements(points, mesh, corner_embedding=corner)
    return Embedding(tet_index=np.asarray(elem, dtype=np.int64), vertex_ids=np.asarray(ids, dtype=np.int64),
                     weights=np.asarray(weights, dtype=np.float64), distances=corner.distances,
                     outside=corner.outside, num_vertices=int(mesh.num_vertices), element_type=etype)
