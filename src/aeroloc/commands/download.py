"""Download a map (XYZ tile server, xyzservices name or Google Static Maps API) covering an area or a flight.

Keys come from $AEROLOC_TILE_KEY ({key} in an XYZ template), $AEROLOC_GOOGLE_KEY (google) or --key-file, never
from the command line. Running the same command again resumes: only missing or broken tiles are fetched.
"""

from __future__ import annotations

import argparse


class _RefuseKey(argparse.Action):
    """``--key VALUE`` would put the key in shell history and process lists: refuse it (without echoing it)."""

    def __call__(self, parser, namespace, values, option_string=None):
        parser.error(
            f"{option_string}: keys are not taken from the command line; set $AEROLOC_TILE_KEY "
            "(XYZ {key}) or $AEROLOC_GOOGLE_KEY (google), or use --key-file FILE"
        )


def add_arguments(p):
    p.allow_abbrev = False  # so '--key SECRET' is never read as '--key-file SECRET'
    area = p.add_mutually_exclusive_group(required=True)
    area.add_argument(
        "--bbox", nargs=4, type=float, metavar=("SOUTH", "WEST", "NORTH", "EAST"), help="area in WGS84 degrees"
    )
    area.add_argument(
        "--around",
        metavar="QUERIES.csv",
        help="cover the positions of a query file (CSV name,lat,lon or the seed's queries.txt)",
    )
    p.add_argument("--margin-m", type=float, default=200.0, help="margin around --around positions (default 200 m)")
    p.add_argument("--zoom", type=int, required=True, help="Web Mercator zoom level (e.g. 17 ≈ 1.2 m/px at 0°)")
    p.add_argument(
        "--provider",
        required=True,
        help="XYZ URL template ({z} {x} {y}, optional {s} {q} {r} {key}), an xyzservices name "
        "(e.g. Esri.WorldImagery) or 'google' (Static Maps API, scale 2, logo strip cropped)",
    )
    p.add_argument("--out", required=True, help="map folder to write (or resume)")
    p.add_argument("--key-file", help="file holding the API key (else $AEROLOC_TILE_KEY / $AEROLOC_GOOGLE_KEY)")
    p.add_argument("--key", "--api-key", action=_RefuseKey, help=argparse.SUPPRESS)
    p.add_argument("--workers", type=int, default=4, help="concurrent requests (default 4)")
    p.add_argument("--rate", type=float, default=8.0, help="max requests per second (default 8)")
    p.add_argument("--retries", type=int, default=6, help="attempts per tile (default 6)")
    p.add_argument("--timeout", type=float, default=30.0, help="read timeout per request in s (default 30)")
    p.add_argument("--retina", action="store_true", help="512 px tiles where the template has {r} (@2x)")
    p.add_argument("--max-tiles", type=int, default=50_000, help="refuse larger downloads (default 50000)")
    p.add_argument("--google-url", help="Static Maps endpoint (default the Google API; for proxies and tests)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args) -> int:
    import logging

    from aeroloc.core.errors import AerolocError
    from aeroloc.maps.download import RetryPolicy, download_map
    from aeroloc.maps.providers import bbox_around, read_key, resolve_provider

    if args.around:
        from aeroloc.core.queries import load_queries

        queries = load_queries(args.around, require_images=False)
        bbox = bbox_around([(q.lat, q.lon) for q in queries], args.margin_m)
    else:
        bbox = args.bbox
    if args.retries < 1 or args.timeout <= 0:
        raise AerolocError("--retries must be >= 1 and --timeout > 0")
    provider = resolve_provider(args.provider, retina=args.retina, google_url=args.google_url)
    key = read_key(provider, args.key_file)
    logging.getLogger("urllib3").setLevel(logging.WARNING)  # its debug lines carry full URLs
    policy = RetryPolicy(attempts=args.retries, read_timeout_s=args.timeout)
    report, manifest = download_map(
        args.out,
        bbox,
        args.zoom,
        provider,
        key=key,
        workers=args.workers,
        rate=args.rate,
        policy=policy,
        progress=not args.no_progress,
        max_tiles=args.max_tiles,
    )
    s, w, n, e = manifest["bounds"]
    print(f"{provider.name} zoom {args.zoom}: bounds S {s:.6f} W {w:.6f} N {n:.6f} E {e:.6f} -> {args.out}")
    print(report.summary())
    return 0 if manifest["complete"] else 1
