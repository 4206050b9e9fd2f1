"""Post-run analysis: plain functions over arrays and tables that return tables.

Modules are imported on their own (``from cobelrun.analysis.place_cells import place_cells``) so
that one analysis never pulls in another's optional dependencies. Nothing here imports the runner.
"""
