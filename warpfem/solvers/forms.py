"""The incremental potential of one implicit step as a weighted list of forms (as in PolyFEM).

Every time integrator of :mod:`warpfem.integrators` and the quasi-static solve minimise

    E(y) = sum_f w_f E_f(y),   x(y) = x_b + s y   (static: x = y, s = 1),

over the per-vertex vec3 unknowns y (the end-of-step velocity for dynamics). A form is a function
of y itself (``variable = "y"``) or of the positions x (``variable = "x"``); for the latter the
chain rule's factors s (gradient) and s^2 (Hessian) are applied here, in
:meth:`IncrementalPotential.scales`, the one place where s enters. The weights w_f are set per step
from the integrator's prediction (:meth:`IncrementalPotential.begin`; the simulator's
``_weights``: inertia 1, damping s, load s x load scale, elasticity 1; forms not named there keep
their own ``weight``, 1 by default).

* :class:`InertiaForm`      1/2 (y - y_hat)^T M (y - y_hat)            (y)
* :class:`DampingForm`      1/2 y^T (alpha M + beta K_n) y             (y; Rayleigh, K_n frozen at the step start)
* :class:`LoadForm`         -y^T f_ext                                 (y; gravity, applied forces, tractions)
* :class:`ElasticForm`      V(x) over the quadrature-point sets        (x)
* ``warpfem.contact.ContactForm``, ``SurfaceContactForm``: barrier + lagged friction (x; bound the line search)

**Evaluation.** A form provides ``energy(y, x, acc)`` (its unweighted value into its row of the
potential's float64 accumulator), ``gradient(y, x, scale, g, acc)`` (g += scale dE_f/d(variable)),
``hessian(y, x, scale, values)`` (blocks added in the pattern), optionally ``max_step(x, d, scale,
acc)`` (the largest step along y + alpha d it allows, into ``acc[acc_slot + 3]``: the form then
*bounds the step*), ``read(row) -> (E, |E|, feasible)`` (``feasible`` False rejects a trial point
outside the form's domain: the line search halves), ``gradient_magnitude(row, scale)`` (the size of
its gradient terms: the scale of their round-off), and ``extra_blocks()`` (off-diagonal vertex
pairs its Hessian adds beyond the mesh's pattern, or None).

**Place.** Forms whose gradient is summed into one magnitude (the quadratic ones: ``joint = True``)
are evaluated first; the others in increasing ``order`` (elastic 0, collider contact 10, surface
contact 20, the load and, by default, a user's form 100), forms of equal order in the order they
were added.

**Life cycle** (the simulator calls these for every form of the potential; the base class's
defaults do nothing, so a form overrides only what it needs, and ``Simulator.add_form`` plugs it
in without the simulator knowing what it is; PolyFEM's ``init_lagging`` / ``update_lagging`` /
``max_step_size`` / ``is_step_valid`` are the model):

1. ``enabled()``: whether the form is in the potential now (asked at each step start; e.g. the
   collider contact without colliders is not).
2. ``begin_step(ctx)`` at each step start (and each static load step), with a :class:`StepContext`:
   the state the step starts from, t0, t1, dt, x_b, s, the prescribed values of the unknown, the
   mask and the vector algebra. Lagged quantities (friction's normal forces), poses of moving
   obstacles and the like are set here.
3. ``check_start(x, ctx)``: only when some form bounds the step, the step starts from the unknown
   that keeps every free vertex where it is (fixed ones at their targets; positions ``x``), cut
   towards the initial guess by :meth:`IncrementalPotential.max_step`. A form raises
   :class:`InfeasibleStart` when that start is outside its domain (a collider moved into the body
   within the step, or a kinematic body into a soft one in surface contact): the simulator raises
   ``SolveFailed`` with its message and the state is left unchanged.
4. The Newton loop: evaluation as above, ``max_step`` before each line search, ``read``'s
   ``feasible`` on each trial; forms with an adaptive parameter (``adaptive_stiffness()`` true)
   also get ``begin_stiffness`` at the start and ``after_iteration`` after each accepted
   iteration, and keep ``stiffness_state()`` / ``restore_stiffness(state)`` for a failed step.
5. ``uses_lagging()`` / ``update_lagging(x, keep_below=0.0) -> (change, scale)``: forms that lag a
   quantity take it again from an iterate near the solution (after an accepted iteration whose
   full Newton step brought the gradient below the form's ``lag_below`` of the start:
   ``LAG_BELOW`` unless the form says otherwise), at most ``friction_iterations`` times per solve
   and form, and while its ``change`` exceeds ``friction_tol`` x its ``scale``
   (:meth:`IncrementalPotential.set_lag_updates`; :func:`lagged_change` measures two arrays);
   the solve then goes on to its tolerance with them. The first update is made only when its
   change exceeds ``keep_below`` (``friction_update_tol``) x its scale: a form that keeps its lag
   returns (change, scale, False) and the potential stays as it is (a form whose
   ``update_lagging`` takes no ``keep_below`` always updates).
6. ``state_dict()`` / ``load_state_dict(state)``: the form's step-to-step state for checkpoints
   (default: none); a form whose later steps depend on more than the step's start state (a
   kept set of pairs, an adaptive parameter) returns it so a continued run is bit-identical.
7. ``static_error()``: None when the form may join a quasi-static solve (x = y, s = 1; its
   ``begin_step`` gets a context with ``static`` True), else the sentence ``solve_static`` refuses
   with. Default: a form of x may, a form of y (the velocity) may not.

To add a term: write a class with these methods and give it to ``Simulator.add_form``; no slot, no
constant to reserve, nothing to edit in the simulator.

The potential reads its accumulator back once per evaluation; :meth:`IncrementalPotential.trial_step`
evaluates the direction check, the energy and the gradient of a full Newton step with one read-back.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import warp as wp

from warpfem.kernels import fem as FK
from warpfem.kernels import linalg as LK
from warpfem.kernels import generic
from warpfem.kernels.generic import CapturedSequences, RecordedLaunch, launch, launch_phases
from warpfem.transfer import read

__all__ = ["Form", "InertiaForm", "DampingForm", "ElasticForm", "LoadForm", "IncrementalPotential",
           "FullSpacePotential", "Workspace", "StepContext", "InfeasibleStart", "lagged_change"]

ROW = 4  # accumulator slots per form
# the potential's own row: joint gradient magnitude^2, ||P g||^2, then the direction check (g.d, max|d|, max|y|, max|x|)
_G_JOINT, _G_NORM, _D_GD = 0, 1, 2
_G_TD = 6  # in the trial's gradient section: g(y + alpha d) . d (the directional derivative there)
_D_CUTS = 7  # in the direction section: 1 + the contacts the friction filter cut (friction_pin's gate)
_HEAD = 8
_F64_ONE = wp.float64(1.0)
#: vertices per row of partial sums of the elastic force magnitude's dot product on the CPU
#: (``ElasticForm.gradient``): fixed, so the rows do not depend on how the vertices are split
FORCE_ROW_BLOCK = 64
#: the elastic force on the CPU lets each thread compute the points its vertices gather (those on
#: the seam with the neighbouring range computed twice: one dispatch) when the busiest thread gets at
#: most this many points beyond an even share (~0.1 ms of force work at ~50 ns per point, about
#: what a second dispatch may cost in wall clock, waking the other cores); otherwise the points are
#: split evenly and the vertices gathered after (two dispatches, no point computed twice)
FORCE_SEAM_MAX_POINTS = 2048
#: lagged quantities are taken again from an iterate whose gradient is below this fraction of the
#: step's reference gradient (and that a full Newton step reached): near the solution. Measured
#: (docs/contact.md): from the first iterate, an impact's overshoot into the barrier gives normal
#: forces many times the converged ones (the stack's impact step then took 100 iterations).
LAG_BELOW = 1e-2


def check_lag_below(value):
    """``friction_lag_below`` (a simulator's override of the forms' ``lag_below``) checked: None, or
    a number in (0, 1)."""
    if value is None:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"friction_lag_below must be a number in (0, 1) or None, got {value!r}") from None
    if not (np.isfinite(v) and 0.0 < v < 1.0):
        raise ValueError(f"friction_lag_below must be in (0, 1), got {value!r}")
    return v


#: ``friction_pin``'s second solve starts from the filtered direction: it solves for the correction
#: c of (A + S) c = r0 = b + S d_cut - (A + S) d_filt, to the tolerance that leaves the same residual
#: as a solve from zero (``cg_tol`` x |b|). The filtered direction is near the pinned one (|r0| is
#: 0.3 |b| in the median on the bunny's impact), so the second solve takes fewer iterations
#: (docs/contact.md, "What an impact step costs"); False: from zero, as first built (for comparison)
PIN_WARM_START = True
#: extrapolation along an accepted full Newton step (``IncrementalPotential.extrapolate``): tried when
#: the slope there is still below this fraction of the start's (the step fell at least this short)
EXTRAPOLATE_BELOW = 0.5
#: the longest extrapolated step, in Newton steps
EXTRAPOLATE_MAX = 32.0


def _ptr(a):
    return 0 if a is None else (a.ptr, a.shape[0])


class Workspace:
    """Device vectors a simulator reuses for every solve (no allocation per Newton iteration)."""

    def __init__(self, ops):
        self.g, self.d, self.rhs, self.y_try, self.g_try = (ops.new_vector() for _ in range(5))
        self.x, self.tmp, self.fa = (ops.new_vector() for _ in range(3))
        self.inv_diag = None  # block-Jacobi inverse for the fallback direction, allocated on first use


@dataclass
class StepContext:
    """What a form's ``begin_step`` is told about the coming step (or static load step).

    state: the :class:`~warpfem.solvers.state.State` the step starts from (x, v, time, history);
    t0, t1, dt: the step's start and end time and its length (static: t0 = t1, dt = 0);
    xb, s: x = x_b + s y (static: ``xb`` None, s = 1); fixed: the prescribed values of the unknown
    (only their fixed components count: velocities, or positions in a static solve); mask: the
    free-component mask; ops: the vector algebra (:class:`~warpfem.solvers.state.DeviceVectors`);
    static: a quasi-static solve; label: how failures name the step ("step 3")."""

    state: object
    t0: float
    t1: float
    dt: float
    xb: object
    s: float
    fixed: object
    mask: object
    ops: object
    static: bool = False
    label: str = "step"


class InfeasibleStart(ValueError):
    """Raised by a form's ``check_start`` when the step's start is outside its domain; ``reason``
    is the short reason the failed step's ``SolveStats`` reports."""

    def __init__(self, message, reason="infeasible start"):
        super().__init__(message)
        self.reason = reason


#: a form that kept its lag (``keep_below``) in a solve not converged this many accepted iterations
#: later makes the update after all (measured: a float32 step of the ``ball_bowl`` scene cycled
#: between two iterates near its solution for 96 iterations on its kept lag)
LAG_KEPT_STALL = 8


def _takes_keep_below(form) -> bool:
    """Whether the form's ``update_lagging`` takes ``keep_below`` (a form written before it did
    not: it always updates)."""
    import inspect

    try:
        params = inspect.signature(form.update_lagging).parameters
    except (TypeError, ValueError):
        return False
    return "keep_below" in params or any(p.kind is p.VAR_KEYWORD for p in params.values())


def lagged_change(before, after):
    """(change, scale) of a lagged array updated from ``before`` to ``after`` (numpy arrays): the
    largest absolute change (inf when the sizes differ: other pairs) and the largest magnitude of
    either; what ``Form.update_lagging`` returns."""
    before, after = np.asarray(before, dtype=np.float64), np.asarray(after, dtype=np.float64)
    scale = max(float(np.abs(after).max(initial=0.0)), float(np.abs(before).max(initial=0.0)))
    if before.shape != after.shape:
        return float("inf"), scale
    return (float(np.abs(after - before).max()) if after.size else 0.0), scale


class Form:
    """Base class of a term of the incremental potential (see the module docstring: evaluation,
    place and life cycle; every life-cycle hook here does nothing)."""

    name = "form"
    variable = "y"  # "y": a function of the unknown; "x": of the positions x = x_b + s y
    joint = False  # gradient measured jointly with the other joint forms (the quadratic terms)
    weight = 1.0
    order = 100  # place among the non-joint forms (elastic 0, contact 10 / 20, load 100)

    def energy(self, y, x, acc):
        pass

    def gradient(self, y, x, scale, g, acc):
        pass

    def hessian(self, y, x, scale, values):
        pass

    def read(self, row):
        """(E, |E|, feasible) from this form's accumulator row (unweighted)."""
        return float(row[0]), abs(float(row[0])), True

    def gradient_magnitude(self, row, scale):
        return 0.0

    def extra_blocks(self):
        """(k, 2) int array of vertex pairs (i != j) whose Hessian blocks this form adds beyond the
        mesh's element pattern, or None."""
        return None

    def bind(self, acc, slot):
        """The potential gives the form its accumulator and the first slot of its row."""
        self.acc_slot = int(slot)

    def capture_key(self):
        """What this form's launches depend on besides the potential's vectors, weights and s
        (a hashable value), or None when its energy / gradient / Hessian do host work or read
        back (then the Newton iteration's launches are not captured as a graph). A form returns a
        key only when equal keys mean identical launches (the same arrays, scalars and structs)."""
        return None

    # -- life cycle (called by the simulator; defaults: nothing) ----------------------------------------
    def enabled(self) -> bool:
        """Whether the form is in the potential of the coming step."""
        return True

    def begin_step(self, ctx: StepContext):
        """A step (or static load step) begins (:class:`StepContext`): set what the form lags or
        moves over the step."""

    def check_start(self, x, ctx: StepContext):
        """Raise :class:`InfeasibleStart` when the positions ``x`` the step starts from are outside
        the form's domain (called only when a form bounds the step)."""

    #: the form's lagged quantities are taken again only from an iterate whose relative gradient is at
    #: most this (and that a full Newton step reached); default ``LAG_BELOW``
    lag_below = LAG_BELOW
    #: the Newton iterations a solve with this form needs at most, as a default: a simulator whose
    #: ``max_iters`` was not given allows the largest of its forms' (None: no need beyond the default)
    newton_iterations = None

    def uses_lagging(self) -> bool:
        """Whether the form lags a quantity that :meth:`update_lagging` can take again."""
        return False

    def update_lagging(self, x, keep_below=0.0):
        """Take the lagged quantities again from the positions x (an iterate near the step's
        solution); returns (change, scale) (:func:`lagged_change`), or None when nothing was lagged
        or nothing changed (then the potential is not evaluated again). With ``keep_below`` > 0 and
        a change of at most ``keep_below`` x scale, the lag stays as it was and (change, scale,
        False) is returned."""
        return None

    def state_dict(self) -> dict:
        """What the form carries from one step to the next that is not a function of the step's
        start state (an adaptive stiffness, a kept set of candidate pairs, a lagged quantity the
        next step reads), as a flat dict of numpy arrays and Python scalars (keys without "/"
        prefixes of their own are fine: the simulator files them under ``form/NAME/``). Saved by
        ``Simulator.state_dict`` so that a run continued from a checkpoint is bit-identical.
        Default: nothing."""
        return {}

    def load_state_dict(self, state):
        """Set what :meth:`state_dict` returned. ``state`` is a read-only mapping of the form's keys
        (a :class:`warpfem.io.checkpoint.StateView`: ``state.array(key, shape, dtype)``,
        ``state.number(key)``, ... check the value and raise a one-line error naming the key).
        Check everything before writing anything. Default: nothing."""

    def static_error(self):
        """None when the form may join a quasi-static solve, else why not (the message of
        ``solve_static``'s ValueError). Default: forms of x may, forms of y (a velocity) not."""
        if self.variable == "x":
            return None
        return (f"solve_static does not handle the form {self.name!r}: it is a function of the step's velocity "
                "(variable 'y')")


class _QuadraticForm(Form):
    """1/2 (y - y0)^T (sum_k c_k A_k) (y - y0) over matrices in the Hessian's pattern."""

    joint = True

    def __init__(self, ops, pattern, terms, y0):
        self.ops, self.pattern, self.terms, self.y0 = ops, pattern, list(terms), y0
        self._tmp = ops.new_vector()

    def _apply(self, y, g, scale, acc, gradient, energy):
        pt, S = self.pattern, self.ops.scalar
        for values, c in self.terms:
            if c != 0.0:
                launch(LK.bsr_diff_mv_kernel, pt.num_rows, [pt.offsets, pt.columns, values(), y, self.y0, S(c * scale),
                                                            g, acc, self.acc_slot, gradient, energy], self.ops.device)

    def energy(self, y, x, acc):
        self._apply(y, self._tmp, 1.0, acc, 0, 1)

    def gradient(self, y, x, scale, g, acc):
        self._apply(y, g, scale, acc, 1, 0)

    def capture_key(self):
        return (id(self), self.acc_slot, _ptr(self.y0), tuple((_ptr(values()), c) for values, c in self.terms if c != 0.0))

    def hessian(self, y, x, scale, values):
        S = self.ops.scalar
        for vals, c in self.terms:
            if c != 0.0:
                launch(LK.add_scaled_kernel, self.pattern.nnz, [vals(), S(c * scale), values], self.ops.device)


class InertiaForm(_QuadraticForm):
    """1/2 (y - y_hat)^T M (y - y_hat): gradient M (y - y_hat), Hessian M. ``mass`` returns the
    mass matrix's block values (a callable: the values follow the pattern when it grows)."""

    name = "inertia"

    def __init__(self, ops, pattern, mass, y_hat=None):
        super().__init__(ops, pattern, [(mass, 1.0)], y_hat)

    def set_prediction(self, y_hat):
        self.y0 = y_hat


class DampingForm(_QuadraticForm):
    """1/2 y^T (alpha M + beta K_n) y: Rayleigh damping (weight s from the integrator)."""

    name = "damping"

    def __init__(self, ops, pattern, mass, alpha, stiffness, beta):
        super().__init__(ops, pattern, [(mass, float(alpha)), (stiffness, float(beta))], ops.zero)


class LoadForm(Form):
    """-y^T f_ext (weight s x load scale): gradient -f_ext. ``fext`` is the device array of the
    external forces (updated in place by the simulator's ``sync_model``), ``norm`` its 2-norm."""

    name = "load"
    order = 100  # last: a constant vector added after the other gradients

    def __init__(self, ops, fext, norm=0.0):
        self.ops, self.fext, self.norm = ops, fext, float(norm)

    def energy(self, y, x, acc):
        launch(LK.dot_slot_kernel, self.ops.n, [y, self.fext, wp.float64(-1.0), acc, self.acc_slot], self.ops.device)

    def gradient(self, y, x, scale, g, acc):
        launch(LK.axpy_kernel, self.ops.n, [self.ops.scalar(-scale), self.fext, g], self.ops.device)

    def gradient_magnitude(self, row, scale):
        return abs(scale) * self.norm

    def capture_key(self):
        return (id(self), self.acc_slot, _ptr(self.fext))


class ElasticForm(Form):
    """V(x) summed over quadrature-point sets (``QuadratureSet``s: count, points, material, energy
    buffer, element group: the pattern's ``block_indices`` entry of its elements, one per body);
    Hessian SPD-projected per point when ``options.project_hessian``."""

    name = "elastic"
    variable = "x"
    order = 0

    def __init__(self, ops, qp_sets, pattern, options):
        self.ops, self.qp_sets, self.pattern, self.options = ops, qp_sets, pattern, options
        self._fa = ops.new_vector()
        #: the Newton loop's choice for its systems (None: the options'; False: the exact Hessian,
        #: project-on-demand Newton before a system needed the projection)
        self.project_now = None

    def energy(self, y, x, acc):
        for qs in self.qp_sets:
            launch(FK.qp_energy_sum_kernel, qs.count, [x, qs.points, qs.material, acc, self.acc_slot], self.ops.device)

    def read(self, row):
        return float(row[0]), float(row[1]), True

    def _gather(self, qs, hessian=False):
        """The gather-assembly maps and slot buffers of a point set (``kernels.fem.element_slot_maps``),
        built on first use per set and pattern: (force offsets, entries, slots) and, with
        ``hessian``, (block offsets, entries, slots)."""
        group = getattr(qs, "group", 0)
        bi = self.pattern.block_indices[group]
        pts = qs.points
        key = (id(pts), qs.count, _ptr(pts.element), _ptr(pts.elements), int(pts.k))
        cache = self.__dict__.setdefault("_maps", {})
        entry = cache.get(key)
        if entry is None:
            dev = self.ops.device
            k = int(pts.k)
            fo, fe = FK.element_slot_maps(pts.element.numpy(), pts.elements.numpy(), k, num_vertices=self.ops.n)
            if len(cache) > 4 * len(self.qp_sets) + 4:  # point sets replaced since: drop the old maps
                cache.clear()
            entry = cache[key] = {"k": k, "points": pts, "force": (wp.array(fo, dtype=wp.int32, device=dev),
                                                                   wp.array(fe, dtype=wp.int32, device=dev),
                                                                   wp.zeros(qs.count * k, dtype=self.ops.vec, device=dev)),
                                  "force_np": (fo, fe)}
        if hessian and entry.get("blocks_of") != (_ptr(bi), self.pattern.nnz):
            dev, k = self.ops.device, entry["k"]
            _, _, bo, be = FK.element_slot_maps(pts.element.numpy(), pts.elements.numpy(), k, bi.numpy(),
                                                num_vertices=self.ops.n, nnz=self.pattern.nnz)
            entry["blocks"] = (wp.array(bo, dtype=wp.int32, device=dev), wp.array(be, dtype=wp.int32, device=dev),
                               wp.zeros(qs.count * k * (k + 1) // 2, dtype=self.ops.mat, device=dev))
            entry["blocks_of"] = (_ptr(bi), self.pattern.nnz)
        return entry

    def add_force(self, x, f):
        """f += the elastic force -dV/dx at x, summed per vertex in a fixed order (the gradient's
        gather maps): the same bits on any device and thread count."""
        dev = self.ops.device
        for qs in self.qp_sets:
            off, ent, slots = self._gather(qs)["force"]
            launch(FK.qp_force_and_abs_kernel, qs.count, [x, qs.points, qs.material, self.ops.scalar(1.0), slots,
                                                          slots, 1], dev)
            launch(FK.gather_force_kernel, off.shape[0] - 1, [off, ent, slots, f, f, 0, FK.no_rows(dev), 0], dev)

    def gradient(self, y, x, scale, g, acc):
        fa, dev = self._fa, self.ops.device
        if self._cpu_rows():
            self._gradient_cpu(x, scale, g, acc)
            return
        fa.zero_()
        none = FK.no_rows(dev)
        for qs in self.qp_sets:
            off, ent, slots = self._gather(qs)["force"]
            launch(FK.qp_force_and_abs_kernel, qs.count, [x, qs.points, qs.material, self.ops.scalar(-scale), slots,
                                                          slots, 1], dev)
            launch(FK.gather_force_kernel, off.shape[0] - 1, [off, ent, slots, g, fa, 1, none, 0], dev)
        launch(LK.dot_slot_kernel, self.ops.n, [fa, fa, _F64_ONE, acc, self.acc_slot + 2], dev)

    def _cpu_rows(self):
        """Whether the force's magnitude is summed in rows of ``FORCE_ROW_BLOCK`` vertices on the CPU
        (:meth:`_gradient_cpu`), rather than by the fixed-order reduction of other devices."""
        on = self.__dict__.get("_on_cpu")
        if on is None:
            on = self._on_cpu = bool(wp.get_device(self.ops.device).is_cpu)
        return on and not generic.ordered_sums(self.ops.device)

    def _force_plan(self, threads):
        """How the CPU force is cut for ``threads`` threads: (vertex bounds, per set the points each
        part computes, halo): the vertex ranges start on row boundaries (``FORCE_ROW_BLOCK``), near
        an even share of the gathered slots where the seam is narrowest; with ``halo`` each part's
        points are every point its vertices gather (a contiguous range, overlapping the next
        part's at the seam), else (``FORCE_SEAM_MAX_POINTS``) the points are cut evenly and
        gathered after all are computed."""
        entries = [self._gather(qs) for qs in self.qp_sets]
        key = (threads, generic.MIN_CHUNK, FORCE_ROW_BLOCK, FORCE_SEAM_MAX_POINTS, tuple((id(e), e["k"]) for e in entries))
        plans = self.__dict__.setdefault("_plans", {})
        plan = plans.get(key)
        if plan is not None:
            return plan
        n, B = self.ops.n, FORCE_ROW_BLOCK
        total = sum(qs.count for qs in self.qp_sets)
        min_chunk = generic.split_min_chunk(FK.qp_force_and_abs_kernel)
        parts = max(1, min(threads, total // min_chunk, -(-n // B)))
        # per vertex: the points it gathers (work), the first and last of them (per set)
        work = np.zeros(n, dtype=np.float64)
        lo_q, hi_q = [], []
        for e in entries:
            fo, fe = e["force_np"]
            cnt = np.diff(fo.astype(np.int64))
            work += cnt / e["k"]
            q = fe.astype(np.int64) // e["k"]
            has = cnt > 0
            mn = np.full(n, np.iinfo(np.int64).max // 4, dtype=np.int64)
            mx = np.full(n, -1, dtype=np.int64)
            if q.size:
                starts = fo[:-1][has].astype(np.int64)
                mn[has] = np.minimum.reduceat(q, starts)
                mx[has] = np.maximum.reduceat(q, starts)
            lo_q.append(mn)
            hi_q.append(mx)
        cum = np.concatenate([[0.0], np.cumsum(work)])
        # the last point gathered by the vertices before b and the first gathered by those from b on:
        # a cut at b makes the parts' point ranges overlap by their difference (computed twice)
        seam = [(np.concatenate([[-1], np.maximum.accumulate(mx)]),
                 np.concatenate([np.minimum.accumulate(mn[::-1])[::-1], [np.iinfo(np.int64).max // 4]]))
                for mn, mx in zip(lo_q, hi_q)]
        bounds = [0]
        for c in range(1, parts):
            target = cum[-1] * c / parts
            lo = max(bounds[-1] + B, int(np.searchsorted(cum, target - cum[-1] / (4 * parts))) // B * B)
            hi = min(n - 1, int(np.searchsorted(cum, target + cum[-1] / (4 * parts))))
            cand = np.arange(lo, hi + 1, B)
            if cand.size == 0:
                continue
            overlap = sum(np.maximum(0, before[cand] + 1 - after[cand]) for before, after in seam)
            best = cand[np.argmin(overlap + 2.0 * np.abs(cum[cand] - target))]
            bounds.append(int(best))
        bounds.append(n)
        ranges = []
        for e, qs in zip(entries, self.qp_sets):
            fo, fe = e["force_np"]
            r = []
            for v0, v1 in zip(bounds[:-1], bounds[1:]):
                q = fe[fo[v0]:fo[v1]] // e["k"]
                r.append((int(q.min()), int(q.max()) + 1) if q.size else (0, 0))
            ranges.append(r)
        # the busiest part's points beyond an even share (the seam's cost on the critical path)
        busiest = max(sum(r[t][1] - r[t][0] for r in ranges) for t in range(len(bounds) - 1))
        halo = len(bounds) == 2 or busiest - total / (len(bounds) - 1) <= FORCE_SEAM_MAX_POINTS
        if not halo:
            ranges = [[(qs.count * c // (len(bounds) - 1), qs.count * (c + 1) // (len(bounds) - 1))
                       for c in range(len(bounds) - 1)] for qs in self.qp_sets]
        if len(plans) > 8:
            plans.clear()
        plan = plans[key] = (bounds, ranges, halo)
        return plan

    def _gradient_cpu(self, x, scale, g, acc):
        """The gradient on the CPU with as few dispatches as the split allows: each thread computes
        its points' slots, then gathers its range of vertices (``with_abs`` 2: the magnitudes
        assigned by the first set, no zeroing pass) and adds their squared magnitudes into rows of
        ``FORCE_ROW_BLOCK`` vertices, all in one dispatch when each part's points are those its
        vertices gather (a point on the seam is computed by both parts, into the same slots with
        the same bits); the rows are then added in order. The same bits for any thread count."""
        from warpfem.threads import get_threads

        fa, dev, n = self._fa, self.ops.device, self.ops.n
        bounds, ranges, halo = self._force_plan(get_threads())
        rows = self.__dict__.get("_rows")
        nrows = -(-n // FORCE_ROW_BLOCK)
        if rows is None or rows.shape[0] != nrows:
            rows = self._rows = wp.zeros(nrows, dtype=wp.float64, device=dev)
        else:
            rows.zero_()
        capturing = generic.cpu_capturing(dev)
        if not capturing:
            # replayed launches (``RecordedLaunch``: the kernel's entry point called with its
            # arguments packed once, ~2 us instead of ~20 us per launch), per set of arguments;
            # structs are packed by value, so their fields are part of the key (as in ``capture_key``)
            mats = tuple((id(qs.points), int(qs.material.kind), float(qs.material.mu), float(qs.material.lam))
                         for qs in self.qp_sets)
            key = (tuple(bounds), halo, id(x), id(g), id(fa), id(rows), id(acc), self.acc_slot, float(scale), mats)
            cache = self.__dict__.setdefault("_replays", {})
            entry = cache.get(key)
            if entry is not None:
                from warpfem.threads import run_chunks

                for ph in entry[0]:
                    if len(ph) > 1:
                        run_chunks(ph)
                        generic.COUNTERS["split"] += 1
                    elif ph:
                        ph[0]()
                entry[1]()
                generic.COUNTERS["launches"] += entry[2]
                return
        c = self.ops.scalar(-scale)
        last = len(self.qp_sets) - 1
        forces, gathers = [], []
        for t, (v0, v1) in enumerate(zip(bounds[:-1], bounds[1:])):
            fs, gs = [], []
            for i, qs in enumerate(self.qp_sets):
                off, ent, slots = self._gather(qs)["force"]
                q0, q1 = ranges[i][t]
                if q1 > q0:
                    fs.append((FK.qp_force_and_abs_kernel, q1 - q0,
                               (x, qs.points, qs.material, c, slots, slots, 1, q0)))
                gs.append((FK.gather_force_kernel, v1 - v0, (off, ent, slots, g, fa, 2 if i == 0 else 1, rows,
                                                             FORCE_ROW_BLOCK if i == last else 0, v0)))
            if halo:  # the thread's own points, then its vertices
                forces.append(fs + gs)
            else:
                forces.append(fs)
                gathers.append(gs)
        phases = [forces] if halo else [forces, gathers]
        reduce = (LK.reduce_rows_kernel, 1, [rows, nrows, 1, 1, 0, acc, self.acc_slot + 2])
        if capturing:  # recorded into the caller's graph, in order
            launch_phases(phases, dev)
            launch(*reduce, dev)
            return
        # recorded (and run) in this thread, in order; replayed by the next calls with these arguments
        if len(cache) >= 8:
            cache.clear()
        recorded = [[[RecordedLaunch(k, dim, list(args), dev, split=False) for k, dim, args in seq] for seq in ph]
                    for ph in phases]
        final = RecordedLaunch(*reduce, dev, split=False)
        for ph in recorded:
            for seq in ph:
                for r in seq:
                    r()
        final()
        counted = sum(max((len(q) for q in ph), default=0) for ph in phases) + 1
        generic.COUNTERS["launches"] += counted
        # split launches, though run in order this once: a graph capture of the caller's sequence
        # would replay them on one thread (``CapturedSequences`` leaves such sequences uncaptured)
        generic.COUNTERS["split"] += sum(1 for ph in phases if sum(1 for q in ph if q) > 1)
        cache[key] = ([[_run_in_order(seq) for seq in ph if seq] for ph in recorded], final, counted)

    def gradient_magnitude(self, row, scale):
        return float(np.sqrt(row[2]))

    def hessian(self, y, x, scale, values):
        self.assemble(x, scale, values, project=self.project_now)

    def capture_key(self):
        # a struct is packed by value into a graph: its fields are part of the key
        mats = tuple((id(qs.points), qs.count, int(qs.material.kind), float(qs.material.mu), float(qs.material.lam),
                      _ptr(self.pattern.block_indices[getattr(qs, "group", 0)])) for qs in self.qp_sets)
        # the projection the Hessian is assembled with (project-on-demand Newton switches it)
        project = self.options.project_hessian if self.project_now is None else self.project_now
        return (id(self), self.acc_slot, _ptr(self._fa), bool(project), mats)

    def assemble(self, x, scale, values, project=None):
        """values += scale d2V/dx2 at x (SPD-projected per point if ``project``, default the options')."""
        project = self.options.project_hessian if project is None else project
        dev = self.ops.device
        for qs in self.qp_sets:
            off, ent, slots = self._gather(qs, hessian=True)["blocks"]
            launch(FK.qp_hessian_kernel, qs.count, [x, qs.points, qs.material, self.ops.scalar(scale), int(project),
                                                    self.pattern.block_indices[getattr(qs, "group", 0)], slots, 1], dev)
            launch(FK.gather_blocks_kernel, off.shape[0] - 1, [off, ent, slots, values], dev)


def _run_in_order(seq):
    def run():
        for r in seq:
            r()

    return run


def _capture_key(form):
    """The form's capture key; a subclass of a built-in form that does not define its own
    ``capture_key`` gets None (it may do host work the built-in key does not describe)."""
    cls = type(form)
    if cls in (InertiaForm, DampingForm, LoadForm, ElasticForm) or "capture_key" in cls.__dict__:
        return form.capture_key()
    return None


class IncrementalPotential:
    """E(y) = sum_f w_f E_f(x(y)) over the mesh's vertices, x = x_b + s y (``xb=None``: x = y).

    The ``problem`` of :func:`~warpfem.solvers.nonlinear.newton_solve`: device vectors, a masked
    block-sparse Newton system solved by ``linear_solver``. Built once per simulator; each step
    calls :meth:`begin` with its prediction and the forms' weights.

    Args:
        ops: the simulator's :class:`~warpfem.solvers.state.DeviceVectors`.
        forms: the forms (joint ones are moved first).
        pattern: the Hessian's :class:`~warpfem.solvers.sparse.BlockPattern` holder (``system``: an
            object with ``pattern``, ``hessian_values`` and ``ensure_blocks(pairs)``).
        mask: the free-component mask (device vec3 array, updated in place).
        linear_solve: ``(values, rhs, out, opts) -> LinearSolveResult``.
        work: the :class:`Workspace`.
    """

    def __init__(self, ops, forms, *, system, mask, linear_solve, work):
        self.ops, self.system, self.mask, self.linear_solve, self.work = ops, system, mask, linear_solve, work
        self.n = ops.n
        self.eps = float(np.finfo(ops.np_dtype).eps)
        # an energy change (or predicted change) below this fraction of the energy's magnitude is not
        # resolved by its sums, whose terms cancel (measured: round-off of 1e-13 relative in float64 on
        # a stiff bar, E = 1e9): a full Newton step is then judged by whether it halves the gradient
        # norm (see newton_solve)
        self.gradient_test_below = max(1e-10, 64.0 * self.eps)
        self.forms = []
        self.host_syncs = 0  # read-backs of this potential (cumulative)
        self.xb, self.s = None, 1.0
        self._x_of_y = None
        #: (y, d, bound, form ids): the step bound along d of some forms, read with the friction
        #: pin's gate (the next max_step(y, d) reads only the other forms' bounds; anything that
        #: writes y or d drops it)
        self._bound = None
        self.projecting = True  # whether Newton systems use the projected Hessian (see set_projection)
        #: the Newton iteration's two fixed sequences of launches (before and after the linear solve),
        #: captured as graphs and replayed (``kernels.generic.CapturedSequences``; ``.enabled``)
        self.graphs = CapturedSequences(ops.device)
        self.set_forms(forms)

    # -- forms --------------------------------------------------------------------------------------
    def set_forms(self, forms):
        """Replace the list of forms (:meth:`ordered`); the accumulator grows to fit."""
        forms = self.ordered(forms)
        self.forms = forms
        size = _HEAD + ROW * len(forms)
        # five sections (energy, gradient, direction of the trial; energy, gradient of the start)
        # and the linear solver's report (4), all read at once by newton_step (views made once)
        self.acc = wp.zeros(5 * size + 4, dtype=wp.float64, device=self.ops.device)
        self._size = size
        self._acc_e, self._acc_g, self._acc_d, self._acc_e0, self._acc_g0 = (
            self.acc[k * size:(k + 1) * size] for k in range(5))
        self._report_at = 5 * size
        for i, f in enumerate(forms):
            f.bind(self.acc, _HEAD + ROW * i)

    @staticmethod
    def ordered(forms):
        """The forms in evaluation order: joint forms first, then the others by ``order`` (a form
        without one: 100), each group in the given order."""
        forms = list(forms)
        return [f for f in forms if f.joint] + sorted((f for f in forms if not f.joint),
                                                      key=lambda f: getattr(f, "order", 100))

    def set_projection(self, on: bool):
        """Project-on-demand Newton (``NewtonOptions.hessian_projection = "on_demand"``): with
        ``on`` False the elastic forms assemble their exact Hessian and the linear solver reports an
        indefinite matrix instead of shifting it (``definite_only``); True restores the options'
        projection."""
        self.projecting = bool(on)
        for f in self.forms:
            if hasattr(f, "project_now"):
                f.project_now = None if on else False
        solver = getattr(self.system, "solver", None)
        if solver is not None and hasattr(solver, "definite_only"):
            solver.definite_only = not on

    def add_form(self, form):
        self.set_forms(self.forms + [form])

    def form(self, name):
        return next((f for f in self.forms if f.name == name), None)

    def begin(self, xb, s, weights=None):
        """A new step (or static load step): x = x_b + s y (``xb=None``: x = y) and the forms'
        weights (name -> w; forms not named keep theirs). Forms that add Hessian blocks outside
        the pattern make it grow here (the linear solver re-analyses it)."""
        self.xb, self.s = xb, float(s)
        self._x_of_y = None
        self._bound = None
        for i, f in enumerate(self.forms):  # a form may serve another potential too (the static one)
            if getattr(f, "acc_slot", None) != _HEAD + ROW * i:
                f.bind(self.acc, _HEAD + ROW * i)
        for f in self.forms:
            if weights and f.name in weights:
                f.weight = float(weights[f.name])
        extra = [b for b in (f.extra_blocks() for f in self.forms) if b is not None and len(b)]
        if extra:
            self.system.ensure_blocks(np.concatenate(extra))
        return self

    def scales(self, form):
        """(gradient scale, Hessian scale) of a form: its weight times the chain factors dx/dy."""
        w = form.weight
        if form.variable == "x":
            return w * self.s, w * self.s * self.s
        return w, w

    # -- vectors ----------------------------------------------------------------------------------
    def new_vector(self):
        return self.ops.new_vector()

    def vectors(self):
        """(g, d, y_try): the work vectors of the Newton loop. The loop swaps its gradient vector
        with ``work.g_try`` when it accepts the fused trial's gradient, so ``work.g`` holds the
        current gradient only until then: a measurement reads the ``g`` the loop passes on."""
        w = self.work
        return w.g, w.d, w.y_try

    def _x_of(self, y):
        if self.xb is None:
            return y
        x = self.work.x
        if self._x_of_y is y:  # x already holds x_b + s y (see assign)
            return x
        self.ops.lincomb(1.0, self.xb, self.s, y, x)
        self._x_of_y = y
        return x

    def x_of(self, y):
        """x = x_b + s y (in the work buffer; y itself when x is the unknown)."""
        return self._x_of(y)

    def trial(self, y, alpha, d, out):
        self._written(out)
        self.ops.lincomb(1.0, y, alpha, d, out)
        if self._bound is not None and (out is self._bound[0] or out is self._bound[1]):
            self._bound = None
        if self._x_of_y is out:
            self._x_of_y = None

    def assign(self, dst, src):
        self._written(dst)
        wp.copy(dst, src)
        self._bound = None
        # x = x_b + s src is still in the work buffer: it is now x of dst
        self._x_of_y = dst if self._x_of_y is src else None

    # -- value, gradient, Hessian (launches only) -----------------------------------------------------
    def _launch_energy(self, y, acc):
        acc.zero_()
        x = self._x_of(y)
        for f in self.forms:
            f.energy(y, x, acc)

    def _launch_gradient(self, y, g, acc, d=None):
        """g = P grad E(y) with its norms into acc; with ``d``, also g . d into acc[_G_TD]."""
        acc.zero_()
        g.zero_()
        x = self._x_of(y)
        joint = False
        for f in self.forms:
            if joint and not f.joint:
                launch(LK.dot_slot_kernel, self.n, [g, g, _F64_ONE, acc, _G_JOINT], self.ops.device)
                joint = False
            f.gradient(y, x, self.scales(f)[0], g, acc)
            joint = joint or f.joint
        if joint:
            launch(LK.dot_slot_kernel, self.n, [g, g, _F64_ONE, acc, _G_JOINT], self.ops.device)
        launch(LK.gradient_finish_kernel, self.n, [g, self.ops.zero, self.ops.scalar(0.0), self.mask, acc, _G_NORM],
               self.ops.device)
        if d is not None:
            launch(LK.dot_slot_kernel, self.n, [g, d, _F64_ONE, acc, _G_TD], self.ops.device)

    def _launch_direction(self, y, g, d, acc):
        acc.zero_()
        use_xb = self.xb is not None
        launch(LK.newton_check_kernel, self.n, [g, d, y, self.xb if use_xb else y, self.ops.scalar(self.s), int(use_xb),
                                                acc, _D_GD], self.ops.device)

    # -- reading the accumulator ----------------------------------------------------------------------
    def _read(self, a):
        self.host_syncs += 1
        return read(a)

    def _energy_of(self, a):
        E = jE = mag = 0.0
        for i, f in enumerate(self.forms):
            o = _HEAD + ROW * i
            e, m, feasible = f.read(a[o:o + ROW])
            if not feasible:  # outside the form's domain (a vertex on or inside a collider)
                return float("inf"), float("inf")
            w = f.weight
            E += w * e
            if f.joint:
                jE += w * e
            else:
                mag += abs(w) * m
        return E, abs(jE) + mag

    def _gradient_of(self, a):
        mag = float(np.sqrt(a[_G_JOINT]))
        for i, f in enumerate(self.forms):
            if not f.joint:
                o = _HEAD + ROW * i
                mag += f.gradient_magnitude(a[o:o + ROW], self.scales(f)[0])
        return mag, float(np.sqrt(a[_G_NORM]))

    def _direction_of(self, a, d):
        # max |d| of the direction checked, kept for direction_max while d is not written again
        self._checked = (d, float(a[_D_GD + 1]))
        scale = a[_D_GD + 2] + (a[_D_GD + 3] / abs(self.s) if self.s != 0.0 else 0.0)
        negligible = bool(a[_D_GD + 1] <= 8.0 * self.eps * scale)
        return float(a[_D_GD]), negligible

    # -- the problem interface of newton_solve --------------------------------------------------------
    def energy(self, y):
        """(E, the sum of the magnitudes of its terms): one host read-back."""
        self._launch_energy(y, self._acc_e)
        return self._energy_of(self._read(self._acc_e))

    def gradient(self, y, g):
        """g = P grad E(y); returns (the sum of the norms of its terms, ||g||): one host read-back."""
        self._launch_gradient(y, g, self._acc_g)
        return self._gradient_of(self._read(self._acc_g))

    def evaluate(self, y, g):
        """(E, |E|, gradient magnitude, ||P g||) with g = P grad E(y): one host read-back."""
        self._launch_energy(y, self._acc_e)
        self._launch_gradient(y, g, self._acc_g)
        s = self._size
        a = self._read(self.acc[:2 * s])
        return self._energy_of(a[:s]) + self._gradient_of(a[s:2 * s])

    def trial_step(self, y, g, d, alpha, y_try, g_try):
        """The direction check of d, then y_try = y + alpha d with its energy and gradient (into
        g_try), all read back at once: (g.d, negligible, E, |E|, gradient magnitude, ||P g_try||,
        g_try . d)."""
        self._launch_direction(y, g, d, self._acc_d)
        self.trial(y, alpha, d, y_try)
        self._launch_energy(y_try, self._acc_e)
        self._launch_gradient(y_try, g_try, self._acc_g, d)
        a = self._read(self.acc[:3 * self._size])
        s = self._size
        return (self._direction_of(a[2 * s:3 * s], d) + self._energy_of(a[:s]) + self._gradient_of(a[s:2 * s])
                + (float(a[s + _G_TD]),))

    def newton_step(self, y, g, d, y_try, g_try, opts, start=False):
        """A Newton iteration's device work with one read-back: the Newton system's solve (a linear
        solver that can defer its read-back runs as many chunks as its last solve needed), the
        direction check of d and the energy and gradient of the full step y_try = y + d (into
        g_try). Returns (linear solve result, the :meth:`trial_step` tuple). Solvers that cannot
        defer (direct, AMG) solve first and the rest is read once after. ``start``: first
        evaluate the energy and gradient (into g) at y, and return their :meth:`evaluate` tuple
        third (the first iteration of a solve then costs one read-back too)."""
        solver = self.system.solver
        values, rhs = self.system.hessian_values, self.work.rhs
        self._written()  # (d, y_try and g_try are written)

        def before_solve():  # the start's energy and gradient, the Hessian, the right-hand side
            if start:
                self._launch_energy(y, self._acc_e0)
                self._launch_gradient(y, g, self._acc_g0)
            self.assemble_hessian(y, values)
            launch(LK.scale_copy_kernel, self.n, [g, self.ops.scalar(-1.0), rhs], self.ops.device)

        self._captured(("hessian", bool(start), self._x_of_y is y), (y, g, values, rhs), before_solve, y)
        chunks = getattr(solver, "deferred_chunks", 0)
        s, r = self._size, self._report_at
        deferred = hasattr(solver, "solve_deferred") and chunks > 0
        if deferred:
            solver.prepare(values, self.mask)
            deferred = solver.can_defer()
            if not deferred:
                lin = solver.solve(rhs, d, tol=opts.cg_tol, maxiter=opts.max_cg_iters)
        else:
            lin = self.linear_solve(values, rhs, d, opts)
        if deferred:
            solver.solve_deferred(rhs, d, tol=opts.cg_tol, maxiter=opts.max_cg_iters, chunks=chunks, report_out=self.acc,
                                  report_offset=r, graphs=self.graphs)

        def after_solve():  # the direction check, the full step, its energy and gradient
            self._launch_direction(y, g, d, self._acc_d)
            self.trial(y, 1.0, d, y_try)
            self._launch_energy(y_try, self._acc_e)
            self._launch_gradient(y_try, g_try, self._acc_g, d)

        self._captured(("trial",), (y, g, d, y_try, g_try), after_solve, y_try)
        a = self._read(self.acc)
        first = (self._energy_of(a[3 * s:4 * s]) + self._gradient_of(a[4 * s:5 * s])) if start else None
        trial = (self._direction_of(a[2 * s:3 * s], d) + self._energy_of(a[:s]) + self._gradient_of(a[s:2 * s])
                 + (float(a[s + _G_TD]),))
        if deferred:
            lin, changed = solver.complete_deferred(a[r:r + 4])
            if changed:  # the solve needed more chunks than guessed: d is new, evaluate its step again
                trial = self.trial_step(y, g, d, 1.0, y_try, g_try)
        return (lin, trial, first) if start else (lin, trial)

    def _captured(self, tag, vectors, fn, x_of):
        """Run ``fn`` (launches only) through the graph cache, keyed by everything its launches
        depend on: the vectors, the step's x_b, s and weights, the forms' own keys, the mask and
        the accumulator; afterwards x = x_b + s ``x_of`` is in the work buffer (as ``fn`` leaves it)."""
        keys = tuple(_capture_key(f) for f in self.forms)
        if any(k is None for k in keys):
            fn()
            return
        w = self.work
        key = (tag, tuple(_ptr(v) for v in vectors), _ptr(self.xb), self.s, tuple(f.weight for f in self.forms), keys,
               _ptr(self.mask), _ptr(self.acc), _ptr(w.x), _ptr(self.ops.zero), self.n)
        self.graphs.run(key, fn)
        if self.xb is not None:
            self._x_of_y = x_of

    def assemble_hessian(self, y, values):
        values.zero_()
        x = self._x_of(y)
        for f in self.forms:
            f.hessian(y, x, self.scales(f)[1], values)
        return values

    # -- forms that adapt during a solve (contact's barrier stiffness) -----------------------------------
    def masked_gradient(self, y, forms=(), add=None):
        """P g at y as a flat float64 numpy array, g the gradient (in y) of ``forms`` plus whatever
        ``add(x, g, acc)`` launches into g (already scaled): one read-back. For tools such as
        the adaptive barrier stiffness; the loop's own vectors are untouched."""
        g = getattr(self, "_g_aux", None)
        if g is None or g.shape[0] != self.n:
            g = self._g_aux = self.ops.new_vector()
        acc = self._acc_g
        acc.zero_()
        g.zero_()
        x = self._x_of(y)
        for f in forms:
            f.gradient(y, x, self.scales(f)[0], g, acc)
        if add is not None:
            add(x, g, acc)
        launch(LK.gradient_finish_kernel, self.n, [g, self.ops.zero, self.ops.scalar(0.0), self.mask, acc, _G_NORM],
               self.ops.device)
        self.host_syncs += 1
        return read(g).astype(np.float64).ravel()

    def adaptive_forms(self):
        """The forms whose own parameters adapt during a solve (``adaptive_stiffness()`` true)."""
        return [f for f in self.forms if getattr(f, "adaptive_stiffness", None) is not None and f.adaptive_stiffness()]

    def begin_adaptive(self, y) -> bool:
        """At a solve's start y: each adaptive form sets its parameters from the gradient of the
        other forms there (``begin_stiffness(potential, y, g_rest)``). Returns whether one changed."""
        forms = self.adaptive_forms()
        if not forms:
            return False
        adaptive = set(map(id, forms))
        rest = [f for f in self.forms if id(f) not in adaptive and not hasattr(f, "adaptive_stiffness")]
        g_rest = self.masked_gradient(y, rest)
        changed = False
        for f in forms:
            changed = f.begin_stiffness(self, y, g_rest) or changed
        return changed

    def set_lag_updates(self, count, tol, keep_below=0.0, below=None):
        """Lagged quantities (friction's normal forces and normals) taken again from the iterate
        after each of the first ``count`` accepted Newton iterations of the coming solve, by the
        forms that lag (``uses_lagging()``, ``update_lagging(x) -> (change, scale)``, None when they
        lag nothing), while the
        change is above ``tol`` x scale (:attr:`lag_updates` counts them). ``keep_below`` > 0: an
        update whose change is at most ``keep_below`` x scale is not made (the lag is consistent
        to that tolerance; the form makes no further update in the solve; :attr:`lags_kept`
        counts them). ``below``: the relative gradient at or under which an iterate reached by a
        full Newton step is near enough to lag from, for every lagging form (None: each form's
        :attr:`Form.lag_below`)."""
        self._lag_below = None if below is None else float(below)
        self._lag_count, self._lag_tol, self.lag_updates = int(count), float(tol), 0
        self._lag_keep, self.lags_kept = float(keep_below), 0
        self._lag_iter, self._lag_kept_at = 0, {}  # accepted iterations; per form: the one that kept its lag
        self._lag_left = {}  # per form: updates it may still make in this solve

    def after_iteration(self, y, alpha=1.0, residual=0.0) -> bool:
        """After an accepted Newton iteration of step length alpha (``newton_solve``'s hook): the
        adaptive forms' ``after_iteration(x, alpha)`` update what they adapt at y, and the lagging
        forms lag again (:meth:`set_lag_updates`); True when the potential changed (the loop
        evaluates it again, so its line searches compare like with like)."""
        forms = [f for f in self.adaptive_forms() if hasattr(f, "after_iteration")]
        # lag again only from an iterate the full Newton step reached (the quadratic model held there:
        # near the solution); a shortened step (the collision bound, the line search) may be far off
        left = getattr(self, "_lag_left", {})
        kept_at = getattr(self, "_lag_kept_at", {})
        self._lag_iter = it = getattr(self, "_lag_iter", 0) + 1
        # a form that kept its lag (friction_update_tol) in a solve that has not converged
        # LAG_KEPT_STALL iterations later makes the update after all (a solve stalled on the
        # kept potential, e.g. float32 iterates cycling near the solution, goes on with it)
        stalled = [f for f in self.forms if id(f) in kept_at and it - kept_at[id(f)] >= LAG_KEPT_STALL]
        below = getattr(self, "_lag_below", None)
        lagging = ([f for f in self.forms if f.uses_lagging() and residual <= (f.lag_below if below is None else below)
                    and (left.setdefault(id(f), self._lag_count) > 0 or f in stalled)]
                   if getattr(self, "_lag_count", 0) > 0 and alpha >= 1.0 else [])
        if not forms and not lagging:  # nothing adapts (a fixed barrier stiffness) or lags: no work
            return False
        x = self._x_of(y)
        changed = False
        for f in forms:
            changed = f.after_iteration(x, alpha) or changed
        updated = False
        keep = getattr(self, "_lag_keep", 0.0)
        for f in lagging:
            forced = kept_at.pop(id(f), None) is not None
            left[id(f)] = max(left[id(f)] - 1, 0)
            if keep > 0.0 and not forced and _takes_keep_below(f):
                r = f.update_lagging(x, keep_below=keep)
            else:
                r = f.update_lagging(x)
            if r is not None and len(r) > 2 and not r[2]:  # kept as it was: consistent to keep_below
                left[id(f)] = 0
                kept_at[id(f)] = it
                self.lags_kept += 1
                continue
            if r is not None:
                updated = True
                if r[0] <= self._lag_tol * r[1]:  # consistent: no further updates of this form in this solve
                    left[id(f)] = 0
        if updated:
            changed = True
            self.lag_updates += 1
        return changed

    def lag_pending(self) -> bool:
        """Whether a lagging form may still update its lagged quantities in this solve (the step
        test of ``NewtonOptions.step_tol`` waits for it)."""
        if getattr(self, "_lag_count", 0) <= 0:
            return False
        left = getattr(self, "_lag_left", {})
        return any(f.uses_lagging() and left.get(id(f), self._lag_count) > 0 for f in self.forms)

    def step_limit(self, step_tol):
        """The step test's limit on max |d| (``NewtonOptions.step_tol``): a move of every vertex
        below ``step_tol`` x ``body_size`` per second over the step's ``time_step`` (x = x_b + s y:
        |d| <= step_tol L h / |s|); 0 (no test) without a time step (a static solve) or body size."""
        h, L = getattr(self, "time_step", 0.0), getattr(self, "body_size", 0.0)
        if not (step_tol > 0.0 and h > 0.0 and L > 0.0 and self.xb is not None and self.s != 0.0):
            return 0.0
        return step_tol * L * h / abs(self.s)

    def direction_max(self, y, g, d, limit=float("inf")):
        """max |d| of the Newton direction d, or of the unfiltered direction when the friction
        filter changed d and that is larger (one more read-back, only when d itself is within
        ``limit``). max |d| is the one read with d's last direction check (:meth:`direction_check`,
        :meth:`trial_step`, :meth:`newton_step`: no read-back of its own in the Newton loop) while
        d has not been written since by this problem's methods (a write from outside them is not
        seen); otherwise d is checked again (one read-back)."""
        m = self._max_of(y, g, d)
        raw = self.unfiltered_direction()
        if raw is not None and raw is not d and m <= limit:
            m = max(m, self._max_of(y, g, raw))
        return m

    def _max_of(self, y, g, d):
        """max |d|: kept from d's last direction check, or read with a new one."""
        kept = getattr(self, "_checked", None)
        if kept is None or kept[0] is not d:
            self.direction_check(y, g, d)
            kept = self._checked
        return kept[1]

    def bounds_step(self) -> bool:
        """Whether a form bounds the line search's step (then :meth:`max_step` reads it back)."""
        return any(hasattr(f, "max_step") for f in self.forms)

    def max_step(self, y, d):
        """The largest step length <= 1 along d that every form allows (contact's continuous
        collision bound; 1 without such a form): one read-back when a form bounds it."""
        kept, self._bound = self._bound, None
        bounded = [(i, f) for i, f in enumerate(self.forms) if hasattr(f, "max_step")]
        if not bounded:
            return 1.0
        bound, done = 1.0, ()
        if kept is not None and kept[0] is y and kept[1] is d:  # some forms' bounds read with the pin's gate
            bound, done = kept[2], kept[3]
        rest = [(i, f) for i, f in bounded if id(f) not in done]
        if not rest:
            return bound
        acc = self._acc_d
        acc.fill_(1.0)
        x = self._x_of(y)
        for _, f in rest:
            f.max_step(x, d, self.s, acc)
        a = self._read(acc)
        return float(min([bound] + [a[_HEAD + ROW * i + 3] for i, _ in rest]))

    # -- Newton system ------------------------------------------------------------------------------
    def solve_newton_system(self, y, g, d, opts):
        """d ~ -H(y)^-1 g on the free components (the simulator's linear solver); returns its result
        (``iterations``, ``host_syncs``, ...)."""
        self._bound = None
        self._written()  # (d and the kept unfiltered and filtered directions are written)
        values = self.assemble_hessian(y, self.system.hessian_values)
        rhs = self.work.rhs
        launch(LK.scale_copy_kernel, self.n, [g, self.ops.scalar(-1.0), rhs], self.ops.device)
        lin = self.linear_solve(values, rhs, d, opts)
        self._raw_kept = False
        if getattr(opts, "friction_filter", False) and self._filtering_forms():
            w = self.work
            if getattr(w, "d_raw", None) is None or w.d_raw.shape[0] != self.n:
                w.d_raw = self.ops.new_vector()
            wp.copy(w.d_raw, d)
            self._raw_kept = True
            weight = float(getattr(opts, "friction_pin", 0.0))
            if weight > 0.0 and any(hasattr(f, "pin_direction") for f in self._filtering_forms()):
                lin = self._pinned_solve(y, g, d, values, rhs, lin, weight, opts)
            else:
                self.filter_direction(y, d)
        return lin

    #: ``friction_pin``'s gate: the pin runs only in the Newton iterations where the friction filter
    #: cut a contact, which the filter's tally tells with the read-back of the line search's step
    #: bound (False: the pin kernel runs and reads its own count back in every filtered iteration,
    #: the same directions with one more read-back each; for comparison)
    pin_gate = True

    def _pinned_solve(self, y, g, d, values, rhs, lin, weight, opts):
        """The friction filter on d, then ``NewtonOptions.friction_pin``: the Newton system solved
        again with tangential springs (``weight`` x the block's mean diagonal) holding the contacts
        that the filter cut at their cut steps, so that the rest of the body follows them (the
        filter's cuts alone strain the elements around the cut vertices, and the line search then
        shortens the whole step). The pinned solve's direction replaces the filtered one when it
        is a descent direction (it is filtered too); otherwise the filtered one stays. Returns the
        linear result with both solves' iterations.

        The filter's cut count rides on the read-back of the filtering forms' step bounds along the
        filtered d (:meth:`max_step`, kept for the loop's next call when nothing was cut): an iteration
        whose filter cut nothing launches and reads nothing for the pin (and keeps no unfiltered
        direction: d is that direction). A vertex's contacts are
        pinned exactly when the filter cut one of them (both test the unfiltered step with the
        same function), so a cut count above 0 is a pinned count above 0."""
        w = self.work
        filters = self._filtering_forms()
        pins = [f for f in filters if hasattr(f, "pin_direction")]
        gate = self.pin_gate and len(pins) == len(filters)
        x = self._x_of(y)
        if gate:
            acc = self._acc_d
            acc.fill_(1.0)  # max_step's start (a bound of 1); acc[_D_CUTS] = 1 + the filter's cuts
            for f in filters:
                f.filter_direction(y, x, d, tally=(acc, _D_CUTS))
            # the filtering forms' own step bounds (plain launches) ride along; others (surface
            # contact's broad phase) wait for the loop's max_step, which they would repeat after a pin
            own = [(i, f) for i, f in enumerate(self.forms) if hasattr(f, "max_step") and any(f is p for p in pins)]
            for _, f in own:
                f.max_step(x, d, self.s, acc)
            a = self._read(acc)
            if a[_D_CUTS] == 1.0:  # nothing cut: d stays; the loop's max_step along it needs only the others
                self._raw_kept = False  # d is the unfiltered direction: nothing to try or measure besides it
                self._bound = (y, d, float(min([1.0] + [a[_HEAD + ROW * i + 3] for i, _ in own])),
                               {id(f) for _, f in own})
                return lin
        else:
            self.filter_direction(y, d)
        if getattr(w, "d_filt", None) is None or w.d_filt.shape[0] != self.n:
            w.d_filt = self.ops.new_vector()
        wp.copy(w.d_filt, d)
        if gate:
            for f in pins:
                f.pin_direction(y, x, w.d_raw, w.d_filt, values, rhs, weight, count=False)
        else:
            pinned = sum(f.pin_direction(y, x, w.d_raw, w.d_filt, values, rhs, weight) for f in pins)
            self.host_syncs += len(pins)
            if pinned == 0:
                return lin
        lin2 = self._pinned_linear_solve(values, rhs, d, opts)
        self.filter_direction(y, d)  # (contacts the pinned solve carries across their zones)
        gd, _ = self.direction_check(y, g, d)
        if not gd < 0.0:  # not a descent direction: the filtered one stays
            self._written(d)
            wp.copy(d, w.d_filt)
        if hasattr(lin, "iterations") and hasattr(lin2, "iterations"):
            lin.iterations += lin2.iterations
            lin.host_syncs = getattr(lin, "host_syncs", 0) + getattr(lin2, "host_syncs", 0)
            return lin
        return int(getattr(lin, "iterations", lin)) + int(getattr(lin2, "iterations", lin2))

    #: whether the linear solver iterates (the simulator sets it from its solver's ``iterative``)
    iterative_solve = staticmethod(lambda: True)

    def _pinned_linear_solve(self, values, rhs, d, opts):
        """d ~ (A + S)^-1 b' (the pinned system, ``values`` and ``rhs`` as ``pin_direction`` left
        them), warm-started from d (the filtered direction; ``PIN_WARM_START``): the correction c of
        (A + S) c = r0 = b' - (A + S) d is solved to ``cg_tol`` |b'| / |r0| of its own right-hand
        side (at most 0.5), so that d + c has the residual a solve from zero to ``cg_tol`` would
        leave, and added to d. One matrix-vector product and one read-back (the two norms) more."""
        if not PIN_WARM_START or not self.iterative_solve():  # (a factorisation gains nothing)
            return self.linear_solve(values, rhs, d, opts)
        w, dev, n = self.work, self.ops.device, self.n
        if getattr(w, "pin_r", None) is None or w.pin_r.shape[0] != n:
            w.pin_r, w.pin_c = self.ops.new_vector(), self.ops.new_vector()
            w.pin_norms = wp.zeros(2, dtype=wp.float64, device=dev)
        pt, r, c, acc = self.system.pattern, w.pin_r, w.pin_c, w.pin_norms
        launch(LK.bsr_masked_mv_kernel, n, [pt.offsets, pt.columns, values, self.mask, d, r, 0], dev)
        launch(LK.lincomb_kernel, n, [self.ops.scalar(1.0), rhs, self.ops.scalar(-1.0), r, r], dev)
        acc.zero_()
        for slot, v in enumerate((rhs, r)):  # (fixed-order sums: the same bits for any thread count)
            launch(LK.dot_slot_kernel, n, [v, v, _F64_ONE, acc, slot], dev)
        bb, rr = (float(v) for v in self._read(acc))
        if not rr > 0.0:  # d solves the pinned system already (or nothing to solve)
            from warpfem.solvers.linear.base import LinearSolveResult

            return LinearSolveResult(0, 0.0, True)
        tol = min(0.5, float(opts.cg_tol) * float(np.sqrt(bb / rr)))
        c.zero_()
        lin = self.linear_solve(values, r, c, replace(opts, cg_tol=tol))
        launch(LK.add_scaled_kernel, n, [c, self.ops.scalar(1.0), d], dev)
        return lin

    def unfiltered_direction(self):
        """The last Newton direction before :meth:`filter_direction` changed it (None when it was
        not filtered, or when the filter's cut count, read with the step bound in the pinned solve's
        gate, says it cut nothing: the Newton loop's fallback to it and the step test then need no
        read-back of it)."""
        return self.work.d_raw if getattr(self, "_raw_kept", False) else None

    def _filtering_forms(self):
        """The forms that filter Newton directions now (``filter_direction``; ``filters_direction()``
        False, e.g. contact without friction: it would leave them as they are)."""
        return [f for f in self.forms if hasattr(f, "filter_direction")
                and getattr(f, "filters_direction", lambda: True)()]

    def filter_direction(self, y, d):
        """Let the forms that filter the Newton direction (``filter_direction(y, x, d)``: lagged
        friction's stick/slip-aware step, :mod:`warpfem.contact.friction`) change d in place."""
        filters = self._filtering_forms()
        if not filters:
            return
        self._written(d)
        x = self._x_of(y)
        for f in filters:
            f.filter_direction(y, x, d)

    def fallback_direction(self, g, d):
        """d = -B^-1 g, B the (masked) block diagonal of the last Newton system: a descent direction
        whatever linear solver produced the rejected one."""
        self._bound = None
        self._written(d)
        pt, w, dev = self.system.pattern, self.work, self.ops.device
        if w.inv_diag is None or w.inv_diag.shape[0] != self.n:
            w.inv_diag = wp.zeros(self.n, dtype=self.ops.mat, device=dev)
        launch(LK.block_jacobi_setup_kernel, self.n, [pt.offsets, pt.columns, self.system.hessian_values, self.mask,
                                                      w.inv_diag], dev)
        launch(LK.scale_copy_kernel, self.n, [g, self.ops.scalar(-1.0), w.rhs], dev)
        launch(LK.block_apply_kernel, self.n, [w.inv_diag, w.rhs, d], dev)

    def extrapolate(self, y, d, gd0, gd1, E1, y_try, g_try):
        """A longer step along d after an accepted full Newton step y_try = y + d (energy E1,
        gradient g_try there): when the energy still falls steeply along d there (g_try . d =
        ``gd1`` < ``EXTRAPOLATE_BELOW`` x g(y) . d = ``gd0``), the minimum of the secant model of
        the slope along d, alpha = gd0 / (gd0 - gd1) (at most ``EXTRAPOLATE_MAX``, within the
        forms' step bound), is tried; kept when its energy is below E1 (then y_try and g_try are
        replaced). Returns (E, |E|, gradient magnitude, ||P g||, alpha) of the kept point, or None.

        Why: SPD projection of a Hessian (per contact pair, per element) adds curvature the energy
        does not have, so projected Newton's full steps fall short along the directions where the
        projection added it and the iteration converges linearly (measured on self contact:
        docs/contact.md, "Longer steps where the projection makes them short")."""
        if not (gd0 < 0.0 and gd1 < EXTRAPOLATE_BELOW * gd0):
            return None
        a = min(gd0 / (gd0 - gd1), EXTRAPOLATE_MAX)
        w = self.work
        if self.bounds_step():
            if getattr(w, "d_long", None) is None or w.d_long.shape[0] != self.n:
                w.d_long = self.ops.new_vector()
            launch(LK.scale_copy_kernel, self.n, [d, self.ops.scalar(a), w.d_long], self.ops.device)
            a *= min(1.0, self.max_step(y, w.d_long))
        if not a > 1.0 + 1e-3:
            return None
        if getattr(w, "y_long", None) is None or w.y_long.shape[0] != self.n:
            w.y_long, w.g_long = self.ops.new_vector(), self.ops.new_vector()
        self.trial(y, a, d, w.y_long)
        E2, mag2, gmag2, gnorm2 = self.evaluate(w.y_long, w.g_long)
        if not (np.isfinite(E2) and E2 < E1 and np.isfinite(gnorm2)):
            return None
        self._written(y_try)
        self._written(g_try)
        wp.copy(y_try, w.y_long)
        wp.copy(g_try, w.g_long)
        return E2, mag2, gmag2, gnorm2, a

    def direction_check(self, y, g, d):
        """(g . d, whether the step d is below the resolution of y and of x = x_b + s y): one read-back."""
        self._launch_direction(y, g, d, self._acc_d)
        return self._direction_of(self._read(self._acc_d), d)

    def _written(self, v=None):
        """Forget the kept max |d| of the last direction check (:meth:`direction_max`) when ``v``
        is the vector it was read from (any vector when None): v is being written."""
        kept = getattr(self, "_checked", None)
        if kept is not None and (v is None or kept[0] is v):
            self._checked = None


FullSpacePotential = IncrementalPotential  # the older name
