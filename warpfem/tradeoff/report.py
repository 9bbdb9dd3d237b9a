"""Reports of a trade-off study: the terminal table (:func:`format_table`), a markdown table
(:func:`format_markdown`), the account of the reference (:func:`reference_lines`) and the Pareto plot
(:func:`plot_pareto`, needs matplotlib).
"""

from __future__ import annotations

import math
import os

import numpy as np

from .grid import QUANTITIES
from .results import ConfigResult, StudyResult

__all__ = ["format_table", "reference_lines", "format_markdown", "plot_pareto"]


def _fmt(v, spec=".2e"):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return format(v, spec)


def _one_line(r: ConfigResult) -> str:
    if r.status != "ok":
        return f"{r.name}: {r.status}: {r.note}"
    return (f"{r.name}: {r.seconds_per_sim_second:.3g} s/sim-s, newton {r.newton_per_step:.2f}/step, "
            f"cg {r.cg_per_step:.1f}/step, rms {_fmt(r.rms_error)}, tip {_fmt(r.tip_error)}, "
            f"energy {_fmt(r.energy_error)}" + (f"  ({r.note})" if r.note else ""))


def format_table(study: StudyResult) -> str:
    """The terminal table: one row per configuration, frontier rows marked '*', skipped ones last."""
    key = QUANTITIES[study.quantity]
    split = _split_key(study)
    head = ["", "configuration", "s/sim-s", "newton/step", "cg/step", "cg/sim-s", "rms err", "surf err", "tip err", "energy err",
            "drift", "unconv"] + ([f"{split} disc", f"{split} solver"] if split else [])
    rows = []
    ok = sorted(study.ok_results(), key=lambda r: r.seconds_per_sim_second)
    for r in [study.reference] + ok:
        rows.append(["*" if r.on_frontier else ("R" if r is study.reference else ""), r.name,
                     _fmt(r.seconds_per_sim_second, ".3g"), _fmt(r.newton_per_step, ".2f"), _fmt(r.cg_per_step, ".1f"),
                     _fmt(r.cg_per_sim_second, ".4g"), _fmt(r.rms_error), _fmt(r.surface_error), _fmt(r.tip_error), _fmt(r.energy_error),
                     _fmt(r.energy_drift, "+.2e"), str(r.unconverged_frames)]
                    + ([_fmt(getattr(r, f"discretisation_{split}_error")), _fmt(getattr(r, f"solver_{split}_error"))]
                       if split else []))
    widths = [max(len(str(x)) for x in col) for col in zip(head, *rows)]
    lines = [f"{study.scene_name}: {study.frames} frames ({study.simulated_seconds:g} s simulated) on {study.device_description}",
             f"frontier (*) on {study.quantity} error ({key}) vs wall time; R = reference ({study.precision_note})",
             "  ".join(h.ljust(w) for h, w in zip(head, widths))]
    lines += ["  ".join(str(x).ljust(w) for x, w in zip(row, widths)) for row in rows]
    for r in study.results:
        if r.status != "ok":
            lines.append(f"  {r.status}: {r.name}: {r.note}")
    lines += reference_lines(study)
    tip = study.tip
    lines.append(f"tip: {tip['how']} at {np.round(tip['point'], 4).tolist()} m, peak displacement "
                 f"{tip['peak_displacement_m']:.4g} m; object size (bbox diagonal) {study.object_size:.4g} m")
    return "\n".join(lines)


def _split_key(study: StudyResult) -> str | None:
    """The error whose split is shown: the frontier's quantity when it is tip or rms, else tip."""
    if not any(math.isfinite(r.discretisation_tip_error) for r in study.ok_results()):
        return None
    return study.quantity if study.quantity in ("tip", "rms") else "tip"


def reference_lines(study: StudyResult) -> list:
    """What the reference is and how converged it is (lines of text)."""
    t = study.truth or {}
    if not t:
        return []
    out = [f"reference: {t.get('kind', '')}" + (f" -- {t['flag']}" if t.get("flag") else "")]
    tm = t.get("time")
    if tm:
        d = ", ".join(_fmt(x) for x in tm.get("difference_tip", []))
        out.append(f"  time: substeps {tm.get('substeps')}, successive tip differences {d}"
                   + (f", observed order {tm['observed_order_tip']:.2f}" if tm.get("observed_order_tip") is not None else "")
                   + f"; estimated reference error: tip {_fmt(tm.get('estimated_error_tip'))}, rms {_fmt(tm.get('estimated_error_rms'))}"
                   + (f" ({tm['method']})" if tm.get("method") else ""))
    sp = t.get("space")
    if sp:
        out.append(f"  space: {t['space_run']['config']['name']}: tip difference {_fmt(sp['difference_tip'])}, "
                   f"rms {_fmt(sp['difference_rms'])} ({sp['note']})")
    for name, m in (t.get("meshes") or {}).items():
        out.append(f"  discretisation error of {name} (time-converged run on that mesh vs the reference): tip "
                   f"{_fmt(m.get('discretisation_tip_error'))}, rms {_fmt(m.get('discretisation_rms_error'))}")
    return out


def format_markdown(study: StudyResult, *, frontier_only=False) -> str:
    """A markdown table (for docs)."""
    rows = sorted(study.ok_results(), key=lambda r: r.seconds_per_sim_second)
    if frontier_only:
        rows = [r for r in rows if r.on_frontier]
    split = _split_key(study)
    extra = f" {split} discretisation | {split} solver/step |" if split else ""
    out = ["| configuration | s / simulated s | Newton / step | CG / step | CG / simulated s | RMS err / size | tip err / peak | energy err | frontier |" + extra,
           "| --- | --- | --- | --- | --- | --- | --- | --- | --- |" + (" --- | --- |" if split else "")]
    for r in [study.reference] + rows:
        name = "reference" if r is study.reference else r.name
        out.append(f"| {name} | {_fmt(r.seconds_per_sim_second, '.3g')} | {_fmt(r.newton_per_step, '.2f')} | "
                   f"{_fmt(r.cg_per_step, '.1f')} | {_fmt(r.cg_per_sim_second, '.4g')} | {_fmt(r.rms_error)} | {_fmt(r.tip_error)} | {_fmt(r.energy_error)} | "
                   f"{'yes' if r.on_frontier else ''} |"
                   + (f" {_fmt(getattr(r, f'discretisation_{split}_error'))} | {_fmt(getattr(r, f'solver_{split}_error'))} |"
                      if split else ""))
    return "\n".join(out)


def plot_pareto(study: StudyResult, path) -> str:
    """Error vs wall time (log-log) with the frontier drawn; needs matplotlib (``pip install warpfem[plot]``)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as e:
        raise ImportError("the Pareto plot needs matplotlib: pip install 'warpfem[plot]' (or pip install matplotlib)") from e
    key = QUANTITIES[study.quantity]
    ok = study.ok_results()
    t = np.array([r.seconds_per_sim_second for r in ok])
    e = np.array([getattr(r, key) for r in ok], dtype=np.float64)
    finite = np.isfinite(e) & np.isfinite(t)
    floor = np.nanmin(e[finite & (e > 0)]) / 10 if np.any(finite & (e > 0)) else 1e-12
    e_plot = np.where(e > 0, e, floor)
    fig, ax = plt.subplots(figsize=(8, 5.5))
    on = np.array([r.on_frontier for r in ok])
    ax.scatter(t[finite & ~on], e_plot[finite & ~on], c="0.6", label="configuration")
    ax.scatter(t[finite & on], e_plot[finite & on], c="C3", label="Pareto frontier", zorder=3)
    order = np.argsort(t[on])
    ax.plot(t[on][order], e_plot[on][order], c="C3", drawstyle="steps-post", lw=1)
    for r, ti, ei in zip(ok, t, e_plot):  # names on the frontier only (the table / JSON has them all)
        if r.on_frontier and np.isfinite(ti) and np.isfinite(ei):
            ax.annotate(r.name, (ti, ei), fontsize=7, xytext=(4, 4), textcoords="offset points")
    ax.axvline(study.reference.seconds_per_sim_second, c="C0", ls="--", lw=1, label="reference time")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall seconds per simulated second")
    ax.set_ylabel({"tip_error": "tip error / peak tip displacement", "rms_error": "RMS vertex error / object size",
                   "surface_error": "RMS surface error / object size", "energy_error": "energy error / energy swing"}[key])
    ax.set_title(f"{study.scene_name}: {study.frames} frames, {study.device_description}", fontsize=8)
    ax.legend(fontsize=8)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
