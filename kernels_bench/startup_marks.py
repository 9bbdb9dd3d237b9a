"""Child of ``bench_startup.py``: ``python -c "$(cat startup_marks.py)" OUT.json warpfem-arguments...``
runs ``python -m warpfem ARGS`` in this process and writes to OUT.json when each stage of its
start-up was reached (wall clock ``time.time()`` and process CPU time ``time.process_time()``), plus
the time spent inside a few functions and imports (inclusive, seconds and calls), as they were at the
first step's start and at the end.

Nothing of warpfem is imported ahead of the command: the marks are set by wrapping functions of a
module right after the command itself imports it (a ``sys.meta_path`` hook), so the modules load in
the command's own order, and a function an older revision lacks is simply not timed. Marks, each at
its first occurrence: ``python`` (this code starts), ``imported`` (``import warpfem`` done, as
``python -m warpfem`` does first), ``parsed`` (the command line parsed), ``scene_loaded``
(``load_scene`` returned: TOML read and validated), ``built`` (``Scene.build`` returned: mesh, model,
simulator, colliders), ``first_step`` (``SceneRun.step_frame`` entered: outputs and progress set up),
``first_step_done`` and ``end`` (the command returned). Timed inside: ``mesh`` (``Scene._make_mesh``),
``model`` (``Model.__init__``), ``warp_init`` (``warpfem.device.init_warp``), ``warp_module_load``
(Warp's ``Module.load``: hashing the module and loading it from the kernel cache), ``usd_writer``
(the USD writer's constructor, prims and frames), ``import_pxr`` and ``import_scipy`` (the outermost
import of each package).
"""

import sys
import time

_T0, _C0 = time.time(), time.process_time()

import functools  # noqa: E402
import importlib.abc  # noqa: E402
import json  # noqa: E402
import runpy  # noqa: E402

OUT, ARGV = sys.argv[1], sys.argv[2:]
marks = {"python": (_T0, _C0)}
inside = {}  # name -> [seconds, calls]
at_first_step = {}


def mark(name):
    if name not in marks:
        marks[name] = (time.time(), time.process_time())
        if name == "first_step":
            at_first_step.update({k: list(v) for k, v in inside.items()})


def count(name, seconds):
    entry = inside.setdefault(name, [0.0, 0])
    entry[0] += seconds
    entry[1] += 1


def wrap(owner, attr, name=None, before=None, after=None):
    f = getattr(owner, attr, None)
    if f is None:
        return

    @functools.wraps(f)
    def timed(*args, **kwargs):
        if before:
            mark(before)
        t0 = time.perf_counter()
        try:
            return f(*args, **kwargs)
        finally:
            if name:
                count(name, time.perf_counter() - t0)
            if after:
                mark(after)

    setattr(owner, attr, timed)


def _usd(m):
    for attr in ("__init__", "add_mesh", "add_tet_mesh", "write_frame"):
        wrap(m.UsdMeshWriter, attr, "usd_writer")


PATCHES = {
    "warp._src.context": lambda m: wrap(m.Module, "load", "warp_module_load"),
    "warpfem.device": lambda m: wrap(m, "init_warp", "warp_init"),
    "warpfem.scenes": lambda m: wrap(m, "load_scene", after="scene_loaded"),
    "warpfem.scenes.scene": lambda m: (wrap(m.Scene, "build", after="built"), wrap(m.Scene, "_make_mesh", "mesh")),
    "warpfem.scenes.run": lambda m: wrap(m.SceneRun, "step_frame", before="first_step", after="first_step_done"),
    "warpfem.model": lambda m: wrap(getattr(m, "Model", None), "__init__", "model"),
    "warpfem.io.usd": _usd,
}
PACKAGES = ("pxr", "scipy")  # imports timed as a whole
_depth = dict.fromkeys(PACKAGES, 0)


class _AfterImport(importlib.abc.MetaPathFinder):
    """Finds a module of PATCHES / PACKAGES with the other finders and wraps its loader's exec_module."""

    def find_spec(self, name, path, target=None):
        package = name.split(".")[0]
        if name not in PATCHES and package not in PACKAGES:
            return None
        for finder in sys.meta_path:
            if finder is not self and hasattr(finder, "find_spec"):
                spec = finder.find_spec(name, path, target)
                if spec is not None:
                    break
        else:
            return None
        loader = spec.loader
        if loader is None or not hasattr(loader, "exec_module"):
            return spec
        execute = loader.exec_module

        def exec_module(module):
            timed = package in PACKAGES
            outer = timed and _depth[package] == 0
            t0 = time.perf_counter()
            if timed:
                _depth[package] += 1
            try:
                execute(module)
            finally:
                if timed:
                    _depth[package] -= 1
                if outer:
                    count("import_" + package, time.perf_counter() - t0)
            if name in PATCHES:
                PATCHES[name](module)

        loader.exec_module = exec_module
        return spec


sys.meta_path.insert(0, _AfterImport())
import argparse  # noqa: E402

wrap(argparse.ArgumentParser, "parse_args", after="parsed")
import warpfem  # noqa: E402, F401  (what `python -m warpfem` imports first)

mark("imported")
sys.argv = [sys.argv[0], *ARGV]
code = 0
try:
    runpy.run_module("warpfem", run_name="__main__", alter_sys=True)
except SystemExit as e:
    code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
mark("end")
with open(OUT, "w") as f:
    json.dump({"exit": code, "marks": marks, "inside": inside, "inside_at_first_step": at_first_step}, f)
