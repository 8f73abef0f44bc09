"""Cut a map into a tile database at any zoom and overlap, with exact georeference per tile.

Zoom is the scale relative to the map's base tile: ``side = round(base / zoom)`` map pixels (zoom 2 -> half the
side, 0.5 -> twice). The base is the raw tile size for tile-folder maps, ``tile_m`` metres when given, and
``DEFAULT_BASE_PX`` (256 map pixels, one web tile) for GeoTIFFs otherwise. Overlap o in [0, 1) sets the step
``round(side * (1 - o))``. Every map pixel is covered: the last row/column is snapped to the map edge (it
overlaps its neighbour a bit more) rather than dropped. A tile's corners are the outer pixel edges.
"""

from __future__ import annotations

import csv
import json
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from affine import Affine

from aeroloc.core import geo
from aeroloc.core.errors import AerolocError
from aeroloc.core.io import write_csv_atomic
from aeroloc.maps.sources import Map, open_map

DEFAULT_BASE_PX = 256
TILES_CSV = "tiles.csv"
TILES_JSON = "tiles.json"
BUILDING_JSON = "building.json"  # the configuration whose images/ are being rendered (absent once complete)
CSV_COLUMNS = [
    "tile",
    "path",
    "tl_lat",
    "tl_lon",
    "br_lat",
    "br_lon",
    "width",
    "height",
    "col",
    "row",
    "crs",
    "a",
    "b",
    "c",
    "d",
    "e",
    "f",
]


@dataclass(frozen=True)
class Tile:
    """A square window of the map. ``transform`` maps the tile's own pixels to the map CRS."""

    id: str
    col: int  # window in map pixels
    row: int
    width: int
    height: int
    transform: Affine
    crs: str
    path: str = ""  # image file relative to the database folder (once rendered)

    def pixel_to_latlon(self, x, y):
        """Tile pixel (x right, y down; 0,0 = outer top-left corner) -> (lat, lon); no clamping."""
        wx, wy = geo.pixel_to_world(self.transform, x, y)
        return geo.crs_to_latlon(wx, wy, self.crs)

    def latlon_to_pixel(self, lat, lon):
        wx, wy = geo.latlon_to_crs(lat, lon, self.crs)
        return geo.world_to_pixel(self.transform, wx, wy)

    @property
    def corners_latlon(self):
        """((tl_lat, tl_lon), (br_lat, br_lon)) of the outer pixel edges."""
        lat, lon = self.pixel_to_latlon([0, self.width], [0, self.height])
        return (float(lat[0]), float(lon[0])), (float(lat[1]), float(lon[1]))

    @property
    def centre_latlon(self):
        lat, lon = self.pixel_to_latlon(self.width / 2, self.height / 2)
        return float(lat), float(lon)


def axis_starts(length: int, side: int, step: int) -> list[int]:
    """Window starts along one axis: 0, step, 2 step … and the last one snapped to ``length - side``."""
    if side > length:
        raise AerolocError(f"tile side {side} px is larger than the map ({length} px)")
    starts = list(range(0, length - side + 1, step))
    if starts[-1] + side < length:
        starts.append(length - side)
    return starts


def tile_count(length: int, side: int, step: int) -> int:
    """Closed form of ``len(axis_starts(...))``: 1 + ceil((length - side) / step)."""
    return 1 + -(-(length - side) // step)


class TileGrid:
    """The tiles of ``map`` at ``zoom`` and ``overlap`` (see the module docstring for the rules)."""

    def __init__(
        self,
        map_: Map,
        zoom: float = 1.0,
        overlap: float = 0.0,
        tile_m: float | None = None,
        base_px: int | None = None,
    ):
        if not (isinstance(zoom, (int, float)) and np.isfinite(zoom) and zoom > 0):
            raise AerolocError(f"zoom must be > 0, got {zoom}")
        if not (isinstance(overlap, (int, float)) and 0 <= overlap < 1):
            raise AerolocError(f"overlap must be in [0, 1), got {overlap}")
        if tile_m is not None and not tile_m > 0:
            raise AerolocError(f"--tile-m must be > 0, got {tile_m}")
        self.map, self.zoom, self.overlap = map_, float(zoom), float(overlap)
        if base_px is None:
            if tile_m is not None:
                base_px = tile_m / map_.resolution_m
            else:
                base_px = map_.base_tile_px or DEFAULT_BASE_PX
        self.base_px = float(base_px)
        self.tile_m = tile_m
        self.side = max(1, int(round(self.base_px / self.zoom)))
        if self.side > min(map_.width, map_.height):
            raise AerolocError(
                f"{map_.path}: tiles of {self.side} px (zoom {zoom}, base {self.base_px:.0f} px) are larger than "
                f"the {map_.width}x{map_.height} map; use a higher zoom or a smaller --tile-m"
            )
        self.step = max(1, int(round(self.side * (1 - self.overlap))))
        self.cols = axis_starts(map_.width, self.side, self.step)
        self.rows = axis_starts(map_.height, self.side, self.step)

    def __len__(self) -> int:
        return len(self.cols) * len(self.rows)

    def __iter__(self):
        t = self.map.transform
        for i, r in enumerate(self.rows):
            for j, c in enumerate(self.cols):
                yield Tile(
                    id=f"r{i:03d}c{j:03d}",
                    col=c,
                    row=r,
                    width=self.side,
                    height=self.side,
                    transform=shifted(t, c, r),
                    crs=self.map.crs,
                    path=f"images/r{i:03d}c{j:03d}.png",
                )

    def params(self) -> dict:
        return {
            "zoom": self.zoom,
            "overlap": self.overlap,
            "tile_m": self.tile_m,
            "base_px": self.base_px,
            "side_px": self.side,
            "step_px": self.step,
            "n_rows": len(self.rows),
            "n_cols": len(self.cols),
        }


def shifted(t: Affine, col: int, row: int) -> Affine:
    """``t`` composed with a translation by (col, row) pixels (spelled out: affine 3 deprecates ``*``)."""
    return Affine(t.a, t.b, t.a * col + t.b * row + t.c, t.d, t.e, t.d * col + t.e * row + t.f)


# --- on-disk tile database ---------------------------------------------------------------------------------
def tile_row(t: Tile) -> dict:
    (tl_lat, tl_lon), (br_lat, br_lon) = t.corners_latlon
    a, b, c, d, e, f = list(t.transform)[:6]
    return {
        "tile": t.id,
        "path": t.path,
        "tl_lat": f"{tl_lat:.9f}",
        "tl_lon": f"{tl_lon:.9f}",
        "br_lat": f"{br_lat:.9f}",
        "br_lon": f"{br_lon:.9f}",
        "width": t.width,
        "height": t.height,
        "col": t.col,
        "row": t.row,
        "crs": t.crs,
        "a": repr(a),
        "b": repr(b),
        "c": repr(c),
        "d": repr(d),
        "e": repr(e),
        "f": repr(f),
    }


def write_tiles(map_path, out_dir, zoom=1.0, overlap=0.0, tile_m=None, progress=True) -> dict:
    """Render every tile once to ``out_dir/images`` and write ``tiles.csv`` + ``tiles.json`` last.

    Resumable: tile images already on disk are kept (each is written atomically), and an existing database
    with the same map and parameters is a cache hit. ``tiles.csv`` appears only when every image is there,
    so a half-built folder is never taken for a complete one.
    """
    from tqdm import tqdm

    from aeroloc.core.images import write_image

    m = map_path if isinstance(map_path, Map) else open_map(map_path)
    grid = TileGrid(m, zoom, overlap, tile_m)
    out = Path(out_dir)
    info = {"map": m.describe(), "grid": grid.params(), "n_tiles": len(grid), "format": 1}
    done = _existing(out, info)
    if done is not None:
        return done
    _discard_other_partial_build(out, info)
    (out / "images").mkdir(parents=True, exist_ok=True)
    for stale in (out / TILES_CSV, out / TILES_JSON):
        stale.unlink(missing_ok=True)
    (out / BUILDING_JSON).write_text(json.dumps(_build_key(info)))
    t0 = time.perf_counter()
    rows, nbytes = [], 0
    for tile in tqdm(list(grid), desc="tiles", unit="tile", disable=not progress, leave=False):
        p = out / tile.path
        if not p.is_file():
            rgb, _ = m.read(tile.col, tile.row, tile.width, tile.height)
            write_image(p, rgb)
        nbytes += p.stat().st_size
        rows.append(tile_row(tile))
    info.update(build_s=round(time.perf_counter() - t0, 3), image_bytes=nbytes)
    (out / TILES_JSON).write_text(json.dumps(info, indent=1))
    write_csv_atomic(out / TILES_CSV, CSV_COLUMNS, rows)  # last: its presence marks a finished tile set
    (out / BUILDING_JSON).unlink(missing_ok=True)
    return info


def _build_key(info: dict) -> dict:
    return {"grid": info["grid"], "map_path": info["map"]["path"], "transform": info["map"]["transform"]}


def _discard_other_partial_build(out: Path, info: dict) -> None:
    """Images left by an interrupted build are reused only when it was building this same configuration."""
    if not (out / "images").is_dir():
        return
    try:
        same = json.loads((out / BUILDING_JSON).read_text()) == json.loads(json.dumps(_build_key(info)))
    except (OSError, json.JSONDecodeError):
        same = False
    if not same:
        shutil.rmtree(out / "images")


def _existing(out: Path, info: dict) -> dict | None:
    meta = out / TILES_JSON
    if not (meta.is_file() and (out / TILES_CSV).is_file()):
        return None
    try:
        old = json.loads(meta.read_text())
    except json.JSONDecodeError:
        return None
    same = (
        old.get("grid") == info["grid"]
        and old.get("map", {}).get("path") == info["map"]["path"]
        and old.get("map", {}).get("transform") == info["map"]["transform"]
    )
    if same:
        return {**old, "cached": True}
    if (out / "images").is_dir():  # another configuration lives here: start afresh
        shutil.rmtree(out / "images")
    return None


def load_tiles(db_dir) -> list[Tile]:
    """Read ``DIR/tiles.csv`` back into tiles with their exact transforms."""
    db_dir = Path(db_dir)
    p = db_dir / TILES_CSV
    if not p.is_file():
        raise AerolocError(f"{p}: tile database not found (build it with 'aeroloc tiles' or 'aeroloc build')")
    tiles = []
    with open(p, newline="") as f:
        reader = csv.DictReader(f)
        missing = {"tile", "tl_lat", "tl_lon", "br_lat", "br_lon"} - set(reader.fieldnames or [])
        if missing:
            raise AerolocError(f"{p}: missing columns {sorted(missing)}")
        for i, r in enumerate(reader, start=2):
            try:
                if r.get("a"):
                    tr = Affine(*(float(r[k]) for k in "abcdef"))
                    tiles.append(
                        Tile(
                            r["tile"],
                            int(r["col"]),
                            int(r["row"]),
                            int(r["width"]),
                            int(r["height"]),
                            tr,
                            r["crs"],
                            r.get("path", ""),
                        )
                    )
                else:
                    tiles.append(_tile_from_corners(r))
            except (ValueError, KeyError) as exc:
                raise AerolocError(f"{p}:{i}: bad row ({exc})") from None
    return tiles


def _tile_from_corners(r: dict) -> Tile:
    """Tiles listed only by corners (other tools' tiles.csv): a Web Mercator georeference from the corners."""
    w, h = int(r.get("width") or 1), int(r.get("height") or 1)
    x0, y0 = geo.mercator_from_latlon(float(r["tl_lat"]), float(r["tl_lon"]))
    x1, y1 = geo.mercator_from_latlon(float(r["br_lat"]), float(r["br_lon"]))
    tr = Affine((float(x1) - float(x0)) / w, 0, float(x0), 0, (float(y1) - float(y0)) / h, float(y0))
    return Tile(r["tile"], 0, 0, w, h, tr, geo.WEB_MERCATOR, r.get("path", ""))


def load_info(db_dir) -> dict:
    p = Path(db_dir) / TILES_JSON
    if not p.is_file():
        raise AerolocError(f"{p}: tile database metadata not found")
    return json.loads(p.read_text())


__all__ = ["Tile", "TileGrid", "axis_starts", "load_info", "load_tiles", "tile_count", "write_tiles"]
