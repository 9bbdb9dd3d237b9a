"""Warp kernels of the contact form: surface vertices against kinematic colliders.

One kernel (``contact_kernel``) loops, per body surface vertex, over the colliders (and over the
primitives of each: one, or a mesh collider's triangles), gets each distance from
``primitive_distance`` (generated from the collider classes' Warp distances, below) and does one of
several jobs chosen by ``mode`` (one module, two precision overloads, no variant per collider type):

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

import re
from typing import Any

import warp as wp

from warpfem.contact.colliders import add_registry_listener, registered_colliders
from warpfem.kernels.generic import both_precisions, splittable

wp.set_module_options({"enable_backward": False})

MODE_ENERGY, MODE_GRADIENT, MODE_HESSIAN, MODE_MAX_STEP, MODE_LAG, MODE_DISTANCE = 0, 1, 2, 3, 4, 5


# -- the distance dispatch, generated from the collider registry ----------------------------------------
# ``primitive_distance(kind, p, a, b, tris, t0)`` is a chain of Warp funcs, one link per registered
# collider class (warpfem.contact.colliders.register_collider), each testing its kind and calling the
# class's ``distance_func`` -- with (a, b) (``distance_args = "params"``) or with triangle
# tris[t0], tris[t0 + 1], tris[t0 + 2] (``"triangle"``) -- or the next link; an unknown kind gives
# distance -1 (inside: the pair fails the step; Python validates kinds). The chain is generated again
# when the registry changes, and ``contact_kernel`` resolves the name when its module is hashed and
# built: each link is named after its type and kind, and Warp's module hash covers a func's name,
# source, captured constants and the funcs it calls, so a new collider type rebuilds this module
# once and a cached build for other types is never reused (as the material dispatch,
# warpfem/materials/dispatch.py). One kernel module for every type: no variant per collider type.
@wp.func
def _no_collider(kind: int, p: Any, a: Any, b: Any, tris: wp.array(dtype=Any), t0: int):
    zero = p[0] - p[0]
    return zero - (zero + type(zero)(1.0)), type(p)(zero, zero, zero)


def _named(fn, cls):
    fn.__name__ = fn.__qualname__ = f"primitive_distance__{re.sub(r'[^0-9A-Za-z_]', '_', cls.type_name)}_k{cls.kind}"
    return wp.func(fn)


def _link_params(cls, rest):
    K, f = wp.constant(cls.kind), cls.distance_func

    def params_link(kind: int, p: Any, a: Any, b: Any, tris: wp.array(dtype=Any), t0: int):
        if kind == K:
            d, n = f(p, a, b)
            return d, n
        d, n = rest(kind, p, a, b, tris, t0)
        return d, n

    return _named(params_link, cls)


def _link_triangle(cls, rest):
    K, f = wp.constant(cls.kind), cls.distance_func

    def triangle_link(kind: int, p: Any, a: Any, b: Any, tris: wp.array(dtype=Any), t0: int):
        if kind == K:
            d, n = f(p, tris[t0], tris[t0 + 1], tris[t0 + 2])
            return d, n
        d, n = rest(kind, p, a, b, tris, t0)
        return d, n

    return _named(triangle_link, cls)


def _build_dispatch():
    """(Re)generate ``primitive_distance`` over the registered colliders; the first registered is
    tested first."""
    global primitive_distance
    chain = _no_collider
    for cls in reversed(registered_colliders()):
        chain = (_link_triangle if cls.distance_args == "triangle" else _link_params)(cls, chain)
    primitive_distance = chain
    wp.get_module(__name__).mark_modified()  # contact_kernel resolves the new chain at its next build


primitive_distance = _no_collider
_build_dispatch()
add_registry_listener(_build_dispatch)


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


# split across CPU threads (``kernels.generic.splittable``): each thread owns one surface vertex's
# gradient entry and diagonal block; energies, magnitudes (sums) and the step bound (a minimum) go
# through rows of partial results
@splittable("reduce", 1024, acc=29, slot=30, n_add=3, n_min=1)
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
    prim_count: wp.array(dtype=wp.int32),
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
    start: int,
    row_block: int,
    row_stride: int,
):
    i = wp.tid() + start
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
        for k in range(prim_count[j]):
            d, nl = primitive_distance(kind, p, pa[j], pb[j], tris, (tri_start[j] + k) * 3)
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
    r = slot + (i // row_block) * row_stride  # rows of partial results when split (``kernels.generic``)
    if mode == 0:
        wp.atomic_add(acc, r, energy)
        if bad > 0:
            wp.atomic_add(acc, r + 1, wp.float64(bad))
    elif mode == 1:
        g[vi] = g[vi] + scale * grad
        wp.atomic_add(acc, r + 2, wp.float64(wp.dot(grad, grad)) * wp.float64(scale * scale))
    elif mode == 2:
        wp.atomic_add(values, diag[vi], scale * hess)  # (vi: one per thread, the surface's vertices are unique)
    elif mode == 3:
        wp.atomic_min(acc, r + 3, wp.float64(alpha))
