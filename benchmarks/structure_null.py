#!/usr/bin/env python
"""How distinct the structure check's peaks are at right and at wrong sweep candidates, per shared set and prior
mode: the measurement behind ``structure_min_ratio`` (aeroloc.localization.structure_check).

For each query the sweep's best candidates are checked with every threshold off; a candidate is *right* when it
lies within max(25 m, 10 map px) of the truth. Wrong candidates whose structural peak lands near them (within the
same reach) are the null: what the check finds where the query is not. Prints per set the share of queries the
check alone would place within t at the configured threshold, and the highest ratio of the null.

usage: python benchmarks/structure_null.py [--n 12] [--sets levir-any,...] [--modes none,rough,exact]
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
MR = DATA / "multi-region"
SETS = {  # name: (map, queries)
    "naip-dev": (DATA / "naip-nd/map_20200831.tif", DATA / "naip-nd/dev/queries.csv"),
    "naip-rotated": (DATA / "naip-nd/map_20200831.tif", DATA / "naip-nd/dev-rotated/queries.csv"),
    "levir-north": (MR / "levir-tx/map.tif", MR / "levir-tx/north/queries.csv"),
    "levir-any": (MR / "levir-tx/map.tif", MR / "levir-tx/any/queries.csv"),
    "szada-north": (MR / "szada-hu/map.tif", MR / "szada-hu/north/queries.csv"),
    "szada-any": (MR / "szada-hu/map.tif", MR / "szada-hu/any/queries.csv"),
}


def candidates(name: str, mode: str, n: int) -> list[dict]:
    """Every checked candidate: set, query, rank, right or not, the peak's ratio/score, its error and agreement."""
    from aeroloc.bench.experiment import sample_queries
    from aeroloc.core import geo
    from aeroloc.core.device import single_threaded_blas
    from aeroloc.core.images import read_image
    from aeroloc.core.queries import load_queries
    from aeroloc.localization.structure_check import confirm_structure
    from aeroloc.localization.sweep_stage import SweepLocator
    from aeroloc.maps.sources import open_map

    map_path, queries_path = SETS[name]
    loc = SweepLocator(open_map(map_path))
    reach = max(25.0, 10.0 * loc.map_gsd)
    off = {**loc.conf, "structure_min_ratio": 0.0, "structure_min_score": 0.0}
    rows = []
    with single_threaded_blas():
        for q in sample_queries(load_queries(queries_path, priors=mode, seed=0), n):
            image = read_image(q.path)
            res = loc.search(image, q.priors if mode != "none" else None)
            for rank, h in enumerate(res.candidates if res else ()):
                lat, lon = loc.map.pixel_to_latlon(h.col, h.row)
                fix = confirm_structure(loc.map, image, h, float("inf"), off)
                if fix is None:
                    continue
                rows.append(
                    {
                        "query": q.name,
                        "rank": rank,
                        "right": float(geo.geodesic_distance(lat, lon, q.lat, q.lon)) <= reach,
                        "ratio": fix.ratio,
                        "score": fix.score,
                        "error_m": float(geo.geodesic_distance(fix.lat, fix.lon, q.lat, q.lon)),
                        "agrees": fix.agreement_m <= reach,
                        "t_m": max(5.0, 2.0 * loc.map_gsd),
                    }
                )
    return rows


def summary(rows: list[dict], n: int, conf: dict) -> dict:
    """Share placed within t by the check alone (first passing candidate per query) and the null's top ratio."""
    placed = {}
    for r in sorted(rows, key=lambda r: r["rank"]):
        ok = r["agrees"] and r["ratio"] >= conf["structure_min_ratio"] and r["score"] >= conf["structure_min_score"]
        if ok and r["query"] not in placed:
            placed[r["query"]] = r
    null = [r["ratio"] for r in rows if r["agrees"] and not r["right"]]
    right = [r["ratio"] for r in rows if r["agrees"] and r["right"]]
    return {
        "within_t": sum(r["error_m"] <= r["t_m"] for r in placed.values()) / max(1, n),
        "wrong": sum(not r["right"] for r in placed.values()),
        "null_max": max(null, default=float("nan")),
        "right_median": statistics.median(right) if right else float("nan"),
    }


def main() -> int:
    from localize_speed import print_table  # benchmarks/ is on sys.path when a script of it runs

    from aeroloc.localization.structure_check import STRUCTURE_DEFAULTS

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=12)
    ap.add_argument("--sets", default=",".join(SETS))
    ap.add_argument("--modes", default="none,rough,exact")
    args = ap.parse_args()
    print(
        f"threshold: ratio >= {STRUCTURE_DEFAULTS['structure_min_ratio']}, score >= {STRUCTURE_DEFAULTS['structure_min_score']}"
    )

    def row(name: str, mode: str) -> list[str]:
        s = summary(candidates(name, mode, args.n), args.n, STRUCTURE_DEFAULTS)
        figures = (s["within_t"], s["wrong"], s["null_max"], s["right_median"])
        return [name, mode, str(args.n), *(f"{f:.2f}" if isinstance(f, float) else str(f) for f in figures)]

    header = ["set", "priors", "n", "within t (check alone)", "wrong", "null: top ratio", "right: median ratio"]
    print_table(header, args.sets.split(","), args.modes.split(","), row)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
