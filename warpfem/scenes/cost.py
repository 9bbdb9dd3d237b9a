"""An estimate of a scene's cost per frame before it runs (``warpfem describe``).

    seconds per frame = steps per frame x Newton iterations per step x seconds per iteration
                        x CONTACT_FACTOR (when the scene has contact)

* steps per frame: ``[integrator] substeps`` (dynamic), ``load_steps`` (static);
* Newton iterations per step: ``NEWTON_PER_STEP`` (1 for ``stiffness_warping``: one linear solve);
* seconds per Newton iteration on a CPU, by the number of mesh vertices n:
  ``ITERATION_OVERHEAD_S + ITERATION_S_PER_VERTEX_POWER * n ** VERTEX_POWER`` (the sparse direct
  factorisation grows faster than the mesh: n^1.5 fits the measurements below to 10-20 %).

Calibration (``kernels_bench/bench_cost_estimate.py``, ``kernels_bench/results/cost_estimate.json``;
and ``kernels_bench/results/target_tets.json``: the bunny meshed to 2,950-35,870 tets, 797-9,293
vertices, 0.016-0.61 s per Newton iteration, 7-11 iterations per step with mass damping; the
scan stand-in, 5,988 vertices, 3-5 iterations at 0.22 s). Contact: ``kernels_bench/results/contact_cost``
(a box dropped on a plane with friction: contact frames 2.35x the time of free frames, 2.6x the
Newton iterations). The estimate is for a CPU in float64 (float32 on a CPU is within ~20 % of it);
on a GPU the per-iteration time is smaller and is not calibrated here. It is meant to say "seconds"
or "minutes" before a long run, not to time it: within ``STATED_FACTOR`` either way on the free
scenes and the ball in a bowl measured; a hard scene is off by more (the twisted bar, 45 Newton
iterations per frame: 11x more than estimated; the bunny drop, whose contact iterations are cheap
at its small step: 5x less).
"""

from __future__ import annotations

__all__ = ["estimate_frame_cost", "NEWTON_PER_STEP", "CONTACT_FACTOR", "ITERATION_OVERHEAD_S",
           "ITERATION_S_PER_VERTEX_POWER", "VERTEX_POWER", "STATED_FACTOR"]

#: Newton iterations per step assumed (measured 2-6 on the shipped scenes of bench_cost_estimate.py,
#: 7-11 on the bunny with mass damping, 53 on the twisted bar: a hard scene is underestimated).
NEWTON_PER_STEP = 4.0
#: Time factor of a scene with contact (colliders or several bodies).
CONTACT_FACTOR = 2.5
#: Fixed seconds per Newton iteration on a CPU (kernel launches, Python; a 100-vertex mesh).
ITERATION_OVERHEAD_S = 2.5e-3
#: ... plus this times n_vertices ** VERTEX_POWER.
ITERATION_S_PER_VERTEX_POWER = 7.0e-7
VERTEX_POWER = 1.5
#: The estimate holds within this factor either way on typical scenes (kernels_bench/bench_cost_estimate.py).
STATED_FACTOR = 3.0


def estimate_frame_cost(*, vertices, steps_per_frame, frames, contact=False, newton=True) -> dict:
    """The estimate and its basis: ``seconds_per_frame``, ``seconds_total``, ``newton_per_frame``,
    ``seconds_per_iteration``, ``contact_factor`` and a one-line ``basis``."""
    per_iter = ITERATION_OVERHEAD_S + ITERATION_S_PER_VERTEX_POWER * float(vertices) ** VERTEX_POWER
    its = NEWTON_PER_STEP if newton else 1.0
    factor = CONTACT_FACTOR if contact else 1.0
    newton_per_frame = steps_per_frame * its
    per_frame = newton_per_frame * per_iter * factor
    basis = (f"{steps_per_frame} step(s) per frame x {its:g} {'Newton iterations' if newton else 'linear solve'} x "
             f"{per_iter * 1e3:.3g} ms per iteration for {vertices} vertices on a CPU"
             + (f" x {CONTACT_FACTOR:g} for contact" if contact else ""))
    return {"seconds_per_frame": per_frame, "seconds_total": per_frame * frames, "newton_per_frame": newton_per_frame,
            "seconds_per_iteration": per_iter, "contact_factor": factor, "stated_factor": STATED_FACTOR, "basis": basis}
