"""The benchmark's data-driven half: experiment YAML validation, sweep grid, results store + resume, tables,
plots and the HTML report (opened in a real headless Chromium, offline).

The runner tests inject a fake ``run_config`` (a test double for the pipeline, which has its own tests) that
returns the documented output dict with errors derived from the real query positions, and counts its calls.
"""

from __future__ import annotations

import csv
import io
import math
import re
import shutil
import sqlite3
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import pytest
import yaml

from aeroloc.bench import plots, tables
from aeroloc.bench.experiment import expand, load_experiment, project_root, sample_queries
from aeroloc.bench.runner import run_experiment
from aeroloc.bench.store import ResultStore, column_name
from aeroloc.core.errors import AerolocError
from aeroloc.core.geo import offset_latlon

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


# --- helpers ------------------------------------------------------------------------------------------------
def make_project(tmp_path: Path, naip_map=None, naip_dev=None) -> Path:
    """A project folder (pyproject.toml marks its root) with an experiments/ folder; the map/queries files are
    real data when given, else small stand-in files (validation only checks that they exist)."""
    root = tmp_path / "proj"
    (root / "experiments").mkdir(parents=True)
    (root / "pyproject.toml").write_text("[project]\nname='x'\n")
    data = root / "data"
    data.mkdir()
    if naip_map is None:
        (data / "map.tif").write_bytes(b"not really a map")
        (data / "queries.csv").write_text("name,lat,lon\nq1.jpg,47.0,-99.1\n")
    else:
        (data / "map.tif").symlink_to(naip_map)
        (data / "queries.csv").symlink_to(naip_dev)
    return root


def base_doc(**over) -> dict:
    doc = {
        "name": "t",
        "maps": [{"name": "m", "path": "data/map.tif"}],
        "queries": [{"name": "q", "path": "data/queries.csv", "map": "m"}],
        "methods": ["xfeat-vlad"],
        "rerankers": ["none", "xfeat-lighterglue"],
        "zooms": [1, 2],
        "overlaps": [0, 0.5],
        "top_n": [5, 20],
        "top_k": 1,
        "thresholds_m": [10, 25],
        "device": "cpu",
        "output": "out/t",
    }
    doc.update(over)
    return doc


def write_yaml(root: Path, doc: dict, name="exp.yaml") -> Path:
    p = root / "experiments" / name
    p.write_text(yaml.safe_dump(doc, sort_keys=False))
    return p


def read_truth(queries_csv) -> list[tuple[str, float, float]]:
    with open(queries_csv, newline="") as f:
        return [(r["name"], float(r["lat"]), float(r["lon"])) for r in csv.DictReader(f)]


class FakePipeline:
    """Stands in for ``aeroloc.bench.pipeline.run_config``: per-query errors from a fixed rule (larger at zoom 2,
    every 7th query not localized), estimates displaced by that many metres, metrics computed from them."""

    def __init__(self, match_image=None, fail_at=None):
        self.calls = []
        self.match_image = match_image
        self.fail_at = fail_at

    def __call__(self, config, cache_dir):
        if self.fail_at is not None and len(self.calls) == self.fail_at:
            raise KeyboardInterrupt
        self.calls.append(config.key())
        truth = sample_queries(read_truth(config.queries_path), config.max_queries)
        rows = []
        for i, (name, lat, lon) in enumerate(truth):
            err = None if (config.reranker and i % 7 == 3) else (3.0 + (i % 11) * 4.0) * config.zoom
            est = offset_latlon(lat, lon, err, 0.0) if err is not None else (None, None)
            rows.append(
                {
                    "name": name,
                    "true_lat": lat,
                    "true_lon": lon,
                    "est_lat": None if err is None else float(est[0]),
                    "est_lon": None if err is None else float(est[1]),
                    "error_m": math.inf if err is None else err,
                    "status": "ok" if err is not None else "not localized: too few inliers",
                    "inliers": 0 if err is None else 200 - i,
                    "top_tiles": "r000c000;r000c001",
                    "vpr_rank": i % 3,
                    "match_image": str(self.match_image) if self.match_image and i < 3 else None,
                }
            )
        errs = [r["error_m"] for r in rows]
        n = len(rows)
        metrics = {
            "n_queries": n,
            "median_error_m": sorted(e for e in errs if math.isfinite(e))[n // 4],
            "p90_error_m": 40.0,
            "not_localized": sum(not math.isfinite(e) for e in errs) / n,
        }
        for t in config.thresholds_m:
            metrics[f"georef_recall@{t:g}m"] = sum(e <= t for e in errs) / n
        for k in (1, 5, 10, 20):
            metrics[f"retrieval_vpr_recall@{k}"] = min(1.0, 0.3 + 0.1 * k / config.zoom)
            metrics[f"vpr_recall@{k}"] = min(
                1.0, metrics[f"retrieval_vpr_recall@{k}"] + (0.2 if config.reranker else 0)
            )
        timing = {
            "descriptor_ms": 7.0,
            "search_ms": 0.2,
            "local_features_ms": 90.0 if config.reranker else 0.0,
            "rerank_ms": 1500.0 if config.reranker else 0.0,
            "align_ms": 1.0 if config.reranker else 0.0,
            "total_ms_per_query": 1598.2 if config.reranker else 7.2,
            "localize_total_s": 12.0,
        }
        memory = {
            "descriptor_bytes_per_tile": 4096.0,
            "local_bytes_per_tile": 60000.0,
            "index_bytes": 4096 * 30,
            "peak_rss_mb": 900.0,
        }
        return {"metrics": metrics, "rows": rows, "timing": timing, "memory": memory, "n_tiles": 30, "n_queries": n}


# --- experiment files ---------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "change, field",
    [
        ({"methods": ["xfeat-vlad", "no-such-method"]}, "methods[1]"),
        ({"rerankers": ["none", "bogus-glue"]}, "rerankers[1]"),
        ({"maps": [{"name": "m", "path": "data/missing.tif"}]}, "maps[0].path"),
        ({"queries": [{"name": "q", "path": "nowhere/queries.csv", "map": "m"}]}, "queries[0].path"),
        ({"queries": [{"name": "q", "path": "data/queries.csv", "map": "other"}]}, "queries[0].map"),
        ({"zooms": [1, 0]}, "zooms[1]"),
        ({"zooms": [-0.5]}, "zooms[0]"),
        ({"overlaps": [0, 1.0]}, "overlaps[1]"),
        ({"overlaps": [-0.1]}, "overlaps[0]"),
        ({"top_n": [0]}, "top_n"),
        ({"top_k": 30}, "top_k"),
        ({"thresholds_m": [10, -1]}, "thresholds_m[1]"),
        ({"maps": [{"name": "m", "path": "data/map.tif", "tile_m": -5}]}, "maps[0].tile_m"),
        ({"maps": [{"name": "m", "path": "data/map.tif", "local_turns": "yes"}]}, "maps[0].local_turns"),
        ({"maps": [{"name": "m", "path": "data/map.tif", "global_turns": 1}]}, "maps[0].global_turns"),
        ({"queries": [{"name": "q", "path": "data/queries.csv", "map": "m", "limit": 0}]}, "queries[0].limit"),
        (
            {"queries": [{"name": "q", "path": "data/queries.csv", "map": "m", "north_up": "yes"}]},
            "queries[0].north_up",
        ),
        ({"queries": [{"name": "q", "path": "data/queries.csv", "map": "m", "query_gsd": 0}]}, "queries[0].query_gsd"),
        (
            {"queries": [{"name": "q", "path": "data/queries.csv", "map": "m", "query_gsd": "5"}]},
            "queries[0].query_gsd",
        ),
        ({"zoom": [1]}, "zoom"),  # typo of zooms: unknown fields are errors, not silently ignored
    ],
)
def test_validation_error_names_file_and_field(tmp_path, change, field):
    root = make_project(tmp_path)
    path = write_yaml(root, base_doc(**change))
    with pytest.raises(AerolocError) as err:
        load_experiment(path)
    msg = str(err.value)
    assert str(path) in msg and f" {field}:" in msg, msg


def test_validation_missing_required_and_bad_yaml(tmp_path):
    root = make_project(tmp_path)
    doc = base_doc()
    del doc["methods"]
    path = write_yaml(root, doc)
    with pytest.raises(AerolocError, match=r"exp\.yaml: methods: is required"):
        load_experiment(path)
    bad = root / "experiments" / "bad.yaml"
    bad.write_text("name: x\nmaps: [unclosed\n")
    with pytest.raises(AerolocError, match=r"bad\.yaml: not valid YAML"):
        load_experiment(bad)
    with pytest.raises(AerolocError, match="not found"):
        load_experiment(root / "experiments" / "absent.yaml")


def test_relative_paths_start_at_project_root(tmp_path):
    root = make_project(tmp_path)
    exp = load_experiment(write_yaml(root, base_doc()))
    assert project_root(root / "experiments" / "exp.yaml") == root
    assert exp.maps[0].path == root / "data" / "map.tif"
    assert exp.output == root / "out" / "t" and exp.cache == root / "out" / "t" / "cache"
    # without a project marker, paths start at the YAML's own folder
    loose = tmp_path / "loose"
    (loose / "data").mkdir(parents=True)
    shutil.copy(root / "data" / "map.tif", loose / "data" / "map.tif")
    shutil.copy(root / "data" / "queries.csv", loose / "data" / "queries.csv")
    (loose / "e.yaml").write_text(yaml.safe_dump(base_doc()))
    if project_root(loose / "e.yaml") == loose:  # tmp_path itself is not inside a project
        assert load_experiment(loose / "e.yaml").maps[0].path == loose / "data" / "map.tif"


def test_grid_expansion(tmp_path):
    root = make_project(tmp_path)
    exp = load_experiment(write_yaml(root, base_doc()))
    configs = expand(exp)
    # 2 zooms x 2 overlaps x (retrieval-only once with the largest N + re-ranker at N=5 and N=20)
    assert len(configs) == 2 * 2 * (1 + 2)
    assert {(c.zoom, c.overlap) for c in configs} == {(1.0, 0.0), (1.0, 0.5), (2.0, 0.0), (2.0, 0.5)}
    assert {c.top_n for c in configs if c.reranker is None} == {20}
    assert {c.top_n for c in configs if c.reranker} == {5, 20}
    keys = [c.key() for c in configs]
    assert len(set(keys)) == len(keys)
    # stable: the same experiment expands to the same keys; a copy of the data elsewhere (same content,
    # other paths and names) measures the same thing, so it gets the same keys
    assert [c.key() for c in expand(load_experiment(write_yaml(root, base_doc())))] == keys
    (root / "copy").mkdir()
    shutil.copy(root / "data" / "map.tif", root / "copy" / "m.tif")
    shutil.copy(root / "data" / "queries.csv", root / "copy" / "q.csv")
    moved = base_doc(
        maps=[{"name": "renamed", "path": "copy/m.tif"}],
        queries=[{"name": "q2", "path": "copy/q.csv", "map": "renamed"}],
    )
    assert [c.key() for c in expand(load_experiment(write_yaml(root, moved, "moved.yaml")))] == keys
    # integer and float spellings of a zoom are one configuration
    assert expand(load_experiment(write_yaml(root, base_doc(zooms=[1.0, 2.0]), "f.yaml")))[0].key() == keys[0]


def test_a_changed_sweep_default_does_not_reuse_old_results(tmp_path, monkeypatch):
    from aeroloc.localization import structure_check
    from aeroloc.matching import sweep

    root = make_project(tmp_path)
    configs = expand(load_experiment(write_yaml(root, base_doc())))
    before = [c.key() for c in configs]
    monkeypatch.setitem(sweep.SWEEP_DEFAULTS, "confirm_inliers", 25)
    after = [c.key() for c in configs]
    monkeypatch.setitem(structure_check.STRUCTURE_DEFAULTS, "structure_min_ratio", 1.7)
    again = [c.key() for c in configs]
    for c, b, a, g in zip(configs, before, after, again, strict=True):
        assert (b != a != g) if c.reranker else (b == a == g)  # retrieval-only configurations never sweep


def test_query_limit_is_an_evenly_spaced_subset_and_part_of_the_key(tmp_path):
    assert sample_queries(list(range(120)), 30) == list(range(0, 120, 4))
    assert sample_queries(list(range(57)), 19) == list(range(0, 57, 3))
    picked = sample_queries(list(range(10)), 4)
    assert len(picked) == 4 and picked[0] == 0 and len(set(picked)) == 4 and picked == sorted(picked)
    assert sample_queries([1, 2], 5) == [1, 2] and sample_queries([1, 2], None) == [1, 2]
    root = make_project(tmp_path)
    full = expand(load_experiment(write_yaml(root, base_doc())))
    limited = expand(
        load_experiment(
            write_yaml(
                root, base_doc(queries=[{"name": "q", "path": "data/queries.csv", "map": "m", "limit": 30}]), "l.yaml"
            )
        )
    )
    assert {c.max_queries for c in full} == {None} and {c.max_queries for c in limited} == {30}
    assert not {c.key() for c in full} & {c.key() for c in limited}


def test_paper_experiments_validate():
    repo = Path(__file__).resolve().parents[1]
    data = repo.parent / "shared" / "data"
    if not data.is_dir():
        pytest.skip(f"real data not found at {data}")
    from aeroloc.retrieval.models import DEFAULT_METHOD

    for name in ("paper-zoom", "paper-overlap", "paper-rerank", "retrieval-sweep", "dense-stage"):
        exp = load_experiment(repo / "experiments" / f"{name}.yaml")
        assert exp.maps[0].path == (data / "naip-nd" / "map_20200831.tif")
        assert DEFAULT_METHOD in {c.method for c in expand(exp)}  # the default method is always measured
    zoom = load_experiment(repo / "experiments" / "paper-zoom.yaml")
    assert zoom.zooms == (0.5, 1.0, 1.5, 2.0) and zoom.overlaps == (0.0,)
    rerank = load_experiment(repo / "experiments" / "paper-rerank.yaml")
    assert set(rerank.rerankers) == {"xfeat-lighterglue", "xfeat-mnn", "aliked-lightglue", "disk-lightglue", "sift"}
    assert rerank.top_n == (20, 100)
    dense = expand(load_experiment(repo / "experiments" / "dense-stage.yaml"))
    assert {(c.queries_name, c.query_gsd, c.north_up) for c in dense} == {
        ("naip-nd/dev", None, True),
        ("naip-nd/dev+dense", 5.0, True),
        ("naip-nd/dev-rotated", None, False),
        ("naip-nd/dev-rotated+dense", 5.0, False),
    }


# --- results store ------------------------------------------------------------------------------------------
def test_store_round_trip(tmp_path):
    root = make_project(tmp_path)
    exp = load_experiment(write_yaml(root, base_doc()))
    configs = expand(exp)
    fake = FakePipeline()
    with ResultStore(tmp_path / "out") as store:
        run = store.start_run(exp.name, exp.file, "cpu")
        assert not store.done(configs[0].key())
        out = fake(configs[0], tmp_path)
        store.add_result(run, configs[0], out)
        store.finish_run(run)
        assert store.done(configs[0].key()) and not store.done(configs[1].key())
        [row] = store.results()
        for k, v in out["metrics"].items():
            assert row[k] == pytest.approx(v), k
        assert row["descriptor_ms"] == 7.0 and row["index_bytes"] == 4096 * 30
        assert (row["zoom"], row["overlap"], row["reranker"], row["queries"]) == (1.0, 0.0, None, "q")
        qrows = store.query_rows(run, configs[0].key())
        assert [q["name"] for q in qrows] == sorted(r["name"] for r in out["rows"])
        [runinfo] = store.runs()
        assert runinfo["status"] == "finished" and runinfo["cpu_count"] >= 1 and runinfo["hostname"]
        csv_path = store.export_csv()
    # plain SQL sees the metrics as columns
    db = sqlite3.connect(tmp_path / "out" / "results.sqlite")
    r1 = db.execute(f"SELECT {column_name('retrieval_vpr_recall@1')}, georef_recall_at_10m FROM results").fetchone()
    assert r1 == (
        pytest.approx(out["metrics"]["retrieval_vpr_recall@1"]),
        pytest.approx(out["metrics"]["georef_recall@10m"]),
    )
    with open(csv_path, newline="") as f:
        [exported] = list(csv.DictReader(f))
    assert float(exported["vpr_recall_at_5"]) == pytest.approx(out["metrics"]["vpr_recall@5"])
    assert exported["config_key"] == configs[0].key()


def test_store_not_localized_query_round_trips_as_none(tmp_path):
    root = make_project(tmp_path)
    exp = load_experiment(write_yaml(root, base_doc()))
    c = next(c for c in expand(exp) if c.reranker)
    out = FakePipeline()(c, tmp_path)
    out["rows"].append(
        {
            **out["rows"][0],
            "name": "zz-lost.jpg",
            "est_lat": None,
            "est_lon": None,
            "error_m": math.inf,
            "status": "not localized",
        }
    )
    with ResultStore(tmp_path / "o") as store:
        run = store.start_run("t")
        store.add_result(run, c, out)
        lost = next(q for q in store.query_rows(run, c.key()) if q["name"] == "zz-lost.jpg")
    assert lost["est_lat"] is None and lost["error_m"] is None and lost["status"] == "not localized"


# --- runner: resume ----------------------------------------------------------------------------------------
def test_a_sweep_resumes_only_what_this_code_measured(tmp_path, monkeypatch, capsys):
    """Stored configurations are skipped only when a run of the same code identity measured them: after a code
    change (another identity) every configuration is measured again and the run says why; a store made before
    runs recorded their code opens and counts as other code."""
    import aeroloc.bench.runner as runner
    import aeroloc.core.provenance as provenance

    monkeypatch.setattr(runner, "write_outputs", lambda exp, configs, store, run_id: exp.output / "r.html")
    root = make_project(tmp_path)
    path = write_yaml(root, base_doc())
    n = len(expand(load_experiment(path)))
    run_experiment(path, run_config=FakePipeline(), progress=False)
    same = FakePipeline()
    run_experiment(path, run_config=same, progress=False)
    assert same.calls == []
    monkeypatch.setattr(provenance, "code_identity", lambda packages=None, root=None: "changed-code")
    changed = FakePipeline()
    run_experiment(path, run_config=changed, progress=True)
    assert len(changed.calls) == n
    assert f"{n} stored configurations were measured by other code than this (changed-code)" in capsys.readouterr().out
    with ResultStore(root / "out" / "t") as store:
        codes = [r["code"] for r in store.runs()]
        assert codes[-1] == "changed-code" and codes[0] == codes[1] != "changed-code"
        assert all(store.done(k, "changed-code") for k in changed.calls)
    # a store of the old schema (runs without a code column)
    old = tmp_path / "old"
    old.mkdir()
    db = sqlite3.connect(old / "results.sqlite")
    db.executescript(
        "CREATE TABLE runs (run_id TEXT PRIMARY KEY, experiment TEXT, experiment_file TEXT, hostname TEXT, "
        "cpu_count INTEGER, torch_version TEXT, device TEXT, python_version TEXT, aeroloc_version TEXT, "
        "started_at TEXT, finished_at TEXT, status TEXT);"
        "INSERT INTO runs VALUES ('r0','t','','h',2,'','cpu','3','0.1','','','finished');"
    )
    db.close()
    with ResultStore(old) as store:
        run = store.start_run("t", code="now")
        assert {r["run_id"]: r["code"] for r in store.runs()} == {"r0": None, run: "now"}


def test_runner_resumes_after_interrupt(tmp_path, monkeypatch):
    import aeroloc.bench.runner as runner

    root = make_project(tmp_path)
    path = write_yaml(root, base_doc())
    n = len(expand(load_experiment(path)))
    # the outputs (plots take ~1 s each here) are built for real once, at the end
    built = []
    monkeypatch.setattr(
        runner,
        "write_outputs",
        lambda exp, configs, store, run_id: built.append(run_id) or exp.output / f"report-{run_id}.html",
    )
    first = FakePipeline(fail_at=2)
    with pytest.raises(KeyboardInterrupt):
        run_experiment(path, run_config=first, progress=False)
    assert len(first.calls) == 2
    with ResultStore(root / "out" / "t") as store:
        assert [r["status"] for r in store.runs()] == ["interrupted"]
        assert all(store.done(k) for k in first.calls)
    assert built == []  # interrupted: no report
    second = FakePipeline()
    report = run_experiment(path, run_config=second, progress=False)
    assert len(second.calls) == n - 2 and not set(second.calls) & set(first.calls)
    assert report.name == f"report-{built[-1]}.html"
    third = FakePipeline()
    run_experiment(path, run_config=third, progress=False)
    assert third.calls == []
    again = FakePipeline()
    run_experiment(path, resume=False, run_config=again, progress=False)
    assert len(again.calls) == n
    monkeypatch.undo()
    only = FakePipeline()
    report = run_experiment(path, report_only=True, run_config=only, progress=False)
    assert report.name == "report.html" and report.is_file() and only.calls == []
    with ResultStore(root / "out" / "t") as store:
        assert len(store.results()) == n  # newest row per configuration
        assert len(store.results(latest=False)) == 2 + (n - 2) + n
        assert [r["status"] for r in store.runs()] == ["interrupted", "finished", "finished", "finished"]
    out = root / "out" / "t"
    assert "**" in (out / "tables.md").read_text() and "\\textbf{" in (out / "tables.tex").read_text()


def test_report_only_without_results_is_a_clear_error(tmp_path):
    root = make_project(tmp_path)
    path = write_yaml(root, base_doc())
    with pytest.raises(AerolocError, match="no results stored"):
        run_experiment(path, report_only=True, progress=False)


def test_cli_bench_reports_bad_experiment(tmp_path, capsys):
    from aeroloc.cli import main

    root = make_project(tmp_path)
    path = write_yaml(root, base_doc(zooms=[0]))
    assert main(["bench", str(path)]) == 2
    err = capsys.readouterr().err
    assert "zooms[0]" in err and str(path) in err and "Traceback" not in err


# --- tables ------------------------------------------------------------------------------------------------
def row(**kw) -> dict:
    base = {
        "queries": "ds",
        "map": "m",
        "method": "xfeat-vlad",
        "reranker": None,
        "zoom": 1.0,
        "overlap": 0.0,
        "top_n": 20,
        "top_k": 1,
        "tile_m": None,
        "config_key": str(kw),
    }
    base.update(kw)
    return base


def recall_row(method, zoom, r1, r5, r10, **kw):
    return row(
        method=method,
        zoom=zoom,
        **{"retrieval_vpr_recall@1": r1, "retrieval_vpr_recall@5": r5, "retrieval_vpr_recall@10": r10},
        **kw,
    )


def test_zoom_table_bolds_best_per_row_and_picks_best_zoom():
    rows = [
        recall_row("a", 0.5, 0.40, 0.70, 0.80),
        recall_row("a", 1.0, 0.68, 0.90, 0.93),
        recall_row("a", 2.0, 0.55, 0.92, 0.93),
        recall_row("b", 0.5, 0.30, 0.50, 0.60),
        recall_row("b", 1.0, 0.20, 0.50, 0.70),
        recall_row("b", 2.0, 0.10, 0.40, 0.65),
    ]
    t = tables.sweep_table(rows, "zoom", "ds")
    assert [c.text for c in t.rows[0][:1]] == ["a"]
    a, b = t.rows
    # value cells: zoom 0.5 (R@1, R@5, R@10), zoom 1 (…), zoom 2 (…), best zoom
    bold_a = [c.text for c in a[1:-1] if c.bold]
    assert bold_a == ["68.0", "93.0", "92.0", "93.0"]  # R@10 ties at zoom 1 and 2: both bold
    assert a[-1].text == "1"
    assert [c.text for c in b[1:-1] if c.bold] == ["30.0", "50.0", "50.0", "70.0"]
    assert b[-1].text == "0.5"
    md, tex, page = t.markdown(), t.latex(), t.html()
    assert "| a | 40.0 | 70.0 | 80.0 | **68.0** |" in md
    assert "\\textbf{68.0}" in tex and "\\multicolumn{3}{c}{zoom 0.5}" in tex
    assert "<b>68.0</b>" in page
    # the rows' retrieval recall is used, not the re-ranked one
    assert "99.0" not in tables.sweep_table([dict(r, **{"vpr_recall@1": 0.99}) for r in rows], "zoom", "ds").markdown()


def test_overlap_table_and_single_value_sweeps():
    rows = [
        row(overlap=o, **{"retrieval_vpr_recall@1": r, "retrieval_vpr_recall@5": r, "retrieval_vpr_recall@10": r})
        for o, r in ((0.0, 0.5), (0.25, 0.6), (0.5, 0.6))
    ]
    t = tables.sweep_table(rows, "overlap", "ds")
    assert [c.text for c in t.rows[0][1:-1] if c.bold] == ["60.0"] * 6 and t.rows[0][-1].text == "0.25"
    assert tables.sweep_table(rows, "zoom", "ds") is None  # one zoom: no zoom table


def test_time_memory_georef_tables_bold_best_per_column():
    fast = row(
        reranker="xfeat-lighterglue",
        **{
            "descriptor_ms": 7.0,
            "search_ms": 0.3,
            "local_features_ms": 80.0,
            "rerank_ms": 1500.0,
            "align_ms": 1.0,
            "total_ms_per_query": 1588.3,
            "georef_recall@10m": 0.90,
            "georef_recall@25m": 0.98,
            "median_error_m": 3.0,
            "p90_error_m": 12.0,
            "not_localized": 0.02,
            "descriptor_bytes_per_tile": 2048,
            "local_bytes_per_tile": 60000,
            "index_bytes": 10240,
            "peak_rss_mb": 800,
            "n_tiles": 12,
        },
    )
    slow = row(
        reranker="aliked-lightglue",
        **{
            "descriptor_ms": 7.5,
            "search_ms": 0.2,
            "local_features_ms": 600.0,
            "rerank_ms": 4400.0,
            "align_ms": 1.0,
            "total_ms_per_query": 5008.7,
            "georef_recall@10m": 0.95,
            "georef_recall@25m": 0.98,
            "median_error_m": 1.7,
            "p90_error_m": 6.0,
            "not_localized": 0.0,
            "descriptor_bytes_per_tile": 2048,
            "local_bytes_per_tile": 90000,
            "index_bytes": 10240,
            "peak_rss_mb": 1200,
            "n_tiles": 12,
        },
    )
    t = tables.time_table([fast, slow], "ds")
    bold = [[c.text for c in r[len(t.labels) :] if c.bold] for r in t.rows]
    assert bold[0] == ["7.0", "80.0", "1500.0", "1588.3"] and bold[1] == ["0.2"]  # align ties: no bold
    g = tables.georef_table([fast, slow], "ds")
    assert [c.text for c in g.rows[1][len(g.labels) :] if c.bold] == ["95.0", "1.7", "6.0", "0.0"]
    assert [c.text for c in g.rows[0][len(g.labels) :] if c.bold] == []  # ≤25 m: 98.0 twice, nothing stands out
    m = tables.memory_table([fast, slow], "ds")
    assert [c.text for c in m.rows[0][len(m.labels) :] if c.bold] == ["58.6", "800"]
    assert [c.text for c in m.rows[1][len(m.labels) :] if c.bold] == []
    r = tables.rerank_table([dict(fast, **{"retrieval_vpr_recall@1": 0.68, "vpr_recall@1": 0.9})], "ds")
    cells = r.rows[0][len(r.labels) :]
    assert [c.text for c in cells] == ["68.0", "90.0", "1580"] and [c.bold for c in cells[:2]] == [False, True]


# --- plots -------------------------------------------------------------------------------------------------
def test_plots_are_valid_pngs(tmp_path):
    from PIL import Image

    rows = [recall_row("a", z, 0.2 * z, 0.3 * z, 0.4 * z, reranker=None) for z in (0.5, 1.0, 2.0)]
    rows += [
        dict(
            recall_row("a", 1.0, 0.5, 0.6, 0.7, reranker="xfeat-lighterglue", config_key="rr"),
            descriptor_ms=7.0,
            search_ms=0.2,
            local_features_ms=80.0,
            rerank_ms=1500.0,
            align_ms=1.0,
        )
    ]
    errors = {"rr": [1.0, 2.5, 7.0, 30.0, None, 120.0]}
    made = plots.make_plots(rows, errors, tmp_path, thresholds=(10, 25))
    assert {p.key for p in made} == {"recall-zoom", "error-cdf", "time"}
    for p in made:
        data = p.path.read_bytes()
        assert data[:8] == PNG_MAGIC
        with Image.open(io.BytesIO(data)) as im:
            im.verify()
        with Image.open(p.path) as im:
            assert im.width > 400 and im.height > 200
            lo, hi = im.convert("L").getextrema()
            assert hi - lo > 100  # drawn, not a blank canvas


def test_map_overlay_sits_on_the_map_footprint(naip_map):
    import base64

    from PIL import Image

    from aeroloc.bench.report import map_overlay
    from aeroloc.maps.sources import open_map

    m = open_map(naip_map)
    ov = map_overlay(naip_map, max_px=400)
    (s, w), (n, e) = ov["bounds"]
    south, west, north, east = m.bounds_latlon()
    # the Web Mercator image's edges are the UTM footprint's extreme corners, to within one output pixel
    # (here 3 map pixels = 15 m), on every side
    m_per_deg_lat, m_per_deg_lon = 111_200.0, 111_200.0 * math.cos(math.radians(north))
    gaps = [
        (south - s) * m_per_deg_lat,
        (n - north) * m_per_deg_lat,
        (west - w) * m_per_deg_lon,
        (e - east) * m_per_deg_lon,
    ]
    assert max(abs(g) for g in gaps) < 15.0, gaps
    _header, data = ov["url"].split(",", 1)
    with Image.open(io.BytesIO(base64.b64decode(data))) as im:
        assert im.mode == "RGBA" and max(im.size) <= 420
        assert abs(im.width / im.height - (e - w) / (n - s) * math.cos(math.radians((n + s) / 2))) < 0.05


# --- HTML report in a real browser --------------------------------------------------------------------------
class _Links(HTMLParser):
    """Every URL-bearing attribute of every element (script/style *text* is not an element)."""

    def __init__(self):
        super().__init__()
        self.urls = []
        self.tags = []

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        for k, v in attrs:
            if k in ("src", "href", "data-full", "srcset", "poster", "action") and v:
                self.urls.append(v)


def external_urls(page: str) -> list[str]:
    p = _Links()
    p.feed(page)
    css_urls = re.findall(r"url\(\s*['\"]?([^)'\"]+)", page)
    return [u for u in p.urls + css_urls if re.match(r"\s*(https?:)?//", u, re.I)]


def chromium(*args, timeout=90) -> subprocess.CompletedProcess:
    exe = shutil.which("chromium")
    if exe is None:
        pytest.skip("chromium is not on PATH (Debian: apt-get install chromium); the report is not browser-tested")
    return subprocess.run(
        [
            exe,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--disable-dev-shm-usage",
            *args,
        ],
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def test_html_report_is_offline_and_renders_in_chromium(tmp_path, naip_map, naip_dev):
    import numpy as np
    from PIL import Image

    root = make_project(tmp_path, naip_map, naip_dev)
    match = tmp_path / "match.jpg"
    Image.fromarray((np.indices((120, 240)).sum(0) % 255).astype(np.uint8)).convert("RGB").save(match)
    path = write_yaml(root, base_doc(rerankers=["xfeat-lighterglue"], zooms=[1, 2], overlaps=[0], top_n=[20]))
    report = run_experiment(path, run_config=FakePipeline(match_image=match), progress=False)
    page = report.read_text()
    assert external_urls(page) == []
    assert "leaflet" in page.lower() and "L.imageOverlay" in page
    assert page.count("data:image/png;base64,") >= 4  # map imagery + plots
    assert "class=thumb" in page  # match visualisations for the sample queries

    shot = tmp_path / "shot.png"
    res = chromium(
        f"--user-data-dir={tmp_path / 'chrome'}",
        f"--screenshot={shot}",
        "--window-size=1280,2000",
        "--virtual-time-budget=4000",
        report.as_uri(),
    )
    assert shot.is_file(), res.stderr[-2000:]
    with Image.open(shot) as im:
        assert im.size == (1280, 2000)
        arr = np.asarray(im.convert("RGB")).astype(int)
    assert arr.std() > 20 and len(np.unique(arr.reshape(-1, 3)[::97], axis=0)) > 50  # a page, not blank

    dom = chromium(
        f"--user-data-dir={tmp_path / 'chrome2'}", "--dump-dom", "--virtual-time-budget=4000", report.as_uri()
    ).stdout
    n_queries = len(read_truth(naip_dev))
    # Leaflet ran offline: the map container exists, the imagery overlay is placed, and the shown configuration
    # draws one interactive SVG path per marker/line (localized: line + 2 dots; not localized: 1 ring)
    assert "leaflet-container" in dom and "leaflet-image-layer" in dom
    from aeroloc.core.provenance import code_identity

    assert f">{code_identity()}</td>" in dom  # the runs table names the code that measured them
    n_lost = len([i for i in range(n_queries) if i % 7 == 3])
    assert dom.count("leaflet-interactive") >= 3 * (n_queries - n_lost) + n_lost
    assert external_urls(dom) == []


def test_key_follows_the_rerankers_effective_settings(tmp_path, monkeypatch):
    """A changed re-ranker default (threshold, geometry …) gives new keys, so old results are measured again;
    retrieval-only configurations keep theirs."""
    from aeroloc.matching import registry

    root = make_project(tmp_path)
    doc = base_doc(rerankers=["none", "xfeat-lighterglue"])
    before = {c.reranker: c.key() for c in expand(load_experiment(write_yaml(root, doc)))}
    entry = registry.RERANKERS["xfeat-lighterglue"]
    changed = {**entry, "cascade": {**entry["cascade"], "min_inliers": 31}}
    monkeypatch.setitem(registry.RERANKERS, "xfeat-lighterglue", changed)
    after = {c.reranker: c.key() for c in expand(load_experiment(write_yaml(root, doc, "b.yaml")))}
    assert after[None] == before[None]
    assert after["xfeat-lighterglue"] != before["xfeat-lighterglue"]


def test_north_up_query_sets_are_their_own_configurations_for_rerankers_only(tmp_path):
    root = make_project(tmp_path)
    q = {"name": "q", "path": "data/queries.csv", "map": "m"}
    plain = {c.reranker: c for c in expand(load_experiment(write_yaml(root, base_doc(queries=[q]))))}
    north = {
        c.reranker: c
        for c in expand(load_experiment(write_yaml(root, base_doc(queries=[{**q, "north_up": True}]), "n.yaml")))
    }
    assert north["xfeat-lighterglue"].north_up and north["xfeat-lighterglue"].key() != plain["xfeat-lighterglue"].key()
    assert "north-up" in north["xfeat-lighterglue"].label()
    assert not north[None].north_up and north[None].key() == plain[None].key()  # retrieval ignores the heading


def test_turned_tile_maps_are_their_own_configurations_for_rerankers_only(tmp_path):
    root = make_project(tmp_path)
    plain = {c.reranker: c for c in expand(load_experiment(write_yaml(root, base_doc())))}
    m = {"name": "m", "path": "data/map.tif", "local_turns": True}
    turned = {c.reranker: c for c in expand(load_experiment(write_yaml(root, base_doc(maps=[m]), "t.yaml")))}
    assert turned["xfeat-lighterglue"].local_turns and "turned tiles" in turned["xfeat-lighterglue"].label()
    assert turned["xfeat-lighterglue"].key() != plain["xfeat-lighterglue"].key()
    assert not turned[None].local_turns and turned[None].key() == plain[None].key()


def test_turned_descriptor_maps_are_their_own_configurations(tmp_path):
    root = make_project(tmp_path)
    plain = {c.reranker: c for c in expand(load_experiment(write_yaml(root, base_doc())))}
    m = {"name": "m", "path": "data/map.tif", "global_turns": True}
    turned = {c.reranker: c for c in expand(load_experiment(write_yaml(root, base_doc(maps=[m]), "t.yaml")))}
    for r in (None, "xfeat-lighterglue"):  # retrieval alone uses them too
        assert turned[r].global_turns and "turned descriptors" in turned[r].label()
        assert turned[r].key() != plain[r].key()


def test_a_query_resolution_makes_dense_configurations_for_rerankers_only(tmp_path):
    root = make_project(tmp_path)
    q = {"name": "q", "path": "data/queries.csv", "map": "m"}
    plain = {c.reranker: c for c in expand(load_experiment(write_yaml(root, base_doc(queries=[q]))))}
    dense = {
        c.reranker: c
        for c in expand(load_experiment(write_yaml(root, base_doc(queries=[{**q, "query_gsd": 5}]), "d.yaml")))
    }
    assert dense["xfeat-lighterglue"].query_gsd == 5.0
    assert dense["xfeat-lighterglue"].key() != plain["xfeat-lighterglue"].key()
    assert "dense @ 5 m/px" in dense["xfeat-lighterglue"].label()
    assert dense[None].query_gsd is None and dense[None].key() == plain[None].key()


def test_prior_modes_are_their_own_configurations_and_bad_ones_are_named(tmp_path):
    root = make_project(tmp_path)
    q = {"name": "q", "path": "data/queries.csv", "map": "m"}
    doc = base_doc(
        queries=[q, {**q, "name": "q rough", "priors": "rough"}, {**q, "name": "q exact", "priors": "exact"}]
    )
    configs = [c for c in expand(load_experiment(write_yaml(root, doc))) if c.reranker]
    by_mode = {c.priors: c for c in configs if (c.zoom, c.overlap, c.top_n) == (1, 0, 5)}
    assert set(by_mode) == {"auto", "rough", "exact"}
    assert len({c.key() for c in by_mode.values()}) == 3 and "priors rough" in by_mode["rough"].label()
    bad = base_doc(queries=[{**q, "priors": "truth"}])
    with pytest.raises(AerolocError, match=r"queries\[0\]\.priors.*none, rough, exact or auto"):
        load_experiment(write_yaml(root, bad, "bad.yaml"))


def test_scaled_recall_counts_in_map_pixels_and_metres():
    from aeroloc.bench.metrics import scaled_recall

    per_query = [{"error_m": e} for e in (1.0, 6.0, 30.0, math.inf)]
    fine = scaled_recall(per_query, 0.5)  # t = 5 m, wrong beyond 25 m
    assert (fine["t_m"], fine["wrong_m"]) == (5.0, 25.0)
    assert fine["georef_recall@t"] == 0.25 and fine["wrong_n"] == 1 and fine["wrong"] == 0.25
    coarse = scaled_recall(per_query, 5.0)  # t = 10 m (2 px), wrong beyond 50 m (10 px)
    assert coarse["georef_recall@t"] == 0.5 and coarse["wrong_n"] == 0  # not localized is a miss, never wrong


def test_the_atlas_table_lists_every_set_and_prior_mode():
    from aeroloc.bench.tables import atlas_table

    rows = [
        {
            "queries": "a",
            "priors": "exact",
            "georef_recall@t": 0.9,
            "t_m": 5.0,
            "not_localized": 0.1,
            "wrong_n": 0,
            "median_ms_per_query": 250.0,
        },
        {
            "queries": "a",
            "priors": "none",
            "georef_recall@t": 0.5,
            "t_m": 5.0,
            "not_localized": 0.5,
            "wrong_n": 1,
            "median_ms_per_query": 1500.0,
        },
        {"queries": "b", "vpr_recall@1": 0.3},  # no scale-aware metrics: not an atlas row
    ]
    md = atlas_table(rows).markdown()
    assert "| a | exact | 90.0 | 5.0 | 10.0 | 0 | 0.25 |" in md and "| a | none | 50.0 | 5.0 | 50.0 | 1 | 1.50 |" in md
    assert "| b |" not in md


def test_the_georef_table_reads_only_metre_thresholds_beside_the_scaled_recall():
    from aeroloc.bench.tables import georef_table

    row = {"queries": "a", "method": "m", "reranker": "r", "georef_recall@5m": 0.5, "georef_recall@t": 0.7}
    md = georef_table([row], "a").markdown()
    assert "≤5 m" in md and "≤t" not in md


def test_the_shipped_experiment_files_load_and_the_rough_seeds_redraw_only_the_noise():
    """Every sweep file in experiments/ loads (a broken shipped file fails here, not in a user's hour-long run),
    and atlas-rough-seeds.yaml holds the atlas's rough rows again at noise seeds 1 and 2: the same sets, maps and
    settings, keys of their own (results are not mixed with seed 0's)."""
    root = Path(__file__).resolve().parents[1] / "experiments"
    sweeps = [p for p in sorted(root.glob("*.yaml")) if "methods" in (yaml.safe_load(p.read_text()) or {})]
    assert {"atlas.yaml", "atlas-rough-seeds.yaml"} <= {p.name for p in sweeps}
    configs = {p.name: expand(load_experiment(p)) for p in sweeps}
    rough = [c for c in configs["atlas.yaml"] if c.priors == "rough"]
    seeds = configs["atlas-rough-seeds.yaml"]
    assert len(seeds) == 2 * len(rough) > 0
    assert {c.seed for c in rough} == {0} and sorted({c.seed for c in seeds}) == [1, 2]
    assert {c.queries_path for c in seeds} == {c.queries_path for c in rough}
    assert {(c.map_path, c.tile_m, c.top_n, c.reranker) for c in seeds} == {
        (c.map_path, c.tile_m, c.top_n, c.reranker) for c in rough
    }
    assert not {c.key() for c in seeds} & {c.key() for c in configs["atlas.yaml"]}
