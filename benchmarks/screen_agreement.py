#!/usr/bin/env python
"""The evidence behind accepting a screen by agreement (aeroloc.localization.agreement), re-measured.

Every photo of each shared set is localized; its first cascade's screened candidates are logged (screen inliers
and where each candidate's transform places the query). For every photo whose best screen lies in 20-39 inliers
(below ``accept_screen``: no early exit, so every candidate was screened), it prints the best screen, its
*support* (the best screen of another tile placing the query within a reach, max(25 m, 10 map px), of it), the
best screen of a place more than two reaches away, whether the best placed the query within a reach of the
truth, and whether the agreement rule accepts it. The truth is read for scoring only.

usage: python benchmarks/screen_agreement.py [--sets naip-rotated,levir-any,...] [--modes none,rough]
       [--db DB ...] (databases as in benchmarks/localize_speed.py)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from localize_speed import SETS, add_database_args, given_databases, open_set


def log_set(name: str, mode: str, dbs: dict, cache: Path) -> list[tuple]:
    """(photo, best screen, support, far best, right, accepted) of every photo whose best screen is 20-39."""
    from aeroloc import LocalizeOptions, Localizer, load_queries, read_image
    from aeroloc.core import geo
    from aeroloc.localization import cascade
    from aeroloc.localization.agreement import centre_px, screen_agreed, support_and_far
    from aeroloc.localization.alignment import reach_m

    db, queries_path = open_set(name, cache, dbs)
    loc = Localizer(db, LocalizeOptions())
    gsd = loc.map_gsd
    logged: list[tuple] = []
    original = cascade.Reranker.__call__

    def logging_call(self, image, tile_ids, *args, **kwargs):
        rr = original(self, image, tile_ids, *args, **kwargs)
        logged.append(([c for c in rr.ranked if c.screen >= 0], (image.shape[1], image.shape[0]), self.conf))
        return rr

    out = []
    cascade.Reranker.__call__ = logging_call
    try:
        for q in load_queries(queries_path, priors=mode, seed=0):
            logged.clear()
            loc(q.name, read_image(q.path), priors=q.priors)
            if not logged:
                continue
            cands, size, conf = logged[0]
            cands = sorted(cands, key=lambda c: (-c.screen, c.retrieval_rank))
            if not cands or not 20 <= cands[0].screen < 40:
                continue
            found = support_and_far(db, cands, size)
            if found is None:
                continue
            support, far = found
            lat, lon = loc.map.pixel_to_latlon(*centre_px(db, cands[0], size))
            right = geo.geodesic_distance(q.lat, q.lon, float(lat), float(lon)) <= reach_m(gsd)
            out.append((q.name, cands[0].screen, support, far, right, screen_agreed(db, cands, size, conf)))
    finally:
        cascade.Reranker.__call__ = original
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", default=",".join(SETS))
    ap.add_argument("--modes", default="none,rough")
    add_database_args(ap)
    args = ap.parse_args()
    dbs = given_databases(args)
    totals = {"photos": 0, "wrong": 0, "accepted": 0, "accepted_wrong": 0}
    print("| set | priors | photo | best screen | support | far best | right | accepted |")
    print("|---|---|---|---:|---:|---:|---|---|")
    for name in args.sets.split(","):
        for mode in args.modes.split(","):
            for photo, top, support, far, right, accepted in log_set(name, mode, dbs, args.cache):
                print(f"| {name} | {mode} | {photo} | {top} | {support} | {far} | {right} | {accepted} |", flush=True)
                totals["photos"] += 1
                totals["wrong"] += not right
                totals["accepted"] += accepted
                totals["accepted_wrong"] += accepted and not right
    print(
        f"\nbest screen 20-39: {totals['photos']} photos, {totals['wrong']} placed more than a reach off; accepted by "
        f"agreement {totals['accepted']}, of them more than a reach off {totals['accepted_wrong']}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
