"""A revision of this repository next to the working tree, for benchmarks that measure "before" and
"after" in one run (``bench_contact_cost.py``, ``bench_startup.py``): ``git archive`` of the
revision extracted into a folder, whose ``warpfem`` a subprocess imports through PYTHONPATH.
Imports no warpfem (a worker must import the extracted one)."""

from __future__ import annotations

import os
import shutil
import subprocess

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _git(*args) -> subprocess.CompletedProcess:
    return subprocess.run(["git", "-C", ROOT, *args], capture_output=True, text=True)


def working_tree_commit() -> str | None:
    """HEAD of this repository, "+dirty" when tracked files differ from it (None without git)."""
    if shutil.which("git") is None:
        return None
    head = _git("rev-parse", "HEAD")
    if head.returncode:
        return None
    dirty = _git("status", "--porcelain", "--untracked-files=no").stdout.strip()
    return head.stdout.strip() + ("+dirty" if dirty else "")


def extract_revision(revision: str, into: str) -> str:
    """``git archive REVISION`` of this repository extracted into the folder ``into``; returns the
    commit. Exits with a message when git, the repository or the revision is missing."""
    if shutil.which("git") is None:
        raise SystemExit(f"revision {revision!r}: git is not on PATH; it is needed to extract that revision")
    if shutil.which("tar") is None:
        raise SystemExit(f"revision {revision!r}: tar is not on PATH; it is needed to extract that revision")
    if _git("rev-parse", "--git-dir").returncode:
        raise SystemExit(f"revision {revision!r}: {ROOT} is not a git repository")
    res = _git("rev-parse", "--verify", "--quiet", f"{revision}^{{commit}}")
    if res.returncode:
        raise SystemExit(f"revision {revision!r}: no such commit in the repository {ROOT}")
    commit = res.stdout.strip()
    archive = subprocess.run(["git", "-C", ROOT, "archive", commit], capture_output=True)
    if archive.returncode:
        raise SystemExit(f"revision {revision!r}: git archive failed: {archive.stderr.decode(errors='replace').strip()}")
    untar = subprocess.run(["tar", "-x", "-C", into], input=archive.stdout, capture_output=True)
    if untar.returncode:
        raise SystemExit(f"revision {revision!r}: tar -x failed: {untar.stderr.decode(errors='replace').strip()}")
    if not os.path.isfile(os.path.join(into, "warpfem", "__init__.py")):
        raise SystemExit(f"revision {revision!r} ({commit}) has no warpfem package")
    return commit
