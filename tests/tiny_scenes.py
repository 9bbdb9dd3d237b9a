"""Small scene files shared by the trade-off tests (a 1 m clamped beam of a few Tet4 cells)."""


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
