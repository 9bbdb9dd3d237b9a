"""Gradients of simulations for Python users who do not write Warp code (docs/gradients.md).

:func:`loss_and_gradients` runs a scene (a TOML file or a loaded :class:`~warpfem.scenes.Scene`)
or a built :class:`~warpfem.Simulator` forward for as many frames as the observation has, takes
the loss

    L = sum over frames f and vertices i of |x_f[i] - observed_f[i]|^2   (m^2)

and returns it with its gradients by parameter name as numpy (:class:`DiffResult`), from the adjoint
of every implicit step (:mod:`warpfem.solvers.adjoint`: one linear solve per step with the step's
exact Hessian, not a replay of the Newton iterations).

Frames follow the ``[output] states`` npz of ``warpfem run``: frame 0 is the state before the first
step, frame k the state after k frames (a scene frame is ``[integrator] substeps`` steps; a
simulator's ``steps_per_frame``).

Gradients (keys of :attr:`DiffResult.gradients`): ``youngs_modulus``, ``poisson_ratio``,
``density`` (scalars), ``element_stiffness_scale`` (m,), ``forces`` (n, 3: the model's constant
applied forces), ``gravity`` (3,), ``initial_positions`` / ``initial_velocities`` (n, 3),
``targets`` ({step: {vertex: (3,)}}: the kinematic handles' targets of each step),
``collider_translations`` / ``collider_rotations`` ({step: {collider: (3,)}}: the poses of planes,
spheres, boxes and meshes), ``collider_friction`` ({collider: mu}), ``contact_friction`` (mu of
surface contact). A scene's run also gives each collider friction as ``friction:<collider name>``.

A scene's gradient run sets (:func:`scene_parameters_of`) ``youngs_modulus``, ``poisson_ratio``,
``density`` (``[material]``), ``contact_friction`` (``[contact] friction``: surface contact
between bodies, self contact) and ``friction:<name>`` (that ``[[collider]]``'s ``friction``; the
name as the scene gives it, default ``<type><position>``: ``plane1``). A friction of 0 is run as
:data:`FRICTION_FLOOR` (at mu = 0 the simulator drops friction, and with it the gradient in mu).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np

__all__ = ["loss_and_gradients", "SceneProblem", "DiffResult", "positions_loss", "SCENE_PARAMETERS", "scene_with_parameters",
           "DiffInputError", "check_observation", "MATERIAL_PARAMETERS", "CONTACT_FRICTION", "FRICTION_PREFIX",
           "FRICTION_FLOOR", "scene_parameters_of", "scene_parameter_values", "check_parameter_names"]

#: the tightest Newton tolerance a float32 gradient run asks for (below it float32 round-off stalls Newton)
FLOAT32_NEWTON_TOL = 1e-5

#: the ``[material]`` parameters of a (one-body) scene's gradient run
MATERIAL_PARAMETERS = ("youngs_modulus", "poisson_ratio", "density")
#: ``[contact] friction``: mu of surface contact (between bodies, self contact)
CONTACT_FRICTION = "contact_friction"
#: ``friction:<collider name>``: the ``friction`` of that ``[[collider]]``
FRICTION_PREFIX = "friction:"
#: the parameters a scene's gradient run can set (and ``warpfem fit`` identify); the names a given
#: scene takes: :func:`scene_parameters_of`
SCENE_PARAMETERS = MATERIAL_PARAMETERS + (CONTACT_FRICTION, FRICTION_PREFIX + "<collider>")
#: a friction parameter of 0 runs as this mu: the simulator lags friction only where mu > 0 (and the
#: adjoint differentiates it only there), so mu = 0 would give no gradient in mu; the loss differs
#: from mu = 0's by FRICTION_FLOOR x its slope
FRICTION_FLOOR = 1e-9


class DiffInputError(ValueError):
    """Bad input of a gradient run (observation shapes, frames, vertices, parameter names)."""


@dataclass
class DiffResult:
    """``loss`` (m^2), ``gradients`` (name -> numpy), ``positions`` (frames, n, 3) of the run,
    ``steps`` (time steps taken), ``recorded_bytes`` (host memory of the recorded steps)."""

    loss: float
    gradients: dict
    positions: np.ndarray
    steps: int = 0
    recorded_bytes: int = 0
    newton_iterations: int = 0
    seconds_forward: float = 0.0
    seconds_backward: float = 0.0
    extra: dict = field(default_factory=dict)


def check_observation(observed, num_vertices, vertices=None, frames=None):
    """(observed (F, k, 3) float64, vertices (k,) int, frames (int list)) validated: ``observed``
    holds every vertex (k = n) or those of ``vertices``; raises :class:`DiffInputError` saying what."""
    obs = np.asarray(observed, dtype=np.float64)
    if obs.ndim != 3 or obs.shape[2] != 3 or obs.shape[0] < 2:
        raise DiffInputError(f"observed positions must have shape (frames >= 2, vertices, 3), got {obs.shape}")
    if not np.all(np.isfinite(obs)):
        bad = np.argwhere(~np.isfinite(obs))[0]
        raise DiffInputError(f"observed positions are not finite (NaN/inf at frame {bad[0]}, vertex {bad[1]})")
    if vertices is None:
        vertices = np.arange(num_vertices)
    else:
        vertices = np.asarray(vertices).reshape(-1)
        if vertices.size == 0 or not np.issubdtype(vertices.dtype, np.integer):
            raise DiffInputError(f"vertices must be a non-empty list of integer indices, got {vertices.dtype} "
                                 f"with {vertices.size} entries")
        if vertices.min() < 0 or vertices.max() >= num_vertices:
            raise DiffInputError(f"vertex index out of range: the mesh has {num_vertices} vertices, got indices "
                                 f"{int(vertices.min())}..{int(vertices.max())}")
    if obs.shape[1] == num_vertices and len(vertices) != num_vertices:
        obs = obs[:, vertices]
    elif obs.shape[1] != len(vertices):
        raise DiffInputError(f"observed positions have {obs.shape[1]} vertices per frame, the mesh has {num_vertices}"
                             + (f" and {len(vertices)} vertices are chosen" if len(vertices) != num_vertices else ""))
    F = obs.shape[0]
    frames = list(range(F)) if frames is None else [int(f) for f in frames]
    bad = [f for f in frames if not 0 <= f < F]
    if bad:
        raise DiffInputError(f"frames {bad} are outside the observation's {F} frames (0..{F - 1})")
    return obs, vertices, frames


def positions_loss(positions, observed, vertices, frames):
    """(L, {frame: dL/dx_frame (n, 3)}) of the squared-distance loss above."""
    loss, grads = 0.0, {}
    for f in frames:
        r = positions[f][vertices] - observed[f]
        loss += float(np.sum(r * r))
        g = np.zeros_like(positions[f])
        np.add.at(g, vertices, 2.0 * r)
        grads[f] = g
    return loss, grads


def _collider_names(spec):
    from warpfem.contact.scene import scene_collider_names

    return scene_collider_names(spec.collider or [])


def scene_parameters_of(scene) -> tuple:
    """The parameter names ``scene``'s gradient run takes: :data:`MATERIAL_PARAMETERS` (a one-body
    scene), ``contact_friction`` (a scene with ``[contact]``) and ``friction:<name>`` for each
    ``[[collider]]``."""
    spec = scene.spec
    names = MATERIAL_PARAMETERS if len(spec.bodies or ()) <= 1 else ()
    if spec.contact is not None:
        names += (CONTACT_FRICTION,)
    return names + tuple(FRICTION_PREFIX + n for n in _collider_names(spec))


def check_parameter_names(scene, names, what="a scene's gradient run"):
    """Raise :class:`DiffInputError` (one line: what is wrong, what the scene has) for a name that
    ``scene`` does not take (:func:`scene_parameters_of`)."""
    known = scene_parameters_of(scene)
    spec = scene.spec
    for k in names:
        if k in known:
            continue
        if not isinstance(k, str):
            raise DiffInputError(f"parameter names are strings, got {k!r}")
        if k.startswith(FRICTION_PREFIX):
            cols = _collider_names(spec)
            have = ("its colliders are " + ", ".join(map(repr, cols))) if cols else "it has no [[collider]]"
            raise DiffInputError(f"{k!r}: the scene has no collider named {k[len(FRICTION_PREFIX):]!r} ({have})")
        if k == CONTACT_FRICTION:
            raise DiffInputError(f"{k!r}: the scene has no [contact] table (surface contact's friction lives there; "
                                 f"add [contact] with friction = ...); it takes {', '.join(known)}")
        if k in MATERIAL_PARAMETERS:
            raise DiffInputError(f"{k!r}: a scene of {len(spec.bodies)} [[body]] tables has a material per body, which "
                                 f"a gradient run does not set; it takes {', '.join(known) or 'nothing'}")
        raise DiffInputError(f"unknown parameter {k!r}; {what} takes {', '.join(known)}")


def scene_parameter_values(scene, names) -> dict:
    """The values of ``names`` (:func:`scene_parameters_of`) in ``scene``'s spec."""
    check_parameter_names(scene, names)
    spec, out = scene.spec, {}
    cols = _collider_names(spec)
    for k in names:
        if k == CONTACT_FRICTION:
            out[k] = float(spec.contact.get("friction") or 0.0)
        elif k.startswith(FRICTION_PREFIX):
            out[k] = float(spec.collider[cols.index(k[len(FRICTION_PREFIX):])].get("friction") or 0.0)
        else:
            out[k] = float(spec.material[k])
    return out


def _run_value(name, value):
    """The value a run uses for ``name``: frictions >= :data:`FRICTION_FLOOR`."""
    if name == CONTACT_FRICTION or name.startswith(FRICTION_PREFIX):
        if value < 0.0:
            raise DiffInputError(f"{name} must be >= 0, got {value!r}")
        return max(value, FRICTION_FLOOR)
    return value


def scene_with_parameters(scene, params=None, *, newton_tol=None):
    """A copy of ``scene`` (a :class:`~warpfem.scenes.Scene`) with ``params`` (names of
    :func:`scene_parameters_of`: ``[material]`` values, ``[contact] friction``, a
    ``[[collider]]``'s ``friction``) written in and the Newton tolerance tightened to
    ``newton_tol`` (gradients hold at the converged solution)."""
    params = dict(params or {})
    check_parameter_names(scene, params)
    if scene.spec.bodies:  # a [[body]] scene caches its bodies' scenes (and their materials): a new one
        sc = type(scene)(copy.deepcopy(scene.spec))
    else:  # the same mesh (loaded once)
        sc = copy.copy(scene)
        sc.spec = copy.deepcopy(scene.spec)
    cols = _collider_names(sc.spec)
    for k, v in params.items():
        v = float(v)
        if not np.isfinite(v):
            raise DiffInputError(f"{k} must be finite, got {v!r}")
        v = _run_value(k, v)
        if k == CONTACT_FRICTION:
            sc.spec.contact["friction"] = v
        elif k.startswith(FRICTION_PREFIX):
            sc.spec.collider[cols.index(k[len(FRICTION_PREFIX):])]["friction"] = v
        else:
            sc.spec.material[k] = v
    if newton_tol is not None:
        sc.spec.integrator["tol"] = min(float(sc.spec.integrator.get("tol", 1e-6)), float(newton_tol))
        sc.spec.integrator["atol"] = 0.0
    return sc


def _scene(source):
    from warpfem.scenes import Scene, load_scene

    if isinstance(source, Scene):
        return source
    return load_scene(source)


class SceneProblem:
    """A scene's gradient runs against one observation, built once: every :meth:`evaluate` changes
    Young's modulus, Poisson ratio and density (``set_material_parameters``, ``set_density``) and
    the frictions (``ContactSet.set_friction``, ``SurfaceContact.set_friction``) in place and
    restarts from the initial state."""

    def __init__(self, scene, observed, *, vertices=None, frames=None, device="cpu", precision="float64",
                 newton_tol=1e-10, run_frames=None):
        if precision == "float32" and newton_tol is not None:
            newton_tol = max(float(newton_tol), FLOAT32_NEWTON_TOL)  # float32's round-off floor
        self.scene = scene_with_parameters(_scene(scene), newton_tol=newton_tol)
        if not self.scene.dynamic:
            raise DiffInputError(f"{self.scene.path or 'the scene'}: gradients need a dynamic integrator "
                                 f"(backward_euler, bdf2, newmark), not {self.scene.integrator_type!r}")
        if self.scene.spec.subspace is not None:
            raise NotImplementedError("gradients of reduced runs ([subspace]) are not supported; remove the "
                                      "[subspace] section to differentiate the full-space run")
        self.device, self.precision = device, precision
        n = self.scene.mesh().num_vertices
        self.observed, self.vertices, self.frames = check_observation(observed, n, vertices, frames)
        # the run that recorded it: the scene's [output] frames, or `warpfem run --frames N` (run_frames)
        want = int(self.scene.spec.output["frames"] if run_frames is None else run_frames) + 1
        if self.observed.shape[0] != want:
            how = "[output] frames" if run_frames is None else "--frames"
            raise DiffInputError(f"the observation has {self.observed.shape[0]} frames, the scene runs "
                                 f"{want - 1} frames ({how}; {want} states with frame 0)")
        self._run = self._initial = None

    def _prepare(self, params):
        from warpfem.solvers.adjoint import set_density, set_material_parameters

        names = scene_parameters_of(self.scene)
        values = {k: _run_value(k, float(params[k])) if k in params else v
                  for k, v in scene_parameter_values(self.scene, names).items()}
        if self._run is None:
            self._run = scene_with_parameters(self.scene, params).build(device=self.device, precision=self.precision)
            sim = self._run.sim
            self._initial = (sim.positions(), sim.velocities())
            self._applied = dict(values)
        sim = self._run.sim
        if CONTACT_FRICTION in params and sim.surface_contact is None:
            raise DiffInputError("contact_friction: the scene's surface contact is off (a single body without "
                                 "[contact] self = true, or bodies = false): it has no surface friction")
        changed = {k for k, v in values.items() if self._applied.get(k) != v}
        if changed & {"youngs_modulus", "poisson_ratio"}:
            set_material_parameters(sim, values["youngs_modulus"], values["poisson_ratio"])
        if "density" in changed:
            set_density(sim, values["density"])
        for k in changed:
            if k == CONTACT_FRICTION and sim.surface_contact is not None:
                sim.surface_contact.set_friction(values[k])
            elif k.startswith(FRICTION_PREFIX):
                sim.contact.set_friction(k[len(FRICTION_PREFIX):], values[k])
        self._applied = dict(values)
        sim.set_positions(self._initial[0])  # clears the integrator's history
        sim.set_velocities(self._initial[1])
        sim.time = 0.0
        sim.step_count = 0
        sim.control.targets.clear()
        self._run.frame = 0
        return self._run

    def evaluate(self, params=None, wanted=None, element_stiffness_scale=None, last_frame=None) -> DiffResult:
        """Loss and gradients at ``params`` (names of :func:`scene_parameters_of`; others keep the
        scene's) and the per-element stiffness factors (default 1). ``last_frame``: run only up to
        that frame, the loss over the chosen frames up to it (the handles still ramp as in the
        whole run). ``wanted``: the gradients to compute (names of the adjoint's ``PARAMETERS`` or
        of the scene's; default all); each collider friction's gradient also comes as
        ``friction:<name>``."""
        from warpfem.solvers.adjoint import set_element_stiffness_scale

        params = dict(params or {})
        scene_with_parameters(self.scene, params)  # validates the names and values
        if wanted is not None:
            wanted = list(dict.fromkeys("collider_friction" if str(w).startswith(FRICTION_PREFIX) else w
                                        for w in wanted))
        run = self._prepare(params)
        set_element_stiffness_scale(run.sim, element_stiffness_scale)
        F = self.observed.shape[0]
        last = F - 1 if last_frame is None else int(last_frame)
        if not 1 <= last <= F - 1:
            raise DiffInputError(f"last_frame must be in 1..{F - 1}, got {last_frame!r}")
        frames = [f for f in self.frames if f <= last]
        res = _record_and_differentiate(run.sim, last + 1, self.observed, self.vertices, frames, wanted,
                                        lambda f: run.step_frame(total_frames=F - 1))
        cf = res.gradients.get("collider_friction")
        if cf is not None:  # every collider's, 0 where no vertex came within its dhat
            for name in _collider_names(self.scene.spec):
                res.gradients[FRICTION_PREFIX + name] = float(cf.get(name, 0.0))
        return res


def _record_and_differentiate(sim, F, obs, vertices, frames, wanted, advance):
    import time

    from warpfem.solvers.adjoint import Recording

    rec = Recording(sim, wanted)
    positions, steps_at, newton = [sim.positions()], [0], 0
    t0 = time.perf_counter()
    with rec:
        for f in range(1, F):
            st = advance(f)
            if not st.converged:
                raise RuntimeError(f"frame {f}: the step did not converge ({st.reason}); gradients need converged steps")
            newton += st.newton_iterations
            positions.append(sim.positions())
            steps_at.append(rec.steps)
    t1 = time.perf_counter()
    positions = np.asarray(positions)
    loss, xg = positions_loss(positions, obs, vertices, frames)
    try:
        grads = rec.backward({steps_at[f]: g for f, g in xg.items()})
    finally:
        rec.release()  # the factorisations the steps kept for this reverse pass
    t2 = time.perf_counter()
    return DiffResult(loss=loss, gradients=grads, positions=positions, steps=rec.steps, recorded_bytes=rec.nbytes,
                      newton_iterations=newton, seconds_forward=t1 - t0, seconds_backward=t2 - t1)


def loss_and_gradients(source, observed, *, vertices=None, frames=None, params=None, steps_per_frame=1,
                       targets=None, element_stiffness_scale=None, device="cpu", precision="float64",
                       newton_tol=1e-10, wanted=None, run_frames=None) -> DiffResult:
    """Run ``source`` forward for ``len(observed) - 1`` frames and return the squared-distance loss
    to ``observed`` and its gradients (see the module docstring).

    Args:
        source: a scene file path or :class:`~warpfem.scenes.Scene` (built here with ``params``),
            or a built :class:`~warpfem.Simulator` (run from its current state; ``params`` must be
            None: build it with the values you want).
        observed: (frames, n or len(vertices), 3) positions (m); frame 0 is the initial state.
        vertices: indices of the observed vertices (default all).
        frames: the frames in the loss (default all).
        params: scene parameters (:func:`scene_parameters_of`: ``[material]`` values,
            ``contact_friction``, ``friction:<collider name>``) for a scene source.
        steps_per_frame: time steps per frame of a simulator source (a scene uses its substeps).
        targets: for a simulator source, ``targets(step) -> {vertex: (3,)}`` (kinematic handles) or None.
        element_stiffness_scale: (m,) per-element stiffness factors applied before the run.
        newton_tol: the Newton tolerance of a scene's run (tightened to it; gradients are exact at
            the converged solution); a simulator source keeps its own.
        wanted: parameter names to compute (default all).
        run_frames: the frames of a scene's run (default its ``[output] frames``, as ``warpfem run``
            without ``--frames``); the observation must have run_frames + 1.
    """
    from warpfem.simulator import Simulator
    from warpfem.solvers.adjoint import set_element_stiffness_scale

    if not isinstance(source, Simulator):
        problem = SceneProblem(source, observed, vertices=vertices, frames=frames, device=device, precision=precision,
                               newton_tol=newton_tol, run_frames=run_frames)
        return problem.evaluate(params, wanted, element_stiffness_scale=element_stiffness_scale)
    if params:
        raise DiffInputError("params are for scene sources; build the simulator with the values you want")
    sim = source
    obs, vertices, frames = check_observation(observed, sim.num_vertices, vertices, frames)
    if element_stiffness_scale is not None:
        set_element_stiffness_scale(sim, element_stiffness_scale)
    counter = [0]

    def advance(f):
        from warpfem.solvers.nonlinear import SolveStats

        total = SolveStats(converged=True)
        for _ in range(int(steps_per_frame)):
            if targets is not None:
                t = targets(counter[0])
                if t:
                    idx = list(t)
                    sim.set_targets(idx, np.array([t[i] for i in idx]))
            st = sim.step()
            counter[0] += 1
            total.newton_iterations += st.newton_iterations
            if not st.converged:
                total.converged, total.reason = False, st.reason
        return total

    return _record_and_differentiate(sim, obs.shape[0], obs, vertices, frames, wanted, advance)
