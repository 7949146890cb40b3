"""HTML result reports built from a workflow's pipeline cache (``cobgs report``).

    from stages.commands.report import build_report   # the program's registry and scene reader
    index = build_report("workflows/demo.toml", out_dir="runs/reports/demo")

(:func:`reports.builder.build_report` itself takes them as arguments: ``reports/`` imports
nothing of ``stages/``.)

Modules: :mod:`~reports.collect` reads the cache; :mod:`~reports.methods` describes each method
once (and the reference), :mod:`~reports.records` turns the results into records,
:mod:`~reports.ablation` the paper's Tables 5 and 4, :mod:`~reports.plotdata` the plots' data;
:mod:`~reports.tables`, :mod:`~reports.pictures` and :mod:`~reports.plots` render
them, :mod:`~reports.paper` holds the quoted paper numbers, :mod:`~reports.builder` writes
the folder. The package itself re-exports nothing.
"""
