"""Saint Venant-Kirchhoff material.

    E   = (F^T F - I)/2                      (Green-Lagrange strain)
    psi = mu E:E + lambda/2 tr(E)^2
    P   = F (2 mu E + lambda tr(E) I)         (= F S, S the second Piola-Kirchhoff stress)

mu = E/(2(1+nu)), lambda = E nu/((1+nu)(1-2nu)) (Young's modulus E, not the strain).
Rotation invariant, but it softens under compression: uniaxially, P11 = E a (a^2 - 1)/2 peaks
in magnitude at a = 1/sqrt3 and vanishes at a = 0, so elements can collapse and invert.

In the signed singular values s (Smith, de Goes, Kim 2019, sec. 7.2 / Kim & Eberle 2020
"Dynamic deformables", ch. 7), with trE = (s0^2 + s1^2 + s2^2 - 3)/2:

    Psi        = mu/4 sum_i (s_i^2 - 1)^2 + lambda/2 trE^2
    Psi_i      = (mu (s_i^2 - 1) + lambda trE) s_i
    Psi_ii     = mu (3 s_i^2 - 1) + lambda (trE + s_i^2)          (scaling block A)
    Psi_ij     = lambda s_i s_j                                     (i != j)
    flip_k     = (Psi_i - Psi_j)/(s_i - s_j) = mu (s_i^2 + s_i s_j + s_j^2 - 1) + lambda trE
    twist_k    = (Psi_i + Psi_j)/(s_i + s_j) = mu (s_i^2 - s_i s_j + s_j^2 - 1) + lambda trE
"""

from typing import Any

import warp as wp

from .base import Material
from .registry import register_material
from .eigensystem import pair_axes

__all__ = ["StVenantKirchhoff", "stvk_psi", "stvk_pk1", "stvk_eigen"]


@wp.func
def stvk_psi(F: Any, mu: Any, lam: Any):
    """psi = mu E:E + lambda/2 tr(E)^2, E = (F^T F - I)/2."""
    E = F.dtype(0.5) * (wp.transpose(F) * F - wp.identity(n=3, dtype=F.dtype))
    tr = wp.trace(E)
    return mu * wp.ddot(E, E) + F.dtype(0.5) * lam * tr * tr


@wp.func
def stvk_pk1(F: Any, mu: Any, lam: Any):
    """P = F (2 mu E + lambda tr(E) I)."""
    I = wp.identity(n=3, dtype=F.dtype)
    E = F.dtype(0.5) * (wp.transpose(F) * F - I)
    return F * (F.dtype(2.0) * mu * E + lam * wp.trace(E) * I)


@wp.func
def stvk_eigen(s: Any, mu: Any, lam: Any):
    """(A, twist, flip) of the StVK Hessian at signed singular values s (see module docstring)."""
    one = type(mu)(1.0)
    trE = type(mu)(0.5) * (wp.dot(s, s) - type(mu)(3.0))
    A = wp.outer(s, s) * lam
    for i in range(3):
        A[i, i] = mu * (type(mu)(3.0) * s[i] * s[i] - one) + lam * (trE + s[i] * s[i])
    twist = wp.vector(length=3, dtype=type(mu))
    flip = wp.vector(length=3, dtype=type(mu))
    for k in range(3):
        i, j = pair_axes(k)
        q = s[i] * s[i] + s[j] * s[j] - one
        p = s[i] * s[j]
        flip[k] = mu * (q + p) + lam * trE
        twist[k] = mu * (q - p) + lam * trE
    return A, twist, flip


@register_material("stvk", kind=1, psi=stvk_psi, pk1=stvk_pk1, eigen=stvk_eigen)
class StVenantKirchhoff(Material):
    """Saint Venant-Kirchhoff: psi = mu E:E + lambda/2 tr(E)^2, E = (F^T F - I)/2."""

