"""``warpfem fit SCENE --observed OBS.npz --params youngs_modulus poisson_ratio``: identify material
parameters and friction coefficients (``contact_friction``, ``friction:<collider name>``) from a
recorded trajectory (:func:`warpfem.diff.fit.fit`; docs/gradients.md).

Listed in :data:`warpfem.cli.COMMANDS`. Exit codes as in :mod:`warpfem.cli`: 0 fitted, 1 a run
failed (a step diverged), 2 bad input (scene, observation, vertices, parameters, bounds, output
paths), 130 interrupted.
"""

from __future__ import annotations

from warpfem import cli as _cli


def _bounds(items):
    out = {}
    for it in items or ():
        name, sep, rng = it.partition("=")
        lo, sep2, hi = rng.partition(",")
        if not sep or not sep2:
            raise ValueError(f"--bounds {it!r}: write NAME=LOWER,UPPER (e.g. youngs_modulus=1e4,1e8 or "
                             f"friction:floor=0,1.5)")
        out[name] = (float(lo), float(hi))
    return out


def _cmd_fit(args) -> int:
    import os

    from warpfem.diff import DiffInputError
    from warpfem.scenes import SceneError
    from warpfem.solvers.nonlinear import SolveFailed

    if _cli.check_device(args) is not None:
        return _cli.EXIT_INVALID
    from warpfem.diff.fit import fit, load_observation, load_vertices, write_fitted_scene
    from warpfem.io.outputs import OutputPathError, check_output_paths

    try:
        scene = _cli.load(args.scene)
        observed = load_observation(args.observed)
        vertices = load_vertices(args.vertices) if args.vertices else None
        bounds = _bounds(args.bounds)
        check_output_paths({"--report": args.report, "--out": args.out})
    except (SceneError, DiffInputError, OutputPathError, ValueError) as e:
        _cli.error(str(e).splitlines()[0])
        return _cli.EXIT_INVALID
    init = _cli.init_warp
    if init is not None:
        init(args.device, args.verbose)

    def progress(k, loss, vals):
        if not args.quiet:
            shown = ", ".join(f"{p} = {v:.6g}" for p, v in vals.items())
            print(f"iteration {k}: loss {loss:.6e} m^2, {shown}", flush=True)

    def stage(frames, total):
        if not args.quiet:
            print(f"fitting frames 1-{frames} of {total}" + (" (all)" if frames == total else ""), flush=True)

    try:
        res = fit(scene, observed, args.params, vertices=vertices, bounds=bounds, max_iterations=args.max_iterations,
                  device=args.device, precision=args.precision, newton_tol=args.newton_tol, progress=progress,
                  run_frames=args.frames, stage_progress=stage)
    except (DiffInputError, SceneError) as e:
        _cli.error(f"{args.scene}: {str(e).splitlines()[0]}")
        return _cli.EXIT_INVALID
    except NotImplementedError as e:
        _cli.error(f"{args.scene}: {e}")
        return _cli.EXIT_INVALID
    except (SolveFailed, RuntimeError) as e:
        _cli.error(f"{args.scene}: the fit stopped: {str(e).splitlines()[0]}")
        return _cli.EXIT_FAILED
    except KeyboardInterrupt:
        _cli.error("interrupted")
        return _cli.EXIT_INTERRUPTED
    shown = ", ".join(f"{p} = {v:.6g} (start {res.initial[p]:.6g})" for p, v in res.params.items())
    print(f"fitted {shown}; loss {res.loss_history[0]:.3e} -> {res.loss:.3e} m^2 in {res.iterations} iterations "
          f"({res.evaluations} runs, {res.seconds:.1f} s); gradient norm {res.gradient_norm:.2e}; {res.message}")
    if args.report:
        res.to_json(args.report)
        print(f"report: {args.report}")
    if args.out:
        write_fitted_scene(args.scene, res.params, args.out,
                           header=[f"Fitted by `warpfem fit` from {os.path.basename(args.scene)} and "
                                   f"{os.path.basename(args.observed)}: {shown}"])
        print(f"scene with the fitted values: {args.out}")
    return _cli.EXIT_OK


def register(subparsers):
    from warpfem.diff import CONTACT_FRICTION, FRICTION_PREFIX, MATERIAL_PARAMETERS

    p = subparsers.add_parser("fit", help="identify material parameters and friction coefficients from a recorded "
                                          "trajectory (adjoint gradients + L-BFGS-B)")
    p.add_argument("scene", help="TOML scene file (dynamic integrator); its values are the start")
    p.add_argument("--observed", required=True, help="npz with 'positions' (frames, n, 3), as [output] states writes")
    p.add_argument("--params", nargs="+", default=["youngs_modulus", "poisson_ratio"],
                   metavar="NAME", help="parameters to fit (default youngs_modulus poisson_ratio): "
                                        f"{', '.join(MATERIAL_PARAMETERS)} ([material]); {CONTACT_FRICTION} ([contact] "
                                        f"friction: surface contact); {FRICTION_PREFIX}NAME (the friction of the "
                                        "[[collider]] named NAME; default names <type><position>, e.g. plane1)")
    p.add_argument("--vertices", help="file of observed vertex indices (text or .npy); the observation holds "
                                      "those vertices, or all of them")
    p.add_argument("--bounds", nargs="*", metavar="NAME=LO,HI",
                   help="search bounds (SI units; defaults E 10..1e13 Pa, nu 0..0.495, density 0.1..1e5 kg/m^3, "
                        "frictions 0..2), e.g. youngs_modulus=1e4,1e8 friction:floor=0,1.5")
    p.add_argument("--frames", type=int, help="frames of the recorded run, as `warpfem run --frames` (default the "
                                              "scene's [output] frames); the observation has one more")
    p.add_argument("--max-iterations", type=int, default=50, help="L-BFGS-B iterations (default 50)")
    p.add_argument("--newton-tol", type=float, default=1e-10,
                   help="Newton tolerance of the runs (tightened to it: gradients hold at converged steps)")
    p.add_argument("--report", help="JSON report: fitted params, loss history, iterations, gradient norm")
    p.add_argument("--out", help="write the scene with the fitted values (TOML)")
    p.add_argument("--device", default="cpu", help="Warp device: cpu, cuda, cuda:0, ... or auto (default cpu)")
    _cli.add_threads_option(p)
    p.add_argument("--precision", choices=("float32", "float64"), default="float64")
    p.add_argument("--quiet", action="store_true", help="only the final report")
    p.add_argument("--verbose", action="store_true", help="show Warp's initialisation and compile messages")
    p.set_defaults(func=_cmd_fit)
