"""Public names of a package loaded on first access (PEP 562): ``import warpfem`` stays cheap, and a
scene loads only the packages it uses (start-up measured in ``kernels_bench/bench_startup.py``)."""

from __future__ import annotations

import importlib
import sys

__all__ = ["lazy_attributes"]


def lazy_attributes(package: str, table: dict):
    """(``__getattr__``, ``__dir__``) for the package named ``package``: a name of ``table`` (name ->
    defining module) is imported from its module on first access and kept in the package, so later
    lookups do not come here; any other name is an AttributeError naming the package."""

    def __getattr__(name):
        module = table.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__():
        return sorted(set(vars(sys.modules[package])) | set(table))

    return __getattr__, __dir__
