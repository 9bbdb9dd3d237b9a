"""No module reads another object's private attributes, checked on the syntax tree like
the import layers (tests/test_import_layers.py).

Every attribute access ``obj._name`` in ``warpfem/`` whose object is not ``self``, ``cls`` or
``super()`` is a reach-in: it ties a module to another's internals. The few that remain are listed
in ALLOWED with the reason; anything else fails the test, and so does an entry of ALLOWED that no
longer occurs (the list shrinks as they go).
"""

from __future__ import annotations

import ast
import collections
import os

ROOT = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "warpfem")

# (file relative to warpfem/, "object._attribute") -> (count, why it stays)
ALLOWED = {
    ("kernels/generic.py", "kernel._add_normalized_overload"): (2, "Warp's overload lookup: no public API; "
                                                                   "guarded, falls back to the plain launch"),
    ("kernels/generic.py", "cmd.kernel._invoke_cache"): (1, "Warp's CPU entry-point cache (version-pinned direct call)"),
    ("solvers/linear/direct.py", "ps._mkl_pardiso"): (1, "pypardiso's MKL entry point: its _call_pardiso passes "
                                                         "maxfct = mnum = 1, the kept factorisations need PARDISO's "
                                                         "factor slots (and a chosen phase has no public call)"),
    ("solvers/adjoint.py", "wp._src"): (1, "Warp's runtime holds the active wp.Tape: no public call says whether a "
                                           "tape records or pauses it (steps on a tape record their own backward)"),
    ("tradeoff/cluster.py", "os._exit"): (1, "the standard library's exit without clean-up (a public function)"),
}


def reach_ins():
    """Counter of (file, "object._attribute") over warpfem/."""
    found = collections.Counter()
    for dirpath, _, files in os.walk(ROOT):
        for name in files:
            if not name.endswith(".py"):
                continue
            path = os.path.join(dirpath, name)
            rel = os.path.relpath(path, ROOT).replace(os.sep, "/")
            tree = ast.parse(open(path, encoding="utf-8").read(), filename=path)
            for node in ast.walk(tree):
                if not (isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")):
                    continue
                v = node.value
                if isinstance(v, ast.Name) and v.id in ("self", "cls"):
                    continue
                if isinstance(v, ast.Call) and isinstance(v.func, ast.Name) and v.func.id == "super":
                    continue
                found[(rel, ast.unparse(node))] += 1
    return found


def test_no_module_reads_private_attributes_of_other_objects():
    found = reach_ins()
    extra = {k: c for k, c in found.items() if c > ALLOWED.get(k, (0, ""))[0]}
    assert not extra, ("private attributes of other objects read (use a public attribute, or justify it in "
                       f"ALLOWED): {sorted(extra.items())}")
    stale = {k for k, (c, _) in ALLOWED.items() if found.get(k, 0) < c}
    assert not stale, f"ALLOWED lists reach-ins that are gone (shrink the list): {sorted(stale)}"
    assert sum(found.values()) <= 6


def test_the_checker_sees_a_reach_in():
    tree = ast.parse("def f(sim):\n    return sim._x + self._y + super()._z\n")
    hits = [ast.unparse(n) for n in ast.walk(tree) if isinstance(n, ast.Attribute) and n.attr.startswith("_")
            and not (isinstance(n.value, ast.Name) and n.value.id == "self")
            and not (isinstance(n.value, ast.Call) and getattr(n.value.func, "id", "") == "super")]
    assert hits == ["sim._x"]
