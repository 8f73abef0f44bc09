"""A ``Map`` is a georeferenced raster: a pixel grid with a CRS and an affine transform (pixel -> CRS), from
which any pixel window can be read without loading the whole mosaic.

Sources:
- a GeoTIFF (any CRS) through rasterio; an alpha band / nodata becomes the valid mask;
- a folder of raw tiles with the seed's ``map_metadata.txt``
  (header, then ``filename top_left_lat top_left_lon bottom_right_lat bottom_right_lon``, row-major);
  tiles are Web Mercator images, so the mosaic's transform is affine in EPSG:3857;
- an XYZ folder ``{z}/{x}/{y}.png|jpg`` (Web Mercator, 256 px tiles or whatever size the files have);
- a map folder written by ``aeroloc download``/``import`` (``manifest.json`` names the layout).
Pixel coordinates: (col, row), (0, 0) is the outer top-left corner of the first pixel.
"""

from __future__ import annotations

import json
import os
import re
from collections import OrderedDict
from pathlib import Path

import numpy as np
from affine import Affine

from aeroloc.core import geo
from aeroloc.core.errors import AerolocError
from aeroloc.core.images import read_image

RASTER_SUFFIXES = {".tif", ".tiff", ".vrt", ".jp2", ".img"}


class Map:
    """Common georeferencing maths; subclasses implement ``_read`` and set the attributes below."""

    path: Path
    crs: str  # WKT or "EPSG:n"
    transform: Affine  # pixel (col, row) -> CRS (x, y)
    width: int
    height: int
    base_tile_px: int | None = None  # longer side of the raw tiles of tile-folder maps
    base_tile_size: tuple[int, int] | None = None  # (width, height) of those raw tiles: the zoom-1 tile

    def read(self, col: int, row: int, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """RGB uint8 (height x width x 3) and valid mask (bool) of a window inside the map."""
        if col < 0 or row < 0 or width <= 0 or height <= 0 or col + width > self.width or row + height > self.height:
            raise AerolocError(
                f"{self.path}: window col={col} row={row} {width}x{height} is outside the {self.width}x{self.height} map"
            )
        rgb, valid = self._read(int(col), int(row), int(width), int(height))
        rgb = np.where(valid[..., None], rgb, 0).astype(np.uint8)
        return rgb, valid

    def _read(self, col, row, width, height):  # pragma: no cover - abstract
        raise NotImplementedError

    # --- georeference -----------------------------------------------------------------------------------
    def pixel_to_latlon(self, col, row):
        x, y = geo.pixel_to_world(self.transform, col, row)
        return geo.crs_to_latlon(x, y, self.crs)

    def latlon_to_pixel(self, lat, lon):
        x, y = geo.latlon_to_crs(lat, lon, self.crs)
        return geo.world_to_pixel(self.transform, x, y)

    def contains_latlon(self, lat, lon) -> np.ndarray:
        c, r = self.latlon_to_pixel(lat, lon)
        eps = 1e-6  # pixels: a point on the edge stays inside despite round-trip float noise (inclusive)
        return (c >= -eps) & (c <= self.width + eps) & (r >= -eps) & (r <= self.height + eps)

    @property
    def resolution_m(self) -> float:
        """Ground size of one pixel at the map centre (geodesic, mean of x and y)."""
        cc, rr = self.width / 2, self.height / 2
        lat, lon = self.pixel_to_latlon([cc, cc + 1, cc], [rr, rr, rr + 1])
        dx = geo.geodesic_distance(lat[0], lon[0], lat[1], lon[1])
        dy = geo.geodesic_distance(lat[0], lon[0], lat[2], lon[2])
        return float((dx + dy) / 2)

    def bounds_latlon(self) -> tuple[float, float, float, float]:
        """(south, west, north, east) of the four corners."""
        lat, lon = self.pixel_to_latlon([0, self.width, 0, self.width], [0, 0, self.height, self.height])
        return float(np.min(lat)), float(np.min(lon)), float(np.max(lat)), float(np.max(lon))

    def describe(self) -> dict:
        return {
            "path": str(self.path),
            "kind": type(self).__name__,
            "crs": self.crs,
            "transform": list(self.transform)[:6],
            "width": self.width,
            "height": self.height,
            "base_tile_px": self.base_tile_px,
            "resolution_m": round(self.resolution_m, 4),
        }


class GeoTiffMap(Map):
    """A GeoTIFF/COG (or any raster GDAL reads) in its own CRS. The dataset is reopened per process so the
    map can be read from DataLoader workers."""

    def __init__(self, path: str | os.PathLike):
        import rasterio
        from rasterio.errors import RasterioIOError

        self.path = Path(path)
        if not self.path.is_file():
            raise AerolocError(f"{self.path}: map file not found")
        try:
            with rasterio.open(self.path) as ds:
                if ds.crs is None:
                    raise AerolocError(f"{self.path}: the raster has no coordinate reference system")
                self.crs = geo.parse_crs(ds.crs).to_string()
                self.transform = ds.transform
                self.width, self.height, self.count = ds.width, ds.height, ds.count
                self._alpha = 4 if ds.count >= 4 else None
                if ds.transform.is_identity:
                    raise AerolocError(f"{self.path}: the raster has no georeference (identity transform)")
        except RasterioIOError as exc:
            raise AerolocError(f"{self.path}: not a readable raster ({exc})") from None
        self._ds, self._pid = None, None

    def _dataset(self):
        import rasterio

        if self._ds is None or self._pid != os.getpid():
            self._ds, self._pid = rasterio.open(self.path), os.getpid()
        return self._ds

    def _read(self, col, row, width, height):
        from rasterio.windows import Window

        ds = self._dataset()
        win = Window(col, row, width, height)
        bands = [1, 2, 3] if self.count >= 3 else [1, 1, 1]
        data = ds.read(bands, window=win)
        rgb = _to_uint8(np.moveaxis(data, 0, -1))
        if self._alpha:
            valid = ds.read(self._alpha, window=win) > 0
        else:
            valid = ds.read_masks(1, window=win) > 0
        return rgb, valid

    def __getstate__(self):
        return {**self.__dict__, "_ds": None, "_pid": None}


def _to_uint8(a: np.ndarray) -> np.ndarray:
    if a.dtype == np.uint8:
        return a
    a = a.astype(np.float64)
    hi = np.percentile(a, 99.5) or 1.0
    return np.clip(a / hi * 255, 0, 255).astype(np.uint8)


class TileFolderMap(Map):
    """A mosaic of equally sized image tiles on a regular grid in Web Mercator (seed metadata or XYZ)."""

    def __init__(
        self,
        path,
        cells: dict[tuple[int, int], Path],
        n_rows: int,
        n_cols: int,
        tile_w: int,
        tile_h: int,
        transform: Affine,
    ):
        self.path = Path(path)
        self.crs = geo.WEB_MERCATOR
        self.cells, self.n_rows, self.n_cols = cells, n_rows, n_cols
        self.tile_w, self.tile_h = tile_w, tile_h
        self.width, self.height = n_cols * tile_w, n_rows * tile_h
        self.transform = transform
        self.base_tile_px = max(tile_w, tile_h)
        self.base_tile_size = (tile_w, tile_h)
        self._cache: OrderedDict = OrderedDict()

    def _tile(self, r: int, c: int):
        key = (r, c)
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        p = self.cells.get(key)
        if p is None:
            img, valid = np.zeros((self.tile_h, self.tile_w, 3), np.uint8), np.zeros((self.tile_h, self.tile_w), bool)
        else:
            img = read_image(p)
            if img.shape[:2] != (self.tile_h, self.tile_w):
                raise AerolocError(
                    f"{p}: tile is {img.shape[1]}x{img.shape[0]} px, expected "
                    f"{self.tile_w}x{self.tile_h} like the other tiles"
                )
            valid = np.ones(img.shape[:2], bool)
        self._cache[key] = (img, valid)
        if len(self._cache) > 64:
            self._cache.popitem(last=False)
        return img, valid

    def _read(self, col, row, width, height):
        out = np.zeros((height, width, 3), np.uint8)
        valid = np.zeros((height, width), bool)
        for r in range(row // self.tile_h, (row + height - 1) // self.tile_h + 1):
            for c in range(col // self.tile_w, (col + width - 1) // self.tile_w + 1):
                img, ok = self._tile(r, c)
                y0, x0 = r * self.tile_h, c * self.tile_w
                ys, xs = max(row, y0), max(col, x0)
                ye, xe = min(row + height, y0 + self.tile_h), min(col + width, x0 + self.tile_w)
                out[ys - row : ye - row, xs - col : xe - col] = img[ys - y0 : ye - y0, xs - x0 : xe - x0]
                valid[ys - row : ye - row, xs - col : xe - col] = ok[ys - y0 : ye - y0, xs - x0 : xe - x0]
        return out, valid

    def __getstate__(self):
        return {**self.__dict__, "_cache": OrderedDict()}


def _image_size(path: Path) -> tuple[int, int]:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            return im.size
    except (UnidentifiedImageError, OSError) as exc:
        raise AerolocError(f"{path}: not a readable image ({exc})") from None


def open_metadata_folder(folder: str | os.PathLike, metadata: str = "map_metadata.txt") -> TileFolderMap:
    """The seed's layout: ``map_metadata.txt`` rows (lat before lon) on a row-major grid."""
    folder = Path(folder)
    meta = folder / metadata
    if not meta.is_file():
        raise AerolocError(f"{meta}: metadata file not found")
    rows = []
    for i, line in enumerate(meta.read_text().splitlines()[1:], start=2):
        if not line.strip():
            continue
        parts = line.split()
        try:
            if len(parts) < 5:
                raise ValueError("missing columns")
            rows.append((parts[0], *map(float, parts[1:5])))
        except (ValueError, IndexError):
            raise AerolocError(f"{meta}:{i}: expected 'filename tl_lat tl_lon br_lat br_lon', got {line!r}") from None
    if not rows:
        raise AerolocError(f"{meta}: no tiles listed")
    first_lat = rows[0][1]
    n_cols = sum(1 for r in rows if abs(r[1] - first_lat) < 1e-9)
    if n_cols == 0 or len(rows) % n_cols:
        raise AerolocError(f"{meta}: {len(rows)} rows do not form a grid of {n_cols} columns")
    n_rows = len(rows) // n_cols
    grid = [rows[i * n_cols : (i + 1) * n_cols] for i in range(n_rows)]
    tol = 1e-7
    for ri, line in enumerate(grid):
        for ci, (name, tl_lat, tl_lon, br_lat, br_lon) in enumerate(line):
            ok = abs(tl_lat - grid[ri][0][1]) < tol and abs(tl_lon - grid[0][ci][2]) < tol
            ok &= tl_lat > br_lat and br_lon > tl_lon
            if ci:
                ok &= abs(tl_lon - line[ci - 1][4]) < tol
            if ri:
                ok &= abs(tl_lat - grid[ri - 1][ci][3]) < tol
            if not ok:
                raise AerolocError(
                    f"{meta}: tile {name} (row {ri}, column {ci}) breaks the row-major grid "
                    "(rows must run north to south, columns west to east, edges shared)"
                )
    tw, th = _image_size(folder / grid[0][0][0])
    x0, y0 = geo.mercator_from_latlon(grid[0][0][1], grid[0][0][2])
    x1, y1 = geo.mercator_from_latlon(grid[-1][-1][3], grid[-1][-1][4])
    W, H = n_cols * tw, n_rows * th
    transform = Affine((float(x1) - float(x0)) / W, 0, float(x0), 0, (float(y1) - float(y0)) / H, float(y0))
    _check_even_spacing(meta, grid, transform, tw, th)
    cells = {(ri, ci): folder / grid[ri][ci][0] for ri in range(n_rows) for ci in range(n_cols)}
    for p in cells.values():
        if not p.is_file():
            raise AerolocError(f"{p}: tile listed in {meta} not found")
    return TileFolderMap(folder, cells, n_rows, n_cols, tw, th, transform)


def _check_even_spacing(meta: Path, grid, transform: Affine, tw: int, th: int, tol_px: float = 0.5) -> None:
    """One affine transform georeferences the mosaic only if every tile spans the same Mercator extent."""
    inv = ~transform
    for ri, line in enumerate(grid):
        for ci, (name, tl_lat, tl_lon, br_lat, br_lon) in enumerate(line):
            x, y = geo.mercator_from_latlon([tl_lat, br_lat], [tl_lon, br_lon])
            cols, rows = geo.pixel_to_world(inv, x, y)
            err = np.abs(np.r_[cols - [ci * tw, (ci + 1) * tw], rows - [ri * th, (ri + 1) * th]]).max()
            if err > tol_px:
                raise AerolocError(
                    f"{meta}: tile {name} (row {ri}, column {ci}) is {err:.1f} px off an evenly "
                    "spaced grid (all tiles must span the same Web Mercator extent)"
                )


def open_xyz_folder(folder: str | os.PathLike, zoom: int | None = None) -> TileFolderMap:
    """An XYZ pyramid folder ``{z}/{x}/{y}.ext``; the covered x/y range of one zoom level becomes the mosaic."""
    folder = Path(folder)
    zooms = sorted(int(p.name) for p in folder.iterdir() if p.is_dir() and p.name.isdigit())
    if not zooms:
        raise AerolocError(f"{folder}: no {{z}}/{{x}}/{{y}} tiles found")
    if zoom is None:
        if len(zooms) > 1:
            raise AerolocError(f"{folder}: several zoom levels {zooms}; name one in manifest.json ('zoom')")
        zoom = zooms[0]
    files = {}
    for xdir in (folder / str(zoom)).iterdir():
        if xdir.is_dir() and xdir.name.isdigit():
            for f in xdir.iterdir():
                m = re.fullmatch(r"(\d+)\.(png|jpg|jpeg|webp)", f.name, re.I)
                if m:
                    files[(int(m.group(1)), int(xdir.name))] = f
    if not files:
        raise AerolocError(f"{folder}/{zoom}: no tile images")
    ys, xs = [k[0] for k in files], [k[1] for k in files]
    y0, x0 = min(ys), min(xs)
    n_rows, n_cols = max(ys) - y0 + 1, max(xs) - x0 + 1
    tw, th = _image_size(next(iter(files.values())))
    if tw != th:
        raise AerolocError(f"{folder}: XYZ tiles must be square, found {tw}x{th}")
    cells = {(y - y0, x - x0): p for (y, x), p in files.items()}
    return TileFolderMap(folder, cells, n_rows, n_cols, tw, th, geo.mercator_transform(zoom, x0, y0, tw))


def open_map(path: str | os.PathLike) -> Map:
    """Open any supported map (see the module docstring); a one-line AerolocError when it can't."""
    path = Path(path)
    if not path.exists():
        raise AerolocError(f"{path}: map not found")
    if path.is_file():
        if path.name == "map_metadata.txt":
            return open_metadata_folder(path.parent)
        return GeoTiffMap(path)
    manifest = path / "manifest.json"
    if manifest.is_file():
        try:
            info = json.loads(manifest.read_text())
        except json.JSONDecodeError as exc:
            raise AerolocError(f"{manifest}: not valid JSON ({exc})") from None
        layout = info.get("layout")
        if layout == "xyz":
            return open_xyz_folder(path, info.get("zoom"))
        if layout == "metadata":
            return open_metadata_folder(path)
        if layout == "geotiff":
            return GeoTiffMap(path / info.get("file", "map.tif"))
        raise AerolocError(f"{manifest}: unknown layout {layout!r} (xyz, metadata or geotiff)")
    if (path / "map_metadata.txt").is_file():
        return open_metadata_folder(path)
    if any(p.is_dir() and p.name.isdigit() for p in path.iterdir()):
        return open_xyz_folder(path)
    rasters = [p for p in path.iterdir() if p.suffix.lower() in RASTER_SUFFIXES]
    if len(rasters) == 1:
        return GeoTiffMap(rasters[0])
    raise AerolocError(f"{path}: not a map (no GeoTIFF, map_metadata.txt, manifest.json or {{z}}/{{x}}/{{y}} tiles)")


def meters_to_pixels(m: Map, metres: float) -> int:
    return max(1, int(round(metres / m.resolution_m)))


__all__ = [
    "GeoTiffMap",
    "Map",
    "TileFolderMap",
    "meters_to_pixels",
    "open_map",
    "open_metadata_folder",
    "open_xyz_folder",
]
