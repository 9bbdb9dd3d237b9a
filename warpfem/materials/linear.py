"""Linear (small-strain) isotropic elasticity.

    eps = sym(F - I) = (F + F^T)/2 - I
    psi = mu eps:eps + lambda/2 tr(eps)^2
    P   = 2 mu eps + lambda tr(eps) I

with the Lame parameters mu = E/(2(1+nu)), lambda = E nu/((1+nu)(1-2nu)). Not rotation
invariant: a rigid rotation gives P != 0 ("ghost" forces).

Hessian (constant) in the eigen form of Smith, de Goes, Kim 2019 with U = V = I:
twist modes 0 (the antisymmetric part of F does not strain), flip modes 2 mu, scaling block
A = 2 mu I + lambda 1 1^T (eigenvalues 2 mu + 3 lambda once, 2 mu twice).
"""

from typing import Any

import warp as wp

from .base import Material
from .registry import register_material

__all__ = ["LinearElastic", "linear_psi", "linear_pk1", "linear_eigen"]


@wp.func
def linear_strain(F: Any):
    """eps = (F + F^T)/2 - I."""
    return F.dtype(0.5) * (F + wp.transpose(F)) - wp.identity(n=3, dtype=F.dtype)


@wp.func
def linear_psi(F: Any, mu: Any, lam: Any):
    """psi = mu eps:eps + lambda/2 tr(eps)^2."""
    eps = linear_strain(F)
    tr = wp.trace(eps)
    return mu * wp.ddot(eps, eps) + F.dtype(0.5) * lam * tr * tr


@wp.func
def linear_pk1(F: Any, mu: Any, lam: Any):
    """P = 2 mu eps + lambda tr(eps) I."""
    eps = linear_strain(F)
    return F.dtype(2.0) * mu * eps + lam * wp.trace(eps) * wp.identity(n=3, dtype=F.dtype)


@wp.func
def linear_eigen(F: Any, mu: Any, lam: Any):
    """(A, twist, flip) with U = V = I: A = 2 mu I + lambda 1 1^T, twist = 0, flip = 2 mu.

    F is only used for its scalar type.
    """
    two_mu = F.dtype(2.0) * mu
    d = two_mu + lam
    A = wp.matrix(d, lam, lam, lam, d, lam, lam, lam, d, shape=(3, 3))
    zero = F.dtype(0.0)
    twist = wp.vector(zero, zero, zero)
    flip = wp.vector(two_mu, two_mu, two_mu)
    return A, twist, flip


@register_material("linear", kind=0, psi=linear_psi, pk1=linear_pk1, eigen=linear_eigen, svd=False)
class LinearElastic(Material):
    """Linear (small-strain) elasticity: psi = mu eps:eps + lambda/2 tr(eps)^2, eps = sym(F - I)."""

