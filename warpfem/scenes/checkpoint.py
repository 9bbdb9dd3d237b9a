"""Checkpoints of a scene run and ``--resume``.

A run's checkpoints live in one folder next to its first output (``out/beam.usda`` ->
``out/beam.checkpoint/``, :func:`warpfem.io.outputs.checkpoint_directory`)::

    checkpoint.json   the commit record: frame, time, the state file, the run's totals, the scene's
                      physics keys and precision, the warpfem version
    state_0.npz       the simulator's whole state (warpfem.save_state), written in turn with
    state_1.npz       the other slot, so the state named by checkpoint.json is never being written

A checkpoint is written after the frame's outputs: the new state goes to the slot that
``checkpoint.json`` does not name, then ``checkpoint.json`` is replaced atomically (a temporary file
and a rename). A process killed at any moment therefore leaves the previous or the new checkpoint,
never a mixture, and every output already holds the checkpointed frame.

:meth:`Checkpoint.restore` loads it back: the simulator's state (positions, velocities, integrator
history, contact and friction state, adaptive stiffness, time, ...) and the run's frame index and
totals; the outputs are then cut back to that frame by their writers (``RunInfo.resume_after``).
"""

from __future__ import annotations

import json
import os

from warpfem.io.writers import FrameWriter

__all__ = ["Checkpoint", "ResumeError", "NothingToResume", "physics_keys", "SOLVER_KEYS"]

FORMAT = 1

#: ``[integrator]`` keys that control the solver, not the physics: they may change between a
#: checkpoint and its resume (e.g. more Newton iterations after a failed step).
SOLVER_KEYS = frozenset({"tol", "atol", "cg_tol", "max_iters", "max_cg_iters", "require_convergence",
                         "linear_solver", "hessian_projection", "project_hessian"})


class ResumeError(ValueError):
    """A run that cannot be resumed (the scene's physics changed; a damaged checkpoint): one line."""


class NothingToResume(ResumeError):
    """``--resume`` without a checkpoint, or with a run that already has every frame asked for."""


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


def _write_json_atomic(path, data):
    tmp = path + ".partial"
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump(data, f)
        f.write("\n")
    os.replace(tmp, path)


class Checkpoint:
    """The checkpoint folder of a :class:`warpfem.scenes.SceneRun` (see the module's documentation)."""

    def __init__(self, folder, run):
        self.folder = os.fspath(folder)
        self.run = run
        self.record_path = os.path.join(self.folder, "checkpoint.json")

    def read(self) -> dict | None:
        """The commit record, or None when there is none."""
        try:
            with open(self.record_path, encoding="utf-8") as f:
                rec = json.load(f)
        except FileNotFoundError:
            return None
        except (OSError, ValueError) as e:
            raise ResumeError(f"{self.record_path}: cannot read the checkpoint: {e}") from None
        if rec.get("format") != FORMAT:
            raise ResumeError(f"{self.record_path}: checkpoint format {rec.get('format')!r}, expected {FORMAT}")
        return rec

    def save(self, total_frames: int) -> None:
        """Checkpoint the run as it is now (after its frame ``run.frame``)."""
        import warpfem

        run = self.run
        os.makedirs(self.folder, exist_ok=True)
        rec = self.read() if os.path.exists(self.record_path) else None
        slot = "state_1.npz" if rec is not None and rec.get("state") == "state_0.npz" else "state_0.npz"
        keys = physics_keys(run, total_frames)
        warpfem.save_state(run.sim, os.path.join(self.folder, slot), fingerprint=keys)
        _write_json_atomic(self.record_path, {
            "format": FORMAT, "frame": int(run.frame), "time": float(run.current_time), "state": slot,
            "frames": int(total_frames), "steps": int(run.steps_total),
            "unconverged": [list(u) for u in run.unconverged], "physics": keys,
            "warpfem_version": warpfem.__version__})

    def restore(self, total_frames: int) -> int:
        """Load the last checkpoint into the run (refused when the physics changed); returns its frame."""
        import warpfem

        run = self.run
        rec = self.read()
        if rec is None:
            raise NothingToResume(f"nothing to resume: no checkpoint in {self.folder}")
        k = int(rec["frame"])
        if k >= total_frames:
            raise NothingToResume(f"nothing to resume: {self.folder} is at frame {k}, the run has {total_frames} "
                                  f"frames (ask for more with --frames)")
        keys = physics_keys(run, total_frames)
        old = rec.get("physics", {})
        differ = sorted(set(old) ^ set(keys) | {key for key in set(old) & set(keys) if old[key] != keys[key]})
        if differ:
            shown = ", ".join(f"{key} ({_shown(old.get(key))} -> {_shown(keys.get(key))})" for key in differ[:6])
            more = f" and {len(differ) - 6} more" if len(differ) > 6 else ""
            raise ResumeError(f"cannot resume from {self.folder} (frame {k}): the scene's physics changed since: "
                              f"{shown}{more}")
        try:
            warpfem.load_state(run.sim, os.path.join(self.folder, rec["state"]), expect_fingerprint=keys)
        except (ValueError, OSError) as e:  # CheckpointError (a ValueError), a missing or damaged file
            raise ResumeError(f"cannot resume from {self.folder} (frame {k}): {e}") from None
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
        super().__init__(checkpoint.record_path)
        self.checkpoint, self.total = checkpoint, int(total_frames)

    def open(self, run):
        pass

    def write(self, snapshot):
        if snapshot.sync:
            self.checkpoint.save(self.total)

    def close(self, complete, reason=None):
        pass
