"""The ``auto`` linear solver: block-Jacobi PCG that hands over to the direct solver when the
systems turn out to be hard.

Rule (measurements in docs/linear_solvers.md):

* CUDA: ``pcg`` only (the data stay on the device; the loop is a CUDA graph with a host check
  every k iterations; the host backends would copy the matrix down and back every iteration).
* CPU, small systems (at most SMALL_DIRECT_DOFS_CPU unknowns): ``direct`` from the first solve,
  when the solver is built by a simulator (``initial="size"``, the simulators' default): one
  factorisation costs less than the launches of even a few dozen PCG iterations (measured with
  kernels_bench/bench_auto_crossover.py). A factorisation that meets a non-positive pivot is
  retried with a small diagonal shift by the direct solver itself (a semi-definite projected
  Hessian); only a matrix that no shift makes positive definite (an unprojected Hessian far from
  convex) sends that system and all later ones to PCG.
* CPU, larger systems: start with ``pcg``; when a solve needs more than ``switch_iterations`` (250) iterations,
  every later ``prepare`` uses ``direct`` instead (its symbolic analysis is done at that moment,
  once), provided the system has at most DIRECT_MAX_DOFS_CPU unknowns (PARDISO installed) or
  SUPERLU_MAX_DOFS_CPU (SuperLU only). The choice never goes back, so a run stays deterministic.

Why an iteration count: whether the factorisation pays depends on how hard the systems are
(stiffness against mass, Poisson ratio), not only on size. Per step on this CPU, block-Jacobi PCG
won on the mass-dominated box beam (60 and 211 iterations per solve at nu = 0.3 / 0.49: 2.3x and
1.6x faster than direct) and was even with it on the octopus at 90 iterations, while direct won
where PCG needed 271 (octopus, nu = 0.49: 3x), 370 (bunny: 1.5x) and 983 iterations (bunny,
nu = 0.49: 5x).
"""

from __future__ import annotations

import logging

from warpfem.solvers.linear.base import LinearSolver, LinearSolveResult

log = logging.getLogger(__name__)

DIRECT_MAX_DOFS_CPU = 200_000
SUPERLU_MAX_DOFS_CPU = 20_000
SWITCH_ITERATIONS = 250
SMALL_DIRECT_DOFS_CPU = 10_000  # crossover measured in kernels_bench/bench_auto_crossover.py
INITIAL_CHOICES = ("pcg", "size")


def starts_direct(pattern) -> bool:
    """The small-system rule: direct from the first solve (CPU, at most SMALL_DIRECT_DOFS_CPU unknowns)."""
    return (not pattern.device.is_cuda) and 3 * pattern.num_rows <= SMALL_DIRECT_DOFS_CPU


def describe_choice(num_dofs: int) -> dict:
    """What ``auto`` (as the simulators build it) will run for a system of ``num_dofs`` unknowns,
    by device (``warpfem describe``): {"cpu": text, "cuda": text}, from the same rule and limits
    as :func:`starts_direct` and :func:`direct_allowed`."""
    from warpfem.solvers.linear.direct import available_backends

    backend = available_backends()[0]
    limit = DIRECT_MAX_DOFS_CPU if backend == "pardiso" else SUPERLU_MAX_DOFS_CPU
    if num_dofs <= SMALL_DIRECT_DOFS_CPU:
        cpu = (f"direct (sparse Cholesky, {backend}) from the first solve: {num_dofs:,} unknowns <= "
               f"{SMALL_DIRECT_DOFS_CPU:,}; block-Jacobi PCG if a factorisation finds the matrix not positive definite")
    elif num_dofs <= limit:
        cpu = (f"block-Jacobi PCG, switching to direct (sparse Cholesky, {backend}) for good after a solve that "
               f"needs more than {SWITCH_ITERATIONS} iterations ({num_dofs:,} unknowns: above {SMALL_DIRECT_DOFS_CPU:,}, "
               f"within the direct limit {limit:,})")
    else:
        cpu = (f"block-Jacobi PCG only ({num_dofs:,} unknowns: above the direct limit {limit:,} with {backend})")
    return {"cpu": cpu, "cuda": "block-Jacobi PCG (the data stay on the device)"}


def simulator_options(name: str, options: dict | None) -> dict:
    """The options a simulator passes to ``make_linear_solver``: for ``auto``, the small-system
    rule (``initial="size"``) unless the caller chose ``initial`` itself."""
    options = dict(options or {})
    if name == "auto":
        options.setdefault("initial", "size")
    if name in ("auto", "pcg"):  # the whole PCG solve as one launch on the CPU (DevicePCG.cpu_serial)
        options.setdefault("cpu_serial", True)
    return options


def _pardiso_available() -> bool:
    from warpfem.solvers.linear.direct import available_backends

    return available_backends()[0] == "pardiso"


def direct_allowed(pattern) -> bool:
    """Whether ``auto`` may hand this pattern's systems to the direct solver."""
    if pattern.device.is_cuda:
        return False
    limit = DIRECT_MAX_DOFS_CPU if _pardiso_available() else SUPERLU_MAX_DOFS_CPU
    return 3 * pattern.num_rows <= limit


class AutoSolver(LinearSolver):
    """PCG first; direct from the first ``prepare`` after a PCG solve that needed more than
    ``switch_iterations`` iterations (when :func:`direct_allowed`).

    Args:
        switch_iterations: the PCG iteration count that triggers the switch.
        initial: "pcg" (start with PCG whatever the size) or "size" (direct from the first solve
            when :func:`starts_direct`; what the simulators use).
        check_every, use_cuda_graph: passed to the PCG; backend: passed to the direct solver.
        positions: accepted and ignored (the model description the other solvers get).
    """

    name = "auto"
    eager_inv_diag = False  # the inner solvers keep their own (``self.pcg.inv_diag``, ``self.direct.inv_diag``)
    # ``self.pcg`` (the PCG workspace: six vectors and the block-Jacobi diagonal) exists only once PCG is
    # used: a small CPU system that stays direct never allocates it

    def __init__(self, pattern, *, vec_type, scalar, switch_iterations: int = SWITCH_ITERATIONS,
                 check_every: int = 16, use_cuda_graph: bool = True, backend: str = "auto", positions=None,
                 initial: str = "pcg", cpu_serial: bool = False):
        if initial not in INITIAL_CHOICES:
            raise ValueError(f"initial must be one of {INITIAL_CHOICES}, got {initial!r}")
        self._initial = initial
        if int(switch_iterations) != switch_iterations or switch_iterations < 1:
            raise ValueError(f"switch_iterations must be a positive integer, got {switch_iterations!r}")
        self.switch_iterations = int(switch_iterations)
        self._pcg_options = dict(check_every=check_every, use_cuda_graph=use_cuda_graph, cpu_serial=cpu_serial)
        self._backend = backend
        super().__init__(pattern, vec_type=vec_type, scalar=scalar)

    def _analyse(self, pattern):
        if self.analyse_count > 1:  # a grown pattern: the solvers built so far analyse it
            for s in (self.pcg, self.direct):
                if s is not None:
                    s.analyse(pattern)
            return
        self.pcg = None
        self.direct = None
        self.active = "pcg"
        self._may_switch = direct_allowed(pattern)
        if self._initial == "size" and self._may_switch and starts_direct(pattern):
            self.active = "direct"
            log.debug("linear solver auto: %d unknowns on the CPU; direct from the first solve", 3 * pattern.num_rows)
            self._make_direct()  # its symbolic set-up now, with the simulator's, not inside the first timed step
        else:
            self._make_pcg()  # likewise

    def _make_pcg(self):
        from warpfem.solvers.linear.pcg import DevicePCG

        self.pcg = DevicePCG(self.pattern, vec_type=self.vec_type, scalar=self.scalar, **self._pcg_options)

    def _make_direct(self):
        from warpfem.solvers.linear.direct import DirectSolver

        self.direct = DirectSolver(self.pattern, vec_type=self.vec_type, scalar=self.scalar, backend=self._backend)

    def _prepare(self, values, mask):
        if self.active == "direct" and self.direct is None:
            self._make_direct()
        if self.active == "direct":
            self.direct.prepare(values, mask)
            if self.direct.failure:
                # not positive definite (an unprojected Hessian, a singular static system): PCG
                # handles these (it stops at negative curvature with a descent direction), so this
                # and every later system go to PCG; no switching back
                log.info("linear solver auto: %s; PCG from now on", self.direct.failure)
                self.active, self._may_switch = "pcg", False
        if self.active == "pcg":
            if self.pcg is None:  # started direct, and the direct solver gave up on this system
                self._make_pcg()
            self.pcg.prepare(values, mask)

    def _solve(self, b, x, *, tol, maxiter) -> LinearSolveResult:
        if self.active == "direct":
            return self.direct.solve(b, x, tol=tol, maxiter=maxiter)
        res = self.pcg.solve(b, x, tol=tol, maxiter=maxiter)
        if self._may_switch and res.iterations > self.switch_iterations:
            log.info("linear solver auto: PCG needed %d iterations (> %d); switching to the direct solver",
                     res.iterations, self.switch_iterations)
            self.active = "direct"
        return res

    # -- deferred solves (PCG only): see DevicePCG.solve_deferred -----------------------------------
    @property
    def deferred_chunks(self) -> int:
        return self.pcg.deferred_chunks if self.pcg is not None else 0

    def can_defer(self) -> bool:
        return self.active == "pcg" and self.pcg is not None and self.pcg.can_defer()

    def solve_deferred(self, b, x, **kw):
        self.pcg.solve_deferred(b, x, **kw)

    def complete_deferred(self, report):
        res, changed = self.pcg.complete_deferred(report)
        self.host_syncs += res.host_syncs
        if self._may_switch and res.iterations > self.switch_iterations:
            log.info("linear solver auto: PCG needed %d iterations (> %d); switching to the direct solver",
                     res.iterations, self.switch_iterations)
            self.active = "direct"
        return res, changed
