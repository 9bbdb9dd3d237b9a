"""One newton scene, two solvers: newton's SolverVBD and warpfem's SolverFEM, one line apart.

    python examples/newton_soft_body.py --headless
    python examples/newton_soft_body.py --num-frames 60 --stage-path out/newton_fem.usda --headless

The scene (built with newton's ``ModelBuilder``): a soft beam 1 m x 0.2 m x 0.2 m (10 x 2 x 2 cells,
6 tets each: 240 tets), E = 1e6 Pa, nu = 0.3, rho = 1000 kg/m^3 (``add_soft_mesh``: k_mu, k_lambda),
clamped at x = 0 (zero-mass particles), sagging under gravity from rest above newton's ground
plane, one step of 1/60 s per frame. The same model is stepped by

    solver = newton.solvers.SolverVBD(model, iterations=10)     # --solvers vbd
    solver = SolverFEM(model)                                   # --solvers fem  (warpfem)

and both are compared with a reference (SolverFEM with 8 substeps per frame, ``--reference-substeps``, Newmark, tol 1e-8):
the tip's mean z (the particles of the face x = 1) over the frames, RMS error relative to the
reference's largest tip deflection, and the wall time per simulated second. ``--stage-path`` writes
the SolverFEM run with newton's own ``ViewerUSD`` (the model as newton draws it).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

import warp as wp  # noqa: E402

import warpfem as wf  # noqa: E402

FPS = 60.0


def build_model(device=None, *, cells=(10, 2, 2)):
    """The newton model of the beam (clamped particles: zero mass) and its tip particles."""
    import newton

    mesh = wf.box_tet_mesh(size=(1.0, 0.2, 0.2), cells=cells)
    material = wf.StableNeoHookean(youngs_modulus=1.0e6, poisson_ratio=0.3, density=1000.0)
    builder = newton.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    builder.add_ground_plane()
    builder.add_soft_mesh(pos=wp.vec3(0.0, 0.0, 1.0), rot=wp.quat_identity(), scale=1.0, vel=wp.vec3(0.0, 0.0, 0.0),
                          vertices=mesh.vertices.tolist(), indices=np.asarray(mesh.elements).ravel().tolist(),
                          density=1000.0, k_mu=material.mu_lame, k_lambda=material.lam_lame, k_damp=0.0)
    clamped = np.flatnonzero(mesh.vertices[:, 0] < 1e-9)
    for i in clamped:
        builder.particle_mass[int(i)] = 0.0
        builder.particle_flags[int(i)] &= ~int(newton.ParticleFlags.ACTIVE)
    builder.color()  # SolverVBD's graph colouring
    model = builder.finalize(device=device)
    return model, np.flatnonzero(mesh.vertices[:, 0] > 1.0 - 1e-9)


def make_solver(name, model):
    import newton

    from warpfem.interop.newton import SolverFEM

    if name == "vbd":
        return newton.solvers.SolverVBD(model, iterations=10)
    if name == "fem":
        return SolverFEM(model)
    if name == "reference":
        return SolverFEM(model, integrator="newmark", tol=1e-8, cg_tol=1e-8)
    raise ValueError(f"unknown solver {name!r}: vbd, fem")


def run(name, model, tip, frames, *, substeps=1, viewer=None):
    """(tip mean z after each frame, wall seconds of the steps)."""
    solver = make_solver(name, model)
    s0, s1 = model.state(), model.state()
    control = model.control()
    dt = 1.0 / FPS / substeps
    tips, seconds = [], 0.0
    for frame in range(frames):
        if viewer is not None:
            viewer.begin_frame(frame / FPS)
            viewer.log_state(s0)
            viewer.end_frame()
        t0 = time.perf_counter()
        for _ in range(substeps):
            s0.clear_forces()
            solver.step(s0, s1, control, None, dt)
            s0, s1 = s1, s0
        wp.synchronize_device(model.device)
        seconds += time.perf_counter() - t0
        tips.append(float(s0.particle_q.numpy()[tip, 2].mean()))
    if viewer is not None:
        viewer.begin_frame(frames / FPS)
        viewer.log_state(s0)
        viewer.end_frame()
    return np.array(tips), seconds


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default=None)
    parser.add_argument("--num-frames", type=int, default=30)
    parser.add_argument("--stage-path", default=None, help="write the SolverFEM run with newton's ViewerUSD")
    parser.add_argument("--headless", action="store_true", help="accepted for Warp-example compatibility")
    parser.add_argument("--solvers", default="vbd,fem", help="comma-separated: vbd, fem")
    parser.add_argument("--reference-substeps", type=int, default=8, help="the reference's steps per frame")
    args = parser.parse_args(argv)
    try:
        import newton  # noqa: F401
    except ImportError:
        print("this example needs newton: pip install 'warpfem[newton]'")
        return {}
    with wp.ScopedDevice(args.device):
        model, tip = build_model(args.device)
        rest = float(model.particle_q.numpy()[tip, 2].mean())
        ref, _ = run("reference", model, tip, args.num_frames, substeps=args.reference_substeps)
        peak = float(np.abs(ref - rest).max())
        out = {"frames": args.num_frames, "reference_peak_m": peak}
        print(f"beam 1 m, 240 tets, {args.num_frames} frames of 1/60 s; reference tip deflection peak {peak * 1e3:.1f} mm")
        for name in args.solvers.split(","):
            viewer = None
            if name == "fem" and args.stage_path:
                import newton.viewer

                viewer = newton.viewer.ViewerUSD(output_path=args.stage_path, fps=int(FPS), up_axis="Z")
                viewer.set_model(model)
            tips, seconds = run(name, model, tip, args.num_frames, viewer=viewer)
            if viewer is not None:
                viewer.close()
            err = float(np.sqrt(np.mean((tips - ref) ** 2)) / peak)
            per_s = seconds / (args.num_frames / FPS)
            out[name] = {"tip_error": err, "seconds_per_simulated_second": per_s, "final_tip_m": float(tips[-1] - rest)}
            print(f"  {name:4s}: tip RMS error {err:.2e} of the peak, {per_s:.2f} s per simulated second, "
                  f"final tip {1e3 * (tips[-1] - rest):+.2f} mm")
    return out


if __name__ == "__main__":
    main()
