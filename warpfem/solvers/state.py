"""State, control and the simulator base shared by the three simulators (``Simulator``,
``StiffnessWarpingSimulator``, ``ReducedSimulator``).

As in NVIDIA's ``newton``, what a step reads and writes is kept apart from the model:

* the :class:`~warpfem.model.Model` (mesh, material, mass, fixed set, loads) does not change
  during a step;
* a :class:`State` is what a step advances: positions, velocities (device arrays; the reduced
  simulator's coordinate arrays), the integrator's history (``history``: x_{n-1}, v_{n-1} or a_n and the step size they belong to)
  and the time;
* a :class:`Control` is what drives one step from outside: kinematic targets of fixed vertices and
  the load scale.

``sim.step(state_in, state_out, control, dt)`` reads ``state_in`` only and writes ``state_out``, so
a failed step leaves every state as it was; ``sim.step()`` is the convenience that steps the
simulator's own state (two states used in turn: no allocation per step).
:class:`DeviceVectors` is the vector algebra of the device vec3 arrays (the
:class:`warpfem.integrators.VectorOps` the integrators use).

:class:`StepperBase` is what the three simulators share (state and control, both forms of
``step``, ``new_state``, ``predict``, the failure handling ``_finish`` / :func:`check_solve`, the
total energy); :class:`SimulatorBase` adds what the two full-space ones share (device vectors,
the Hessian system and linear solver, ``sync_model``, the forms' weights, prescribed velocities,
Newmark's a_0). :class:`SimulatorState` is a mixin of the latter: positions and velocities as device arrays of vec3, Dirichlet
components (``fix``/``release``, kept on the model) and kinematic targets for the next step.
A class using it provides:

* ``self.model`` (a :class:`~warpfem.model.Model`: ``fix``, ``release``, ``_indices``),
* ``self.num_vertices``, ``self.state`` (a :class:`State`), ``self.control`` (a :class:`Control`),
* ``self._vec_array(a=None)`` -> a device vec3 array of n entries (zeros, or from a float64 (n, 3)),
* ``self.sync_model()`` (uploads the fixed mask / external forces after a model change).
"""

from __future__ import annotations

import time
import warnings

import numpy as np
import warp as wp

from warpfem.kernels import linalg as LK
from warpfem.kernels.generic import launch
from warpfem.solvers.adjoint import active_tape, recorded_step
from warpfem.transfer import read, to_device, upload

__all__ = ["newton_options_from", "SimulatorBase", "SimulatorState", "StepperBase", "ControlledSimulator", "check_solve", "State", "Control", "DeviceVectors", "PRECISIONS", "check_simulator_options"]

#: precision name -> (scalar, vec3, mat33 Warp types, numpy dtype)
PRECISIONS = {
    "float32": (wp.float32, wp.vec3, wp.mat33, np.float32),
    "float64": (wp.float64, wp.vec3d, wp.mat33d, np.float64),
}


def check_simulator_options(precision, dt, damping_mass, damping_stiffness):
    """Validate the options every time stepper takes; returns ``PRECISIONS[precision]``.

    Raises ValueError naming the option: precision not "float32"/"float64", dt not a positive
    finite number of seconds, a negative (or NaN) Rayleigh coefficient."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be 'float32' or 'float64', got {precision!r}")
    if not (isinstance(dt, (int, float, np.integer, np.floating)) and not isinstance(dt, bool)
            and np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive number of seconds, got {dt!r}")
    if not (damping_mass >= 0 and damping_stiffness >= 0):
        raise ValueError(f"Rayleigh damping coefficients must be >= 0, got damping_mass={damping_mass!r}, "
                         f"damping_stiffness={damping_stiffness!r}")
    return PRECISIONS[precision]


def newton_options_from(options: dict):
    """The :class:`~warpfem.solvers.nonlinear.NewtonOptions` of a simulator's keyword options,
    validated; raises TypeError naming unknown keys, ValueError naming a bad value."""
    from warpfem.solvers.nonlinear import NewtonOptions

    known = NewtonOptions.__dataclass_fields__
    unknown = set(options) - set(known)
    if unknown:
        raise TypeError(f"unknown solver option(s) {sorted(unknown)}; known: {sorted(known)}")
    opts = NewtonOptions(**options)
    opts.validate()
    return opts


class State:
    """What a time step advances: positions ``x`` and velocities ``v`` (vectors of the simulator:
    device vec3 arrays, or numpy coordinates for the reduced simulator), the integrator's
    ``history`` (dict; see :mod:`warpfem.integrators`) and the ``time`` (s)."""

    def __init__(self, x, v, history=None, time=0.0):
        self.x, self.v = x, v
        self.history = {} if history is None else history
        self.time = float(time)

    def __repr__(self):
        return f"State(t={self.time:g}, history={sorted(self.history)})"


class Control:
    """What drives a step from outside: ``targets`` (vertex -> (3,) end-of-step position of a fixed
    vertex: kinematic handles) and ``load_scale`` (the external forces, gravity included, act
    scaled by it; the model itself is never rescaled)."""

    def __init__(self, targets=None, load_scale=1.0):
        self.targets = {} if targets is None else dict(targets)
        self.load_scale = float(load_scale)

    def __repr__(self):
        return f"Control(targets={len(self.targets)}, load_scale={self.load_scale:g})"


class DeviceVectors:
    """Vector algebra of n device vec3 arrays in one precision (the integrators' ``VectorOps``).

    ``acceleration`` (Newmark's a_0) is the simulator's, given at construction."""

    def __init__(self, n, device, types, acceleration=None):
        self.n, self.device = int(n), device
        self.scalar, self.vec, self.mat, self.np_dtype = types
        self._acceleration = acceleration
        self.zero = self.new_vector()  # read-only zeros

    def new_vector(self, a=None):
        if a is None:
            return wp.zeros(self.n, dtype=self.vec, device=self.device)
        return to_device(np.asarray(a, dtype=self.np_dtype), self.vec, self.device)

    def lincomb(self, a, x, b, y, out):
        launch(LK.lincomb_kernel, self.n, [self.scalar(a), x, self.scalar(b), y, out], self.device)

    def copy(self, dst, src):
        if dst is not src:
            wp.copy(dst, src)

    @staticmethod
    def clone(a):
        """A copy of a vector of this algebra (its own buffer); anything else (a step size) as it is."""
        return wp.clone(a) if isinstance(a, wp.array) else a

    def acceleration(self, state, out):
        self._acceleration(state, out)


class ControlledSimulator:
    """``load_scale``: a view of ``self.control`` (a :class:`Control`), shared by every simulator
    (the full-space ones through :class:`SimulatorState`, and the reduced one)."""

    @property
    def load_scale(self) -> float:
        """The control's load scale (external forces act scaled by it; load ramps)."""
        return self.control.load_scale

    @load_scale.setter
    def load_scale(self, value):
        self.control.load_scale = float(value)


class SimulatorState(ControlledSimulator):
    """positions / velocities / set_positions / set_velocities / fix / release / set_targets, on
    ``self.state`` (a :class:`State`) and ``self.control`` (a :class:`Control`)."""

    # -- the current state and control ------------------------------------------------------------
    @property
    def x(self):
        """Current positions (device vec3 array; the state's own buffer, rewritten by later steps)."""
        return self.state.x

    @x.setter
    def x(self, value):
        self.state.x = value

    @property
    def v(self):
        """Current velocities (device vec3 array; the state's own buffer)."""
        return self.state.v

    @v.setter
    def v(self, value):
        self.state.v = value

    @property
    def _targets(self):
        return self.control.targets

    @_targets.setter
    def _targets(self, value):
        self.control.targets = value

    def _new_state(self):
        """A state with zeroed buffers of this simulator's size (for ``step(state_in, state_out, ...)``)."""
        return State(self._vec_array(), self._vec_array())

    # -- boundary conditions (no re-assembly, no pattern rebuild) --------------------------------------
    def fix(self, indices, components="xyz"):
        """Fix vertex components (a subset of "xyz") at their current positions from the next step on."""
        self.model.fix(indices, components)
        self.sync_model()

    def release(self, indices, components="xyz"):
        """Release fixed components (no re-assembly)."""
        self.model.release(indices, components)
        self.sync_model()

    def set_targets(self, indices, positions):
        """Prescribe end-of-step positions (m) of fixed vertices for the next step or static solve
        (kinematic handles); ``positions`` has one row of 3 per index."""
        idx = self.model.indices(indices)
        pos = np.asarray(positions, dtype=np.float64).reshape(len(idx), 3)
        if not np.all(np.isfinite(pos)):
            raise ValueError("target positions must be finite")
        for i, p in zip(idx.tolist(), pos):
            self._targets[i] = p

    # -- state access ------------------------------------------------------------------------------
    def positions(self) -> np.ndarray:
        """Current positions (n, 3), m, float64 copy."""
        return read(self.x).astype(np.float64)

    def velocities(self) -> np.ndarray:
        """Current velocities (n, 3), m/s, float64 copy."""
        return read(self.v).astype(np.float64)

    def _checked_state(self, a, what: str) -> np.ndarray:
        a = np.asarray(a, dtype=np.float64)
        if a.shape != (self.num_vertices, 3) or not np.all(np.isfinite(a)):
            raise ValueError(f"{what} must be finite with shape ({self.num_vertices}, 3), got {a.shape}")
        return a

    def set_positions(self, x):
        """Replace the positions (m), (n, 3); raises ValueError (state untouched) for a wrong shape or NaN/inf."""
        upload(self.state.x, self._checked_state(x, "positions").astype(self._np))
        self._state_changed()

    def set_velocities(self, v):
        """Replace the velocities (m/s), (n, 3); raises ValueError (state untouched) for a wrong shape or NaN/inf."""
        upload(self.state.v, self._checked_state(v, "velocities").astype(self._np))
        self._state_changed()


def check_solve(stats, what: str, *, require_convergence: bool, finite: bool = True, stacklevel: int = 3) -> bool:
    """The failure handling of every simulator's step: raise :class:`SolveFailed` (the caller has
    not written its state) on NaN/inf (``finite`` False, a non-finite energy or a "non-finite"
    reason) or, with ``require_convergence``, on non-convergence; otherwise, when not converged,
    warn (:class:`~warpfem.solvers.nonlinear.NotConvergedWarning`, a RuntimeWarning: the reason,
    the relative gradient and the tolerance) and return False. Returns True for a converged solve."""
    from warpfem.solvers.nonlinear import NotConvergedWarning, SolveFailed, not_converged_message

    if stats.converged:
        return True
    if not finite or "non-finite" in stats.reason or not np.isfinite(stats.energy):
        raise SolveFailed(f"{what} diverged ({stats.reason}); state left unchanged", stats)
    message = not_converged_message(stats, what)
    if require_convergence:
        raise SolveFailed(f"{message}; state left unchanged", stats)
    warnings.warn(message, NotConvergedWarning, stacklevel=stacklevel)
    return False


class StepperBase(ControlledSimulator):
    """What every simulator (full space, stiffness warping, reduced) shares: the current
    :class:`State` and :class:`Control` (``state``, ``control``, ``time``, ``load_scale``), the two
    forms of ``step`` (two states used in turn: no allocation per step), ``new_state``,
    ``predict``, the failure handling of a step (:meth:`_finish`, :func:`check_solve`) and the
    total energy (with the load scale).

    ``unconverged_steps`` counts the steps (and static solves) accepted without converging (each
    one also warned with a :class:`~warpfem.solvers.nonlinear.NotConvergedWarning`); with
    ``require_convergence`` such a step raises instead and is not counted.

    A subclass calls :meth:`_setup_states` and provides ``_step(state_in, state_out, control, dt)
    -> SolveStats`` (reads ``state_in`` only, raises before writing ``state_out``), ``dt``,
    ``integrator``, ``ops`` (its vector algebra, with ``clone``), ``_prediction_work`` (dict),
    ``require_convergence``, ``kinetic_energy()``, ``elastic_energy()`` and
    ``_external_work(state)`` (x^T f_ext of the unscaled external forces)."""

    def _setup_options(self, model, device, precision, types, dt, damping_mass, damping_stiffness, require_convergence):
        """The options every simulator takes (validated by :func:`check_simulator_options`, which
        returned ``types``): model, device, precision and its types, dt, Rayleigh damping."""
        from warpfem.device import get_device

        self.model = model
        self.device = get_device(device)
        self.precision = precision
        self._s, self._vec, self._mat, self._np = types
        self.dt = float(dt)
        self.damping_mass = float(damping_mass)
        self.damping_stiffness = float(damping_stiffness)
        self.require_convergence = bool(require_convergence)
        self.unconverged_steps = 0  # steps (and static solves) accepted without converging
        self.num_vertices = model.num_vertices

    def _setup_states(self, state, spare):
        """The simulator's state, the spare state ``step()`` writes, a fresh :class:`Control`."""
        self.state, self._spare = state, spare
        self.control = Control()
        self._step_control = self.control  # the control of the step being taken (Newmark's a_0 reads it)
        self.step_count = 0

    # -- the current state --------------------------------------------------------------------------
    @property
    def time(self) -> float:
        """Simulated time (s) of the current state."""
        return self.state.time

    @time.setter
    def time(self, value):
        self.state.time = float(value)

    def new_state(self, requires_grad=False) -> State:
        """A copy of the current state (its own buffers and history): an input or output of
        ``step(state_in, state_out, control, dt)``. ``requires_grad``: positions and velocities
        with gradient arrays, for steps recorded on a ``wp.Tape`` (docs/gradients.md)."""
        c = self.ops.clone
        st = self.state
        if requires_grad:
            x, v = wp.clone(st.x, requires_grad=True), wp.clone(st.v, requires_grad=True)
        else:
            x, v = c(st.x), c(st.v)
        return State(x, v, {k: c(h) for k, h in st.history.items()}, st.time)

    def _state_changed(self):
        """The state was set from outside: time integrators restart their history (BDF2 takes a
        backward Euler step, Newmark recomputes the acceleration)."""
        self.state.history.clear()

    def predict(self, state=None, dt=None):
        """The integrator's prediction (x_b, v_hat, s) for a step of ``dt`` from ``state``
        (defaults: the simulator's); the vectors are work buffers, valid until the next step."""
        return self.integrator.predict(self.state if state is None else state, self.dt if dt is None else float(dt),
                                       self.ops, self._prediction_work)

    # -- the full step state (warpfem.io.checkpoint) ----------------------------------------------------
    def state_dict(self) -> dict:
        """Everything that influences later steps, as a flat dict of numpy arrays and Python scalars
        under namespaced keys: "x", "v" (the state's vectors in the simulator's precision; the
        reduced simulator's coordinates), "time", "step_count", "integrator/..." (the integrator's
        history: x_{n-1}, v_{n-1}, Newmark's a_n, the step size, the extrapolated guess's v_{n-1}),
        "control/..." (load scale, pending targets), and what the simulator adds (forms, pattern,
        linear solver: :meth:`_state_parts`). ``load_state_dict`` into a fresh simulator of the same
        scene continues bit for bit; ``warpfem.save_state`` writes it to a file."""
        st = self.state
        d = {"meta/simulator": type(self).__name__, "meta/precision": self.precision,
             "meta/integrator": self.integrator.name, "time": float(st.time), "step_count": int(self.step_count),
             "unconverged_steps": int(getattr(self, "unconverged_steps", 0)),
             "x": self._vector_of(st.x), "v": self._vector_of(st.v),
             "control/load_scale": float(self.control.load_scale)}
        for k, h in st.history.items():
            d[f"integrator/{k}"] = float(h) if isinstance(h, (int, float, np.integer, np.floating)) else self._vector_of(h)
        keys = sorted(self.control.targets)
        vals = [np.asarray(self.control.targets[k], dtype=np.float64).reshape(-1) for k in keys]
        d["control/target_keys"] = np.asarray(keys, dtype=np.int64)
        d["control/target_sizes"] = np.asarray([len(v) for v in vals], dtype=np.int64)
        d["control/target_values"] = np.concatenate(vals) if vals else np.zeros(0)
        for prefix, part in self._state_parts():
            for k, v in part.state_dict().items():
                d[f"{prefix}/{k}"] = v
        return d

    def load_state_dict(self, d):
        """Set the full step state from ``d`` (a :meth:`state_dict` of a simulator of the same
        scene, or what ``warpfem.io.checkpoint.read_state`` read). Every key is checked (precision,
        shape, dtype; keys this simulator does not have are refused): a mismatch raises
        :class:`warpfem.io.checkpoint.CheckpointError` naming the key, and the simulator is left as
        it was."""
        from warpfem.io.checkpoint import CheckpointError, StateView

        view = d if isinstance(d, StateView) else StateView(dict(d))
        view.expect_text("meta/simulator", type(self).__name__, "a")
        view.expect_text("meta/precision", self.precision, "a simulator of precision")
        view.expect_text("meta/integrator", self.integrator.name, "a simulator with the integrator")
        before = self.state_dict()
        try:
            self._load_state(view)
            extra = view.unused()
            if extra:
                raise CheckpointError(f"state key(s) {extra[:6]}{' ...' if len(extra) > 6 else ''} are not part of this "
                                      "simulator (saved from another scene?)")
        except BaseException:
            self._load_state(StateView(before, restoring=True))
            raise

    def _load_state(self, view):
        x = self._vector_of(self.state.x)
        shape, dtype = x.shape, x.dtype
        xs = view.array("x", shape, dtype, finite=True)
        vs = view.array("v", shape, dtype, finite=True)
        hv = view.view("integrator")
        hist = {}
        for k in list(hv):
            val = hv[k]
            hist[k] = hv.array(k, shape, dtype, finite=True) if isinstance(val, np.ndarray) else hv.number(k)
        tk = view.array("control/target_keys", (None,), np.int64)
        sizes = view.array("control/target_sizes", (len(tk),), np.int64)
        tv = view.array("control/target_values", (int(sizes.sum()),), np.float64, finite=True)
        targets = {}
        for k, a, b in zip(tk.tolist(), np.cumsum(sizes) - sizes, np.cumsum(sizes)):
            targets[int(k)] = self._checked_target(view, int(k), tv[a:b].copy())
        time_, steps = view.number("time"), view.integer("step_count")
        unconverged, load_scale = view.integer("unconverged_steps"), view.number("control/load_scale")
        parts = [(prefix, part, view.view(prefix)) for prefix, part in self._state_parts(view)]
        # everything checked that can be without writing: write
        self._assign_vector(self.state.x, xs)
        self._assign_vector(self.state.v, vs)
        st = self.state
        st.history = {k: (v if isinstance(v, float) else self._assign_vector(self.ops.new_vector(), v))
                      for k, v in hist.items()}
        st.time, self.step_count, self.unconverged_steps = time_, steps, unconverged
        self.control.targets = targets
        self.control.load_scale = load_scale
        for _, part, sub in parts:
            part.load_state_dict(sub)
            sub.use_all()

    def _checked_target(self, view, key, value):
        """A pending target of the control as saved (the full-space simulators: a vertex and its
        end-of-step position; the reduced one: a handle group and its coordinates)."""
        return value

    def _state_parts(self, view=None):
        """(key prefix, object with ``state_dict()`` / ``load_state_dict(view)``) of the parts of the
        simulator that carry step-to-step state beyond the :class:`State` (none here). With
        ``view`` (a load): the parts the saved state has, made ready to be loaded into."""
        return []

    def _vector_of(self, a) -> np.ndarray:
        """A state vector (device vec3 array or numpy coordinates) as a numpy copy in its own dtype."""
        return a.numpy().copy() if isinstance(a, wp.array) else np.array(a, copy=True)

    @staticmethod
    def _assign_vector(buf, a):
        if isinstance(buf, wp.array):
            buf.assign(a)
        else:
            buf[...] = a
        return buf

    # -- energies -------------------------------------------------------------------------------------
    def total_energy(self) -> float:
        """Kinetic + elastic - x^T f_ext (J, f_ext times ``load_scale``): conserved by the exact
        dynamics without damping."""
        return self.kinetic_energy() + self.elastic_energy() - self.load_scale * self._external_work(self.state)

    # -- the step ---------------------------------------------------------------------------------------
    def step(self, state_in=None, state_out=None, control=None, dt=None):
        """Advance one step; returns its :class:`~warpfem.SolveStats`.

        ``step()``: the simulator's own state by ``dt`` (the simulator's, or the argument) with its control (targets set by
        :meth:`set_targets`, cleared after the step, and ``load_scale``). ``step(state_in,
        state_out, control=None, dt=None)``: a step from ``state_in`` written into ``state_out``
        (two distinct :class:`State`s, e.g. from ``new_state()``); ``state_in`` is never written.

        On NaN/inf (or non-convergence with ``require_convergence``) raises :class:`SolveFailed`;
        the input state (and with ``step()`` the simulator's state, time and the integrator's
        history) is as it was.
        """
        if state_in is None:
            if state_out is not None:
                raise TypeError("step(): give both state_in and state_out, or neither")
            own_in, own_out = self._own_states()
            stats = self._run_step(own_in, own_out, self.control, self.dt if dt is None else float(dt), own=True)
            self._commit(own_out)
            self.control.targets.clear()
            self.step_count += 1
            return stats
        if state_out is None or state_out is state_in:
            raise ValueError("step(state_in, state_out, ...) needs a distinct output state (see new_state())")
        return self._run_step(state_in, state_out, Control() if control is None else control,
                              self.dt if dt is None else float(dt))

    def _run_step(self, state_in, state_out, control, dt, own=False):
        """``_step``, or, while a gradient recording (``step_recorder``) or a ``wp.Tape`` is
        active, the recorded step of :func:`warpfem.solvers.adjoint.recorded_step`."""
        if getattr(self, "step_recorder", None) is None and active_tape() is None:
            return self._step(state_in, state_out, control, dt)

        def run():
            return self._step(state_in, state_out, control, dt)

        return recorded_step(self, run, state_in, state_out, control, dt, own=own)

    def _finish(self, stats, t0, what, *, finite=True, stacklevel=5):
        """The end of every simulator's solve: its time, then :func:`check_solve` (raises before the
        caller writes any state; ``finite`` False: the solution has NaN/inf)."""
        stats.seconds = time.perf_counter() - t0
        if not check_solve(stats, what, require_convergence=self.require_convergence, finite=finite,
                           stacklevel=stacklevel):
            self.unconverged_steps = getattr(self, "unconverged_steps", 0) + 1

    def _own_states(self):
        return self.state, self._spare

    def _commit(self, state_out):
        self.state, self._spare = state_out, self.state


class SimulatorBase(SimulatorState, StepperBase):
    """What the full-space simulators (``Simulator``, ``StiffnessWarpingSimulator``) share beyond
    :class:`StepperBase`: set-up of the model, device, precision and step options, the device
    vector algebra, the block-sparse :class:`~warpfem.solvers.sparse.HessianSystem` (``system``:
    pattern, "mass" values, the linear solver), the model's mask and external forces
    (``sync_model``), masked products and linear solves, the kinetic energy, the forms' weights
    (``_weights``), the prescribed velocities of fixed vertices and the equation-of-motion
    acceleration (Newmark's a_0). A subclass provides ``_step``, ``elastic_energy``, ``options``
    (:class:`~warpfem.solvers.nonlinear.NewtonOptions`), ``_work`` (a
    :class:`~warpfem.solvers.forms.Workspace`) and ``_elastic_force_for_acceleration(x, out) ->
    the stiffness values at x for stiffness damping (or None)`` (out := the elastic force at x)."""

    def _setup_base(self, model, device, precision, types, dt, damping_mass, damping_stiffness, require_convergence):
        self._setup_options(model, device, precision, types, dt, damping_mass, damping_stiffness, require_convergence)
        n = self.num_vertices
        self.ops = DeviceVectors(n, self.device, types, acceleration=self._equation_of_motion_acceleration)
        self._vec_array = self.ops.new_vector
        self._zero = self.ops.zero
        self._setup_states(State(self._vec_array(model.rest_positions), self._vec_array()), None)
        self._spare = self._new_state()  # the other state of step(): the two are used in turn
        self._mask = None
        self.sync_model()

    def _setup_system(self, elements, nodes_per_element, linear_solver, linear_solver_options):
        """The Hessian's pattern of the mesh, the mass matrix in it and the linear solver bound to it."""
        from warpfem.solvers.linear import make_linear_solver
        from warpfem.solvers.linear.auto import simulator_options
        from warpfem.solvers.sparse import BlockPattern, HessianSystem

        self.system = HessianSystem(BlockPattern(elements, nodes_per_element, self.num_vertices, device=self.device,
                                                 block_type=self._mat))
        self.system.values["mass"] = self.system.pattern.values_from_scalar_matrix(self.model.mass)
        self.system.new_values("hessian")
        self._pcg = make_linear_solver(linear_solver, self.system.pattern, vec_type=self._vec, scalar=self._s,
                                       positions=self.model.rest_positions,
                                       **simulator_options(linear_solver, linear_solver_options))
        self.system.solver = self._pcg

    @property
    def _pattern(self):
        return self.system.pattern

    @property
    def _mass_values(self):
        return self.system.values["mass"]

    # -- model changes (no pattern rebuild) -----------------------------------------------------------
    def sync_model(self):
        """Upload the model's fixed mask and external forces (call after changing them; in place)."""
        mask = (~self.model.fixed).astype(self._np)
        fext = self.model.external_forces()
        if getattr(self, "_mask", None) is None:
            self._mask, self._fext = self._vec_array(mask), self._vec_array(fext)
        else:
            upload(self._mask, mask)
            upload(self._fext, fext.astype(self._np))
        self._fext_norm = float(np.linalg.norm(fext))
        if getattr(self, "_load", None) is not None:
            self._load.norm = self._fext_norm

    # -- the full step state (StepperBase.state_dict) ------------------------------------------------------
    def _state_parts(self, view=None):
        """The fixed components ("model/fixed"), the Hessian pattern's added blocks
        ("pattern/extra_pairs": contact pairs grow it, and the direct solvers' orderings follow
        it), the forms' own state ("form/NAME/...", :meth:`_form_parts`), and the linear solver's
        recorded decisions ("linear_solver/...")."""
        solver = self._pcg if hasattr(self._pcg, "state_dict") else _NoState()
        return [("model", _FixedState(self)), ("pattern", _PatternState(self.system))] + self._form_parts(view) + [
            ("linear_solver", solver)]

    def _form_parts(self, view=None):
        return []

    def _checked_target(self, view, key, value):
        if not (0 <= key < self.num_vertices) or value.shape != (3,):
            raise view.error("control/target_keys", f"a target of vertex {key} with {value.size} values does not fit "
                             f"{self.num_vertices} vertices")
        return value

    # -- products and solves ------------------------------------------------------------------------
    def _bsr_mv(self, values, x, alpha, y):
        """y += alpha A x, A the block matrix ``values`` in the current pattern."""
        pt = self._pattern
        launch(LK.bsr_mv_kernel, pt.num_rows, [pt.offsets, pt.columns, values, x, self._s(alpha), y], self.device)

    def _linear_solve(self, values, rhs, out, opts):
        """out ~ A^-1 rhs on the free components (A the masked block matrix ``values``, rhs masked):
        the Newton systems' linear solver; returns its result (``iterations``, ``converged``, ...)."""
        return self._pcg.solve(values, self._mask, rhs, out, tol=opts.cg_tol, maxiter=opts.max_cg_iters)

    # -- energies -----------------------------------------------------------------------------------
    def _dot(self, a, b) -> float:
        return self._pcg.dot(a, b)

    def kinetic_energy(self) -> float:
        """1/2 v^T M v (J)."""
        q = self._work_vector()
        q.zero_()
        self._bsr_mv(self._mass_values, self.v, 1.0, q)
        return 0.5 * self._dot(self.v, q)

    def _external_work(self, state) -> float:
        return self._dot(state.x, self._fext)

    def _work_vector(self):
        if getattr(self, "_energy_tmp", None) is None:
            self._energy_tmp = self._vec_array()
        return self._energy_tmp

    # -- the step ---------------------------------------------------------------------------------------
    def _weights(self, s, control):
        """The forms' weights for a step of scale s (the one place the integrator's s enters the
        weights; the chain factors of the forms of x are the potential's; forms not named keep
        their own weight)."""
        return {"inertia": 1.0, "damping": s, "elastic": 1.0, "load": s * control.load_scale}

    def _prescribed_velocity(self, state, xb, s, control, out):
        """``out`` := the end-of-step velocity that puts fixed components at their target (or keeps
        them where they are), (p - x_b) / s; only its fixed components are used."""
        if not control.targets:
            if xb is state.x:
                out.zero_()
            else:  # (x - x_b) first, then the scale: exact zero where x_b = x
                self.ops.lincomb(1.0, state.x, -1.0, xb, out)
                self.ops.lincomb(1.0 / s, out, 0.0, out, out)
            return out
        p = read(state.x).astype(np.float64)
        for i, t in control.targets.items():
            p[i] = t
        upload(out, (p - read(xb).astype(np.float64)) / s)
        return out

    def _equation_of_motion_acceleration(self, state, out):
        """out = a with M a = f(x) + f_ext - C v on the free components (0 on fixed ones), f the
        elastic force and C = alpha M + beta K the Rayleigh damping at ``state`` (Newmark's a_0)."""
        from warpfem.solvers.nonlinear import SolveFailed, SolveStats

        n = self.num_vertices
        rhs = self._work.tmp  # (forms.Workspace)
        K = self._elastic_force_for_acceleration(state.x, rhs)  # rhs = f(x); K(x) when damping needs it
        launch(LK.axpy_kernel, n, [self._s(self._step_control.load_scale), self._fext, rhs], self.device)
        if self.damping_mass != 0.0:
            self._bsr_mv(self._mass_values, state.v, -self.damping_mass, rhs)
        if self.damping_stiffness != 0.0:
            self._bsr_mv(K, state.v, -self.damping_stiffness, rhs)
        launch(LK.mask_kernel, n, [self._mask, rhs], self.device)
        res = self._pcg.solve(self._mass_values, self._mask, rhs, out, tol=1e-12, maxiter=max(self.options.max_cg_iters, 100))
        if not np.isfinite(res.residual):
            raise SolveFailed("the initial acceleration M a = f + f_ext - C v is not finite; state left unchanged",
                              SolveStats(reason="non-finite initial acceleration"))


class _NoState:
    """A part without step-to-step state."""

    def state_dict(self):
        return {}

    def load_state_dict(self, view):
        pass


class _FixedState:
    """The model's fixed components (``fix`` / ``release`` change them during a run)."""

    def __init__(self, sim):
        self.sim = sim

    def state_dict(self):
        return {"fixed": np.array(self.sim.model.fixed, dtype=bool)}

    def load_state_dict(self, view):
        a = view.array("fixed", (self.sim.num_vertices, 3), bool)
        if not np.array_equal(a, self.sim.model.fixed):
            self.sim.model.fixed[...] = a
            self.sim.sync_model()


class _PatternState:
    """The blocks added to the Hessian's pattern (contact pairs): the same pattern after a load."""

    def __init__(self, system):
        self.system = system

    def state_dict(self):
        return {"extra_pairs": np.array(self.system.pattern.extra_pairs, dtype=np.int64)}

    def load_state_dict(self, view):
        pairs = view.array("extra_pairs", (None, 2), np.int64)
        n = self.system.pattern.num_rows
        if pairs.size and (pairs.min() < 0 or pairs.max() >= n):
            raise view.error("extra_pairs", f"vertex indices outside [0, {n})")
        have = self.system.pattern.extra_pairs
        if len(have) and not view.restoring:
            keys = np.sort(pairs[:, 0] * n + pairs[:, 1])
            mine = have[:, 0] * n + have[:, 1]
            pos = np.minimum(np.searchsorted(keys, mine), max(len(keys) - 1, 0))
            if not len(keys) or np.any(keys[pos] != mine):
                raise view.error("extra_pairs", "this simulator's pattern has blocks the saved one lacks "
                                 "(saved from another scene, or this one has stepped already)")
        self.system.ensure_blocks(pairs)
