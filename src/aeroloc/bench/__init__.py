"""The benchmark: experiment files (YAML) -> sweep of configurations -> results store (SQLite) -> paper-style
tables, plots and a self-contained HTML report. ``aeroloc bench EXPERIMENT.yaml`` drives it (see runner.py)."""
