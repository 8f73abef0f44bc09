"""Country-size maps (issue #15): prints the figures of tiles-as-windows, sharded in-process vs Ray builds, build
RAM, approximate-index recall and a 10^6-vector index. Not part of the test suite; bounded to minutes.

    nice .venv/bin/python benchmarks/scale.py [--only tiling|build|recall|million] [--no-ray] [--out /tmp/aeroloc-scale]

Builds run in child processes so each peak RSS (ru_maxrss) is its own. The build method is effnet-vlad on
small NAIP tiles (zoom 10 = 26 px, 130 m): a cheap way to get >= 2x10^4 real tiles from the 934x723 px map.
"""

from __future__ import annotations

import argparse
import json
import os
import re
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


def _best_s(fn, repeat: int) -> float:
    """Seconds of the fastest of ``repeat`` calls of ``fn`` (the machine is shared: the least disturbed run)."""
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def bench_tiling(work: Path, repeat: int = 5) -> list[dict]:
    """tiles/s of the window database, the PNG database and aero-vloc's cut on a seed-format map, best of
    ``repeat`` runs each. The window database is timed three ways: the first call of the process (imports, the
    first coordinate transformation, the map's content hash), later calls on a map whose hash is not cached
    (``cold hash``: every raw file read and hashed), and on a map hashed before (``warm``: the cached hash)."""
    import os

    sys.path.insert(0, str(REPO / "tests"))
    os.environ["AEROLOC_CACHE"] = str(work / "cache")  # a private hash cache, emptied for the cold runs
    from _mapfolders import build_seed_folder
    from aeroloc.maps import windows
    from aeroloc.maps.tilesource import TileSource
    from aeroloc.maps.tiling import write_tiles

    seed = build_seed_folder(work / "seed", NAIP, n_rows=2, n_cols=3, tile_w=1280, tile_h=1230, upsample=5).path
    time.sleep(windows.HASH_CACHE_MIN_AGE_S + 0.1)  # files this new are never cached (racily clean)
    rows = []
    for k, (zoom, overlap) in enumerate([(1.5, 0.5), (3, 0.75)]):
        n_av = aero_vloc_cut(seed, zoom, overlap)
        av_s = _best_s(lambda z=zoom, o=overlap: aero_vloc_cut(seed, z, o), repeat)

        def windows_db(cold: bool, zoom=zoom, overlap=overlap):
            shutil.rmtree(work / "win", ignore_errors=True)
            if cold:
                shutil.rmtree(work / "cache", ignore_errors=True)
            return write_tiles(seed, work / "win", zoom, overlap, progress=False)

        first_s = _best_s(lambda: windows_db(True), 1) if k == 0 else None
        cold_s = _best_s(lambda: windows_db(True), repeat)
        windows_db(False)
        warm_s = _best_s(lambda: windows_db(False), repeat)
        rep = windows_db(False)
        t0 = time.perf_counter()
        for _ in TileSource(work / "win").images(0, rep.n_tiles):
            pass
        read = rep.n_tiles / (time.perf_counter() - t0)
        shutil.rmtree(work / "png", ignore_errors=True)
        t0 = time.perf_counter()
        write_tiles(seed, work / "png", zoom, overlap, progress=False, write_images=True)
        png = rep.n_tiles / (time.perf_counter() - t0)
        n = rep.n_tiles
        rows.append(
            {
                "grid": f"seed 3x2 x 1280x1230, zoom {zoom}, overlap {overlap}",
                "tiles": n,
                "aero-vloc tiles": n_av,
                "aero-vloc tiles/s": n_av / av_s,
                "first call ms": None if first_s is None else first_s * 1000,
                "cold hash ms": cold_s * 1000,
                "warm ms": warm_s * 1000,
                "cold hash x": (n / cold_s) / (n_av / av_s),
                "warm x": (n / warm_s) / (n_av / av_s),
                "first call x": None if first_s is None else (n / first_s) / (n_av / av_s),
                "window reads tiles/s": read,
                "PNG db tiles/s": png,
            }
        )
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


def recall_factories(n: int, which: str = "all") -> list[tuple[str, dict]]:
    """(factory, search parameters) compared with exact Flat. ``two-stage``: ``auto``'s large-map index (a PCA1024
    coarse HNSW over 8-bit codes, its candidates re-ranked exactly from the store) at 200-800 candidates, and
    with PCA512 / PCA256; ``one-stage``: PCA + IVF, IVF without PCA at growing nprobe, the SQ8 scan, HNSW32,SQ8."""
    from aeroloc.retrieval.index import COARSE

    two = [(f"{COARSE},Rerank400", {"candidates": r}) for r in (200, 400, 800)]
    two += [("PCA512,L2norm,HNSW32,SQ8,Rerank400", {"candidates": r}) for r in (100, 200, 400, 800)]
    two += [("PCA256,L2norm,HNSW32,SQ8,Rerank400", {"candidates": 400})]
    nlist = int(2 ** round(np.log2(4 * np.sqrt(n))))
    one = [(f"PCA256,IVF{nlist},SQ8", {"nprobe": 32}), (f"PCA1024,IVF{nlist},SQ8", {"nprobe": 32})]
    one += [(f"IVF{nlist},SQ8", {"nprobe": p}) for p in (32, 128)]
    one += [("SQ8", {}), ("HNSW32,SQ8", {"efSearch": 64}), ("HNSW32,SQ8", {"efSearch": 256})]
    # auto's index at other search breadths (efSearch) and candidates; ":f32": the query projected by faiss's
    # float32 transforms instead of the float16 PCA matrix
    ef = [(f"{COARSE},Rerank400", {"candidates": r, "efSearch": e}) for r, e in _EF_GRID]
    ef += [(f"{COARSE},Rerank400", {"candidates": 400, "efSearch": 400, "f32": True})]
    # three stages: the graph walks the first 256 (or 128) of the 1024 components, the full projection's 8-bit
    # codes re-score its Refine x R best, the store R
    three = [
        (f"PCA1024,L2norm,Prefix{p},HNSW32,SQ8,Refine{f},Rerank150", {"candidates": r})
        for p, f in ((256, 8), (256, 16), (512, 4), (512, 8))
        for r in (150, 200)
    ]
    # the graph over product-quantised codes (table look-ups instead of 1024-d decoding on its walk)
    pq = [(f"PCA1024,L2norm,HNSW32,PQ{m},Rerank400", {"candidates": r}) for m in (128, 256) for r in (200, 400)]
    groups = {"two-stage": two, "auto": two[:3], "ef": ef, "one-stage": one, "three-stage": three, "pq": pq}
    return {**groups, "all": two + three + one}[which]


# (candidates, efSearch) of the "ef" factories
_EF_GRID = [(100, 100), (100, 400), (200, 200), (200, 400), (200, 800), (300, 300), (300, 600), (400, 400)]
_EF_GRID += [(400, 800), (400, 1200), (600, 600), (800, 800)]


def _set_params(index, params: dict) -> None:
    """Search breadth of a loaded index (the same IVF or HNSW index is measured at several)."""
    import faiss

    if "candidates" in params:
        index.candidates = params["candidates"]
        index._projection = None if params.get("f32") else index._projection
    if "nprobe" in params:
        faiss.extract_index_ivf(index).nprobe = params["nprobe"]
    if "efSearch" in params and hasattr(index, "ef_search"):  # a two-stage index: its coarse graph
        index.ef_search = params["efSearch"]
    elif "efSearch" in params:
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


def bench_recall_set(
    work: Path, name: str, map_path: Path, tile_m: float, overlap: float, folders, which: str = "all"
) -> list[dict]:
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
    np.save(folder / "photo_queries.npy", queries["queries"])  # for bench_million
    for factory, params in recall_factories(store.n, which):
        path = folder / "global" / "recall.faiss"  # beside the store: a two-stage index re-ranks from it
        if factory != built:  # the same index searched with other parameters is built once
            t0 = time.perf_counter()
            build_index_from_store(store.path, path, factory)  # a two-stage index: re-ranks from the store
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
    for f in path.parent.glob("recall.faiss*"):
        f.unlink()
    return rows


def bench_recall(work: Path, which: str = "all", sets: str = "") -> list[dict]:
    """Neighbour recall of approximate factories vs exact on every real set (or those whose name starts with one
    of the comma-separated ``sets``; see bench_recall_set)."""
    pick = [s for s in RECALL_SETS if not sets or any(s[0].startswith(x) for x in sets.split(","))]
    return [r for s in pick for r in bench_recall_set(work, *s, which=which)]


def _proc_status_mb(key: str) -> float:
    """A memory figure of this process from /proc/self/status (VmHWM: the peak RSS of this program since its
    exec, unlike ru_maxrss, which keeps the peak of the process it was forked from)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _exact_top10(npy: Path, q: np.ndarray, chunk: int = 50_000) -> np.ndarray:
    """Exact top-10 ids of ``q`` over the float16 store, scanned in chunks (rows decoded exactly by
    :func:`~aeroloc.retrieval.index.as_float32`, scored by one matrix product each: what Flat computes)."""
    from aeroloc.retrieval.index import as_float32

    mm = np.load(npy, mmap_mode="r")
    best = np.full((len(q), 10), -1)
    scores = np.full((len(q), 10), -np.inf, np.float32)
    for s in range(0, len(mm), chunk):
        sc = q @ as_float32(mm[s : s + chunk]).T
        allsc = np.concatenate([scores, sc], 1)
        allid = np.concatenate([best, np.arange(s, s + sc.shape[1])[None].repeat(len(q), 0)], 1)
        top = np.argsort(-allsc, 1, kind="stable")[:, :10]
        scores, best = np.take_along_axis(allsc, top, 1), np.take_along_axis(allid, top, 1)
    return best


def _phases(idx, q: np.ndarray, r: int) -> dict:
    """Median CPU ms per query of each step of a two-stage search (one query at a time, one thread): the
    query's projection, the coarse graph walk for ``r`` candidates, reading their rows, scoring them."""
    import faiss

    faiss.omp_set_num_threads(1)
    proj, inner = idx._projection, idx._projection.inner
    exact = idx._scorer
    t = {"projection": [], "walk": [], "read": [], "score": []}
    for x in q:
        c0 = time.thread_time()
        y = proj(x)
        c1 = time.thread_time()
        c = np.unique(inner.search(y, r)[1][0])
        c2 = time.thread_time()
        nbytes = len(c) * idx.d * 2
        exact.codes.resize(nbytes)
        idx._read_into(c, memoryview(faiss.rev_swig_ptr(exact.codes.data(), nbytes)))
        exact.ntotal = len(c)
        c3 = time.thread_time()
        exact.search(x[None], 10)
        c4 = time.thread_time()
        for k, v in zip(t, (c1 - c0, c2 - c1, c3 - c2, c4 - c3)):
            t[k].append(v * 1000)
    return {f"{k} cpu ms": round(float(np.median(v)), 2) for k, v in t.items()}


def child_million(npy: Path, index: Path, queries: Path, candidates: str) -> None:
    """Search the 1e6 index one query at a time: ms/query with the store in the page cache, and after its pages
    were dropped from the cache (posix_fadvise DONTNEED on that file only: reads from disk), for each entry of
    ``candidates`` (``R`` or ``R/ef``: R candidates, the graph walked with efSearch ef; by default the built
    one; a ``:f32`` suffix projects the query with faiss's float32 transforms instead, ``:4k`` searches a second
    copy of the index left on 4 KB pages); the CPU of each step (:func:`_phases`); recall@10 vs exact (ids in ``queries`` + ``.exact.npy``);
    peak and current RSS of this program."""
    import torch

    from aeroloc.retrieval.index import RerankIndex, load_index, search

    torch.set_num_threads(1)  # one query, one thread: the int8 PCA product too (faiss's steps run on one)
    base, t0 = _proc_status_mb("VmRSS"), time.perf_counter()
    idx = huge = load_index(index)
    loaded, load_s = _proc_status_mb("VmRSS"), time.perf_counter() - t0
    q = np.load(queries).astype(np.float32)
    exact = np.load(str(queries).replace(".npy", ".exact.npy"))
    out = {"rss_start_mb": base, "rss_after_load_mb": loaded, "ntotal": idx.ntotal, "n_queries": len(q)}
    built_ef = idx.ef_search
    out["built efSearch"] = built_ef
    out["load s"], out["huge page MB"] = round(load_s, 2), round(idx.huge_page_bytes / 2**20, 1)
    small_pages = None
    for spec in candidates.split(","):
        spec, f32 = spec.removesuffix(":f32"), spec.endswith(":f32")
        spec, four_k = spec.removesuffix(":4k"), spec.endswith(":4k")
        if four_k and small_pages is None:  # ":4k": the same index loaded again, left on 4 KB pages
            small_pages = RerankIndex.open(index, huge_pages=False)
        idx = small_pages if four_k else huge
        projection = idx._projection
        r, ef = (int(v) for v in spec.split("/")) if "/" in spec else (int(spec), built_ef)
        idx.candidates, name = r, (f"R{r}" if ef == built_ef else f"R{r}/ef{ef}") + (" f32 PCA" if f32 else "")
        name += " 4K pages" if four_k else ""
        if ef is not None:
            idx.ef_search = ef
        idx._projection = None if f32 else projection  # ":f32": the query through faiss's float32 transforms
        for i in range(len(q)):  # every query once first: "warm" means every row it reads is in the page cache
            search(idx, q[i : i + 1], 10)
        for cache in ("warm", "cold"):
            if cache == "cold":
                fd = os.open(npy, os.O_RDONLY)
                os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
                os.close(fd)
            got, wall, cpu = [], [], []
            for i in range(len(q)):
                t0, c0 = time.perf_counter(), time.process_time()
                got.append(search(idx, q[i : i + 1], 10)[1])
                wall.append((time.perf_counter() - t0) * 1000)
                cpu.append((time.process_time() - c0) * 1000)
            got = np.concatenate(got)
            # mean and median per query; CPU time: what a query costs when it has a core (the wall time waits
            # for one on a busy machine, and for the disk when a row is not in the page cache)
            out[f"{name} {cache} ms/query"] = round(float(np.mean(wall)), 2)
            out[f"{name} {cache} cpu ms/query"] = round(float(np.mean(cpu)), 2)
            out[f"{name} {cache} median ms / cpu ms"] = [round(float(np.median(v)), 2) for v in (wall, cpu)]
        out[f"{name} r@1"], out[f"{name} r@10"] = _recall(got, exact)
        if idx._projection is not None:
            out[f"{name} phases (warm)"] = _phases(idx, q, r)
        idx._projection = projection
        out[f"{name} load"] = round(os.getloadavg()[0], 1)
    out["rss_peak_mb"], out["rss_end_mb"] = _proc_status_mb("VmHWM"), _proc_status_mb("VmRSS")
    out["rss_file_end_mb"] = _proc_status_mb("RssFile")
    print(json.dumps(out))


def bench_million(
    work: Path,
    n: int = 1_000_000,
    noise: float = 0.3,
    candidates: str = "200,400,800",
    factory: str = "auto",
    reuse: bool = False,
) -> dict:
    """10^6 real 8192-d descriptors: the tiles of the three real sets (from ``--only recall``), repeated with
    noise (each copy: a real row + Gaussian noise of norm ``noise``, renormalised) into a float16 store of
    16 GB; ``auto``'s two-stage index built from it; searched in a child process with every set's real photos
    (their exact top-10 over the 10^6 rows computed first). ``reuse``: the exact top-10 and the index of an
    earlier run are searched again (only the search is measured)."""
    from aeroloc.retrieval.index import build_index_from_store

    stores = [next((work / f"recall-{s[0].split()[0]}" / "global").glob("*/descriptors.npy")) for s in RECALL_SETS]
    real = np.concatenate([np.load(p).astype(np.float32) for p in stores])
    q = np.concatenate([np.load(p.parents[2] / "photo_queries.npy") for p in stores]).astype(np.float32)
    folder = work / "million"
    folder.mkdir(parents=True, exist_ok=True)
    npy, qpath = folder / "descriptors.npy", folder / "queries.npy"
    # auto's index is index.faiss; another factory's is named after it (both can be searched again, --reuse)
    index_path = folder / (
        "index.faiss" if factory == "auto" else f"index-{re.sub(r'[^A-Za-z0-9]+', '-', factory)}.faiss"
    )
    d = real.shape[1]
    t0 = time.perf_counter()
    if not (npy.is_file() and np.load(npy, mmap_mode="r").shape == (n, d)):
        import faiss

        fp16 = faiss.IndexScalarQuantizer(d, faiss.ScalarQuantizer.QT_fp16, faiss.METRIC_INNER_PRODUCT)
        rng = np.random.default_rng(0)
        mm = np.lib.format.open_memmap(folder / "part.npy", "w+", np.float16, (n, d))
        mm[: len(real)] = real  # the real tiles themselves, then noisy copies
        for s in range(len(real), n, 20_000):
            m = min(20_000, n - s)
            x = real[rng.integers(0, len(real), m)]
            x += rng.standard_normal((m, d), dtype=np.float32) * (noise / np.sqrt(d))
            mm[s : s + m] = fp16.sa_encode(x / np.linalg.norm(x, axis=1, keepdims=True)).view(np.float16)
        mm.flush()
        del mm
        (folder / "part.npy").replace(npy)
    gen_s = time.perf_counter() - t0
    print(f"million: store of {n} x {d} ready in {gen_s:.0f} s", flush=True)
    t0 = time.perf_counter()
    same_q = reuse and qpath.is_file() and np.array_equal(np.load(qpath), q)
    if not (same_q and (folder / "queries.exact.npy").is_file()):
        np.save(qpath, q)
        np.save(folder / "queries.exact.npy", _exact_top10(npy, q))
    exact_s = time.perf_counter() - t0
    print(f"million: exact top-10 of {len(q)} photos in {exact_s:.0f} s", flush=True)
    t0, c0 = time.perf_counter(), time.process_time()
    if reuse and index_path.is_file():
        factory = f"{factory} (index of an earlier run)"
    else:
        factory = build_index_from_store(npy, index_path, factory)
    build_s, build_cpu_s = time.perf_counter() - t0, time.process_time() - c0
    print(
        f"million: {factory} built in {build_s:.0f} s, {build_cpu_s:.0f} s CPU (load {os.getloadavg()[0]:.1f})",
        flush=True,
    )
    out = subprocess.run(
        [sys.executable, __file__, "--child-million", str(npy), str(index_path), str(qpath), candidates],
        capture_output=True,
        text=True,
    )
    if out.returncode:
        raise SystemExit(out.stderr[-2000:])
    res = json.loads(out.stdout.strip().splitlines()[-1])
    return {
        "factory": factory,
        "n": n,
        "real rows": len(real),
        "generate_s": round(gen_s, 1),
        "exact_s": round(exact_s, 1),
        "build_s": round(build_s, 1),
        "build_cpu_s": round(build_cpu_s, 1),
        "coarse index MB": round(index_path.stat().st_size / 2**20, 1),
        "store GB": round(npy.stat().st_size / 2**30, 2),
        "load average": round(os.getloadavg()[0], 1),
        **res,
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="/tmp/aeroloc-scale")
    ap.add_argument("--child", nargs=5)
    ap.add_argument("--child-million", nargs=4)
    ap.add_argument("--only", choices=["tiling", "build", "recall", "million"])
    ap.add_argument("--no-ray", action="store_true", help="builds: in-process only (the RSS figures)")
    ap.add_argument(
        "--factories",
        choices=["all", "auto", "ef", "two-stage", "three-stage", "pq", "one-stage"],
        default="all",
        help="recall: which",
    )
    ap.add_argument("--sets", default="", help="recall: only these sets (e.g. levir,szada)")
    ap.add_argument("--n", type=int, default=1_000_000, help="million: rows of the synthetic store")
    ap.add_argument("--factory", default="auto", help="million: the index built")
    ap.add_argument("--candidates", default="200,400,800", help="million: R or R/efSearch, comma-separated")
    ap.add_argument("--reuse", action="store_true", help="million: search the index and exact top-10 built before")
    a = ap.parse_args()
    if a.child:
        out, zoom, overlap, ray, workers = a.child
        return child_build(Path(out), float(zoom), float(overlap), ray or None, int(workers))
    if a.child_million:
        return child_million(*map(Path, a.child_million[:3]), a.child_million[3])
    work = Path(a.out)
    work.mkdir(parents=True, exist_ok=True)
    if a.only in (None, "tiling"):
        print(f"load average before: {os.getloadavg()[0]:.1f}")
        print(
            "| map, grid | tiles | aero-vloc tiles/s (tiles) | windows db: first call / cold hash / warm, ms "
            "| x aero-vloc tiles/s | window reads tiles/s | PNG db tiles/s |"
        )
        for r in bench_tiling(work):
            first = "—" if r["first call ms"] is None else f"{r['first call ms']:.1f}"
            first_x = "—" if r["first call x"] is None else f"{r['first call x']:.0f}"
            print(
                f"| {r['grid']} | {r['tiles']} | {r['aero-vloc tiles/s']:.0f} ({r['aero-vloc tiles']}) "
                f"| {first} / {r['cold hash ms']:.1f} / {r['warm ms']:.1f} "
                f"| {first_x} / {r['cold hash x']:.0f} / {r['warm x']:.0f} "
                f"| {r['window reads tiles/s']:.0f} | {r['PNG db tiles/s']:.1f} |",
                flush=True,
            )
        print(f"load average after: {os.getloadavg()[0]:.1f}")
    if a.only in (None, "build"):
        print(json.dumps(bench_builds(work, not a.no_ray), indent=1), flush=True)
    if a.only in (None, "recall"):
        print(json.dumps(bench_recall(work, a.factories, a.sets)), flush=True)
    if a.only in (None, "million"):
        print(
            json.dumps(bench_million(work, a.n, candidates=a.candidates, factory=a.factory, reuse=a.reuse)), flush=True
        )


if __name__ == "__main__":
    main()
