"""Coordinate helpers: WGS84 <-> any CRS (pyproj), Web Mercator tile maths, geodesic distances, affine
pixel <-> world. Everything is vectorised over numpy arrays; the API order is always (lat, lon)."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from affine import Affine
from pyproj import CRS, Geod, Transformer
from pyproj.exceptions import CRSError

from aeroloc.core.errors import AerolocError

WGS84 = "EPSG:4326"
WEB_MERCATOR = "EPSG:3857"
EARTH_RADIUS_M = 6378137.0  # the sphere Web Mercator is defined on
MAX_MERCATOR_LAT = 85.0511287798066
_GEOD = Geod(ellps="WGS84")


def parse_crs(crs) -> CRS:
    """A pyproj CRS from anything pyproj understands (EPSG code, WKT, rasterio CRS); clear error otherwise."""
    try:
        return CRS.from_user_input(crs.to_wkt() if hasattr(crs, "to_wkt") else crs)
    except (CRSError, TypeError) as exc:
        raise AerolocError(f"unreadable coordinate reference system {str(crs)[:80]!r} ({exc})") from None


@lru_cache(maxsize=64)
def _transformer(src: str, dst: str) -> Transformer:
    return Transformer.from_crs(parse_crs(src), parse_crs(dst), always_xy=True)


def _key(crs) -> str:
    return parse_crs(crs).to_wkt() if not isinstance(crs, str) else crs


def latlon_to_crs(lat, lon, crs):
    """WGS84 (lat, lon) -> (x, y) in ``crs`` (easting/northing order)."""
    x, y = _transformer(WGS84, _key(crs)).transform(np.asarray(lon, float), np.asarray(lat, float))
    return x, y


def crs_to_latlon(x, y, crs):
    """(x, y) in ``crs`` -> WGS84 (lat, lon)."""
    lon, lat = _transformer(_key(crs), WGS84).transform(np.asarray(x, float), np.asarray(y, float))
    return lat, lon


# --- affine pixel <-> world -------------------------------------------------------------------------------
def pixel_to_world(transform: Affine, col, row):
    """Pixel coordinates (col, row; 0,0 = outer top-left corner of the first pixel) -> world (x, y)."""
    col, row = np.asarray(col, float), np.asarray(row, float)
    return transform.a * col + transform.b * row + transform.c, transform.d * col + transform.e * row + transform.f


def world_to_pixel(transform: Affine, x, y):
    return pixel_to_world(~transform, x, y)


# --- Web Mercator (Google / XYZ) --------------------------------------------------------------------------
def mercator_from_latlon(lat, lon):
    """WGS84 -> Web Mercator metres (spherical formula, identical to EPSG:3857)."""
    lat = np.clip(np.asarray(lat, float), -MAX_MERCATOR_LAT, MAX_MERCATOR_LAT)
    x = EARTH_RADIUS_M * np.radians(np.asarray(lon, float))
    y = EARTH_RADIUS_M * np.log(np.tan(np.pi / 4 + np.radians(lat) / 2))
    return x, y


def latlon_from_mercator(x, y):
    lon = np.degrees(np.asarray(x, float) / EARTH_RADIUS_M)
    lat = np.degrees(2 * np.arctan(np.exp(np.asarray(y, float) / EARTH_RADIUS_M)) - np.pi / 2)
    return lat, lon


def world_size_px(zoom: int, tile_size: int = 256) -> float:
    return tile_size * 2.0**zoom


def latlon_to_global_px(lat, lon, zoom: int, tile_size: int = 256):
    """WGS84 -> global pixel (x right, y down) of the XYZ pyramid at ``zoom``."""
    x, y = mercator_from_latlon(lat, lon)
    size = world_size_px(zoom, tile_size)
    half = math.pi * EARTH_RADIUS_M
    return (x + half) / (2 * half) * size, (half - y) / (2 * half) * size


def global_px_to_latlon(px, py, zoom: int, tile_size: int = 256):
    size = world_size_px(zoom, tile_size)
    half = math.pi * EARTH_RADIUS_M
    x = np.asarray(px, float) / size * 2 * half - half
    y = half - np.asarray(py, float) / size * 2 * half
    return latlon_from_mercator(x, y)


def xyz_tile_bounds(z: int, x: int, y: int):
    """Outer edges of XYZ tile (z, x, y) as (north, west, south, east) in degrees."""
    north, west = global_px_to_latlon(x * 256, y * 256, z)
    south, east = global_px_to_latlon((x + 1) * 256, (y + 1) * 256, z)
    return float(north), float(west), float(south), float(east)


def latlon_to_tile(lat, lon, z: int):
    px, py = latlon_to_global_px(lat, lon, z)
    n = 2**z
    return int(np.clip(px // 256, 0, n - 1)), int(np.clip(py // 256, 0, n - 1))


def mercator_transform(z: int, x0: int, y0: int, tile_size: int = 256) -> Affine:
    """Affine (pixel -> EPSG:3857 metres) of a mosaic whose top-left pixel is that of XYZ tile (z, x0, y0)."""
    half = math.pi * EARTH_RADIUS_M
    res = 2 * half / world_size_px(z, tile_size)
    return Affine(res, 0, -half + x0 * tile_size * res, 0, -res, half - y0 * tile_size * res)


def quadkey(x: int, y: int, z: int) -> str:
    """Bing-style quadkey of an XYZ tile."""
    digits = []
    for i in range(z, 0, -1):
        mask = 1 << (i - 1)
        digits.append(str((1 if x & mask else 0) + (2 if y & mask else 0)))
    return "".join(digits)


# --- distances ---------------------------------------------------------------------------------------------
def geodesic_distance(lat1, lon1, lat2, lon2):
    """Distance in metres on the WGS84 ellipsoid (Karney's algorithm via pyproj.Geod); vectorised."""
    lat1, lon1, lat2, lon2 = np.broadcast_arrays(*(np.asarray(v, float) for v in (lat1, lon1, lat2, lon2)))
    _, _, d = _GEOD.inv(lon1, lat1, lon2, lat2)
    return np.asarray(d) if np.ndim(d) else float(d)


def offset_latlon(lat, lon, east_m, north_m):
    """Move a point by (east, north) metres along geodesics (for margins and synthetic tests)."""
    lat, lon, east_m, north_m = np.broadcast_arrays(*(np.asarray(v, float) for v in (lat, lon, east_m, north_m)))
    dist = np.hypot(east_m, north_m)
    az = np.degrees(np.arctan2(east_m, north_m))
    lon2, lat2, _ = _GEOD.fwd(lon, lat, az, dist)
    return np.asarray(lat2), np.asarray(lon2)
