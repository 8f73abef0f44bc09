"""Run an experiment: every configuration of the sweep through the pipeline, each stored as soon as it finishes
(so Ctrl-C or a crash loses at most the configuration in progress and the next run resumes), then the
tables, plots and HTML report from the store.

Outputs in the experiment's ``output`` folder: ``results.sqlite`` (every run), ``results.csv``, ``tables.md``,
``tables.tex``, ``plots/*.png``, ``report-<run id>.html`` and ``report.html`` (the latest).
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable
from pathlib import Path

from aeroloc.bench.experiment import Config, Experiment, expand, load_experiment
from aeroloc.bench.store import ResultStore
from aeroloc.core.errors import AerolocError

RunConfig = Callable[[Config, Path], dict]


def run_experiment(
    path, resume: bool = True, report_only: bool = False, run_config: RunConfig | None = None, progress: bool = True
) -> Path:
    """Run (or resume) the sweep of experiment file ``path`` and return the HTML report's path.

    ``run_config(config, cache_dir) -> dict`` defaults to :func:`aeroloc.bench.pipeline.run_config`; configurations
    a run of this same code already stored (aeroloc.core.provenance) are skipped unless ``resume`` is False;
    ``report_only`` rebuilds the outputs from the store without running anything."""
    exp = load_experiment(path)
    configs = expand(exp)
    with ResultStore(exp.output) as store:
        run_id = None
        if not report_only:
            if run_config is None:
                from aeroloc.bench.pipeline import run_config
            run_id = sweep(exp, configs, store, run_config, resume, progress)
        return write_outputs(exp, configs, store, run_id)


def sweep(
    exp: Experiment, configs: list[Config], store: ResultStore, run_config: RunConfig, resume: bool, progress: bool
) -> str:
    from tqdm import tqdm

    from aeroloc.core.provenance import code_identity

    code = code_identity()
    todo = [c for c in configs if not (resume and store.done(c.key(), code))]
    stale = sum(1 for c in todo if resume and store.done(c.key()))
    run_id = store.start_run(exp.name, exp.file, exp.device, code)
    skipped = len(configs) - len(todo)
    if progress and skipped:
        print(f"{exp.name}: {skipped} of {len(configs)} configurations already in {store.path}, {len(todo)} to run")
    if progress and stale:  # a resumed sweep must not pass the old code's figures off as this code's
        print(f"{exp.name}: {stale} stored configurations were measured by other code than this ({code}): run again")
    status, current = "failed", None
    bar = tqdm(
        total=len(todo),
        desc=exp.name,
        unit="config",
        disable=not progress,
        dynamic_ncols=True,
        bar_format="{n_fmt}/{total_fmt} configs [{elapsed} elapsed, {remaining} left] {desc}",
    )
    try:
        exp.cache.mkdir(parents=True, exist_ok=True)
        for current in todo:
            bar.set_description_str(current.label())
            t0 = time.perf_counter()
            out = run_config(current, exp.cache)
            out.setdefault("timing", {}).setdefault("config_s", time.perf_counter() - t0)
            store.add_result(run_id, current, out)
            bar.update()
        status = "finished"
    except KeyboardInterrupt:
        status = "interrupted"
        raise
    except AerolocError as exc:
        raise AerolocError(f"{exp.file}: configuration {current.label() if current else '?'}: {exc}") from None
    finally:
        bar.close()
        store.finish_run(run_id, status)
    return run_id


def write_outputs(exp: Experiment, configs: list[Config], store: ResultStore, run_id: str | None) -> Path:
    """Tables, plots, CSV and the HTML report from the newest stored result of each configuration."""
    from aeroloc.bench import plots as plots_mod
    from aeroloc.bench import tables as tables_mod
    from aeroloc.bench.report import write_report

    rows = store.results(keys=[c.key() for c in configs])
    if not rows:
        raise AerolocError(
            f"{exp.file}: no results stored in {store.path} yet; run 'aeroloc bench {exp.file}' "
            f"without --report-only first"
        )
    out = exp.output
    qrows = {r["config_key"]: store.query_rows(r["run_id"], r["config_key"]) for r in rows}
    errors = {k: [q["error_m"] for q in qs] for k, qs in qrows.items()}
    tables = tables_mod.build_tables(rows)
    (out / "tables.md").write_text(f"# {exp.name}\n\n" + tables_mod.markdown(tables))
    (out / "tables.tex").write_text(tables_mod.latex(tables))
    plots = plots_mod.make_plots(rows, errors, out / "plots", exp.thresholds_m)
    csv_path = store.export_csv(out / "results.csv")
    run_ids = {r["run_id"] for r in rows} | ({run_id} if run_id else set())
    runs = [r for r in store.runs() if r["run_id"] in run_ids]
    name = f"report-{run_id}.html" if run_id else "report.html"
    report = write_report(
        out / name,
        exp.name,
        rows,
        qrows,
        tables,
        plots,
        runs,
        exp.thresholds_m,
        exp.description or f"experiment file {exp.file}",
        files={
            "results.csv": csv_path.name,
            "tables.md": "tables.md",
            "tables.tex": "tables.tex",
            "results.sqlite": store.path.name,
        },
    )
    if report.name != "report.html":
        shutil.copyfile(report, out / "report.html")
    return report
