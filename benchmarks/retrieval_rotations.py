"""Query-side rotation search (``Retriever(rotations=k)``) on NAIP: VPR Recall@1/5/10 for queries of any heading.

Builds (or reuses) a database of the NAIP map -- 1000 m tiles, overlap 0.5, the default method -- in ``--work``,
then retrieves the top-10 tiles of every query of ``dev-rotated`` (any heading) and ``dev`` (within ±15° of
north) with the query described at k headings, and scores them with ``aeroloc.bench.metrics.evaluate`` (a hit@N: the
true centre lies inside one of the top-N tiles). ``chance`` is the recall of N tiles drawn at random. With
``--pooled K`` the same table is made for the DenseVLAD option ``rotations: K`` (K rotations pooled into one
descriptor, tiles and queries alike), which needs its own descriptors (built once, cached in the database).

    python benchmarks/retrieval_rotations.py                       # rotations 1, 4, 8 (~2-4 min on 2 cores)
    python benchmarks/retrieval_rotations.py --pooled 4 --rotations 1 4
"""

from __future__ import annotations

import argparse
import sys
from math import comb
from pathlib import Path

import numpy as np
import torch

from aeroloc.bench.metrics import evaluate, tile_contains
from aeroloc.core.images import read_image
from aeroloc.core.queries import load_queries
from aeroloc.localization.results import Localization
from aeroloc.maps.tiling import write_tiles
from aeroloc.retrieval.database import Database, build_global
from aeroloc.retrieval.retriever import Retriever

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "naip-nd"
NS = (1, 5, 10)


def chance(tiles, queries) -> dict:
    """Recall@N of N tiles drawn at random (each query's centre lies in a few overlapping tiles)."""
    n = len(tiles)
    true = [sum(tile_contains(t, q.lat, q.lon) for t in tiles) for q in queries]
    return {k: float(np.mean([1 - comb(n - m, k) / comb(n, k) for m in true])) for k in NS}


def run_set(db: Database, retriever: Retriever, queries, images, k: int) -> dict:
    results, t_desc = [], []
    for q, im in zip(queries, images):
        r = retriever(im, max(NS), rotations=k)
        lat, lon = db.by_id[r.tile_ids[0]].centre_latlon
        results.append(Localization(q.name, lat, lon, top_tiles=list(r.tile_ids)))
        t_desc.append(r.times_ms["descriptor"])
    m = evaluate(results, queries, db.tiles, ns=NS)
    return {
        **{n: m[f"vpr_recall@{n}"] for n in NS},
        "ms": float(np.median(t_desc)),
        "per_query": {p["name"]: p["vpr_rank"] for p in m["per_query"]},
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default="out/bench-rotations", help="database folder (built once, then reused)")
    ap.add_argument("--data", default=str(DATA), help="the naip-nd folder")
    ap.add_argument("--method", default="effnet-vlad")
    ap.add_argument("--rotations", type=int, nargs="+", default=[1, 4, 8], help="query headings searched")
    ap.add_argument(
        "--pooled",
        type=int,
        nargs="*",
        default=[],
        help="also DenseVLAD conf rotations=K (pooled into one descriptor, tiles and queries)",
    )
    ap.add_argument("--sets", nargs="+", default=["dev-rotated", "dev"])
    ap.add_argument("--per-query", action="store_true", help="print each query's rank of the first true tile")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (1: steadier times on a shared machine)")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)

    data = Path(args.data)
    write_tiles(data / "map_20200831.tif", args.work, zoom=1, overlap=0.5, tile_m=1000, progress=False)
    db = Database(args.work)
    sets = {}
    for name in args.sets:
        qs = load_queries(data / name / "queries.csv")
        sets[name] = (qs, [read_image(q.path) for q in qs])
    print(f"{args.method}, {len(db.tiles)} tiles of 1000 m, overlap 0.5; VPR recall (hit: true centre in a tile)")
    print("k: query headings searched; ms: median descriptor time per query (all k views), 1 torch thread")
    header = f"{'set':<12}{'method conf':<22}{'k':>3}" + "".join(f"{'R@' + str(n):>7}" for n in NS) + f"{'ms':>10}"
    print(header)
    print("-" * len(header))
    for name, (qs, _) in sets.items():
        c = chance(db.tiles, qs)
        print(f"{name:<12}{'(chance)':<22}{'':>3}" + "".join(f"{100 * c[n]:>7.1f}" for n in NS))
    for pooled in [None, *args.pooled]:
        conf = {"rotations": pooled} if pooled else None
        build_global(db, args.method, conf, progress=False)  # cached after the first run; sets the entry used
        retriever = Retriever(db, args.method, "cpu")
        label = f"pooled rot{pooled}" if pooled else "default"
        for name, (qs, ims) in sets.items():
            for k in args.rotations:
                r = run_set(db, retriever, qs, ims, k)
                print(
                    f"{name:<12}{label:<22}{k:>3}" + "".join(f"{100 * r[n]:>7.1f}" for n in NS) + f"{r['ms']:>10.1f}",
                    flush=True,
                )
                if args.per_query:
                    print("   ranks:", " ".join("-" if v is None else str(v) for v in r["per_query"].values()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
