"""Vertex selections for boundary conditions."""

from __future__ import annotations

import numpy as np

__all__ = ["select_vertices_in_box"]


def select_vertices_in_box(vertices, box_min, box_max, *, tol=1e-9):
    """Indices (int64, sorted) of vertices with ``box_min - eps <= x <= box_max + eps``.

    ``vertices`` is an (n, 3) array or a mesh (its ``.vertices``). ``tol`` is relative:
    eps = tol * (bounding-box diagonal of the vertices, or 1 if that is 0). Bounds may be
    +-inf to leave an axis open, e.g. ``select_vertices_in_box(v, (-inf,)*3, (0, inf, inf))``.
    """
    x = np.asarray(getattr(vertices, "vertices", vertices), dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"vertices must have shape (n, 3), got {x.shape}")
    lo = np.broadcast_to(np.asarray(box_min, dtype=np.float64), (3,))
    hi = np.broadcast_to(np.asarray(box_max, dtype=np.float64), (3,))
    if np.isnan(lo).any() or np.isnan(hi).any() or (lo > hi).any():
        raise ValueError(f"invalid box: min {lo.tolist()} max {hi.tolist()}")
    if x.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    scale = float(np.linalg.norm(x.max(axis=0) - x.min(axis=0))) or 1.0
    eps = tol * scale
    inside = np.all((x >= lo - eps) & (x <= hi + eps), axis=1)
    return np.flatnonzero(inside).astype(np.int64)
