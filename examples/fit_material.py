"""Material identification: recover Young's modulus and Poisson's ratio of a beam from a noisy
recording of its motion, with the adjoint gradients of ``warpfem.diff`` and L-BFGS-B
(``warpfem.diff.fit.fit``: what ``warpfem fit SCENE --observed OBS.npz`` runs).

A 30 cm beam (Tet4, stable neo-Hookean, gravity) is clamped at x = 0 and its far end pulled 3 cm in
0.1 s (so the lateral contraction shows nu). The "recording" is the run with E = 100 kPa and
nu = 0.12 plus Gaussian noise on every coordinate; the fit starts 3x off (300 kPa, 0.36).

    python examples/fit_material.py [--device cpu] [--num-frames 12] [--noise 1e-5] [--stage-path out/fit.usda]
"""

from __future__ import annotations

import argparse

import numpy as np

TRUE = {"youngs_modulus": 1.0e5, "poisson_ratio": 0.12}


def beam_scene(frames: int, start=(3.0e5, 0.36)):
    """The scene as a document (what a TOML file would hold), validated by warpfem.scenes."""
    from warpfem.scenes import Scene
    from warpfem.scenes.schema import parse_scene_dict

    doc = {
        "name": "fit_beam", "gravity": [0.0, -9.81, 0.0],
        "mesh": {"generator": "box", "size": [0.3, 0.05, 0.05], "cells": [3, 1, 1], "element": "tet4"},
        "material": {"model": "stable_neo_hookean", "youngs_modulus": start[0], "poisson_ratio": start[1],
                     "density": 1000.0},
        "fixed": [{"box_min": [-1.0, -1.0, -1.0], "box_max": [0.0, 1.0, 1.0]}],
        "handle": [{"box_min": [0.29, -1.0, -1.0], "box_max": [1.0, 1.0, 1.0], "translation": [0.03, 0.0, 0.0],
                    "ramp_time": 0.1}],
        "integrator": {"type": "backward_euler", "dt": 1.0 / 60.0},
        "output": {"fps": 60.0, "frames": int(frames)},
    }
    return Scene(parse_scene_dict(doc))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default=None)
    ap.add_argument("--num-frames", type=int, default=12)
    ap.add_argument("--noise", type=float, default=1e-5, help="standard deviation of the recording's noise (m)")
    ap.add_argument("--stage-path", default=None, help="USD of the fitted run (None: no USD)")
    ap.add_argument("--headless", action="store_true", help="accepted for Warp-example compatibility")
    args = ap.parse_args(argv)

    import warp as wp

    wp.config.quiet = True
    from warpfem.diff import scene_with_parameters
    from warpfem.diff.fit import fit

    device = args.device or "cpu"
    scene = beam_scene(args.num_frames)
    truth = scene_with_parameters(scene, TRUE, newton_tol=1e-10).build(device=device)
    recorded = [truth.sim.positions()]
    for _ in range(args.num_frames):
        truth.step_frame()
        recorded.append(truth.sim.positions())
    rng = np.random.default_rng(0)
    observed = np.asarray(recorded) + args.noise * rng.standard_normal((len(recorded),) + recorded[0].shape)

    def progress(k, loss, vals):
        print(f"  iteration {k}: loss {loss:.3e} m^2, E = {vals['youngs_modulus']:.1f} Pa, "
              f"nu = {vals['poisson_ratio']:.4f}")

    res = fit(scene, observed, ["youngs_modulus", "poisson_ratio"], device=device, progress=progress)
    E, nu = res.params["youngs_modulus"], res.params["poisson_ratio"]
    print(f"fitted E = {E:.1f} Pa ({100 * (E / TRUE['youngs_modulus'] - 1):+.3f} %), nu = {nu:.4f} "
          f"({nu - TRUE['poisson_ratio']:+.4f}); start 300000 Pa, 0.36; {res.iterations} iterations, "
          f"{res.evaluations} runs, {res.seconds:.1f} s; loss {res.loss:.3e} m^2 (noise floor "
          f"{observed.size * args.noise ** 2:.3e})")
    if args.stage_path and args.stage_path != "None":
        scene_with_parameters(scene, res.params).build(device=device).run(usd=args.stage_path, states="")
    return {"youngs_modulus": E, "poisson_ratio": nu, "iterations": res.iterations, "loss": res.loss,
            "loss_history": res.loss_history}


if __name__ == "__main__":
    main()
