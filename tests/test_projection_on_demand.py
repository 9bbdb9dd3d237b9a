"""Project-on-demand Newton (``hessian_projection = "on_demand"``, the default): each solve starts
from the exact Hessian and projects only once a Newton system is indefinite, its direction is not a
descent direction or its full step fails (Longva et al. 2023, "Pitfalls of Projection: A study of
Newton-type solvers for incremental potentials"). Projected Newton's clamping makes it converge
linearly where the exact Hessian is definite; on demand keeps Newton's quadratic convergence there
and falls back to the projection where it is needed."""

import numpy as np
import pytest

import warpfem as wf
from kernels_bench import stability_cases as S


def _squeezed_beam(mode, *, solver="direct", dt=1.0 / 60.0, steps=3, precision="float64"):
    """stability_cases.squeezed_beam: compressed elements whose dP/dF the projection clamps."""
    sim, advance = S.squeezed_beam(steps, precision=precision, dt=dt, linear_solver=solver, hessian_projection=mode,
                                   tol=1e-8)
    stats = [advance(k) for k in range(steps)]
    return stats, sim.positions()


@pytest.mark.parametrize("solver", ["direct", "pcg"])
def test_on_demand_keeps_newtons_quadratic_convergence_and_the_same_answer(solver):
    st_p, x_p = _squeezed_beam("always", solver=solver)
    st_d, x_d = _squeezed_beam("on_demand", solver=solver)
    assert all(s.converged for s in st_p + st_d)
    # the same steps: positions agree far below the 5 cm motion
    assert np.abs(x_p - x_d).max() < 1e-6
    n_p = [s.newton_iterations for s in st_p]
    n_d = [s.newton_iterations for s in st_d]
    assert max(n_d) <= 5 and 2 * sum(n_d) <= sum(n_p), (n_d, n_p)  # measured: [5, 4, 3] against [10, 12, 14]
    assert all(s.projected_retries == 0 for s in st_d)  # the exact Hessian was definite throughout
    # quadratic: the last reduction of the gradient is far larger than projected Newton's linear rate
    g_d = [h[1] for h in st_d[-1].history]
    g_p = [h[1] for h in st_p[-1].history]
    assert g_d[-1] / g_d[-2] < 1e-3 < g_p[-1] / g_p[-2], (g_d, g_p)


@pytest.mark.parametrize("solver", ["direct", "pcg"])
def test_on_demand_projects_when_the_exact_hessian_is_indefinite(solver):
    """At dt = 1 s the squeeze is nearly quasi-static and the beam buckles: the exact Hessian of the
    first Newton system is indefinite, the step switches to the projection and still converges to
    projected Newton's answer."""
    st_p, x_p = _squeezed_beam("always", solver=solver, dt=1.0, steps=4)
    st_d, x_d = _squeezed_beam("on_demand", solver=solver, dt=1.0, steps=4)
    assert st_p[0].converged and st_d[0].converged
    assert st_d[0].projected_retries == 1 and st_p[0].projected_retries == 0
    assert sum(s.newton_iterations for s in st_d) <= sum(s.newton_iterations for s in st_p)


def test_hessian_projection_is_validated_and_a_scene_key():
    from warpfem.scenes.schema import INTEGRATOR_KEYS

    mesh = wf.box_tet_mesh(size=(1.0, 0.2, 0.2), cells=(2, 1, 1))
    model = wf.Model(mesh, wf.make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0))
    with pytest.raises(ValueError, match="hessian_projection must be one of"):
        wf.Simulator(model, hessian_projection="sometimes")
    assert INTEGRATOR_KEYS["hessian_projection"].default == "on_demand"
    assert wf.Simulator(model).options.hessian_projection == "on_demand"
