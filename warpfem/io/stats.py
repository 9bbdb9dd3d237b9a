"""``[output] stats``: the statistics log, one JSON object per line and per frame (frames 1..N: the
frame's ``FrameStats`` fields plus ``warpfem_version``), flushed after each frame; a step that
raised adds a last line ``{"frame", "converged": false, "error", "newton_iterations"}``."""

from __future__ import annotations

import json
import os

from .writers import FrameWriter

__all__ = ["StatsOutput", "read_stats"]


def read_stats(path) -> list[dict]:
    """The records of a statistics log (a last line cut short by a kill is skipped)."""
    out = []
    with open(os.fspath(path), encoding="utf-8") as f:
        for line in f:
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                break
    return out


class StatsOutput(FrameWriter):
    label = "statistics log"

    def __init__(self, path, **options):
        super().__init__(path, **options)
        self._f = None

    def open(self, run):
        self.version = run.version
        os.makedirs(os.path.dirname(os.path.abspath(self.path)), exist_ok=True)
        if run.resume_after is not None and os.path.exists(self.path):
            # keep the records of frames 1..k (the same bytes), drop later ones and any error line
            keep = []
            with open(self.path, encoding="utf-8") as f:
                for line in f:
                    try:
                        rec = json.loads(line)
                    except json.JSONDecodeError:
                        break
                    if "error" in rec or rec.get("frame", 0) > run.resume_after:
                        break
                    keep.append(line if line.endswith("\n") else line + "\n")
            tmp = self.path + ".partial"
            with open(tmp, "w", encoding="utf-8") as f:
                f.writelines(keep)
            os.replace(tmp, self.path)
            self._f = open(self.path, "a", encoding="utf-8")
        else:
            self._f = open(self.path, "w", encoding="utf-8")

    def write(self, snapshot):
        if snapshot.stats is None:  # frame 0: the rest state, no step
            return
        self._f.write(json.dumps({**snapshot.stats.as_dict(), "warpfem_version": self.version}) + "\n")
        self._f.flush()

    def failed(self, record: dict):
        self._f.write(json.dumps({**record, "warpfem_version": self.version}) + "\n")
        self._f.flush()

    def close(self, complete, reason=None):
        if self._f is not None:
            f, self._f = self._f, None
            f.close()

    def abandon(self):
        if self._f is not None:
            f, self._f = self._f, None
            try:
                f.close()
            except OSError:
                pass
