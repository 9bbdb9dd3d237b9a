"""Start-up: ``import warpfem`` loads Warp and little more (kernels_bench/bench_startup.py measures it);
the optional heavy modules, the solvers and the reduced / trade-off / fitting packages load on first use,
and every public name still resolves. ``warpfem run`` of a plain scene imports neither the other
subcommands' code nor the contact, VTU or comparison modules, and as a program it pauses the garbage
collector during its start-up and freezes the start-up objects (``main(argv)`` from Python does not)."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

HEAVY = {"scipy", "pyamg", "pypardiso", "meshio", "pxr", "matplotlib", "tetgen", "wildmeshing",
         "fast_simplification", "dask", "ipctk", "newton"}
LAZY_WARPFEM = ("warpfem.reduced", "warpfem.tradeoff", "warpfem.diff", "warpfem.contact", "warpfem.simulator",
                "warpfem.solvers", "warpfem.mesh.locate", "warpfem.io", "warpfem.interop")


def _modules_after(code: str) -> list:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([ROOT, *filter(None, [env.get("PYTHONPATH")])])
    out = subprocess.run([sys.executable, "-c", code + "\nimport sys; print(repr(sorted(sys.modules)))"],
                         capture_output=True, text=True, env=env, check=True)
    return eval(out.stdout.strip().splitlines()[-1])


def test_import_warpfem_loads_no_heavy_optional_module():
    mods = _modules_after("import warpfem")
    assert sorted(m for m in mods if m.split(".")[0] in HEAVY) == []
    assert sorted(m for m in mods if m.startswith(LAZY_WARPFEM)) == []


def test_a_plain_scene_build_does_not_load_the_reduced_package_or_contact():
    mods = _modules_after(f"from warpfem.scenes import load_scene\n"
                          f"load_scene({os.path.join(ROOT, 'examples', 'scenes', 'cantilever.toml')!r})"
                          f".build(device='cpu')")
    assert [m for m in mods if m.startswith(("warpfem.reduced", "warpfem.tradeoff", "warpfem.contact.surface"))] == []
    assert [m for m in mods if m.split(".")[0] in {"pyamg", "meshio", "matplotlib", "dask", "scipy.optimize"}] == []


def test_every_public_name_resolves():
    import warpfem
    import warpfem.contact
    import warpfem.reduced
    import warpfem.tradeoff

    import warpfem.io
    import warpfem.skinning

    for pkg in (warpfem, warpfem.contact, warpfem.reduced, warpfem.tradeoff, warpfem.io, warpfem.skinning):
        missing = [n for n in pkg.__all__ if getattr(pkg, n, None) is None]
        assert missing == [], f"{pkg.__name__}: {missing}"
        assert set(pkg.__all__) <= set(dir(pkg))
    from warpfem.contact import Plane  # the documented import paths
    from warpfem.reduced import ReducedSimulator, train_subspace

    assert Plane is warpfem.Plane and callable(train_subspace) and ReducedSimulator.__name__ == "ReducedSimulator"
    assert warpfem.Simulator.__module__ == "warpfem.simulator"


def test_an_unknown_name_is_an_attribute_error():
    import warpfem

    try:
        warpfem.no_such_name  # noqa: B018
    except AttributeError as e:
        assert "no_such_name" in str(e)
    else:
        raise AssertionError("expected AttributeError")


CANTILEVER = os.path.join(ROOT, "examples", "scenes", "cantilever.toml")
# imported by none of: loading / building / running the cantilever (no contact, no VTU, no comparison)
NOT_FOR_A_PLAIN_RUN = ("warpfem.tradeoff", "warpfem.reduced", "warpfem.diff", "warpfem.contact.contact",
                       "warpfem.contact.scene", "warpfem.contact.surface", "warpfem.contact.kernels",
                       "warpfem.io.compare", "warpfem.io.preview", "warpfem.skinning.skinner")


def test_loading_and_building_a_plain_scene_imports_no_output_or_contact_module():
    mods = _modules_after(f"from warpfem.scenes import load_scene\nload_scene({CANTILEVER!r}).build(device='cpu')")
    assert [m for m in mods if m.startswith(NOT_FOR_A_PLAIN_RUN)] == []
    assert [m for m in mods if m.startswith(("warpfem.io.", "pxr", "matplotlib", "xml.sax", "urllib.request",
                                             "http.client", "scipy.sparse.linalg", "scipy.optimize"))] == []


def test_building_a_contact_scene_loads_no_scipy_linear_algebra():
    """The stack (two bodies, surface contact): the bodies' components are labelled in numpy, so its
    set-up does not import scipy.sparse.csgraph and with it scipy.sparse.linalg and scipy.linalg
    (about 0.2 s before the first step); the labels are csgraph's (tests/test_surface_contact.py)."""
    stack = os.path.join(ROOT, "examples", "scenes", "stack.toml")
    mods = _modules_after(f"from warpfem.scenes import load_scene\nload_scene({stack!r}).build(device='cpu')")
    assert "warpfem.contact.surface" in mods
    assert [m for m in mods if m.startswith(("scipy.sparse.csgraph", "scipy.sparse.linalg", "scipy.linalg"))] == []


def test_checking_output_paths_loads_no_writer():
    mods = _modules_after("from warpfem.io.outputs import check_output_paths\ncheck_output_paths({'usd': 'a.usda'})")
    assert [m for m in mods if m.startswith(("warpfem.io.states", "warpfem.io.compare", "pxr", "xml.sax"))] == []


def test_the_run_parser_loads_only_the_run_subcommand():
    mods = _modules_after("from warpfem.cli import build_parser\np = build_parser(['run', 'x.toml'])\n"
                          "a = p.parse_args(['run', 'x.toml', '--frames', '2'])\nassert a.frames == 2")
    assert [m for m in mods if m.startswith(("warpfem.tradeoff", "warpfem.reduced", "warpfem.diff",
                                             "warpfem.scenes"))] == []
    from warpfem.cli import COMMANDS, build_parser

    def choices(parser):
        return sorted(next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction").choices)

    assert choices(build_parser(["run", "x.toml"])) == ["run"]
    assert choices(build_parser(["describe", "x.toml"])) == ["describe"]
    # no subcommand, an unknown one or an option first: every subcommand (help, error messages)
    assert choices(build_parser()) == choices(build_parser(["bogus"])) == choices(build_parser(["--help"])) \
        == sorted(COMMANDS)


def test_a_run_process_of_a_plain_scene_loads_only_what_it_uses_and_freezes_its_start_up(tmp_path):
    """``python -m warpfem run`` (main() owning the process): contact, trade-off, reduced and VTU code
    never imported (nor xml.sax); the collector is on again at the end, with the start-up objects frozen."""
    code = ("import gc, runpy, sys\n"
            "import warpfem.scenes.run as R\n"  # whether the USD library is loaded when the first step starts
            "at_first_step, step = [], R.SceneRun.step_frame\n"
            "R.SceneRun.step_frame = lambda self, **k: (at_first_step.append('pxr' in sys.modules), step(self, **k))[1]\n"
            f"sys.argv = ['warpfem', 'run', {CANTILEVER!r}, '--frames', '2', '--quiet', '--out', 'c.usda']\n"
            "try:\n    runpy.run_module('warpfem', run_name='__main__', alter_sys=True)\n"
            "except SystemExit as e:\n    assert not e.code, e.code\n"
            "print(repr((gc.isenabled(), gc.get_freeze_count(), at_first_step)))")
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([ROOT, *filter(None, [env.get("PYTHONPATH")])])
    out = subprocess.run([sys.executable, "-c", code + "\nprint(repr(sorted(sys.modules)))"], capture_output=True,
                         text=True, env=env, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.strip().splitlines()
    enabled, frozen, pxr_loaded = eval(lines[-2])
    mods = eval(lines[-1])
    assert enabled and frozen > 10_000  # Warp's built-ins alone are tens of thousands of objects
    # the USD stage is made after the first step (pxr not loaded before it), with frame 0 as it was
    assert pxr_loaded == [False, True] and "pxr.Usd" in mods
    from warpfem.io import read_usd_mesh_frames
    from warpfem.scenes import load_scene
    from warpfem.scenes.loads import boundary_surface

    times, frames = read_usd_mesh_frames(str(tmp_path / "c.usda"), "boundary")
    mesh = load_scene(CANTILEVER).mesh()
    ids, _ = boundary_surface(mesh)
    assert list(times) == [0.0, 1.0, 2.0]
    np.testing.assert_array_equal(frames[0], np.asarray(mesh.vertices, dtype=np.float32)[ids])
    assert np.abs(frames[2] - frames[0]).max() > 1e-4  # it sags: frames 1, 2 are the stepped states
    assert [m for m in mods if m.startswith(NOT_FOR_A_PLAIN_RUN)] == []
    assert [m for m in mods if m.startswith(("warpfem.io.compare", "xml.sax", "matplotlib"))] == []


def test_main_called_from_python_leaves_the_collector_alone(tmp_path, capsys):
    import gc

    from warpfem.cli import main

    frozen = gc.get_freeze_count()
    assert main(["describe", CANTILEVER]) == 0
    assert "cantilever" in capsys.readouterr().out
    assert gc.isenabled() and gc.get_freeze_count() == frozen
