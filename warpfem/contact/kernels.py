"""Warp kernels of the contact form: surface vertices against kinematic colliders.

One kernel (``contact_kernel``) loops, per body surface vertex, over the colliders (and over the
triangles of mesh colliders) and does one of several jobs chosen by ``mode`` (one module, two
precision overloads, no variant per collider type):

* ``MODE_ENERGY``: barrier + lagged friction energy into ``acc[slot]`` (float64), the number of
  pairs at distance <= 0 into ``acc[slot + 1]``;
* ``MODE_GRADIENT``: ``g[v] += scale * dE/dx`` (scale = dx/dy), sum of squares into ``acc[slot + 2]``;
* ``MODE_HESSIAN``: ``values[diag[v]] += scale * d2E/dx2`` (SPD-projected; scale = (dx/dy)^2);
* ``MODE_MAX_STEP``: the largest alpha in (0, 1] such that no vertex comes closer to any collider
  than ``eta`` times its current distance along x + alpha dx, dx = scale * g (g holds the direction
  here), atomic min into ``acc[slot + 3]``;
* ``MODE_LAG``: the friction data of the step (normal force, normal, collider displacement of the
  contact point over the step), from the start-of-step positions;
* ``MODE_DISTANCE``: the distance of every (vertex, collider) pair into ``lam``.

Barrier (Li et al. 2020, "Incremental Potential Contact"): b(d) = -(d - dhat)^2 ln(d / dhat) for
0 < d < dhat, 0 beyond, times the stiffness kappa. Every collider distance used here (plane,
sphere exterior, box exterior, point-triangle) is a convex function of the point with gradient n
and a Hessian that is PSD and orthogonal to n, so the SPD projection of the barrier's Hessian
kappa (b'' n n^T + b' d2d/dx2) is exactly kappa b'' n n^T (b' <= 0, b'' >= 0), and the convexity
gives the step bound d(x + a dx) >= d(x) + a n.dx used by ``MODE_MAX_STEP``.

Friction (same paper, lagged): D = mu lambda f0(|u|), u = P (x - x_n - w), x - x_n passed as
x0 + sy * ydisp (x_b - x_n plus s y in a step's potential), P = I - n n^T with the
normal n and normal force lambda from the start of the step, w the collider's motion at the contact
point, f0 the C1 smoothing of |u| over eps = eps_v h (``friction_f0``: a linear spring below eps).
"""

from __future__ import annotations

from typing import Any

import warp as wp

from warpfem.kernels.generic import both_precisions

wp.set_module_options({"enable_backward": False})

PLANE, SPHERE, BOX, MESH = 0, 1, 2, 3
MODE_ENERGY, MODE_GRADIENT, MODE_HESSIAN, MODE_MAX_STEP, MODE_LAG, MODE_DISTANCE = 0, 1, 2, 3, 4, 5


@wp.func
def closest_on_triangle(p: Any, a: Any, b: Any, c: Any):
    """Closest point to p on triangle abc (Ericson, "Real-Time Collision Detection", 5.1.5)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    zero = d1 - d1
    if d1 <= zero and d2 <= zero:
        return a
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= zero and d4 <= d3:
        return b
    vc = d1 * d4 - d3 * d2
    if vc <= zero and d1 >= zero and d3 <= zero:
        return a + ab * (d1 / (d1 - d3))
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= zero and d5 <= d6:
        return c
    vb = d5 * d2 - d1 * d6
    if vb <= zero and d2 >= zero and d6 <= zero:
        return a + ac * (d2 / (d2 - d6))
    va = d3 * d6 - d5 * d4
    if va <= zero and (d4 - d3) >= zero and (d5 - d6) >= zero:
        return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)))
    den = va + vb + vc
    return a + ab * (vb / den) + ac * (vc / den)


@wp.func
def primitive_distance(kind: int, p: Any, a: Any, b: Any):
    """Signed distance of a local-frame point p to a primitive and its gradient (unit normal).
    plane: point a, unit normal b; sphere: centre a, radius b[0]; box: centre a, half extents b."""
    zero = p[0] - p[0]
    one = zero + type(zero)(1.0)
    if kind == 0:
        return wp.dot(b, p - a), b
    if kind == 1:
        r = p - a
        L = wp.length(r)
        if L > zero:
            return L - b[0], r / L
        return -b[0], type(p)(zero, one, zero)
    # box
    r = p - a
    sg = type(p)(one, one, one)
    for k in range(3):
        if r[k] < zero:
            sg[k] = -one
    q = type(p)(wp.abs(r[0]) - b[0], wp.abs(r[1]) - b[1], wp.abs(r[2]) - b[2])
    qmax = wp.max(wp.max(q[0], q[1]), q[2])
    if qmax > zero:
        m = type(p)(wp.max(q[0], zero), wp.max(q[1], zero), wp.max(q[2], zero))
        L = wp.length(m)
        return L, wp.cw_mul(sg, m) / L
    n = type(p)(zero, zero, zero)
    if q[0] >= q[1] and q[0] >= q[2]:
        n[0] = sg[0]
    elif q[1] >= q[2]:
        n[1] = sg[1]
    else:
        n[2] = sg[2]
    return qmax, n


@wp.func
def barrier(d: Any, dhat: Any):
    """(b, b', b'') of b(d) = -(d - dhat)^2 ln(d / dhat) for 0 < d < dhat."""
    two = type(d)(2.0)
    t = d - dhat
    lg = wp.log(d / dhat)
    b0 = -t * t * lg
    b1 = -two * t * lg - t * t / d
    b2 = -two * lg - type(d)(4.0) * t / d + t * t / (d * d)
    return b0, b1, b2


@wp.func
def friction_f0(y: Any, eps: Any):
    """The smoothed |u| of lagged friction: y beyond eps (sliding, force mu lambda), a linear spring
    y^2 / (2 eps) + eps / 2 below it (sticking, force mu lambda y / eps): C1, the half-space friction
    of Li et al. 2020's code. Inside the zone the friction energy is quadratic, so a Newton step
    that lands in it is exact there (docs/contact.md, "Why frictional steps crawl")."""
    if y >= eps:
        return y
    return y * y / (type(y)(2.0) * eps) + eps / type(y)(2.0)


@both_precisions(x="v[]", rots="m[]", trans="v[]", rots0="m[]", trans0="v[]", pa="v[]", pb="v[]", tris="v[]",
                 kappa="s[]", dhat="s[]", mu="s[]", epsf="s[]", lam="s[]", nrm="v[]", wdisp="v[]", x0="v[]",
                 ydisp="v[]", sy="s", eta="s", scale="s", g="v[]", values="m[]")
@wp.kernel
def contact_kernel(
    x: wp.array(dtype=Any),
    surf: wp.array(dtype=wp.int32),
    num_colliders: int,
    kinds: wp.array(dtype=wp.int32),
    rots: wp.array(dtype=Any),
    trans: wp.array(dtype=Any),
    rots0: wp.array(dtype=Any),
    trans0: wp.array(dtype=Any),
    pa: wp.array(dtype=Any),
    pb: wp.array(dtype=Any),
    tri_start: wp.array(dtype=wp.int32),
    tri_count: wp.array(dtype=wp.int32),
    tris: wp.array(dtype=Any),
    kappa: wp.array(dtype=Any),
    dhat: wp.array(dtype=Any),
    mu: wp.array(dtype=Any),
    epsf: wp.array(dtype=Any),
    lam: wp.array(dtype=Any),
    nrm: wp.array(dtype=Any),
    wdisp: wp.array(dtype=Any),
    x0: wp.array(dtype=Any),
    ydisp: wp.array(dtype=Any),
    sy: Any,
    eta: Any,
    scale: Any,
    mode: int,
    g: wp.array(dtype=Any),
    diag: wp.array(dtype=wp.int32),
    values: wp.array(dtype=Any),
    acc: wp.array(dtype=wp.float64),
    slot: int,
):
    i = wp.tid()
    vi = surf[i]
    xi = x[vi]
    zero = eta - eta
    one = zero + type(eta)(1.0)
    energy = wp.float64(0.0)
    grad = xi - xi
    hess = wp.outer(grad, grad)
    alpha = one
    bad = int(0)
    dx = grad
    if mode == 3:
        dx = scale * g[vi]
    for j in range(num_colliders):
        R = rots[j]
        p = wp.transpose(R) * (xi - trans[j])
        dh = dhat[j]
        kp = kappa[j]
        lam_sum = zero
        n_sum = grad - grad
        dmin = dh + dh + one
        kind = kinds[j]
        count = int(1)
        if kind == 3:
            count = tri_count[j]
        for k in range(count):
            d = zero
            nl = grad - grad
            if kind == 3:
                t0 = (tri_start[j] + k) * 3
                q = closest_on_triangle(p, tris[t0], tris[t0 + 1], tris[t0 + 2])
                r = p - q
                d = wp.length(r)
                if d > zero:
                    nl = r / d
            else:
                d, nl = primitive_distance(kind, p, pa[j], pb[j])
            n = R * nl
            dmin = wp.min(dmin, d)
            if d <= zero:
                bad = bad + 1
                alpha = zero
            else:
                if mode == 3:
                    rate = -wp.dot(n, dx)
                    if rate > zero:
                        alpha = wp.min(alpha, (one - eta) * d / rate)
                if d < dh:
                    b0, b1, b2 = barrier(d, dh)
                    if mode == 0:
                        energy += wp.float64(kp * b0)
                    elif mode == 1:
                        grad += (kp * b1) * n
                    elif mode == 2:
                        hess += (kp * b2) * wp.outer(n, n)
                    elif mode == 4:
                        lam_sum += -kp * b1
                        n_sum += (-kp * b1) * n
        p_idx = i * num_colliders + j
        if mode == 5:
            lam[p_idx] = dmin
        elif mode == 4:
            nn = wp.length(n_sum)
            if nn > zero and mu[j] > zero:
                nv = n_sum / nn
                lam[p_idx] = lam_sum
                nrm[p_idx] = nv
                # the collider's motion over the step at the point (start pose -> end pose)
                pl = wp.transpose(rots0[j]) * (xi - trans0[j])
                wdisp[p_idx] = R * pl + trans[j] - xi
            else:
                lam[p_idx] = zero
                nrm[p_idx] = grad - grad
                wdisp[p_idx] = grad - grad
        elif mode <= 2:
            lm = lam[p_idx]
            if lm > zero:
                nv = nrm[p_idx]
                Pm = wp.identity(3, type(eta)) - wp.outer(nv, nv)
                # displacement over the step x - x_n = x0 + sy * ydisp (x0 = x_b - x_n, ydisp = y: no
                # cancellation of positions in float32)
                u = Pm * (x0[vi] + sy * ydisp[vi] - wdisp[p_idx])
                y = wp.length(u)
                eps = epsf[j]
                c = mu[j] * lm
                if mode == 0:
                    energy += wp.float64(c * friction_f0(y, eps))
                elif mode == 1:
                    if y >= eps:
                        grad += (c / y) * u
                    else:
                        grad += (c / eps) * u
                else:
                    if y >= eps:
                        hess += (c / y) * (Pm - wp.outer(u, u) / (y * y))
                    else:
                        hess += (c / eps) * Pm
    if mode == 0:
        wp.atomic_add(acc, slot, energy)
        if bad > 0:
            wp.atomic_add(acc, slot + 1, wp.float64(bad))
    elif mode == 1:
        g[vi] = g[vi] + scale * grad
        wp.atomic_add(acc, slot + 2, wp.float64(wp.dot(grad, grad)) * wp.float64(scale * scale))
    elif mode == 2:
        wp.atomic_add(values, diag[vi], scale * hess)
    elif mode == 3:
        wp.atomic_min(acc, slot + 3, wp.float64(alpha))
