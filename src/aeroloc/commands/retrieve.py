"""Top-N tiles per query by global descriptor; writes name,lat,lon (best tile centre),top_tiles."""

from __future__ import annotations

from aeroloc.commands.build import add_trust_argument, trust_from_args
from aeroloc.core.io import write_csv_atomic


def add_arguments(p):
    p.add_argument("db", help="database folder built by 'aeroloc build'")
    p.add_argument("queries", help="queries.csv / queries.txt / folder of photos")
    p.add_argument("--top-n", type=int, default=10)
    p.add_argument("--method", help="method to use if the database holds several (default: last built)")
    p.add_argument(
        "--rotations",
        type=int,
        default=1,
        metavar="K",
        help="search the query at K headings (360/K steps) and keep each tile's best score; for queries "
        "of unknown heading (default %(default)s: upright only; 4 or 8 cost K descriptors)",
    )
    p.add_argument(
        "--north-up",
        action="store_true",
        help="the queries are north-up: upright ranking only, even when the database holds turned descriptors "
        "(aeroloc build --global-turns; otherwise the best tiles by their best turn are interleaved at the front)",
    )
    p.add_argument("--out", required=True, help="results CSV")
    p.add_argument("--device", default="auto")
    add_trust_argument(p)


def run(args) -> int:
    from tqdm import tqdm

    from aeroloc.core.canvas import photo_view
    from aeroloc.core.device import pick_device
    from aeroloc.core.errors import AerolocError
    from aeroloc.core.images import read_image
    from aeroloc.core.queries import load_queries
    from aeroloc.retrieval.database import Database
    from aeroloc.retrieval.retriever import Retriever

    if args.top_n < 1:
        raise AerolocError(f"--top-n must be >= 1, got {args.top_n}")
    if args.rotations < 1:  # before any work: the database and queries are not read
        raise AerolocError(f"--rotations must be >= 1 (1 = upright query only), got {args.rotations}")
    if args.north_up and args.rotations != 1:  # as aeroloc localize refuses them
        raise AerolocError(
            f"--north-up and --rotations > 1 contradict each other: north-up queries need no rotation search, but "
            f"rotations={args.rotations} was asked for"
        )
    trust_from_args(args)
    db = Database(args.db)
    queries = load_queries(args.queries)
    retriever = Retriever(db, args.method, pick_device(args.device), args.rotations)
    turned = not args.north_up and args.rotations == 1 and retriever.turned_index is not None
    rows, batch = [], []

    def flush():
        # queries are searched in batches: an exact scan of many tiles is shared by the whole batch
        if not batch:
            return
        for (q, desc, t_desc), r in zip(batch, retriever.rank([d for _, d, _ in batch], args.top_n)):
            if turned:  # heading unknown: with the turned tiles too, as aeroloc localize does
                r = retriever.fuse_turned(desc, r, args.top_n)
            r.times_ms["descriptor"] = t_desc
            rows.append(_row(db, q, r))
        batch.clear()

    for q in tqdm(queries, desc="retrieve", unit="query", leave=False):
        image = read_image(q.path)
        view = photo_view(image)  # a photo on a black canvas: described alone, as aeroloc localize sees it
        batch.append((q, *retriever.describe(image if view is None else view.image)))
        if len(batch) == SEARCH_BATCH:
            flush()
    flush()
    write_rows(args.out, rows)
    print(f"{len(rows)} queries -> {args.out}")
    return 0


SEARCH_BATCH = 256  # queries per Faiss search


def _row(db, q, r) -> dict:
    lat, lon = db.by_id[r.tile_ids[0]].centre_latlon
    return {
        "name": q.name,
        "lat": f"{lat:.8f}",
        "lon": f"{lon:.8f}",
        "top_tiles": ";".join(r.tile_ids),
        "scores": ";".join(f"{s:.4f}" for s in r.scores),
        "descriptor_ms": f"{r.times_ms['descriptor']:.1f}",
        "search_ms": f"{r.times_ms['search']:.3f}",
    }


def write_rows(path, rows: list[dict]) -> None:
    """Write a results CSV atomically."""
    fields = list(dict.fromkeys(k for r in rows for k in r)) or ["name", "lat", "lon", "top_tiles"]
    write_csv_atomic(path, fields, rows)
