"""A PNG preview of a run: a few frames of the render surface side by side (matplotlib, Agg, headless).

``warpfem run SCENE --preview out/x.png`` records the render surface (the one the USD gets) at a
few evenly spaced frames while it runs (:class:`PreviewRecorder`) and draws them with
:func:`render_preview` after the run, with the scene's colliders at their pose of each drawn frame,
at one scale for all frames (limits computed once, after the run, from everything drawn in every
frame). matplotlib is the ``plot`` extra (``pip install "warpfem[plot]"``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["PreviewRecorder", "render_preview", "preview_figure", "require_matplotlib", "preview_frames"]

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
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if str(up_axis).upper() == "Y":
        return np.stack([p[:, 0], -p[:, 2], p[:, 1]], axis=1)
    return p


def _from_plot(points, up_axis):
    """The inverse of :func:`_to_plot`: matplotlib's coordinates -> the scene's."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if str(up_axis).upper() == "Y":
        return np.stack([p[:, 0], p[:, 2], -p[:, 1]], axis=1)
    return p


def _collider_meshes(colliders, snapshots, body_lo, body_hi):
    """[(name, faces, [vertices (k, 3) in scene coordinates per snapshot])]: each collider's output mesh
    (``Collider.surface``, the one the USD gets) at its pose at each snapshot's time. An infinite plane
    is a square of half size 0.6 x the body's largest extent over all frames (the USD's is 2 x the
    rest size), slid within its plane so that its centre is the point of the plane nearest the
    centre of the body's box over all frames."""
    centre = 0.5 * (body_lo + body_hi)
    extent = 0.6 * float(np.max(body_hi - body_lo)) + 1e-9
    out = []
    for c in colliders:
        V, F = c.surface(extent)
        V = np.asarray(V, dtype=np.float64)
        per_frame = []
        for _, t, _ in snapshots:
            W = V
            if getattr(c, "type_name", "") == "plane":  # slide the square (its own t = 0 frame) under the body's centre
                R, p = c.pose(t)
                local = R.T @ (centre - p) - c.point
                W = V + local - np.dot(local, c.normal) * c.normal
            per_frame.append(c.posed(W, t))  # duck-typed: io does not import contact
        out.append((c.name, np.asarray(F, dtype=np.int64), per_frame))
    return out


_BODY_RGB = np.array([0.35, 0.55, 0.85])
_COLLIDER_RGB = np.array([0.72, 0.68, 0.60])  # muted grey-beige, behind the blue body


def _shaded(tri, rgb, light):
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
    shade = 0.35 + 0.65 * np.abs(nrm @ light)
    return np.clip(shade[:, None] * rgb[None, :], 0.0, 1.0)


def preview_figure(snapshots, faces, *, colliders=(), up_axis: str = "Y", title: str | None = None,
                   panel_inches: float = 3.0, dpi: int = 100):
    """The preview's matplotlib ``Figure`` (on its own Agg canvas) and what was drawn in it.

    ``snapshots`` [(frame, time (s), points (p, 3))] of the triangle surface ``faces`` (f, 3), one 3D
    panel each, side by side; ``colliders``: :class:`~warpfem.contact.Collider` objects, each drawn at
    its pose at the panel's time (muted colour, behind the body). The scale is fixed once for the
    whole figure: every panel has the same limits, the bounding box of everything drawn in all
    panels (body and colliders), equal scale on the three axes, the same view (elevation 20, azimuth
    -60, the scene's ``up_axis`` up) and axis ticks in metres in scene coordinates.

    Returns ``(fig, drawn)``: ``drawn["limits"]`` ((x0, x1), (y0, y1), (z0, z1)) in matplotlib's axes
    (for a Y-up scene: scene x, -z, y), ``drawn["panels"]``: one dict per snapshot with ``frame``,
    ``time``, ``axes``, ``body`` (its Poly3DCollection) and ``colliders`` {name: (Poly3DCollection,
    vertices (k, 3) drawn, scene coordinates)}.
    """
    require_matplotlib()
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import FuncFormatter, MaxNLocator
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    if not snapshots:
        raise ValueError("no frames to draw")
    faces = np.asarray(faces, dtype=np.int64)
    y_up = str(up_axis).upper() == "Y"
    scene_pts = [np.asarray(p, dtype=np.float64).reshape(-1, 3) for _, _, p in snapshots]
    body_all = np.concatenate(scene_pts)
    cols = _collider_meshes(colliders, snapshots, body_all.min(axis=0), body_all.max(axis=0))
    pts = [_to_plot(p, up_axis) for p in scene_pts]
    allp = np.concatenate(pts + [_to_plot(v, up_axis) for _, _, vs in cols for v in vs])
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    half = np.maximum(half, 0.02 * half.max() + 1e-12)  # flat bodies still get a visible box
    half = half * 1.02  # a little room around what is drawn
    limits = tuple((float(c - h), float(c + h)) for c, h in zip(centre, half))
    light = np.array([0.3, -0.5, 0.8])
    light /= np.linalg.norm(light)
    n = len(snapshots)
    w_px, h_px = int(round(n * panel_inches * dpi)), int(round(panel_inches * dpi))
    fig = Figure(figsize=(w_px / dpi, h_px / dpi), dpi=dpi)
    FigureCanvasAgg(fig)
    labels = ("x (m)", "z (m)", "y (m)") if y_up else ("x (m)", "y (m)", "z (m)")
    panels = []
    for i, ((frame, t, _), p) in enumerate(zip(snapshots, pts)):
        ax = fig.add_subplot(1, n, i + 1, projection="3d")
        ax.computed_zorder = False  # colliders behind the body, whatever the depth
        drawn = {}
        for name, cf, vs in cols:
            tri = _to_plot(vs[i], up_axis)[cf]
            art = Poly3DCollection(tri, facecolors=_shaded(tri, _COLLIDER_RGB, light), edgecolors=(0, 0, 0, 0.08),
                                   linewidths=0.2, alpha=0.75, zorder=1)
            art.set_gid(f"collider:{name}")
            ax.add_collection3d(art)
            drawn[name] = (art, vs[i])
        tri = p[faces]
        body = Poly3DCollection(tri, facecolors=_shaded(tri, _BODY_RGB, light), edgecolors=(0, 0, 0, 0.15),
                                linewidths=0.2, zorder=2)
        body.set_gid("body")
        ax.add_collection3d(body)
        ax.set_xlim(*limits[0])
        ax.set_ylim(*limits[1])
        ax.set_zlim(*limits[2])
        ax.set_box_aspect(tuple(half))  # equal scale on the three axes
        ax.view_init(elev=20.0, azim=-60.0)
        for axis, set_label, label in zip((ax.xaxis, ax.yaxis, ax.zaxis), (ax.set_xlabel, ax.set_ylabel, ax.set_zlabel),
                                          labels):
            axis.set_major_locator(MaxNLocator(nbins=3))
            axis.set_tick_params(labelsize=7, pad=1)
            set_label(label, fontsize=7, labelpad=-2)
            axis.set_pane_color((0.97, 0.97, 0.97, 1.0))
            # a space ahead of each value: the minus sign is not hidden under its tick mark
            axis.set_major_formatter(FuncFormatter(lambda v, _: "  " + f"{v + 0.0:g}".replace("-", "\u2212")))
        if y_up:  # matplotlib's y is the scene's -z: ticks in scene z
            ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: "  " + f"{-v + 0.0:g}".replace("-", "\u2212")))
        ax.grid(False)
        ax.text2D(0.5, 1.0, f"frame {frame}, t = {t:.3g} s", transform=ax.transAxes, ha="center", va="bottom", fontsize=9)
        panels.append({"frame": int(frame), "time": float(t), "axes": ax, "body": body, "colliders": drawn})
    if title:
        fig.suptitle(title, fontsize=10, y=0.995)
    fig.subplots_adjust(left=0.0, right=0.98, bottom=0.06, top=0.86 if title else 0.92, wspace=0.0)
    return fig, {"limits": limits, "panels": panels}


def render_preview(path, snapshots, faces, *, colliders=(), up_axis: str = "Y", title: str | None = None,
                   panel_inches: float = 3.0, dpi: int = 100) -> tuple[int, int]:
    """Draw ``snapshots`` [(frame, time (s), points (p, 3))] of the triangle surface ``faces`` (f, 3) and
    the ``colliders`` side by side into the PNG ``path`` (:func:`preview_figure`: one fixed scale for
    all panels, colliders at their pose of each frame).

    The figure is ``len(snapshots) * panel_inches`` x ``panel_inches`` inches at ``dpi``: returns its
    (width, height) in pixels.
    """
    import os

    fig, _ = preview_figure(snapshots, faces, colliders=colliders, up_axis=up_axis, title=title,
                            panel_inches=panel_inches, dpi=dpi)
    os.makedirs(os.path.dirname(os.path.abspath(os.fspath(path))), exist_ok=True)
    fig.savefig(path, dpi=dpi, format="png")
    w, h = fig.canvas.get_width_height()
    return int(w), int(h)
