"""Flight mode (issue #14): memory while the track is lost. A simulated flight of an experiments file (written by
benchmarks/flights.py) is tracked normally up to --start, then every frame is searched as a lost track's is (around
the prediction, the whole-map dense stage every 3rd frame, the single-image pipeline every 2nd:
TrackConfig.dense_every and pipeline_every) and the track is kept lost, so the whole-map searches run --frames
times in a row. Prints RSS (MB) and CPU seconds every --every frames, with the native heap returned after each
whole-map search (the default) or not (--no-trim);
--whole-map skips the search around the prediction (over ground it can place, it would end the loss at once).

usage: nice python benchmarks/flight_memory.py experiments/flights.yaml --only naip-telemetry [--no-trim]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import yaml

from aeroloc.flight.filter import FilterConfig
from aeroloc.flight.frames import load_flight
from aeroloc.flight.tracker import TrackConfig, Tracker
from aeroloc.localization.localizer import Localizer
from aeroloc.retrieval.database import Database


def rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def main(argv=None) -> int:
    from flights import slug

    ap = argparse.ArgumentParser()
    ap.add_argument("experiments")
    ap.add_argument("--only", required=True, help="the (simulated) flight whose name contains this")
    ap.add_argument("--start", type=int, default=150, help="frames tracked normally first")
    ap.add_argument("--frames", type=int, default=60, help="frames then searched as lost")
    ap.add_argument("--every", type=int, default=10)
    ap.add_argument("--no-trim", action="store_true", help="keep freed native memory (no malloc_trim)")
    ap.add_argument(
        "--whole-map", action="store_true", help="no search around the prediction: only the whole-map searches"
    )
    args = ap.parse_args(argv)
    conf = yaml.safe_load(Path(args.experiments).read_text())
    f = next(f for f in conf["flights"] if args.only in f["name"] and f["kind"] == "simulated")
    folder = Path(conf.get("out", "out/flights")) / slug(f["name"])
    if not (folder / "frames.csv").is_file():
        print(f"{folder}: no simulated flight (run benchmarks/flights.py on it first)", file=sys.stderr)
        return 2
    flight = load_flight(folder / "frames.csv", folder / "telemetry.csv" if f.get("telemetry") else None)
    config = TrackConfig(
        filter=replace(FilterConfig(), speed_max_mps=f.get("speed_max", 60.0)), trim_native=not args.no_trim
    )
    tracker = Tracker(Localizer(Database(f["db"])), config)
    lost_config = replace(config, near_max_px=1) if args.whole_map else config  # windows never fit: none searched
    print(f"| frame | state | RSS MB | CPU s |  (trim {'off' if args.no_trim else 'on'})")
    lost = 0
    cpu0 = None
    for i, (ref, image) in enumerate(flight.images()):
        if i < args.start:
            tracker(ref, image)
            continue
        if lost >= args.frames:
            break
        if cpu0 is None:
            cpu0 = time.process_time()
            tracker.cfg = lost_config
            print(f"| {i} | tracked to here | {rss_mb():.0f} | 0 |", flush=True)
        if image is None or float(image.std()) < 3.0:
            continue
        tracker.pose, tracker.dead = None, None  # kept lost: every frame searched as a lost track's is
        tracker.filter.lose()
        tracker.lost_since = tracker.lost_since or ref.time
        tracker._relocalize(ref, image)
        lost += 1
        if lost % args.every == 0:
            print(f"| {i} | {lost} lost | {rss_mb():.0f} | {time.process_time() - cpu0:.0f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
