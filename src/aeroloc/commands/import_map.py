"""Import a GeoTIFF/COG orthophoto (any CRS) as a map folder: MAPDIR/map.tif (tiled COG) + manifest.json."""

from __future__ import annotations


def add_arguments(p):
    p.add_argument("ortho", metavar="ORTHO.tif", help="georeferenced raster (GeoTIFF, COG or any GDAL format)")
    p.add_argument("--out", required=True, help="map folder to write")
    p.add_argument("--to-webmercator", action="store_true", help="reproject to EPSG:3857 (Web Mercator)")
    p.add_argument(
        "--resampling", default="bilinear", help="for --to-webmercator: nearest, bilinear (default), cubic, lanczos"
    )


def run(args) -> int:
    from aeroloc.maps.orthophoto import import_orthophoto

    info = import_orthophoto(args.ortho, args.out, args.to_webmercator, args.resampling)
    s, w, n, e = info["bounds"]
    print(
        f"{args.ortho} ({info['source_crs']}) -> {args.out}/{info['file']}: {info['width']}x{info['height']} px "
        f"in {info['crs']} at {info['resolution_m']:.2f} m/px, bounds S {s:.6f} W {w:.6f} N {n:.6f} E {e:.6f}"
    )
    return 0
