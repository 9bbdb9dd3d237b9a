"""The derivatives of collider contact that the reverse pass of a step needs (``warpfem.solvers.adjoint``).

The collider contact energy of a step is a sum over the body's surface vertices i and colliders j
of e_ij(x_i; x_n,i, pose_1, pose_0, mu_j) (``warpfem.contact.kernels``): the barrier
kappa b(d) of every primitive within dhat (a plane, sphere or box: one distance; a mesh: every
triangle's point-triangle distance) in the collider's end-of-step pose, plus the lagged friction
mu lam_n f0(|P (x - x_n - w)|) with the normal force lam_n and normal from x_n in the end pose and
w the collider's motion of the point over the step (start pose -> end pose). Each term depends on
one vertex, so every derivative is per vertex.

The gradient g_i = de/dx_i is written here on the host in numpy, complex-safe (branches on real
parts, lengths as sqrt(r . r), no abs; each collider's distance is its own ``local_distances``,
the host counterpart of its kernel distance, in ``warpfem.contact.colliders``: not imported here,
the solvers layer sits below contact), and differentiated by the **complex step**
(Im g(z + i h e) / h with h = 1e-30): exact to round-off, with no finite-difference step to choose.
It gives, per contact vertex, the exact Hessian block d g_i / dx_i (the barrier's curvature term
included, which the forward's SPD-projected Hessian leaves out) and the derivatives of g_i in x_n,i
and in the parameters: the end and start poses' translation (3 each), their rotation (3 each) and
mu. **Rotation parameter**: an axis-angle vector omega (radians) applied to the pose at that time
about the collider's current centre c(t) = R c_0 + p (c_0 = ``Collider.center()``): X -> E(omega)
(R X + p - c(t)) + c(t), E = exp([omega]x); the gradient is dL/domega at omega = 0.
"""

from __future__ import annotations

import numpy as np

H_CS = 1e-30  # the complex step


def _dot(a, b):
    return np.sum(a * b, axis=-1)


def _barrier_b1(d, dh):
    t = d - dh
    return -2.0 * t * np.log(d / dh) - t * t / d


def _barrier_sum(c, x, R1, p1, kappa, dh):
    """At world points x with the pose (R1, p1): (sum over the primitives within dhat of kappa b'(d) n,
    sum of -kappa b'(d) (the lagged normal force), whether any is within dhat)."""
    pl = (x - p1) @ R1  # R1^T (x - p1) row-wise
    d, nl = c.local_distances(pl)  # the collider's host distance (warpfem.contact.colliders)
    act = (np.real(d) > 0) & (np.real(d) < dh)
    ds = np.where(act, d, dh)
    b1 = np.where(act, _barrier_b1(ds, dh), 0.0)
    n = nl @ R1.T
    return kappa * np.sum(b1[..., None] * n, axis=1), -kappa * np.sum(b1, axis=1), act.any(axis=1)


class ColliderTerms:
    """The complex-step derivatives of one collider's contact gradient at a step (see the module
    docstring). ``verts``: the surface vertices with a contact term; ``H`` (k, 3, 3): d g / dx;
    ``D_xn`` (k, 3, 3): d g / dx_n (columns: components of x_n); ``D_par`` (k, 3, 13): d g / d
    (t1, omega1, t0, omega0, mu)."""

    def __init__(self, verts, H, D_xn, D_par):
        self.verts, self.H, self.D_xn, self.D_par = verts, H, D_xn, D_par


def collider_terms(c, surf, x1, xn, pose1, pose0, kappa, dh, eps) -> ColliderTerms | None:
    """The derivatives of collider ``c``'s contact gradient at the step's end positions ``x1``
    (host, (n, 3)), from its start ``xn``, with the poses (R, p) at the end and start; None when
    no vertex is in contact."""
    R1, p1 = pose1
    R0, p0 = pose0
    mu = float(c.friction)
    xs, xns = x1[surf], xn[surf]
    _, _, act_b = _barrier_sum(c, xs, R1, p1, kappa, dh)
    act_f = np.zeros(len(surf), dtype=bool)
    if mu > 0.0:
        fn, _, _ = _barrier_sum(c, xns, R1, p1, kappa, dh)
        act_f = _dot(fn, fn) > 0
    act = act_b | act_f
    if not np.any(act):
        return None
    xs, xns = xs[act], xns[act]
    c0 = np.asarray(c.center(), dtype=np.float64)

    def grad(x, xn_, t1, w1, t0, w0, mu_):
        # the perturbed poses: rotation omega about the collider's current centre, then translation
        Ra, pa = _pose(R1, p1, c0, w1, t1)
        Rb, pb = _pose(R0, p0, c0, w0, t0)
        g, _, _ = _barrier_sum(c, x, Ra, pa, kappa, dh)
        if mu > 0.0:
            # lagged from x_n in the end pose: lam_n = sum of -kappa b', nv = the unit sum of -kappa b' n
            fsum, lam, _ = _barrier_sum(c, xn_, Ra, pa, kappa, dh)
            nn2 = _dot(fsum, fsum)
            has = np.real(nn2) > 0
            nv = -fsum / np.sqrt(np.where(has, nn2, 1.0))[:, None]
            w = (xn_ - pb) @ Rb @ Ra.T + pa - xn_  # R1 R0^T (x_n - p0) + p1 - x_n
            u0 = x - xn_ - w
            u = u0 - _dot(nv, u0)[:, None] * nv
            y2 = _dot(u, u)
            y = np.sqrt(np.where(np.real(y2) > 0, y2, 1.0))
            big = np.real(y) >= eps
            f1 = np.where(big, 1.0 / y, 1.0 / eps)
            f1 = np.where(np.real(y2) > 0, f1, 1.0 / eps)
            g = g + np.where(has, mu_ * lam * f1, 0.0)[:, None] * u
        return g

    zero3 = np.zeros(3, dtype=complex)
    base = dict(x=xs.astype(complex), xn_=xns.astype(complex), t1=zero3, w1=zero3, t0=zero3, w0=zero3,
                mu_=complex(mu))

    def d_of(name, k=None):
        args = dict(base)
        v = args[name].copy() if isinstance(args[name], np.ndarray) else args[name]
        if k is None:
            v = v + 1j * H_CS
        elif v.ndim == 1:
            v[k] += 1j * H_CS
        else:
            v[:, k] += 1j * H_CS
        args[name] = v
        return np.imag(grad(**args)) / H_CS

    H = np.stack([d_of("x", k) for k in range(3)], axis=-1)
    D_xn = np.stack([d_of("xn_", k) for k in range(3)], axis=-1) if mu > 0.0 else np.zeros_like(H)
    cols = [d_of(nm, k) for nm in ("t1", "w1") for k in range(3)]
    if mu > 0.0:
        cols += [d_of(nm, k) for nm in ("t0", "w0") for k in range(3)] + [d_of("mu_")]
    else:
        cols += [np.zeros_like(cols[0])] * 7
    return ColliderTerms(np.asarray(surf)[act], H, D_xn, np.stack(cols, axis=-1))


def _pose(R, p, c0, w, t):
    """The pose (R, p) rotated by omega = w about its current centre R c0 + p, then translated by t
    (to first order in w, which is all a complex step of 1e-30 sees: exp([w]) = I + [w])."""
    E = np.eye(3) + _skew_c(w)
    c = R @ c0 + p
    return E @ R, E @ (p - c) + c + t


def _skew_c(w):
    z = np.zeros((3, 3), dtype=np.result_type(w, np.float64))
    z[0, 1], z[0, 2], z[1, 2] = -w[2], w[1], -w[0]
    z[1, 0], z[2, 0], z[2, 1] = w[2], -w[1], w[0]
    return z
