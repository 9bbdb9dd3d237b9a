"""Structured box meshes: each hex cell split into 6 tets around the cell diagonal 0-6."""

from __future__ import annotations

import numbers

import numpy as np

from .element_types.base import HexElement
from .tetmesh import MeshError, TetMesh

__all__ = ["box_tet_mesh", "HEX_CORNERS", "HEX_TO_TETS"]

#: Unit-cell corner offsets (i, j, k) in the reference order 0..7.
HEX_CORNERS = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]],
    dtype=np.int64,
)
#: The 6 tets of a cell around the diagonal 0-6 (all positively oriented with HEX_CORNERS): the hex
#: element types' corner sub-tets.
HEX_TO_TETS = HexElement.corner_tets


def box_tet_mesh(*, size=(1.0, 1.0, 1.0), cells=(1, 1, 1), origin=(0.0, 0.0, 0.0), name=None):
    """Tet4 mesh of the box ``origin + [0, size]`` with ``cells = (nx, ny, nz)`` hex cells.

    Vertex (i, j, k) of the grid has index ``i + (nx+1) * (j + (ny+1) * k)`` and position
    ``origin + (i, j, k) * size / cells``. Cell (ci, cj, ck) gives tets
    ``6 * (ci + nx * (cj + ny * ck)) + s`` for the six split tets s of ``HEX_TO_TETS``.
    """
    cells = tuple(cells)
    if len(cells) != 3 or not all(
        isinstance(c, numbers.Integral) and not isinstance(c, bool) for c in cells
    ):
        raise MeshError(f"cells must be three integers, got {cells!r}")
    if min(cells) < 1:
        raise MeshError(f"cells must be >= 1, got {cells!r}")
    size = np.asarray(size, dtype=np.float64)
    origin = np.asarray(origin, dtype=np.float64)
    if size.shape != (3,) or not np.all(np.isfinite(size)) or not np.all(size > 0):
        raise MeshError(f"size must be three finite values > 0, got {size.tolist()}")
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise MeshError(f"origin must be three finite values, got {origin.tolist()}")

    nx, ny, nz = (int(c) for c in cells)
    k, j, i = np.meshgrid(np.arange(nz + 1), np.arange(ny + 1), np.arange(nx + 1), indexing="ij")
    ijk = np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1)  # index = i + (nx+1)(j + (ny+1)k)
    h = size / np.array([nx, ny, nz], dtype=np.float64)
    vertices = origin + ijk * h
    # Exact far faces (avoid i*h rounding away from origin + size).
    for d, n in enumerate((nx, ny, nz)):
        vertices[ijk[:, d] == n, d] = origin[d] + size[d]

    ck, cj, ci = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    base = np.stack([ci.ravel(), cj.ravel(), ck.ravel()], axis=1)  # (ncells, 3)
    corner = base[:, None, :] + HEX_CORNERS[None, :, :]  # (ncells, 8, 3)
    cid = corner[..., 0] + (nx + 1) * (corner[..., 1] + (ny + 1) * corner[..., 2])
    tets = cid[:, HEX_TO_TETS].reshape(-1, 4)
    return TetMesh(vertices, tets, reorient=True, name=name)
