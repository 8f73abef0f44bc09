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
    from aeroloc.core.device import pick_device
    from aeroloc.core.errors import AerolocError
    from aeroloc.matching.registry import DEFAULT_RERANKER

    data, out = Path(args.data), Path(args.out)
    if not data.is_dir():
        raise AerolocError(f"{data}: shared data folder not found (pass --data or set AEROLOC_DATA)")
    device = pick_device(args.device)
    rerank = args.rerank or DEFAULT_RERANKER
    lines = []
    for name, map_rel, q_rel, zoom, overlap, tile_m, north_up, query_gsd in DEMO_SETS:
        print(f"\n== {name} ==")
        db = _database(data / map_rel, out / Path(map_rel).parent.name, zoom, overlap, tile_m, rerank, device)
        options = _options(args, rerank, north_up, query_gsd)
        line = _localize_set(name, db, data / q_rel, out, options, device, args.limit)
        lines.append(line)
    print("\n== summary ==\n" + "\n".join(lines))
    return 0


def _options(args, rerank: str, north_up: bool, query_gsd: float | None):
    from aeroloc.localization.options import LocalizeOptions
    from aeroloc.retrieval.models import DEFAULT_METHOD

    return LocalizeOptions(
        top_n=args.top_n, top_k=1, method=DEFAULT_METHOD, rerank=rerank, north_up=north_up, query_gsd=query_gsd
    )


def _database(map_path: Path, db_dir: Path, zoom, overlap, tile_m, rerank: str, device):
    """The set's tiles, descriptors and local features (cached in ``db_dir``)."""
    from aeroloc.commands.tiles import summary
    from aeroloc.maps.tiling import write_tiles
    from aeroloc.matching.features import build_local
    from aeroloc.retrieval.database import Database, build_global
    from aeroloc.retrieval.models import DEFAULT_METHOD

    t0 = time.perf_counter()
    info = write_tiles(map_path, db_dir, zoom, overlap, tile_m)
    print(summary(info, db_dir))
    db = Database(db_dir)
    g = build_global(db, DEFAULT_METHOD, device=device)
    build_local(db, rerank, device)
    print(f"database: {DEFAULT_METHOD} {g.dim}-d descriptors + {rerank} features in {time.perf_counter() - t0:.1f} s")
    return db


def _localize_set(name: str, db, queries_path: Path, out: Path, options, device, limit) -> str:
    """Localize and score one query set; returns its summary line."""
    from aeroloc.bench.pipeline import score
    from aeroloc.core.queries import load_queries
    from aeroloc.localization.run import localize_queries

    queries = load_queries(queries_path)[:limit]
    stem = db.folder.name
    csv_path, matches = out / f"{stem}-results.csv", out / f"{stem}-matches"
    t0 = time.perf_counter()
    results = localize_queries(db, queries, csv_path, options, device, save_matches=matches)
    dt = time.perf_counter() - t0
    m = score(results, queries, db.tiles, (10, 25, 50, 100))
    ms = sum(r.total_ms for r in results) / max(1, len(results))
    med = "n/a" if m["median_error_m"] is None else f"{m['median_error_m']:.1f} m"
    line = (
        f"{name}: {len(results)} queries | VPR R@1 {m['retrieval_vpr_recall@1']:.2f} -> {m['vpr_recall@1']:.2f} "
        f"after re-ranking (R@10 {m.get('retrieval_vpr_recall@10', float('nan')):.2f}) | Georef R@10m "
        f"{m['georef_recall@10m']:.2f} R@25m {m['georef_recall@25m']:.2f} R@50m {m['georef_recall@50m']:.2f}"
        f" | median error {med} | not localized {m['not_localized']:.2f} | {ms / 1000:.2f} s/query"
    )
    print(line)
    print(f"results: {csv_path}  ({dt:.0f} s); match images: {matches}")
    return line
