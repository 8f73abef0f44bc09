"""Results database: every run of every experiment in ``<output>/results.sqlite`` (stdlib sqlite3), so results
across runs and machines can be queried, compared, merged and exported.

Tables:
- ``runs``: one row per ``aeroloc bench`` invocation: run id, experiment, machine (hostname, CPU count, torch
  version, device), start/finish time and status (running, finished, interrupted, failed).
- ``results``: one row per (run, configuration): the configuration's fields, ``n_tiles``/``n_queries``, the
  exact metrics/timing/memory dicts as JSON, and every scalar of them also as a REAL column for SQL, named with
  ``@`` spelled ``_at_`` (``vpr_recall@1`` -> ``vpr_recall_at_1``, ``georef_recall@10m`` -> ``georef_recall_at_10m``).
  Columns are added when a new metric first appears, so other thresholds/N need no migration.
- ``query_results``: per-query outcome (truth, estimate, error, status, inliers, top tiles, match image).

A configuration is *done* once its row is committed (one transaction per configuration), which is what makes
an interrupted sweep resume where it stopped.
"""

from __future__ import annotations

import json
import math
import os
import platform
import re
import secrets
import socket
import sqlite3
from datetime import UTC, datetime
from pathlib import Path

from aeroloc.core.errors import AerolocError
from aeroloc.core.io import write_csv_atomic

DB_NAME = "results.sqlite"

CONFIG_COLUMNS = [
    "experiment",
    "map",
    "map_path",
    "tile_m",
    "queries",
    "queries_path",
    "method",
    "reranker",
    "zoom",
    "overlap",
    "top_n",
    "top_k",
    "device",
]
QUERY_COLUMNS = [
    "name",
    "true_lat",
    "true_lon",
    "est_lat",
    "est_lon",
    "error_m",
    "status",
    "inliers",
    "top_tiles",
    "vpr_rank",
    "match_image",
]

SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    run_id TEXT PRIMARY KEY, experiment TEXT, experiment_file TEXT, hostname TEXT, cpu_count INTEGER,
    torch_version TEXT, device TEXT, python_version TEXT, aeroloc_version TEXT,
    started_at TEXT, finished_at TEXT, status TEXT, code TEXT);
CREATE TABLE IF NOT EXISTS results (
    run_id TEXT NOT NULL REFERENCES runs(run_id), config_key TEXT NOT NULL,
    experiment TEXT, map TEXT, map_path TEXT, tile_m REAL, queries TEXT, queries_path TEXT, method TEXT,
    reranker TEXT, zoom REAL, overlap REAL, top_n INTEGER, top_k INTEGER, device TEXT,
    n_tiles INTEGER, n_queries INTEGER, created_at TEXT,
    metrics_json TEXT, timing_json TEXT, memory_json TEXT, extra_json TEXT,
    PRIMARY KEY (run_id, config_key));
CREATE INDEX IF NOT EXISTS results_key ON results(config_key);
CREATE TABLE IF NOT EXISTS query_results (
    run_id TEXT NOT NULL, config_key TEXT NOT NULL, name TEXT NOT NULL,
    true_lat REAL, true_lon REAL, est_lat REAL, est_lon REAL, error_m REAL, status TEXT, inliers INTEGER,
    top_tiles TEXT, vpr_rank INTEGER, match_image TEXT,
    PRIMARY KEY (run_id, config_key, name));
"""


def column_name(key: str) -> str:
    """SQL column for a metric key: ``@`` -> ``_at_``, anything else outside [a-z0-9_] -> ``_``."""
    return re.sub(r"[^a-z0-9_]", "_", key.lower().replace("@", "_at_"))


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


def _finite_or_none(v):
    if v is None or isinstance(v, bool):
        return v
    if isinstance(v, (int, float)):
        return float(v) if math.isfinite(v) else None
    return v


def machine_info() -> dict:
    from importlib.metadata import PackageNotFoundError, version

    def ver(pkg):
        try:
            return version(pkg)
        except PackageNotFoundError:
            return None

    return {
        "hostname": socket.gethostname(),
        "cpu_count": os.cpu_count(),
        "torch_version": ver("torch"),
        "python_version": platform.python_version(),
        "aeroloc_version": ver("aeroloc"),
    }


class ResultStore:
    """Open (or create) ``<output>/results.sqlite``. Use as a context manager or call :meth:`close`."""

    def __init__(self, output_dir):
        self.folder = Path(output_dir)
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            self.path = self.folder / DB_NAME
            self.db = sqlite3.connect(self.path, timeout=60)
            self.db.row_factory = sqlite3.Row
            self.db.executescript(SCHEMA)
            if "code" not in {r["name"] for r in self.db.execute("PRAGMA table_info(runs)")}:
                with self.db:  # stores made before runs recorded their code (aeroloc.core.provenance)
                    self.db.execute("ALTER TABLE runs ADD COLUMN code TEXT")
        except (OSError, sqlite3.DatabaseError) as exc:
            raise AerolocError(f"{self.folder / DB_NAME}: cannot open the results database ({exc})") from None
        self._columns = {r["name"] for r in self.db.execute("PRAGMA table_info(results)")}

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        self.db.close()

    # --- runs ---------------------------------------------------------------------------------------------
    def start_run(self, experiment: str, experiment_file="", device: str = "", code: str | None = None) -> str:
        """A new run; ``code``: the identity of the code measuring it (aeroloc.core.provenance.code_identity)."""
        info = machine_info()
        run_id = f"{datetime.now():%Y%m%d-%H%M%S}-{info['hostname'][:20]}-{secrets.token_hex(2)}"
        with self.db:
            self.db.execute(
                "INSERT INTO runs (run_id, experiment, experiment_file, hostname, cpu_count, torch_version, device, "
                "python_version, aeroloc_version, started_at, finished_at, status, code) "
                "VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?)",
                (
                    run_id,
                    experiment,
                    str(experiment_file),
                    info["hostname"],
                    info["cpu_count"],
                    info["torch_version"],
                    device,
                    info["python_version"],
                    info["aeroloc_version"],
                    _now(),
                    None,
                    "running",
                    code,
                ),
            )
        return run_id

    def finish_run(self, run_id: str, status: str = "finished") -> None:
        with self.db:
            self.db.execute("UPDATE runs SET finished_at=?, status=? WHERE run_id=?", (_now(), status, run_id))

    def runs(self, experiment: str | None = None) -> list[dict]:
        q, args = "SELECT * FROM runs", ()
        if experiment is not None:
            q, args = q + " WHERE experiment=?", (experiment,)
        return [dict(r) for r in self.db.execute(q + " ORDER BY started_at, rowid", args)]

    # --- results ------------------------------------------------------------------------------------------
    def done(self, config_key: str, code: str | None = None) -> bool:
        """True once a run stored this configuration; with ``code``, a run of that code identity (a result of
        other code, or of a run that recorded none, is not this code's)."""
        q = "SELECT 1 FROM results r JOIN runs u ON u.run_id = r.run_id WHERE r.config_key=?"
        args: tuple = (config_key,)
        if code is not None:
            q, args = q + " AND u.code=?", (config_key, code)
        return self.db.execute(q + " LIMIT 1", args).fetchone() is not None

    def add_result(self, run_id: str, config, output: dict) -> None:
        """Store one configuration's output (``run_config``'s dict) in one transaction."""
        metrics = {k: v for k, v in (output.get("metrics") or {}).items() if k != "per_query"}
        timing, memory = dict(output.get("timing") or {}), dict(output.get("memory") or {})
        extra = {k: v for k, v in output.items() if k not in ("metrics", "timing", "memory", "rows")}
        cfg = config.as_dict() if hasattr(config, "as_dict") else dict(config)
        values = {
            "run_id": run_id,
            "config_key": config.key(),
            "experiment": cfg["experiment"],
            "map": cfg["map_name"],
            "map_path": cfg["map_path"],
            "tile_m": cfg["tile_m"],
            "queries": cfg["queries_name"],
            "queries_path": cfg["queries_path"],
            "method": cfg["method"],
            "reranker": cfg["reranker"],
            "zoom": cfg["zoom"],
            "overlap": cfg["overlap"],
            "top_n": cfg["top_n"],
            "top_k": cfg["top_k"],
            "device": cfg["device"],
            "n_tiles": output.get("n_tiles"),
            "n_queries": output.get("n_queries", metrics.get("n_queries")),
            "created_at": _now(),
            "metrics_json": json.dumps(metrics, default=str),
            "timing_json": json.dumps(timing, default=str),
            "memory_json": json.dumps(memory, default=str),
            "extra_json": json.dumps({"config": cfg, **extra}, default=str),
        }
        for src in (metrics, timing, memory):
            for k, v in src.items():
                col = column_name(k)
                if col in values or isinstance(v, (str, list, dict, tuple)):
                    continue
                values[col] = _finite_or_none(v)
        with self.db:
            for col in values:
                if col not in self._columns:
                    self.db.execute(f'ALTER TABLE results ADD COLUMN "{col}" REAL')
                    self._columns.add(col)
            names = ",".join(f'"{c}"' for c in values)
            self.db.execute(
                f"INSERT OR REPLACE INTO results ({names}) VALUES ({','.join('?' * len(values))})",
                list(values.values()),
            )
            self.db.execute("DELETE FROM query_results WHERE run_id=? AND config_key=?", (run_id, values["config_key"]))
            self.db.executemany(
                f"INSERT INTO query_results (run_id, config_key, {','.join(QUERY_COLUMNS)}) "
                f"VALUES ({','.join('?' * (2 + len(QUERY_COLUMNS)))})",
                [
                    (run_id, values["config_key"], *(_query_value(r, c) for c in QUERY_COLUMNS))
                    for r in output.get("rows") or []
                ],
            )

    def results(self, keys=None, experiment: str | None = None, latest: bool = True) -> list[dict]:
        """Result rows as flat dicts: configuration fields, ``run_id``, ``config_key``, ``n_tiles``, ``n_queries``
        and the original metric/timing/memory keys (``vpr_recall@1``, ``descriptor_ms`` …). ``keys`` keeps the
        given configuration keys in that order; ``latest`` keeps only the newest row per configuration."""
        q, args = "SELECT * FROM results", []
        if experiment is not None:
            q, args = q + " WHERE experiment=?", [experiment]
        rows = [_flatten(r) for r in self.db.execute(q + " ORDER BY created_at, rowid", args)]
        if latest:
            newest = {}
            for r in rows:
                newest[r["config_key"]] = r
            rows = list(newest.values())
        if keys is not None:
            by_key: dict[str, list[dict]] = {}
            for r in rows:
                by_key.setdefault(r["config_key"], []).append(r)
            rows = [r for k in keys for r in by_key.get(k, [])]
        return rows

    def query_rows(self, run_id: str, config_key: str) -> list[dict]:
        cur = self.db.execute(
            f"SELECT {','.join(QUERY_COLUMNS)} FROM query_results WHERE run_id=? AND config_key=? ORDER BY name",
            (run_id, config_key),
        )
        return [dict(r) for r in cur]

    def export_csv(self, path=None, experiment: str | None = None) -> Path:
        """All result rows (every run) with their SQL columns, JSON blobs left out."""
        path = Path(path) if path else self.folder / "results.csv"
        q, args = "SELECT * FROM results", ()
        if experiment is not None:
            q, args = q + " WHERE experiment=?", (experiment,)
        cur = self.db.execute(q + " ORDER BY created_at, rowid", args)
        cols = [d[0] for d in cur.description if not d[0].endswith("_json")]
        write_csv_atomic(path, cols, ({c: "" if r[c] is None else r[c] for c in cols} for r in cur))
        return path


def _query_value(row: dict, col: str):
    v = row.get(col)
    if col == "top_tiles" and isinstance(v, (list, tuple)):
        v = ";".join(map(str, v))
    if col == "match_image" and v is not None:
        v = str(v)
    return _finite_or_none(v)


def _flatten(r: sqlite3.Row) -> dict:
    out = {c: r[c] for c in ("run_id", "config_key", *CONFIG_COLUMNS, "n_tiles", "n_queries", "created_at")}
    for blob in ("metrics_json", "timing_json", "memory_json", "extra_json"):
        for k, v in json.loads(r[blob] or "{}").items():
            if not isinstance(v, (dict, list)):
                out.setdefault(k, v)  # extra: the pipeline's db folder, results CSV …
    config = json.loads(r["extra_json"] or "{}").get("config") or {}
    out.setdefault("priors", config.get("priors", "auto"))  # the query set's prior mode (atlas table)
    return out
