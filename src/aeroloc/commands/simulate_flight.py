"""Fly a simulated nadir camera over a real image of other dates than the map and write frames + telemetry +
truth (aeroloc.flight.simulate): the flight to track against the map."""

from __future__ import annotations


def add_arguments(p):
    p.add_argument("map", help="the map (GeoTIFF …): its grid and georeference, never its pixels")
    p.add_argument(
        "crops",
        nargs="+",
        help="query set(s) of other dates with exact footprints (queries.csv with "
        "lat,lon,heading_deg and footprint_m or gsd_m): composed into the image flown over",
    )
    p.add_argument("--out", required=True, help="flight folder: frames/, frames.csv, telemetry.csv, truth.csv")
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--rate", type=float, default=2.0, help="frames per second (default %(default)s)")
    p.add_argument("--speed", type=float, default=40.0, help="m/s (default %(default)s)")
    p.add_argument("--size", default="480x360", help="frame width x height in px (default %(default)s)")
    p.add_argument("--hfov", type=float, default=60.0, help="camera field of view, degrees")
    p.add_argument("--alt", default="700,950", help="height above ground range, metres (default %(default)s)")
    p.add_argument("--gap", type=int, default=30, help="frames lost (half black, half missing; default 30)")
    p.add_argument("--factor", type=float, default=2.0, help="composite resolution x the map's (default 2)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--compass",
        type=float,
        metavar="DEG",
        help="also write a compass heading to telemetry.csv, erring slowly within ±DEG (heading_tol_deg = DEG)",
    )


def run(args) -> int:
    from aeroloc.core.errors import AerolocError
    from aeroloc.core.queries import load_queries
    from aeroloc.flight.composite import compose
    from aeroloc.flight.simulate import FlightPlan, write_flight
    from aeroloc.maps.sources import open_map

    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
        lo, hi = (float(v) for v in args.alt.split(","))
    except ValueError:
        raise AerolocError(f"--size WxH and --alt LO,HI expected, got {args.size!r}, {args.alt!r}") from None
    m = open_map(args.map)
    crops = [q for c in args.crops for q in load_queries(c, priors="none")]
    comp = compose(m, crops, args.factor)
    plan = FlightPlan(
        frames=args.frames,
        rate_hz=args.rate,
        speed_mps=args.speed,
        width=w,
        height=h,
        hfov_deg=args.hfov,
        alt_m=(lo, hi),
        gap_frames=args.gap,
        seed=args.seed,
        compass_deg=args.compass,
    )
    n = write_flight(args.out, m, comp, plan)
    dates = sorted(set(comp.dates))
    print(f"{n} frames over a composite of {len(crops)} crops ({', '.join(dates)}) -> {args.out}")
    return 0
