"""Start-up: ``import warpfem`` loads Warp and little more (kernels_bench/bench_startup.py measures it);
the optional heavy modules, the solvers and the reduced / trade-off / fitting packages load on first use,
and every public name still resolves."""

from __future__ import annotations

import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

HEAVY = {"scipy", "pyamg", "pypardiso", "meshio", "pxr", "matplotlib", "tetgen", "wildmeshing",
         "fast_simplification", "dask", "ipctk"}
LAZY_WARPFEM = ("warpfem.reduced", "warpfem.tradeoff", "warpfem.diff", "warpfem.contact", "warpfem.simulator",
                "warpfem.solvers", "warpfem.mesh.locate", "warpfem.io")


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

    for pkg in (warpfem, warpfem.contact, warpfem.reduced, warpfem.tradeoff):
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
