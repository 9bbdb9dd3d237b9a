"""Speed/accuracy trade-off study of a scene over solver configurations (``warpfem tradeoff``) and
the search for the cheapest configuration within an error budget (``warpfem tune``).

    from warpfem.tradeoff import builtin_grid, run_study, format_table
    study = run_study("examples/scenes/cantilever.toml", builtin_grid("quick"), frames=12)
    print(format_table(study)); study.to_json("out/tradeoff.json")
    scene = variant_scene(scene_document(path), path, chosen_config)   # run a configuration you picked

Errors are measured against a converged reference (refined higher-order mesh, time-step ladder;
:class:`TruthSpec`) and split into discretisation and solver/step parts. Runs can execute on a Dask
cluster (:mod:`warpfem.tradeoff.cluster`). See :mod:`warpfem.tradeoff.study` for what is measured,
docs/tradeoff.md for results and docs/tune.md for ``tune``.
"""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the same names for type checkers and the API docs (read statically)
    from .study import (QUANTITIES, SCHEMA_VERSION, ConfigResult, GridError, StudyResult, TradeoffConfig, TradeoffGrid,
                        TruthSpec, builtin_grid, format_markdown, format_table, load_grid, load_study, pareto_front,
                        plot_pareto, run_study, scene_document, set_quantity, variant_scene, without_timings)

from warpfem.lazy import lazy_attributes  # noqa: E402

# name -> defining module, imported on first access (PEP 562): the command line imports
# warpfem.tradeoff.cli without the study
_LAZY = {
    **dict.fromkeys(['QUANTITIES', 'SCHEMA_VERSION', 'ConfigResult', 'GridError', 'StudyResult', 'TradeoffConfig', 'TradeoffGrid', 'TruthSpec', 'builtin_grid', 'format_markdown', 'format_table', 'load_grid', 'load_study', 'pareto_front', 'plot_pareto', 'run_study', 'scene_document', 'set_quantity', 'variant_scene', 'without_timings'], 'warpfem.tradeoff.study'),
}

__all__ = ["QUANTITIES", "SCHEMA_VERSION", "ConfigResult", "GridError", "StudyResult", "TradeoffConfig", "TradeoffGrid",
           "TruthSpec", "builtin_grid", "format_markdown", "format_table", "load_grid", "load_study", "pareto_front",
           "plot_pareto", "run_study", "scene_document", "set_quantity", "variant_scene", "without_timings"]


__getattr__, __dir__ = lazy_attributes(__name__, _LAZY)
