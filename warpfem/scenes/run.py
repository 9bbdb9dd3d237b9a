"""Running a built scene frame by frame (:class:`SceneRun`) and the per-frame record
(:class:`FrameStats`); ``Scene.build`` (``scene.py``) returns a ``SceneRun``."""

from __future__ import annotations

import json
import logging
import os
import time
import warnings
from dataclasses import dataclass

import numpy as np

from .loads import boundary_surface, handle_targets

__all__ = ["SceneRun", "FrameStats"]

_logger = logging.getLogger(__name__)


@dataclass
class FrameStats:
    """Statistics of one output frame (sums over its steps).

    ``residual`` is the last step's relative gradient; ``converged`` is False when any step of
    the frame did not converge, ``unconverged_steps`` counts them and ``reason`` names each
    ("step 12: reached max_iters=30 (relative gradient 3.10e-04 > tol 1.0e-06)", joined by "; ")."""

    frame: int
    time: float
    steps: int
    step_seconds: float
    newton_iterations: int
    cg_iterations: int
    residual: float
    energy: float
    converged: bool
    reason: str = ""
    unconverged_steps: int = 0
    worst_residual: float = 0.0  # the largest relative gradient of the frame's unconverged steps (0: none)

    def as_dict(self):
        return dict(self.__dict__)


def _step_note(stats, what: str) -> str:
    """``"step 12: <reason> (relative gradient 3.10e-04 > tol 1.0e-06)"``: a non-converged step
    in a frame's ``reason``."""
    tol = f" > tol {stats.tolerance:.1e}" if getattr(stats, "tolerance", 0.0) > 0.0 else ""
    return f"{what}: {stats.reason} (relative gradient {stats.residual:.2e}{tol})"


def log_not_converged(fs: FrameStats) -> None:
    """The one warning line of a frame with non-converged steps."""
    _logger.warning(f"frame {fs.frame}: {fs.unconverged_steps} of {fs.steps} step{'s' if fs.steps != 1 else ''} "
                f"not converged: {fs.reason}")


def _incomplete_reason(e: BaseException, frame: int) -> str:
    """What an incomplete output records: ``"SolveFailed: ..."``, ``"KeyboardInterrupt: interrupted
    (Ctrl-C) at frame 3"``, ``"Terminated: SIGTERM at frame 3"`` (an exception's own message when it
    has one)."""
    msg = str(e)
    if isinstance(e, KeyboardInterrupt):
        msg = f"{msg or 'interrupted (Ctrl-C)'} at frame {frame}"
    return f"{type(e).__name__}: {msg}"


class SceneRun:
    """A built scene: ``model``, ``sim`` (the integrator), ``skinner`` (None without [surface])."""

    def __init__(self, scene: "Scene", model, sim, handle_ids, *, device, precision):
        self.scene, self.model, self.sim = scene, model, sim
        self.device, self.precision = device, precision
        sp = scene.spec
        self.fps = float(sp.output["fps"])
        self.frames = int(sp.output["frames"])
        self.frame = 0
        self._handles = [(h, ids, model.rest_positions[ids].copy()) for h, ids in zip(sp.handle, handle_ids)]
        self._gravity = model.gravity.copy()
        self._forces = model.forces.copy()
        mesh = scene.mesh()
        # a simulator may map an embedding to surface points itself (e.g. a reduced one, O(r) per point)
        self._sim_surface_points = getattr(sim, "surface_points", None)
        self.body_surfaces = None  # [[body]] scenes: [(prim name, faces, count, points())] per body
        if sp.bodies:
            self._setup_body_surfaces(scene, device, precision)
        elif sp.surface is not None:
            from warpfem.skinning import SurfaceSkinner, embed_points_in_mesh, load_surface

            pts, tris = load_surface(sp.surface["path"])
            self.embedding = embed_points_in_mesh(pts, mesh)  # k weights per point (k = nodes per element)
            self.skinner = None
            if self._sim_surface_points is None:
                self.skinner = SurfaceSkinner(self.embedding, mesh, device=device, precision=precision)
            self.surface_faces = tris
            self.surface_vertex_ids = None
            self.surface_name = sp.surface["name"]
        else:
            self.embedding = None
            self.skinner = None
            self.surface_vertex_ids, self.surface_faces = boundary_surface(mesh)
            self.surface_name = "boundary"

    def _setup_body_surfaces(self, scene, device, precision):
        """One render surface per body (its [surface], embedded in its own elements, or its boundary);
        ``surface_points()`` / ``surface_faces`` are all of them concatenated (previews)."""
        from warpfem.skinning import SurfaceSkinner, embed_points_in_mesh, load_surface

        self.embedding = self.skinner = None
        self.surface_vertex_ids = None
        self.surface_name = "bodies"
        out = []
        offsets = self.model.body_offsets
        for b, lo, hi in zip(scene.bodies, offsets[:-1], offsets[1:]):
            lo, hi = int(lo), int(hi)
            bm = b.mesh()
            if b.spec.surface is not None:
                pts, tris = load_surface(b.spec.surface["path"])
                emb = embed_points_in_mesh(np.asarray(pts, dtype=np.float64) + b.offset, bm)
                skinner = SurfaceSkinner(emb, bm, device=device, precision=precision)

                def points(skinner=skinner, lo=lo, hi=hi):
                    return skinner.apply(self.sim.x[lo:hi]).numpy().astype(np.float64)

                out.append((b.body_name, np.asarray(tris), emb.num_points, points))
            else:
                ids, tris = boundary_surface(bm)

                def points(ids=ids + lo):
                    return self.sim.positions()[ids]

                out.append((b.body_name, np.asarray(tris), int(ids.size), points))
        self.body_surfaces = out
        starts = np.concatenate([[0], np.cumsum([c for _, _, c, _ in out])])
        self.surface_faces = np.concatenate([f + int(o) for (_, f, _, _), o in zip(out, starts[:-1])])

    def usd_surfaces(self) -> list:
        """The USD prims of the render surfaces: [(name, faces, number of points)] (one per body)."""
        if self.body_surfaces is not None:
            return [(name, faces, count) for name, faces, count, _ in self.body_surfaces]
        return [(self.surface_name, self.surface_faces, self.num_surface_points)]

    def usd_surface_points(self) -> dict:
        """{prim name: current points} of :meth:`usd_surfaces`."""
        if self.body_surfaces is not None:
            return {name: points() for name, _, _, points in self.body_surfaces}
        return {self.surface_name: self.surface_points()}

    def usd_volumes(self) -> list:
        """``[output] usd_volume``: [(prim name, tets (m, 4) over the body's own vertices, surface faces,
        first vertex, end vertex)], one per body (a one-body scene: "volume"); corner tets of
        higher-order elements, so the TetMesh shows the element corners' motion."""
        out = []
        offsets = self.model.body_offsets
        meshes = [b.mesh() for b in self.scene.bodies] or [self.scene.mesh()]
        names = [f"{b.body_name}_volume" for b in self.scene.bodies] or ["volume"]
        for name, m, lo, hi in zip(names, meshes, offsets[:-1], offsets[1:]):
            tets = np.asarray(m.corner_tets(), dtype=np.int64)
            faces = np.asarray(m.boundary_faces(), dtype=np.int64) if m.element.is_linear_tet else None
            out.append((name, tets, faces, int(lo), int(hi)))
        return out

    @property
    def num_surface_points(self) -> int:
        if self.body_surfaces is not None:
            return int(sum(c for _, _, c, _ in self.body_surfaces))
        if self.embedding is not None:
            return self.embedding.num_points
        return int(self.surface_vertex_ids.size)

    def duration(self, frames=None) -> float:
        """Length of the run (s) over which handles ramp by default."""
        return (self.frames if frames is None else frames) / self.fps

    def surface_points(self) -> np.ndarray:
        """Current render-surface points (p, 3): x_surface = W x on the device (the skinner), or the
        simulator's own ``surface_points(embedding)`` when it has one; without ``[surface]`` the
        boundary vertices' positions. ``[[body]]`` scenes: every body's, concatenated in body order."""
        if self.body_surfaces is not None:
            return np.concatenate([points() for _, _, _, points in self.body_surfaces])
        if self.embedding is not None:
            if self._sim_surface_points is not None:
                return np.asarray(self._sim_surface_points(self.embedding), dtype=np.float64)
            return self.skinner.apply(self.sim.x).numpy().astype(np.float64)
        return self.sim.positions()[self.surface_vertex_ids]

    def set_handles(self, fraction_of):
        """Targets of every handle for the coming step: ``fraction_of(handle)`` of its motion."""
        for h, ids, rest in self._handles:
            self.sim.set_targets(ids, handle_targets(rest, h, fraction_of(h)))

    def step_frame(self, *, total_frames=None) -> FrameStats:
        """Advance one output frame (1/fps of simulated time, or one static load frame)."""
        from . import INTEGRATORS

        total = self.frames if total_frames is None else int(total_frames)
        sim = self.sim
        integ = self.scene.spec.integrator
        entry = INTEGRATORS[self.scene.integrator_type]
        t0 = time.perf_counter()
        newton = cg = 0
        residual = energy = 0.0
        converged, reasons = True, []
        worst = 0.0
        self.frame += 1
        if entry.dynamic:
            steps = integ["substeps"]
            T = self.duration(total)
            for _ in range(steps):
                t_next = sim.time + sim.dt
                self.set_handles(lambda h: t_next / (h["ramp_time"] or T))
                index = getattr(sim, "step_count", None)
                st = sim.step()
                newton += st.newton_iterations
                cg += st.cg_iterations
                residual, energy = st.residual, st.energy
                if not st.converged:
                    converged = False
                    reasons.append(_step_note(st, "step" if index is None else f"step {index}"))
                    worst = max(worst, float(st.residual)) if st.residual == st.residual else float("nan")
            t = sim.time
        else:
            steps = 1
            frac = self.frame / total
            if hasattr(sim, "load_scale"):  # a control of the solver: the model is not rescaled
                sim.load_scale = frac
            else:
                self.model.gravity = self._gravity * frac
                self.model.forces = self._forces * frac
                sim.sync_model()
            self.set_handles(lambda h: frac)
            st = entry.static_solve(sim, integ)
            newton, cg, residual, energy = st.newton_iterations, st.cg_iterations, st.residual, st.energy
            converged = st.converged
            reasons = [_step_note(st, "static solve")] if not st.converged else []
            worst = float(st.residual) if not st.converged else 0.0
            t = self.frame / self.fps
        return FrameStats(frame=self.frame, time=t, steps=steps, step_seconds=time.perf_counter() - t0,
                          newton_iterations=newton, cg_iterations=cg, residual=float(residual),
                          energy=float(energy), converged=converged, reason="; ".join(reasons),
                          unconverged_steps=len(reasons), worst_residual=worst)

    def run(self, *, frames=None, usd=None, states=None, stats=None, progress=None, vtu=None):
        """Run ``frames`` output frames (default: the scene's) writing the outputs.

        Frame 0 is the rest state; frames 1..N follow every 1/fps s (static: load fraction k/N).
        ``usd``/``states``/``stats`` default to the scene's [output] (paths relative to the
        current directory). ``vtu``: a ParaView collection (.pvd) of the volume mesh, written frame
        by frame (:class:`warpfem.io.VtuSeriesWriter`); default the scene's [output].vtu. Every
        stats record carries ``warpfem_version``. The USD stage is made once the first frame is stepped
        (frame 0 kept until then). ``progress(FrameStats)`` is called after each frame. On
        :class:`warpfem.SolveFailed` (or Ctrl-C) the USD is closed marked incomplete with the
        frames done so far, the npz/stats hold them too, and the exception propagates.
        A step that does not converge (``require_convergence`` off) is not a Python warning here:
        each frame with such steps logs one warning line on the ``warpfem.scenes.run`` logger
        (``frame 9: 1 of 4 steps not converged: step 33: ...``); the frames' ``unconverged_steps``
        count them. Returns the list of :class:`FrameStats`.
        """
        from warpfem.io import StatesWriter, UsdMeshWriter

        out = self.scene.spec.output
        total = self.frames if frames is None else int(frames)
        if total < 1:
            raise ValueError(f"frames must be >= 1, got {total}")
        usd = out["usd"] if usd is None else usd
        states = out["states"] if states is None else states
        from .scene import Scene

        stats = Scene.stats_path(usd, out["stats"] if stats is None else stats)
        vtu = out.get("vtu") if vtu is None else vtu
        from warpfem.io.outputs import check_output_paths

        # every output path before anything is written (OutputPathError, a ValueError, names the bad one)
        check_output_paths({"usd": usd, "states": states, "stats": stats, "vtu": vtu})
        writer = log = volume = pending_usd = None
        from warpfem.io.vtu import VtuSeriesWriter, warpfem_version

        version = warpfem_version()
        history = []
        positions = None  # frames stream to disk (StatesWriter): memory does not grow with the run
        if states:
            extra = {}
            if self.scene.spec.bodies:  # rest / positions hold every body's vertices in body order
                extra = {"body_offsets": np.asarray(self.model.body_offsets, dtype=np.int64),
                         "body_names": np.array(self.model.body_names)}
            positions = StatesWriter(states, rest=self.model.rest_positions, max_frames=total + 1, fps=self.fps,
                                     extra=extra)
            positions.write_frame(self.sim.positions(), self._time())
        try:
            if usd:
                volumes = self.usd_volumes() if out.get("usd_volume") else []
                colliders = []
                if getattr(self.sim, "contact", None) is not None:  # the contact modules only when there is contact
                    from warpfem.contact.scene import collider_prims

                    colliders = collider_prims(self.sim, 2.0 * float(np.ptp(self.model.rest_positions, axis=0).max()))

                def usd_frame():
                    frame = self.usd_surface_points()
                    if volumes:
                        x = self.sim.positions()
                        frame.update({name: x[lo:hi] for name, _, _, lo, hi in volumes})
                    frame.update({name: pts() for name, _, pts in colliders})
                    return frame

                def open_usd(first):
                    w = UsdMeshWriter(usd, fps=self.fps, up_axis=out["up_axis"], clip_frames=out["clip_frames"] or None)
                    for name, faces, count in self.usd_surfaces():
                        w.add_mesh(name, faces, count)
                    for name, tets, faces, lo, hi in volumes:
                        w.add_tet_mesh(name, tets, hi - lo, surface_faces=faces)
                    for name, faces, pts in colliders:
                        w.add_mesh(name, faces, len(pts()))
                    w.write_frame(*first)
                    return w

                # the stage is made, with frame 0, once the first frame is stepped: the USD library
                # (~0.2 s to import) does not hold up the first step
                pending_usd = (open_usd, (self.frame, {k: np.array(v, copy=True) for k, v in usd_frame().items()}))
            if vtu:
                if self.scene.spec.bodies:  # one block per body, by name
                    from warpfem.io.vtu import VtuBodiesWriter

                    offs = self.model.body_offsets
                    volume = VtuBodiesWriter(vtu, bodies=[(b.body_name, b.mesh().elements, b.mesh().element_type,
                                                           int(lo), int(hi))
                                                          for b, lo, hi in zip(self.scene.bodies, offs[:-1], offs[1:])])
                else:
                    qd = self.model.quadrature
                    volume = VtuSeriesWriter(vtu, cells=qd.elements, element_type=qd.element_type)
                volume.write_state(self._time(), self.sim, self.model)
            if stats:
                os.makedirs(os.path.dirname(os.path.abspath(stats)), exist_ok=True)
                log = open(stats, "w")
            for _ in range(total):
                try:
                    with warnings.catch_warnings():  # reported below, one line per frame
                        from warpfem.solvers.nonlinear import NotConvergedWarning

                        warnings.simplefilter("ignore", NotConvergedWarning)
                        fs = self.step_frame(total_frames=total)
                except Exception as e:
                    if log is not None:
                        failed = getattr(e, "stats", None)
                        log.write(json.dumps({"frame": self.frame, "converged": False, "error": str(e),
                                              "newton_iterations": getattr(failed, "newton_iterations", None),
                                              "warpfem_version": version}) + "\n")
                    raise
                history.append(fs)
                if fs.unconverged_steps:
                    log_not_converged(fs)
                if log is not None:
                    log.write(json.dumps({**fs.as_dict(), "warpfem_version": version}) + "\n")
                    log.flush()
                if positions is not None:
                    positions.write_frame(self.sim.positions(), fs.time)
                if pending_usd is not None:  # the first frame is stepped: the stage now, with frame 0
                    (opener, first), pending_usd = pending_usd, None
                    writer = opener(first)
                if writer is not None:
                    writer.write_frame(self.frame, usd_frame())
                if volume is not None:
                    volume.write_state(fs.time, self.sim, self.model)
                if progress is not None:
                    progress(fs)
        except BaseException as e:
            reason = _incomplete_reason(e, self.frame)
            if pending_usd is not None:  # the first frame failed: frame 0 is still written, marked incomplete
                try:
                    writer = pending_usd[0](pending_usd[1])
                except Exception as usd_error:  # noqa: BLE001 - the step's error is the one raised
                    _logger.warning(f"{usd}: not written: {usd_error}")
            if writer is not None:
                writer.close(complete=False, reason=reason)
            if volume is not None:
                volume.close(complete=False, reason=reason)
            raise
        else:
            if writer is not None:
                writer.close(complete=True)
            if volume is not None:
                volume.close(complete=True)
        finally:
            if log is not None:
                log.close()
            if positions is not None:
                positions.close()
        return history

    @staticmethod
    def convergence_summary(history) -> dict:
        """What a run's frames say about convergence: ``steps`` (all), ``unconverged_steps``,
        ``unconverged_frames`` (the frame numbers with at least one) and ``worst`` ((frame, relative
        gradient) of the unconverged step farthest from the tolerance, or None)."""
        bad = [fs for fs in history if fs.unconverged_steps]
        worst = None
        if bad:
            fs = max(bad, key=lambda f: (f.worst_residual if f.worst_residual == f.worst_residual else float("inf")))
            worst = (fs.frame, float(fs.worst_residual))
        return {"steps": int(sum(fs.steps for fs in history)),
                "unconverged_steps": int(sum(fs.unconverged_steps for fs in history)),
                "unconverged_frames": [fs.frame for fs in bad], "worst": worst}

    def _time(self):
        """Simulated time of the current state (s): the integrator's clock, or frame / fps (static)."""
        if self.scene.dynamic and hasattr(self.sim, "time"):
            return float(self.sim.time)
        return self.frame / self.fps
