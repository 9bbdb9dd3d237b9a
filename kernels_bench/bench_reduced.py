"""Reduced (cubature) vs full backward Euler on the cantilever beam and the Stanford bunny (An, Kim & James 2008, optimized cubature).

For each object, r in {10, 20, 40} (modal derivatives on; by default the load-response column
K^-1 f_ext is one of the r columns, as in scenes) and cubature tolerance in {0.1, 0.05, 0.01}, and
one or more sources of cubature training poses (default ``random+snapshots``, the scenes'
``training = "mixed"``):

* ``random``: 100 random poses, per-column amplitude ~ 1/frequency (30 random validation poses);
* ``snapshots``: the frames of a full run under a *different* load (gravity x 1.3, same steps),
  projected onto the basis; every 4th frame held out for validation. The reduced run itself is
  compared with the full run at the nominal gravity, so the test trajectory is not in the
  training set;
* ``random+snapshots``: both train, the random validation poses validate.

One full reference run (and one snapshot run) per object serves every row.

``--exact-cubature`` adds, per r, a row with every tet at weight 1 (poses ``exact``): the Galerkin
reduced model without cubature error, which separates the subspace's error from the cubature's.

Reported per row: cubature points, training / validation force error, training time (basis +
cubature; the snapshot run's time is printed once per object), time per reduced step, time per
full step (the baseline, measured in the same process), speed-up, and two trajectory errors
against the full run: ``tip err / peak`` = max over steps of |tip_reduced - tip_full| divided by the
peak tip displacement of the full run (tip: mean of the beam's end face / the bunny's ears), and
``RMS err / size`` = max over steps of the RMS vertex error divided by the bounding-box diagonal.

    .venv/bin/python kernels_bench/bench_reduced.py [--objects beam,bunny] [--beam-steps 30]
        [--bunny-steps 12] [--device cpu] [--poses random,snapshots,random+snapshots] [--no-load-response]
        [--exact-cubature] [--machine "cpu, 2 cores, shared/loaded machine"] [--out kernels_bench/results/reduced]

``--scenes thin_cantilever,octopus,bunny`` measures example scenes instead (their own loads,
handles, integrator and step): one full reference run, one full training run (``warpfem train``'s,
``--training-dt-scale`` for coarse steps) and, per ``--mixes modes:pod_modes`` and ``--scene-tols``,
a basis with POD columns of the training run, its cubature and a reduced run, with the floor (best
mass-weighted fit of the full run in the span), training cost and break-even frames. Writes
``<out>_scene_<name>.json`` / ``.md``.

Writes ``<out>_<object>.json`` and ``.md`` (and prints the markdown). The device is named in the
output; on the project's CI machine it is "cpu, 2 cores, shared/loaded machine".
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
import warnings

import numpy as np
import warp as wp

import warpfem as wf
from warpfem.reduced import ReducedSimulator, Subspace, build_basis, train_cubature
from warpfem.reduced.basis import _full_simulator
from warpfem.reduced.cubature import Cubature
from warpfem.reduced.subspace import material_parameters, mesh_hash

wp.config.quiet = True
HERE = os.path.dirname(os.path.abspath(__file__))
BUNNY = os.path.join(HERE, "..", "examples", "meshes", "bunny.mesh")


def beam(gravity_scale=1.0):
    mesh = wf.box_tet_mesh(size=(10.0, 1.0, 1.0), cells=(20, 2, 2))
    model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=1e7, poisson_ratio=0.3, density=100.0),
                     gravity=(0, 0, -9.81 * gravity_scale))
    model.fix(wf.select_vertices_in_box(mesh.vertices, (-1, -1, -1), (1e-6, 2, 2)))
    tip = np.flatnonzero(mesh.vertices[:, 0] > 10 - 1e-6)
    return dict(name="beam 10 x 1 x 1 m, 20x2x2 cells (480 tets, 189 vertices), stable neo-Hookean E = 1e7 Pa, "
                     "nu = 0.3, rho = 100, clamped at x = 0, gravity -z",
                model=model, tip=tip, dt=1 / 30, sim_options={}, max_points=300)


def bunny(gravity_scale=1.0):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mesh = wf.load_mesh(BUNNY, inside_surface=True)
    model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=5e4, poisson_ratio=0.4, density=1000.0),
                     gravity=(0, -9.81 * gravity_scale, 0))
    model.fix(wf.select_vertices_in_box(mesh.vertices, (-1, -1, -1), (1, 0.038, 1)))
    tip = np.flatnonzero(mesh.vertices[:, 1] >= 0.17)
    return dict(name=f"Stanford bunny ({mesh.num_tets} tets, {mesh.num_vertices} vertices, tets inside bunny.mesh's "
                     "surface), stable neo-Hookean E = 5e4 Pa, nu = 0.4, rho = 1000, pinned at its base (y <= 0.038 m), "
                     "gravity -y, mass damping 1/s",
                model=model, tip=tip, dt=1 / 24, sim_options={"damping_mass": 1.0}, max_points=200)


OBJECTS = {"beam": beam, "bunny": bunny}


def full_run(obj, steps, device):
    fs = wf.Simulator(obj["model"], dt=obj["dt"], device=device, **obj["sim_options"])
    xs, t = [], 0.0
    for _ in range(steps):
        t0 = time.perf_counter()
        fs.step()
        t += time.perf_counter() - t0
        xs.append(fs.positions())
    return np.array(xs), t / steps


def run_object(key, args):
    obj = OBJECTS[key]()
    model, tip = obj["model"], obj["tip"]
    steps = args.beam_steps if key == "beam" else args.bunny_steps
    X = model.rest_positions
    size = float(np.linalg.norm(X.max(0) - X.min(0)))
    print(f"# {key}: full reference run ({steps} steps of {obj['dt']:.4g} s) ...", flush=True)
    x_full, t_full = full_run(obj, steps, args.device)
    tip_full = x_full[:, tip].mean(1)
    peak = float(np.linalg.norm(tip_full - X[tip].mean(0), axis=1).max())
    print(f"# {key}: full step {t_full:.3f} s; training snapshot run (gravity x 1.3) ...", flush=True)
    t0 = time.perf_counter()
    snaps, _ = full_run(OBJECTS[key](gravity_scale=1.3), steps, args.device)
    t_snap = time.perf_counter() - t0
    snapshots = [X] + list(snaps)
    sim = _full_simulator(model)
    rows = []

    def write(rows, partial):
        _report(key, obj, args, rows, steps=steps, peak=peak, size=size, t_full=t_full, t_snap=t_snap, partial=partial)

    for r in [int(v) for v in args.modes.split(",")]:
        t0 = time.perf_counter()
        basis = build_basis(model, modes=r, modal_derivatives_=True, load_response=args.load_response, sim=sim)
        t_basis = time.perf_counter() - t0
        runs = [(float(tol), source) for tol in args.tols.split(",") for source in args.poses.split(",")]
        for tol, source in runs + ([(0.0, "exact")] if args.exact_cubature else []):
            if source == "exact":  # every tet at weight 1: the Galerkin reduced model without cubature error
                cub = Cubature.full(model.quadrature.num_elements)
            else:
                kw = dict(snapshots=snapshots, pose_source=source) if "snapshots" in source else {}
                cub = train_cubature(model, basis.U, tolerance=tol, max_points=obj["max_points"], seed=0, sim=sim, **kw)
            sub = Subspace(basis, cub, mesh_hash(model), material_parameters(model))
            rs = ReducedSimulator(model, sub, dt=obj["dt"], device=args.device, **obj["sim_options"])
            t_red, err_tip, err_rms, failed = 0.0, 0.0, 0.0, ""
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                for k in range(steps):
                    t1 = time.perf_counter()
                    try:
                        rs.step()
                    except wf.SolveFailed as e:
                        failed = str(e)
                        break
                    t_red += time.perf_counter() - t1
                    x = rs.positions()
                    err_tip = max(err_tip, float(np.linalg.norm(x[tip].mean(0) - tip_full[k])))
                    err_rms = max(err_rms, float(np.sqrt(((x - x_full[k]) ** 2).sum(1).mean())))
            t_red /= max(rs.step_count, 1)
            row = dict(r=r, tol=tol, poses=source, points=cub.num_points, train_err=cub.training_error,
                       valid_err=cub.validation_error, training_s=t_basis + cub.training_seconds,
                       reduced_step_ms=1e3 * t_red, full_step_ms=1e3 * t_full, speedup=t_full / max(t_red, 1e-12),
                       tip_err_rel_peak=err_tip / peak if not failed else float("nan"),
                       rms_err_rel_size=err_rms / size if not failed else float("nan"), failed=failed)
            rows.append(row)
            write(rows, partial=True)
            print(f"# {key} r={r} tol={tol} {source}: {cub.num_points} pts, tip err/peak {row['tip_err_rel_peak']:.3f}, "
                  f"rms/size {row['rms_err_rel_size']:.4f}, reduced {row['reduced_step_ms']:.1f} ms", flush=True)
    write(rows, partial=False)
    return rows


def _report(key, obj, args, rows, *, steps, peak, size, t_full, t_snap, partial):
    device = f"{args.device} ({platform.processor() or platform.machine()}, {os.cpu_count()} logical cores visible), " \
             f"{args.machine}"
    head = (f"### {key}: {obj['name']}\n\n{steps} steps of dt = {obj['dt']:.4g} s; peak tip displacement of the full run "
            f"{peak:.4g} m, object size (bbox diagonal) {size:.4g} m; device: {device}. Full step "
            f"{1e3 * t_full:.0f} ms (Newton + block-Jacobi PCG, float64). Snapshot training run (gravity x 1.3, "
            f"{steps} steps): {t_snap:.1f} s, not included in 'training s'. Basis: modal derivatives, load-response "
            f"column {'on' if args.load_response else 'off'}.\n")
    table = ["| r | tol | poses | cubature pts | train err | valid err | training s | reduced step ms | full step ms | "
             "speed-up | tip err / peak | RMS err / size |", "|" + "---|" * 12]
    for w in rows:
        table.append(f"| {w['r']} | {w['tol']} | {w['poses']} | {w['points']} | {w['train_err']:.3f} | {w['valid_err']:.3f} | "
                     f"{w['training_s']:.1f} | {w['reduced_step_ms']:.1f} | {w['full_step_ms']:.0f} | {w['speedup']:.0f}x | "
                     f"{w['tip_err_rel_peak']:.3f} | {w['rms_err_rel_size']:.4f} |" + (" failed" if w["failed"] else ""))
    md = head + "\n" + "\n".join(table) + "\n" + ("\n(partial: the run was still going)\n" if partial else "")
    if not partial:
        print(md, flush=True)
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(f"{args.out}_{key}.json", "w") as f:
            json.dump(dict(object=key, description=obj["name"], steps=steps, dt=obj["dt"], device=device, partial=partial,
                           peak_tip_displacement=peak, size=size, full_step_ms=1e3 * t_full,
                           snapshot_run_s=t_snap, load_response=bool(args.load_response), rows=rows), f, indent=1)
        with open(f"{args.out}_{key}.md", "w") as f:
            f.write(md)


# ------------------------------------------------------------------------------------------------
# Scene rows: the scene's own loads and handles, the scene's integrator and step. One full run of
# the scene (the reference) and one full training run (train_scene's: ``T`` frames, handle ramps
# over those T frames) per scene; each row trains a basis (modal + POD columns of the training
# run) and a cubature, and runs the reduced scene through the same SceneRun driver.
SCENES = {  # name: (scene file, reference frames N, training frames T)
    "thin_cantilever": ("thin_cantilever.toml", 48, 48),
    "octopus_reduced": ("octopus_reduced.toml", 48, 48),
    "thin_cantilever_fine": ("thin_cantilever_fine.toml", 48, 48),
    "octopus": ("octopus.toml", 96, 48),
    "bunny": ("bunny.toml", 8, 4),
}


def _scene_full_run(scene, frames, total):
    run = scene.build(full=True)
    xs, steps, t = [run.model.rest_positions.copy()], 0, 0.0
    for k in range(frames):
        fs = run.step_frame(total_frames=total)
        if k > 0 or frames == 1:  # the first frame pays one-time kernel loading: not a step's cost
            steps += fs.steps
            t += fs.step_seconds
        xs.append(run.sim.positions())
    return run, np.array(xs), steps, t


def _runs_cache_file(args, key, integ, N, T, k):
    return os.path.join(args.cache_runs, f"{key}_{integ}_N{N}_T{T}_k{k}.npz")


def _load_cached_runs(args, key, integ, N, T, k):
    if not args.cache_runs:
        return None
    path = _runs_cache_file(args, key, integ, N, T, k)
    if not os.path.exists(path):
        return None
    print(f"# {key}: reference and training runs from {os.path.basename(path)} (--cache-runs)", flush=True)
    with np.load(path) as z:
        return {name: z[name] for name in z.files}


def _save_cached_runs(args, key, integ, N, T, k, **arrays):
    os.makedirs(args.cache_runs, exist_ok=True)
    np.savez(_runs_cache_file(args, key, integ, N, T, k), **arrays)


def run_scene(key, args):
    from warpfem.reduced import train_subspace
    from warpfem.reduced.basis import snapshot_displacements
    from warpfem.reduced.scene import _reduced_simulator, scene_handles
    from warpfem.scenes import handle_targets, load_scene

    if key.endswith(".toml"):  # any scene file: --scene-frames and --scene-training-frames give N and T
        fname, N, T = key, 0, 0
        scene = load_scene(key)
        key = scene.name
        SCENES[key] = (os.path.basename(fname), 0, 0)
    else:
        fname, N, T = SCENES[key]
        scene = load_scene(os.path.join(HERE, "..", "examples", "scenes", fname))
    N = args.scene_frames or N
    T = args.scene_training_frames or T
    scene.spec.surface = None  # the render surface is not what is measured
    if args.integrator:  # the same integrator for the full reference, the training run and the reduced runs
        scene.spec.integrator["type"] = args.integrator
    integ_name = scene.integrator_type
    spec_frames = int(scene.spec.output["frames"])
    k = args.training_dt_scale
    cached = _load_cached_runs(args, key, integ_name, N, T, k)
    if cached is None:
        print(f"# {key}: full reference run ({N} frames of {integ_name}, ramps over {spec_frames}) ...", flush=True)
        run, xs, full_steps, t_ref = _scene_full_run(scene, N, spec_frames)
    else:  # exploration only (--cache-runs): the reference and training runs of an earlier invocation
        run = scene.build(full=True)
        xs, full_steps, t_ref = cached["xs"], int(cached["full_steps"]), float(cached["t_ref"])
    t_full = t_ref / full_steps
    print(f"# {key}: full step {t_full:.3f} s; training run ({T} frames, ramps over {T}) ...", flush=True)
    if cached is not None:
        snaps, train_steps, t_train_run = list(cached["snaps"]), int(cached["train_steps"]), float(cached["t_train_run"])
    elif scene.spec.handle or T > N or k > 1:
        from warpfem.reduced.scene import _drive

        scene.spec.subspace = dict(scene.spec.subspace or {}, training_frames=T, training_dt_scale=k)
        trun = scene.build(full=True)
        snaps, train_steps, t_train_run = _drive(scene, trun, T)
    else:  # same loads, no ramp: the training run is the reference's first T frames (timed as such)
        snaps, train_steps = xs[:T + 1], T * int(scene.spec.integrator["substeps"])
        t_train_run = train_steps * t_full
    if cached is None and args.cache_runs:
        _save_cached_runs(args, key, integ_name, N, T, k, xs=xs, full_steps=full_steps, t_ref=t_ref,
                          snaps=np.array(snaps), train_steps=train_steps, t_train_run=t_train_run)
    model = run.model
    X = model.rest_positions
    size = float(np.linalg.norm(X.max(0) - X.min(0)))
    disp = np.linalg.norm(xs - X, axis=2)
    free = ~np.asarray(model.fixed).all(axis=1)
    tipv = int(np.argmax(disp.max(0) * free))
    peak = float(disp[:, tipv].max())
    sel = scene_handles(scene)
    rest = [X[ids].copy() for ids, _ in sel]

    def targets_at(f):
        return [handle_targets(r0, h, f) for r0, h in zip(rest, scene.spec.handle)]

    sim = _full_simulator(model)
    M = sim.mass_matrix()
    substeps = int(scene.spec.integrator["substeps"])
    rows = []
    for mix in args.mixes.split(","):
        modes, pod = (int(v) for v in mix.split(":"))
        for tol_s in args.scene_tols.split(","):
            exact = tol_s == "exact"  # every tet at weight 1: the Galerkin reduced model without cubature error
            tol = 0.5 if exact else float(tol_s)
            sub = train_subspace(model, modes=modes, modal_derivatives=True, cubature_tolerance=tol,
                                 max_cubature_points=args.scene_max_points, seed=0, snapshots=list(snaps),
                                 pose_source=args.scene_poses, handles=sel,
                                 handle_targets_at=targets_at if sel else None, load_response=True, pod_modes=pod)
            if exact:
                sub = Subspace(sub.basis, Cubature.full(model.quadrature.num_elements), sub.mesh_hash, sub.material,
                               sub.settings, sub.report, sub.lifting)
                tol = "exact"
            rep = sub.report
            t_train = t_train_run + rep["basis_seconds"] + rep["cubature_seconds"]
            D = snapshot_displacements(model, xs, sub.lifting)
            R = (D - sub.U @ (sub.U.T @ (M @ D))).reshape(-1, 3, D.shape[1])
            floor_tip = float(np.linalg.norm(R[tipv], axis=0).max() / peak)
            floor_rms = float(np.sqrt((R ** 2).sum(1).mean(0)).max() / size)
            rs = _reduced_simulator(scene, model, sub, device=args.device)
            run.sim, run.frame = rs, 0
            ys, t_red, red_steps, failed = [X.copy()], 0.0, 0, ""
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                for f in range(N):
                    try:
                        fs = run.step_frame(total_frames=spec_frames)
                    except wf.SolveFailed as e:
                        failed = str(e)
                        break
                    if f > 0 or N == 1:  # as for the full run: the first frame loads kernels
                        t_red += fs.step_seconds
                        red_steps += fs.steps
                    ys.append(rs.positions())
            t_red /= max(red_steps, 1)
            if failed:
                tip_err = rms_err = float("nan")
            else:
                e = np.linalg.norm(np.array(ys) - xs, axis=2)
                tip_err = float(e[:, tipv].max() / peak)
                rms_err = float(np.sqrt((e ** 2).mean(1)).max() / size)
            gain = (t_full - t_red) * substeps
            row = dict(modes=modes, pod=pod, r=sub.U.shape[1], tol=tol, points=sub.cubature.num_points,
                       train_err=sub.cubature.training_error, valid_err=sub.cubature.validation_error,
                       floor_tip=floor_tip, floor_rms=floor_rms, tip_err=tip_err, rms_err=rms_err,
                       reduced_step_ms=1e3 * t_red, full_step_ms=1e3 * t_full, speedup=t_full / max(t_red, 1e-12),
                       training_s=t_train, training_full_steps=train_steps,
                       break_even_frames=int(np.ceil(t_train / gain)) if gain > 0 else None, failed=failed)
            rows.append(row)
            print(f"# {key} {modes}+{pod} (r={row['r']}) tol {tol}: {row['points']} pts, valid {row['valid_err']:.3g}, "
                  f"floor tip {floor_tip:.4f} / rms {floor_rms:.5f}, tip {tip_err:.4f}, rms {rms_err:.5f}, "
                  f"{row['reduced_step_ms']:.1f} ms ({row['speedup']:.0f}x), train {t_train:.0f} s", flush=True)
            _scene_report(key, scene, args, rows, N=N, T=T, peak=peak, size=size, t_full=t_full,
                          train_steps=train_steps, t_train_run=t_train_run, tipv=tipv)
    return rows


def _scene_report(key, scene, args, rows, *, N, T, peak, size, t_full, train_steps, t_train_run, tipv):
    device = f"{args.device} ({platform.processor() or platform.machine()}, {os.cpu_count()} logical cores visible), " \
             f"{args.machine}"
    integ = scene.spec.integrator
    m = scene.mesh()
    head = (f"### {key} (examples/scenes/{SCENES[key][0]}): {m.num_elements} tets, {m.num_vertices} vertices\n\n"
            f"{N} frames ({N * int(integ['substeps'])} {scene.integrator_type} steps of {integ['dt']:.4g} s, the same integrator "
            "and step for the full reference, the training run and the reduced runs) of the scene; "
            f"training run: {T} frames ({train_steps} full steps of {args.training_dt_scale} x dt, {t_train_run:.1f} s, "
            f"handles ramped over those {T} frames). Tip: vertex {tipv} (the free vertex that moved most), peak displacement {peak:.4g} m; size "
            f"(bbox diagonal) {size:.4g} m. Device: {device}. Full step {1e3 * t_full:.0f} ms. Step times leave out "
            "the first frame of each run (one-time kernel loading). Errors are maxima over "
            "all frames; 'floor' = the best mass-weighted fit of the full run in the span (same normalisation).\n")
    table = ["| modes + POD | r | tol | cubature pts | train / valid err | floor tip | tip err / peak | floor RMS | "
             "RMS err / size | reduced step ms | full step ms | speed-up | training s (full steps) | break-even frames |",
             "|" + "---|" * 14]
    for w in rows:
        table.append(f"| {w['modes']} + {w['pod']} | {w['r']} | {w['tol']} | {w['points']} | {w['train_err']:.3f} / "
                     f"{w['valid_err']:.3f} | {w['floor_tip']:.4f} | {w['tip_err']:.4f} | {w['floor_rms']:.5f} | "
                     f"{w['rms_err']:.5f} | {w['reduced_step_ms']:.1f} | {w['full_step_ms']:.0f} | {w['speedup']:.0f}x | "
                     f"{w['training_s']:.0f} ({w['training_full_steps']}) | {w['break_even_frames']} |"
                     + (" failed" if w["failed"] else ""))
    md = head + "\n" + "\n".join(table) + "\n"
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(f"{args.out}_scene_{key}.json", "w") as f:
            json.dump(dict(scene=key, integrator=scene.integrator_type, frames=N, training_frames=T, device=device, peak_tip_displacement=peak, size=size,
                           full_step_ms=1e3 * t_full, training_run_s=t_train_run, rows=rows), f, indent=1)
        with open(f"{args.out}_scene_{key}.md", "w") as f:
            f.write(md)
    return md


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--objects", default="beam,bunny")
    ap.add_argument("--scenes", default="",
                    help=f"comma list of {', '.join(SCENES)}: scene rows (modal + POD bases) instead of --objects")
    ap.add_argument("--mixes", default="20:0,20:10,10:20",
                    help="scene rows: comma list of modes:pod_modes (r = modes + pod_modes)")
    ap.add_argument("--scene-tols", default="0.01")
    ap.add_argument("--scene-max-points", type=int, default=300)
    ap.add_argument("--scene-poses", default="random+snapshots", choices=("random+snapshots", "snapshots"),
                    help="scene rows: cubature training poses (the scenes' training = \"mixed\" or \"snapshots\")")
    ap.add_argument("--scene-frames", type=int, default=None, help="override the reference frames N")
    ap.add_argument("--scene-training-frames", type=int, default=None, help="override the training frames T")
    ap.add_argument("--training-dt-scale", type=int, default=1,
                    help="the training run steps k x dt over its T frames ([subspace] training_dt_scale)")
    ap.add_argument("--integrator", default=None, choices=("backward_euler", "bdf2", "newmark"),
                    help="scene rows: run the full reference, the training run and the reduced runs with this "
                         "integrator (default: the scene's)")
    ap.add_argument("--cache-runs", default=None,
                    help="exploration only: store / reuse the reference and training runs in this folder "
                         "(final rows run the reference in the same process: leave it off)")
    ap.add_argument("--beam-steps", type=int, default=30)
    ap.add_argument("--bunny-steps", type=int, default=12)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--modes", default="10,20,40")
    ap.add_argument("--tols", default="0.1,0.05,0.01")
    ap.add_argument("--poses", default="random+snapshots",
                    help="comma list of random, snapshots, random+snapshots (default: the scenes' 'mixed')")
    ap.add_argument("--load-response", action=argparse.BooleanOptionalAction, default=True,
                    help="K^-1 f_ext as a basis column (default on, as in scenes)")
    ap.add_argument("--exact-cubature", action="store_true",
                    help="add a row per r with every tet at weight 1 (poses 'exact'): the reduced model's own error")
    ap.add_argument("--machine", default="cpu, 2 cores, shared/loaded machine", help="how loaded the machine is (printed)")
    ap.add_argument("--out", default=os.path.join(HERE, "results", "reduced"))
    args = ap.parse_args()
    warnings.simplefilter("ignore", RuntimeWarning)
    if args.scenes:
        for key in args.scenes.split(","):
            run_scene(key, args)
        return
    for key in args.objects.split(","):
        run_object(key, args)


if __name__ == "__main__":
    main()
