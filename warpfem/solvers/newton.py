"""Newton's method with a backtracking Armijo line search on an incremental potential.

The potential is E(y) over per-vertex vec3 unknowns y with some components fixed (mask). Each
Newton system H d = -g is solved by block-Jacobi PCG on the device (``warpfem.solvers.pcg``).
The loop runs *while* the gradient norm is above the tolerance, and a step length a is accepted
when E(y + a d) <= E(y) + c a d^T g (seed 004, with its slips corrected).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import warp as wp

from warpfem.kernels import linalg as K


@dataclass
class NewtonOptions:
    """Accuracy/speed knobs of the Newton solve (all keyword-settable on the simulator).

    Attributes:
        tol: stop when ||P g|| <= tol * ||P g_0|| (relative gradient norm), P the free-DOF mask.
        atol: absolute floor on ||P g|| (units of the potential's gradient); also declares a step
            converged when its start is already at equilibrium.
        max_iters: cap on Newton iterations per solve.
        cg_tol: relative residual of each PCG solve (inexact Newton).
        max_cg_iters: cap on PCG iterations per Newton iteration.
        max_line_search: cap on step halvings per Newton iteration.
        armijo: sufficient-decrease constant c.
        project_hessian: SPD-project each element's dP/dF (needed for non-convex materials far from
            rest; off gives the exact Hessian).
    """

    tol: float = 1e-6
    atol: float = 0.0
    max_iters: int = 30
    cg_tol: float = 1e-4
    max_cg_iters: int = 2000
    max_line_search: int = 30
    armijo: float = 1e-4
    project_hessian: bool = True

    def validate(self):
        for name in ("tol", "cg_tol"):
            v = getattr(self, name)
            if not (np.isfinite(v) and 0.0 < v < 1.0):
                raise ValueError(f"{name} must be in (0, 1), got {v!r}")
        if not (np.isfinite(self.atol) and self.atol >= 0.0):
            raise ValueError(f"atol must be >= 0, got {self.atol!r}")
        for name in ("max_iters", "max_cg_iters", "max_line_search"):
            v = getattr(self, name)
            if int(v) != v or v < 1:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
        if not 0.0 < self.armijo < 0.5:
            raise ValueError(f"armijo must be in (0, 0.5), got {self.armijo!r}")


@dataclass
class SolveStats:
    """What one nonlinear solve (a time step or a static load step) did.

    ``converged`` is False when an iteration cap was hit or the line search could not decrease
    the energy; ``reason`` says which. ``residual`` is the final ||P g|| / ||P g_0||.
    """

    converged: bool = False
    reason: str = ""
    newton_iterations: int = 0
    cg_iterations: int = 0
    line_search_steps: int = 0
    residual: float = 0.0
    gradient_norm: float = 0.0
    energy: float = 0.0
    seconds: float = 0.0
    linear_iterations: int = 0  # iterations of the linear solver (CG iterations; 1 per direct solve)
    host_syncs: int = 0  # host read-backs made inside the linear solves (see warpfem.solvers.linear)
    history: list = field(default_factory=list)

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        d.pop("history")
        return d


class SolveFailed(RuntimeError):
    """A solve produced NaN/inf or (with ``require_convergence``) did not converge.

    The simulator's state is left as it was before the failed step; ``stats`` says what happened.
    """

    def __init__(self, message: str, stats: SolveStats):
        super().__init__(message)
        self.stats = stats


def newton_solve(problem, y, opts: NewtonOptions, pcg) -> SolveStats:
    """Minimise ``problem``'s potential over ``y`` (device array, updated in place).

    ``problem`` provides ``energy(y) -> (E, magnitude)``, ``gradient(y, g) -> magnitude`` (g masked),
    ``resolution_scale(y)`` (max |y| + max |x| / s, the scale of y's round-off),
    ``assemble_hessian(y) -> values``, ``mask`` and ``n``; ``pcg`` a ``BlockJacobiPCG``.
    """
    st = SolveStats()
    dev, n, s = pcg.device, problem.n, pcg.scalar
    vec = y.dtype
    g = wp.zeros(n, dtype=vec, device=dev)
    d = wp.zeros(n, dtype=vec, device=dev)
    rhs = wp.zeros(n, dtype=vec, device=dev)
    y_try = wp.zeros(n, dtype=vec, device=dev)
    eps_mach = float(np.finfo(np.float32 if s == wp.float32 else np.float64).eps)

    E, mag = problem.energy(y)
    gmag = problem.gradient(y, g)
    gnorm0 = np.sqrt(pcg.dot(g, g))
    # Below this the gradient is round-off of its own terms: no precision can reduce it further.
    floor_factor = 64.0 * eps_mach
    st.energy, st.gradient_norm = E, gnorm0
    if not (np.isfinite(E) and np.isfinite(gnorm0)):
        st.reason = "non-finite energy or gradient at the start"
        return st
    if gnorm0 <= opts.atol or gnorm0 <= floor_factor * gmag:
        st.converged, st.reason = True, "already at equilibrium"
        return st
    gnorm = gnorm0
    for _ in range(opts.max_iters):
        values = problem.assemble_hessian(y)
        wp.launch(K.scale_copy_kernel, dim=n, inputs=[g, s(-1.0), rhs], device=dev)
        res = pcg.solve(values, problem.mask, rhs, d, tol=opts.cg_tol, maxiter=opts.max_cg_iters)
        st.cg_iterations += res.iterations
        st.linear_iterations += res.iterations
        st.host_syncs += getattr(res, "host_syncs", 0)
        gd = pcg.dot(g, d)
        if not (gd < 0.0):  # not a descent direction (indefinite Hessian or CG breakdown)
            wp.launch(K.block_apply_kernel, dim=n, inputs=[pcg.inv_diag, rhs, d], device=dev)
            gd = pcg.dot(g, d)
            if not (gd < 0.0):
                st.reason = "no descent direction"
                break
        # A Newton step below the resolution of the unknowns (and of x = xb + s y) in this precision
        # cannot be taken: the state is as converged as the precision allows.
        if np.abs(d.numpy()).max() <= 8.0 * eps_mach * problem.resolution_scale(y):
            st.converged = True
            st.reason = "at the precision limit (Newton step below the resolution of the positions)"
            break
        alpha, accepted = 1.0, False
        noise = 16.0 * eps_mach * mag
        for _ls in range(opts.max_line_search):
            wp.launch(K.lincomb_kernel, dim=n, inputs=[s(1.0), y, s(alpha), d, y_try], device=dev)
            E_try, mag_try = problem.energy(y_try)
            if np.isfinite(E_try) and E_try <= E + opts.armijo * alpha * gd + noise:
                accepted = True
                break
            alpha *= 0.5
            st.line_search_steps += 1
        if not accepted:
            if gnorm <= 1e3 * floor_factor * gmag:
                st.converged, st.reason = True, "at the precision limit (energy differences below round-off)"
            else:
                st.reason = "line search could not decrease the energy"
            break
        wp.copy(y, y_try)
        E, mag = E_try, mag_try
        gmag = problem.gradient(y, g)
        gnorm = np.sqrt(pcg.dot(g, g))
        st.newton_iterations += 1
        st.history.append((E, gnorm, alpha, res.iterations))
        if not np.isfinite(gnorm):
            st.reason = "non-finite gradient"
            break
        if gnorm <= opts.tol * gnorm0 or gnorm <= opts.atol:
            st.converged, st.reason = True, "gradient below tolerance"
            break
        if gnorm <= floor_factor * gmag:
            st.converged, st.reason = True, "gradient at the round-off floor of its terms"
            break
    else:
        st.reason = f"reached max_iters={opts.max_iters}"
    st.energy, st.gradient_norm, st.residual = E, gnorm, gnorm / gnorm0
    return st
