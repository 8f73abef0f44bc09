"""The dense stage on a map (aeroloc.matching.dense): working resolution, search region, map pixel -> latitude/longitude.

Queries and map are brought to the coarser of their two ground resolutions (the query's is given: satellite
metadata, or a drone's height over ground and its camera's field of view). A map that fits ``max_region_px`` at
that resolution is described once and searched whole for every query; a larger one is searched over the
bounding box of the query's best retrieved tiles that fits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aeroloc.core.errors import AerolocError
from aeroloc.core.frames import resize
from aeroloc.maps.tiling import Tile
from aeroloc.matching.dense import DenseMatch, DenseRegion


def check_query_gsd(query_gsd) -> float | None:
    if query_gsd is None:
        return None
    try:
        g = float(query_gsd)
    except (TypeError, ValueError):
        g = float("nan")
    if not np.isfinite(g) or g <= 0:
        raise AerolocError(f"query ground resolution must be a positive number of metres per pixel, got {query_gsd!r}")
    return g


@dataclass
class DenseResult:
    match: DenseMatch  # match.angle: degrees the query's content is turned clockwise from the north-up map
    col: float  # query centre in map pixels
    row: float
    lat: float
    lon: float

    def footprint(self, query_size: tuple[int, int], query_gsd: float, map_gsd: float) -> np.ndarray:
        """The query's four corners (top-left, top-right, bottom-right, bottom-left) in map pixels."""
        w, h = query_size
        k = query_gsd * self.match.scale / map_gsd  # query px -> map px
        t = np.radians(self.match.angle)  # query offsets -> map offsets: OpenCV's rotation by the matched angle
        rot = np.array([[np.cos(t), np.sin(t)], [-np.sin(t), np.cos(t)]])
        corners = np.array([[-w, -h], [w, -h], [w, h], [-w, h]], np.float64) / 2 * k
        return corners @ rot.T + [self.col, self.row]

    def status(self) -> str:
        return (
            f"localized (dense: score {self.match.score:.2f}, ratio {self.match.ratio:.2f}, "
            f"turned {self.match.angle:+.1f}°, scale {self.match.scale:.2f})"
        )


class DenseMapLocator:
    def __init__(self, map_, query_gsd: float, conf: dict | None = None, max_region_px: int = 4_000_000):
        self.map = map_
        self.conf = conf
        self.query_gsd = check_query_gsd(query_gsd)
        self.map_gsd = map_gsd = map_.resolution_m
        work = max(self.query_gsd, map_gsd)
        self.map_factor = map_gsd / work  # map px -> working px (<= 1)
        self.query_factor = self.query_gsd / work
        self.max_region_px = max_region_px
        self._whole: DenseRegion | None = None

    def _fits(self, w: int, h: int) -> bool:
        return w * h * self.map_factor**2 <= self.max_region_px

    def _region(self, col: int, row: int, w: int, h: int) -> DenseRegion:
        rgb, valid = self.map.read(col, row, w, h)
        return DenseRegion(
            resize(rgb, self.map_factor), resize(valid.astype(np.uint8), self.map_factor, True) > 0, self.conf
        )

    def region(self, tiles: list[Tile]) -> tuple[DenseRegion, int, int] | None:
        """The region to search and its top-left map pixel: the whole map (described once) when it fits, else the
        bounding box of the longest prefix of ``tiles`` (best first) that fits; None if not even one does."""
        m = self.map
        if self._fits(m.width, m.height):
            if self._whole is None:
                self._whole = self._region(0, 0, m.width, m.height)
            return self._whole, 0, 0
        box = None
        for t in tiles:
            c0, r0 = max(0, t.col), max(0, t.row)
            c1, r1 = min(m.width, t.col + t.width), min(m.height, t.row + t.height)
            nb = (
                (c0, r0, c1, r1)
                if box is None
                else (min(box[0], c0), min(box[1], r0), max(box[2], c1), max(box[3], r1))
            )
            if not self._fits(nb[2] - nb[0], nb[3] - nb[1]):
                break
            box = nb
        if box is None:
            return None
        return self._region(box[0], box[1], box[2] - box[0], box[3] - box[1]), box[0], box[1]

    def locate(self, image: np.ndarray, tiles: list[Tile]) -> DenseResult | None:
        """The trusted dense position of ``image`` (RGB at ``query_gsd``), or None (no distinct structural match:
        the caller falls back to local features)."""
        found = self.region(tiles)
        if found is None:
            return None
        region, col0, row0 = found
        match = region.locate(resize(image, self.query_factor))
        if match is None or not match.trusted(region.conf):
            return None
        col, row = col0 + match.x / self.map_factor, row0 + match.y / self.map_factor
        lat, lon = self.map.pixel_to_latlon(col, row)
        return DenseResult(match, float(col), float(row), float(lat), float(lon))
