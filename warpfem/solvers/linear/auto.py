"""The ``auto`` linear solver: a fixed rule picks the solver from the problem alone (its size,
the device, the extras installed, and CG iteration counts), so the same scene makes the same
choice, and the same numbers, on an idle or a loaded machine (docs/linear_solvers.md, "auto").

The rule (``rule="model"``, the default; the constants are calibrated on the measurements in
docs/linear_solvers.md):

* Candidates: ``pcg`` always; ``multigrid`` when pyamg is installed; ``direct`` on the CPU up to
  DIRECT_MAX_DOFS_CPU unknowns (PARDISO installed) or SUPERLU_MAX_DOFS_CPU (SuperLU only). CUDA:
  ``pcg`` and ``multigrid`` (the host backends would copy the matrix down and back every Newton
  iteration).
* CPU systems of at most SMALL_DIRECT_DOFS_CPU unknowns: ``direct`` from the first solve when the
  solver is built by a simulator (``initial="size"``, the simulators' default; one factorisation
  of such a system costs less than the launches of a few dozen PCG iterations,
  kernels_bench/bench_auto_crossover.py).
* Above MULTIGRID_MIN_DOFS unknowns (CPU and CUDA): ``multigrid`` when it is a candidate (the
  cheapest per step from 12k tets on, at nu 0.3 and 0.49, on the boxes and the bunny measured).
* Otherwise ``pcg``; above SMALL_DIRECT_DOFS_CPU unknowns it hands every later system to ``multigrid`` (when it is a candidate, else
  to ``direct`` where allowed) once one of its solves needs more than SWITCH_AFTER_ITERATIONS x
  (unknowns / 8000) ** 0.8 CG iterations (:func:`switch_after_iterations`; the set-up of the
  other solvers grows faster with the size than a CG iteration's cost, so the crossover count
  grows with it). A soft material at a loose tolerance stays with PCG, a stiff one or a tight
  tolerance switches after its first Newton system (kernels_bench/bench_auto_rule.py). An
  iteration count is a property of the system, not of the machine's load.
* A factorisation that meets a non-positive pivot is retried with a small diagonal shift by the
  direct solver itself (a semi-definite projected Hessian); only a matrix that no shift makes
  positive definite (an unprojected Hessian far from convex) sends that system and all later ones
  to PCG (which stops at negative curvature with a descent direction); ``direct`` is then no longer
  a candidate.

``rule="measured"`` keeps the earlier rule, for comparison (kernels_bench/bench_auto_rule.py): it
times the candidates on the run's first Newton system that costs more than ``explore_seconds``
(systems above ``explore_min_dofs`` unknowns) and keeps the cheapest by ``switch_margin``,
re-measuring when the moving average of the chosen solver's cost passes ``recheck_factor`` times
the cost at the choice (at most ``max_explorations`` times). Its choice depends on the measured
times, so two runs on a loaded machine may differ.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import warp as wp

from warpfem.solvers.linear.base import LinearSolver, LinearSolveResult
from warpfem.transfer import strict_device

log = logging.getLogger(__name__)

DIRECT_MAX_DOFS_CPU = 200_000
SUPERLU_MAX_DOFS_CPU = 20_000
#: CPU systems of at most this many unknowns run direct from the first solve (``initial="size"``)
SMALL_DIRECT_DOFS_CPU = 3_000
EXPLORE_SECONDS = 0.02
#: systems with at most this many unknowns are never timed against the other candidates: their
#: solver is the starting one, so small runs (tests, studies compared bit for bit, a serial and a
#: Dask run of the same study) are reproducible whatever the machine's load
EXPLORE_MIN_DOFS = 3_000
INITIAL_CHOICES = ("pcg", "size")
CANDIDATES = ("pcg", "multigrid", "direct")
RULES = ("model", "measured")
#: ``rule="model"``: systems above this many unknowns run multigrid when it is a candidate
MULTIGRID_MIN_DOFS = 10_000
#: ``rule="model"``, PCG: CG iterations of one solve, at 8000 unknowns, past which the later systems
#: go to multigrid (or, without pyamg, on the CPU, to the direct solver; scaled by (unknowns / 8000) ** 0.8)
SWITCH_AFTER_ITERATIONS = 100


def switch_after_iterations(num_dofs: int) -> int:
    """``rule="model"``: the CG iterations of one PCG solve past which the later systems of
    ``num_dofs`` unknowns go to multigrid (or direct; see the module)."""
    return int(round(SWITCH_AFTER_ITERATIONS * (max(num_dofs, 1) / 8000.0) ** 0.8))


def _host_solvers_allowed(pattern) -> bool:
    """The host (direct) solver is a candidate: on the CPU, outside strict device mode (which makes
    the CPU choose as on CUDA, where the matrix would cross to the host every Newton iteration)."""
    return not pattern.device.is_cuda and not strict_device()


def starts_direct(pattern) -> bool:
    """The small-system rule: direct from the first solve (CPU, at most SMALL_DIRECT_DOFS_CPU unknowns)."""
    return _host_solvers_allowed(pattern) and 3 * pattern.num_rows <= SMALL_DIRECT_DOFS_CPU


def describe_choice(num_dofs: int) -> dict:
    """What ``auto`` (as the simulators build it, ``rule="model"``) will run for a system of
    ``num_dofs`` unknowns, by device (``warpfem describe``): {"cpu": text, "cuda": text}, from the
    same rule and limits as :func:`starts_direct`, :func:`direct_allowed` and the candidates."""
    from warpfem.solvers.linear.direct import available_backends

    backend = available_backends()[0]
    limit = DIRECT_MAX_DOFS_CPU if backend == "pardiso" else SUPERLU_MAX_DOFS_CPU
    mg = _multigrid_available() and num_dofs > MULTIGRID_MIN_DOFS
    mg_text = f"multigrid-preconditioned CG ({num_dofs:,} unknowns > {MULTIGRID_MIN_DOFS:,}, pyamg installed)"
    if num_dofs <= SMALL_DIRECT_DOFS_CPU:
        cpu = (f"direct (sparse Cholesky, {backend}) from the first solve: {num_dofs:,} unknowns <= "
               f"{SMALL_DIRECT_DOFS_CPU:,}; block-Jacobi PCG if a factorisation finds the matrix not "
               f"positive definite")
    elif mg:
        cpu = mg_text
    elif _multigrid_available() or num_dofs <= limit:
        then = "multigrid-preconditioned CG" if _multigrid_available() else f"direct (sparse Cholesky, {backend})"
        cpu = (f"block-Jacobi PCG; {then} from the Newton system after the first PCG solve that needs more than "
               f"{switch_after_iterations(num_dofs)} CG iterations ({num_dofs:,} unknowns)")
    else:
        cpu = f"block-Jacobi PCG ({num_dofs:,} unknowns: above the direct limit {limit:,} with {backend})"
    if mg:
        cuda = mg_text
    elif _multigrid_available() and num_dofs > SMALL_DIRECT_DOFS_CPU:
        cuda = (f"block-Jacobi PCG; multigrid-preconditioned CG from the Newton system after the first PCG solve that "
                f"needs more than {switch_after_iterations(num_dofs)} CG iterations")
    else:
        cuda = "block-Jacobi PCG"
    cuda += " (the data stay on the device)"
    return {"cpu": cpu, "cuda": cuda}


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


def _multigrid_available() -> bool:
    import importlib.util

    return importlib.util.find_spec("pyamg") is not None  # without importing it (~0.05 s at start-up)


def direct_allowed(pattern) -> bool:
    """Whether ``auto`` may hand this pattern's systems to the direct solver."""
    if not _host_solvers_allowed(pattern):
        return False
    limit = DIRECT_MAX_DOFS_CPU if _pardiso_available() else SUPERLU_MAX_DOFS_CPU
    return 3 * pattern.num_rows <= limit


class AutoSolver(LinearSolver):
    """The solver the rule of the module picks for the problem (``rule="model"``, deterministic), or
    the cheapest of the candidates by measured time per Newton system (``rule="measured"``).

    Args:
        rule: "model" (default) or "measured" (see the module).
        initial: "pcg" (no direct start whatever the size) or "size" (direct from the first solve
            when :func:`starts_direct`; what the simulators use).
        candidates: the solvers the rule may use (default: pcg, multigrid when pyamg is installed,
            direct where :func:`direct_allowed`); names outside these are ignored.
        explore_seconds (``rule="measured"``): measure the other candidates only when the first solve took longer.
        switch_margin: switch only to a candidate at most this fraction of the current cost.
        recheck_factor, max_explorations: measure again when the chosen solver's cost grows past
            this factor of its cost at the choice, at most this many measurements per run.
        check_every, use_cuda_graph: passed to the PCG; backend: passed to the direct solver;
            positions: the rest positions (the multigrid's rigid-body modes).
    """

    name = "auto"
    eager_inv_diag = False  # the inner solvers keep their own
    # only the solvers in use are built: a small CPU system that stays direct never allocates the
    # PCG workspace (``self.pcg`` stays None)

    def __init__(self, pattern, *, vec_type, scalar, rule: str = "model", initial: str = "pcg", candidates=None,
                 explore_seconds: float = EXPLORE_SECONDS, switch_margin: float = 0.8, recheck_factor: float = 2.0,
                 max_explorations: int = 2, check_every: int = 16, use_cuda_graph: bool = True, backend: str = "auto",
                 positions=None, cpu_serial: bool = False, explore_min_dofs: int = EXPLORE_MIN_DOFS):
        if rule not in RULES:
            raise ValueError(f"rule must be one of {RULES}, got {rule!r}")
        self.rule = rule
        if initial not in INITIAL_CHOICES:
            raise ValueError(f"initial must be one of {INITIAL_CHOICES}, got {initial!r}")
        if not (explore_seconds >= 0.0):
            raise ValueError(f"explore_seconds must be >= 0, got {explore_seconds!r}")
        if not (0.0 < switch_margin <= 1.0):
            raise ValueError(f"switch_margin must be in (0, 1], got {switch_margin!r}")
        if not (recheck_factor >= 1.0):
            raise ValueError(f"recheck_factor must be >= 1, got {recheck_factor!r}")
        if int(max_explorations) != max_explorations or max_explorations < 0:
            raise ValueError(f"max_explorations must be an integer >= 0, got {max_explorations!r}")
        if candidates is not None:
            unknown = set(candidates) - set(CANDIDATES)
            if unknown:
                raise ValueError(f"unknown candidate(s) {sorted(unknown)}; auto chooses among {', '.join(CANDIDATES)}")
        self._initial = initial
        self._candidates_arg = None if candidates is None else tuple(candidates)
        self.explore_seconds, self.switch_margin = float(explore_seconds), float(switch_margin)
        self.explore_min_dofs = int(explore_min_dofs)
        self.recheck_factor, self.max_explorations = float(recheck_factor), int(max_explorations)
        self._pcg_options = dict(check_every=check_every, use_cuda_graph=use_cuda_graph, cpu_serial=cpu_serial)
        self._backend = backend
        self._positions = positions
        super().__init__(pattern, vec_type=vec_type, scalar=scalar)

    # -- candidates -----------------------------------------------------------------------------
    def _analyse(self, pattern):
        if self.analyse_count > 1:  # a grown pattern: the solvers built so far analyse it
            for s in self.solvers.values():
                s.analyse(pattern)
            return
        self.solvers = {}
        allowed = {"pcg": True, "multigrid": _multigrid_available(), "direct": direct_allowed(pattern)}
        wanted = self._candidates_arg or CANDIDATES
        self.candidates = [c for c in CANDIDATES if c in wanted and allowed[c]]
        if "pcg" not in self.candidates:
            self.candidates.insert(0, "pcg")  # the fallback of an indefinite system
        self.active = "pcg"
        n = 3 * pattern.num_rows
        #: rule "model": the CG iterations of a PCG solve past which later systems go to ``switch_to`` (None: never)
        self.switch_iterations, self.switch_to = None, None
        if self._initial == "size" and "direct" in self.candidates and starts_direct(pattern):
            self.active = "direct"
            log.debug("linear solver auto: %d unknowns on the CPU; direct from the first solve", n)
        elif self.rule == "model" and "multigrid" in self.candidates and n > MULTIGRID_MIN_DOFS:
            self.active = "multigrid"
            log.debug("linear solver auto: %d unknowns; multigrid", n)
        elif self.rule == "model" and n > SMALL_DIRECT_DOFS_CPU and ("multigrid" in self.candidates
                                                                    or "direct" in self.candidates):
            self.switch_iterations = switch_after_iterations(n)
            self.switch_to = "multigrid" if "multigrid" in self.candidates else "direct"
        self.costs = {}  # seconds per Newton system (prepare + solve) of each measured candidate
        self.setup_seconds = {}  # one-time set-up of each candidate (not in ``costs``)
        self.explorations = 0
        self._cheap_rechecks = 0
        self._chosen_cost = None  # the cost at the last measurement of the candidates
        self._t_prepare = time.perf_counter()
        self._make(self.active)  # its set-up now, with the simulator's, not inside the first timed step

    def _make(self, name):
        if name not in self.solvers:
            t0 = time.perf_counter()
            if name == "pcg":
                from warpfem.solvers.linear.pcg import DevicePCG

                s = DevicePCG(self.pattern, vec_type=self.vec_type, scalar=self.scalar, **self._pcg_options)
            elif name == "direct":
                from warpfem.solvers.linear.direct import DirectSolver

                s = DirectSolver(self.pattern, vec_type=self.vec_type, scalar=self.scalar, backend=self._backend)
            else:
                from warpfem.solvers.linear.multigrid import MultigridPCG

                s = MultigridPCG(self.pattern, vec_type=self.vec_type, scalar=self.scalar, positions=self._positions)
            self.solvers[name] = s
            self.setup_seconds[name] = self.setup_seconds.get(name, 0.0) + time.perf_counter() - t0
        return self.solvers[name]

    @property
    def pcg(self):
        """The PCG solver, if it has been used (None otherwise)."""
        return self.solvers.get("pcg")

    @property
    def _may_switch(self) -> bool:
        """Whether the direct solver is still a candidate (it is dropped after a failed factorisation)."""
        return "direct" in self.candidates

    @property
    def direct(self):
        """The direct solver, if it has been used (None otherwise)."""
        return self.solvers.get("direct")

    @property
    def iterative(self):
        """Whether the solver in use iterates (the direct one does not)."""
        return self.active != "direct"

    # -- interface --------------------------------------------------------------------------------
    def _prepare(self, values, mask):
        # the cost of a Newton system runs from here to the end of its solve (every solver's solve
        # ends with a read-back, so the device has finished by then: no extra synchronisation)
        self._t_prepare = time.perf_counter()
        if self.active == "direct":
            d = self._make("direct")
            d.prepare(values, mask)
            if d.failure:
                # not positive definite: PCG handles these (it stops at negative curvature with a
                # descent direction), so this and every later system go to PCG, for good
                log.info("linear solver auto: %s; PCG from now on", d.failure)
                self.candidates = [c for c in self.candidates if c != "direct"]
                self.active = "pcg"
        if self.active != "direct":
            self._make(self.active).prepare(values, mask)

    def _after_pcg(self, res):
        """Rule "model": a PCG solve past ``switch_iterations`` CG iterations sends later systems to
        ``switch_to`` (multigrid when it is a candidate, else direct)."""
        if (self.active == "pcg" and self.switch_iterations is not None and self.switch_to in self.candidates
                and res.iterations > self.switch_iterations):
            log.info("linear solver auto: %d CG iterations > %d; %s from the next Newton system", res.iterations,
                     self.switch_iterations, self.switch_to)
            self.active = self.switch_to
            self.switch_iterations = None
            self._make(self.active)

    def _solve(self, b, x, *, tol, maxiter) -> LinearSolveResult:
        res = self.solvers[self.active].solve(b, x, tol=tol, maxiter=maxiter)
        if self.rule == "model":
            self._after_pcg(res)
            return res
        cost = time.perf_counter() - self._t_prepare
        self.costs[self.active] = cost
        others = [c for c in self.candidates if c != self.active]
        if (cost <= self.explore_seconds or not others or self.explorations >= self.max_explorations
                or self._cheap_rechecks >= 3 or 3 * self.num_rows <= self.explore_min_dofs):
            return res
        if self._chosen_cost is not None:
            # after a choice: a moving average over the solves since (one expensive system, such
            # as a multigrid's re-formed coarse operators, does not trigger a new measurement)
            self._since_choice += 1
            self._avg_cost = cost if self._avg_cost is None else 0.7 * self._avg_cost + 0.3 * cost
            if self._since_choice < 5 or self._avg_cost <= self.recheck_factor * self._chosen_cost:
                return res
        return self._explore(b, x, tol, maxiter, res, cost, others)

    def _explore(self, b, x, tol, maxiter, res, cost, others):
        """Solve this system with every other candidate, timed; keep the cheapest (by the margin)."""
        values, mask = self._values, self._mask
        # the current solver again on this system, warm: the cost that triggered this may carry
        # one-time warm-up (kernel loads, allocations, a first factorisation's set-up)
        current = self.solvers[self.active]
        first_syncs = res.host_syncs
        wp.synchronize_device(self.device)
        t0 = time.perf_counter()
        current.prepare(values, mask)
        res = current.solve(b, x, tol=tol, maxiter=maxiter)
        cost = time.perf_counter() - t0
        self.costs[self.active] = cost
        if cost <= self.explore_seconds:
            res.host_syncs += first_syncs
            self._cheap_rechecks += 1  # after three of these, systems near the threshold stop re-solving
            return res  # cheap after all: nothing else is built or measured
        self.explorations += 1
        start, best, best_cost, best_res = self.active, self.active, cost, res
        syncs = first_syncs + res.host_syncs
        trial, best_x = wp.empty_like(x), None
        for name in others:
            s = self._make(name)
            if name == "multigrid" and s.levels is None:  # its hierarchy: set-up, timed apart
                t0 = time.perf_counter()
                s.prepare(values, mask)
                wp.synchronize_device(self.device)
                self.setup_seconds[name] += time.perf_counter() - t0
            wp.synchronize_device(self.device)
            t0 = time.perf_counter()
            s.prepare(values, mask)
            if getattr(s, "failure", ""):
                self.candidates = [c for c in self.candidates if c != name]
                continue
            r = s.solve(b, trial, tol=tol, maxiter=maxiter)
            c = time.perf_counter() - t0
            syncs += r.host_syncs
            self.costs[name] = c
            log.debug("linear solver auto: %s %.3f s (%d iterations) on the measured system", name, c, r.iterations)
            if r.converged and not r.failed and c < best_cost and c < self.switch_margin * cost:
                best, best_cost, best_res = name, c, r
                if best_x is None:
                    best_x = wp.empty_like(x)
                wp.copy(best_x, trial)
        if best != start:
            wp.copy(x, best_x)
            log.info("linear solver auto: %s (%.3f s per Newton system) instead of %s (%.3f s)", best, best_cost,
                     start, cost)
        self.active, self._chosen_cost = best, best_cost
        self._since_choice, self._avg_cost = 0, None
        best_res.host_syncs = syncs
        return best_res

    # -- the recorded choice (a simulator's state_dict) ------------------------------------------------
    def state_dict(self) -> dict:
        """The recorded choice and what decides the next one: the active solver, the candidates left,
        the measured costs, the explorations made, the moving average since the choice; and the
        state of each solver built so far ("solvers/NAME/..."). Loaded into a fresh ``auto``, the
        choice is reused as recorded, not measured again."""
        from warpfem.io.checkpoint import optional_number

        names = sorted(self.costs)
        d = {"active": self.active, "candidates": np.array(self.candidates, dtype=str),
             "explorations": int(self.explorations), "cheap_rechecks": int(self._cheap_rechecks),
             "chosen_cost": optional_number(self._chosen_cost), "since_choice": int(getattr(self, "_since_choice", 0)),
             "avg_cost": optional_number(getattr(self, "_avg_cost", None)), "cost_names": np.array(names, dtype=str),
             "cost_seconds": np.array([self.costs[k] for k in names], dtype=np.float64),
             "built": np.array(sorted(self.solvers), dtype=str)}
        for name, s in self.solvers.items():
            d.update({f"solvers/{name}/{k}": v for k, v in s.state_dict().items()})
        return d

    def load_state_dict(self, view):
        active = view.text("active")
        candidates = view.array("candidates", (None,)).tolist()
        unknown = [c for c in candidates + [active] if c not in CANDIDATES]
        if unknown:
            raise view.error("candidates", f"unknown solver(s) {unknown}; auto chooses among {', '.join(CANDIDATES)}")
        if active != "pcg" and active not in self.candidates:
            raise view.error("active", f"{active!r} is not a candidate here (candidates {self.candidates}: another "
                             "device, or a missing extra)")
        names = view.array("cost_names", (None,)).tolist()
        seconds = view.array("cost_seconds", (len(names),), np.float64)
        built = view.array("built", (None,)).tolist()
        values = dict(explorations=view.integer("explorations"), _cheap_rechecks=view.integer("cheap_rechecks"),
                      _chosen_cost=view.number("chosen_cost", optional=True), _since_choice=view.integer("since_choice"),
                      _avg_cost=view.number("avg_cost", optional=True))
        for name in built:
            if name not in CANDIDATES:
                raise view.error("built", f"unknown solver {name!r}")
            self._make(name).load_state_dict(view.view(f"solvers/{name}"))
        self.active = active
        self.candidates = [c for c in self.candidates if c in candidates or c == "pcg"]
        self._make(active)
        self.costs = dict(zip(names, seconds.tolist()))
        for k, v in values.items():
            setattr(self, k, v)

    # -- deferred solves (PCG only): see DevicePCG.solve_deferred -----------------------------------
    def _may_explore(self) -> bool:
        if self.rule == "model":
            return False
        others = [c for c in self.candidates if c != self.active]
        return (bool(others) and self.explorations < self.max_explorations and self._cheap_rechecks < 3
                and 3 * self.num_rows > self.explore_min_dofs)

    @property
    def deferred_chunks(self) -> int:
        return self.pcg.deferred_chunks if self.pcg is not None else 0

    def can_defer(self) -> bool:
        """PCG's solve may be deferred (its report read with the Newton trial) only where no timed
        comparison with the other candidates is due: a deferred solve is not measured against them.
        So: PCG active, and either nothing left to explore or its systems cheaper than
        ``explore_seconds`` (where one read-back less per Newton iteration matters)."""
        pcg = self.pcg
        if self.active != "pcg" or pcg is None or not pcg.can_defer():
            return False
        return not self._may_explore() or self.costs.get("pcg", float("inf")) <= self.explore_seconds

    def solve_deferred(self, b, x, **kw):
        self.pcg.solve_deferred(b, x, **kw)

    def complete_deferred(self, report):
        res, changed = self.pcg.complete_deferred(report)
        self.host_syncs += res.host_syncs
        if self.rule == "model":
            self._after_pcg(res)
            return res, changed
        self.costs["pcg"] = time.perf_counter() - self._t_prepare  # (with the fused trial: an upper bound)
        return res, changed
