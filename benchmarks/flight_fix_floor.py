"""What a flight's frames allow (issue #14): the tracker's windowed fix placed at each frame's true pose.

usage: nice python benchmarks/flight_fix_floor.py experiments/flights.yaml [--only NAME-SUBSTRING] [--every 3]
       [--pipeline]

For every simulated flight already written by ``benchmarks/flights.py`` (OUT/<name>/ with truth.csv), every
``--every``-th frame that shows the ground is matched by :class:`aeroloc.flight.window_fix.WindowMatcher` around its
*true* pose (true centre, turn and ground resolution; a window of ±3 x 10 m), three ways: the tracker's own search
(turn ± 4°, scales ± 6 %), the true turn and scale alone (a translation search), and ±1° / ±1 % around them. The
share of fixes within t = max(5 m, 2 map px) is the ceiling of what a filter fusing single independent fixes can
reach, and their errors' spread is the fix noise. ``--pipeline``: also the single-image pipeline with the frame's
exact ground resolution and heading (±15°) as priors. Truth is read here for scoring only; it is the search's
starting point, which no tracker has, so these are upper bounds, not results.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from pathlib import Path

import numpy as np
import yaml
from flights import slug  # benchmarks/flights.py, beside this script

from aeroloc.core import geo
from aeroloc.core.images import read_image
from aeroloc.core.priors import Priors
from aeroloc.flight.calibration import Pose
from aeroloc.flight.window_fix import WindowMatcher
from aeroloc.maps.sources import open_map

SEARCHES = {  # name -> (turns around the true one, scales around the true one); None: the tracker's defaults
    "tracker (±4°, ±6 %)": (None, None),
    "translation": ((0.0,), (1.0,)),
    "±1°, ±1 %": ((-1.0, 0.0, 1.0), (0.99, 1.01)),
}


def floor(flight: dict, out: Path, every: int, pipeline: bool) -> dict | None:
    folder = out / slug(flight["name"])  # where benchmarks/flights.py wrote the flight
    if not (folder / "truth.csv").is_file():
        print(f"{flight['name']}: {folder}/truth.csv missing (run benchmarks/flights.py first)", file=sys.stderr)
        return None
    m = open_map(flight["map"])
    matcher = WindowMatcher(m)
    t_m = max(5.0, 2 * m.resolution_m)
    with open(folder / "truth.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    localizer = None
    if pipeline:
        from aeroloc.localization.localizer import Localizer
        from aeroloc.retrieval.database import Database

        localizer = Localizer(Database(flight["db"]))
    errs: dict[str, list[float]] = {k: [] for k in [*SEARCHES, *(["pipeline"] if pipeline else [])]}
    for r in rows[::every]:
        image = read_image(folder / "frames" / r["name"]) if (folder / "frames" / r["name"]).is_file() else None
        if image is None or float(image[::4, ::4].std()) < 3.0:  # blank: nothing to place (the tracker's rule)
            continue
        lat, lon = float(r["lat"]), float(r["lon"])
        col, row = m.latlon_to_pixel(lat, lon)
        turn, scale = float(r["heading_deg"]), float(r["gsd_m"]) / m.resolution_m
        pose = Pose(float(col), float(row), turn, scale)
        for name, (turns, scales) in SEARCHES.items():
            angles = None if turns is None else tuple(turn + d for d in turns)
            fix = matcher(image, pose, 10.0 / m.resolution_m, angles=angles, scales=scales)
            if fix is None:
                errs[name].append(math.nan)
                continue
            flat, flon = m.pixel_to_latlon(fix.x, fix.y)
            errs[name].append(float(geo.geodesic_distance(float(flat), float(flon), lat, lon)))
        if localizer is not None:
            priors = Priors(gsd_m=float(r["gsd_m"]), heading_deg=turn % 360.0, heading_tol_deg=15.0)
            loc = localizer(r["name"], image, priors=priors)
            errs["pipeline"].append(
                float(geo.geodesic_distance(loc.lat, loc.lon, lat, lon)) if loc.localized else math.nan
            )
    return {"name": flight["name"], "t_m": t_m, "errs": errs}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("experiments")
    ap.add_argument("--only", help="the flights whose name contains this")
    ap.add_argument("--every", type=int, default=3, help="every n-th frame")
    ap.add_argument("--pipeline", action="store_true", help="also the single-image pipeline with exact priors")
    a = ap.parse_args(argv)
    conf = yaml.safe_load(Path(a.experiments).read_text())
    out = Path(conf.get("out", "out/flights"))
    print("| flight | search | frames | placed | within t (t) | median err | 90th pct err |")
    print("|---|---|---|---|---|---|---|")
    for f in conf["flights"]:
        if f.get("kind") != "simulated" or (a.only and a.only not in f["name"]):
            continue
        res = floor(f, out, a.every, a.pipeline)
        if res is None:
            continue
        for name, e in res["errs"].items():
            v = np.array(e, float)
            ok = v[np.isfinite(v)]
            if not len(v):
                continue
            med, p90 = (float(np.median(ok)), float(np.percentile(ok, 90))) if len(ok) else (math.nan, math.nan)
            print(
                f"| {res['name']} | {name} | {len(v)} | {len(ok)} | {(ok <= res['t_m']).sum() / len(v):.3f} "
                f"({res['t_m']:.0f} m) | {med:.1f} m | {p90:.1f} m |",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
