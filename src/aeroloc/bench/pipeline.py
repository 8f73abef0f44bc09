"""One configuration end to end, for benchmarks: tiles -> descriptors/index -> localize -> metrics, with the
same clock for every stage and the memory each part takes. Every stage is cached in ``cache_dir`` by its own
configuration key, so a sweep reuses tile sets, descriptor stores, feature stores and indexes."""

from __future__ import annotations

import resource
import time
from pathlib import Path

import numpy as np

from aeroloc.localization.results import STAGES


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _localize_peak_rss(out_csv: Path, reused: bool) -> float | None:
    """The peak RSS of the process that localized ``out_csv``: measured now and kept beside the results, or read
    back when the finished results were reused (this process never held that run's memory); None if unknown."""
    import json

    side = out_csv.with_name(out_csv.name + ".memory.json")
    if reused:
        return json.loads(side.read_text()).get("peak_rss_mb") if side.is_file() else None
    peak = peak_rss_mb()
    side.write_text(json.dumps({"peak_rss_mb": peak}))
    return peak


def _match_image(folder, name):
    if folder is None:
        return None
    p = Path(folder) / f"{Path(name).stem}.jpg"
    return str(p) if p.is_file() else None


def db_folder(cache_dir, map_path, zoom, overlap, tile_m) -> Path:
    from aeroloc.core.io import config_key

    name = Path(map_path).stem
    return Path(cache_dir) / "db" / f"{name}-z{zoom:g}-o{overlap:g}-{config_key(str(Path(map_path).resolve()), tile_m)}"


def run_config(cfg, cache_dir, progress: bool = False) -> dict:
    """``cfg`` (aeroloc.bench.experiment.Config) has map_path, tile_m, queries_path, method, reranker (None =
    retrieval only), zoom, overlap, top_n, top_k, thresholds_m, device, north_up, query_gsd, max_queries.
    Returns the record the results store keeps: metrics, per-query rows, timing (ms/query per stage, totals) and
    memory (bytes per tile, index bytes, peak RSS)."""
    from aeroloc.bench.experiment import sample_queries
    from aeroloc.core.device import pick_device
    from aeroloc.core.queries import load_queries
    from aeroloc.localization.run import localize_queries

    device = pick_device(getattr(cfg, "device", "auto"))
    folder = db_folder(cache_dir, cfg.map_path, cfg.zoom, cfg.overlap, cfg.tile_m)
    db, built = _build(cfg, folder, device, progress)
    priors = getattr(cfg, "priors", "auto")
    queries = load_queries(cfg.queries_path, priors=priors, seed=getattr(cfg, "seed", 0))
    queries = sample_queries(queries, getattr(cfg, "max_queries", None))
    options = localize_options(cfg)
    out_csv = _results_csv(cfg, folder, queries, options)
    matches_dir = out_csv.with_name(f"{out_csv.stem}-matches") if cfg.reranker else None
    stamp = out_csv.stat().st_mtime_ns if out_csv.is_file() else None
    results = localize_queries(db, queries, out_csv, options, device, save_matches=matches_dir, progress=progress)
    peak = _localize_peak_rss(out_csv, reused=stamp == out_csv.stat().st_mtime_ns)
    metrics = score(results, queries, db.tiles, tuple(cfg.thresholds_m), db.info["map"].get("resolution_m"))
    per_query = {p["name"]: p for p in metrics.pop("per_query")}
    return {
        "metrics": metrics,
        "rows": _query_rows(results, queries, per_query, matches_dir),
        "timing": {**_timing(results), **built["timing"]},
        "memory": {**built["memory"], "peak_rss_mb": peak},
        "n_tiles": len(db.tiles),
        "n_queries": len(queries),
        "db": str(folder),
        "results_csv": str(out_csv),
    }


def localize_options(cfg):
    """The localize options of a benchmark configuration: the heading and ground-resolution priors of its query
    set apply to re-rankers only (retrieval-only configurations keep their plain runs)."""
    from aeroloc.localization.options import LocalizeOptions

    rerank = bool(cfg.reranker)
    return LocalizeOptions(
        top_n=cfg.top_n,
        top_k=cfg.top_k,
        method=cfg.method,
        rerank=cfg.reranker,
        north_up=bool(getattr(cfg, "north_up", False)) and rerank,
        query_gsd=getattr(cfg, "query_gsd", None) if rerank else None,
    )


def _build(cfg, folder: Path, device, progress: bool):
    """The configuration's tile set, descriptors + index and local features (each cached by its own key), with
    what they cost."""
    from aeroloc.maps.tiling import write_tiles
    from aeroloc.matching.features import build_local
    from aeroloc.retrieval.database import Database, build_global

    t0 = time.perf_counter()
    tinfo = write_tiles(cfg.map_path, folder, cfg.zoom, cfg.overlap, cfg.tile_m, progress=progress)
    t_tiles = time.perf_counter() - t0
    db = Database(folder)
    grep = build_global(db, cfg.method, device=device, progress=progress, turns=getattr(cfg, "global_turns", False))
    if cfg.reranker:  # the cascade checks fixes on repeated ground at both places
        from aeroloc.retrieval.echoes import build_echoes

        build_echoes(db, cfg.method)
    turns = getattr(cfg, "local_turns", False)
    lrep = build_local(db, cfg.reranker, device, progress=progress, turns=turns) if cfg.reranker else None
    timing = {"tiles_s": t_tiles, "build_descriptors_s": grep.extract_s, "fit_s": grep.fit_s}
    memory = {
        "descriptor_bytes_per_tile": grep.bytes_per_tile,
        "local_bytes_per_tile": lrep.bytes_per_tile if lrep else 0.0,
        "index_bytes": grep.index_bytes,
        "tile_image_bytes": tinfo.image_bytes,
    }
    return db, {"timing": timing, "memory": memory}


def _results_csv(cfg, folder: Path, queries, options) -> Path:
    from aeroloc.core.io import config_key

    key = config_key(
        cfg.method,
        cfg.reranker,
        cfg.top_n,
        cfg.top_k,
        [q.name for q in queries],
        str(Path(cfg.queries_path).resolve()),
        *([{"north_up": True}] if options.north_up else []),
        *([{"query_gsd": float(options.query_gsd)}] if options.query_gsd is not None else []),
        *([{"priors": cfg.priors, "seed": cfg.seed}] if getattr(cfg, "priors", "auto") != "auto" else []),
    )
    return folder / "results" / f"{cfg.method}-{cfg.reranker or 'none'}-n{cfg.top_n}-k{cfg.top_k}-{key}.csv"


def score(results, queries, tiles, thresholds, map_gsd: float | None = None) -> dict:
    """The metrics of ``results``, with the retrieval stage's own VPR recall (before re-ranking, from the
    retrieved lists) as ``retrieval_vpr_recall@N``, and, given the map's resolution, the scale-aware pair of the
    any-terrain benchmark (aeroloc.bench.metrics.scaled_recall)."""
    from aeroloc.bench.metrics import evaluate, scaled_recall
    from aeroloc.localization.results import Localization

    metrics = evaluate(results, queries, tiles, thresholds)
    if map_gsd:
        metrics.update(scaled_recall(metrics["per_query"], map_gsd))
    before = evaluate([Localization(r.name, top_tiles=r.retrieved) for r in results], queries, tiles, thresholds)
    metrics.update({f"retrieval_{k}": v for k, v in before.items() if k.startswith("vpr_recall@")})
    return metrics


def _query_rows(results, queries, per_query: dict, matches_dir) -> list[dict]:
    truth = {q.name: q for q in queries}
    rows = []
    for r in results:
        q, p = truth[r.name], per_query.get(r.name, {})
        rows.append(
            {
                "name": r.name,
                "true_lat": q.lat,
                "true_lon": q.lon,
                "est_lat": r.lat if r.localized else None,
                "est_lon": r.lon if r.localized else None,
                "error_m": p.get("error_m"),
                "status": r.status,
                "inliers": r.inliers,
                "top_tiles": ";".join(r.top_tiles),
                "vpr_rank": p.get("vpr_rank"),
                "match_image": _match_image(matches_dir, r.name),
            }
        )
    return rows


def _timing(results) -> dict:
    """ms per query and stage, from the per-query times, not this call's clock: a resumed or reused results file
    took less of it."""
    n = max(1, len(results))
    timing = {f"{s}_ms": sum(r.times_ms.get(s, 0.0) for r in results) / n for s in STAGES}
    total_ms = sum(r.total_ms for r in results)
    median = float(np.median([r.total_ms for r in results])) if results else 0.0
    timing.update(total_ms_per_query=total_ms / n, median_ms_per_query=median, localize_total_s=total_ms / 1000)
    return timing
