"""Stable neo-Hookean material *with* the log term (Smith, de Goes, Kim 2018, "Stable Neo-Hookean
flesh simulation", ACM TOG 37(2): their energy with the -mu/2 log(I_C + 1) term).

    psi   = mu/2 (I_C - 3) + lambda/2 (J - alpha)^2 - mu/2 log(I_C + 1) - psi_0
    alpha = 1 + 3 mu / (4 lambda)          (= 1 + mu/lambda - mu/(4 lambda), the paper's form)
    P     = mu (1 - 1/(1 + I_C)) F + lambda (J - alpha) cof(F)
    psi_0 = lambda/2 (1 - alpha)^2 - mu log 2     (so psi(I) = 0; changes neither P nor the Hessian)

Why the log term: for the log-free energy (``stable_neo_hookean.py``) F = 0 is a strict local
minimum (psi(eps G) - psi(0) = mu/2 eps^2 |G|^2 + O(eps^3)), so a body squashed to a point stays
there. Here the log term cancels that curvature: -mu/2 log(1 + I_C) = -mu/2 I_C + O(I_C^2), so the
Hessian at F = 0 vanishes and psi(eps G) - psi(0) = -lambda alpha eps^3 det G + O(eps^4), which is
negative along every direction with det G > 0. F = 0 is a (degenerate) saddle, P(0) = 0, and a
body squashed to a point expands again once the jitter has picked an orientation.

Derivation of the constants (verified in ``tests/test_materials.py``):
* P(I) = 0:  mu I + lambda (1 - alpha) I - mu/4 I = 0  =>  lambda (alpha - 1) = 3 mu / 4.
* Hessian at I, as a quadratic form in H = dF: mu |H|^2 + lambda (tr H)^2
  - 3mu/4 ((tr H)^2 - tr(H H))  [lambda (J - alpha) d2J]  - mu/4 |H|^2 + mu/8 (tr H)^2  [log term]
  = 3mu/4 (|H|^2 + tr(H H)) + (lambda - 5mu/8) (tr H)^2. Linear elasticity with Lame (mu_L, lambda_L)
  is mu_L (|H|^2 + tr(H H)) + lambda_L (tr H)^2, hence the reparametrisation (paper sec. 3.4)

      mu = 4/3 mu_L,   lambda = lambda_L + 5/6 mu_L   (> 0 for every -1 < nu < 0.5)

  (the class attributes ``mu`` and ``lam`` hold these; ``mu_lame``, ``lam_lame`` the plain values).

In the signed singular values s (Smith, de Goes, Kim 2019): the log-free part is that of
``snh_eigen`` with lambda (J - alpha) = lambda (J - 1) - 3mu/4; the log term g(I_C) = -mu/2 log(1 + I_C)
adds 2 g' = -mu/(1 + I_C) to every twist and flip eigenvalue and
2 g' delta_ij + 4 g'' s_i s_j = -mu/(1 + I_C) delta_ij + 2 mu s_i s_j / (1 + I_C)^2 to the scaling block.
At F = I: twist = 0 (x3), flip = 3mu/2 = 2 mu_L (x3), scaling 2 mu_L (x2), 3 lambda_L + 2 mu_L.
"""

from typing import Any

import warp as wp

from .base import Material
from .registry import register_material
from .eigensystem import cofactor, pair_axes

__all__ = ["StableNeoHookeanLog", "snh_log_psi", "snh_log_pk1", "snh_log_eigen", "x_minus_log1p"]


@wp.func
def x_minus_log1p(x: Any):
    """x - log(1 + x) for x > -1, accurate to a few ulp also for small |x| (where it is ~ x^2/2 and
    the plain difference would lose all digits; Warp has no log1p).

    For |x| < 1/4: with u = x / (2 + x), log(1 + x) = 2 atanh(u) = 2 (u + u^3/3 + u^5/5 + ...) and
    x - 2u = x^2 / (2 + x), so x - log(1 + x) = x^2/(2 + x) - 2 u^3 (1/3 + u^2/5 + ... + u^18/21)
    (|u| < 1/7: the dropped terms are below 1e-17 relative). Otherwise x - log(1 + x) directly
    (relative error ~ eps / |x| <= 4 eps there)."""
    one = type(x)(1.0)
    two = type(x)(2.0)
    if wp.abs(x) < type(x)(0.25):
        u = x / (two + x)
        u2 = u * u
        p = type(x)(0.0)
        n = type(x)(21.0)
        for _k in range(10):
            p = one / n + u2 * p
            n = n - two
        return x * x / (two + x) - two * u * u2 * p
    return x - wp.log(one + x)


@wp.func
def snh_log_psi(F: Any, mu: Any, lam: Any):
    """psi = mu/2 (I_C - 3) + lambda/2 (J - alpha)^2 - mu/2 log(1 + I_C) - psi_0 (psi(I) = 0).

    Evaluated in the displacement gradient H = F - I without cancellation (exact rewrite; with
    j = J - 1 = tr H + i2 + det H, i2 = ((tr H)^2 - tr(H H))/2, x = (I_C - 3)/4 = (2 tr H + |H|^2)/4,
    log(1 + I_C) = log 4 + log(1 + x), lambda (alpha - 1) = 3mu/4):

        psi = 3mu/8 |H|^2 + lambda/2 j^2 - 3mu/4 (i2 + det H) + mu/2 (x - log(1 + x)).

    Every term is O(|H|^2) on its own, so float32 keeps relative accuracy at small strain (the
    textbook form subtracts O(mu) terms, see ``snh_psi``). lambda = 0 or mu = 0 is allowed.
    """
    half = F.dtype(0.5)
    H = F - wp.identity(n=3, dtype=F.dtype)
    trH = wp.trace(H)
    HH = wp.ddot(H, H)
    i2 = half * (trH * trH - wp.ddot(H, wp.transpose(H)))
    dH = wp.determinant(H)
    j = trH + i2 + dH
    x = F.dtype(0.25) * (F.dtype(2.0) * trH + HH)
    return (F.dtype(0.375) * mu * HH + half * lam * j * j - F.dtype(0.75) * mu * (i2 + dH)
            + half * mu * x_minus_log1p(x))


@wp.func
def snh_log_pk1(F: Any, mu: Any, lam: Any):
    """P = mu (1 - 1/(1 + I_C)) F + lambda (J - alpha) cof(F), evaluated as

        P = 3mu/4 (F - cof F) + mu (I_C - 3) / (4 (1 + I_C)) F + lambda (J - 1) cof(F)

    (mu I_C/(1 + I_C) - 3mu/4 = mu (I_C - 3)/(4 (1 + I_C)); lambda (J - alpha) = lambda (J - 1) - 3mu/4),
    with I_C - 3 = 2 tr H + |H|^2 and J - 1 from H = F - I. Finite for lambda = 0 (the volumetric
    split's parts)."""
    half = F.dtype(0.5)
    H = F - wp.identity(n=3, dtype=F.dtype)
    trH = wp.trace(H)
    ic3 = F.dtype(2.0) * trH + wp.ddot(H, H)
    j = trH + half * (trH * trH - wp.ddot(H, wp.transpose(H))) + wp.determinant(H)
    C = cofactor(F)
    return (F.dtype(0.75) * mu * (F - C) + (F.dtype(0.25) * mu * ic3 / (ic3 + F.dtype(4.0))) * F
            + lam * j * C)


@wp.func
def snh_log_eigen(s: Any, mu: Any, lam: Any):
    """(A, twist, flip) of the stable neo-Hookean (log) Hessian at signed singular values s."""
    one = type(mu)(1.0)
    c = one + wp.dot(s, s)  # 1 + I_C >= 1
    g2 = -mu / c  # 2 g'
    h = type(mu)(2.0) * mu / (c * c)  # 4 g''
    J = s[0] * s[1] * s[2]
    r = lam * (J - one) - type(mu)(0.75) * mu  # = lambda (J - alpha)
    A = type(wp.outer(s, s))()
    twist = wp.vector(length=3, dtype=type(mu))
    flip = wp.vector(length=3, dtype=type(mu))
    for k in range(3):
        i, j = pair_axes(k)
        A[k, k] = mu + g2 + lam * (s[i] * s[j]) * (s[i] * s[j]) + h * s[k] * s[k]
        off = lam * s[i] * s[j] * s[k] * s[k] + r * s[k] + h * s[i] * s[j]
        A[i, j] = off
        A[j, i] = off
        flip[k] = mu + g2 - r * s[k]
        twist[k] = mu + g2 + r * s[k]
    return A, twist, flip


@register_material("stable_neo_hookean_log", kind=4, psi=snh_log_psi, pk1=snh_log_pk1, eigen=snh_log_eigen)
class StableNeoHookeanLog(Material):
    """Stable neo-Hookean with the log term -mu/2 log(I_C + 1) (Smith et al. 2018), reparametrised:
    ``mu = 4/3 mu_L``, ``lam = lambda_L + 5/6 mu_L``. F = 0 is a saddle, not a minimum, so bodies
    squashed to a point (or line) recover; see ``docs/stability.md``."""


    @staticmethod
    def kernel_parameters(mu_lame: float, lam_lame: float) -> tuple[float, float]:
        return 4.0 / 3.0 * mu_lame, lam_lame + 5.0 / 6.0 * mu_lame

    def volumetric_split(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """Selective reduced integration split: ((mu, 5/8 mu), (0, lambda - 5/8 mu)) = Lame ((mu_L, 0), (0, lambda_L)).

        With the rest offset removed, psi(F; mu, lam) = mu/2 (I_C - 3) - mu/2 log((1 + I_C)/4)
        - 3mu/4 (J - 1) + lam/2 (J - 1)^2: lambda enters only through lam/2 (J - 1)^2, so
        psi(F; mu, lam) = psi(F; mu, lam_f) + psi(F; 0, lam - lam_f) exactly for any lam_f. With
        lam_f = 5/8 mu = 5/6 mu_L the full-rule part is this material with Lame (mu_L, 0) (small-strain
        stiffness 2 mu_L sym(H):sym(H), positive semi-definite) and the 1-point part is
        lambda_L/2 (J - 1)^2 (PSD at rest for lambda_L >= 0); both are stress-free at F = I and their sum is
        the linear-elastic SRI split, as for ``StableNeoHookean.volumetric_split``.
        """
        lam_f = 0.625 * self.kernel_mu
        return (self.kernel_mu, lam_f), (0.0, self.kernel_lam - lam_f)
