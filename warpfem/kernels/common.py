"""Warp funcs shared by the quadrature-point kernel modules (``fem.py``, ``warping.py``).

The prologue of every quadrature-point kernel: gather the element's nodes and form the
deformation gradient from displacements,

    F = I + sum_a (x_a - X_a) (dN_a/dX)^T,

with the flat connectivity ``elements`` of stride ``k`` (nodes per element) and the per-point
shape-function gradients ``qp_dNdX[q * k + a]`` (docs/design.md). For Tet4 (k = 4, one point per
element, q = e) this is F = Ds Dm^-1 exactly. Generic over float32/float64.
``point_deformation_gradient(x, points, q)`` is the same for a ``QuadraturePoints`` struct
(``warpfem.kernels.structs``), the form the kernels of ``fem.py`` use.
"""

from __future__ import annotations

from typing import Any

import warp as wp

__all__ = ["qp_deformation_gradient", "point_deformation_gradient"]


@wp.func
def qp_deformation_gradient(
    x: wp.array(dtype=Any),
    X: wp.array(dtype=Any),
    elements: wp.array(dtype=wp.int32),
    k: int,
    e: int,
    q: int,
    qp_dNdX: wp.array(dtype=Any),
):
    """F = I + sum_a (x_a - X_a) (dN_a/dX)^T at point q of element e (k nodes per element).

    From displacements, so float32 keeps small strains accurate wherever the body sits
    (sum_a X_a dN_a^T = I exactly for any complete element)."""
    n0 = elements[e * k]
    g0 = qp_dNdX[q * k]
    F = wp.outer(x[n0] - X[n0], g0)
    for a in range(1, k):
        n = elements[e * k + a]
        F += wp.outer(x[n] - X[n], qp_dNdX[q * k + a])
    one = type(g0[0])(1.0)
    return F + wp.diag(type(g0)(one, one, one))


@wp.func
def point_deformation_gradient(x: wp.array(dtype=Any), points: Any, q: int):
    """F at point q of a ``QuadraturePoints32/64`` set (``warpfem.kernels.structs``): the prologue
    of the quadrature-point kernels, ``qp_deformation_gradient`` with the set's arrays."""
    return qp_deformation_gradient(x, points.X, points.elements, points.k, points.element[q], q, points.dNdX)
