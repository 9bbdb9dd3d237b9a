"""Running a built scene frame by frame (:class:`SceneRun`) and the per-frame record
(:class:`FrameStats`); ``Scene.build`` (``scene.py``) returns a ``SceneRun``."""

from __future__ import annotations

import logging
import re
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


def _one_line(e: BaseException) -> str:
    """An exception as one line: an OSError's reason (and its file when another), else its first line."""
    if isinstance(e, OSError) and e.strerror:
        return e.strerror + (f" ({e.filename})" if e.filename else "")
    text = str(e).strip().splitlines()
    line = (text[0] if text else type(e).__name__).strip()
    return re.sub(r"^Error in '[^']*' at line \d+ in file \S+ : ", "", line)  # pxr's location prefix


def _incomplete_reason(e: BaseException, frame: int) -> str:
    """What an incomplete output records: ``"SolveFailed: ..."``, ``"KeyboardInterrupt: interrupted
    (Ctrl-C) at frame 3"``, ``"Terminated: SIGTERM at frame 3"`` (an exception's own message when it
    has one)."""
    msg = str(e)
    if isinstance(e, KeyboardInterrupt):
        msg = f"{msg or 'interrupted (Ctrl-C)'} at frame {frame}"
    return f"{type(e).__name__}: {msg}"


class _RenderSurface:
    """One body's render surface: USD prim ``name``, ``faces`` over its ``count`` points,
    ``points()`` now; ``embedding`` / ``skinner`` with a [surface], else the model's ``vertex_ids``."""

    def __init__(self, name, faces, count, points, *, embedding=None, skinner=None, vertex_ids=None, local=None,
                 transform=None):
        self.name, self.faces, self.count, self.points = name, faces, count, points
        self.embedding, self.skinner, self.vertex_ids = embedding, skinner, vertex_ids
        # a rigid body's: its points relative to its centre of mass (written once) and transform() its
        # 4x4 pose (USD convention: row vectors, [[A^T, 0], [p, 1]]) now
        self.local, self.transform = local, transform


class SceneRun:
    """A built scene: ``model``, ``sim`` (the integrator), ``surfaces`` (one render surface per
    body); ``skinner`` / ``embedding`` / ``surface_vertex_ids`` are a one-body scene's (None without
    [surface] / with it)."""

    def __init__(self, scene: "Scene", model, sim, handle_ids, *, device, precision):
        self.scene, self.model, self.sim = scene, model, sim
        self.device, self.precision = device, precision
        sp = scene.spec
        self.fps = float(sp.output["fps"])
        self.frames = int(sp.output["frames"])
        self.frame = 0
        self.steps_total, self.unconverged = 0, []  # the run's totals (checkpointed; see _account)
        self.resumed_totals = None  # a resumed run: the totals of the frames before it (convergence_summary)
        self._handles = [(h, ids, model.rest_positions[ids].copy()) for h, ids in zip(sp.handle, handle_ids)]
        self._gravity = model.gravity.copy()
        self._forces = model.forces.copy()
        # a simulator may map an embedding to surface points itself (e.g. a reduced one, O(r) per point)
        self._sim_surface_points = getattr(sim, "surface_points", None)
        # one render surface per body (a one-body scene: its one body); the previews see them all
        offsets = model.body_offsets
        self.surfaces = [self._body_surface(b, int(lo), int(hi), device, precision)
                         for b, lo, hi in zip(scene.bodies, offsets[:-1], offsets[1:])]
        starts = np.concatenate([[0], np.cumsum([c.count for c in self.surfaces])])
        self.surface_faces = np.concatenate([c.faces + int(o) for c, o in zip(self.surfaces, starts[:-1])])
        # the one body's surface as attributes (several bodies: None, and the name "bodies")
        one = self.surfaces[0] if len(self.surfaces) == 1 else _RenderSurface("bodies", None, 0, None)
        self.embedding, self.skinner = one.embedding, one.skinner
        self.surface_vertex_ids, self.surface_name = one.vertex_ids, one.name

    def _body_surface(self, b, lo, hi, device, precision) -> "_RenderSurface":
        """Body ``b``'s render surface (its vertices lo..hi-1 of the model): its [surface] embedded in
        its own elements, or its boundary; the USD prim is ``b.surface_prim``."""
        bm = b.own_mesh()
        if getattr(b, "kind", "soft") == "rigid":  # its boundary at p + A X; USD: rest points under a transform
            r = self.model.body_names.index(b.body_name) - (len(self.model.body_names) - len(self.model.rigid.bodies))
            ids, tris = np.unique(np.asarray(bm.boundary_faces(), dtype=np.int64).reshape(-1), return_inverse=True)
            local = self.model.rigid.bodies[r].local_positions[ids]
            ids = ids + lo

            def transform(r=r):
                p, A = self.model.rigid.pose(self.sim.positions(), r)
                M = np.eye(4)
                M[:3, :3], M[3, :3] = np.asarray(A).T, p
                return M

            return _RenderSurface(b.surface_prim, tris.reshape(-1, 3).astype(np.int64), int(ids.size),
                                  lambda: self.sim.vertex_positions()[ids], vertex_ids=ids, local=local,
                                  transform=transform)
        if b.spec.surface is None:
            ids, tris = boundary_surface(bm)
            ids = ids + lo
            return _RenderSurface(b.surface_prim, np.asarray(tris), int(ids.size),
                                  lambda: self._vertex_positions()[ids], vertex_ids=ids)
        from warpfem.skinning import SurfaceSkinner, embed_points_in_mesh, load_surface  # only with a [surface]

        pts, tris = load_surface(b.spec.surface["path"])
        emb = embed_points_in_mesh(np.asarray(pts, dtype=np.float64) + b.offset, bm)  # k weights per point
        if self._sim_surface_points is not None and hi - lo == self.model.num_vertices:
            def points():  # the simulator maps the embedding itself (its one body)
                return np.asarray(self._sim_surface_points(emb), dtype=np.float64)

            return _RenderSurface(b.surface_prim, np.asarray(tris), emb.num_points, points, embedding=emb)
        skinner = SurfaceSkinner(emb, bm, device=device, precision=precision)

        def points():  # x_surface = W x on the device
            return skinner.apply(self.sim.x[lo:hi]).numpy().astype(np.float64)

        return _RenderSurface(b.surface_prim, np.asarray(tris), emb.num_points, points, embedding=emb, skinner=skinner)

    def _vertex_positions(self):
        """Every body's vertices now (rigid ones at p + A X); a simulator without rigid bodies (reduced,
        stiffness warping) has no ``vertex_positions``: its positions are its vertices."""
        f = getattr(self.sim, "vertex_positions", None)
        return f() if f is not None else self.sim.positions()

    def usd_surfaces(self) -> list:
        """The USD prims of the render surfaces: [(name, faces, number of points)] (one per body)."""
        return [(c.name, c.faces, c.count) for c in self.surfaces if c.local is None]

    def usd_rigid_surfaces(self) -> list:
        """The rigid bodies' USD prims: [(name, faces, points relative to the centre of mass)] (a mesh
        under an Xform whose transform moves it)."""
        return [(c.name, c.faces, c.local) for c in self.surfaces if c.local is not None]

    def usd_surface_points(self) -> dict:
        """{prim name: current points} of :meth:`usd_surfaces`."""
        return {c.name: c.points() for c in self.surfaces if c.local is None}

    def usd_transforms(self) -> dict:
        """{prim name: 4x4 pose now} of :meth:`usd_rigid_surfaces`."""
        return {c.name: c.transform() for c in self.surfaces if c.local is not None}

    def usd_volumes(self) -> list:
        """``[output] usd_volume``: [(prim name, tets (m, 4) over the body's own vertices, surface faces,
        first vertex, end vertex)], one per body (a one-body scene: "volume"); corner tets of
        higher-order elements, so the TetMesh shows the element corners' motion."""
        out = []
        offsets = self.model.body_offsets
        for b, lo, hi in zip(self.scene.bodies, offsets[:-1], offsets[1:]):
            if getattr(b, "kind", "soft") == "rigid":  # its Xform moves its surface: no volume to show
                continue
            m = b.own_mesh()
            tets = np.asarray(m.corner_tets(), dtype=np.int64)
            faces = np.asarray(m.boundary_faces(), dtype=np.int64) if m.element.is_linear_tet else None
            out.append((b.volume_prim, tets, faces, int(lo), int(hi)))
        return out

    @property
    def num_surface_points(self) -> int:
        return int(sum(c.count for c in self.surfaces))

    def duration(self, frames=None) -> float:
        """Length of the run (s) over which handles ramp by default."""
        return (self.frames if frames is None else frames) / self.fps

    def surface_points(self) -> np.ndarray:
        """Current render-surface points (p, 3): x_surface = W x on the device (the skinner), or the
        simulator's own ``surface_points(embedding)`` when it has one; without ``[surface]`` the
        boundary vertices' positions. Every body's, concatenated in body order."""
        return np.concatenate([c.points() for c in self.surfaces])

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

    def run(self, *, frames=None, usd=None, states=None, stats=None, progress=None, vtu=None, resume: bool = False,
            checkpoint_every=None):
        """Run ``frames`` output frames (default: the scene's) writing the outputs.

        Frame 0 is the rest state; frames 1..N follow every 1/fps s (static: load fraction k/N).
        ``usd``/``states``/``stats``/``vtu`` default to the scene's [output] (paths relative to the
        current directory). Each output is a :class:`warpfem.io.writers.FrameWriter` (the table
        ``warpfem.io.outputs.OUTPUT_FORMATS``) fed one :class:`warpfem.io.writers.FrameSnapshot` per
        frame. Every stats record carries ``warpfem_version``. ``progress(FrameStats)`` is called after
        each frame.

        Checkpoints: every ``checkpoint_every`` frames (default the scene's ``[output] checkpoint_every``,
        1; 0 = none) and at the last frame, after the frame's outputs, the simulator's whole state and the
        run's go to ``X.checkpoint/`` next to the first output (:class:`warpfem.scenes.checkpoint.Checkpoint`),
        and each output makes its frames so far readable on disk. ``resume=True`` continues from the
        last checkpoint: the outputs keep their frames up to it (later ones are dropped) and the run goes
        on to ``frames``; it raises :class:`warpfem.scenes.checkpoint.ResumeError` when there is nothing
        to resume or the scene's physics changed since (naming the keys).

        On :class:`warpfem.SolveFailed` (or Ctrl-C) the outputs are closed marked incomplete with the
        frames done so far and the exception propagates. An output that cannot be written (full disk,
        folder removed) raises :class:`warpfem.io.writers.OutputWriteError` naming the file and the
        frame; the other outputs are closed with every earlier frame.
        A step that does not converge (``require_convergence`` off) is not a Python warning here:
        each frame with such steps logs one warning line on the ``warpfem.scenes.run`` logger
        (``frame 9: 1 of 4 steps not converged: step 33: ...``); the frames' ``unconverged_steps``
        count them. Returns the list of :class:`FrameStats` of the frames stepped by this call.
        """
        from warpfem.io.outputs import check_output_paths, checkpoint_path, make_writers

        from .checkpoint import Checkpoint

        out = self.scene.spec.output
        total = self.frames if frames is None else int(frames)
        if total < 1:
            raise ValueError(f"frames must be >= 1, got {total}")
        paths = self.scene.output_paths(usd=usd, states=states, stats=stats, vtu=vtu)
        every = int(out.get("checkpoint_every", 1) if checkpoint_every is None else checkpoint_every)
        if every < 0:
            raise ValueError(f"checkpoint_every must be >= 0, got {every}")
        ckpt = checkpoint_path(paths) if (every or resume) else None
        # every output path before anything is written (OutputPathError, a ValueError, names the bad one)
        check_output_paths({**paths, "checkpoint": ckpt})
        checkpoint = Checkpoint(ckpt, self) if ckpt is not None else None
        resume_after = None
        if resume:
            if checkpoint is None:
                from .checkpoint import ResumeError

                raise ResumeError("nothing to resume: the run writes no output (no checkpoint)")
            resume_after = checkpoint.restore(total)
            _logger.info(f"resuming after frame {resume_after} (t = {self.current_time:.6g} s) from {ckpt}")
        writers = make_writers(paths)
        if checkpoint is not None and every:
            writers.append(checkpoint.writer(total))
        info = self._run_info(total, resume_after)
        history = []
        opened, failed = [], []

        def feed(fs):
            # frame 0 (the start, fs None) is not checkpointed: a run stopped before frame 1 starts again
            sync = fs is not None and bool(every) and (self.frame % every == 0 or self.frame == total)
            snap = self._snapshot(fs, sync, info)
            for w in opened:
                self._call(w, failed, w.write, snap)

        try:
            for w in writers:
                self._call(w, failed, w.open, info)
                opened.append(w)
            if resume_after is None:
                feed(None)
            while self.frame < total:
                try:
                    with warnings.catch_warnings():  # reported below, one line per frame
                        from warpfem.solvers.nonlinear import NotConvergedWarning

                        warnings.simplefilter("ignore", NotConvergedWarning)
                        fs = self.step_frame(total_frames=total)
                except Exception as e:
                    stats_of = getattr(e, "stats", None)
                    record = {"frame": self.frame, "converged": False, "error": str(e),
                              "newton_iterations": getattr(stats_of, "newton_iterations", None)}
                    for w in opened:  # the step's error is the one reported
                        try:
                            w.failed(record)
                        except Exception:  # noqa: BLE001
                            failed.append(w)
                    raise
                history.append(fs)
                self._account(fs)
                if fs.unconverged_steps:
                    log_not_converged(fs)
                feed(fs)
                if progress is not None:
                    progress(fs)
        except BaseException as e:
            reason = _incomplete_reason(e, self.frame)
            for w in opened:
                try:
                    w.abandon() if w in failed else w.close(False, reason)
                except Exception as close_error:  # noqa: BLE001 - the first error is the one reported
                    _logger.warning(f"{w.path}: could not be closed: {_one_line(close_error)}")
            raise
        errors = []
        for w in opened:
            try:
                self._call(w, failed, w.close, True, None)
            except Exception as e:  # noqa: BLE001 - close the others, then report the first
                errors.append(e)
        if errors:
            raise errors[0]
        return history

    def _call(self, writer, failed, method, *args):
        """``method(*args)`` of ``writer``; any error becomes an :class:`OutputWriteError` naming the file
        and the frame (and the writer is marked failed: abandoned, not closed)."""
        from warpfem.io.writers import OutputWriteError

        try:
            method(*args)
        except OutputWriteError:
            failed.append(writer)
            raise
        except Exception as e:
            failed.append(writer)
            what = "finish" if method.__name__ == "close" else "open" if method.__name__ == "open" else \
                f"write frame {self.frame} to"
            raise OutputWriteError(f"{writer.label} {writer.path}: cannot {what} it: {_one_line(e)}") from e

    def _account(self, fs):
        """The run's totals (kept in checkpoints): steps, and the frames with unconverged steps."""
        self.steps_total += fs.steps
        if fs.unconverged_steps:
            self.unconverged.append((fs.frame, fs.unconverged_steps, float(fs.worst_residual)))

    def _run_info(self, total, resume_after):
        """The :class:`warpfem.io.writers.RunInfo` of this run (surfaces, volumes, colliders, blocks)."""
        from warpfem.io.vtu import warpfem_version
        from warpfem.io.writers import RunInfo

        out = self.scene.spec.output
        volumes = self.usd_volumes() if out.get("usd_volume") else []
        colliders = []
        if getattr(self.sim, "contact", None) is not None:  # the contact modules only when there is contact
            from warpfem.contact.scene import collider_prims

            colliders = collider_prims(self.sim, 2.0 * float(np.ptp(self.model.rest_positions, axis=0).max()))
        self._collider_points = [(name, pts) for name, _, pts in colliders]
        self._volumes = volumes
        offs = self.model.body_offsets  # rest / positions hold every body's vertices in body order
        extra = {}
        if self.scene.named_bodies:  # the states name the bodies of a [[body]] scene
            extra = {"body_offsets": np.asarray(offs, dtype=np.int64), "body_names": np.array(self.model.body_names)}
        blocks = [(b.block_name, b.own_mesh().elements, b.own_mesh().element_type, int(lo), int(hi))
                  if b.own_mesh().num_elements else  # a rigid body given by its surface: its triangles
                  (b.block_name, b.own_mesh().boundary_faces(), "tri3", int(lo), int(hi))
                  for b, lo, hi in zip(self.scene.bodies, offs[:-1], offs[1:])]
        rest = getattr(self.model, "vertex_rest_positions", self.model.rest_positions)  # every body's vertices
        return RunInfo(fps=self.fps, total_frames=total, rest=rest, resume_after=resume_after,
                       version=warpfem_version(), surfaces=self.usd_surfaces(), volumes=volumes,
                       rigid_surfaces=self.usd_rigid_surfaces(),
                       colliders=[(name, faces, len(pts())) for name, faces, pts in colliders], blocks=blocks,
                       states_extra=extra, options=dict(out))

    def _snapshot(self, fs, sync, info):
        """The :class:`warpfem.io.writers.FrameSnapshot` of the current state (``fs``: its FrameStats, None
        for frame 0)."""
        from warpfem.io.writers import FrameSnapshot

        snap = None

        def positions():  # every body's vertices (rigid ones at p + A X), in body order
            return self._vertex_positions()

        def surface_points():
            pts = self.usd_surface_points()
            if self._volumes:
                x = snap.positions
                pts.update({name: x[lo:hi] for name, _, _, lo, hi in self._volumes})
            pts.update({name: p() for name, p in self._collider_points})
            return pts

        velocities = getattr(self.sim, "vertex_velocities", self.sim.velocities)  # as _vertex_positions
        snap = FrameSnapshot(self.frame, self._time() if fs is None else fs.time, stats=fs, sync=sync,
                             providers={"positions": positions, "velocities": velocities,
                                        "surface_points": surface_points, "transforms": self.usd_transforms,
                                        "element_fields": lambda: self.element_fields(snap.positions)})
        return snap

    def element_fields(self, x=None) -> list:
        """Per-element ``J``, ``cauchy_stress`` and ``von_mises`` at positions x (default current), one
        dict per body (one for a one-body scene), from the simulator's own ``stresses(x)``
        (:func:`warpfem.io.element_stress_fields`)."""
        from warpfem.io.vtu import deformation_gradients, element_stress_fields_by_body

        x = self._vertex_positions() if x is None else np.asarray(x, dtype=np.float64)
        stresses = getattr(self.sim, "stresses", None)  # a simulator without: the material at F (one body)
        xq = x
        if getattr(self.model, "rigid", None) is not None:  # the unknown: soft vertices are its first rows
            xq = self.sim.positions()
            xq[:self.model.rigid.num_soft] = x[:self.model.rigid.num_soft]
        P = stresses(xq) if stresses is not None else self.model.material.pk1(deformation_gradients(self.model, x))
        return element_stress_fields_by_body(self.model, x, P)

    @staticmethod
    def convergence_summary(history, prior=None) -> dict:
        """What a run's frames say about convergence: ``steps`` (all), ``unconverged_steps``,
        ``unconverged_frames`` (the frame numbers with at least one) and ``worst`` ((frame, relative
        gradient) of the unconverged step farthest from the tolerance, or None). ``prior``: the
        frames before ``history`` of a resumed run (:attr:`resumed_totals`: steps and [(frame,
        unconverged steps, worst)])."""
        bad = [(fs.frame, fs.unconverged_steps, float(fs.worst_residual)) for fs in history if fs.unconverged_steps]
        steps = int(sum(fs.steps for fs in history))
        if prior:
            steps += int(prior["steps"])
            bad = [tuple(b) for b in prior["unconverged"]] + bad
        worst = None
        if bad:
            b = max(bad, key=lambda f: (f[2] if f[2] == f[2] else float("inf")))
            worst = (b[0], float(b[2]))
        return {"steps": steps, "unconverged_steps": int(sum(b[1] for b in bad)),
                "unconverged_frames": [b[0] for b in bad], "worst": worst}

    @property
    def current_time(self) -> float:
        """Simulated time of the current state (s)."""
        return self._time()

    def _time(self):
        """Simulated time of the current state (s): the integrator's clock, or frame / fps (static)."""
        if self.scene.dynamic and hasattr(self.sim, "time"):
            return float(self.sim.time)
        return self.frame / self.fps
