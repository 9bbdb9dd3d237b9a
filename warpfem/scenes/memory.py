"""What ``warpfem describe`` reports before anything is built: quadrature points per element, the
cell types of a volume file, and the device-memory estimate."""

from __future__ import annotations

import numpy as np

__all__ = ["quadrature_points_per_element", "estimate_device_memory"]


def quadrature_points_per_element(element_type, volumetric_integration="full"):
    """Quadrature points per element the simulator allocates (stiffness rule, + 1 with
    selective reduced integration on hex8)."""
    from warpfem.mesh.element_types import gauss_rule

    q = len(gauss_rule(element_type)[1])
    return q + (1 if volumetric_integration == "reduced" else 0)


def _volume_cell_types(path) -> dict:
    """{meshio cell type: count} of a mesh file (all cell blocks)."""
    import meshio

    try:
        mesh = meshio.read(path)
    except Exception as e:  # meshio raises many types
        from warpfem.mesh import MeshError

        raise MeshError(f"{path}: meshio could not read the file: {type(e).__name__}: {e}") from e
    out = {}
    for c in mesh.cells:
        if len(c.data):
            out[c.type] = out.get(c.type, 0) + len(c.data)
    return out


def _block_nnz(elements, k, n):
    e = np.asarray(elements, dtype=np.int64).reshape(-1, k)
    pairs = (e[:, :, None] * n + e[:, None, :]).ravel()
    return int(np.unique(pairs).size)


def estimate_device_memory(*, num_vertices, num_elements, nodes_per_element, num_points, block_nnz,
                           precision="float64", surface_points=0, stiffness_damping=False,
                           weights_per_point=4) -> int:
    """Estimated device bytes of a built scene (arrays the simulator and skinner allocate).

    Counts: quadrature data, connectivity, ~16 vec3 work vectors (state, Newton, PCG), the mass and
    Hessian block matrices (+1 for stiffness damping) with their index arrays, the block-Jacobi
    inverse diagonal, and the skinning weights/ids/output. An estimate, not a measurement.
    """
    s = 4 if precision == "float32" else 8
    n, m, k, q = num_vertices, num_elements, nodes_per_element, num_points
    b = 0
    b += m * k * 4 + q * (4 + s + k * 3 * s)           # connectivity, qp element/weight/dNdX
    b += 16 * n * 3 * s                                # vectors
    nmat = 3 if stiffness_damping else 2
    b += nmat * block_nnz * 9 * s + block_nnz * 4 + (n + 1) * 4 + m * k * k * 4  # values, cols, offsets, block index
    b += n * 9 * s + q * s                             # PCG diagonal, per-qp energy
    b += surface_points * (weights_per_point * (4 + s) + 3 * s)  # skinning: ids, weights, output
    return int(b)


def _fmt_bytes(b):
    for unit in ("B", "KiB", "MiB", "GiB"):
        if b < 1024 or unit == "GiB":
            return f"{b:.1f} {unit}" if unit != "B" else f"{b} B"
        b /= 1024.0
