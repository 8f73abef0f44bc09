"""Localize a whole flight: a filtered track (odometry + windowed map fixes + global re-localization), streamed
to a resumable CSV, and optionally GeoJSON, KML, an offline HTML map and a MAVLink GPS_INPUT stream."""

from __future__ import annotations


def add_arguments(p):
    p.add_argument("db", help="database folder built by 'aeroloc build' (its map is tracked on)")
    p.add_argument(
        "frames",
        help="frames CSV name,time[,priors…] (or a folder holding frames.csv), a folder of "
        "photos (EXIF time order), or a video file",
    )
    p.add_argument("--out", required=True, help="track CSV name,time,lat,lon,status,sigma_m,source,…")
    p.add_argument("--telemetry", help="telemetry CSV time,alt_agl_m,hfov_deg,heading_deg,… or a DJI .SRT")
    p.add_argument("--no-telemetry", action="store_true", help="a video without telemetry: its own timestamps")
    p.add_argument("--truth", help="CSV name,lat,lon of the true positions, for the HTML/GeoJSON errors only")
    p.add_argument("--geojson", help="write the track as GeoJSON (LineString + points with status and sigma)")
    p.add_argument("--kml", help="write the track as KML")
    p.add_argument("--html", help="write an offline HTML map of the track over the map (truth and errors if known)")
    p.add_argument("--mavlink", metavar="URL", help="stream GPS_INPUT messages, e.g. udpout:127.0.0.1:14550")
    p.add_argument("--speed-max", type=float, default=60.0, help="speed bound in m/s (default %(default)s)")
    p.add_argument("--device", default="auto")


def read_truth(path) -> dict[str, tuple[float, float]]:
    import csv

    from aeroloc.core.errors import AerolocError

    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows or not {"name", "lat", "lon"} <= set(rows[0]):
        raise AerolocError(f"{path}: truth needs columns name,lat,lon")
    return {r["name"]: (float(r["lat"]), float(r["lon"])) for r in rows if r["lat"].strip() and r["lon"].strip()}


def run(args) -> int:
    from dataclasses import replace

    from aeroloc.core.device import pick_device
    from aeroloc.core.errors import AerolocError
    from aeroloc.flight.filter import FilterConfig
    from aeroloc.flight.frames import load_flight
    from aeroloc.flight.run import read_track, track_flight
    from aeroloc.flight.tracker import TrackConfig
    from aeroloc.localization.localizer import Localizer
    from aeroloc.localization.options import LocalizeOptions
    from aeroloc.retrieval.database import Database

    if not args.speed_max > 0:
        raise AerolocError(f"--speed-max must be > 0 m/s, got {args.speed_max}")
    flight = load_flight(args.frames, args.telemetry, args.no_telemetry)
    config = TrackConfig(filter=replace(FilterConfig(), speed_max_mps=args.speed_max))
    localizer = Localizer(Database(args.db), LocalizeOptions(), pick_device(args.device))
    mav = None
    if args.mavlink:
        from aeroloc.flight.outputs import MavlinkOutput

        mav = MavlinkOutput(args.mavlink)
    try:
        # the points are not kept while flying (memory flat over hours); the outputs read them back from the CSV
        track_flight(localizer, flight, args.out, config, on_point=mav.send if mav else None, keep=False)
    finally:
        if mav is not None:
            mav.close()
    points = read_track(args.out)
    truth = read_truth(args.truth) if args.truth else {f.name: f.truth for f in flight.frames if f.truth}
    write_outputs(args, points, truth, localizer.db.info["map"]["path"])
    by = {s: sum(p.source == s for p in points) for s in ("global fix", "tracked", "coasted", "lost")}
    print(f"{len(points)} frames: " + ", ".join(f"{n} {s}" for s, n in by.items()) + f" -> {args.out}")
    return 0


def write_outputs(args, points, truth, map_path) -> None:
    from aeroloc.flight import outputs

    if args.geojson:
        outputs.write_geojson(args.geojson, points, truth)
    if args.kml:
        outputs.write_kml(args.kml, points)
    if args.html:
        from aeroloc.flight.html import write_track_html

        write_track_html(args.html, points, map_path, truth)
