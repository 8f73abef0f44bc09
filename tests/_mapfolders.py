"""Builders of small tile-folder maps (seed ``map_metadata.txt`` layout and XYZ ``{z}/{x}/{y}.png``) from real
NAIP pixels, with corner coordinates computed here from the Web Mercator formulas (not from aeroloc.core.geo)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

R = 6378137.0  # Web Mercator sphere


def merc_to_latlon(x: float, y: float) -> tuple[float, float]:
    return math.degrees(2 * math.atan(math.exp(y / R)) - math.pi / 2), math.degrees(x / R)


def latlon_to_merc(lat: float, lon: float) -> tuple[float, float]:
    return R * math.radians(lon), R * math.log(math.tan(math.pi / 4 + math.radians(lat) / 2))


def xyz_bounds(z: int, x: int, y: int) -> tuple[float, float, float, float]:
    """(north, west, south, east) of an XYZ tile, straight from the slippy-map formulas."""
    n = 2**z

    def lat(row):
        return math.degrees(math.atan(math.sinh(math.pi * (1 - 2 * row / n))))

    return lat(y), x / n * 360 - 180, lat(y + 1), (x + 1) / n * 360 - 180


def naip_pixels(naip_map: Path, height: int, width: int, row: int = 100, col: int = 150) -> np.ndarray:
    import rasterio
    from rasterio.windows import Window

    with rasterio.open(naip_map) as ds:
        return np.moveaxis(ds.read([1, 2, 3], window=Window(col, row, width, height)), 0, -1).copy()


@dataclass
class SeedFolder:
    path: Path
    image: np.ndarray  # the whole mosaic the tiles were cut from
    tile_w: int
    tile_h: int
    n_rows: int
    n_cols: int
    corners: dict  # (r, c) -> (tl_lat, tl_lon, br_lat, br_lon) as written
    origin: tuple[float, float] = (47.03, -99.18)  # (lat, lon) of the mosaic's top-left corner
    res_m: float = 7.25  # Web Mercator metres per mosaic pixel

    def pixel_to_latlon(self, col: float, row: float) -> tuple[float, float]:
        """Mosaic pixel (outer top-left = 0, 0) -> (lat, lon), from the Mercator formulas the corners came from."""
        x0, y0 = latlon_to_merc(*self.origin)
        return merc_to_latlon(x0 + col * self.res_m, y0 - row * self.res_m)


def build_seed_folder(
    folder: Path,
    naip_map: Path,
    n_rows=3,
    n_cols=4,
    tile_w=64,
    tile_h=48,
    origin=(47.03, -99.18),
    res_m=7.25,
    upsample=1,
) -> SeedFolder:
    """Cut a real image into n_rows x n_cols PNG tiles on a Web Mercator grid of ``res_m`` metres/px.

    ``upsample`` > 1 reads ``upsample`` times fewer NAIP pixels per side and enlarges them (bilinear) to the
    mosaic size, for raw tiles larger than the NAIP map allows (the seed's 1280x1230: ``upsample=5``)."""
    folder.mkdir(parents=True, exist_ok=True)
    height, width = n_rows * tile_h, n_cols * tile_w
    if upsample == 1:
        image = naip_pixels(naip_map, height, width)
    else:
        small = naip_pixels(naip_map, round(height / upsample), round(width / upsample))
        image = np.asarray(Image.fromarray(small).resize((width, height), Image.BILINEAR))
    x0, y0 = latlon_to_merc(*origin)
    corners = {}
    lines = ["filename top_left_lat top_left_lon bottom_right_lat bottom_right_lon"]
    for r in range(n_rows):
        for c in range(n_cols):
            name = f"tile_{r}_{c}.png"
            tile = image[r * tile_h : (r + 1) * tile_h, c * tile_w : (c + 1) * tile_w]
            Image.fromarray(tile).save(folder / name, compress_level=1 if upsample > 1 else 6)
            tl = merc_to_latlon(x0 + c * tile_w * res_m, y0 - r * tile_h * res_m)
            br = merc_to_latlon(x0 + (c + 1) * tile_w * res_m, y0 - (r + 1) * tile_h * res_m)
            corners[(r, c)] = (*tl, *br)
            lines.append(f"{name} {tl[0]:.12f} {tl[1]:.12f} {br[0]:.12f} {br[1]:.12f}")
    (folder / "map_metadata.txt").write_text("\n".join(lines) + "\n")
    return SeedFolder(folder, image, tile_w, tile_h, n_rows, n_cols, corners, tuple(origin), res_m)


def build_xyz_folder(
    folder: Path, naip_map: Path, z=14, x0=3679, y0=5761, n_cols=3, n_rows=2, size=64, skip=()
) -> np.ndarray:
    """Write ``folder/z/x/y.png`` tiles of ``size`` px (real pixels); ``skip`` lists (x, y) left out."""
    image = naip_pixels(naip_map, n_rows * size, n_cols * size)
    for r in range(n_rows):
        for c in range(n_cols):
            if (x0 + c, y0 + r) in skip:
                continue
            d = folder / str(z) / str(x0 + c)
            d.mkdir(parents=True, exist_ok=True)
            Image.fromarray(image[r * size : (r + 1) * size, c * size : (c + 1) * size]).save(d / f"{y0 + r}.png")
    return image
