"""Country-size maps (issue #15): prints the figures of tiles-as-windows, sharded in-process vs Ray builds, build
RAM, approximate-index recall and a 10^6-vector index. Not part of the test suite; bounded to minutes.

    nice .venv/bin/python benchmarks/scale.py [--only tiling|build|recall|million] [--no-ray] [--out /tmp/aeroloc-scale]

Builds run in child processes so each peak RSS (ru_maxrss) is its own. The build method is effnet-vlad on
small NAIP tiles (zoom 10 = 26 px, 130 m): a cheap way to get >= 2x10^4 real tiles from the 934x723 px map.
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
NAIP = DATA / "naip-nd" / "map_20200831.tif"
METHOD = "effnet-vlad"


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def aero_vloc_cut(seed: Path, zoom: float, overlap: float) -> int:
    """aero-vloc's way (reproduced): read each raw tile and cut numpy slices of it in memory."""
    from PIL import Image

    n = 0
    for p in sorted(seed.glob("tile_*.png")):
        img = np.asarray(Image.open(p).convert("RGB"))
        h, w = img.shape[:2]
        th, tw = round(h / zoom), round(w / zoom)
        sy, sx = max(1, round(th * (1 - overlap))), max(1, round(tw * (1 - overlap)))
        for y in range(0, h - th + 1, sy):
            for x in range(0, w - tw + 1, sx):
                _ = img[y : y + th, x : x + tw].copy()
                n += 1
    return n


def bench_tiling(work: Path) -> list[tuple]:
    """tiles/s of the window database, the PNG database and aero-vloc's cut on a seed-format map."""
    sys.path.insert(0, str(REPO / "tests"))
    from _mapfolders import build_seed_folder
    from aeroloc.maps.tilesource import TileSource
    from aeroloc.maps.tiling import write_tiles

    seed = build_seed_folder(work / "seed", NAIP, n_rows=2, n_cols=3, tile_w=1280, tile_h=1230, upsample=5).path
    rows = []
    for zoom, overlap in [(1.5, 0.5), (3, 0.75)]:
        t0 = time.perf_counter()
        n_av = aero_vloc_cut(seed, zoom, overlap)
        av = n_av / (time.perf_counter() - t0)
        shutil.rmtree(work / "win", ignore_errors=True)
        t0 = time.perf_counter()
        rep = write_tiles(seed, work / "win", zoom, overlap, progress=False)
        win = rep.n_tiles / (time.perf_counter() - t0)
        t0 = time.perf_counter()
        for _ in TileSource(work / "win").images(0, rep.n_tiles):
            pass
        read = rep.n_tiles / (time.perf_counter() - t0)
        shutil.rmtree(work / "png", ignore_errors=True)
        t0 = time.perf_counter()
        write_tiles(seed, work / "png", zoom, overlap, progress=False, write_images=True)
        png = rep.n_tiles / (time.perf_counter() - t0)
        rows.append((f"seed 3x2 x 1280x1230, zoom {zoom}, overlap {overlap}", rep.n_tiles, win, read, png, n_av, av))
    return rows


def child_build(out: Path, zoom: float, overlap: float, ray: str | None, workers: int) -> None:
    """One build in this (child) process; prints a JSON line with tiles, seconds and peak RSS."""
    from aeroloc.maps.tiling import write_tiles
    from aeroloc.retrieval.database import Database, build_global

    write_tiles(NAIP, out, zoom, overlap, progress=False)
    db = Database(out)
    if ray:
        from aeroloc.retrieval.ray_build import connect

        connect(ray, num_cpus=workers)
    t0 = time.perf_counter()
    rep = build_global(db, METHOD, progress=False, ray=ray, workers=workers, fit_max_tiles=500)
    total = time.perf_counter() - t0
    print(
        json.dumps(
            {
                "n": rep.n_tiles,
                "extract_s": rep.extract_s,
                "fit_s": rep.fit_s,
                "index_s": rep.index_s,
                "total_s": total,
                "tps": rep.tiles_per_s,
                "rss_mb": _rss_mb(),
            }
        )
    )


def run_child(*args) -> dict:
    out = subprocess.run([sys.executable, __file__, "--child", *map(str, args)], capture_output=True, text=True)
    if out.returncode:
        raise SystemExit(out.stderr[-2000:])
    return json.loads(out.stdout.strip().splitlines()[-1])


def bench_builds(work: Path, with_ray: bool = True) -> dict:
    """In-process (1e4 and 2e4 tiles) and Ray local 2 workers (2e4): throughput and peak RSS."""
    res = {}
    runs = [("1e4 in-process", 10, 0.72, ""), ("2e4 in-process", 10, 0.8, ""), ("2e4 ray 2 workers", 10, 0.8, "local")]
    for name, zoom, overlap, ray in runs[: 3 if with_ray else 2]:
        folder = work / f"build-{name.replace(' ', '-')}"
        shutil.rmtree(folder, ignore_errors=True)
        res[name] = run_child(folder, zoom, overlap, ray, 2)
        print(name, res[name], flush=True)
    return res


# real sets for the recall figures: (name, map, tile_m, overlap, query folders)
RECALL_SETS = [
    ("naip-nd 150 m", NAIP, 150, 5 / 6, [DATA / "naip-nd" / "dev"]),
    ("levir-tx 32 m", DATA / "multi-region" / "levir-tx" / "map.tif", 32, 0.5, ["north", "any"]),
    ("szada-hu 96 m", DATA / "multi-region" / "szada-hu" / "map.tif", 96, 0.5, ["north", "any"]),
]


def recall_factories(n: int) -> list[tuple[str, dict]]:
    """(factory, search parameters) compared with exact Flat: auto's large-map shape (PCA256, IVF, SQ8), PCA to
    more dimensions, IVF without PCA at growing nprobe, 8-bit codes scanned in full, and a graph (HNSW)."""
    nlist = int(2 ** round(np.log2(4 * np.sqrt(n))))
    out = [(f"PCA256,IVF{nlist},SQ8", {"nprobe": 32}), (f"PCA1024,IVF{nlist},SQ8", {"nprobe": 32})]
    out += [(f"IVF{nlist},SQ8", {"nprobe": p}) for p in (32, 128)]
    return out + [("SQ8", {}), ("HNSW32,SQ8", {"efSearch": 64}), ("HNSW32,SQ8", {"efSearch": 256})]


def _set_params(index, params: dict) -> None:
    """Search breadth of a loaded index (the same IVF or HNSW index is measured at several)."""
    import faiss

    if "nprobe" in params:
        faiss.extract_index_ivf(index).nprobe = params["nprobe"]
    if "efSearch" in params:
        faiss.downcast_index(index).hnsw.efSearch = params["efSearch"]


def _set_queries(db, model, folders) -> np.ndarray:
    """Descriptors of the set's real query images (resized to the tile side, as the tiles are seen)."""
    import cv2

    from aeroloc.core.images import read_image
    from aeroloc.core.queries import load_queries
    from aeroloc.retrieval.global_shards import describe

    side = db.tiles[0].width
    paths = [x.path for f in folders for x in load_queries(Path(f) / "queries.csv")]
    return describe(model, [cv2.resize(read_image(p), (side, side), interpolation=cv2.INTER_AREA) for p in paths], 16)


def _recall(got: np.ndarray, want: np.ndarray) -> tuple[float, float]:
    """(recall@1, recall@10): the exact top-1 found first; the share of the exact top-10 in the returned 10."""
    return float(np.mean(got[:, 0] == want[:, 0])), float(
        np.mean([len(set(a) & set(b)) / 10 for a, b in zip(got, want)])
    )


def bench_recall_set(work: Path, name: str, map_path: Path, tile_m: float, overlap: float, folders) -> list[dict]:
    """Build the set's real descriptors (exact index), then each factory from the same store: training+fill
    seconds, ms/query and recall@1/@10 of the exact top-10, for the real queries and for 300 tiles as queries."""
    from aeroloc.maps.tiling import write_tiles
    from aeroloc.retrieval.database import Database, build_global
    from aeroloc.retrieval.index import build_index_from_store, load_index, search

    folder = work / f"recall-{name.split()[0]}"
    folders = [f if isinstance(f, Path) else map_path.parent / f for f in folders]
    write_tiles(map_path, folder, 1.0, overlap, tile_m=tile_m, progress=False)
    db = Database(folder)
    build_global(db, METHOD, progress=False, fit_max_tiles=500, index_factory="Flat")
    model, store, exact, _ = db.load_method(METHOD)
    tiles_q = np.asarray(store.load()[np.random.default_rng(2).choice(store.n, 300, replace=False)], np.float32)
    queries = {"queries": _set_queries(db, model, folders).astype(np.float32), "tiles": tiles_q}
    want = {k: search(exact, q, 10)[1] for k, q in queries.items()}
    rows, built, build_s = [], None, 0.0
    for factory, params in recall_factories(store.n):
        path = work / "recall.faiss"
        if factory != built:  # the same index searched with other parameters is built once
            t0 = time.perf_counter()
            build_index_from_store(store.path, path, factory)
            built, build_s = factory, time.perf_counter() - t0
        index = load_index(path)
        _set_params(index, params)
        row = {"set": name, "n": store.n, "factory": factory, **params, "build_s": round(build_s, 1)}
        for k, q in queries.items():
            t0 = time.perf_counter()
            got = np.concatenate([search(index, q[i : i + 1], 10)[1] for i in range(len(q))])
            row[f"{k} ms"] = round((time.perf_counter() - t0) * 1000 / len(q), 2)
            row[f"{k} r@1"], row[f"{k} r@10"] = _recall(got, want[k])
        row["n queries"] = len(queries["queries"])
        print(json.dumps(row), flush=True)
        rows.append(row)
        del index
    for f in work.glob("recall.faiss*"):
        f.unlink()
    return rows


def bench_recall(work: Path) -> list[dict]:
    """Neighbour recall of approximate factories vs exact on every real set (see bench_recall_set)."""
    return [r for s in RECALL_SETS for r in bench_recall_set(work, *s)]


def child_million(npy: Path, index: Path) -> None:
    """Search the memory-mapped 1e6 index: ms/query one at a time, recall@10 vs exact, peak RSS."""
    from aeroloc.retrieval.index import load_index, search

    base = _rss_mb()
    idx = load_index(index)
    mm = np.load(npy, mmap_mode="r")
    rng = np.random.default_rng(5)
    q = np.asarray(mm[rng.choice(len(mm), 200, replace=False)], np.float32) + rng.normal(0, 0.02, (200, mm.shape[1]))
    q = (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)
    search(idx, q[:5], 10)
    t0 = time.perf_counter()
    got = np.concatenate([search(idx, q[i : i + 1], 10)[1] for i in range(len(q))])
    ms = (time.perf_counter() - t0) * 1000 / len(q)
    rss = _rss_mb()
    best = np.full((len(q), 10), -1)
    scores = np.full((len(q), 10), -np.inf)
    for s in range(0, len(mm), 100_000):  # exact top-10 in chunks (after the RSS reading)
        sc = q @ np.asarray(mm[s : s + 100_000], np.float32).T
        allsc = np.concatenate([scores, sc], 1)
        allid = np.concatenate([best, np.arange(s, s + sc.shape[1])[None].repeat(len(q), 0)], 1)
        top = np.argsort(-allsc, 1)[:, :10]
        scores, best = np.take_along_axis(allsc, top, 1), np.take_along_axis(allid, top, 1)
    r10 = float(np.mean([len(set(a) & set(b)) / 10 for a, b in zip(got, best)]))
    print(json.dumps({"ms_per_query": ms, "rss_mb": rss, "rss_before_mb": base, "r@10": r10, "ntotal": idx.ntotal}))


def bench_million(work: Path, n: int = 1_000_000) -> dict:
    """10^6 vectors: the 2e4 real descriptors PCA-reduced to 256-d, repeated with noise; IVF4096,SQ8 on disk."""
    from aeroloc.retrieval.index import build_index_from_store
    from aeroloc.retrieval.store import DescriptorStore

    gdir = next((work / "build-2e4-in-process" / "global").iterdir())
    real = DescriptorStore.open_complete(gdir).load(mmap=False).astype(np.float32)
    sample = real[np.random.default_rng(1).choice(len(real), 3000, replace=False)]
    mean = sample.mean(0)
    w, v = np.linalg.eigh((sample - mean) @ (sample - mean).T)  # PCA through the 3000 x 3000 Gram matrix
    axes = ((sample - mean).T @ v[:, -256:]) / np.sqrt(np.maximum(w[-256:], 1e-12))
    small = (real - mean) @ axes
    small /= np.linalg.norm(small, axis=1, keepdims=True)
    npy = work / "million.npy"
    rng = np.random.default_rng(0)
    mm = np.lib.format.open_memmap(npy, "w+", np.float16, (n, 256))
    for s in range(0, n, 50_000):
        x = small[rng.integers(0, len(small), 50_000)] + rng.normal(0, 0.05, (50_000, 256)).astype(np.float32)
        mm[s : s + 50_000] = (x / np.linalg.norm(x, axis=1, keepdims=True))[: n - s]
    mm.flush()
    del mm
    t0 = time.perf_counter()
    factory = build_index_from_store(npy, work / "million.faiss", "auto", nprobe=32)
    build_s = time.perf_counter() - t0
    out = subprocess.run(
        [sys.executable, __file__, "--child-million", str(npy), str(work / "million.faiss")],
        capture_output=True,
        text=True,
    )
    if out.returncode:
        raise SystemExit(out.stderr[-2000:])
    return {"factory": factory, "build_s": build_s, **json.loads(out.stdout.strip().splitlines()[-1])}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="/tmp/aeroloc-scale")
    ap.add_argument("--child", nargs=5)
    ap.add_argument("--child-million", nargs=2)
    ap.add_argument("--only", choices=["tiling", "build", "recall", "million"])
    ap.add_argument("--no-ray", action="store_true", help="builds: in-process only (the RSS figures)")
    a = ap.parse_args()
    if a.child:
        out, zoom, overlap, ray, workers = a.child
        return child_build(Path(out), float(zoom), float(overlap), ray or None, int(workers))
    if a.child_million:
        return child_million(Path(a.child_million[0]), Path(a.child_million[1]))
    work = Path(a.out)
    work.mkdir(parents=True, exist_ok=True)
    if a.only in (None, "tiling"):
        print(
            "| map, grid | tiles | windows db tiles/s | window reads tiles/s | PNG db tiles/s | aero-vloc tiles | aero-vloc tiles/s |"
        )
        for r in bench_tiling(work):
            print(f"| {r[0]} | {r[1]} | {r[2]:.0f} | {r[3]:.0f} | {r[4]:.1f} | {r[5]} | {r[6]:.0f} |", flush=True)
    if a.only in (None, "build"):
        print(json.dumps(bench_builds(work, not a.no_ray), indent=1), flush=True)
    if a.only in (None, "recall"):
        print(json.dumps(bench_recall(work)), flush=True)
    if a.only in (None, "million"):
        print(json.dumps(bench_million(work)), flush=True)


if __name__ == "__main__":
    main()
