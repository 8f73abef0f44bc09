#!/usr/bin/env python
"""Seconds per query of single-image localization, per shared set and prior mode, as CPU time of one thread.

Why CPU time with one torch thread: wall time on this shared 2-core machine depends on whatever else runs; the
CPU time of a single-threaded run is what one idle core takes (an upper bound of the wall time on 2 idle cores).
Prints a table: set, priors, queries, share within t = max(5 m, 2 map px), wrong (> max(25 m, 10 map px)), median
and p90 CPU s/query, and the median of each stage.

usage: python benchmarks/localize_speed.py [--n 12] [--sets levir-any,szada-any,...] [--modes none,rough,exact]
       [--per-query] (databases are built once under --cache, tiles about the queries' footprint as in
       experiments/atlas.yaml)

``--per-query`` also prints, for every photo, its CPU seconds, the screens and matcher runs it cost (counted
around the re-ranker's screen and match calls) and its error: where a set's median time goes.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
MR = DATA / "multi-region"
SETS = {  # name: (map, queries, tile_m)
    "naip-dev": (DATA / "naip-nd/map_20200831.tif", DATA / "naip-nd/dev/queries.csv", 1000),
    "naip-rotated": (DATA / "naip-nd/map_20200831.tif", DATA / "naip-nd/dev-rotated/queries.csv", 1000),
    "toledo": (DATA / "toledo/orthomosaic.tif", DATA / "toledo/queries.csv", 200),
    "levir-north": (MR / "levir-tx/map.tif", MR / "levir-tx/north/queries.csv", 150),
    "levir-any": (MR / "levir-tx/map.tif", MR / "levir-tx/any/queries.csv", 150),
    "szada-north": (MR / "szada-hu/map.tif", MR / "szada-hu/north/queries.csv", 340),
    "szada-any": (MR / "szada-hu/map.tif", MR / "szada-hu/any/queries.csv", 340),
}


class CallCounts:
    """Screens and matcher runs of the re-ranker, counted around its two calls while in use (instrumentation:
    the calls themselves are the real ones)."""

    def __init__(self):
        from aeroloc.localization.cascade import Reranker

        self.counts = {"screens": 0, "matches": 0}
        self._cls, self._orig = Reranker, (Reranker.screen_pair, Reranker.match_pair)

    def __enter__(self):
        counts, (screen, match) = self.counts, self._orig

        def counted(fn, key):
            def call(*args, **kwargs):
                counts[key] += 1
                return fn(*args, **kwargs)

            return call

        self._cls.screen_pair, self._cls.match_pair = counted(screen, "screens"), counted(match, "matches")
        return self

    def __exit__(self, *exc):
        self._cls.screen_pair, self._cls.match_pair = self._orig

    def take(self) -> dict:
        out = dict(self.counts)
        self.counts.update(screens=0, matches=0)
        return out


def open_set(name: str, cache: Path, dbs: dict):
    """(database, queries CSV) of shared set ``name``: the database given for its map (``dbs``: map path ->
    folder), else one built once under ``cache`` with tiles about the queries' footprint."""
    from aeroloc import build_database

    map_path, queries_path, tile_m = SETS[name]
    folder = dbs.get(str(map_path)) or cache / f"{map_path.parent.name}-{map_path.stem}-{tile_m}"
    return build_database(map_path, folder, tile_m=tile_m), queries_path


def run_set(name: str, mode: str, n: int, cache: Path, dbs: dict) -> dict:
    from aeroloc import LocalizeOptions, Localizer, load_queries, read_image
    from aeroloc.bench.experiment import sample_queries
    from aeroloc.core import geo

    db, queries_path = open_set(name, cache, dbs)
    loc = Localizer(db, LocalizeOptions())
    qs = sample_queries(load_queries(queries_path, priors=mode, seed=0), n)
    gsd = loc.map_gsd
    t_m, wrong_m = max(5.0, 2 * gsd), max(25.0, 10 * gsd)
    loc(qs[0].name, read_image(qs[0].path), priors=qs[0].priors)  # warm-up: models, map pyramid
    cpu, hits, wrong, stages, lines = [], 0, 0, {}, []
    with CallCounts() as calls:
        for q in qs:
            image = read_image(q.path)
            calls.take()
            c0 = time.process_time()
            r = loc(q.name, image, priors=q.priors)
            cpu.append(time.process_time() - c0)
            for s, ms in r.times_ms.items():
                stages.setdefault(s, []).append(ms / 1000)
            e = geo.geodesic_distance(q.lat, q.lon, r.lat, r.lon) if r.localized else math.nan
            hits += e <= t_m
            wrong += e > wrong_m
            c = calls.take()
            lines.append(
                (
                    cpu[-1],
                    f"  {cpu[-1]:5.2f} s  {c['screens']:3d} screens  {c['matches']} matches  "
                    f"error {e:6.1f} m  {q.name}  {r.status[:60]}",
                )
            )

    cpu.sort()
    return {
        "set": name,
        "priors": mode,
        "n": len(qs),
        "within_t": hits / len(qs),
        "wrong": wrong,
        "median_s": statistics.median(cpu),
        "p90_s": cpu[math.ceil(0.9 * (len(cpu) - 1))],
        "stages": {s: statistics.median(v) for s, v in stages.items()},
        "per_query": [f"{name} {mode}, per photo (fastest first):"] + [line for _, line in sorted(lines)],
    }


def add_database_args(ap: argparse.ArgumentParser) -> None:
    """The benchmarks' database options: ``--cache`` (where databases are built once) and ``--db`` (existing ones)."""
    ap.add_argument("--cache", type=Path, default=ROOT / "runs" / "speed-cache")
    ap.add_argument("--db", action="append", default=[], help="an existing database folder to use for its map")


def given_databases(args) -> dict:
    """Map path -> database folder of every ``--db``; torch on one thread (the benchmarks measure one core)."""
    import torch

    from aeroloc.retrieval.database import Database

    torch.set_num_threads(1)
    return {Database(d).info["map"]["path"]: Path(d) for d in args.db}


def print_table(header: list[str], sets: list[str], modes: list[str], row) -> None:
    """A markdown table with a row ``row(set, mode)`` (its cells) per set x prior mode, printed as it is measured."""
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for name in sets:
        for mode in modes:
            print("| " + " | ".join(row(name, mode)) + " |", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=12)
    ap.add_argument("--sets", default=",".join(SETS))
    ap.add_argument("--modes", default="none,rough,exact")
    add_database_args(ap)
    ap.add_argument("--per-query", action="store_true", help="also print each photo's CPU s, screens, matcher runs")
    args = ap.parse_args()
    dbs = given_databases(args)

    def row(name: str, mode: str) -> list[str]:
        r = run_set(name, mode, args.n, args.cache, dbs)
        per_query.extend(r["per_query"])
        st = ", ".join(f"{k} {v:.2f}" for k, v in r["stages"].items() if v >= 0.005)
        cells = (r["within_t"], r["wrong"], r["median_s"], r["p90_s"])
        return [
            r["set"],
            r["priors"],
            str(r["n"]),
            *(f"{c:.2f}" if isinstance(c, float) else str(c) for c in cells),
            st,
        ]

    header = ["set", "priors", "n", "within t", "wrong", "CPU s/query median", "p90", "stage medians (s)"]
    per_query: list[str] = []
    print_table(header, args.sets.split(","), args.modes.split(","), row)
    if args.per_query:
        print("\n".join(per_query))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
