"""Run an experiment file: the sweep, then paper-style tables, plots and a self-contained HTML report."""

from __future__ import annotations


def add_arguments(p):
    p.add_argument("experiment", help="experiment YAML (see experiments/*.yaml and aeroloc/bench/experiment.py)")
    p.add_argument(
        "--no-resume",
        dest="resume",
        action="store_false",
        help="measure every configuration again instead of skipping those already stored",
    )
    p.add_argument(
        "--report-only",
        action="store_true",
        help="rebuild tables, plots and the report from the stored results without running anything",
    )
    p.add_argument("--quiet", action="store_true", help="no progress display")


def run(args) -> int:
    from aeroloc.bench.runner import run_experiment

    report = run_experiment(args.experiment, resume=args.resume, report_only=args.report_only, progress=not args.quiet)
    print(f"report: {report}")
    print(f"tables: {report.parent / 'tables.md'} (LaTeX: tables.tex), results: {report.parent / 'results.sqlite'}")
    return 0
