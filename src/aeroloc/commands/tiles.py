"""Cut a map into a tile database (tiles.csv with exact georeference + a reference to the map; tile images only
with --write-images) at a zoom and overlap."""

from __future__ import annotations


def add_map_grid_arguments(p):
    p.add_argument("map", help="GeoTIFF, seed tile folder (map_metadata.txt), XYZ folder or aeroloc map folder")
    p.add_argument("--zoom", type=float, default=1.0, help="scale vs the base tile: 2 = half the side (default 1)")
    p.add_argument("--overlap", type=float, default=0.0, help="overlap between neighbours in [0, 1) (default 0)")
    p.add_argument("--tile-m", type=float, help="base tile side in metres for GeoTIFFs (default 256 map px)")
    p.add_argument(
        "--write-images",
        action="store_true",
        help="also write every tile as a PNG to images/ (to look at them; tiles are read from the map otherwise)",
    )


def add_arguments(p):
    add_map_grid_arguments(p)
    p.add_argument("--out", required=True, help="output folder (tiles.csv, tiles.json[, images/])")


def run(args) -> int:
    from aeroloc.maps.tiling import write_tiles

    report = write_tiles(
        args.map, args.out, args.zoom, args.overlap, args.tile_m, progress=True, write_images=args.write_images
    )
    print(summary(report, args.out))
    return 0


def summary(report, out) -> str:
    """One line about a :class:`~aeroloc.maps.tiling.TilesReport`: ``N tiles (R rows x C cols) of S px …``
    (``W``x``H`` px for rectangular tiles)."""
    g, m = report.grid, report.map
    (w, h), (sx, sy) = report.tile_px, report.step_px
    res = m["resolution_m"]
    if w == h and sx == sy:
        size, size_m, step = f"{w} px", f"~{w * res:.0f} m", f"{sx} px"
    else:
        size, size_m, step = f"{w}x{h} px", f"~{w * res:.0f}x{h * res:.0f} m", f"{sx}x{sy} px"
    cached = " (cached)" if report.cached else f" in {report.build_s or 0:.2f} s"
    return (
        f"{report.n_tiles} tiles ({g['n_rows']} rows x {g['n_cols']} cols) of {size} "
        f"({size_m}), step {step}, zoom {g['zoom']:g}, overlap {g['overlap']:g}; "
        f"map {m['width']}x{m['height']} px at {res:.2f} m/px fully covered; "
        + (f"{(report.image_bytes or 0) / 1e6:.1f} MB of images" if report.images else "tiles read from the map")
        + f"{cached} -> {out}"
    )
