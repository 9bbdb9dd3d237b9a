"""A PNG preview of a run: a few frames of the render surface side by side (matplotlib, Agg, headless).

``warpfem run SCENE --preview out/x.png`` records the render surface (the one the USD gets) at a
few evenly spaced frames while it runs (:class:`PreviewRecorder`) and draws them with
:func:`render_preview` after the run. matplotlib is the ``plot`` extra (``pip install "warpfem[plot]"``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["PreviewRecorder", "render_preview", "require_matplotlib", "preview_frames"]

MISSING = 'the preview needs matplotlib: install the "plot" extra (pip install "warpfem[plot]")'


def require_matplotlib():
    """Import matplotlib; ImportError naming the ``plot`` extra if it is missing. The preview draws on
    an Agg canvas of its own (no pyplot, no display, the global backend is left alone)."""
    try:
        import matplotlib
    except ImportError as e:
        raise ImportError(MISSING) from e
    return matplotlib


def preview_frames(total_frames: int, count: int = 4) -> list[int]:
    """``count`` evenly spaced frames of 0..total_frames (frame 0 = rest and the last frame included)."""
    total_frames = int(total_frames)
    if total_frames < 0 or count < 1:
        raise ValueError(f"need total_frames >= 0 and count >= 1, got {total_frames}, {count}")
    if count == 1:
        return [total_frames]
    return sorted({int(round(i * total_frames / (count - 1))) for i in range(count)})


class PreviewRecorder:
    """Keep copies of the surface points at the frames of :func:`preview_frames` (memory: ``count`` frames)."""

    def __init__(self, total_frames: int, count: int = 4):
        self.frames = preview_frames(total_frames, count)
        self.snapshots: list[tuple[int, float, np.ndarray]] = []

    def wants(self, frame: int) -> bool:
        return int(frame) in self.frames

    def add(self, frame: int, time: float, points):
        if self.wants(frame):
            self.snapshots.append((int(frame), float(time), np.array(points, dtype=np.float64)))


def _to_plot(points, up_axis):
    """Scene coordinates -> matplotlib's (z up): a Y-up scene is rotated +90 deg about x, (x, y, z) -> (x, -z, y)."""
    p = np.asarray(points, dtype=np.float64)
    if str(up_axis).upper() == "Y":
        return np.stack([p[:, 0], -p[:, 2], p[:, 1]], axis=1)
    return p


def render_preview(path, snapshots, faces, *, up_axis: str = "Y", title: str | None = None,
                   panel_inches: float = 3.0, dpi: int = 100) -> tuple[int, int]:
    """Draw ``snapshots`` [(frame, time (s), points (p, 3))] of the triangle surface ``faces`` (f, 3) side by
    side (one 3D panel each, same limits and equal axes in all panels) into the PNG ``path``.

    The figure is ``len(snapshots) * panel_inches`` x ``panel_inches`` inches at ``dpi``: returns its
    (width, height) in pixels.
    """
    require_matplotlib()
    import os

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    if not snapshots:
        raise ValueError("no frames to draw")
    faces = np.asarray(faces, dtype=np.int64)
    pts = [_to_plot(p, up_axis) for _, _, p in snapshots]
    allp = np.concatenate(pts)
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    half = np.maximum(half, 0.02 * half.max() + 1e-12)  # flat bodies still get a visible box
    light = np.array([0.3, -0.5, 0.8])
    light /= np.linalg.norm(light)
    n = len(snapshots)
    w_px, h_px = int(round(n * panel_inches * dpi)), int(round(panel_inches * dpi))
    fig = Figure(figsize=(w_px / dpi, h_px / dpi), dpi=dpi)
    FigureCanvasAgg(fig)
    for i, ((frame, t, _), p) in enumerate(zip(snapshots, pts)):
        ax = fig.add_subplot(1, n, i + 1, projection="3d")
        tri = p[faces]
        nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
        shade = 0.35 + 0.65 * np.abs(nrm @ light)
        colors = np.clip(shade[:, None] * np.array([0.35, 0.55, 0.85])[None, :], 0.0, 1.0)
        ax.add_collection3d(Poly3DCollection(tri, facecolors=colors, edgecolors=(0, 0, 0, 0.15), linewidths=0.2))
        ax.set_xlim(centre[0] - half[0], centre[0] + half[0])
        ax.set_ylim(centre[1] - half[1], centre[1] + half[1])
        ax.set_zlim(centre[2] - half[2], centre[2] + half[2])
        ax.set_box_aspect(tuple(half))  # equal scale on the three axes
        ax.view_init(elev=20.0, azim=-60.0)
        ax.set_axis_off()
        ax.text2D(0.5, 0.04, f"frame {frame}, t = {t:.3g} s", transform=ax.transAxes, ha="center", fontsize=9)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.0, top=0.92 if title else 1.0, wspace=0.0)
    os.makedirs(os.path.dirname(os.path.abspath(os.fspath(path))), exist_ok=True)
    fig.savefig(path, dpi=dpi, format="png")
    return w_px, h_px
