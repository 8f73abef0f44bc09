"""Build a retrieval database: tiles + global descriptors + Faiss index (+ local features for re-ranking)."""

from __future__ import annotations

from aeroloc.commands.tiles import add_map_grid_arguments, summary
from aeroloc.core.errors import AerolocError


def add_trust_argument(p) -> None:
    """``--trust-checkpoint PATH`` (repeatable), for the commands that load model weights."""
    p.add_argument(
        "--trust-checkpoint",
        action="append",
        default=[],
        metavar="PATH",
        help="load this checkpoint even though it holds pickled Python objects (which can run code: only for "
        "files from a source you trust); repeatable, or list them in $AEROLOC_TRUST_CHECKPOINTS",
    )


def trust_from_args(args) -> None:
    from aeroloc.core.weights import trust_checkpoints

    trust_checkpoints(getattr(args, "trust_checkpoint", None) or [])


def add_arguments(p):
    from aeroloc.retrieval.models import DEFAULT_METHOD

    add_map_grid_arguments(p)
    p.add_argument("--out", required=True, help="database folder")
    p.add_argument(
        "--method", default=DEFAULT_METHOD, help="retrieval method (default %(default)s; see 'aeroloc methods')"
    )
    p.add_argument("--weights", help="explicit weights file for the method")
    add_trust_argument(p)
    p.add_argument("--local", help="also precompute local features of this re-ranker (e.g. xfeat-lighterglue)")
    p.add_argument(
        "--local-turns",
        action="store_true",
        help="with --local: the tiles' local features at eight turns (45° steps) too, so a photo of unknown heading "
        "is extracted once instead of at up to eight turns (faster localization; x8 local-feature disk and build time)",
    )
    p.add_argument(
        "--global-turns",
        action="store_true",
        help="the tiles' global descriptors at eight turns (45° steps) too: a photo of unknown heading retrieves its "
        "place with one descriptor, the best tiles by their best turn interleaved at the front of its upright "
        "ranking (fewer screens a photo; x8 descriptors, their build time and the index)",
    )
    p.add_argument(
        "--index",
        default="auto",
        help="faiss factory string, optionally ending in ',Rerank<N>' (the N best candidates re-ranked exactly from "
        "the store), or aeroloc's prefix form PCA<D>,L2norm,Prefix<P>,<graph>,Refine<F>[,Rerank<N>] (a graph over "
        "the first P components, its F x k best re-scored with all D); default auto: Flat under 1e5 tiles, else "
        "PCA1024,L2norm,HNSW32,SQ8,Rerank400",
    )
    p.add_argument("--device", default="auto", help="auto, cpu, cuda, cuda:N, mps")
    p.add_argument("--batch-size", type=int, default=16)
    p.add_argument("--workers", type=int, help="Ray model actors (default: the cluster's CPUs)")
    p.add_argument(
        "--ray",
        nargs="?",
        const="local",
        metavar="ADDRESS",
        help="build the shards on a Ray cluster: HOST:PORT of 'ray start --head', auto, or nothing for a new "
        "local one (needs aeroloc[ray]); the result is identical to the build without it",
    )
    p.add_argument("--half", action="store_true", help="half precision on GPU")


def run(args) -> int:
    from aeroloc.core.device import pick_device
    from aeroloc.maps.tiling import write_tiles
    from aeroloc.matching.registry import rerank_conf
    from aeroloc.retrieval.database import Database, build_global
    from aeroloc.retrieval.models import method_class

    method_class(args.method)  # unknown names fail now, not after the tiles (or the descriptors) are built
    if args.local:
        rerank_conf(args.local)
    elif args.local_turns:
        raise AerolocError("--local-turns needs --local RERANKER (the turned tiles are that re-ranker's features)")
    trust_from_args(args)
    device = pick_device(args.device)
    if args.ray is not None:
        from aeroloc.retrieval.ray_build import connect

        connect(args.ray)  # an address that does not answer fails now, in seconds
    tiles_report = write_tiles(args.map, args.out, args.zoom, args.overlap, args.tile_m, write_images=args.write_images)
    print(summary(tiles_report, args.out))
    db = Database(args.out)
    rep = build_global(
        db,
        args.method,
        None,
        args.weights,
        device,
        args.batch_size,
        args.workers,
        args.index,
        args.half,
        ray=args.ray,
        turns=args.global_turns,
    )
    if rep.cached:
        print(f"descriptors {args.method}: cached ({rep.dim}-d, {rep.bytes_per_tile / 1024:.1f} KB/tile)")
    else:
        print(
            f"descriptors {args.method}: {rep.n_tiles} tiles, {rep.dim}-d, {rep.tiles_per_s:.1f} tiles/s, "
            f"fit {rep.fit_s:.1f} s, index {rep.index_s * 1000:.0f} ms, "
            f"{rep.bytes_per_tile / 1024:.1f} KB/tile"
        )
    if args.global_turns:
        print(f"turned descriptors {args.method}: {rep.turned_rows} ({len(db.tiles)} tiles x 7 turns)")
    from aeroloc.retrieval.echoes import build_echoes

    echoes = build_echoes(db, args.method)
    if echoes:
        far = max(echoes, key=lambda e: e.score)
        print(
            f"repeated ground: {len(echoes)} tiles show ground found again elsewhere on the map (e.g. {far.tile_id} "
            f"at {far.dx:+d}, {far.dy:+d} px, correlation {far.score:.2f}); fixes there are checked at both places"
        )
    if args.local:
        from aeroloc.matching.features import build_local

        lrep = build_local(db, args.local, device, ray=args.ray, workers=args.workers, turns=args.local_turns)
        print(
            f"local features {args.local}: {lrep.n_tiles} tiles, {lrep.bytes_per_tile / 1024:.1f} KB/tile"
            + (" (cached)" if lrep.cached else f", {lrep.tiles_per_s:.1f} tiles/s")
        )
    return 0
