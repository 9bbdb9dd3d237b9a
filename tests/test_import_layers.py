"""The import-layer contract of docs/design.md ("Map of the code"), checked on the source with ``ast``.

Every ``import`` of a ``warpfem`` module (at module level or inside a function) must go to the same
layer or a lower one, and the units of LAYERS (packages, or modules listed on their own) must not import each other in a
cycle. A new
package gets a line in LAYERS; a module not covered by LAYERS fails the test, so the map stays
complete.
"""

from __future__ import annotations

import ast
import os

import pytest

ROOT = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "warpfem")

# module prefix -> layer (the longest matching prefix wins). Lower numbers are lower layers.
LAYERS = {
    "warpfem.device": 0,
    "warpfem.transfer": 0,
    "warpfem.progress": 0,
    "warpfem.paths": 0,
    "warpfem.lazy": 0,
    "warpfem.threads": 0,
    "warpfem.mesh": 1,
    "warpfem.materials": 1,
    "warpfem.integrators": 1,
    "warpfem.elements": 2,
    "warpfem.model": 2,
    "warpfem.rigid.body": 2,
    "warpfem.rigid.model": 2,
    "warpfem.rigid.kernels": 3,
    "warpfem.rigid": 4,
    "warpfem.kernels": 3,
    "warpfem.skinning": 3,
    "warpfem.io": 3,
    "warpfem.solvers": 4,
    "warpfem.contact": 4,
    "warpfem.simulator": 5,
    "warpfem.reduced": 5,
    "warpfem.reduced.scene": 6,
    "warpfem.reduced.cli": 6,
    "warpfem.scenes": 6,
    "warpfem.tradeoff": 6,
    "warpfem.diff": 6,
    "warpfem.cli": 6,
    "warpfem.__main__": 7,
    "warpfem.interop": 8,
}

# Known violations still to remove: (importer prefix, imported prefix). Keep this empty.
KNOWN_EXCEPTIONS: set = set()


def _module_name(path: str) -> str:
    rel = os.path.relpath(path, os.path.dirname(ROOT))[:-3].replace(os.sep, ".")
    return rel[: -len(".__init__")] if rel.endswith(".__init__") else rel


def _is_module(name: str) -> bool:
    p = os.path.join(os.path.dirname(ROOT), *name.split("."))
    return os.path.isfile(p + ".py") or os.path.isfile(os.path.join(p, "__init__.py"))


def _imports(path: str):
    """(line, imported module) for every warpfem import in the file; ``from pkg import sub`` counts
    as an import of ``pkg.sub`` when ``sub`` is a module."""
    mod = _module_name(path)
    package = mod if path.endswith("__init__.py") else mod.rpartition(".")[0]
    tree = ast.parse(open(path, encoding="utf-8").read(), filename=path)
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield node.lineno, a.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                if node.level > 1:
                    base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            subs = [f"{target}.{a.name}" for a in node.names if _is_module(f"{target}.{a.name}")]
            yield from ((node.lineno, s) for s in subs) if subs else [(node.lineno, target)]


def _layer(name: str):
    best = None
    for prefix, layer in LAYERS.items():
        if (name == prefix or name.startswith(prefix + ".")) and (best is None or len(prefix) > len(best[0])):
            best = (prefix, layer)
    return best


def _sources():
    for d, _, files in os.walk(ROOT):
        for f in sorted(files):
            if f.endswith(".py"):
                yield os.path.join(d, f)


def _edges():
    out = []
    for path in _sources():
        mod = _module_name(path)
        for line, target in _imports(path):
            if target.startswith("warpfem.") and target != mod:
                out.append((mod, target, f"{os.path.relpath(path, os.path.dirname(ROOT))}:{line}"))
    return out


def test_every_module_has_a_layer():
    missing = [_module_name(p) for p in _sources() if _module_name(p) != "warpfem" and _layer(_module_name(p)) is None]
    assert missing == [], f"modules without a layer in LAYERS (add them, and to docs/design.md): {missing}"


def test_imports_go_down_the_layers():
    bad = []
    for mod, target, where in _edges():
        lm, lt = _layer(mod), _layer(target)
        if lm is None or lt is None:
            continue
        if lt[1] > lm[1] and (lm[0], lt[0]) not in KNOWN_EXCEPTIONS:
            bad.append(f"{where}: {mod} (layer {lm[1]}) imports {target} (layer {lt[1]})")
    assert bad == [], "imports upwards across the layers:\n" + "\n".join(bad)


def _top(name: str) -> str:
    """The unit of the cycle check: the LAYERS entry a module belongs to."""
    found = _layer(name)
    return found[0] if found else name


def test_no_cycles_between_packages():
    graph: dict = {}
    for mod, target, _ in _edges():
        a, b = _top(mod), _top(target)
        if a != b and (a, b) not in KNOWN_EXCEPTIONS:
            graph.setdefault(a, set()).add(b)
    cycles = []

    def visit(node, stack):
        for nxt in sorted(graph.get(node, ())):
            if nxt in stack:
                cycles.append(" -> ".join(stack[stack.index(nxt):] + [nxt]))
            elif len(stack) < 12:
                visit(nxt, stack + [nxt])

    for start in sorted(graph):
        visit(start, [start])
    assert cycles == [], "import cycles between packages:\n" + "\n".join(sorted(set(cycles)))


@pytest.mark.parametrize("importer,imported,ok", [("warpfem.kernels.fem", "warpfem.scenes", False),
                                                   ("warpfem.scenes.scene", "warpfem.kernels.fem", True)])
def test_the_checker_sees_direction(importer, imported, ok):
    """The checker itself: an upward import is caught, a downward one is not."""
    lm, lt = _layer(importer), _layer(imported)
    assert (lt[1] <= lm[1]) is ok


def test_cli_command_table_is_the_parser():
    """The command line offers exactly the subcommands of warpfem.cli.COMMANDS, in that order."""
    import argparse

    from warpfem.cli import COMMANDS, build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert list(sub.choices) == list(COMMANDS)
