"""Retrieve, re-rank by verified inliers and align: latitude/longitude per query, with per-stage times."""

from __future__ import annotations

from aeroloc.commands.build import add_trust_argument, trust_from_args

# --refine-window: an accepted match whose query reaches 15 % of a tile side beyond the tile is re-matched on the map
# (NAIP dev, 1280 m tiles: 57 windows for 120 queries; Georef@10 m 0.82 -> 0.85, median error 4.7 -> 3.9 m)
REFINE_OUTSIDE = 0.15


def add_arguments(p):
    from aeroloc.matching.registry import DEFAULT_RERANKER, RERANKERS

    p.add_argument("db", help="database folder built by 'aeroloc build'")
    p.add_argument("queries", help="queries.csv / queries.txt / folder of photos with EXIF GPS")
    p.add_argument("--top-n", type=int, default=20, help="candidates retrieved (default %(default)s)")
    p.add_argument(
        "--rerank",
        default=DEFAULT_RERANKER,
        help=f"re-ranker: {', '.join(sorted(RERANKERS))} or none (default %(default)s)",
    )
    p.add_argument("--top-k", type=int, default=1, help="tiles kept after re-ranking (default %(default)s)")
    p.add_argument("--method", help="retrieval method if the database holds several")
    p.add_argument(
        "--rotations",
        type=int,
        default=1,
        metavar="K",
        help="retrieve with the query at K headings (360/K steps), for queries of unknown heading "
        "(default %(default)s: upright only)",
    )
    p.add_argument(
        "--north-up",
        action="store_true",
        help="queries are north-up within about ±45° (compass/gimbal yaw, satellite imagery): skip the "
        "re-ranker's 90° rotation search",
    )
    p.add_argument(
        "--refine-window",
        action="store_true",
        help="re-match queries that reach beyond their best tile against the map window they cover: "
        "more inliers and metres of accuracy, ~0.3 s more for those queries",
    )
    p.add_argument(
        "--query-gsd",
        type=float,
        metavar="M",
        help="ground size of a query pixel in metres (satellite metadata, or height over ground x pixel "
        "angle): first match the query's structure densely over the map (aeroloc.matching.dense), at "
        "headings within ±15° of north with --north-up (~0.25 s per query), else at every heading "
        "(~2 s); local features only when that finds no distinct match",
    )
    p.add_argument(
        "--no-sweep",
        action="store_true",
        help="don't sweep the whole map at every heading and scale (aeroloc.localization.sweep_stage); by default "
        "queries with a heading or ground-resolution prior are swept first, the others when the quarter-turn "
        "re-ranking finds nothing",
    )
    p.add_argument(
        "--no-neighbours",
        action="store_true",
        help="don't re-rank the tiles beside the first 3 retrieved ones when no retrieved tile placed a query "
        "without priors (aeroloc.localization.neighbours; before the sweep)",
    )
    p.add_argument(
        "--no-structure-refine",
        action="store_true",
        help="don't refine local-feature fixes by the dense structure at their own heading and scale "
        "(aeroloc.localization.structure_refine; it moves a fix by at most max(25 m, 10 map px))",
    )
    p.add_argument(
        "--min-confidence",
        type=float,
        default=0.5,
        metavar="P",
        help="calibrated probability (within max(5 m, 2 map px)) a fix needs, else 'not localized' "
        "(default %(default)s; aeroloc.localization.confidence)",
    )
    from aeroloc.commands.priors_args import add_prior_arguments

    add_prior_arguments(p)
    p.add_argument("--out", required=True, help="results CSV")
    p.add_argument("--save-matches", metavar="DIR", help="write match visualisations here")
    p.add_argument("--device", default="auto")
    add_trust_argument(p)


def options_from_args(args):
    """The validated localize options the command line asks for (every check in LocalizeOptions)."""
    from aeroloc.localization.options import LocalizeOptions

    rerank = None if args.rerank in ("none", "") else args.rerank
    return LocalizeOptions(
        top_n=args.top_n,
        top_k=args.top_k,
        method=args.method,
        rerank=rerank,
        rerank_overrides={"refine_outside": REFINE_OUTSIDE} if args.refine_window and rerank else None,
        rotations=args.rotations,
        north_up=args.north_up,
        query_gsd=args.query_gsd,
        sweep=not args.no_sweep,
        neighbours=not args.no_neighbours,
        structure_refine=not args.no_structure_refine,
        min_confidence=args.min_confidence,
    )


def priors_line(queries, options) -> str:
    """What the run knows of the queries' ground resolution and heading: their own priors, and the options that
    stand in for them (``--query-gsd`` is the dense stage's default, not a per-query prior: without it here the
    line said "no ground resolution" for a run given one)."""
    from aeroloc.core.priors import describe_priors

    line = describe_priors(queries)
    if options.query_gsd is not None:
        line += f"; --query-gsd {options.query_gsd:g} m for queries without their own"
    if options.north_up:
        line += "; --north-up for queries without their own heading"
    return line


def run(args) -> int:
    from aeroloc.commands.priors_args import priors_from_args
    from aeroloc.core.device import pick_device
    from aeroloc.core.errors import AerolocError
    from aeroloc.core.priors import apply_overrides
    from aeroloc.core.queries import load_queries
    from aeroloc.localization.run import localize_queries
    from aeroloc.retrieval.database import Database

    if args.top_n < 1 or args.top_k < 1:
        raise AerolocError("--top-n and --top-k must be >= 1")
    if args.rotations < 1:
        raise AerolocError(f"--rotations must be >= 1 (1 = upright query only), got {args.rotations}")
    options = options_from_args(args)  # bad or contradicting options fail before the database and queries are read
    trust_from_args(args)
    overrides = priors_from_args(args)
    db = Database(args.db)
    queries = apply_overrides(load_queries(args.queries), overrides)
    print(priors_line(queries, options))
    results = localize_queries(db, queries, args.out, options, pick_device(args.device), save_matches=args.save_matches)
    n_loc = sum(r.localized for r in results)
    print(f"{n_loc}/{len(results)} queries localized -> {args.out}")
    return 0
