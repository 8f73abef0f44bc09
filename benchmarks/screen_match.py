#!/usr/bin/env python
"""The screen's mutual nearest neighbours on real photo/tile pairs: aeroloc's float32 product vs an 8-bit one.

The screen (aeroloc.localization.cascade) matches a photo of unknown heading with tens of candidate tiles and turns,
one 2048 x 2048 x 64 similarity matrix each. This records the descriptor pairs the screens of ``--n`` queries of each
set really see (priors none: the most screens), then times aeroloc's ``mutual_nn`` and the alternative measured on
2026-12-06 (pairs found on 8-bit codes by torch's int8 product, scores in float32; not adopted, README #13) on one
thread, and says how many pairs they share (|A ∩ B| / max(|A|, |B|); a changed pair is a near-tie of a row's best).

usage: python benchmarks/screen_match.py [--sets levir-any,naip-rotated,szada-any] [--n 6] [--db DB ...]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
from localize_speed import SETS, add_database_args, given_databases, print_table


def int8_mutual_nn(d0, d1, min_similarity: float) -> np.ndarray:
    """The 8-bit alternative: the photo's unit rows coded on the finest 8-bit grid their largest component allows
    (one scale), the tile's at 127 like the feature store's; mutual pairs of the int32 products, cut on float32
    cosines."""
    import torch

    from aeroloc.matching.models.xfeat import mutual_rows

    a = d0 / (np.linalg.norm(d0, axis=1, keepdims=True) + 1e-8)
    b = d1 / (np.linalg.norm(d1, axis=1, keepdims=True) + 1e-8)
    qa = np.rint(a * (127 / max(float(np.abs(a).max()), 1e-8))).astype(np.int8)
    sim = torch._int_mm(torch.from_numpy(qa), torch.from_numpy(np.rint(b * 127).astype(np.int8)).T).numpy()
    keep, nn01, _ = mutual_rows(sim)  # the same mutual rule as aeroloc's, on the int32 products
    keep = keep[np.einsum("ij,ij->i", a[keep], b[nn01[keep]]) > min_similarity]
    return np.stack([keep, nn01[keep]], 1)


def screen_pairs(name: str, n: int, cache: Path, dbs: dict) -> list:
    """The (photo descriptors, tile descriptors, min similarity) of every screen of ``n`` queries of set ``name``."""
    import aeroloc.localization.cascade as cascade
    from aeroloc import LocalizeOptions, Localizer, build_database, load_queries, read_image
    from aeroloc.bench.experiment import sample_queries

    map_path, queries_path, tile_m = SETS[name]
    folder = dbs.get(str(map_path)) or cache / f"{map_path.parent.name}-{map_path.stem}-{tile_m}"
    loc = Localizer(build_database(map_path, folder, tile_m=tile_m), LocalizeOptions())
    seen, mnn = [], cascade.mutual_nn

    def record(d0, d1, min_sim=0.0):
        seen.append((np.asarray(d0, np.float32), np.asarray(d1, np.float32), float(min_sim)))
        return mnn(d0, d1, min_sim)

    cascade.mutual_nn = record
    try:
        for q in sample_queries(load_queries(queries_path, priors="none", seed=0), n):
            loc(q.name, read_image(q.path), priors=q.priors)
    finally:
        cascade.mutual_nn = mnn
    return seen


def per_pair_ms(fn, pairs: list) -> list[float]:
    out = []
    for d0, d1, m in pairs:
        t0 = time.perf_counter()
        fn(d0, d1, m)
        out.append((time.perf_counter() - t0) * 1e3)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=6)
    ap.add_argument("--sets", default="levir-any,naip-rotated,szada-any")
    add_database_args(ap)
    args = ap.parse_args()
    from aeroloc.matching.models.xfeat import mutual_nn

    dbs = given_databases(args)

    def row(name: str, _mode: str) -> list[str]:
        pairs = screen_pairs(name, args.n, args.cache, dbs)
        per_pair_ms(int8_mutual_nn, pairs[:3])  # warm-up: the int8 product's kernels for these shapes
        ms32, ms8 = per_pair_ms(mutual_nn, pairs), per_pair_ms(int8_mutual_nn, pairs)
        agree = []
        for d0, d1, m in pairs:
            a = {tuple(p) for p in mutual_nn(d0, d1, m)[0].tolist()}
            b = {tuple(p) for p in int8_mutual_nn(d0, d1, m).tolist()}
            agree.append(len(a & b) / max(len(a), len(b), 1))
        f32, i8 = statistics.median(ms32), statistics.median(ms8)
        return [name, str(len(pairs)), f"{f32:.2f}", f"{i8:.2f}", f"{f32 / i8:.1f}x"] + [
            f"{statistics.mean(agree):.3f} / {min(agree):.3f}"
        ]

    header = [
        "set",
        "screens",
        "aeroloc float32 ms (median)",
        "int8 ms (median)",
        "speed-up",
        "pairs shared mean / min",
    ]
    print_table(header, args.sets.split(","), ["none"], row)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
