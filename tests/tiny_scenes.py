"""Small scene files shared by the tests: a 1 m clamped beam of a few Tet4 cells (trade-off tests)
and an 8 m clamped beam of 8 cells with an optional handle at its free end (reduced-run tests: as a
scene file, as a Python model, and the runners that step them); and the 4-cell command-line beam of
the CLI and first-hour tests."""


def cli_beam_toml(*, frames: int = 5) -> str:
    """The command-line tests' beam: 1 m x 0.2 m x 0.2 m, 4 x 1 x 1 Tet4 cells, E 1e5, clamped at
    x = 0, gravity along -y, backward Euler at dt 0.025, 20 fps, ``frames`` frames (no states file)."""
    return f"""
gravity = [0.0, -9.81, 0.0]
[mesh]
generator = "box"
size = [1.0, 0.2, 0.2]
cells = [4, 1, 1]
[material]
model = "stable_neo_hookean"
youngs_modulus = 1e5
poisson_ratio = 0.3
[[fixed]]
box_min = [-1.0, -1.0, -1.0]
box_max = [0.0, 1.0, 1.0]
[integrator]
type = "backward_euler"
dt = 0.025
[output]
fps = 20
frames = {frames}
"""


def tiny_beam_toml(name: str = "tiny_beam", *, cells: int = 4, frames: int = 2) -> str:
    """A clamped stable neo-Hookean beam, 1 m x 0.2 m x 0.2 m, `cells` x 1 x 1 cells, 24 fps."""
    return f"""
name = "{name}"
gravity = [0.0, -9.81, 0.0]
[mesh]
generator = "box"
size = [1.0, 0.2, 0.2]
cells = [{cells}, 1, 1]
[material]
model = "stable_neo_hookean"
youngs_modulus = 2.0e5
poisson_ratio = 0.3
density = 1000.0
[[fixed]]
box_min = [-1.0, -1.0, -1.0]
box_max = [0.0, 1.0, 1.0]
[integrator]
type = "backward_euler"
tol = 1e-6
cg_tol = 1e-4
[output]
fps = 24
frames = {frames}
"""


def handle_toml(axis=None, angle: float = 90.0) -> str:
    """A [[handle]] over the free end (x = 8 m) of :func:`reduced_beam_toml`'s beam, turning by
    ``angle`` degrees about ``axis`` over the run (no rotation when ``axis`` is None)."""
    text = "[[handle]]\nbox_min = [8.0, -1.0, -1.0]\nbox_max = [9.0, 2.0, 2.0]\n"
    if axis is not None:
        text += f"rotation_axis = [{axis[0]:.1f}, {axis[1]:.1f}, {axis[2]:.1f}]\nrotation_angle = {angle}\n"
    return text


def reduced_beam_toml(name: str, *, g: float = 0.0, handle: str = "", integrator: str = "backward_euler",
                      frames: int = 12, states: bool = False, subspace: str = "") -> str:
    """A clamped stable neo-Hookean beam, 8 m x 1 m x 1 m, 8 x 1 x 1 cells, gravity ``g`` along z,
    30 fps, mass damping 2; ``handle``, ``subspace`` are TOML text appended in place."""
    states_line = f'states = "{name}.npz"\n' if states else ""
    return f"""
name = "{name}"
gravity = [0.0, 0.0, {g}]
[mesh]
generator = "box"
size = [8.0, 1.0, 1.0]
cells = [8, 1, 1]
[material]
model = "stable_neo_hookean"
youngs_modulus = 1e6
poisson_ratio = 0.3
density = 100.0
[[fixed]]
box_min = [-1.0, -1.0, -1.0]
box_max = [1e-6, 2.0, 2.0]
{handle}
[integrator]
type = "{integrator}"
damping_mass = 2.0
tol = 1e-8
[output]
fps = 30
frames = {frames}
{states_line}{subspace}
"""


def scene_positions(path):
    """Build the scene at ``path`` and run all its frames: (the run, positions (frames + 1, n, 3),
    the rest pose first). Non-converged steps only warn (the tests check the numbers)."""
    import warnings

    import numpy as np

    from warpfem.scenes import load_scene

    run = load_scene(path).build()
    xs = [run.sim.positions()]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for _ in range(run.frames):
            run.step_frame()
            xs.append(run.sim.positions())
    return run, np.array(xs)


def step_positions(sim, steps: int):
    """Positions of ``sim`` now and after each of ``steps`` steps, (steps + 1, n, 3); non-converged
    steps only warn (the tests check the numbers)."""
    import warnings

    import numpy as np

    xs = [sim.positions()]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for _ in range(steps):
            sim.step()
            xs.append(sim.positions())
    return np.array(xs)


def reduced_beam_model(gravity=(0.0, 0.0, -9.81)):
    """The beam of :func:`reduced_beam_toml` built in Python: a ``warpfem.Model``, clamped at x = 0."""
    import warpfem as wf

    mesh = wf.box_tet_mesh(size=(8.0, 1.0, 1.0), cells=(8, 1, 1))
    model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=1e6, poisson_ratio=0.3, density=100.0), gravity=gravity)
    model.fix(wf.select_vertices_in_box(mesh.vertices, (-1, -1, -1), (1e-6, 2, 2)))
    return model


def beam_on_block_model(E: float = 1e5, dforce=None):
    """Two bodies for the surface-contact gradient tests: a Tet4 beam (0.2 x 0.05 x 0.05 m, 2 x 1 x 1
    cells, E ``E``) pushed down by 0.5 N per vertex and gravity onto a Hex8 block (0.3 x 0.1 x
    0.05 m, E 1e5) 9 mm below it whose bottom face is clamped; stable neo-Hookean, nu 0.3, 1000
    kg/m^3. ``dforce`` (n, 3) is added to the applied forces. Returns the model (the beam's
    vertices first)."""
    import numpy as np

    import warpfem as wf

    top = wf.box_tet_mesh(size=(0.2, 0.05, 0.05), cells=(2, 1, 1))
    base = wf.box_hex_mesh(size=(0.3, 0.1, 0.05), cells=(2, 1, 1))
    bodies = [wf.Body(top, wf.StableNeoHookean(youngs_modulus=E, poisson_ratio=0.3, density=1000.0), name="top"),
              wf.Body(base, wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0), name="base",
                      offset=(-0.05, -0.025, -0.059))]
    model = wf.Model.from_bodies(bodies, gravity=(0.0, 0.0, -9.81))
    model.forces[:top.num_vertices] = (0.0, 0.0, -0.5)
    if dforce is not None:
        model.forces[:] += dforce
    model.fix(np.flatnonzero(model.rest_positions[:, 2] < -0.05))  # the block's bottom face
    return model


def soft_box_toml(*, cells: int = 1, origin=None) -> str:
    """The head of the contact tests' scenes: gravity along -y and a 10 cm stable neo-Hookean box
    (E 1e5, nu 0.3) of ``cells``^3 Tet4 cells with its corner at ``origin`` (default 0)."""
    at = "" if origin is None else f"origin = {list(map(float, origin))}\n"
    return (f'gravity = [0.0, -9.81, 0.0]\n[mesh]\ngenerator = "box"\nsize = [0.1, 0.1, 0.1]\n'
            f'cells = [{cells}, {cells}, {cells}]\n{at}[material]\nmodel = "stable_neo_hookean"\n'
            'youngs_modulus = 1e5\npoisson_ratio = 0.3\n')
