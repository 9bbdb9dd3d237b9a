"""``warpfem tune`` on a scene whose mesh is a surface file: its physics mesh size (``target_tets``,
candidates below the scene's value) and float32 are in the search space, and the reference is a
finer mesh of the same surface, so the discretisation error of a coarser mesh is measured (not
just the solver and time-step error) and the reference's cost is reported."""

import numpy as np
import pytest

from warpfem.tradeoff.grid import TruthSpec
from warpfem.tradeoff.runner import scene_document, surface_target_tets
from warpfem.tradeoff.tune import format_tune, search_space, space_axes, tune

pytest.importorskip("tetgen", reason="the mesh extra (pip install warpfem[mesh]) is not installed")
pytest.importorskip("fast_simplification", reason="the mesh extra (pip install warpfem[mesh]) is not installed")


@pytest.fixture(autouse=True)
def cache_in_tmp(tmp_path, monkeypatch):
    monkeypatch.setenv("WARPFEM_CACHE_DIR", str(tmp_path / "cache"))


def _ball(tmp_path, target=100):
    """A 0.1 m sphere (an icosahedron split twice: 320 triangles), its base clamped, gravity."""
    from kernels_bench.scan_surface import midpoint_subdivide

    t = (1 + 5 ** 0.5) / 2
    V = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
                  [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    F = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
                  [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11],
                  [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    for _ in range(2):
        V, F = midpoint_subdivide(V, F)
    V = 0.1 * V / np.linalg.norm(V, axis=1, keepdims=True)
    (tmp_path / "ball.obj").write_text("".join(f"v {a:.17g} {b:.17g} {c:.17g}\n" for a, b, c in V)
                                       + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in F))
    scene = tmp_path / "ball.toml"
    scene.write_text(f"""gravity = [0.0, -9.81, 0.0]
[mesh]
path = "ball.obj"
target_tets = {target}
[material]
model = "stable_neo_hookean"
youngs_modulus = 2e4
poisson_ratio = 0.3
density = 1000.0
[[fixed]]
box_min = [-1.0, -1.0, -1.0]
box_max = [1.0, -0.07, 1.0]
[integrator]
type = "backward_euler"
[output]
fps = 24
frames = 2
""")
    return str(scene)


def test_surface_scene_space_has_target_tets_and_float32(tmp_path):
    scene = _ball(tmp_path)
    doc = scene_document(scene)
    assert surface_target_tets(doc) == 100
    axes = space_axes("default", doc)
    assert axes["target_tets"] == [25, 50, 100] and axes["precision"] == ["float32", "float64"]
    cands, _ = search_space(doc, scene, {"integrator": ["backward_euler"], "element": ["tet4"], "substeps": [1]})
    assert {(c.target_tets, c.precision) for c in cands} == {(t, p) for t in (25, 50, 100) for p in ("float32", "float64")}
    # a box scene's default space is unchanged (float64, no mesh-size axis)
    assert surface_target_tets({"mesh": {"generator": "box"}}) is None
    assert "target_tets" not in space_axes("default", {"mesh": {"generator": "box"}})


def test_tune_measures_the_discretisation_error_of_target_tets(tmp_path):
    scene = _ball(tmp_path)
    axes = {"integrator": ["backward_euler"], "element": ["tet4"], "substeps": [1]}
    res = tune(scene, 1.0, frames=2, axes=axes, truth=TruthSpec(element="tet4", refine=2, substeps=2), cost="work",
               keep=1)
    ref = res.reference
    assert ref["kind"] == "converged" and "finer mesh of the same surface (target_tets = 800" in ref["flag"]
    # the reference mesh is finer than every candidate's: its cost is reported
    assert ref["cost"]["elements"] > 1.5 * 100 and ref["cost"]["work"] > 0
    disc = {k: v["discretisation_tip_error"] for k, v in ref["meshes"].items()}
    assert set(disc) == {"tet4 tets=25", "tet4 tets=50", "tet4 tets=100"}
    assert all(0.0 < d < 1.0 for d in disc.values())
    assert disc["tet4 tets=25"] > disc["tet4 tets=100"]  # the coarser physics mesh is the less accurate
    text = format_tune(res)
    assert "finer mesh of the same surface" in text and "the reference run cost" in text
    assert "no discretisation error" not in text
    w = res.winner
    assert w is not None and w["discretisation_error"] == pytest.approx(disc[f"tet4 tets={w['config']['target_tets']}"])
    ran = {r["config"]["precision"] for rung in res.rungs for r in rung["evaluated"] if r["status"] == "ok"}
    assert ran == {"float32", "float64"}
