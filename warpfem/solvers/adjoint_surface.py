"""The derivatives of surface-contact friction that the reverse pass of a step needs (``warpfem.solvers.adjoint``).

Surface contact's lagged friction (``warpfem.contact.surface``, ``friction_kernel``) is, over the
pairs p (point-triangle or edge-edge, four vertices each) within dhat at the step start x_n,

    D = sum_p mu lam_p f0(|u_p|),   u_p = P_p sum_i w_p,i (x_i - x_i^n),   P_p = I - n_p n_p^T,

with the lagged normal force lam_p = kappa m_p (-b'(s_p)) 2 sqrt(s_p) (s_p the pair's squared
distance, b the squared-distance barrier, m_p the edge-edge mollifier), the closest-point weights
w_p and the normal n_p = r_p / |r_p| (r_p = sum_i w_p,i x_i^n) all functions of x_n: the pair
kernel's lag mode. Its gradient in x = x_{n+1} is g_p,i = w_p,i mu lam_p (f1(y) / y) u_p.

This module writes the lag (the closest features exactly as ``pt_features`` / ``ee_features``
choose them, the barrier's slope, the mollifier) and that gradient in numpy, complex-safe
(branches on real parts, lengths as sqrt(r . r)), vectorised over the pairs, and differentiates
them by the **complex step** (Im g(z + i h e_k) / h, h = 1e-30; exact to round-off) per pair's 12
coordinates: the exact friction Hessian blocks d g / d x_{n+1} (which ``friction_kernel``'s mode 2
also gives: tests/test_adjoint_surface_friction.py compares them), the derivative d g / d x_n
through lam_p, w_p, n_p and the explicit -x^n, and d g / d mu = g / mu.

The pairs are the surface contact's candidates at x_n (its broad phase: body and self filters,
the rest-gap rule of self contact) within dhat with lam_p > 0, as ``SurfaceContact.lag`` keeps
them. A recorded step lags once, from x_n: the simulator does not run its ``friction_iterations``
while a recording or a tape is active, for colliders and surface pairs alike.
"""

from __future__ import annotations

import numpy as np

#: the pair kinds of ``warpfem.contact.surface_kernels`` (PT point-triangle, EE edge-edge; not imported:
#: warpfem.contact imports warpfem.solvers, tests/test_import_layers.py)
PT, EE = 0, 1

__all__ = ["SurfaceFrictionTerms", "surface_friction_terms", "lag_host", "friction_gradient_host"]

H_CS = 1e-30  # the complex step


def _dot(a, b):
    return np.sum(a * b, axis=-1)


def _clamp01(t):
    R = np.real
    return np.where(R(t) < 0.0, 0.0, np.where(R(t) > 1.0, 1.0, t))


def _safe(x, ok):
    return np.where(ok, x, 1.0)


def _pe_param(p, a, b):
    """``_pe_param`` of the kernel: t of the closest point a + t (b - a) to p (clamped) and |r|^2."""
    e = b - a
    ee = _dot(e, e)
    ok = np.real(ee) > 0.0
    t = np.where(ok, _clamp01(_dot(p - a, e) / _safe(ee, ok)), 0.0)
    r = p - a - t[:, None] * e
    return t, _dot(r, r)


def _pt_weights(p, a, b, c):
    """The weights w (k, 4) of ``pt_features`` (r = w . (p, a, b, c))."""
    R = np.real
    k = p.shape[0]
    ab, ac, ap = b - a, c - a, p - a
    d00, d01, d11 = _dot(ab, ab), _dot(ab, ac), _dot(ac, ac)
    e0, e1 = _dot(ab, ap), _dot(ac, ap)
    den = d00 * d11 - d01 * d01
    ok = R(den) > 1e-12 * R(d00 * d11)
    dens = _safe(den, ok)
    u = (d11 * e0 - d01 * e1) / dens
    v = (d00 * e1 - d01 * e0) / dens
    inside = ok & (R(u) >= 0.0) & (R(v) >= 0.0) & (R(u + v) <= 1.0)
    one = np.ones(k, dtype=u.dtype)
    w_in = np.stack([one, -(1.0 - u - v), -u, -v], axis=1)
    # outside: the closest of the edges ab (1-2), bc (2-3), ca (3-1), the first on ties
    t, best = _pe_param(p, a, b)
    i0, i1 = np.full(k, 1), np.full(k, 2)
    for (q0, q1), (j0, j1) in (((b, c), (2, 3)), ((c, a), (3, 1))):
        t2, s2 = _pe_param(p, q0, q1)
        sel = R(s2) < R(best)
        best, t = np.where(sel, s2, best), np.where(sel, t2, t)
        i0, i1 = np.where(sel, j0, i0), np.where(sel, j1, i1)
    lo, hi = R(t) <= 0.0, R(t) >= 1.0
    w_out = np.zeros((k, 4), dtype=w_in.dtype)
    w_out[:, 0] = 1.0
    rows = np.arange(k)
    w_out[rows, i0] = np.where(lo, -1.0, np.where(hi, 0.0, -(1.0 - t)))
    w_out[rows, i1] = np.where(lo, 0.0, np.where(hi, -1.0, -t))
    return np.where(inside[:, None], w_in, w_out)


def _ee_weights(a0, a1, b0, b1):
    """The weights w (k, 4) of ``ee_features`` (r = (a0 + s da) - (b0 + t db))."""
    R = np.real
    d1, d2, r0 = a1 - a0, b1 - b0, a0 - b0
    A, E, F = _dot(d1, d1), _dot(d2, d2), _dot(d2, r0)
    C, B = _dot(d1, r0), _dot(d1, d2)
    den = A * E - B * B
    ok = R(den) > 1e-10 * R(A * E)
    s = np.where(ok, _clamp01((B * F - C * E) / _safe(den, ok)), 0.0)
    t = (B * s + F) / E
    lo = R(t) < 0.0
    hi = ~lo & (R(t) > 1.0)
    s = np.where(lo, _clamp01(-C / A), np.where(hi, _clamp01((B - C) / A), s))
    t = np.where(lo, 0.0, np.where(hi, 1.0, t))
    return np.stack([1.0 - s, s, -(1.0 - t), -t], axis=1)


def _barrier_slope(s, t):
    """b'(s) of b(s) = -(s - t)^2 ln(s / t) (the kernel's ``barrier``, in squared distances)."""
    d = s - t
    return -2.0 * d * np.log(s / t) - d * d / s


def lag_host(X, kinds, rest, kappa, dhat):
    """The lagged friction quantities of pairs at positions X (k, 4, 3) (the pair kernel's
    ``MODE_LAG``): (lam (k,), w (k, 4), n (k, 3)); lam = 0 for a pair not within (0, dhat).
    ``rest`` (k, 4, 3): the rest positions (the edge-edge mollifier's scale)."""
    X = np.asarray(X)
    kinds = np.asarray(kinds)
    k = X.shape[0]
    dt = np.result_type(X.dtype, np.float64)
    w = np.zeros((k, 4), dtype=dt)
    pt, ee = np.flatnonzero(kinds == PT), np.flatnonzero(kinds == EE)
    if len(pt):
        w[pt] = _pt_weights(X[pt, 0], X[pt, 1], X[pt, 2], X[pt, 3])
    if len(ee):
        w[ee] = _ee_weights(X[ee, 0], X[ee, 1], X[ee, 2], X[ee, 3])
    r = np.einsum("pi,pic->pc", w, X)
    s = _dot(r, r)
    dh2 = float(dhat) ** 2
    act = (np.real(s) > 0.0) & (np.real(s) < dh2)
    ss = np.where(act, s, 0.5 * dh2)
    m = np.ones(k, dtype=dt)
    if len(ee):
        u, v = X[ee, 1] - X[ee, 0], X[ee, 3] - X[ee, 2]
        cr = np.cross(u, v)
        cc = _dot(cr, cr)
        ru, rv = rest[ee, 1] - rest[ee, 0], rest[ee, 3] - rest[ee, 2]
        epsx = 1e-3 * _dot(ru, ru) * _dot(rv, rv)
        q = cc / epsx
        m[ee] = np.where(np.real(cc) >= epsx, 1.0, (2.0 - q) * q)
    L = np.sqrt(ss)
    lam = np.where(act, float(kappa) * m * (-_barrier_slope(ss, dh2)) * 2.0 * L, 0.0)
    n = r / L[:, None]
    return lam, w, n


def friction_gradient_host(X1, XN, kinds, rest, kappa, dhat, mu, eps):
    """g (k, 4, 3): each pair's friction gradient at x_{n+1} = X1 lagged from x_n = XN (both (k, 4, 3))."""
    lam, w, n = lag_host(XN, kinds, rest, kappa, dhat)
    rel = np.einsum("pi,pic->pc", w, X1 - XN)
    u = rel - _dot(n, rel)[:, None] * n
    y2 = _dot(u, u)
    pos = np.real(y2) > 0.0
    y = np.sqrt(np.where(pos, y2, 1.0))
    f1 = np.where(np.real(y) >= eps, 1.0 / y, 1.0 / eps)
    f1 = np.where(pos, f1, 1.0 / eps)
    c = mu * lam * f1
    return c[:, None, None] * w[:, :, None] * u[:, None, :]


class SurfaceFrictionTerms:
    """The complex-step derivatives of surface friction's gradient at a step (module docstring):
    ``pairs`` (k, 4) vertex indices; ``H`` and ``D_xn`` (k, 4, 3, 4, 3): d g_(p, i) / d x_(p, j) at
    x_{n+1} and in x_n; ``g`` (k, 4, 3) the gradient itself; ``mu``."""

    def __init__(self, pairs, H, D_xn, g, mu):
        self.pairs, self.H, self.D_xn, self.g, self.mu = pairs, H, D_xn, g, float(mu)

    def __len__(self):
        return len(self.pairs)

    def add_hessian(self, K, pattern):
        """Add the Hessian blocks into the host block values ``K`` ((nnz, 3, 3)) of ``pattern``."""
        q = self.pairs
        a = np.repeat(q, 4, axis=1).reshape(-1)  # block (i, j) of each pair: row q_i, column q_j
        b = np.tile(q, (1, 4)).reshape(-1)
        pos = pattern.pair_index(np.stack([a, b], axis=1))
        if np.any(pos < 0):
            raise RuntimeError("surface friction: a pair's Hessian block is missing from the pattern")
        blocks = self.H.transpose(0, 1, 3, 2, 4).reshape(-1, 3, 3)  # (k, i, j, r, c)
        np.add.at(K, pos, blocks.astype(K.dtype))

    def xn_product(self, lam):
        """(n, 3): (d g / d x_n)^T lam for the adjoint lam (n, 3)."""
        lp = lam[self.pairs]  # (k, 4, 3)
        out = np.zeros_like(lam)
        np.add.at(out, self.pairs, np.einsum("piajc,pia->pjc", self.D_xn, lp))
        return out

    def mu_product(self, lam) -> float:
        """(d g / d mu) . lam (g is linear in mu)."""
        return float(np.sum(self.g * lam[self.pairs])) / self.mu


def surface_friction_terms(pairs, kinds, x1, xn, rest, *, kappa, dhat, mu, eps) -> SurfaceFrictionTerms | None:
    """The derivatives of the friction gradient of the candidate ``pairs`` ((k, 4), ``kinds`` PT /
    EE) at x_n = ``xn`` whose lag keeps them (within dhat, lam > 0), at x_{n+1} = ``x1``; host
    (n, 3) positions, ``rest`` (n, 3). None when no pair is lagged (or mu = 0)."""
    if mu <= 0.0 or len(pairs) == 0:
        return None
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 4)
    kinds = np.asarray(kinds).reshape(-1)
    lam, _, _ = lag_host(xn[pairs], kinds, rest[pairs], kappa, dhat)
    keep = lam > 0.0
    if not np.any(keep):
        return None
    pairs, kinds = pairs[keep], kinds[keep]
    X1, XN, RR = x1[pairs], xn[pairs], rest[pairs]
    k = len(pairs)

    def jac(which):
        # 12 complex-step evaluations stacked along the pair axis: coordinate (j, c) of every pair
        Z1 = np.repeat(X1[None].astype(complex), 12, axis=0)
        ZN = np.repeat(XN[None].astype(complex), 12, axis=0)
        Z = Z1 if which == "x1" else ZN
        for j in range(4):
            for c in range(3):
                Z[3 * j + c, :, j, c] += 1j * H_CS
        g = friction_gradient_host(Z1.reshape(-1, 4, 3), ZN.reshape(-1, 4, 3), np.tile(kinds, 12),
                                   np.tile(RR, (12, 1, 1)), kappa, dhat, mu, eps)
        d = np.imag(g).reshape(12, k, 4, 3) / H_CS  # (jc, p, i, a)
        return d.transpose(1, 2, 3, 0).reshape(k, 4, 3, 4, 3)

    g = friction_gradient_host(X1, XN, kinds, RR, kappa, dhat, mu, eps)
    return SurfaceFrictionTerms(pairs, jac("x1"), jac("xn"), g, mu)
