"""A run's outputs in one place: which writer writes each ``[output]`` key (:data:`OUTPUT_FORMATS`,
:func:`make_writers`), where its checkpoint goes (:func:`checkpoint_path`), and the check of
every output path before any work: a run must not stop with a traceback after minutes of
simulation (and a partial USD) because ``--out a_file/x.usda`` names a file as a folder.

:func:`output_path_problem` says why one path cannot be written, without creating anything;
:func:`check_output_paths` checks a set of named paths (and the folders the writers put next to
them: a USD's ``.clips`` folder, a ParaView collection's ``.vtu`` folder) and raises
:class:`OutputPathError` with a one-line message naming the first bad one.
"""

from __future__ import annotations

import os

__all__ = ["OutputPathError", "output_path_problem", "check_output_paths", "companion_folders", "OUTPUT_FORMATS",
           "make_writers", "checkpoint_path"]

#: ``[output]`` key -> ``"module:FrameWriter subclass"`` writing it (in the order a run writes them).
#: A new output format is a module with a :class:`warpfem.io.writers.FrameWriter` and a line here
#: (and its key in the scene schema's ``[output]`` table).
OUTPUT_FORMATS = {
    "stats": "warpfem.io.stats:StatsOutput",
    "states": "warpfem.io.states:StatesOutput",
    "usd": "warpfem.io.usd:UsdOutput",
    "vtu": "warpfem.io.vtu:ParaViewOutput",
}


def make_writers(paths: dict, **options) -> list:
    """The writers of ``paths`` ({``[output]`` key: path or None}), in :data:`OUTPUT_FORMATS` order."""
    import importlib

    writers = []
    for key, spec in OUTPUT_FORMATS.items():
        if paths.get(key):
            module, _, name = spec.partition(":")
            writers.append(getattr(importlib.import_module(module), name)(paths[key], **options))
    return writers


def checkpoint_path(paths: dict) -> str | None:
    """Where a run's checkpoint goes: ``X.checkpoint.npz`` next to its first output (USD, states,
    statistics log, ParaView collection; ``out/beam.usda`` -> ``out/beam.checkpoint.npz``); None
    without outputs."""
    for key in ("usd", "states", "stats", "vtu"):
        p = paths.get(key)
        if p:
            p = os.fspath(p)
            base = p[:-len(".stats.jsonl")] if p.endswith(".stats.jsonl") else os.path.splitext(p)[0]
            return base + ".checkpoint.npz"
    return None


class OutputPathError(ValueError):
    """An output path that cannot be created or written (the message names it and why)."""


def _existing_ancestor(path: str) -> str:
    probe = path
    while probe and not os.path.lexists(probe):
        parent = os.path.dirname(probe)
        if parent == probe:
            break
        probe = parent
    return probe


def output_path_problem(path, *, folder: bool = False) -> str | None:
    """Why ``path`` (a file, or a folder with ``folder=True``) cannot be created or written, or None.

    Nothing is created: the nearest existing ancestor must be a writable folder (every missing
    folder below it can then be made), and an existing ``path`` must be of the right kind and
    writable."""
    p = os.path.abspath(os.fspath(path))
    if os.path.lexists(p):
        if folder and not os.path.isdir(p):
            return "it exists and is a file, not a folder"
        if not folder and os.path.isdir(p):
            return "it is a folder"
        if not os.access(p, os.W_OK):
            return "it exists and is not writable"
        return None
    ancestor = _existing_ancestor(os.path.dirname(p))
    if not os.path.isdir(ancestor):
        return f"{_shown(ancestor, path)} is a file, not a folder"
    if not os.access(ancestor, os.W_OK | os.X_OK):
        return f"the folder {_shown(ancestor, path)} is not writable"
    return None


def _shown(ancestor: str, path) -> str:
    """``ancestor`` as the user wrote it (relative when ``path`` was)."""
    if os.path.isabs(os.fspath(path)):
        return ancestor
    rel = os.path.relpath(ancestor)
    return rel if not rel.startswith("..") else ancestor


def companion_folders(label: str, path) -> list[tuple[str, str]]:
    """The folders a writer puts next to ``path``: a USD's value clips (``X.clips``), a ParaView
    collection's frames (``X.vtu``)."""
    p = os.fspath(path)
    ext = os.path.splitext(p)[1].lower()
    if ext in (".usd", ".usda", ".usdc"):
        from .usd import clip_directory

        return [(f"{label} (its value clips)", clip_directory(p))]
    if ext == ".pvd":
        from .vtu import frame_directory

        return [(f"{label} (its frames)", frame_directory(p))]
    if ext == ".npz":
        from .states import stream_directory

        return [(f"{label} (its frame stream)", stream_directory(p))]
    return []


def check_output_paths(named, *, companions: bool = True) -> None:
    """Raise :class:`OutputPathError` for the first of ``named`` (``{label: path}``, or pairs; a
    None / empty path is skipped) that cannot be written: ``"--out a_file/x.usda: cannot create
    it: a_file is a file, not a folder"``. ``companions``: also the clip / frame folders."""
    items = list(named.items()) if isinstance(named, dict) else list(named)
    for label, path in items:
        if not path:
            continue
        why = output_path_problem(path)
        if why is None and companions:
            for sub_label, folder in companion_folders(label, path):
                sub = output_path_problem(folder, folder=True)
                if sub is not None:
                    raise OutputPathError(f"{sub_label} {folder}: cannot write it: {sub}")
        if why is not None:
            verb = "write" if os.path.lexists(os.path.abspath(os.fspath(path))) else "create"
            raise OutputPathError(f"{label} {os.fspath(path)}: cannot {verb} it: {why}")
