"""Stable neo-Hookean material without the log term (Smith, de Goes, Kim 2018, "Stable
Neo-Hookean flesh simulation", ACM TOG 37(2), sec. 3.4, eq. 14-16).

    psi   = mu/2 (I_C - 3) + lambda/2 (J - alpha)^2,   I_C = tr(F^T F), J = det F
    alpha = 1 + mu/lambda
    P     = mu F + lambda (J - alpha) cof(F),           cof(F) = dJ/dF
          = mu (F - cof F) + lambda (J - 1) cof(F)      (as evaluated: finite for lambda = 0)

Reparametrisation (sec. 3.4) so that the small-strain moduli are those of E, nu: with the Lame
values mu_L = E/(2(1+nu)), lambda_L = E nu/((1+nu)(1-2nu)) the kernel parameters are

    mu = mu_L,   lambda = lambda_L + mu_L = E/(2(1+nu)(1-2nu))  (> 0 for -1 < nu < 0.5)

(the class attributes ``mu`` and ``lam`` hold these). Then P(I) = 0, the Hessian at F = I equals
the linear-elastic one, and psi(I) = mu^2/(2 lambda) (a constant offset). The energy is smooth
through inversion (det F < 0) and rotation invariant.

In the signed singular values (Smith, de Goes, Kim 2019, sec. 7.4):

    Psi_ii  = mu + lambda (J/s_i)^2 = mu + lambda (s_j s_k)^2             (scaling block A)
    Psi_ij  = lambda (J/s_i)(J/s_j) + lambda (J - alpha) s_k               (i != j)
    flip_k  = mu - lambda (J - alpha) s_k
    twist_k = mu + lambda (J - alpha) s_k

At F = I: twist = 0 (x3), flip = 2 mu (x3), scaling 2 mu (x2) and 3 lambda - mu = 3 lambda_L + 2 mu_L.
"""

from typing import Any

import warp as wp

from .base import Material
from .registry import register_material
from .eigensystem import cofactor, pair_axes

__all__ = ["StableNeoHookean", "snh_psi", "snh_pk1", "snh_eigen"]


@wp.func
def snh_psi(F: Any, mu: Any, lam: Any):
    """psi = mu/2 (tr(F^T F) - 3) + lambda/2 (J - alpha)^2 - mu^2 / (2 lambda), alpha = 1 + mu/lambda.

    The constant -mu^2/(2 lambda) = -lambda/2 (1 - alpha)^2 makes psi(I) = 0 (rest energy zero,
    so reported elastic energies are meaningful); it changes neither P nor the Hessian.

    Evaluated without cancellation in the displacement gradient H = F - I (exact rewrite):
    psi = mu/2 |H|^2 + lambda/2 j^2 - mu (i2 + det H),  j = J - 1 = tr H + i2 + det H,
    i2 = ((tr H)^2 - tr(H H)) / 2. The textbook form subtracts O(mu) terms to get an O(mu |H|^2)
    result, so in float32 its error (~3 eps mu per unit volume) swamped the energy of strains
    below ~1e-3 and the Newton line search compared noise.
    """
    half = F.dtype(0.5)
    H = F - wp.identity(n=3, dtype=F.dtype)
    trH = wp.trace(H)
    i2 = half * (trH * trH - wp.ddot(H, wp.transpose(H)))
    dH = wp.determinant(H)
    j = trH + i2 + dH
    return half * mu * wp.ddot(H, H) + half * lam * j * j - mu * (i2 + dH)


@wp.func
def snh_pk1(F: Any, mu: Any, lam: Any):
    """P = mu F + lambda (J - alpha) cof(F), written as mu (F - cof F) + lambda (J - 1) cof(F)
    (lambda (J - alpha) = lambda (J - 1) - mu), so lambda = 0 or mu = 0 is allowed (the parts of
    selective reduced integration, ``StableNeoHookean.volumetric_split``)."""
    C = cofactor(F)
    return mu * (F - C) + lam * (wp.determinant(F) - F.dtype(1.0)) * C


@wp.func
def snh_eigen(s: Any, mu: Any, lam: Any):
    """(A, twist, flip) of the stable neo-Hookean Hessian at signed singular values s."""
    J = s[0] * s[1] * s[2]
    r = lam * (J - type(mu)(1.0)) - mu  # = lambda (J - alpha), finite for lambda = 0
    A = type(wp.outer(s, s))()
    twist = wp.vector(length=3, dtype=type(mu))
    flip = wp.vector(length=3, dtype=type(mu))
    for k in range(3):
        i, j = pair_axes(k)
        A[k, k] = mu + lam * (s[i] * s[j]) * (s[i] * s[j])
        off = lam * s[i] * s[j] * s[k] * s[k] + r * s[k]
        A[i, j] = off
        A[j, i] = off
        flip[k] = mu - r * s[k]
        twist[k] = mu + r * s[k]
    return A, twist, flip


@register_material("stable_neo_hookean", kind=3, psi=snh_psi, pk1=snh_pk1, eigen=snh_eigen)
class StableNeoHookean(Material):
    """Stable neo-Hookean without log term (Smith et al. 2018, sec. 3.4), reparametrised:
    ``mu = mu_L``, ``lam = lambda_L + mu_L``."""


    @staticmethod
    def kernel_parameters(mu_lame: float, lam_lame: float) -> tuple[float, float]:
        return mu_lame, lam_lame + mu_lame

    def volumetric_split(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """Selective reduced integration split: ((mu, mu), (0, lambda - mu)) = ((mu_L, mu_L), (0, lambda_L)).

        psi(mu, lam) = mu/2 (I_C - 3) - mu (J - 1) + lam/2 (J - 1)^2 (rest offset removed), so
        psi(F; mu, lam) = psi(F; mu, mu) + psi(F; 0, lam - mu) exactly. The 1-point part is
        lambda_L/2 (J - 1)^2; the full-rule part is stable neo-Hookean with Lame (mu_L, 0). Splitting
        at (mu, 0) + (0, lam) instead would also be exact but leave the full-rule part indefinite
        at rest (eigenvalue -mu for dilation: mu/2 (I_C - 3) - mu (J - 1) ~ mu eps:eps - mu/2 tr(eps)^2),
        so its SPD projection would change the small-strain stiffness; with this split both parts
        are positive semi-definite at rest and their sum is the linear-elastic SRI split.
        """
        return (self.kernel_mu, self.kernel_mu), (0.0, self.kernel_lam - self.kernel_mu)
