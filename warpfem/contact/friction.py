"""The stick/slip-aware Newton step of lagged friction (a direction filter of the contact forms).

Lagged friction adds mu lambda f0(|u|) per contact, u the tangential displacement over the step;
f0 (IPC's C1 smoothing, ``kernels.friction_f0``) is quadratic in a sticking zone |u| < eps = eps_v h
and linear (slope 1) beyond it. Outside the zone its Hessian has no curvature along u, so the
Newton model of a contact that should stick sees the friction force as a constant and carries the
contact straight across the zone: by the friction force over the stiffness of the rest of the
system, typically tens to thousands of eps. A line search can only shorten the whole step with
one length for every vertex, and halves it until the overshooting contacts land in their zones:
measured, most of the extra Newton iterations and all the line-search halvings of frictional
contact steps come from this (docs/contact.md, "Why frictional steps crawl").

The same holds for a contact whose step passes *near* the zone: along a segment that goes by
u = 0 at a distance b, |u| falls to b at the closest point and rises after it, the friction force
turning against the step, while the Newton model, curved by mu lambda / |u0| across u only, sees
a force that keeps pulling along the step (measured on the bunny's impact: with only the steps
through the zone cut, the line search took 1/8 - 1/2 of most steps after friction's lag update;
cutting these too removed every halving; docs/contact.md, "Steps that pass near a sticking zone").

The filter acts per collider contact (a surface vertex against a collider; surface pairs are not
filtered: cutting the steps of both sides of a pair slowed the stack's impacts, docs/contact.md)
on the Newton direction d before the line search: with u(t) = u0 + t du
the contact's tangential displacement along the step (du = s P d, P = I - n n^T), when the contact
starts outside its sticking zone (|u0| >= eps) and the full step goes past the point of the
segment closest to u = 0 (at t* = -u0.du / du.du in (0, 1)), the tangential part of the vertex's
step is cut to t* of itself: the contact lands where its friction energy is lowest along the step.
Normal components, free vertices and contacts that slide on (t* <= 0: the step does not move them
towards u = 0) are left alone. The minimiser of the potential is unchanged (only the path to it),
and the line search still checks sufficient decrease along the filtered direction, which the
Newton loop uses as it is (its slope g.d is measured on it).
"""

from __future__ import annotations

from typing import Any

import warp as wp

from warpfem.kernels.generic import both_precisions

wp.set_module_options({"enable_backward": False})


@wp.func
def crossing_fraction(u: Any, du: Any, eps: Any):
    """t* in (0, 1) when the segment u + t du (t in [0, 1]) starts outside the ball |u| < eps and
    goes past its point closest to u = 0 (t* = -u.du / du.du inside the segment): there the
    friction energy, increasing in |u|, is lowest along the step; 1 otherwise."""
    zero = eps - eps
    one = zero + type(eps)(1.0)
    q = wp.dot(du, du)
    if wp.length(u) < eps or q <= zero:
        return one
    t = -wp.dot(u, du) / q
    if t <= zero or t >= one:
        return one
    return t


@wp.func
def step_crossing(n: Any, r: Any, step: Any, sy: Any, eps: Any):
    """:func:`crossing_fraction` of a collider contact with normal n whose relative position is r
    (dbase + sy y - w) under the vertex step ``step`` (in y): tangential parts of both."""
    u = r - wp.dot(r, n) * n
    dd = sy * step
    du = dd - wp.dot(dd, n) * n
    return crossing_fraction(u, du, eps)


@both_precisions(lam="s[]", nrm="v[]", wdisp="v[]", dbase="v[]", y="v[]", sy="s", epsf="s[]", mu="s[]", d="v[]")
@wp.kernel
def collider_filter_kernel(surf: wp.array(dtype=wp.int32), num_colliders: int, lam: wp.array(dtype=Any),
                           nrm: wp.array(dtype=Any), wdisp: wp.array(dtype=Any), dbase: wp.array(dtype=Any),
                           y: wp.array(dtype=Any), sy: Any, epsf: wp.array(dtype=Any), mu: wp.array(dtype=Any),
                           d: wp.array(dtype=Any), count: wp.array(dtype=wp.int32), tally: wp.array(dtype=wp.float64),
                           tally_at: int):
    """Per surface vertex: its step d (in y) with the tangential part cut where a frictional
    collider contact's step goes past its point closest to u = 0 (module docstring). u = P (dbase + sy y - w).
    The cut contacts are added to ``count[0]`` and to ``tally[tally_at]`` (a slot of an accumulator
    read back with other numbers: the Newton loop learns whether this call cut anything without a
    read-back of its own)."""
    i = wp.tid()
    vi = surf[i]
    di = d[vi]
    zero = sy - sy
    cut = int(0)
    for j in range(num_colliders):
        p = i * num_colliders + j
        lm = lam[p]
        if lm > zero and mu[j] > zero:
            n = nrm[p]
            t = step_crossing(n, dbase[vi] + sy * y[vi] - wdisp[p], di, sy, epsf[j])
            if t < zero + type(sy)(1.0):
                dn = wp.dot(di, n) * n
                di = dn + t * (di - dn)
                cut = cut + 1
    if cut > 0:
        d[vi] = di
        wp.atomic_add(count, 0, cut)
        wp.atomic_add(tally, tally_at, wp.float64(cut))


@both_precisions(lam="s[]", nrm="v[]", wdisp="v[]", dbase="v[]", y="v[]", sy="s", epsf="s[]", mu="s[]", d_raw="v[]",
                 d="v[]", values="m[]", rhs="v[]", weight="s")
@wp.kernel
def collider_pin_kernel(surf: wp.array(dtype=wp.int32), num_colliders: int, lam: wp.array(dtype=Any),
                        nrm: wp.array(dtype=Any), wdisp: wp.array(dtype=Any), dbase: wp.array(dtype=Any),
                        y: wp.array(dtype=Any), sy: Any, epsf: wp.array(dtype=Any), mu: wp.array(dtype=Any),
                        d_raw: wp.array(dtype=Any), d: wp.array(dtype=Any), diag: wp.array(dtype=wp.int32),
                        values: wp.array(dtype=Any), rhs: wp.array(dtype=Any), weight: Any,
                        count: wp.array(dtype=wp.int32)):
    """Per surface vertex whose frictional collider contact the unfiltered step ``d_raw`` carries
    past its point closest to u = 0 (the contacts :func:`collider_filter_kernel` cuts): a tangential spring
    k P (P = I - n n^T, k = ``weight`` x the mean diagonal of the vertex's Newton block) added to
    the block and k P d (d the filtered step) to the right-hand side, so that a second solve of the
    Newton system holds these contacts' tangential steps at their cut value and lets the rest of
    the body follow them (``NewtonOptions.friction_pin``)."""
    i = wp.tid()
    vi = surf[i]
    dr = d_raw[vi]
    zero = sy - sy
    pm = wp.outer(dr - dr, dr - dr)
    pinned = int(0)
    for j in range(num_colliders):
        p = i * num_colliders + j
        lm = lam[p]
        if lm > zero and mu[j] > zero:
            n = nrm[p]
            t = step_crossing(n, dbase[vi] + sy * y[vi] - wdisp[p], dr, sy, epsf[j])
            if t < zero + type(sy)(1.0):
                pm = pm + wp.identity(3, type(sy)) - wp.outer(n, n)
                pinned = pinned + 1
    if pinned > 0:
        b = diag[vi]
        blk = values[b]
        k = weight * (blk[0, 0] + blk[1, 1] + blk[2, 2]) / type(sy)(3.0)
        values[b] = blk + k * pm
        rhs[vi] = rhs[vi] + k * (pm * d[vi])
        wp.atomic_add(count, 0, pinned)
