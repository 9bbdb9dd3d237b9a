"""Longer steps along accepted Newton steps (``NewtonOptions.extrapolate``): where SPD projection
makes projected Newton's steps short (the twisted bar's self contact: the per-pair projection of the
barrier's Hessian adds curvature the energy does not have), the secant step along the Newton
direction cuts the Newton iterations; the solution is the same, every kept step lowers the energy,
and the coils stay intersection-free."""

import os

import numpy as np
import pytest

from test_contact_scenes import _no_intersection

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FRAMES = 68  # the bar first touches itself in frame 62


def _run(precision, extrapolate):
    from warpfem.scenes import load_scene

    run = load_scene(os.path.join(ROOT, "examples", "scenes", "twisted_bar.toml")).build(precision=precision)
    sim = run.sim
    sim.options.extrapolate = extrapolate
    stats = []
    step = sim.step

    def recorded():
        st = step()
        stats.append(st)
        return st

    sim.step = recorded
    for _ in range(FRAMES):
        run.step_frame(total_frames=90)
    return run, stats


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_extrapolation_cuts_self_contact_iterations_and_keeps_the_solution(precision):
    run_off, off = _run(precision, False)
    run_on, on = _run(precision, True)
    assert all(st.converged for st in off + on)
    contact = slice(61, FRAMES)  # one step per frame
    its_off = sum(st.newton_iterations for st in off[contact])
    its_on = sum(st.newton_iterations for st in on[contact])
    # measured: float64 216 -> 114, float32 (its own friction-free path) similar
    assert its_on <= 0.75 * its_off, (its_on, its_off)
    assert sum(st.extrapolations for st in on) > 0 and sum(st.extrapolations for st in off) == 0
    # free frames: the elastic steps converge quadratically, nothing to lengthen there
    assert sum(st.extrapolations for st in on[:55]) <= 2
    # every accepted iterate lowers the energy (an extrapolated one only if below the full step's)
    # (float32: up to the line search's round-off allowance, 16 eps of the energy's terms)
    slack = 1e-9 if precision == "float64" else 16 * np.finfo(np.float32).eps
    for st in on:
        E = [h[0] for h in st.history]
        rise = max([b - a for a, b in zip(E, E[1:])] + [0.0])
        assert rise <= slack * max(abs(e) for e in E), (rise, E)
    longer = [h[2] for st in on for h in st.history if h[2] > 1.0]
    assert longer and max(longer) <= 32.0
    # the same solution: the steps converge to tol 1e-6 of their start gradient
    x_off, x_on = run_off.sim.positions(), run_on.sim.positions()
    tol = 1e-5 if precision == "float64" else 2e-3
    assert np.abs(x_on - x_off).max() < tol
    assert _no_intersection(x_on, run_on.model)
