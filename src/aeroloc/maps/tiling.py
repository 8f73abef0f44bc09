"""Cut a map into a tile database at any zoom and overlap, with exact georeference per tile.

Zoom is the scale relative to the map's base tile, per axis: a tile is ``round(base_w / zoom)`` x
``round(base_h / zoom)`` map pixels (zoom 2 -> half of each side, 0.5 -> twice). The base is the raw tile size
(width x height) for tile-folder maps, so rectangular raw tiles (the seed's 1280x1230) give rectangular tiles
and zoom 1 without overlap gives exactly the raw tiles; it is a square of ``tile_m`` metres when given, and of
``DEFAULT_BASE_PX`` (256 map pixels, one web tile) for GeoTIFFs otherwise. Overlap o in [0, 1) sets the step
along each axis, ``round(side * (1 - o))`` of that axis's side. Every map pixel is covered: the last
row/column is snapped to the map edge (it overlaps its neighbour a bit more) rather than dropped. A tile's
corners are the outer pixel edges.
"""

from __future__ import annotations

import csv
import io
import json
import shutil
import time
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from affine import Affine

from aeroloc.core import geo
from aeroloc.core.errors import AerolocError
from aeroloc.core.io import atomic_path
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
    """A window of the map (square unless the raw tiles are not). ``transform`` maps the tile's own pixels to
    the map CRS."""

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
    """The tiles of ``map`` at ``zoom`` and ``overlap`` (see the module docstring for the rules).

    ``tile_w`` x ``tile_h`` is the tile size and ``step_x``/``step_y`` the steps in map pixels; ``side`` and
    ``step`` are the same numbers for square tiles (rectangular grids have no single side).
    """

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
        self.tile_m = tile_m
        self.base_w, self.base_h = _base_size(map_, tile_m, base_px)
        self.tile_w = max(1, int(round(self.base_w / self.zoom)))
        self.tile_h = max(1, int(round(self.base_h / self.zoom)))
        if self.tile_w > map_.width or self.tile_h > map_.height:
            raise AerolocError(
                f"{map_.path}: tiles of {self._size_text()} px (zoom {zoom}, base {self._base_text()} px) are larger "
                f"than the {map_.width}x{map_.height} map; use a higher zoom or a smaller --tile-m"
            )
        self.step_x = max(1, int(round(self.tile_w * (1 - self.overlap))))
        self.step_y = max(1, int(round(self.tile_h * (1 - self.overlap))))
        self.cols = axis_starts(map_.width, self.tile_w, self.step_x)
        self.rows = axis_starts(map_.height, self.tile_h, self.step_y)

    @property
    def square(self) -> bool:
        return self.base_w == self.base_h

    @property
    def base_px(self) -> float:
        """The square base side (square grids only)."""
        return self._one("base_px", self.base_w)

    @property
    def side(self) -> int:
        """The square tile side (square grids only; see ``tile_w``/``tile_h``)."""
        return self._one("side", self.tile_w)

    @property
    def step(self) -> int:
        """The step along both axes (square grids only; see ``step_x``/``step_y``)."""
        return self._one("step", self.step_x)

    def _one(self, name: str, value):
        if not self.square:
            raise AerolocError(f"{self.map.path}: {name}: the tiles are {self._size_text()} px, not square")
        return value

    def _size_text(self) -> str:
        return f"{self.tile_w}" if self.square else f"{self.tile_w}x{self.tile_h}"

    def _base_text(self) -> str:
        return f"{self.base_w:.0f}" if self.square else f"{self.base_w:.0f}x{self.base_h:.0f}"

    def __len__(self) -> int:
        return len(self.cols) * len(self.rows)

    def __iter__(self):
        return (self[k] for k in range(len(self)))

    def __getitem__(self, k: int) -> Tile:
        """Tile ``k`` in row-major order (the tiles.csv order), without making the others."""
        if not 0 <= k < len(self):
            raise IndexError(k)
        i, j = divmod(k, len(self.cols))
        c, r = self.cols[j], self.rows[i]
        name = f"r{i:03d}c{j:03d}"
        return Tile(
            name, c, r, self.tile_w, self.tile_h, shifted(self.map.transform, c, r), self.map.crs, f"images/{name}.png"
        )

    def csv_chunks(self, tiles_per_chunk: int = 65_536) -> Iterator[str]:
        """The text of tiles.csv (header first), a block of grid rows at a time: the bytes csv.writer gives for
        ``tile_table(list(self))`` (tested), without a Tile, a dict or a list per window, and in memory one block
        at a time (a country grid has 10^7 rows). Each tile's transform offset and corners are the same float
        arithmetic as :func:`shifted` and :func:`_table`, done on arrays, and every number is formatted once per
        distinct value (north-up, a transform offset repeats along its grid column or row)."""
        t, n_cols = self.map.transform, len(self.cols)
        crs = _csv_cell(self.map.crs)
        a, b, d, e = (repr(float(v)) for v in (t.a, t.b, t.d, t.e))
        size = f"{self.tile_w},{self.tile_h}"
        cid = [f"c{j:03d}" for j in range(n_cols)]
        ccell = [str(int(c)) for c in self.cols]
        cols = np.asarray(self.cols, float)
        w, h = float(self.tile_w), float(self.tile_h)
        yield ",".join(CSV_COLUMNS) + "\r\n"
        step = max(1, tiles_per_chunk // n_cols)
        for i0 in range(0, len(self.rows), step):
            i1 = min(i0 + step, len(self.rows))
            n = (i1 - i0) * n_cols
            col = np.tile(cols, i1 - i0)
            row = np.repeat(np.asarray(self.rows[i0:i1], float), n_cols)
            c = t.a * col + t.b * row + t.c
            f = t.d * col + t.e * row + t.f
            zero = np.zeros(n)
            xs = np.concatenate([t.a * zero + t.b * zero + c, t.a * w + t.b * h + c])
            ys = np.concatenate([t.d * zero + t.e * zero + f, t.d * w + t.e * h + f])
            lat, lon = geo.crs_to_latlon(xs, ys, self.map.crs)
            lat, lon = np.asarray(lat, float).reshape(2, -1, n_cols), np.asarray(lon, float).reshape(2, -1, n_cols)
            nine = "{:.9f}".format
            cells = [_cells(x, nine) for x in (lat[0], lon[0], lat[1], lon[1])]
            cells += [_cells(c.reshape(-1, n_cols), repr), _cells(f.reshape(-1, n_cols), repr)]
            ids = [f"r{i:03d}{x}" for i in range(i0, i1) for x in cid]
            rcell = [x for i in range(i0, i1) for x in [str(int(self.rows[i]))] * n_cols]
            lines = [
                f"{t_id},images/{t_id}.png,{tl_lat},{tl_lon},{br_lat},{br_lon},{size},{cc},{rc},{crs},{a},{b},{c_},"
                f"{d},{e},{f_}\r\n"
                for t_id, tl_lat, tl_lon, br_lat, br_lon, c_, f_, cc, rc in zip(ids, *cells, ccell * (i1 - i0), rcell)
            ]
            yield "".join(lines)

    def params(self) -> dict:
        """The grid as tiles.json holds it. Square grids keep the one-side keys (``base_px``, ``side_px``,
        ``step_px``); rectangular ones give each axis (``base_px`` [w, h], ``width_px``, ``height_px``,
        ``step_x_px``, ``step_y_px``)."""
        if self.square:
            size = {"base_px": self.base_w, "side_px": self.tile_w, "step_px": self.step_x}
        else:
            size = {
                "base_px": [self.base_w, self.base_h],
                "width_px": self.tile_w,
                "height_px": self.tile_h,
                "step_x_px": self.step_x,
                "step_y_px": self.step_y,
            }
        return {
            "zoom": self.zoom,
            "overlap": self.overlap,
            "tile_m": self.tile_m,
            **size,
            "n_rows": len(self.rows),
            "n_cols": len(self.cols),
        }


def _base_size(map_: Map, tile_m: float | None, base_px: float | None) -> tuple[float, float]:
    """(width, height) of the zoom-1 tile in map pixels: ``base_px`` if given, else a square of ``tile_m``
    metres, else the map's raw tile size (tile folders), else ``DEFAULT_BASE_PX``."""
    if base_px is not None:
        return float(base_px), float(base_px)
    if tile_m is not None:
        side = tile_m / map_.resolution_m
        return float(side), float(side)
    if map_.base_tile_size is not None:
        w, h = map_.base_tile_size
        return float(w), float(h)
    return float(DEFAULT_BASE_PX), float(DEFAULT_BASE_PX)


def shifted(t: Affine, col: int, row: int) -> Affine:
    """``t`` composed with a translation by (col, row) pixels (spelled out: affine 3 deprecates ``*``)."""
    return Affine(t.a, t.b, t.a * col + t.b * row + t.c, t.d, t.e, t.d * col + t.e * row + t.f)


def _csv_cell(text: str) -> str:
    """``text`` as csv.writer writes it in a row of several cells (quoted if it holds a comma, quote or line
    break: a WKT CRS does)."""
    if not text:
        return ""
    buf = io.StringIO()
    csv.writer(buf).writerow([text])
    return buf.getvalue()[:-2]


def _cells(v: np.ndarray, fmt) -> list[str]:
    """``fmt`` of each value of the (rows, cols) array ``v`` in row-major order, formatted once per grid column
    when every row holds the same values (bit for bit: 0.0 and -0.0 differ), once per row when every column
    does, else once per value."""
    bits = v.view(np.uint64)
    if (bits == bits[:1]).all():
        return [fmt(x) for x in v[0].tolist()] * len(v)
    if (bits == bits[:, :1]).all():
        return [s for x in v[:, 0].tolist() for s in [fmt(x)] * v.shape[1]]
    return [fmt(x) for x in v.ravel().tolist()]


# --- on-disk tile database ---------------------------------------------------------------------------------
def tile_row(t: Tile, corners=None) -> dict:
    """The tiles.csv row of ``t`` (``corners``: its ``corners_latlon`` when already computed)."""
    (tl_lat, tl_lon), (br_lat, br_lon) = corners or t.corners_latlon
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


def tile_rows(tiles: list[Tile]) -> list[dict]:
    """``tile_row`` of many tiles (see :func:`tile_table`), as dicts keyed by ``CSV_COLUMNS``."""
    return [dict(zip(CSV_COLUMNS, r)) for r in tile_table(tiles)]


def tile_table(tiles: list[Tile]) -> list[list]:
    """The tiles.csv rows of ``tiles`` as lists in ``CSV_COLUMNS`` order, with one coordinate transformation
    for all corners (the same numbers as ``tile_row``: the same affine arithmetic per element, one pyproj call
    instead of one per tile, ~1 ms each) and no per-tile dict: a country grid has 10^7 rows."""
    if not tiles:
        return []
    crs = {t.crs for t in tiles}
    if len(crs) != 1:
        return [[r[k] for k in CSV_COLUMNS] for r in map(tile_row, tiles)]
    tr = np.array(
        [(t.transform.a, t.transform.b, t.transform.c, t.transform.d, t.transform.e, t.transform.f) for t in tiles]
    )
    w = np.array([t.width for t in tiles], float)
    h = np.array([t.height for t in tiles], float)
    fixed = [(t.width, t.height, t.col, t.row, t.crs) for t in tiles]
    return _table([t.id for t in tiles], [t.path for t in tiles], tr, w, h, fixed, crs.pop())


def _table(ids, paths, tr: np.ndarray, w: np.ndarray, h: np.ndarray, fixed, crs: str) -> list[list]:
    """tiles.csv rows from the tiles' columns: ``tr`` (n, 6) transforms, ``w``/``h`` sizes and ``fixed`` the
    (width, height, col, row, crs) cells; the corners' lat/lon in one pyproj call."""
    a, b, c, d, e, f = tr.T
    zero = np.zeros(len(ids))
    xs = np.concatenate([a * zero + b * zero + c, a * w + b * h + c])
    ys = np.concatenate([d * zero + e * zero + f, d * w + e * h + f])
    lat, lon = geo.crs_to_latlon(xs, ys, crs)
    n = len(ids)
    lat, lon, coefs = np.asarray(lat, float).tolist(), np.asarray(lon, float).tolist(), tr.tolist()
    return [
        [ids[i], paths[i], f"{lat[i]:.9f}", f"{lon[i]:.9f}", f"{lat[n + i]:.9f}", f"{lon[n + i]:.9f}", *fixed[i]]
        + [repr(v) for v in coefs[i]]
        for i in range(n)
    ]


def write_grid_csv(path: Path, grid: TileGrid) -> None:
    """tiles.csv of ``grid`` from :meth:`TileGrid.csv_chunks`, renamed into place when complete."""
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        for chunk in grid.csv_chunks():
            f.write(chunk)


def write_tiles_csv(path: Path, table: list[list]) -> None:
    """tiles.csv from ``tile_table`` rows (a plain csv writer: the same bytes as a DictWriter of the dicts),
    renamed into place when complete."""
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(CSV_COLUMNS)
        w.writerows(table)


@dataclass(frozen=True)
class TilesReport:
    """What ``write_tiles`` built (or found cached): the map, the grid and the cost. ``to_json()`` is the
    content of ``tiles.json`` (``cached`` is not stored: it says whether this call rendered anything)."""

    map: dict  # Map.describe()
    grid: dict  # TileGrid.params()
    n_tiles: int
    format: int = 2  # 1: tiles were always images; 2: tiles are windows of the map, images only if asked
    build_s: float | None = None  # seconds spent rendering (of the build that wrote tiles.json)
    image_bytes: int | None = None  # total size of the tile images
    images: bool = True  # images/ holds every tile (format 1 always did)
    cached: bool = False

    @property
    def tile_px(self) -> tuple[int, int]:
        """(width, height) of every tile in map pixels."""
        g = self.grid
        return (g["side_px"], g["side_px"]) if "side_px" in g else (g["width_px"], g["height_px"])

    @property
    def step_px(self) -> tuple[int, int]:
        """(x, y) step between neighbouring tiles in map pixels."""
        g = self.grid
        return (g["step_px"], g["step_px"]) if "step_px" in g else (g["step_x_px"], g["step_y_px"])

    def to_json(self) -> dict:
        d = {"map": self.map, "grid": self.grid, "n_tiles": self.n_tiles, "format": self.format, "images": self.images}
        if self.build_s is not None:
            d["build_s"] = self.build_s
        if self.image_bytes is not None:
            d["image_bytes"] = self.image_bytes
        return d

    @classmethod
    def from_json(cls, d: dict, cached: bool = False) -> TilesReport:
        return cls(
            map=d["map"],
            grid=d["grid"],
            n_tiles=int(d["n_tiles"]),
            format=int(d.get("format", 1)),
            build_s=d.get("build_s"),
            image_bytes=d.get("image_bytes"),
            images=bool(d.get("images", True)),
            cached=cached,
        )


def write_tiles(
    map_path, out_dir, zoom=1.0, overlap=0.0, tile_m=None, progress=True, write_images: bool = False
) -> TilesReport:
    """Write ``tiles.csv`` + ``tiles.json`` (the grid and a reference to the map, see
    :func:`aeroloc.maps.windows.map_reference`); with ``write_images`` also every tile to ``out_dir/images``.

    Tiles are windows of the map: later stages read their pixels from it, so without images this costs the
    georeference of each tile, not a PNG encode. Resumable: tile images already on disk are kept (each is written
    atomically), and an existing database with the same map and parameters is a cache hit. ``tiles.csv`` is
    written last, so a half-built folder is never taken for a complete one.
    """
    from aeroloc.maps.windows import CONTENT_KEY, map_reference

    m = map_path if isinstance(map_path, Map) else open_map(map_path)
    grid = TileGrid(m, zoom, overlap, tile_m)
    out = Path(out_dir)
    report = TilesReport(map=m.describe(), grid=grid.params(), n_tiles=len(grid), images=write_images)
    done = _existing(out, report)
    if done is not None:
        return done
    for stale in (out / TILES_CSV, out / TILES_JSON):
        stale.unlink(missing_ok=True)
    t0 = time.perf_counter()
    if write_images:
        _discard_other_partial_build(out, report)
        (out / "images").mkdir(parents=True, exist_ok=True)
        (out / BUILDING_JSON).write_text(json.dumps(_build_key(report)))
        rows, nbytes = _render(m, list(grid), out, progress)
    else:
        out.mkdir(parents=True, exist_ok=True)
        rows, nbytes = None, 0
    report = replace(
        report,
        map={**report.map, CONTENT_KEY: map_reference(m, grid)[CONTENT_KEY]},
        build_s=round(time.perf_counter() - t0, 3),
        image_bytes=nbytes,
    )
    (out / TILES_JSON).write_text(json.dumps(report.to_json(), indent=1))
    if rows is None:  # last: its presence marks a finished tile set
        write_grid_csv(out / TILES_CSV, grid)
    else:
        write_tiles_csv(out / TILES_CSV, rows)
    (out / BUILDING_JSON).unlink(missing_ok=True)
    return report


def _render(m: Map, tiles: list[Tile], out: Path, progress: bool) -> tuple[list[list], int]:
    """Write the images not on disk yet; the tiles.csv rows and the total image bytes."""
    from tqdm import tqdm

    from aeroloc.core.images import write_image

    rows, nbytes = [], 0
    for tile in tqdm(tiles, desc="tiles", unit="tile", disable=not progress, leave=False):
        p = out / tile.path
        if not p.is_file():
            rgb, _ = m.read(tile.col, tile.row, tile.width, tile.height)
            write_image(p, rgb)
        nbytes += p.stat().st_size
        row = tile_row(tile)
        rows.append([row[k] for k in CSV_COLUMNS])
    return rows, nbytes


def _build_key(report: TilesReport) -> dict:
    return {"grid": report.grid, "map_path": report.map["path"], "transform": report.map["transform"]}


def _discard_other_partial_build(out: Path, report: TilesReport) -> None:
    """Images left by an interrupted build are reused only when it was building this same configuration."""
    if not (out / "images").is_dir():
        return
    try:
        same = json.loads((out / BUILDING_JSON).read_text()) == json.loads(json.dumps(_build_key(report)))
    except (OSError, json.JSONDecodeError):
        same = False
    if not same:
        shutil.rmtree(out / "images")


def _existing(out: Path, report: TilesReport) -> TilesReport | None:
    meta = out / TILES_JSON
    if not (meta.is_file() and (out / TILES_CSV).is_file()):
        return None
    try:
        old = json.loads(meta.read_text())
    except json.JSONDecodeError:
        return None
    same = (
        old.get("grid") == report.grid
        and old.get("map", {}).get("path") == report.map["path"]
        and old.get("map", {}).get("transform") == report.map["transform"]
        and (old.get("images", True) or not report.images)  # images asked for and missing: render them
    )
    if same:
        try:
            return TilesReport.from_json(old, cached=True)
        except (KeyError, TypeError, ValueError):
            pass  # an unreadable tiles.json: rebuild
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


__all__ = [
    "Tile",
    "TileGrid",
    "TilesReport",
    "axis_starts",
    "load_info",
    "load_tiles",
    "tile_count",
    "write_tiles",
]
