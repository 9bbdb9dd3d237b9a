"""Paths as results record them (JSON documents, reports): never an absolute path of this machine.

A result written by ``warpfem tradeoff`` / ``warpfem tune`` or a benchmark is committed and read
elsewhere, so a path in it is relative to the repository root when the file is inside the
repository (``examples/scenes/cantilever.toml``), ``<tmp>/<name>`` in the temporary directory, and
otherwise just the file name.
"""

from __future__ import annotations

import os
import re
import tempfile

__all__ = ["repository_root", "portable_path", "portable_message"]


def repository_root() -> str | None:
    """The checkout this ``warpfem`` package lives in (the folder holding ``pyproject.toml`` next to
    the package), or None for an installed package."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    return root if os.path.isfile(os.path.join(root, "pyproject.toml")) else None


def _inside(path: str, folder: str) -> bool:
    try:
        return os.path.commonpath([path, folder]) == folder
    except ValueError:  # other drive (Windows) or mixed absolute / relative
        return False


def portable_path(path, *, root: str | None = None) -> str:
    """``path`` as results record it: relative to ``root`` (default: the repository root) with
    forward slashes when inside it, ``<tmp>/<file name>`` when in the temporary directory, else the
    file name alone."""
    path = os.fspath(path)
    root = root if root is not None else repository_root()
    absolute = os.path.abspath(path)
    candidates = {absolute, os.path.realpath(absolute)}
    if root is not None:
        for folder in {os.path.abspath(root), os.path.realpath(root)}:
            for p in candidates:
                if _inside(p, folder):
                    return os.path.relpath(p, folder).replace(os.sep, "/")
    tmp = tempfile.gettempdir()
    for folder in {os.path.abspath(tmp), os.path.realpath(tmp)}:
        if any(_inside(p, folder) for p in candidates):
            return "<tmp>/" + os.path.basename(absolute)
    return os.path.basename(absolute)


def portable_message(message: str) -> str:
    """A message (or a log) as a result records it: absolute paths inside the repository written
    relative to it, paths in the temporary directory as ``<tmp>/<file name>``, the rest of the home
    folder as ``~/...`` (e.g. Warp's kernel cache)."""
    message = str(message)
    root = repository_root()
    for folder in ({os.path.abspath(root), os.path.realpath(root)} if root else set()):
        message = message.replace(folder + os.sep, "")
    tmp = tempfile.gettempdir()
    for folder in {os.path.abspath(tmp), os.path.realpath(tmp)}:
        message = re.sub(re.escape(folder + os.sep) + r"(?:[^\s'\"`:,;()]*[/\\])?", "<tmp>/", message)
    home = os.path.expanduser("~")
    if home and os.path.dirname(home) != home:  # not "/" (or "~" unresolved)
        for folder in {os.path.abspath(home), os.path.realpath(home)}:
            message = message.replace(folder + os.sep, "~" + os.sep)
    return message
