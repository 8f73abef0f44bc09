"""Country-size maps (issue #15): prints the figures of tiles-as-windows, sharded in-process vs Ray builds, build
RAM, approximate-index recall and a 10^6-vector index. Not part of the test suite; bounded to minutes.

    nice .venv/bin/python benchmarks/scale.py [--tiles 20000] [--skip-build] [--out /tmp/aeroloc-scale]

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


def bench_builds(work: Path) -> dict:
    """In-process (1e4 and 2e4 tiles) and Ray local 2 workers (2e4): throughput and peak RSS."""
    res = {}
    for name, zoom, overlap, ray in [
        ("1e4 in-process", 10, 0.72, ""),
        ("2e4 in-process", 10, 0.8, ""),
        ("2e4 ray 2 workers", 10, 0.8, "local"),
    ]:
        folder = work / f"build-{name.replace(' ', '-')}"
        shutil.rmtree(folder, ignore_errors=True)
        res[name] = run_child(folder, zoom, overlap, ray, 2)
        print(name, res[name], flush=True)
    return res


def bench_recall(work: Path) -> dict:
    """Neighbour recall@1/10 of the auto large-map index (PCA256,IVF,SQ8) vs exact, on real tile descriptors,
    queried with the NAIP dev photos' descriptors."""
    from aeroloc.core.images import read_image
    from aeroloc.core.queries import load_queries
    from aeroloc.retrieval.database import Database
    from aeroloc.retrieval.descriptors import describe_image
    from aeroloc.retrieval.index import build_index_from_store, load_index, search

    folder = work / "build-2e4-in-process"
    db = Database(folder)
    model, store, exact, _ = db.load_method(METHOD)
    qs = load_queries(DATA / "naip-nd" / "dev" / "queries.csv")
    side = db.tiles[0].width
    import cv2

    q = np.concatenate([describe_image(model, cv2.resize(read_image(x.path), (side, side)), "cpu")[0] for x in qs])
    _, want = search(exact, q, 10)
    nlist = 256
    build_index_from_store(store.path, work / "approx.faiss", f"PCA256,IVF{nlist},SQ8", nprobe=32)
    _, got = search(load_index(work / "approx.faiss"), q, 10)
    return {
        "n": store.n,
        "queries": len(q),
        "factory": f"PCA256,IVF{nlist},SQ8 nprobe 32",
        "r@1": float(np.mean(got[:, 0] == want[:, 0])),
        "r@10": float(np.mean([len(set(a) & set(b)) / 10 for a, b in zip(got, want)])),
    }


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
        print(json.dumps(bench_builds(work), indent=1), flush=True)
    if a.only in (None, "recall"):
        print(json.dumps(bench_recall(work)), flush=True)
    if a.only in (None, "million"):
        print(json.dumps(bench_million(work)), flush=True)


if __name__ == "__main__":
    main()
