"""The warpfem command line: run a tiny scene end to end, describe, version, failures."""

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from warpfem.cli import main
from warpfem.io import read_usd_mesh_frames, usd_validation_errors

from tiny_scenes import cli_beam_toml

SCENE = cli_beam_toml(frames=5) + 'states = "{states}"\n'

SURFACE_OBJ = "v 0.2 0.05 0.05\nv 0.9 0.05 0.05\nv 0.9 0.15 0.05\nv 0.5 0.1 0.15\nf 1 2 3\nf 1 2 4\nf 2 3 4\nf 3 1 4\n"


def write_scene(tmp_path, text, name="tiny.toml"):
    p = tmp_path / name
    p.write_text(textwrap.dedent(text))
    return str(p)


def layer_info(path):
    from pxr import Sdf

    layer = Sdf.Layer.FindOrOpen(str(path))
    layer.Reload()
    return dict(layer.customLayerData)["warpfem"]


def check_usd(path, name, num_points, num_frames):
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(path))
    assert stage.GetStartTimeCode() == 0 and stage.GetEndTimeCode() == num_frames - 1
    assert stage.GetTimeCodesPerSecond() == 20 and UsdGeom.GetStageUpAxis(stage) == "Y"
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath(f"/Root/{name}"))
    times, frames = read_usd_mesh_frames(path, name)
    assert times.tolist() == list(range(num_frames))
    for t, p in zip(times, frames):
        assert p.shape == (num_points, 3)
        ext = np.array(mesh.GetExtentAttr().Get(t))
        np.testing.assert_array_equal(ext, np.stack([p.min(axis=0), p.max(axis=0)]))
    assert usd_validation_errors(stage) == []
    return frames


def test_run_end_to_end(tmp_path, capsys):
    states = tmp_path / "states.npz"
    scene = write_scene(tmp_path, SCENE.format(states=states))
    out = tmp_path / "out" / "tiny.usda"
    assert main(["run", scene, "--device", "cpu", "--precision", "float64", "--frames", "3", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "frame 3/3" in printed and "t = 0.1500 s" in printed and "newton" in printed
    # boundary surface of the 4x1x1 box: all 20 vertices; frames 0 (rest) .. 3
    frames = check_usd(out, "boundary", 20, 4)
    assert layer_info(out)["complete"] is True
    # it falls: the free end moves down, the clamp stays
    assert frames[-1][:, 1].min() < -1e-3
    log = [json.loads(line) for line in (tmp_path / "out" / "tiny.stats.jsonl").read_text().splitlines()]
    assert [r["frame"] for r in log] == [1, 2, 3]
    assert all(r["converged"] and r["steps"] == 2 and r["newton_iterations"] >= 1 and r["cg_iterations"] >= 1 for r in log)
    assert {"step_seconds", "residual", "energy", "time"} <= set(log[0])
    st = np.load(states)
    assert st["positions"].shape == (4, 20, 3) and st["times"] == pytest.approx([0, 0.05, 0.1, 0.15])
    np.testing.assert_array_equal(st["positions"][0], st["rest"])
    # the USD holds the same boundary points (float32), in the same order as the boundary ids
    from warpfem.skinning import mesh_boundary_surface

    ids, _ = mesh_boundary_surface(st["rest"], np.asarray(__import__("warpfem").box_tet_mesh(size=(1, .2, .2), cells=(4, 1, 1)).tets))
    np.testing.assert_allclose(frames[-1], st["positions"][-1][ids], atol=1e-6)


def test_run_with_embedded_surface(tmp_path):
    (tmp_path / "s.obj").write_text(SURFACE_OBJ)
    scene = write_scene(tmp_path, SCENE.replace('states = "{states}"\n', "") + '[surface]\npath = "s.obj"\nname = "skin"\n')
    out = tmp_path / "skin.usda"
    assert main(["run", scene, "--frames", "2", "--out", str(out), "--quiet"]) == 0
    frames = check_usd(out, "skin", 4, 3)
    np.testing.assert_allclose(frames[0][0], [0.2, 0.05, 0.05], atol=1e-7)


def test_describe_and_version(tmp_path, capsys):
    scene = write_scene(tmp_path, SCENE.format(states="x.npz"))
    assert main(["describe", scene]) == 0
    text = capsys.readouterr().out
    assert "24 elements, 20 vertices" in text and "estimated device memory" in text and "no embedding" in text
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.strip() == "warpfem 0.1.0"


def test_invalid_scene_exits_nonzero_in_process(tmp_path, capsys):
    scene = write_scene(tmp_path, SCENE.format(states="x.npz").replace("poisson_ratio = 0.3", "poisson_ratio = 0.5"))
    out = tmp_path / "bad.usda"
    assert main(["run", scene, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "[material].poisson_ratio" in err and scene in err
    assert not out.exists()


def test_non_converged_step_exits_nonzero_and_marks_usd_incomplete(tmp_path, capsys):
    text = SCENE.format(states="x.npz").replace("dt = 0.025", "dt = 0.025\nrequire_convergence = true\nmax_iters = 1\ntol = 1e-12")
    out = tmp_path / "fail.usda"
    assert main(["run", write_scene(tmp_path, text), "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err.strip()
    assert "did not converge" in err and "frame 1" in err and err.count("\n") == 0
    info = layer_info(out)
    assert info["complete"] is False and info["framesWritten"] == 1 and "SolveFailed" in info["incompleteReason"]
    assert usd_validation_errors(out) == []


def test_invalid_scene_subprocess_exit_code(tmp_path):
    scene = write_scene(tmp_path, SCENE.format(states="x.npz").replace("[material]", "[material]\nyoungs_modulos = 3.0"))
    out = tmp_path / "never.usda"
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    r = subprocess.run([sys.executable, "-m", "warpfem.cli", "run", scene, "--out", str(out)], capture_output=True,
                       text=True, cwd=root, timeout=120)
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0, r.stderr
    assert "did you mean 'youngs_modulus'" in r.stderr and "[material].youngs_modulos" in r.stderr
    assert not out.exists()


def test_hex8_scene_end_to_end_writes_valid_clipped_usd(tmp_path):
    """A tiny Hex8 scene with an embedded surface: USD in value clips of 2 frames, valid, and the
    skinned surface equals W x of the simulated positions (8 shape functions per vertex)."""
    (tmp_path / "s.obj").write_text(SURFACE_OBJ)
    states = tmp_path / "h.npz"
    text = (SCENE.format(states=states).replace("cells = [4, 1, 1]", 'cells = [4, 1, 1]\nelement = "hex8"')
            .replace("frames = 5", "frames = 5\nclip_frames = 2") + '[surface]\npath = "s.obj"\nname = "skin"\n')
    out = tmp_path / "hex.usda"
    assert main(["run", write_scene(tmp_path, text), "--frames", "3", "--out", str(out), "--quiet"]) == 0
    frames = check_usd(out, "skin", 4, 4)
    assert layer_info(out)["complete"] is True and layer_info(out)["clips"] == 2
    assert sorted(os.listdir(tmp_path / "hex.clips")) == ["clip_000000.usdc", "clip_000001.usdc", "manifest.usda"]
    st = np.load(states)
    assert st["positions"].shape == (4, 20, 3)  # 5 x 2 x 2 hex nodes
    from warpfem.mesh import box_hex_mesh
    from warpfem.skinning import embed_points_in_mesh, load_surface

    emb = embed_points_in_mesh(load_surface(tmp_path / "s.obj")[0], box_hex_mesh(size=(1, .2, .2), cells=(4, 1, 1)))
    assert emb.weights.shape == (4, 8)
    for f in range(4):
        np.testing.assert_allclose(frames[f], emb.apply(st["positions"][f]), atol=2e-6)
    assert frames[-1][1, 1] < 0.05 - 1e-4  # the free end (x = 0.9) sags


def test_warp_banner_only_with_verbose(tmp_path):
    """Warp's start-up banner and module-load lines appear with --verbose only (fresh processes)."""
    scene = write_scene(tmp_path, SCENE.format(states=tmp_path / "v.npz"))
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    outputs = {}
    for flag in ([], ["--verbose"]):
        r = subprocess.run([sys.executable, "-m", "warpfem.cli", "run", scene, "--frames", "1", "--quiet",
                            "--out", str(tmp_path / "v.usda"), *flag], capture_output=True, text=True, cwd=root, timeout=300)
        assert r.returncode == 0, r.stderr
        outputs[bool(flag)] = r.stdout + r.stderr
    quiet, verbose = outputs[False], outputs[True]
    assert "Warp " not in quiet and "Module " not in quiet, quiet
    assert "initialized:" in verbose and "Module warpfem." in verbose and "load on device 'cpu'" in verbose, verbose


def test_describe_json_counts_and_outputs(tmp_path, capsys):
    """``describe --json`` is one JSON object with the counts the text prints (24 tets, 20 vertices, 4
    clamped vertices at x = 0), the outputs and the memory estimates."""
    text = SCENE.format(states="x.npz") + 'vtu = "out/tiny.pvd"\nusd = "out/tiny.usda"\n'
    scene = write_scene(tmp_path, text)
    assert main(["describe", scene, "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert main(["describe", scene]) == 0
    described = capsys.readouterr().out
    mesh = d["mesh"]
    assert (mesh["elements"], mesh["vertices"], mesh["dofs"], mesh["nodes_per_element"]) == (24, 20, 60, 4)
    assert mesh["quadrature_points_per_element"] == 1 and mesh["quadrature_points"] == 24 and mesh["element"] == "tet4"
    assert f"{mesh['elements']} elements, {mesh['vertices']} vertices" in described
    assert [s["vertices"] for s in d["selections"]["fixed"]] == [4] and "fixed #1: 4 vertices" in described
    assert d["material"]["model"] == "stable_neo_hookean" and d["material"]["youngs_modulus"] == 1e5
    assert d["integrator"]["type"] == "backward_euler" and d["integrator"]["substeps"] == 2 and d["integrator"]["dynamic"]
    assert (d["frames"], d["fps"], d["duration"]) == (5, 20.0, 0.25)
    assert d["render_surface"] == {"source": "boundary", "vertices": 20, "triangles": 36, "embedded": False}
    assert d["outputs"] == {"usd": "out/tiny.usda", "usd_clip_frames": 100, "states": "x.npz",
                            "stats": "out/tiny.stats.jsonl", "vtu": "out/tiny.pvd"}
    from warpfem.scenes.scene import _fmt_bytes

    mem = d["estimated_device_memory_bytes"]
    assert 0 < mem["float32"] < mem["float64"]
    assert f"estimated device memory (float64): {_fmt_bytes(mem['float64'])}" in described
    assert d["warpfem_version"] == __import__("warpfem").__version__


def test_preview_png_and_version_in_stats(tmp_path, capsys):
    """``--preview`` draws frames 0..3 (4 panels of 300 x 300 px) into a PNG; every stats record carries
    warpfem_version."""
    import matplotlib.image

    import warpfem

    scene = write_scene(tmp_path, SCENE.format(states=tmp_path / "p.npz"))
    png, out = tmp_path / "pic" / "p.png", tmp_path / "p.usda"
    assert main(["run", scene, "--frames", "3", "--out", str(out), "--preview", str(png), "--quiet"]) == 0
    assert 5_000 < png.stat().st_size < 200_000
    img = matplotlib.image.imread(str(png))
    assert img.shape[:2] == (300, 1200)
    rgb = img[..., :3]
    body = (rgb[..., 2] > rgb[..., 0] + 0.2)  # the blue-shaded surface
    assert 0.01 < body.mean() < 0.5
    # four panels, each with some of the body in it
    assert all(body[:, 300 * i:300 * (i + 1)].any() for i in range(4))
    log = [json.loads(line) for line in (tmp_path / "p.stats.jsonl").read_text().splitlines()]
    assert len(log) == 3 and all(r["warpfem_version"] == warpfem.__version__ for r in log)


PREVIEW_COLLIDERS = """
[[collider]]
type = "plane"
name = "floor"
point = [0.0, -0.4, 0.0]
[[collider]]
type = "sphere"
name = "ball"
center = [0.5, 0.7, 0.1]
radius = 0.1
translation = [0.6, 0.0, 0.0]
ramp_time = 0.15
"""


def test_preview_draws_colliders_at_one_scale(tmp_path, monkeypatch):
    """A beam under a floor-plane and a moving sphere (both out of reach), previewed at frames 0..3: every
    panel has the same limits, enclosing the body and both colliders, and the same view; each panel
    holds the body and one artist per collider (drawn behind it); the sphere drawn in each panel is
    its t = 0 mesh at its pose of that frame (it moves), the plane a square in y = -0.4."""
    import warpfem.io.preview as preview
    from warpfem.contact import Sphere

    made = []
    real = preview.preview_figure

    def spy(*a, **kw):
        made.append((real(*a, **kw), kw))
        return made[-1][0]

    monkeypatch.setattr(preview, "preview_figure", spy)
    scene = write_scene(tmp_path, cli_beam_toml(frames=3) + PREVIEW_COLLIDERS)
    png = tmp_path / "c.png"
    assert main(["run", scene, "--frames", "3", "--out", str(tmp_path / "c.usda"), "--preview", str(png),
                 "--quiet"]) == 0
    assert png.stat().st_size > 5_000
    (fig, drawn), kw = made[0]
    panels = drawn["panels"]
    assert [p["frame"] for p in panels] == [0, 1, 2, 3]
    limits = [(p["axes"].get_xlim(), p["axes"].get_ylim(), p["axes"].get_zlim()) for p in panels]
    assert all(np.allclose(lim, drawn["limits"]) for lim in limits)  # one scale for every frame
    assert all((p["axes"].elev, p["axes"].azim) == (20.0, -60.0) for p in panels)
    assert len({tuple(p["axes"].get_box_aspect()) for p in panels}) == 1
    (x0, x1), (y0, y1), (z0, z1) = drawn["limits"]  # matplotlib's (x, y, z) = the scene's (x, -z, y)
    assert z0 <= -0.4 and z1 >= 0.8 and x1 >= 0.5 + 0.6 + 0.1  # the floor, the ball's top and its last x
    ball = next(c for c in kw["colliders"] if isinstance(c, Sphere))
    V0, _ = ball.surface(1.0)
    centres = []
    for p in panels:
        ax = p["axes"]
        assert set(p["colliders"]) == {"floor", "ball"}
        arts = [a for a in ax.collections if (a.get_gid() or "").startswith("collider:")]
        assert len(arts) == 2 and p["body"] in ax.collections
        assert all(a.get_zorder() < p["body"].get_zorder() for a in arts) and not ax.computed_zorder
        art, verts = p["colliders"]["ball"]
        assert art in arts
        R, t = ball.pose(p["time"])
        np.testing.assert_allclose(verts, V0 @ R.T + t, atol=1e-12)  # its pose of that frame
        centres.append(verts.mean(axis=0))
        floor = p["colliders"]["floor"][1]
        np.testing.assert_allclose(floor[:, 1], -0.4, atol=1e-12)
    np.testing.assert_allclose([c[0] - centres[0][0] for c in centres], [0.6 * min(p["time"] / 0.15, 1.0) for p in panels],
                               atol=1e-9)
    assert centres[-1][0] > centres[0][0] + 0.5  # the sphere moved


def test_preview_needs_png_and_matplotlib(tmp_path, capsys, monkeypatch):
    scene = write_scene(tmp_path, SCENE.format(states=tmp_path / "q.npz"))
    assert main(["run", scene, "--preview", str(tmp_path / "q.jpg"), "--quiet"]) == 2
    assert "--preview must end in .png" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    assert main(["run", scene, "--preview", str(tmp_path / "q.png"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert 'install the "plot" extra' in err and "warpfem[plot]" in err
    assert not (tmp_path / "q.npz").exists()  # nothing ran
