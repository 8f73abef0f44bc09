#!/usr/bin/env python
"""Search time per query and index size: exact Flat and approximate IVF-Flat / HNSW on 10^4 tiles, IVF-PQ on 10^6.

Synthetic descriptors are clustered unit vectors (like real tiles: many near-duplicates), generated and added in
chunks so RAM stays bounded. Prints ms/query and bytes/vector.
usage: python benchmarks/search_speed.py [--dim 8192] [--n-large 1000000] [--factory IVF4096,PQ64]
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def clustered(rng, n, dim, centres):
    c = centres[rng.integers(0, len(centres), n)]
    x = c + 0.5 * rng.standard_normal((n, dim)).astype(np.float32) / np.sqrt(dim)
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def timed_search(index, q, k):
    index.search(q[:2], k)  # warm-up
    t0 = time.perf_counter()
    index.search(q, k)
    return (time.perf_counter() - t0) / len(q) * 1000


def one_by_one(index, q, k):
    """ms per query searched alone (how localization calls it), median."""
    times = []
    for row in q[:50]:
        t0 = time.perf_counter()
        index.search(row[None], k)
        times.append((time.perf_counter() - t0) * 1000)
    return float(np.median(times))


def recall_vs_exact(index, exact, q, k):
    _, got = index.search(q, k)
    _, ref = exact.search(q, k)
    return float(np.mean([len(set(a) & set(b)) / k for a, b in zip(got, ref)]))


def main():
    import faiss

    from aeroloc.retrieval.index import build_index

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dim", type=int, default=8192)
    ap.add_argument("--n-flat", type=int, default=10_000)
    ap.add_argument("--n-large", type=int, default=1_000_000)
    ap.add_argument("--large-dim", type=int, default=1024, help="dim of the 10^6 set (PCA-reduced descriptors)")
    ap.add_argument("--factory", default="IVF4096,PQ64")
    ap.add_argument("--queries", type=int, default=200)
    a = ap.parse_args()
    rng = np.random.default_rng(0)
    print(f"faiss {faiss.__version__}, threads {faiss.omp_get_max_threads()}")

    centres = rng.standard_normal((2000, a.dim)).astype(np.float32)
    x = clustered(rng, a.n_flat, a.dim, centres)
    q = clustered(rng, a.queries, a.dim, centres)
    index = build_index(x, "Flat")
    print(
        f"Flat  n={a.n_flat:>8} dim={a.dim}: {timed_search(index, q, 20):.3f} ms/query in a batch of "
        f"{len(q)}, {one_by_one(index, q, 20):.3f} ms alone; {a.dim * 4} B/vector (store: float16 {a.dim * 2} B)"
    )
    exact = index
    for factory, probes in (("IVF100,Flat", (4, 8)), ("HNSW32", (64,))):
        approx = build_index(x, factory)
        for p in probes:
            if factory.startswith("IVF"):
                faiss.extract_index_ivf(approx).nprobe = p
            else:
                approx.hnsw.efSearch = p
            print(
                f"{factory} n={a.n_flat} dim={a.dim} {'nprobe' if 'IVF' in factory else 'efSearch'}={p}: "
                f"{one_by_one(approx, q, 20):.3f} ms alone, recall@20 vs exact {recall_vs_exact(approx, exact, q, 20):.3f}"
            )

    if not a.n_large:  # --n-large 0: the 10^4 part only
        return
    d = a.large_dim
    centres = rng.standard_normal((20000, d)).astype(np.float32)
    t0 = time.perf_counter()
    train = clustered(rng, min(a.n_large, 100_000), d, centres)
    index = faiss.index_factory(d, a.factory, faiss.METRIC_INNER_PRODUCT)
    index.train(train)
    t_train = time.perf_counter() - t0
    t0 = time.perf_counter()
    sample = []
    for start in range(0, a.n_large, 100_000):
        chunk = clustered(rng, min(100_000, a.n_large - start), d, centres)
        index.add(chunk)
        if start == 0:
            sample = chunk[:20_000]
    t_add = time.perf_counter() - t0
    q = sample[rng.choice(len(sample), a.queries, replace=False)]
    q = q + 0.3 * rng.standard_normal(q.shape).astype(np.float32) / np.sqrt(d)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    for nprobe in (8, 32):
        faiss.extract_index_ivf(index).nprobe = nprobe
        ms = timed_search(index, q, 20)
        print(
            f"{a.factory} n={a.n_large} dim={d} nprobe={nprobe}: {ms:.3f} ms/query "
            f"(train {t_train:.0f} s, add {t_add:.0f} s, {faiss.serialize_index(index).nbytes / a.n_large:.0f} B/vector)"
        )


if __name__ == "__main__":
    main()
