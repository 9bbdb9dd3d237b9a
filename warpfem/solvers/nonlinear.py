"""Newton's method with a backtracking Armijo line search on an incremental potential: the one
loop every simulator uses (full space, stiffness warping's potential, reduced).

The potential is E(y) over unknowns y (per-vertex vec3 device arrays with some components fixed by
a mask, or a reduced coordinate vector), given as a ``problem`` (``warpfem.solvers.forms``
for the full space, ``warpfem.reduced.simulator`` for subspaces) that also solves its Newton
systems H d = -g (sparse on the device, or dense). The loop runs *while* the gradient norm is above
the tolerance (converged: ||P g|| <= tol * ||P g_ref||, g_ref the gradient at the start of the solve
or a given reference, e.g. the start of the time step a continuing solve belongs to), and a step
length a is accepted when E(y + a d) <= E(y) + c a d^T g (Nocedal & Wright, "Numerical
Optimization", ch. 3, backtracking with the Armijo condition).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from warpfem.solvers.linear.forcing import FORCING, ForcingTerms


#: the values of ``NewtonOptions.hessian_projection``
#: with ``friction_filter``: when the line search cut the filtered Newton step below this length,
#: the unfiltered direction is tried too (at most ``UNFILTERED_HALVINGS`` halvings from its own
#: collision bound) and taken when its point is lower (docs/contact.md, "Why frictional steps crawl")
UNFILTERED_BELOW = 0.3
UNFILTERED_HALVINGS = 6
HESSIAN_PROJECTIONS = ("always", "on_demand")


def indefinite_system(lin) -> bool:
    """Whether a linear solve's result says its matrix was not positive definite: PCG met
    non-positive curvature, a direct factorisation failed or needed a diagonal shift, or
    (near) null directions were deflated."""
    return bool(getattr(lin, "negative_curvature", False) or getattr(lin, "failed", "")
                or getattr(lin, "shift", 0.0) > 0.0 or getattr(lin, "deflated", 0) > 0)


@dataclass
class NewtonOptions:
    """Accuracy/speed knobs of the Newton solve (all keyword-settable on the simulator).

    Attributes:
        tol: converged when ||P g|| <= tol * ||P g_ref|| (relative gradient norm), P the free-DOF
            mask and g_ref the gradient at the start of the solve, or the ``reference`` given to
            :func:`newton_solve` (a solve that continues a step passes the step's own start
            gradient, so a whole step has one tolerance; friction's lag updates happen inside the
            one solve and keep its reference).
        atol: absolute floor on ||P g|| (units of the potential's gradient): ||P g|| <= atol is
            converged too; also declares a step converged when its start is already at equilibrium.
        max_iters: cap on Newton iterations per solve.
        cg_tol: relative residual of each PCG solve (inexact Newton).
        max_cg_iters: cap on PCG iterations per Newton iteration.
        max_line_search: cap on step halvings per Newton iteration.
        armijo: sufficient-decrease constant c.
        project_hessian: SPD-project each element's dP/dF (needed for non-convex materials far from
            rest; off gives the exact Hessian).
        forcing: "fixed" (every linear solve to ``cg_tol``) or "eisenstat_walker" (adaptive
            tolerances, loose far from the solution, never tighter than ``cg_tol``;
            :mod:`warpfem.solvers.linear.forcing`, measured effect in docs/linear_solvers.md).
        hessian_projection: with ``project_hessian``, "always" (every Newton system from the
            projected Hessian: projected Newton) or "on_demand" (each solve starts from the exact
            Hessian and switches to the projected one for the rest of the solve as soon as a
            Newton system is found indefinite, its direction is not a descent direction, or its
            line search fails: Longva et al. 2023, "Pitfalls of Projection: A study of Newton-type
            solvers for incremental potentials", project-on-demand Newton). The projection's
            clamping makes projected Newton converge linearly; on demand keeps Newton's quadratic
            convergence where the exact Hessian is definite (measured in docs/integrators.md).
        friction_filter: with lagged friction in the potential, cut each contact's tangential step
            where the Newton step would carry it past its point closest to zero tangential
            displacement, through its sticking zone or near it (stick/slip-aware steps,
            :mod:`warpfem.contact.friction`). Changes the path to the step's solution, not the
            solution; off: the plain Newton direction (measured effect in docs/contact.md). When
            the line search cuts a filtered step below 0.3 of its length, the unfiltered
            direction is tried as well and taken where it goes lower (a cut that fights the
            elastic forces).
        extrapolate: after a full Newton step that the line search accepted, when the energy
            still falls steeply along the step (its slope there below half the start's), try the
            secant model's longer step along it and keep it if the energy is lower: corrects the
            short steps of projected Hessians (contact pairs, elements). Changes the path, not
            the solution; one energy and gradient evaluation per try (measured in docs/contact.md).
        step_tol: a second stopping test, on the Newton step (as in "Incremental Potential
            Contact"): the solve is also converged after a full step (step length 1) whose Newton
            direction moves no vertex faster than ``step_tol`` body diagonals per second over the
            time step (|x_{k+1} - x_k|_inf / h <= step_tol x L, L the bounding-box diagonal of the
            rest mesh; with the friction filter, the unfiltered direction's move counts too), taken
            only once the step's friction lag update is made. 0 (default): off, the relative
            gradient alone decides. Full-space dynamics only (static solves and reduced models ignore
            it); measured effect on iterations and accuracy in docs/contact.md ("Where a contact
            step's Newton iterations go"): it saves little where Newton converges quadratically and
            costs accuracy where it converges linearly, hence off.
        friction_pin: with ``friction_filter``, a second solve of the Newton system in the
            iterations where the filter cut a contact's step: the cut contacts' tangential steps
            held at their cut values by springs of ``friction_pin`` times their vertex's mean
            diagonal Newton entry, so that the rest of the body follows them (the cuts alone strain
            the elements around the cut vertices, and the line search then shortens every
            vertex's step). The pinned direction is taken when it is a descent direction. Default
            3; 0: off (the filtered direction alone). Changes the path, not the potential's minimiser
            (friction's lag update inside the solve is taken on the path, so it moves with it);
            costs one more linear solve in those iterations (measured in docs/contact.md, "What an impact
            step costs").
    """

    tol: float = 1e-6
    atol: float = 0.0
    max_iters: int = 30
    cg_tol: float = 1e-4
    max_cg_iters: int = 2000
    max_line_search: int = 30
    armijo: float = 1e-4
    project_hessian: bool = True
    forcing: str = "fixed"
    hessian_projection: str = "on_demand"
    friction_filter: bool = True
    extrapolate: bool = True
    step_tol: float = 0.0
    friction_pin: float = 3.0

    def validate(self):
        for name in ("tol", "cg_tol"):
            v = getattr(self, name)
            if not (np.isfinite(v) and 0.0 < v < 1.0):
                raise ValueError(f"{name} must be in (0, 1), got {v!r}")
        if not (np.isfinite(self.atol) and self.atol >= 0.0):
            raise ValueError(f"atol must be >= 0, got {self.atol!r}")
        if not (np.isfinite(self.friction_pin) and self.friction_pin >= 0.0):
            raise ValueError(f"friction_pin must be >= 0 (0: off), got {self.friction_pin!r}")
        if not (np.isfinite(self.step_tol) and self.step_tol >= 0.0):
            raise ValueError(f"step_tol must be >= 0 (0: off), got {self.step_tol!r}")
        for name in ("max_iters", "max_cg_iters", "max_line_search"):
            v = getattr(self, name)
            if int(v) != v or v < 1:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
        if not 0.0 < self.armijo < 0.5:
            raise ValueError(f"armijo must be in (0, 0.5), got {self.armijo!r}")
        if self.forcing not in FORCING:
            raise ValueError(f"forcing must be one of {FORCING}, got {self.forcing!r}")
        if self.hessian_projection not in HESSIAN_PROJECTIONS:
            raise ValueError(f"hessian_projection must be one of {HESSIAN_PROJECTIONS}, got {self.hessian_projection!r}")


@dataclass
class SolveStats:
    """What one nonlinear solve (a time step or a static load step) did.

    ``converged`` is True when the final gradient passes the tolerance test, ||P g|| <= tol *
    ``initial_gradient`` (or <= atol), whatever stopped the loop, when the solve stopped at
    the precision limit of its arithmetic, or by the step test of ``NewtonOptions.step_tol``
    (``reason`` says which); it is False when an iteration cap
    was hit, the line search could not decrease the energy or there was no descent direction with
    the gradient above the tolerance; ``reason`` says which. ``residual`` is the final ||P g|| /
    ``initial_gradient`` (the relative gradient), ``tolerance`` the ``tol`` it was tested against:
    a solve with ``residual <= tolerance`` is never reported as not converged.
    ``initial_gradient`` is the reference ||P g_ref||: the gradient norm at the start of the solve,
    or the ``reference`` given to :func:`newton_solve` (for a solve that continues a time step:
    the gradient at the start of the step's first solve).
    """

    converged: bool = False
    reason: str = ""
    newton_iterations: int = 0
    cg_iterations: int = 0
    line_search_steps: int = 0
    residual: float = 0.0
    gradient_norm: float = 0.0
    initial_gradient: float = 0.0  # the reference ||P g_ref|| of the tolerance test (and of residual)
    tolerance: float = 0.0  # the relative tolerance tol the solve was tested against
    energy: float = 0.0
    seconds: float = 0.0
    linear_iterations: int = 0  # iterations of the linear solver (CG iterations; 1 per direct solve)
    host_syncs: int = 0  # host read-backs made inside the linear solves (see warpfem.solvers.linear)
    newton_syncs: int = 0  # host read-backs of the Newton loop outside the linear solves (energies, gradients, checks)
    launches: int = 0  # kernel launches of the step (kernels.generic.COUNTERS, recorded PCG launches included)
    hessian_evaluations: int = 0  # Newton matrices evaluated (counted by the reduced simulator, which keeps its matrix)
    singular_solves: int = 0  # Newton systems a direct solve found singular or indefinite (shifted and/or deflated)
    friction_iterations: int = 0  # updates of friction's lagged normal forces inside the solve (Simulator)
    friction_kept: int = 0  # lag updates not made: the forces changed by at most friction_update_tol (Simulator)
    projected_retries: int = 0  # hessian_projection="on_demand": Newton systems solved again with the projected Hessian
    adaptations: int = 0  # Newton iterations after which the potential changed (an adaptive barrier stiffness doubled)
    extrapolations: int = 0  # Newton iterations whose accepted step was lengthened (NewtonOptions.extrapolate)
    unfiltered_steps: int = 0  # Newton iterations that took the unfiltered direction (friction_filter's fallback)
    history: list = field(default_factory=list)

    #: the work counters a step made of several solves (load steps) sums
    COUNTS = ("newton_iterations", "cg_iterations", "line_search_steps", "linear_iterations", "host_syncs",
              "newton_syncs", "hessian_evaluations", "singular_solves", "projected_retries", "adaptations",
              "extrapolations", "unfiltered_steps")

    def add_counts(self, other: "SolveStats") -> None:
        """Add ``other``'s work counters (``COUNTS``) to this one's."""
        for name in self.COUNTS:
            setattr(self, name, getattr(self, name) + getattr(other, name))

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


class NotConvergedWarning(RuntimeWarning):
    """A step (or static solve) was accepted without converging (``require_convergence`` off):
    the warning of ``sim.step()``; its message states the reason, the relative gradient and the
    tolerance. A :class:`RuntimeWarning`, so filters on that category keep working; a scene run
    (``SceneRun.run``, ``warpfem run``) reports these as log lines instead."""


def not_converged_message(stats: SolveStats, what: str) -> str:
    """One line saying why ``what`` (e.g. "step 12") did not converge: its reason, and its relative
    gradient against the tolerance it was tested with."""
    tol = f" > tol {stats.tolerance:.1e}" if stats.tolerance > 0.0 else ""
    return f"{what} did not converge: {stats.reason} (relative gradient {stats.residual:.2e}{tol})"


def newton_solve(problem, y, opts: NewtonOptions, reference=None) -> SolveStats:
    """Minimise ``problem``'s potential over ``y`` (updated in place): Newton with a backtracking
    Armijo line search, one loop for every simulator.

    The solve is converged when ||P g|| <= ``opts.tol`` * ref (or <= ``opts.atol``), ref the
    gradient norm at ``y`` on entry, or ``reference`` when given (> 0): a solve that continues
    another one (from an almost converged point of a slightly changed potential) passes the first
    solve's ``initial_gradient``, so that both are held to the same tolerance; a start already
    within it is converged without an iteration.
    ``SolveStats.residual`` is ||P g|| / ref, ``SolveStats.initial_gradient`` is ref.

    ``problem`` provides (vectors are whatever it uses: device arrays, numpy arrays):

    * ``energy(y) -> (E, magnitude)`` and ``gradient(y, g) -> (magnitude, ||g||)`` (g masked),
      the magnitudes being the sums of the sizes of their terms (the scale of their round-off);
    * ``solve_newton_system(y, g, d, opts)``: d ~ -H(y)^-1 g (a sparse iterative or direct solve,
      or a dense one for reduced models); returns its iteration count, or a result with
      ``iterations`` and ``host_syncs``;
    * ``fallback_direction(g, d)``: a descent direction (preconditioned -g) when d is not one;
    * ``direction_check(y, g, d) -> (g . d, negligible)``: negligible when d is below the resolution
      of the unknowns (and positions) in the working precision;
    * ``new_vector()`` (optionally ``vectors()``: three work vectors g, d, y_try it keeps, distinct
      from y), ``trial(y, alpha, d, out)`` (out = y + alpha d), ``assign(dst, src)``;
    * optionally ``refresh_direction() -> bool``: after a failed line search, True when the problem
      can offer a better direction from the same point (the reduced simulator's kept Newton matrix:
      the next ``solve_newton_system`` evaluates it afresh), and the loop tries again;
    * optionally ``max_step(y, d) -> alpha_max``: the line search starts at min(1, alpha_max)
      (contact's continuous-collision bound: no step crosses a collider);
    * optionally ``after_iteration(y, alpha, residual=r) -> bool``: called after each accepted
      iteration (alpha: its step length, r: the gradient norm relative to the reference); True when
      the potential itself changed there (contact's adaptive barrier stiffness doubled), and its
      energy and gradient at y are evaluated again (``evaluate``);
    * optionally ``step_limit(step_tol) -> limit``, ``direction_max(y, g, d, limit) -> max |d|`` and
      ``lag_pending() -> bool`` (``opts.step_tol``): the step test's limit on the largest
      component of a Newton direction (0: no test), that component (the larger of the direction's
      and, where a filter changed it, the unfiltered one's), and whether the potential will still
      change in this solve (a lag update to come: the step test waits for it);
    * ``eps`` (machine epsilon of the unknowns) and ``gradient_test_below``: when > 0 and a full
      step changes the energy, or the Newton model predicts it to change (|g.d|), by less than that
      fraction of its magnitude (below what the energy sum resolves), the step is accepted if it
      halves the gradient norm.
    """
    st = SolveStats()
    syncs0 = getattr(problem, "host_syncs", None)
    # project-on-demand Newton: the exact Hessian until a Newton system says it is not enough
    on_demand = (opts.project_hessian and opts.hessian_projection == "on_demand"
                 and hasattr(problem, "set_projection"))
    if on_demand:
        problem.set_projection(False)
    if hasattr(problem, "vectors"):  # work vectors the problem keeps (no allocation per solve)
        g, d, y_try = problem.vectors()
    else:
        g, d, y_try = problem.new_vector(), problem.new_vector(), problem.new_vector()
    # a problem with trial_step evaluates the direction check, the energy and the gradient of a
    # full step with one read-back (into a second gradient vector, swapped with g on acceptance)
    fused = hasattr(problem, "trial_step") and hasattr(problem, "work")
    g_try = problem.work.g_try if fused else None
    eps_mach = problem.eps
    after_iteration = getattr(problem, "after_iteration", None)

    # with newton_step, the start's energy and gradient are read with the first iteration's numbers
    # inexact Newton's forcing terms (None: every solve to cg_tol); the first solve's tolerance is
    # known before the start's gradient (eta0), so it can ride with the start's evaluation
    forcing = None if opts.forcing == "fixed" else ForcingTerms(opts.forcing, opts.cg_tol, opts.tol)
    first = None
    if fused and hasattr(problem, "newton_step") and not problem.bounds_step() and opts.max_iters > 0:
        opts0 = opts if forcing is None else replace(opts, cg_tol=forcing.first_tolerance())
        lin0, pre0, (E, mag, gmag, gnorm0) = problem.newton_step(y, g, d, y_try, g_try, opts0, start=True)
        first = (lin0, pre0)
    elif hasattr(problem, "evaluate"):  # energy and gradient with one read-back
        E, mag, gmag, gnorm0 = problem.evaluate(y, g)
    else:
        E, mag = problem.energy(y)
        gmag, gnorm0 = problem.gradient(y, g)
    # Below this the gradient is round-off of its own terms: no precision can reduce it further.
    floor_factor = 64.0 * eps_mach
    st.energy, st.gradient_norm = E, gnorm0
    # the reference of the tolerance test: the start's gradient, or the given one (a re-solve)
    ref = float(reference) if reference is not None and np.isfinite(reference) and reference > 0.0 else gnorm0
    st.initial_gradient, st.tolerance = ref, opts.tol

    def relative(gn):
        """||P g|| / ref (0 at an exact equilibrium; inf / nan when not finite)."""
        if ref > 0.0 and np.isfinite(ref):
            return gn / ref
        return 0.0 if gn == 0.0 else float("nan")

    def within_tolerance(gn):
        return bool(np.isfinite(gn) and (gn <= opts.tol * ref or gn <= opts.atol))

    def finish():
        st.residual = relative(st.gradient_norm)
        if not st.converged and within_tolerance(st.gradient_norm) and np.isfinite(st.energy):
            # whatever stopped the loop (max_iters, the line search, no descent direction), the
            # gradient passes the tolerance test: the solve is converged, and says why it stopped
            st.converged = True
            st.reason = (f"gradient within tolerance (relative {st.residual:.2e} <= tol {opts.tol:.1e}) "
                         f"when the solve stopped: {st.reason}")
        if on_demand:
            problem.set_projection(True)
        if syncs0 is not None:
            st.newton_syncs = problem.host_syncs - syncs0
        return st

    if not (np.isfinite(E) and np.isfinite(gnorm0)):
        st.reason = "non-finite energy or gradient at the start"
        return finish()
    if gnorm0 <= opts.atol or gnorm0 <= floor_factor * gmag:
        st.converged, st.reason = True, "already at equilibrium"
        return finish()
    if gnorm0 <= opts.tol * ref:  # only with a reference (tol < 1): a re-solve's start within the tolerance
        st.converged = True
        st.reason = (f"start already within tolerance (relative gradient {relative(gnorm0):.2e} "
                     f"<= tol {opts.tol:.1e})")
        return finish()
    gnorm = gnorm0
    # the step test's limit on max |d| (units of the unknowns; 0: off) and whether the potential may
    # still change in this solve (friction's lag update to come)
    step_limit = float(problem.step_limit(opts.step_tol)) if opts.step_tol > 0.0 and hasattr(problem, "step_limit") else 0.0
    lag_pending = getattr(problem, "lag_pending", lambda: False)
    if forcing is not None:
        forcing.start(gnorm0, first_solved=first is not None)
    for _ in range(opts.max_iters):
        pre = None  # the fused first trial: (g.d, negligible, E, |E|, gradient magnitude, ||g_try||)
        alpha_pre = 1.0  # the step length of that trial
        def solve_system(lin_opts):
            """This iteration's Newton system: (linear result, fused first trial or None, its step length)."""
            if fused and not problem.bounds_step():
                if hasattr(problem, "newton_step"):  # solve + first trial, one read-back
                    return problem.newton_step(y, g, d, y_try, g_try, lin_opts) + (1.0,)
                lin = problem.solve_newton_system(y, g, d, lin_opts)
                return lin, problem.trial_step(y, g, d, 1.0, y_try, g_try), 1.0
            if fused:  # a bounded step (contact): the bound first, then the trial at it, one read-back each
                lin = problem.solve_newton_system(y, g, d, lin_opts)
                a_pre = min(1.0, problem.max_step(y, d))
                return lin, problem.trial_step(y, g, d, a_pre, y_try, g_try), a_pre
            return problem.solve_newton_system(y, g, d, lin_opts), None, 1.0  # an iteration count or a LinearSolveResult

        lin_opts = None
        if first is not None:  # done with the start's evaluation (its solve ran at the first tolerance)
            (lin, pre), first = first, None
        else:
            lin_opts = opts if forcing is None else replace(opts, cg_tol=forcing.next(gnorm))
            lin, pre, alpha_pre = solve_system(lin_opts)
        for retry in range(2):
            iterations = int(getattr(lin, "iterations", lin))
            st.cg_iterations += iterations
            st.linear_iterations += iterations
            st.host_syncs += int(getattr(lin, "host_syncs", 0))
            st.singular_solves += int(getattr(lin, "shift", 0.0) > 0.0 or getattr(lin, "deflated", 0) > 0)
            if pre is not None:
                gd, negligible = pre[0], pre[1]
            else:
                gd, negligible = problem.direction_check(y, g, d)
            if not (on_demand and retry == 0 and not problem.projecting):
                break
            # a full step of the exact Hessian's direction that fails the Armijo test (the fused trial
            # tells) is a sign its model of the energy is not to be trusted either
            full_rejected = pre is not None and not (
                np.isfinite(pre[2]) and (pre[2] <= E + opts.armijo * alpha_pre * gd + 16.0 * eps_mach * mag
                                         or (min(abs(pre[2] - E), abs(gd)) <= problem.gradient_test_below * mag
                                             and pre[5] <= 0.5 * gnorm)))
            if not (indefinite_system(lin) or not (gd < 0.0) or full_rejected):
                break
            # the exact Hessian was not enough: project from now on in this solve, and solve again
            problem.set_projection(True)
            st.projected_retries += 1
            if lin_opts is None:
                lin_opts = opts if forcing is None else replace(opts, cg_tol=forcing.next(gnorm))
            lin, pre, alpha_pre = solve_system(lin_opts)
        bounded = hasattr(problem, "max_step")
        if not (gd < 0.0):  # not a descent direction (indefinite Hessian or CG breakdown)
            pre = None
            problem.fallback_direction(g, d)
            gd, negligible = problem.direction_check(y, g, d)
            if not (gd < 0.0):
                st.reason = "no descent direction"
                break
        # A Newton step below the resolution of the unknowns (and of x = xb + s y) in this precision
        # cannot be taken: the state is as converged as the precision allows.
        if negligible:
            st.converged = True
            st.reason = "at the precision limit (Newton step below the resolution of the positions)"
            break
        # the step test (opts.step_tol): does this direction move every vertex by less than the limit?
        small_step = step_limit > 0.0 and problem.direction_max(y, g, d, step_limit) <= step_limit
        # continuous-collision filter (contact): no step may carry the state across a collider
        if pre is not None:
            alpha = alpha_pre
        else:
            alpha = min(1.0, problem.max_step(y, d)) if bounded else 1.0
        accepted = False
        noise = 16.0 * eps_mach * mag
        g_new = None  # the gradient at the accepted point when the fused trial computed it
        for _ls in range(opts.max_line_search):
            if pre is not None and _ls == 0:
                E_try, mag_try = pre[2], pre[3]
            else:
                problem.trial(y, alpha, d, y_try)
                E_try, mag_try = problem.energy(y_try)
            if np.isfinite(E_try) and E_try <= E + opts.armijo * alpha * gd + noise:
                accepted = True
                if pre is not None and _ls == 0:
                    g_new = pre[4], pre[5]
                break
            if (_ls == 0 and problem.gradient_test_below > 0.0 and np.isfinite(E_try)
                    and min(abs(E_try - E), abs(gd)) <= problem.gradient_test_below * mag):
                # energy change (or the decrease the Newton model predicts) below what the sums
                # resolve: accept the full Newton step if it halves the gradient norm (it is then a
                # contraction); the fused trial has that norm
                if pre is not None:
                    if pre[5] <= 0.5 * gnorm:
                        accepted, g_new = True, (pre[4], pre[5])
                        break
                elif problem.gradient(y_try, problem.new_vector())[1] <= 0.5 * gnorm:
                    accepted = True
                    break
            alpha *= 0.5
            st.line_search_steps += 1
        if not accepted:
            if on_demand and not problem.projecting:  # the exact Hessian's direction failed: project from now on
                problem.set_projection(True)
                st.projected_retries += 1
                continue
            if getattr(problem, "refresh_direction", None) is not None and problem.refresh_direction():
                continue  # the direction came from a kept (older) Newton matrix: try again with a fresh one
            if gnorm <= 1e3 * floor_factor * gmag:
                st.converged, st.reason = True, "at the precision limit (energy differences below round-off)"
            else:
                st.reason = "line search could not decrease the energy"
            break
        if (accepted and alpha < UNFILTERED_BELOW and getattr(problem, "unfiltered_direction", None) is not None
                and problem.unfiltered_direction() is not None):
            # the filtered direction's step was cut short by the line search: the plain Newton
            # direction may go further (a filter cut that fights the elastic forms)
            d_raw = problem.unfiltered_direction()
            gd_r, _ = problem.direction_check(y, g, d_raw)
            if gd_r < 0.0 and gd_r != gd:  # (the same slope: the filter cut nothing, the same direction)
                a_r = min(1.0, problem.max_step(y, d_raw)) if bounded else 1.0
                y_alt = getattr(problem.work, "y_alt", None)
                if y_alt is None or y_alt.shape[0] != y.shape[0]:
                    y_alt = problem.work.y_alt = problem.new_vector()
                for _k in range(UNFILTERED_HALVINGS):
                    if a_r <= alpha:
                        break
                    problem.trial(y, a_r, d_raw, y_alt)
                    E_r, mag_r = problem.energy(y_alt)
                    if np.isfinite(E_r) and E_r <= E + opts.armijo * a_r * gd_r + noise:
                        if E_r < E_try:
                            st.unfiltered_steps += 1
                            problem.assign(y_try, y_alt)
                            E_try, mag_try, g_new, alpha = E_r, mag_r, None, a_r
                        break
                    a_r *= 0.5
        if (opts.extrapolate and pre is not None and _ls == 0 and alpha >= 1.0 and g_new is not None and len(pre) > 6
                and hasattr(problem, "extrapolate")):
            longer = problem.extrapolate(y, d, gd, pre[6], E_try, y_try, g_try)
            if longer is not None:
                E_try, mag_try, g_new, alpha = longer[0], longer[1], longer[2:4], longer[4]
                st.extrapolations += 1
        problem.assign(y, y_try)
        E, mag = E_try, mag_try
        if g_new is not None:  # the fused trial's gradient is the gradient at y: swap the buffers
            g, g_try = g_try, g
            gmag, gnorm = g_new
        else:
            gmag, gnorm = problem.gradient(y, g)
        # a problem whose terms adapt (contact's barrier stiffness) may change its potential here:
        # its energy and gradient at y are evaluated again (the line search compares like with like)
        changed = after_iteration is not None and after_iteration(y, alpha, residual=relative(gnorm))
        if changed:
            E, mag, gmag, gnorm = problem.evaluate(y, g)
            st.adaptations += 1
        st.newton_iterations += 1
        st.history.append((E, gnorm, alpha, iterations))
        if not np.isfinite(gnorm):
            st.reason = "non-finite gradient"
            break
        if gnorm <= opts.tol * ref or gnorm <= opts.atol:
            st.converged, st.reason = True, "gradient below tolerance"
            break
        if gnorm <= floor_factor * gmag:
            st.converged, st.reason = True, "gradient at the round-off floor of its terms"
            break
        # a full step of a direction below the step limit, on a potential that stays as it is (no
        # lag update now or still to come): converged by the step test
        if small_step and alpha >= 1.0 and not changed and not lag_pending():
            st.converged = True
            st.reason = f"Newton step below step_tol={opts.step_tol:g} (relative gradient {relative(gnorm):.2e})"
            break
    else:
        st.reason = f"reached max_iters={opts.max_iters}"
    st.energy, st.gradient_norm = E, gnorm
    return finish()
