"""How far apart two runs of a scene are: :func:`compare_runs` (``warpfem compare A B``).

A and B are each a states ``.npz`` (``[output] states``, :class:`warpfem.io.StatesWriter`; a killed run's
frame stream when it has one, :func:`warpfem.io.read_states`) or a
USD file (``.usda`` / ``.usd`` / ``.usdc``, :class:`warpfem.io.UsdMeshWriter`) written by
``warpfem run``, typically the same scene run twice with different speed/accuracy settings (time
step, precision, Newton iterations, mesh resolution with the same render surface).

**What is compared.** A states file: its ``positions`` (every vertex), and for a scene of several
bodies each body too (named by ``body_names``). A USD file: every animated point-based prim
(``Mesh``, ``TetMesh``) whose path both files have; collider prims (``collider_*``) only when named
with ``prim``. Both files must be of the same kind, and a compared prim must have the same number
of points in both (the same surface).

**Which times.** Frames are matched by time (seconds: a states file's ``times``; a USD file's time
codes over its ``timeCodesPerSecond``), over the time both cover. When the two have different frame
rates the comparison is at the times of the coarser one (A when equal), and the finer one is
interpolated linearly between its two neighbouring frames where it has no frame at that time
(exact for a motion linear in time); the result says so (``matching``).

**What is reported**, per compared item: RMS over points and frames of |x_A - x_B| (m), the maximum
with the time, frame and point where it occurs, both relative to A's bounding-box diagonal at its
first frame (t = 0), and the RMS over points of each compared frame (``rms_per_frame``, and
``series``: 5 evenly spaced of them), plus a one-line ``verdict``.
"""

from __future__ import annotations

import math
import os

import numpy as np

__all__ = ["compare_runs", "CompareError", "format_comparison", "STATES_EXTENSIONS", "USD_EXTENSIONS"]

STATES_EXTENSIONS = (".npz",)
USD_EXTENSIONS = (".usda", ".usd", ".usdc")
COLLIDER_PREFIX = "collider_"
SERIES_POINTS = 5
# verdict thresholds on the largest max difference relative to A's bounding-box diagonal
NEGLIGIBLE, SMALL = 1e-4, 1e-2


class CompareError(ValueError):
    """The two runs cannot be compared: a missing file, an unknown format, different point counts,
    no common time, a prim not in both."""


class _Item:
    """One compared point set of a run: ``times`` (k,) s, ``labels`` (k,) frame numbers, and
    ``points(i)`` -> (n, 3) float64 metres."""

    def __init__(self, name, times, labels, num_points, points):
        self.name, self.times, self.labels = name, np.asarray(times, dtype=np.float64), np.asarray(labels)
        self.num_points, self.points = int(num_points), points


class _Run:
    def __init__(self, path, kind, fps, items, colliders=()):
        self.path, self.kind, self.fps, self.items, self.colliders = path, kind, fps, items, list(colliders)


def _kind(path) -> str:
    ext = os.path.splitext(path)[1].lower()
    if ext in STATES_EXTENSIONS:
        return "states"
    if ext in USD_EXTENSIONS:
        return "usd"
    raise CompareError(f"{path}: unknown format {ext or '(no extension)'!r}: expected a states .npz or a USD file "
                       f"({', '.join(USD_EXTENSIONS)})")


class _Arrays(dict):
    """The arrays of a states stream (:func:`warpfem.io.read_states`) as ``np.load`` shows an npz."""

    @property
    def files(self):
        return list(self)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def _load_states(path) -> _Run:
    from .states import StatesError, read_states, stream_directory

    try:
        if os.path.isdir(stream_directory(path)):  # a run in progress or killed: its frame stream
            data = _Arrays({k: v for k, v in read_states(path).items() if k != "complete"})
        else:
            data = np.load(path, allow_pickle=False)
    except (OSError, ValueError, StatesError) as e:
        raise CompareError(f"{path}: cannot read it as an .npz: {e}") from None
    with data:
        missing = [k for k in ("positions", "times") if k not in data.files]
        if missing:
            raise CompareError(f"{path}: not a warpfem states file (no {' or '.join(missing)}; has {sorted(data.files)})")
        positions = np.asarray(data["positions"], dtype=np.float64)
        times = np.asarray(data["times"], dtype=np.float64)
        fps = float(data["fps"]) if "fps" in data.files else None
        offsets = np.asarray(data["body_offsets"]) if "body_offsets" in data.files else None
        names = [str(n) for n in data["body_names"]] if "body_names" in data.files else None
    if positions.ndim != 3 or positions.shape[2] != 3 or positions.shape[0] != times.shape[0]:
        raise CompareError(f"{path}: positions {positions.shape} and times {times.shape} are not (k, n, 3) and (k,)")
    if positions.shape[0] == 0:
        raise CompareError(f"{path}: no frame")
    labels = np.arange(positions.shape[0])
    items = {"positions": _Item("positions", times, labels, positions.shape[1], lambda i: positions[i])}
    if offsets is not None and len(offsets) > 2:
        names = names or [f"body{b}" for b in range(len(offsets) - 1)]
        for name, lo, hi in zip(names, offsets[:-1], offsets[1:]):
            lo, hi = int(lo), int(hi)
            items[name] = _Item(name, times, labels, hi - lo, lambda i, lo=lo, hi=hi: positions[i, lo:hi])
    return _Run(path, "states", fps, items)


def _load_usd(path) -> _Run:
    from pxr import Usd, UsdGeom

    try:
        stage = Usd.Stage.Open(path)
    except Exception as e:  # noqa: BLE001 - pxr raises its own error types
        raise CompareError(f"{path}: cannot open it as a USD stage: {str(e).strip().splitlines()[-1] if str(e).strip() else e}") from None
    if stage is None:
        raise CompareError(f"{path}: cannot open it as a USD stage")
    tcps = float(stage.GetTimeCodesPerSecond())
    mpu = float(UsdGeom.GetStageMetersPerUnit(stage))
    items, colliders = {}, []
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.PointBased):
            continue
        attr = UsdGeom.PointBased(prim).GetPointsAttr()
        codes = np.array(attr.GetTimeSamples(), dtype=np.float64)
        if codes.size == 0:  # not animated
            continue
        name = str(prim.GetPath())
        first = attr.Get(codes[0])
        count = 0 if first is None else len(first)

        def points(i, attr=attr, codes=codes, name=name, count=count):
            v = attr.Get(codes[i])
            p = np.array(v, dtype=np.float64).reshape(-1, 3) * mpu
            if p.shape[0] != count:
                raise CompareError(f"{path}: prim {name}: {p.shape[0]} points at time code {codes[i]:g}, "
                                   f"{count} at the first")
            return p

        labels = np.array([int(c) if float(c).is_integer() else float(c) for c in codes], dtype=object)
        item = _Item(name, codes / tcps, labels, count, points)
        if prim.GetName().startswith(COLLIDER_PREFIX):
            colliders.append(item)
        else:
            items[name] = item
    run = _Run(path, "usd", tcps, items, colliders)
    run.stage = stage  # the prims' attributes read from it lazily
    return run


def _load(path) -> _Run:
    path = os.fspath(path)
    kind = _kind(path)
    from .states import stream_directory

    streamed = kind == "states" and os.path.isdir(stream_directory(path))  # a killed run's frames
    if not os.path.exists(path) and not streamed:
        raise CompareError(f"{path}: no such file")
    if not os.path.isfile(path) and not streamed:
        raise CompareError(f"{path}: not a file")
    return _load_states(path) if kind == "states" else _load_usd(path)


def _find(run: _Run, name: str, everything: dict):
    """The item of ``run`` named ``name``: a full prim path, or a prim / body name."""
    if name in everything:
        return name
    hits = [k for k in everything if k.rsplit("/", 1)[-1] == name.strip("/").rsplit("/", 1)[-1]
            and (not name.startswith("/") or k == name)]
    if len(hits) == 1:
        return hits[0]
    what = "prim" if run.kind == "usd" else "item"
    if len(hits) > 1:
        raise CompareError(f"{run.path}: {what} {name!r} is ambiguous: {', '.join(hits)} (give the full path)")
    raise CompareError(f"{run.path}: no animated {what} {name!r} (it has: {', '.join(everything) or 'none'})")


def _frame_interval(times) -> float:
    return float(np.median(np.diff(times))) if len(times) > 1 else math.inf


def _match_times(a: _Item, b: _Item, path_a, path_b):
    """The compared times: [(time, frame label, index in A or (i0, i1, w), index in B or ...)],
    which run's times are used, and how many samples of the other were interpolated."""
    da, db = _frame_interval(a.times), _frame_interval(b.times)
    finite = [d for d in (da, db) if math.isfinite(d) and d > 0]
    tol = 1e-6 * min(finite) if finite else 1e-9
    coarse_is_a = not (db > da + tol)  # the coarser run's times (A when the rates are equal)
    coarse, fine = (a, b) if coarse_is_a else (b, a)
    lo = max(a.times[0], b.times[0]) - tol
    hi = min(a.times[-1], b.times[-1]) + tol
    picked = np.nonzero((coarse.times >= lo) & (coarse.times <= hi))[0]
    if picked.size == 0:
        raise CompareError(f"no common time: {path_a} covers t = {a.times[0]:g} .. {a.times[-1]:g} s, "
                           f"{path_b} covers t = {b.times[0]:g} .. {b.times[-1]:g} s")
    out, interpolated = [], 0
    for i in picked:
        t = coarse.times[i]
        j = int(np.searchsorted(fine.times, t - tol))
        if j < len(fine.times) and abs(fine.times[j] - t) <= tol:
            f = (j, j, 0.0)
        else:  # fine.times[j-1] < t < fine.times[j]
            j0, j1 = j - 1, j
            f = (j0, j1, float((t - fine.times[j0]) / (fine.times[j1] - fine.times[j0])))
            interpolated += 1
        c = (int(i), int(i), 0.0)
        out.append((float(t), coarse.labels[i], c if coarse_is_a else f, f if coarse_is_a else c))
    return out, ("A" if coarse_is_a else "B"), interpolated


def _at(item: _Item, where):
    i0, i1, w = where
    if w == 0.0:
        return item.points(i0)
    return (1.0 - w) * item.points(i0) + w * item.points(i1)


def _json_label(v):
    return int(v) if isinstance(v, (int, np.integer)) else float(v)


def _compare_items(a: _Item, b: _Item, path_a, path_b) -> dict:
    if a.num_points != b.num_points:
        raise CompareError(f"{a.name}: {path_a} has {a.num_points} points, {path_b} has {b.num_points}: "
                           f"the same points are needed (the same mesh or render surface)")
    matched, sampled_at, interpolated = _match_times(a, b, path_a, path_b)
    x0 = a.points(0)
    diagonal = float(np.linalg.norm(np.ptp(x0, axis=0))) if len(x0) else 0.0
    sumsq, count = 0.0, 0
    worst, worst_at = -1.0, None
    per_frame = []
    for k, (t, label, wa, wb) in enumerate(matched):
        d = np.linalg.norm(_at(a, wa) - _at(b, wb), axis=1)
        sq = float(np.dot(d, d))
        sumsq += sq
        count += d.size
        per_frame.append(math.sqrt(sq / d.size) if d.size else 0.0)
        if d.size:
            p = int(np.argmax(d))
            if d[p] > worst:
                worst, worst_at = float(d[p]), (t, label, p)
    rms = math.sqrt(sumsq / count) if count else 0.0
    worst = max(worst, 0.0)

    def rel(v):
        return v / diagonal if diagonal > 0 else None

    times = [t for t, *_ in matched]
    labels = [_json_label(label) for _, label, *_ in matched]
    picks = sorted(set(int(round(x)) for x in np.linspace(0, len(matched) - 1, min(SERIES_POINTS, len(matched)))))
    return {
        "name": a.name, "points": a.num_points, "frames": len(matched), "bbox_diagonal": diagonal,
        "rms": rms, "rms_relative": rel(rms),
        "max": worst, "max_relative": rel(worst),
        "max_time": worst_at[0] if worst_at else None,
        "max_frame": _json_label(worst_at[1]) if worst_at else None,
        "max_point": worst_at[2] if worst_at else None,
        "series": [{"time": times[i], "frame": labels[i], "rms": per_frame[i]} for i in picks],
        "times": times, "frame_labels": labels, "rms_per_frame": per_frame,
        "matching": {"sampled_at": sampled_at, "interpolated": "B" if sampled_at == "A" else "A",
                     "interpolated_frames": interpolated,
                     "first_time": times[0], "last_time": times[-1]},
    }


def _verdict(items) -> str:
    worst = max(items, key=lambda r: (r["max_relative"] if r["max_relative"] is not None else math.inf, r["max"]))
    rel = worst["max_relative"]
    if worst["max"] == 0.0:
        word = "identical"
    elif rel is None:
        word = "different"
    elif rel < NEGLIGIBLE:
        word = "negligible"
    elif rel < SMALL:
        word = "small"
    else:
        word = "large"
    if word == "identical":
        return "identical: every compared point is at the same place at every compared time"
    size = f" ({_pct(rel)} of A's bounding-box diagonal)" if rel is not None else ""
    rms = f"; RMS {worst['rms']:.3g} m" + (f" ({_pct(worst['rms_relative'])})" if worst["rms_relative"] is not None else "")
    return (f"{word}: B is at most {worst['max']:.3g} m from A{size}, {worst['name']} at "
            f"t = {worst['max_time']:.4g} s{rms}")


def _pct(v) -> str:
    return "n/a" if v is None else f"{100.0 * v:.3g}%"


def _describe(run: _Run, items) -> dict:
    times = items[0].times if items else np.zeros(0)
    return {"path": run.path, "kind": run.kind, "fps": run.fps, "frames": int(len(times)),
            "first_time": float(times[0]) if len(times) else None, "last_time": float(times[-1]) if len(times) else None}


def compare_runs(a, b, prim=None) -> dict:
    """Compare run B against run A (paths of two states ``.npz`` or two USD files).

    Parameters
    ----------
    a, b : the two files, of the same kind (see the module's description for what is compared).
    prim : a prim path / name (USD) or an item name (states: ``positions`` or a body name), or a
        list of them, to compare only those (a collider prim is compared only when named here).
        Default: every animated prim both files have, colliders excluded (states: every item).

    Returns
    -------
    dict
        ``a`` and ``b``: path, kind, fps, frames, first / last time (of the first compared item).
        ``items``: one dict per compared prim / item with ``name``, ``points``, ``frames``
        (compared), ``bbox_diagonal`` (A at its first frame, m), ``rms`` and ``max`` (m),
        ``rms_relative`` and ``max_relative`` (over the diagonal), ``max_time`` (s), ``max_frame``
        (frame number in the run whose times are compared), ``max_point`` (point index; the first
        frame, then the lowest index, where the maximum occurs), ``series`` (5 evenly spaced
        ``{time, frame, rms}``), ``times`` / ``frame_labels`` / ``rms_per_frame`` (every compared
        frame) and ``matching`` (``sampled_at``: "A" or "B", whose times are used;
        ``interpolated``: the other; ``interpolated_frames``: at how many of those times it was
        interpolated linearly). ``skipped``: prims of one file only, and colliders not compared.
        ``verdict``: one line (identical, negligible under 0.01 % of the diagonal, small under
        1 %, else large).

    Raises
    ------
    CompareError
        (a ValueError) a missing file, an unknown format, files of different kinds, a named prim
        not in both, different point counts, no common time.
    """
    a, b = os.fspath(a), os.fspath(b)
    ra, rb = _load(a), _load(b)
    if ra.kind != rb.kind:
        kinds = {"states": "states", "usd": "USD"}
        raise CompareError(f"{a} is a {kinds[ra.kind]} file and {b} a {kinds[rb.kind]} file: "
                           f"compare two states .npz or two USD files")
    every_a = {**ra.items, **{c.name: c for c in ra.colliders}}
    every_b = {**rb.items, **{c.name: c for c in rb.colliders}}
    skipped = []
    if prim is not None:
        names = [prim] if isinstance(prim, (str, os.PathLike)) else list(prim)
        pairs = []
        for n in names:
            ka, kb = _find(ra, str(n), every_a), _find(rb, str(n), every_b)
            pairs.append((every_a[ka], every_b[kb]))
    else:
        common = [k for k in ra.items if k in rb.items]
        if not common:
            raise CompareError(f"nothing to compare: no animated prim is in both ({a}: {', '.join(ra.items) or 'none'}; "
                               f"{b}: {', '.join(rb.items) or 'none'})")
        pairs = [(ra.items[k], rb.items[k]) for k in common]
        skipped += [{"name": k, "why": "only in A"} for k in ra.items if k not in rb.items]
        skipped += [{"name": k, "why": "only in B"} for k in rb.items if k not in ra.items]
        skipped += [{"name": c.name, "why": "a collider; name it with prim to compare it"}
                    for c in ra.colliders if c.name in every_b]
    items = [_compare_items(ia, ib, a, b) for ia, ib in pairs]
    return {"a": _describe(ra, [p[0] for p in pairs]), "b": _describe(rb, [p[1] for p in pairs]), "items": items,
            "skipped": skipped, "verdict": _verdict(items)}


def _run_line(tag, d) -> str:
    kind = "states" if d["kind"] == "states" else "USD"
    fps = f", {d['fps']:g} fps" if d["fps"] else ""
    return f"{tag}: {d['path']} ({kind}, {d['frames']} frames{fps}, t = {d['first_time']:.4g} .. {d['last_time']:.4g} s)"


def _matching_line(result) -> str:
    item = result["items"][0]
    m = item["matching"]
    at, other = m["sampled_at"], m["interpolated"]
    fps = {"A": result["a"]["fps"], "B": result["b"]["fps"]}
    line = (f"times: {item['frames']} compared, t = {m['first_time']:.4g} .. {m['last_time']:.4g} s, at {at}'s frames")
    if m["interpolated_frames"]:
        rates = f" ({other} at {fps[other]:g} fps, {at} at {fps[at]:g} fps)" if fps[at] and fps[other] else ""
        line += f"; {other} interpolated linearly at {m['interpolated_frames']} of them{rates}"
    elif fps["A"] and fps["B"] and fps["A"] != fps["B"]:
        line += f" ({at} is the coarser: {fps[at]:g} fps; {other}'s {fps[other]:g} fps frames include them)"
    return line


def format_comparison(result) -> str:
    """The text ``warpfem compare`` prints for a :func:`compare_runs` result."""
    lines = [_run_line("A", result["a"]), _run_line("B", result["b"]), _matching_line(result)]
    for r in result["items"]:
        lines.append(f"{r['name']}: {r['points']} points; A's bounding-box diagonal at t = 0: {r['bbox_diagonal']:.4g} m")
        lines.append(f"  RMS  {r['rms']:.3e} m  ({_pct(r['rms_relative'])} of the diagonal)")
        if r["max_time"] is not None:
            lines.append(f"  max  {r['max']:.3e} m  ({_pct(r['max_relative'])}) at t = {r['max_time']:.4g} s "
                         f"(frame {r['max_frame']} of {r['matching']['sampled_at']}), point {r['max_point']}")
        lines.append("  RMS over time: " + ", ".join(f"t = {s['time']:.4g} s: {s['rms']:.2e} m" for s in r["series"]))
    for s in result["skipped"]:
        lines.append(f"not compared: {s['name']}: {s['why'].replace('with prim', 'with --prim')}")
    lines.append(f"verdict: {result['verdict']}")
    return "\n".join(lines)
