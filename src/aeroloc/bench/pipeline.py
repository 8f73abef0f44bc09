"""One configuration end to end, for benchmarks: tiles -> descriptors/index -> localize -> metrics, with the
same clock for every stage and the memory each part takes. Every stage is cached in ``cache_dir`` by its own
configuration key, so a sweep reuses tile sets, descriptor stores, feature stores and indexes."""

from __future__ import annotations

import resource
import time
from pathlib import Path

from aeroloc.localization.localizer import STAGES


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
    """``cfg`` has map_path, tile_m, queries_path, method, reranker (None = retrieval only), zoom, overlap,
    top_n, top_k, thresholds_m, device. Returns metrics, per-query rows, timing (ms/query per stage, totals)
    and memory (bytes per tile, index bytes, peak RSS)."""
    from aeroloc.bench.metrics import Result, evaluate, read_results
    from aeroloc.core.device import pick_device
    from aeroloc.core.io import config_key
    from aeroloc.core.queries import load_queries
    from aeroloc.localization.localizer import localize_queries
    from aeroloc.maps.tiling import write_tiles
    from aeroloc.matching.features import build_local
    from aeroloc.retrieval.database import Database, build_global

    device = pick_device(getattr(cfg, "device", "auto"))
    folder = db_folder(cache_dir, cfg.map_path, cfg.zoom, cfg.overlap, cfg.tile_m)
    t0 = time.perf_counter()
    tinfo = write_tiles(cfg.map_path, folder, cfg.zoom, cfg.overlap, cfg.tile_m, progress=progress)
    t_tiles = time.perf_counter() - t0
    db = Database(folder)
    grep = build_global(db, cfg.method, device=device, progress=progress)
    lrep = build_local(db, cfg.reranker, device, progress=progress) if cfg.reranker else None
    from aeroloc.bench.experiment import sample_queries

    queries = sample_queries(load_queries(cfg.queries_path), getattr(cfg, "max_queries", None))
    north_up = bool(getattr(cfg, "north_up", False))
    query_gsd = getattr(cfg, "query_gsd", None) if cfg.reranker else None
    key = config_key(
        cfg.method,
        cfg.reranker,
        cfg.top_n,
        cfg.top_k,
        [q.name for q in queries],
        str(Path(cfg.queries_path).resolve()),
        *([{"north_up": True}] if north_up else []),
        *([{"query_gsd": float(query_gsd)}] if query_gsd is not None else []),
    )
    stem = f"{cfg.method}-{cfg.reranker or 'none'}-n{cfg.top_n}-k{cfg.top_k}-{key}"
    out_csv = folder / "results" / f"{stem}.csv"
    matches_dir = folder / "results" / f"{stem}-matches" if cfg.reranker else None
    stamp = out_csv.stat().st_mtime_ns if out_csv.is_file() else None
    rows = localize_queries(
        db,
        queries,
        out_csv,
        cfg.top_n,
        cfg.top_k,
        cfg.method,
        cfg.reranker,
        device,
        save_matches=matches_dir,
        progress=progress,
        north_up=north_up and bool(cfg.reranker),
        query_gsd=query_gsd,
    )
    peak = _localize_peak_rss(out_csv, reused=stamp == out_csv.stat().st_mtime_ns)
    results = read_results(out_csv)
    metrics = evaluate(results, queries, db.tiles, tuple(cfg.thresholds_m))
    # recall of the retrieval stage alone (before re-ranking), from the retrieved lists
    retrieved = {r["name"]: tuple(t for t in r["retrieved_tiles"].split(";") if t) for r in rows}
    before = evaluate(
        [Result(r.name, top_tiles=retrieved.get(r.name, ())) for r in results],
        queries,
        db.tiles,
        tuple(cfg.thresholds_m),
    )
    metrics.update({f"retrieval_{k}": v for k, v in before.items() if k.startswith("vpr_recall@")})
    per_query = {p["name"]: p for p in metrics.pop("per_query")}
    truth = {q.name: q for q in queries}
    out_rows = []
    for r in rows:
        q, p = truth[r["name"]], per_query.get(r["name"], {})
        out_rows.append(
            {
                "name": r["name"],
                "true_lat": q.lat,
                "true_lon": q.lon,
                "est_lat": float(r["lat"]) if r["lat"] else None,
                "est_lon": float(r["lon"]) if r["lon"] else None,
                "error_m": p.get("error_m"),
                "status": r["status"],
                "inliers": int(r["inliers"]),
                "top_tiles": r["top_tiles"],
                "vpr_rank": p.get("vpr_rank"),
                "match_image": _match_image(matches_dir, r["name"]),
            }
        )
    n = max(1, len(rows))
    timing = {f"{s}_ms": sum(float(r[f"{s}_ms"]) for r in rows) / n for s in STAGES}
    total_ms = sum(float(r["total_ms"]) for r in rows)
    # from the per-query times, not this call's clock: a resumed or reused results file took less of it
    timing.update(
        total_ms_per_query=total_ms / n,
        localize_total_s=total_ms / 1000,
        tiles_s=t_tiles,
        build_descriptors_s=grep.extract_s,
        fit_s=grep.fit_s,
    )
    memory = {
        "descriptor_bytes_per_tile": grep.bytes_per_tile,
        "local_bytes_per_tile": lrep.bytes_per_tile if lrep else 0.0,
        "index_bytes": grep.index_bytes,
        "tile_image_bytes": tinfo.image_bytes,
        "peak_rss_mb": peak,
    }
    return {
        "metrics": metrics,
        "rows": out_rows,
        "timing": timing,
        "memory": memory,
        "n_tiles": len(db.tiles),
        "n_queries": len(queries),
        "db": str(folder),
        "results_csv": str(out_csv),
    }
