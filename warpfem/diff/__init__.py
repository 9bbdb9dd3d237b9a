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
surface contact).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np

__all__ = ["loss_and_gradients", "SceneProblem", "DiffResult", "positions_loss", "SCENE_PARAMETERS", "scene_with_parameters",
           "DiffInputError", "check_observation"]

#: the tightest Newton tolerance a float32 gradient run asks for (below it float32 round-off stalls Newton)
FLOAT32_NEWTON_TOL = 1e-5

#: the parameters a scene's gradient run can set (and ``warpfem fit`` identify)
SCENE_PARAMETERS = ("youngs_modulus", "poisson_ratio", "density")


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


def scene_with_parameters(scene, params=None, *, newton_tol=None):
    """A copy of ``scene`` (a :class:`~warpfem.scenes.Scene`) with ``[material]`` values replaced by
    ``params`` (names of :data:`SCENE_PARAMETERS`) and the Newton tolerance tightened to
    ``newton_tol`` (gradients hold at the converged solution)."""
    params = dict(params or {})
    unknown = [k for k in params if k not in SCENE_PARAMETERS]
    if unknown:
        raise DiffInputError(f"unknown parameter(s) {', '.join(map(repr, unknown))}; a scene's gradient run "
                             f"takes {', '.join(SCENE_PARAMETERS)}")
    sc = copy.copy(scene)
    sc.spec = copy.deepcopy(scene.spec)
    for k, v in params.items():
        v = float(v)
        if not np.isfinite(v):
            raise DiffInputError(f"{k} must be finite, got {v!r}")
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
    Young's modulus, Poisson ratio and density in place (``set_material_parameters``,
    ``set_density``) and restarts from the initial state."""

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

        mat = self.scene.spec.material
        if self._run is None:
            self._run = scene_with_parameters(self.scene, params).build(device=self.device, precision=self.precision)
            sim = self._run.sim
            self._initial = (sim.positions(), sim.velocities())
            return self._run
        sim = self._run.sim
        set_material_parameters(sim, params.get("youngs_modulus", mat["youngs_modulus"]),
                                params.get("poisson_ratio", mat["poisson_ratio"]))
        set_density(sim, params.get("density", mat["density"]))
        sim.set_positions(self._initial[0])  # clears the integrator's history
        sim.set_velocities(self._initial[1])
        sim.time = 0.0
        sim.step_count = 0
        sim.control.targets.clear()
        self._run.frame = 0
        return self._run

    def evaluate(self, params=None, wanted=None, element_stiffness_scale=None, last_frame=None) -> DiffResult:
        """Loss and gradients at ``params`` (names of :data:`SCENE_PARAMETERS`; others keep the
        scene's) and the per-element stiffness factors (default 1). ``last_frame``: run only up to
        that frame, the loss over the chosen frames up to it (the handles still ramp as in the
        whole run)."""
        from warpfem.solvers.adjoint import set_element_stiffness_scale

        params = dict(params or {})
        scene_with_parameters(self.scene, params)  # validates the names and values
        run = self._prepare(params)
        set_element_stiffness_scale(run.sim, element_stiffness_scale)
        F = self.observed.shape[0]
        last = F - 1 if last_frame is None else int(last_frame)
        if not 1 <= last <= F - 1:
            raise DiffInputError(f"last_frame must be in 1..{F - 1}, got {last_frame!r}")
        frames = [f for f in self.frames if f <= last]
        return _record_and_differentiate(run.sim, last + 1, self.observed, self.vertices, frames, wanted,
                                         lambda f: run.step_frame(total_frames=F - 1))


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
        params: scene parameters (:data:`SCENE_PARAMETERS`) for a scene source.
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
