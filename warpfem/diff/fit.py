"""Parameter identification from a recorded trajectory: ``warpfem fit`` (docs/gradients.md).

:func:`fit` minimises the squared-distance loss of :func:`warpfem.diff.loss_and_gradients` between a
scene's run and observed positions (the ``positions`` of an ``[output] states`` npz) over chosen
material parameters and friction coefficients (``contact_friction``, ``friction:<collider>``), by
L-BFGS-B (scipy) on the adjoint gradients, within bounds. The optimiser works on log E and log
density (positive, wide ranges) and on nu and the frictions themselves (mu may go to 0), with the
loss divided by its value at the start (so its tolerances do not depend on units or noise level).
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from warpfem.diff import (CONTACT_FRICTION, FRICTION_PREFIX, SCENE_PARAMETERS, DiffInputError, check_parameter_names,
                          scene_parameter_values)

__all__ = ["fit", "FitResult", "DEFAULT_BOUNDS", "load_observation", "load_vertices", "write_fitted_scene"]

#: parameter -> (lower, upper) bounds of the search (SI units); "friction": every friction coefficient
#: (``contact_friction``, ``friction:<collider>``)
DEFAULT_BOUNDS = {"youngs_modulus": (1e1, 1e13), "poisson_ratio": (0.0, 0.495), "density": (1e-1, 1e5),
                  "friction": (0.0, 2.0)}
#: whether the optimiser works on the parameter's logarithm (by DEFAULT_BOUNDS key)
_LOG = {"youngs_modulus": True, "poisson_ratio": False, "density": True, "friction": False}


def _kind(p):
    """The DEFAULT_BOUNDS / _LOG key of parameter ``p``."""
    return "friction" if p == CONTACT_FRICTION or p.startswith(FRICTION_PREFIX) else p


@dataclass
class FitResult:
    """What :func:`fit` found: ``params`` (fitted values), ``initial`` (the scene's), ``loss`` (m^2,
    final), ``loss_history`` (per iteration, m^2), ``iterations``, ``evaluations`` (forward +
    adjoint runs), ``gradient_norm`` (of the normalised loss in the optimiser's variables, final),
    ``converged`` and ``message`` (L-BFGS-B's), ``seconds``."""

    params: dict
    initial: dict
    loss: float
    loss_history: list
    iterations: int
    evaluations: int
    gradient_norm: float
    converged: bool
    message: str
    seconds: float
    frames: int = 0
    vertices: int = 0
    bounds: dict = field(default_factory=dict)

    def to_json(self, path):
        os.makedirs(os.path.dirname(os.path.abspath(path)) or ".", exist_ok=True)
        with open(path, "w") as f:
            json.dump(asdict(self), f, indent=2)
        return path


def load_observation(path):
    """``positions`` (frames, n, 3) of an npz written by ``[output] states`` (or a .npy array)."""
    if not os.path.isfile(path):
        raise DiffInputError(f"{path}: observation file not found")
    try:
        data = np.load(path)
    except Exception as e:  # noqa: BLE001 - any unreadable file is a bad input
        raise DiffInputError(f"{path}: not a readable .npz/.npy ({e})") from e
    if isinstance(data, np.ndarray):
        return data
    if "positions" not in data.files:
        raise DiffInputError(f"{path}: no 'positions' array (an [output] states npz has one); found {data.files}")
    return data["positions"]


def load_vertices(path):
    """Vertex indices from a text file (whitespace or comma separated integers) or a .npy array."""
    if not os.path.isfile(path):
        raise DiffInputError(f"{path}: vertices file not found")
    try:
        if path.endswith(".npy"):
            v = np.load(path)
        else:
            with open(path) as f:
                text = f.read().replace(",", " ")
            v = np.array([int(t) for t in text.split()], dtype=np.int64)
    except ValueError as e:
        raise DiffInputError(f"{path}: vertex indices must be integers ({e})") from e
    v = np.asarray(v).reshape(-1)
    if not np.issubdtype(v.dtype, np.integer):
        raise DiffInputError(f"{path}: vertex indices must be integers, got {v.dtype}")
    return v


def _check_params(params, scene):
    params = list(params)
    if not params:
        raise DiffInputError("no parameters to fit (choose from " + ", ".join(SCENE_PARAMETERS) + ")")
    check_parameter_names(scene, params, what="fit")
    if len(set(params)) != len(params):
        raise DiffInputError(f"a parameter is named twice: {params}")
    return params


def fit(scene, observed, params=("youngs_modulus", "poisson_ratio"), *, vertices=None, frames=None, bounds=None,
        initial=None, max_iterations=50, device="cpu", precision="float64", newton_tol=1e-10, gtol=1e-9,
        progress=None, run_frames=None, stages=None, first_stage_frames=5, stage_progress=None) -> FitResult:
    """Fit ``params`` of ``scene`` (path or Scene) to ``observed`` (frames, n or k, 3) positions.

    ``bounds``: name -> (lo, hi) (default :data:`DEFAULT_BOUNDS`); ``initial``: name -> start
    value (default the scene's); ``progress(iteration, loss, params)`` after each iteration;
    ``run_frames``: the frames of the recorded run (default the scene's ``[output] frames``);
    ``stages``: continuation over the recording's length, each stage an L-BFGS-B run on a prefix
    of the frames starting where the last one ended (the loss of a long oscillating trajectory has
    many local minima in E and density; on a short prefix it has one): None (default) doubles the
    prefix from ``first_stage_frames`` (5, 10, 20, ..., all frames); an int k takes k equal
    steps; 1 fits all frames at once. ``stage_progress(frames, total)`` at the start of each stage
    (the losses ``progress`` reports are those of the stage's frames)."""
    from scipy.optimize import minimize

    from warpfem.diff import SceneProblem

    problem = SceneProblem(scene, observed, vertices=vertices, frames=frames, device=device, precision=precision,
                           newton_tol=newton_tol, run_frames=run_frames)
    sc, obs, vertices, frames = problem.scene, problem.observed, problem.vertices, problem.frames
    params = _check_params(params, sc)
    bnds = {p: DEFAULT_BOUNDS[_kind(p)] for p in params}
    for k, b in (bounds or {}).items():
        try:
            check_parameter_names(sc, [k], what="fit")
        except DiffInputError as e:
            raise DiffInputError(f"bounds given for {e}") from None
        lo, hi = float(b[0]), float(b[1])
        if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
            raise DiffInputError(f"bounds of {k} must be finite with lower < upper, got {b!r}")
        if _kind(k) == "friction" and lo < 0:
            raise DiffInputError(f"the lower bound of {k} must be >= 0 (a friction coefficient), got {lo}")
        bnds[k] = (lo, hi)
    log = {p: _LOG[_kind(p)] for p in params}
    start = scene_parameter_values(sc, params)
    start.update({k: float(v) for k, v in (initial or {}).items() if k in params})
    for p in params:
        lo, hi = bnds[p]
        if log[p] and lo <= 0:
            raise DiffInputError(f"the lower bound of {p} must be > 0, got {lo}")
        start[p] = min(max(start[p], lo), hi)

    def to_z(vals):
        return np.array([math.log(vals[p]) if log[p] else vals[p] for p in params])

    def from_z(z):
        return {p: (math.exp(v) if log[p] else float(v)) for p, v in zip(params, z)}

    zb = [((math.log(bnds[p][0]), math.log(bnds[p][1])) if log[p] else bnds[p]) for p in params]
    evals, history = [0], []
    t0 = time.perf_counter()
    F = obs.shape[0]
    if stages is None:
        lasts, k = [], max(1, int(first_stage_frames))
        while k < F - 1:
            lasts.append(k)
            k *= 2
        lasts.append(F - 1)
    elif int(stages) < 1:
        raise DiffInputError(f"stages must be >= 1, got {stages!r}")
    else:
        lasts = sorted({max(1, math.ceil((F - 1) * k / int(stages))) for k in range(1, int(stages) + 1)})

    def make_eval(last):
        cache, L0 = {}, [None]

        def evaluate(z):
            key = tuple(np.round(z, 15))
            if key in cache:
                return cache[key]
            vals = from_z(z)
            res = problem.evaluate(vals, wanted=list(params), last_frame=last)
            evals[0] += 1
            if L0[0] is None:
                L0[0] = res.loss if res.loss > 0 else 1.0
            g = np.array([res.gradients[p] * (vals[p] if log[p] else 1.0) for p in params])
            out = (res.loss / L0[0], g / L0[0], res.loss)
            if not (np.isfinite(out[0]) and np.all(np.isfinite(out[1]))):
                raise RuntimeError(f"the loss or its gradient is not finite at {vals}")
            cache[key] = out
            return out

        return evaluate

    z = to_z(start)
    it = [0]
    opt = None
    nit = 0
    whole = make_eval(lasts[-1])
    history.append(whole(z)[2])  # the loss over every frame: at the start, after each stage, per last-stage iteration
    for last in lasts:
        evaluate = whole if last == lasts[-1] else make_eval(last)
        if stage_progress is not None:
            stage_progress(last, F - 1)

        def callback(zk, evaluate=evaluate, last=last):
            it[0] += 1
            _, _, L = evaluate(zk)
            if last == lasts[-1]:
                history.append(L)
            if progress is not None:
                progress(it[0], L, from_z(zk))

        opt = minimize(lambda zz, evaluate=evaluate: evaluate(zz)[:2], z, jac=True, method="L-BFGS-B", bounds=zb,
                       callback=callback,
                       options={"maxiter": int(max_iterations), "ftol": 1e-15, "gtol": float(gtol), "maxls": 30})
        z = opt.x
        nit += int(opt.nit)
        if last != lasts[-1]:
            history.append(whole(z)[2])
    final = whole(opt.x)
    # the projected gradient's norm (components pushing out of an active bound do not count)
    g = final[1].copy()
    for i, (lo, hi) in enumerate(zb):
        if (opt.x[i] <= lo and g[i] > 0) or (opt.x[i] >= hi and g[i] < 0):
            g[i] = 0.0
    return FitResult(params=from_z(opt.x), initial=start, loss=final[2], loss_history=[float(h) for h in history],
                     iterations=nit, evaluations=evals[0], gradient_norm=float(np.linalg.norm(g)),
                     converged=bool(opt.success), message=str(opt.message), seconds=time.perf_counter() - t0,
                     frames=len(frames), vertices=int(len(vertices)), bounds={p: list(bnds[p]) for p in params})




def write_fitted_scene(scene_path, fitted: dict, out_path, header=None) -> str:
    """Write ``scene_path``'s document with ``fitted`` values written in (``[material]`` values,
    ``[contact] friction`` for ``contact_friction``, the ``friction`` of the ``[[collider]]`` that
    ``friction:<name>`` names) to ``out_path``: its input paths (mesh, surface, index files) re-anchored
    to the new folder, its ``[output]`` paths kept as they are (relative to the folder a scene is run
    from, so the fitted scene run from the same folder writes the files the original would)."""
    from warpfem.contact.scene import scene_collider_names
    from warpfem.scenes import SceneError
    from warpfem.scenes.schema import read_toml, rebase_scene_paths
    from warpfem.tradeoff.tune import toml_dumps

    doc = read_toml(scene_path, SceneError, what="scene file")
    cols = doc.get("collider") or []
    names = scene_collider_names(cols)
    for k, v in fitted.items():
        if k == CONTACT_FRICTION:
            doc.setdefault("contact", {})["friction"] = float(v)
        elif k.startswith(FRICTION_PREFIX):
            name = k[len(FRICTION_PREFIX):]
            if name not in names:
                raise DiffInputError(f"{scene_path}: no [[collider]] named {name!r} to write {k} into")
            cols[names.index(name)]["friction"] = float(v)
        elif doc.get("body"):  # a one-body [[body]] scene (fit takes no material parameter of several)
            doc["body"][0].setdefault("material", {})[k] = float(v)
        else:
            doc.setdefault("material", {})[k] = float(v)
    src_dir = os.path.dirname(os.path.abspath(scene_path))
    out_dir = os.path.dirname(os.path.abspath(out_path))
    output = dict(doc.get("output") or {})
    rebase_scene_paths(doc, src_dir, out_dir)
    if output:  # outputs are relative to the folder a scene is run from, not to the scene file: kept
        doc["output"] = output
    os.makedirs(out_dir, exist_ok=True)
    with open(out_path, "w") as f:
        if header:
            f.write("".join(f"# {line}\n" for line in header))
        f.write(toml_dumps(doc))
    return out_path
