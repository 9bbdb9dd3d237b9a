"""Speed/accuracy trade-off study of a scene over solver configurations (``warpfem tradeoff``).

    from warpfem.tradeoff import builtin_grid, run_study, format_table
    study = run_study("examples/scenes/cantilever.toml", builtin_grid("quick"), frames=12)
    print(format_table(study)); study.to_json("out/tradeoff.json")
    scene = variant_scene(scene_document(path), path, chosen_config)   # run a configuration you picked

See :mod:`warpfem.tradeoff.study` for what is measured and docs/tradeoff.md for results.
"""

from .study import (QUANTITIES, SCHEMA_VERSION, ConfigResult, GridError, StudyResult, TradeoffConfig, TradeoffGrid,
                    builtin_grid, format_markdown, format_table, load_grid, load_study, pareto_front, plot_pareto,
                    run_study, scene_document, set_quantity, variant_scene)

__all__ = ["QUANTITIES", "SCHEMA_VERSION", "ConfigResult", "GridError", "StudyResult", "TradeoffConfig", "TradeoffGrid",
           "builtin_grid", "format_markdown", "format_table", "load_grid", "load_study", "pareto_front", "plot_pareto",
           "run_study", "scene_document", "set_quantity", "variant_scene"]
