"""Where a contact step's Newton iterations go: the history of every Newton iteration of the contact
steps of a case of ``bench_contact_cost.py`` (its relative gradient, step length, friction lag update,
the iterate's largest vertex move, and the distance of each iterate to the step's final positions),
and a summary of where the iterations are spent.

Per Newton iteration k of a step (iterate k-1 -> k):

* ``rel``: ||P g|| at iterate k over the step's reference (the tolerance test's quantity);
* ``alpha``: its step length (> 1: extrapolated, < 1: the collision bound or the line search);
* ``lag``: whether friction's lagged normal forces were taken again after it (``rel_before``: the
  relative gradient before that update, ``rel`` the one after); ``kept``: whether the update was
  looked at there and not made (``friction_update_tol``: the normal forces changed by less);
* ``move``: max_i |x_k - x_{k-1}|_inf over the body size L (the bounding-box diagonal of the rest
  mesh), ``move_v``: that move over h, in L per second; ``dir_v`` the full Newton direction's
  (move / alpha) over h, in L per second;
* ``dist``: max_i |x_{k-1} - x_final|_inf / L, the distance of the iterate the iteration *starts*
  from to the step's final positions (that of the solve's tolerance).

Iterations are counted as "tail" when they start within 1e-6 L (and 1e-5, 1e-4) of the final
positions, and "short" when alpha < 1.

    PYTHONPATH=. .venv/bin/python kernels_bench/newton_history.py --case box_drop --precision float64
        [--frames 60] [--first-contact-frames N] [--json PATH] [--summary PATH] [--config key=value,...]

Summaries of the runs in docs/contact.md: kernels_bench/results/contact_cost/newton_history.json.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.dirname(HERE))

import bench_contact_cost as B  # noqa: E402
import warpfem.simulator as S  # noqa: E402


def record_histories(case, precision, frames, first_contact_frames=None, config=None, device="cpu", log=print):
    run = B.build_case(case, precision, device)
    sim = run.sim
    for k, v in (config or {}).items():
        if hasattr(sim.options, k):
            setattr(sim.options, k, v)
        else:
            setattr(sim, k, v)
    L = float(np.linalg.norm(np.ptp(np.asarray(run.model.rest_positions, dtype=np.float64), axis=0)))
    steps = []
    orig = S.newton_solve

    def solve(pot, y, opts, *a, **kw):
        xs = [pot.x_of(y).numpy().astype(np.float64).copy()]
        alphas, lags, rels, kept = [], [], [], []  # rels: the relative gradient before a lag update
        hook = pot.after_iteration
        dirs = [None]  # (max |d| raw, max |d| filtered) of the last Newton system, in x units
        raws = []
        solve_sys = pot.solve_newton_system

        def solve_system(yy, g, d, o):
            lin = solve_sys(yy, g, d, o)
            raw = pot.unfiltered_direction()
            dn = float(np.abs(d.numpy()).max()) * abs(pot.s)
            dirs[0] = (float(np.abs(raw.numpy()).max()) * abs(pot.s) if raw is not None else dn, dn)
            return lin

        pot.solve_newton_system = solve_system

        def after(yy, alpha=1.0, residual=0.0):
            n0, k0 = pot.lag_updates, getattr(pot, "lags_kept", 0)
            changed = hook(yy, alpha, residual=residual)
            kept.append(getattr(pot, "lags_kept", 0) > k0)
            xs.append(pot.x_of(yy).numpy().astype(np.float64).copy())
            alphas.append(float(alpha))
            lags.append(pot.lag_updates > n0)
            rels.append(float(residual))
            raws.append(dirs[0])
            return changed

        pot.after_iteration = after
        try:
            st = orig(pot, y, opts, *a, **kw)
        finally:
            del pot.after_iteration
            del pot.solve_newton_system
        ref = st.initial_gradient
        xf = xs[-1]
        h = float(sim.dt)
        its = []
        for k in range(1, len(xs)):
            move = float(np.abs(xs[k] - xs[k - 1]).max()) / L
            its.append(dict(rel=float(st.history[k - 1][1] / ref) if ref > 0 else 0.0, rel_before=rels[k - 1],
                            alpha=alphas[k - 1],
                            lag=bool(lags[k - 1]), kept=bool(kept[k - 1]), move=move, move_v=move / h,
                            dir_v=move / h / max(alphas[k - 1], 1e-300),
                            dist=float(np.abs(xs[k - 1] - xf).max()) / L,
                            raw_v=(raws[k - 1][0] / h / L if raws[k - 1] else None),
                            filt_v=(raws[k - 1][1] / h / L if raws[k - 1] else None)))
        steps.append(dict(iterations=its, converged=bool(st.converged), reason=st.reason,
                          newton=int(st.newton_iterations), residual=float(st.residual)))
        return st

    S.newton_solve = solve
    out = []
    try:
        contact_before = B.in_contact(sim)
        contact_frames = 0
        for f in range(1, frames + 1):
            n0 = len(steps)
            run.advance()
            contact = contact_before or B.in_contact(sim)
            contact_before = B.in_contact(sim)
            for s in steps[n0:]:
                s.update(frame=f, contact=contact)
            out.extend(steps[n0:])
            if contact:
                contact_frames += 1
                log(f"  {case} {precision} frame {f}: contact, {sum(s['newton'] for s in steps[n0:])} Newton")
                if first_contact_frames and contact_frames >= first_contact_frames:
                    break
    finally:
        S.newton_solve = orig
    return dict(case=case, precision=precision, body_size=L, dt=float(sim.dt), steps=out)


def summarize(r):
    steps = [s for s in r["steps"] if s["contact"]]
    free = [s for s in r["steps"] if not s["contact"]]
    its = [it for s in steps for it in s["iterations"]]
    n = len(its)
    out = dict(case=r["case"], precision=r["precision"], contact_steps=len(steps), iterations=n,
               free_steps=len(free), free_iterations=sum(len(s["iterations"]) for s in free))
    if not n:
        return out
    for thr in (1e-4, 1e-5, 1e-6):
        out[f"tail_{thr:.0e}"] = sum(it["dist"] <= thr for it in its) / n
    out["short"] = sum(it["alpha"] < 1.0 for it in its) / n
    # a step length that is a power of 2 below 1 was halved from the full step by the line search
    # (Armijo); any other below 1 started at the collision (CCD) bound
    halved = [it["alpha"] < 1.0 and float(np.log2(it["alpha"])).is_integer() for it in its]
    out["short_halved"] = sum(halved) / n
    out["short_ccd"] = sum(it["alpha"] < 1.0 and not hv for it, hv in zip(its, halved)) / n
    per_step_before = per_step_after = 0
    halved_after = 0
    for st in steps:
        ks = [k for k, it in enumerate(st["iterations"]) if it["lag"]]
        if ks:
            per_step_before += ks[0] + 1
            per_step_after += len(st["iterations"]) - 1 - ks[0]
            halved_after += sum(it["alpha"] < 1.0 and float(np.log2(it["alpha"])).is_integer()
                                for it in st["iterations"][ks[0] + 1:])
    out["steps_with_lag"] = sum(any(it["lag"] for it in st["iterations"]) for st in steps)
    # steps whose lag update was not made (friction_update_tol: the normal forces changed by less)
    out["steps_lag_kept"] = sum(any(it.get("kept", False) for it in st["iterations"]) for st in steps)
    out["newton_per_contact_step"] = n / len(steps)
    out["newton_per_free_step"] = out["free_iterations"] / len(free) if free else None
    # lag updates made at an iterate already within the solve's tolerance (1e-6 of the reference):
    # the update then works as a re-solve; and the iterations after those
    at_tol = [(st, k) for st in steps for k, it in enumerate(st["iterations"]) if it["lag"] and it["rel_before"] <= 1e-6]
    out["lag_updates_within_tol"] = len(at_tol)
    out["iterations_after_lag_within_tol"] = sum(len(st["iterations"]) - 1 - k for st, k in at_tol)
    jumps = [it["rel"] for st in steps for it in st["iterations"] if it["lag"]]
    out["rel_after_lag_quantiles"] = np.quantile(jumps, [0.25, 0.5, 0.75]).tolist() if jumps else None
    out["iterations_to_lag"] = per_step_before
    out["iterations_after_lag"] = per_step_after
    out["halved_after_lag"] = halved_after
    out["extrapolated"] = sum(it["alpha"] > 1.0 for it in its) / n
    out["lag_updates"] = sum(it["lag"] for it in its)
    # iterations after the step's last lag update
    after_lag = 0
    for s in steps:
        ks = [k for k, it in enumerate(s["iterations"]) if it["lag"]]
        if ks:
            after_lag += len(s["iterations"]) - 1 - ks[-1]
    out["after_last_lag"] = after_lag / n
    # iterations whose start's relative gradient is below 1e-2 (the lag threshold)...
    below = 0
    for s in steps:
        prev = 1.0
        for it in s["iterations"]:
            below += prev <= 1e-2
            prev = it["rel"]
    out["start_rel_below_1e-2"] = below / n
    # the full Newton direction's largest vertex speed (L / s) at iterations within 1e-6 L
    dv = np.array([it["dir_v"] for it in its])
    dist = np.array([it["dist"] for it in its])
    out["dir_v_quantiles_tail"] = (np.quantile(dv[dist <= 1e-6], [0.1, 0.5, 0.9]).tolist() if (dist <= 1e-6).any()
                                   else None)
    out["dir_v_quantiles_far"] = (np.quantile(dv[dist > 1e-4], [0.1, 0.5, 0.9]).tolist() if (dist > 1e-4).any()
                                  else None)
    # the linear rate of the tail: median of rel_k / rel_{k-1} over iterations with alpha == 1 and dist <= 1e-5
    rates = []
    for s in steps:
        prev = None
        for it in s["iterations"]:
            if prev is not None and it["alpha"] == 1.0 and it["dist"] <= 1e-5 and prev > 0:
                rates.append(it["rel"] / prev)
            prev = it["rel"]
    out["tail_rate_median"] = float(np.median(rates)) if rates else None
    # iterations a step test at tol_v would save: after the first iteration whose (unfiltered) Newton
    # direction's largest vertex speed is below tol_v L/s, taken once friction's lag update (when the
    # step makes one) is done, the step ends; saved = the iterations after it, left = the distance of
    # the point it ends at to the final positions
    for key in ("raw_v", "dir_v"):
        for tol_v in (1e-2, 1e-3, 1e-4):
            saved, left = simulate_stop(steps, tol_v, key)
            out[f"saved_{key}_{tol_v:.0e}"] = saved / n
            out[f"left_{key}_{tol_v:.0e}"] = left
    fits = [len(s["iterations"]) for s in free]
    out["free_saved_raw_v_1e-03"] = simulate_stop(free, 1e-3, "raw_v")[0]
    return out


def simulate_stop(steps, tol_v, key="raw_v"):
    """(iterations saved, largest distance / L left) by a stop when the direction's speed (``key``)
    is below tol_v L/s, after the step's lag update if it makes one."""
    saved = left = 0
    for s in steps:
        its = s["iterations"]
        lag_at = [k for k, it in enumerate(its) if it["lag"]]
        first_ok = lag_at[0] + 1 if lag_at else 0  # directions computed after the lag update
        for k, it in enumerate(its):
            v = it.get(key)
            if k >= first_ok and v is not None and v < tol_v and not it["lag"]:
                saved += len(its) - 1 - k
                left = max(left, its[k + 1]["dist"] if k + 1 < len(its) else 0.0)
                break
    return saved, left


def print_steps(r, limit=None):
    for s in r["steps"]:
        if not s["contact"]:
            continue
        print(f"frame {s['frame']} step: {s['newton']} Newton, {s['reason']}")
        for k, it in enumerate(s["iterations"][:limit]):
            print(f"   {k + 1:3d} rel {it['rel']:.1e} alpha {it['alpha']:.3g} lag {int(it['lag'])} "
                  f"move {it['move']:.1e} L (dir {it['dir_v']:.1e} L/s) start dist {it['dist']:.1e} L")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="box_drop")
    ap.add_argument("--precision", default="float64")
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--first-contact-frames", type=int, default=None)
    ap.add_argument("--config", default="", help="key=value,... (NewtonOptions fields or simulator attributes)")
    ap.add_argument("--print", action="store_true", help="every contact step's iterations")
    ap.add_argument("--json", default=None, help="every step's history (JSON)")
    ap.add_argument("--summary", default=None, help="a JSON file of summaries (updated: one entry per case/precision)")
    a = ap.parse_args(argv)
    config = {}
    for kv in filter(None, a.config.split(",")):
        k, v = kv.split("=")
        config[k] = json.loads(v)
    frames = a.frames or B.DEFAULT_FRAMES[a.case]
    r = record_histories(a.case, a.precision, frames, a.first_contact_frames, config)
    if a.print:
        print_steps(r)
    print(json.dumps(summarize(r), indent=1))
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(r, fh)
    if a.summary:  # summaries of several runs, one file (case/precision keys)
        try:
            with open(a.summary) as fh:
                allsum = json.load(fh)
        except FileNotFoundError:
            allsum = {}
        allsum[f"{a.case}/{a.precision}"] = dict(summarize(r), frames=frames, first_contact_frames=a.first_contact_frames,
                                                 config=config)
        with open(a.summary, "w") as fh:
            json.dump(allsum, fh, indent=1, sort_keys=True)


if __name__ == "__main__":
    main()
