"""The end-to-end demo on ../shared/data: NAIP cross-season satellite queries and Toledo drone photos are
localized against their maps (tiles -> XFeat-VLAD retrieval -> re-ranking -> homography -> lat/lon) and scored."""

from __future__ import annotations

import os
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[3]
# (name, map, queries, zoom, overlap, tile_m, north_up, query_gsd): the tile side should be close to the query
# footprint. NAIP queries are north-up within ±15° and cut at the map's 5 m/px (satellite imagery: both known from
# the image metadata), so they go through the dense stage first; the drone photos were taken at any heading and
# at a height the demo does not use.
DEMO_SETS = [
    (
        "naip-nd/dev (cross-season satellite)",
        "naip-nd/map_20200831.tif",
        "naip-nd/dev/queries.csv",
        1.0,
        0.5,
        None,
        True,
        5.0,
    ),
    ("toledo (DJI drone photos)", "toledo/orthomosaic.tif", "toledo/queries.csv", 1.0, 0.5, 200.0, False, None),
]


def add_arguments(p):
    p.add_argument(
        "--data",
        default=os.environ.get("AEROLOC_DATA", str(REPO.parent / "shared" / "data")),
        help="the shared data folder (default ../shared/data)",
    )
    p.add_argument("--out", default=str(REPO / "out" / "demo"), help="work folder (default out/demo)")
    p.add_argument("--rerank", default=None, help="re-ranker (default: the library default)")
    p.add_argument("--top-n", type=int, default=20)
    p.add_argument("--limit", type=int, help="only the first N queries of each set (quick look)")
    p.add_argument("--device", default="auto")


def run(args) -> int:
    from aeroloc.bench.metrics import evaluate, read_results
    from aeroloc.commands.tiles import summary
    from aeroloc.core.device import pick_device
    from aeroloc.core.errors import AerolocError
    from aeroloc.core.queries import load_queries
    from aeroloc.localization.localizer import localize_queries
    from aeroloc.maps.tiling import write_tiles
    from aeroloc.matching.features import build_local
    from aeroloc.matching.registry import DEFAULT_RERANKER
    from aeroloc.retrieval.database import Database, build_global
    from aeroloc.retrieval.models import DEFAULT_METHOD

    data, out = Path(args.data), Path(args.out)
    if not data.is_dir():
        raise AerolocError(f"{data}: shared data folder not found (pass --data or set AEROLOC_DATA)")
    device = pick_device(args.device)
    rerank = args.rerank or DEFAULT_RERANKER
    lines = []
    for name, map_rel, q_rel, zoom, overlap, tile_m, north_up, query_gsd in DEMO_SETS:
        print(f"\n== {name} ==")
        db_dir = out / Path(map_rel).parent.name
        t0 = time.perf_counter()
        tiles_report = write_tiles(data / map_rel, db_dir, zoom, overlap, tile_m)
        print(summary(tiles_report, db_dir))
        db = Database(db_dir)
        g = build_global(db, DEFAULT_METHOD, device=device)
        build_local(db, rerank, device)
        print(
            f"database: {DEFAULT_METHOD} {g.dim}-d descriptors + {rerank} features in {time.perf_counter() - t0:.1f} s"
        )
        queries = load_queries(data / q_rel)[: args.limit]
        csv_path = out / f"{db_dir.name}-results.csv"
        t0 = time.perf_counter()
        rows = localize_queries(
            db,
            queries,
            csv_path,
            args.top_n,
            1,
            DEFAULT_METHOD,
            rerank,
            device,
            save_matches=out / f"{db_dir.name}-matches",
            north_up=north_up,
            query_gsd=query_gsd,
        )
        dt = time.perf_counter() - t0
        m = evaluate(read_results(csv_path), queries, db.tiles, (10, 25, 50, 100))
        before = evaluate([_retrieved(r) for r in rows], queries, db.tiles, (10, 25, 50, 100))
        ms = sum(float(r["total_ms"]) for r in rows) / max(1, len(rows))
        med = "n/a" if m["median_error_m"] is None else f"{m['median_error_m']:.1f} m"
        line = (
            f"{name}: {len(rows)} queries | VPR R@1 {before['vpr_recall@1']:.2f} -> {m['vpr_recall@1']:.2f} "
            f"after re-ranking (R@10 {before.get('vpr_recall@10', float('nan')):.2f}) | Georef R@10m "
            f"{m['georef_recall@10m']:.2f} R@25m {m['georef_recall@25m']:.2f} R@50m {m['georef_recall@50m']:.2f}"
            f" | median error {med} | not localized {m['not_localized']:.2f} | {ms / 1000:.2f} s/query"
        )
        print(line)
        print(f"results: {csv_path}  ({dt:.0f} s); match images: {out / (db_dir.name + '-matches')}")
        lines.append(line)
    print("\n== summary ==\n" + "\n".join(lines))
    return 0


def _retrieved(row):
    from aeroloc.bench.metrics import Result

    return Result(row["name"], top_tiles=tuple(t for t in row["retrieved_tiles"].split(";") if t))
