"""Checkpoints of a scene run and ``--resume``.

A run's checkpoint is one file next to its first output (``out/beam.usda`` ->
``out/beam.checkpoint.npz``, :func:`warpfem.io.outputs.checkpoint_path`), written by
:func:`warpfem.save_state` (a temporary file synced to disk, then renamed over the previous one: a
process killed at any moment leaves the previous or the new checkpoint, never a mixture). It holds
the simulator's whole state (positions, velocities, integrator history, contact and friction state,
adaptive stiffness, the linear solver's choices, time) and, in its fingerprint, the scene's physics
keys (:func:`physics_keys`) and the run's own state under ``"run"``: the frame, the frame count,
the steps so far and the frames with unconverged steps. It is written after the frame's outputs,
so every output already holds the checkpointed frame.

:meth:`Checkpoint.restore` loads it back into a freshly built run (refused, naming the keys, when
the physics changed); the outputs are then cut back to its frame by their writers
(``RunInfo.resume_after``).
"""

from __future__ import annotations

import json
import os

from warpfem.io.writers import FrameWriter

__all__ = ["Checkpoint", "ResumeError", "NothingToResume", "physics_keys", "SOLVER_KEYS"]

#: ``[integrator]`` keys that control the solver, not the physics: they may change between a
#: checkpoint and its resume (e.g. more Newton iterations after a failed step).
SOLVER_KEYS = frozenset({"tol", "atol", "cg_tol", "max_iters", "max_cg_iters", "require_convergence",
                         "linear_solver", "hessian_projection", "project_hessian"})


class ResumeError(ValueError):
    """A run that cannot be resumed (the scene's physics changed; a damaged checkpoint): one line."""


class NothingToResume(ResumeError):
    """``--resume`` without a checkpoint (``complete`` False), or with a run that already has every
    frame asked for (``complete`` True)."""

    def __init__(self, message, *, complete: bool = False):
        super().__init__(message)
        self.complete = complete


def _plain(v):
    """A value as JSON data (numpy arrays and scalars as lists and numbers, specs as dicts)."""
    import dataclasses

    import numpy as np

    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return {f.name: _plain(getattr(v, f.name)) for f in dataclasses.fields(v)}
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    return v


def _flatten(prefix, value, out):
    if isinstance(value, dict) and value:
        for k, v in value.items():
            _flatten(f"{prefix}.{k}" if prefix else str(k), v, out)
    elif isinstance(value, list) and value and all(isinstance(x, dict) for x in value):
        for i, v in enumerate(value):
            _flatten(f"{prefix} #{i + 1}", v, out)
    else:
        out[prefix] = json.dumps(value, sort_keys=True)


def physics_keys(run, total_frames: int) -> dict:
    """{key: value as JSON text} of everything in the scene that decides the numbers of a frame: every
    section but ``[output]`` and the render ``[surface]``, without the solver controls of
    :data:`SOLVER_KEYS` and the scene's name; plus ``[output].fps``, the precision, and the frame
    count where it moves things (a static scene's load fraction, a handle or a moving collider
    without ``ramp_time``, which ramp over the run)."""
    sp = run.scene.spec
    out = {}
    for name in ("top", "mesh", "material", "integrator", "subspace", "contact", "fixed", "handle", "force",
                 "traction", "collider", "extra", "bodies"):
        value = _plain(getattr(sp, name))
        if name == "top":
            value = {k: v for k, v in value.items() if k not in ("name", "description")}
            _flatten("", value, out)
            continue
        if name == "integrator":
            value = {k: v for k, v in value.items() if k not in SOLVER_KEYS}
        if name == "bodies":
            for b in value:  # a body's own spec: its physics sections only
                spec = b.get("spec") or {}
                b["spec"] = {k: spec.get(k) for k in ("mesh", "material", "fixed", "handle", "force", "traction")}
        label = {"fixed": "[[fixed]]", "handle": "[[handle]]", "force": "[[force]]", "traction": "[[traction]]",
                 "collider": "[[collider]]", "bodies": "[[body]]"}.get(name, f"[{name}]")
        if value in (None, {}, []):
            out[label] = json.dumps(value)
        else:
            _flatten(label, value, out)
    out["[output].fps"] = json.dumps(float(sp.output["fps"]))
    out["precision"] = json.dumps(run.precision)
    from . import INTEGRATORS

    dynamic = INTEGRATORS[run.scene.integrator_type].dynamic
    if not dynamic or any(not h.get("ramp_time") for h in sp.handle):
        out["frames (handles and static loads ramp over the run)"] = json.dumps(int(total_frames))
    moving = [c for c in sp.collider if (c.get("translation") is not None and any(c["translation"]))
              or c.get("rotation_angle")]
    if any(c.get("ramp_time") is None for c in moving):
        out["[output].frames (moving colliders ramp over it)"] = json.dumps(int(sp.output["frames"]))
    return out


class Checkpoint:
    """The checkpoint file of a :class:`warpfem.scenes.SceneRun` (see the module's documentation)."""

    def __init__(self, path, run):
        self.path = os.fspath(path)
        self.run = run
        self._keys = {}  # physics keys per frame count (computed once)

    def physics(self, total_frames: int) -> dict:
        if total_frames not in self._keys:
            self._keys[total_frames] = physics_keys(self.run, total_frames)
        return self._keys[total_frames]

    def save(self, total_frames: int) -> None:
        """Checkpoint the run as it is now (after its frame ``run.frame``)."""
        import warpfem

        run = self.run
        warpfem.save_state(run.sim, self.path, fingerprint={**self.physics(total_frames), "run": {
            "frame": int(run.frame), "time": float(run.current_time), "frames": int(total_frames),
            "steps": int(run.steps_total), "unconverged": [list(u) for u in run.unconverged],
            "warpfem_version": warpfem.__version__}})

    def restore(self, total_frames: int) -> int:
        """Load the checkpoint into the run (refused when the physics changed); returns its frame."""
        from warpfem.io.checkpoint import read_state

        run = self.run
        if not os.path.exists(self.path):
            raise NothingToResume(f"nothing to resume: no checkpoint {self.path}")
        try:
            state, fp = read_state(self.path)
        except (ValueError, OSError) as e:  # CheckpointError (a ValueError): damaged, another format
            raise ResumeError(f"cannot resume: {e}") from None
        fp = dict(fp or {})
        rec = fp.pop("run", None)
        if not isinstance(rec, dict) or "frame" not in rec:
            raise ResumeError(f"cannot resume: {self.path} is not a scene run's checkpoint (no run record)")
        k = int(rec["frame"])
        if k >= total_frames:
            raise NothingToResume(f"nothing to resume: {self.path} is at frame {k}, the run has {total_frames} "
                                  f"frames (ask for more with --frames)", complete=True)
        keys = self.physics(total_frames)
        differ = sorted(set(fp) ^ set(keys) | {key for key in set(fp) & set(keys) if fp[key] != keys[key]})
        if differ:
            shown = ", ".join(f"{key} ({_shown(fp.get(key))} -> {_shown(keys.get(key))})" for key in differ[:6])
            more = f" and {len(differ) - 6} more" if len(differ) > 6 else ""
            raise ResumeError(f"cannot resume from {self.path} (frame {k}): the scene's physics changed since: "
                              f"{shown}{more}")
        try:
            run.sim.load_state_dict(state)
        except ValueError as e:  # CheckpointError: the simulator is left as it was
            raise ResumeError(f"cannot resume from {self.path} (frame {k}): {e}") from None
        run.frame = k
        run.steps_total = int(rec.get("steps", 0))
        run.unconverged = [tuple(u) for u in rec.get("unconverged", [])]
        run.resumed_totals = {"steps": run.steps_total, "unconverged": list(run.unconverged)}
        return k

    def writer(self, total_frames: int) -> "CheckpointOutput":
        """The run's writer that checkpoints the frames it is told to (``snapshot.sync``)."""
        return CheckpointOutput(self, total_frames)


def _shown(text):
    if text is None:
        return "absent"
    return text if len(text) <= 40 else text[:37] + "..."


class CheckpointOutput(FrameWriter):
    """The checkpoints as a run output: a snapshot with ``sync`` (every ``[output] checkpoint_every``
    frames and the last) is checkpointed; it comes after every other writer of the run."""

    label = "checkpoint"

    def __init__(self, checkpoint: Checkpoint, total_frames: int):
        super().__init__(checkpoint.path)
        self.checkpoint, self.total = checkpoint, int(total_frames)

    def open(self, run):
        pass

    def write(self, snapshot):
        if snapshot.sync:
            self.checkpoint.save(self.total)

    def close(self, complete, reason=None):
        pass
