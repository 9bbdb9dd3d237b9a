"""Fixed corotated material (Stomakhin, Howes, Schroeder, Teran 2012, "Energetically consistent
invertible elasticity", SCA, eq. 4 with the J - 1 volume term).

    psi = mu ||F - R||_F^2 + lambda/2 (J - 1)^2,   J = det F
    P   = 2 mu (F - R) + lambda (J - 1) cof(F),    cof(F) = dJ/dF = J F^{-T}

mu = E/(2(1+nu)), lambda = E nu/((1+nu)(1-2nu)). R = U V^T comes from the signed SVD
F = U diag(s) V^T with det U = det V = +1 (reflection in s[2] < 0), so det R = +1 even for
inverted F (det F < 0): R is the rotation closest to F (Irving, Teran, Fedkiw 2004).

In the signed singular values (Smith, de Goes, Kim 2019, sec. 7.3), with J = s0 s1 s2:

    Psi        = mu sum_i (s_i - 1)^2 + lambda/2 (J - 1)^2
    Psi_ii     = 2 mu + lambda (J/s_i)^2 = 2 mu + lambda (s_j s_k)^2       (scaling block A)
    Psi_ij     = lambda (J/s_i)(J/s_j) + lambda (J - 1) s_k = lambda s_i s_j s_k^2 + lambda (J-1) s_k
    flip_k     = 2 mu - lambda (J - 1) s_k
    twist_k    = 2 mu - 4 mu/(s_i + s_j) + lambda (J - 1) s_k

Denominator guard (convention): with the signed SVD, s0 >= s1 >= |s2|, so s_i + s_j >= 0 for
every pair; it is 0 only at a degenerate (flattened/inverting) configuration. The denominator is
clamped to s_i + s_j >= 1e-6 max(s0, 1) (relative to the largest stretch, with an absolute floor
so that F = 0 stays finite); the clamp is inactive for any non-degenerate F, so the Hessian is
exact there. Near the singularity the twist eigenvalue is a large negative number that the SPD
projection clamps to 0.
"""

from typing import Any

import warp as wp

from .base import Material
from .registry import register_material
from .eigensystem import cofactor, pair_axes, signed_svd

__all__ = ["Corotated", "corotated_psi", "corotated_pk1", "corotated_eigen", "COROTATED_TWIST_EPS"]

#: relative clamp of the twist denominator s_i + s_j (see module docstring)
COROTATED_TWIST_EPS = 1.0e-6
_TWIST_EPS = wp.constant(COROTATED_TWIST_EPS)


@wp.func
def corotated_psi(F: Any, mu: Any, lam: Any):
    """psi = mu ||F - R||_F^2 + lambda/2 (J - 1)^2, R = U V^T (signed SVD)."""
    U, s, V = signed_svd(F)
    D = F - U * wp.transpose(V)
    Jm1 = wp.determinant(F) - F.dtype(1.0)
    return mu * wp.ddot(D, D) + F.dtype(0.5) * lam * Jm1 * Jm1


@wp.func
def corotated_pk1(F: Any, mu: Any, lam: Any):
    """P = 2 mu (F - R) + lambda (J - 1) cof(F)."""
    U, s, V = signed_svd(F)
    R = U * wp.transpose(V)
    Jm1 = wp.determinant(F) - F.dtype(1.0)
    return F.dtype(2.0) * mu * (F - R) + lam * Jm1 * cofactor(F)


@wp.func
def corotated_eigen(s: Any, mu: Any, lam: Any):
    """(A, twist, flip) of the fixed-corotated Hessian at signed singular values s."""
    one = type(mu)(1.0)
    two_mu = type(mu)(2.0) * mu
    J = s[0] * s[1] * s[2]
    Jm1 = J - one
    eps = type(mu)(_TWIST_EPS) * wp.max(s[0], one)
    A = type(wp.outer(s, s))()
    twist = wp.vector(length=3, dtype=type(mu))
    flip = wp.vector(length=3, dtype=type(mu))
    for k in range(3):
        i, j = pair_axes(k)
        A[k, k] = two_mu + lam * (s[i] * s[j]) * (s[i] * s[j])
        off = lam * s[i] * s[j] * s[k] * s[k] + lam * Jm1 * s[k]
        A[i, j] = off
        A[j, i] = off
        denom = wp.max(s[i] + s[j], eps)
        flip[k] = two_mu - lam * Jm1 * s[k]
        twist[k] = two_mu - type(mu)(4.0) * mu / denom + lam * Jm1 * s[k]
    return A, twist, flip


@register_material("corotated", kind=2, psi=corotated_psi, pk1=corotated_pk1, eigen=corotated_eigen)
class Corotated(Material):
    """Fixed corotated (Stomakhin et al. 2012): psi = mu ||F - R||^2 + lambda/2 (J - 1)^2."""

