"""A trained subspace (basis + cubature), its npz cache, and ``train_subspace`` (the train entry)."""

from __future__ import annotations

import hashlib
import json
import logging
import os
from dataclasses import dataclass, field

import numpy as np

from warpfem.reduced.basis import Basis, build_basis, snapshot_displacements
from warpfem.reduced.cubature import Cubature, train_cubature
from warpfem.reduced.lifting import Lifting, build_lifting, handle_signature

FORMAT_VERSION = 2


class SubspaceMismatch(ValueError):
    """A saved subspace does not belong to the model (mesh, fixed vertices or material differ)."""


def mesh_hash(model) -> str:
    """sha256 of rest positions (float64), connectivity (int64) and the fixed mask: anything that
    changes the basis changes the hash."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(model.rest_positions, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(model.quadrature.elements, dtype=np.int64).tobytes())
    h.update(np.ascontiguousarray(model.fixed, dtype=np.uint8).tobytes())
    return h.hexdigest()


def material_parameters(model) -> dict:
    m = model.material
    return {"name": str(getattr(m, "name", type(m).__name__)), "kind": int(m.kind),
            "youngs_modulus": float(getattr(m, "youngs_modulus", float("nan"))),
            "poisson_ratio": float(getattr(m, "poisson_ratio", float("nan"))),
            "density": float(m.density), "mass_matrix": str(model.mass_matrix_kind)}


@dataclass
class Subspace:
    """Basis + cubature + the model fingerprint they were trained for.

    ``report`` holds the numbers a user wants to see: modes, modal frequencies (Hz), cubature
    points, training / validation error, training times.
    """

    basis: Basis
    cubature: Cubature
    mesh_hash: str
    material: dict
    settings: dict = field(default_factory=dict)
    report: dict = field(default_factory=dict)
    lifting: Lifting | None = None

    @property
    def U(self) -> np.ndarray:
        return self.basis.U

    @property
    def num_handle_coords(self) -> int:
        return 0 if self.lifting is None else self.lifting.size

    def check(self, model, *, source: str = "subspace", handles=None) -> None:
        """Raise :class:`SubspaceMismatch` naming what differs when this subspace is not for ``model``
        (and, with ``handles`` = [(ids, components)], for those kinematic handles)."""
        if handles is not None:
            want = handle_signature(handles) if handles else None
            have = self.lifting.signature if self.lifting is not None and self.lifting.size else None
            if want != have:
                what = (f"{len(self.lifting.groups)} handle(s)" if have else "no handles")
                raise SubspaceMismatch(f"{source} was trained for {what} but the scene has "
                                       f"{len(handles) if handles else 'no'} handle(s) with other vertices or "
                                       "components; retrain it (warpfem train)")
        h = mesh_hash(model)
        if h != self.mesh_hash:
            raise SubspaceMismatch(f"{source} was trained for a different mesh or fixed vertices "
                                   f"(hash {self.mesh_hash[:12]}..., this model {h[:12]}...); retrain it (warpfem train)")
        mat = material_parameters(model)
        diff = [k for k in mat if k in self.material and mat[k] != self.material[k]
                and not (isinstance(mat[k], float) and np.isnan(mat[k]) and np.isnan(self.material[k]))]
        if diff:
            detail = ", ".join(f"{k}: saved {self.material[k]!r} vs model {mat[k]!r}" for k in diff)
            raise SubspaceMismatch(f"{source} was trained for a different material ({detail}); retrain it (warpfem train)")
        if self.U.shape[0] != 3 * model.num_vertices:
            raise SubspaceMismatch(f"{source} basis has {self.U.shape[0]} rows, model needs {3 * model.num_vertices}")

    def save(self, path) -> None:
        """Write everything to one npz (``path``)."""
        b, c = self.basis, self.cubature
        meta = {"format": FORMAT_VERSION, "mesh_hash": self.mesh_hash, "material": self.material,
                "settings": self.settings, "report": self.report, "num_rigid": b.num_rigid,
                "handles": [] if self.lifting is None else
                [{"ids": g[0].tolist(), "components": g[1], "first": int(g[3]), "num_functions": int(g[2].shape[1]),
                  **({"rotation_order": int(self.lifting.rotation[i][0]),
                      "rotation_centre": [float(v) for v in self.lifting.rotation[i][1]]}
                     if self.lifting._rotation_of(i) is not None else {})}
                 for i, g in enumerate(self.lifting.groups)],
                "modal_derivatives": b.modal_derivatives, "basis_info": b.info,
                "cubature": {"training_error": c.training_error, "validation_error": c.validation_error,
                             "training_seconds": c.training_seconds, "tolerance": c.tolerance,
                             "max_points": c.max_points, "seed": c.seed, "reached_tolerance": c.reached_tolerance,
                             "num_validation_poses": c.num_validation_poses}}
        path = os.fspath(path)
        tmp = path + ".tmp.npz"
        np.savez(tmp, U=b.U, linear_frequencies=b.linear_frequencies, frequencies=b.frequencies,
                 cubature_elements=c.elements, cubature_weights=c.weights, training_poses=c.training_poses,
                 lifting=np.zeros((b.U.shape[0], 0)) if self.lifting is None else self.lifting.L,
                 lifting_functions=np.zeros((0, 0)) if self.lifting is None or not self.lifting.groups
                 else np.vstack([np.pad(g[2], ((0, 0), (0, 4 - g[2].shape[1]))) for g in self.lifting.groups]),
                 meta=np.array(json.dumps(meta)))
        os.replace(tmp, path)


def load_subspace(path, model=None, *, handles=None) -> Subspace:
    """Read a subspace npz; with ``model`` given, raise :class:`SubspaceMismatch` if it does not match
    (with ``handles`` = [(ids, components), ...] also when it was trained for other handles)."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"subspace cache {path!r} not found; create it with train_subspace / `warpfem train`")
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            arrays = {k: z[k] for k in z.files if k != "meta"}
    except (OSError, ValueError, KeyError) as exc:
        raise SubspaceMismatch(f"{path!r} is not a warpfem subspace file ({exc})") from exc
    if meta.get("format") != FORMAT_VERSION:
        raise SubspaceMismatch(f"{path!r} has format {meta.get('format')!r}, expected {FORMAT_VERSION}; retrain it")
    cm = meta["cubature"]
    basis = Basis(U=arrays["U"], linear_frequencies=arrays["linear_frequencies"], frequencies=arrays["frequencies"],
                  num_rigid=int(meta["num_rigid"]), modal_derivatives=bool(meta["modal_derivatives"]),
                  info=meta.get("basis_info", {}))
    cub = Cubature(elements=arrays["cubature_elements"], weights=arrays["cubature_weights"],
                   training_error=cm["training_error"], validation_error=cm["validation_error"],
                   training_seconds=cm["training_seconds"], training_poses=arrays["training_poses"],
                   tolerance=cm["tolerance"], max_points=cm["max_points"], seed=cm["seed"],
                   reached_tolerance=cm["reached_tolerance"], num_validation_poses=int(cm.get("num_validation_poses", 0)))
    lifting = None
    if meta.get("handles"):
        groups, row, rotation = [], 0, []
        Qs = arrays["lifting_functions"]
        for h in meta["handles"]:
            ids = np.asarray(h["ids"], dtype=np.int64)
            groups.append((ids, h["components"], Qs[row:row + len(ids), :int(h["num_functions"])], int(h["first"])))
            rotation.append((int(h["rotation_order"]), np.asarray(h["rotation_centre"], dtype=np.float64))
                            if h.get("rotation_order") else None)
            row += len(ids)
        lifting = Lifting(arrays["lifting"], groups, rotation if any(r is not None for r in rotation) else None)
    sub = Subspace(basis, cub, meta["mesh_hash"], meta["material"], meta.get("settings", {}), meta.get("report", {}),
                   lifting)
    if model is not None:
        sub.check(model, source=f"subspace cache {path!r}", handles=handles)
        if lifting is not None:
            lifting.bind(model.rest_positions)
    return sub


def train_subspace(model, *, modes: int = 20, modal_derivatives: bool = True, cubature_tolerance: float = 0.05,
                   max_cubature_points: int = 200, seed: int = 0, cache=None, retrain: bool = False,
                   num_training_poses: int = 100, num_validation_poses: int = 30, candidates: int = 256,
                   pose_amplitude: float = 0.1, snapshots=None, pose_source: str | None = None, handles=None,
                   handle_targets_at=None, load_response: bool = False, pod_modes: int = 0,
                   rotation_lifting: int = 0, verbose: bool = False) -> Subspace:
    """Build the basis and train the cubature for ``model`` (the ``warpfem train`` entry point).

    Args:
        modes: r, the subspace dimension.
        modal_derivatives: add Barbic-James modal derivatives (needs fixed vertices) before mass-PCA.
        cubature_tolerance: target relative training force error (0..1).
        max_cubature_points: cap on cubature points.
        seed: seeds training poses and candidate sampling (deterministic).
        cache: npz path. If it exists, matches the model and was trained with the same settings it
            is loaded instead of retraining; otherwise (or with ``retrain=True``) training runs and
            the file is (over)written. ``report["cache"]`` says which happened and why.
        num_training_poses, num_validation_poses, candidates, pose_amplitude, snapshots, pose_source:
            see :func:`warpfem.reduced.cubature.train_cubature`.
        load_response: make the linear static response to the loads, K^-1 f_ext, a basis column
            (see :func:`warpfem.reduced.basis.build_basis`).
        pod_modes: k > 0 adds k basis columns from the ``snapshots`` (mass-weighted POD of their
            displacements outside the modal span, handle motion removed; see
            :func:`warpfem.reduced.basis.pod_columns`): r = ``modes`` + k.
        handles: kinematic handles [(vertex ids, components), ...], fixed in ``model``: a lifting
            field (:mod:`warpfem.reduced.lifting`) is built so the reduced simulator can move them.
        rotation_lifting: J >= 2 makes the lifting of handles with all three components
            rotation-aware (:mod:`warpfem.reduced.lifting`: the rotation angle is interpolated into
            the body instead of the displacement, series order J); 0 = the linear elastic extension.
        handle_targets_at: ``f(fraction in [0, 1]) -> [targets (h_g, 3) per handle]``, the handle
            motion random training poses sample (64 fractions); default: handles at rest.
        verbose: log the training report (:func:`format_report`) at INFO level on this module's logger.
    """
    handles = [(np.unique(np.asarray(ids, dtype=np.int64)), str(c)) for ids, c in (handles or [])]
    settings = {"modes": int(modes), "modal_derivatives": bool(modal_derivatives),
                "cubature_tolerance": float(cubature_tolerance), "max_cubature_points": int(max_cubature_points),
                "seed": int(seed), "num_training_poses": int(num_training_poses),
                "num_validation_poses": int(num_validation_poses), "candidates": int(candidates),
                "pose_amplitude": float(pose_amplitude), "snapshots": 0 if snapshots is None else len(snapshots),
                "pose_source": pose_source or ("random" if snapshots is None else "random+snapshots"),
                "handles": handle_signature(handles) if handles else None}
    if load_response:
        settings["load_response"] = True
    if int(pod_modes) != pod_modes or pod_modes < 0:
        raise ValueError(f"pod_modes must be a non-negative integer, got {pod_modes!r}")
    if pod_modes:
        if snapshots is None or len(snapshots) < 2:
            raise ValueError("pod_modes > 0 needs snapshots (full-mesh positions of a full run) to take the POD of")
        settings["pod_modes"] = int(pod_modes)
    if rotation_lifting:
        settings["rotation_lifting"] = int(rotation_lifting)
    why = "no cache given"
    if cache is not None and not retrain:
        if os.path.exists(cache):
            try:
                sub = load_subspace(cache, model, handles=handles)
                if sub.settings == settings:
                    sub.report["cache"] = f"loaded {os.fspath(cache)!r}"
                    return sub
                why = "settings changed"
            except SubspaceMismatch as exc:
                why = str(exc)
        else:
            why = "cache file did not exist"
    elif retrain:
        why = "retrain requested"
    import time

    from warpfem.reduced.basis import _full_simulator

    sim = _full_simulator(model)
    t0 = time.perf_counter()
    lifting, handle_coords = None, None
    if handles:
        lifting = build_lifting(model, handles, sim=sim, rotation_order=int(rotation_lifting))
        if handle_targets_at is not None:
            handle_coords = np.array([lifting.coords_from_targets(handle_targets_at(f)) for f in np.linspace(0, 1, 64)])
    D = snapshot_displacements(model, snapshots, lifting) if pod_modes else None
    basis = build_basis(model, modes=modes, modal_derivatives_=modal_derivatives, load_response=load_response, sim=sim,
                        snapshot_displacements_=D, pod_modes=int(pod_modes))
    t_basis = time.perf_counter() - t0
    cub = train_cubature(model, basis.U, tolerance=cubature_tolerance, max_points=max_cubature_points, seed=seed,
                         num_training_poses=num_training_poses, num_validation_poses=num_validation_poses,
                         candidates=candidates, amplitude=pose_amplitude, snapshots=snapshots,
                         pose_source=pose_source, lifting=lifting, handle_coords=handle_coords, sim=sim)
    report = {
        "modes": basis.size,
        "pod_modes": int(basis.info.get("pod_modes", 0)),
        "num_rigid": basis.num_rigid,
        "modal_derivatives": basis.modal_derivatives,
        "linear_frequencies_hz": (basis.linear_frequencies / (2 * np.pi)).tolist(),
        "basis_frequencies_hz": (basis.frequencies / (2 * np.pi)).tolist(),
        "handles": 0 if lifting is None else len(lifting.groups),
        "handle_coords": 0 if lifting is None else lifting.size,
        "pose_source": settings["pose_source"],
        "training_poses": int(len(cub.training_poses)),
        "cubature_points": cub.num_points,
        "num_elements": model.quadrature.num_elements,
        "training_error": cub.training_error,
        "validation_error": cub.validation_error,
        "validation_poses": int(cub.num_validation_poses),
        "reached_tolerance": cub.reached_tolerance,
        "basis_seconds": t_basis,
        "cubature_seconds": cub.training_seconds,
        "cache": f"trained ({why})",
    }
    sub = Subspace(basis, cub, mesh_hash(model), material_parameters(model), settings, report, lifting)
    if cache is not None:
        sub.save(cache)
        report["cache"] += f", saved to {os.fspath(cache)!r}"
    if verbose:
        logging.getLogger(__name__).info("%s", format_report(report))
    return sub


def format_report(report: dict) -> str:
    """Human-readable training summary."""
    f = report.get("linear_frequencies_hz", [])
    pod = int(report.get("pod_modes", 0) or 0)
    lines = [f"subspace: r = {report.get('modes')} ({report.get('num_rigid', 0)} rigid"
             + (f", {pod} POD columns from the training run" if pod else "")
             + f"), modal derivatives: {report.get('modal_derivatives')}",
             "linear modal frequencies (Hz): " + ", ".join(f"{x:.4g}" for x in f[:10]) + (" ..." if len(f) > 10 else ""),
             *([f"handles: {report['handles']} (lifting field, {report.get('handle_coords')} handle coordinates)"]
               if report.get("handles") else []),
             f"training poses: {report.get('training_poses', '?')} ({report.get('pose_source', 'random')})",
             f"cubature: {report.get('cubature_points')} of {report.get('num_elements')} elements, training error "
             f"{report.get('training_error', float('nan')):.3g}, validation error {report.get('validation_error', float('nan')):.3g}"
             f"{'' if report.get('reached_tolerance', True) else ' (point cap reached before the tolerance)'}",
             *([] if "training_items" in report else  # train_scene itemises every time below
               [f"time: basis {report.get('basis_seconds', 0):.2f} s, cubature {report.get('cubature_seconds', 0):.2f} s"
                + (f", full-simulation snapshots {report['snapshot_seconds']:.2f} s" if "snapshot_seconds" in report
                   else "")]),
             f"cache: {report.get('cache')}"]
    if "training_items" in report:
        items = report["training_items"]
        lines.append(f"training cost: {report['training_seconds']:.1f} s = "
                     + " + ".join(f"{k} {v:.1f} s" for k, v in items.items())
                     + f" ({report.get('full_steps', 0)} full step(s)"
                     + (f"; {report['kernel_load_seconds']:.1f} s of it loading Warp kernels in the first frames, "
                        "once per process" if report.get("kernel_load_seconds", 0) >= 0.05 else "") + ")")
    elif "training_seconds" in report:  # a cache written before the itemised report
        lines.append(f"training cost: {report['training_seconds']:.1f} s including {report.get('full_steps', 0)} full step(s)")
    if "replay_tip_error" in report:
        lines.append(f"reduced replay of the training run: tip error {report['replay_tip_error']:.3g} of its peak, "
                     f"RMS error {report['replay_rms_error']:.3g} of the size (in-sample: the basis saw this run)")
    b = report.get("budget")
    if b and b.get("max_error"):
        at = b.get("attempts") or []
        if not b.get("checked"):
            lines.append(f"error budget: [subspace] max_error = {b['max_error']:g} not checked (training = \"random\" "
                         "has no training run to replay)")
        elif at:
            tried = ", ".join(f"{a['pod_modes']} POD: {100 * a['rms_error']:.2g} %" for a in at)
            lines.append(f"error budget: replay RMS error {100 * at[-1]['rms_error']:.2g} % "
                         f"{'<=' if b.get('met') else '>'} max_error {100 * b['max_error']:.2g} % with r = {at[-1]['r']}"
                         + (f" ({at[-1]['pod_modes']} POD columns chosen; tried {tried})" if len(at) > 1
                            else " (the scene's sizes)"))
    if "predicted_speedup" in report:
        be = report.get("break_even_frames")
        lines.append(f"predicted: reduced step {1e3 * report['reduced_step_seconds']:.3g} ms vs full "
                     f"{1e3 * report['full_step_seconds']:.4g} ms, {report['predicted_speedup']:.0f}x faster per step; "
                     + (f"training + reduced run is cheaper than a full run for scenes longer than {be} frames "
                        f"({report.get('break_even_seconds', report.get('training_seconds', 0.0)):.1f} s of training "
                        "beyond what a full run also pays (set-up, kernel loading), over the time saved per frame)"
                        if be is not None else "no break-even (the reduced step is not faster here)"))
    return "\n".join(lines)
