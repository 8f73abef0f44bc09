"""Cut a map into a tile database (images + tiles.csv with exact georeference) at a zoom and overlap."""

from __future__ import annotations


def add_map_grid_arguments(p):
    p.add_argument("map", help="GeoTIFF, seed tile folder (map_metadata.txt), XYZ folder or aeroloc map folder")
    p.add_argument("--zoom", type=float, default=1.0, help="scale vs the base tile: 2 = half the side (default 1)")
    p.add_argument("--overlap", type=float, default=0.0, help="overlap between neighbours in [0, 1) (default 0)")
    p.add_argument("--tile-m", type=float, help="base tile side in metres for GeoTIFFs (default 256 map px)")


def add_arguments(p):
    add_map_grid_arguments(p)
    p.add_argument("--out", required=True, help="output folder (tiles.csv, tiles.json, images/)")


def run(args) -> int:
    from aeroloc.maps.tiling import write_tiles

    info = write_tiles(args.map, args.out, args.zoom, args.overlap, args.tile_m, progress=True)
    print(summary(info, args.out))
    return 0


def summary(info: dict, out) -> str:
    g, m = info["grid"], info["map"]
    side_m = g["side_px"] * m["resolution_m"]
    cached = " (cached)" if info.get("cached") else f" in {info.get('build_s', 0):.2f} s"
    return (
        f"{info['n_tiles']} tiles ({g['n_rows']} rows x {g['n_cols']} cols) of {g['side_px']} px "
        f"(~{side_m:.0f} m), step {g['step_px']} px, zoom {g['zoom']:g}, overlap {g['overlap']:g}; "
        f"map {m['width']}x{m['height']} px at {m['resolution_m']:.2f} m/px fully covered; "
        f"{info.get('image_bytes', 0) / 1e6:.1f} MB of images{cached} -> {out}"
    )
