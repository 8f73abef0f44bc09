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
    query_gsd: float = float("nan")  # metres per query pixel the search assumed (match.scale refines it)
    map_gsd: float = float("nan")

    def footprint(self, query_size: tuple[int, int], query_gsd: float | None = None, map_gsd: float | None = None):
        """The query's four corners (top-left, top-right, bottom-right, bottom-left) in map pixels."""
        from aeroloc.localization.window import footprint_at

        query_gsd = self.query_gsd if query_gsd is None else query_gsd
        map_gsd = self.map_gsd if map_gsd is None else map_gsd
        k = query_gsd * self.match.scale / map_gsd  # query px -> map px
        return footprint_at(self.col, self.row, self.match.angle, k, query_size)

    def status(self) -> str:
        return (
            f"localized (dense: score {self.match.score:.2f}, ratio {self.match.ratio:.2f}, "
            f"turned {self.match.angle:+.1f}°, scale {self.match.scale:.2f})"
        )


def scale_ladder(tol: float | None, step: float = 0.05) -> tuple[float, ...] | None:
    """Scales refined around the peak for a ground resolution known within ``tol`` (relative): geometric steps of
    about ``step`` covering [1 - tol, 1 + tol]; None (the stage's default ±10 %) when ``tol`` is unknown."""
    if tol is None:
        return None
    lo, hi = 1.0 - tol, 1.0 + tol
    n = max(2, int(np.ceil(np.log(hi / lo) / np.log(1.0 + step))) + 1)
    return tuple(float(s) for s in np.geomspace(lo, hi, n))


class DenseMapLocator:
    """The dense stage over one map: a query of known ground resolution is placed by structural correlation.

    The map is described at the working resolution of each query (the coarser of query and map); regions are
    kept per working resolution, so queries finer than the map (drone photos) share one description."""

    def __init__(self, map_, query_gsd: float | None = None, conf: dict | None = None, max_region_px: int = 4_000_000):
        self.map = map_
        self.conf = conf
        self.map_gsd = map_.resolution_m
        self.query_gsd = check_query_gsd(query_gsd)  # the default of locate(); a query's own prior overrides it
        self.max_region_px = max_region_px
        self._whole: dict[float, DenseRegion] = {}  # map factor -> the whole map, described

    @property
    def map_factor(self) -> float:
        """Map px -> working px at the default query resolution."""
        return self.factors(self.query_gsd)[0]

    @property
    def query_factor(self) -> float:
        return self.factors(self.query_gsd)[1]

    def factors(self, query_gsd: float) -> tuple[float, float]:
        """(map px -> working px, query px -> working px): both <= 1."""
        work = max(query_gsd, self.map_gsd)
        return self.map_gsd / work, query_gsd / work

    def _fits(self, w: int, h: int, map_factor: float) -> bool:
        return w * h * map_factor**2 <= self.max_region_px

    def read_region(self, col: int, row: int, w: int, h: int, map_factor: float) -> DenseRegion:
        """The map window (``col``, ``row``, ``w``, ``h`` map px) described at ``map_factor`` working px per map px."""
        rgb, valid = self.map.read(col, row, w, h)
        return DenseRegion(resize(rgb, map_factor), resize(valid.astype(np.uint8), map_factor, True) > 0, self.conf)

    def region(self, tiles: list[Tile], map_factor: float | None = None) -> tuple[DenseRegion, int, int] | None:
        """The region to search and its top-left map pixel: the whole map (described once per working
        resolution) when it fits, else the bounding box of the longest prefix of ``tiles`` (best first) that fits;
        None if not even one does."""
        m = self.map
        map_factor = self.map_factor if map_factor is None else map_factor
        key = round(map_factor, 6)
        if self._fits(m.width, m.height, map_factor):
            if key not in self._whole:
                if len(self._whole) >= 2:  # bounded: queries coarser than the map each have their own factor
                    self._whole.pop(next(iter(self._whole)))
                self._whole[key] = self.read_region(0, 0, m.width, m.height, map_factor)
            return self._whole[key], 0, 0
        box = None
        for t in tiles:
            c0, r0 = max(0, t.col), max(0, t.row)
            c1, r1 = min(m.width, t.col + t.width), min(m.height, t.row + t.height)
            nb = (
                (c0, r0, c1, r1)
                if box is None
                else (min(box[0], c0), min(box[1], r0), max(box[2], c1), max(box[3], r1))
            )
            if not self._fits(nb[2] - nb[0], nb[3] - nb[1], map_factor):
                break
            box = nb
        if box is None:
            return None
        return self.read_region(box[0], box[1], box[2] - box[0], box[3] - box[1], map_factor), box[0], box[1]

    def locate(
        self,
        image: np.ndarray,
        tiles: list[Tile],
        query_gsd: float | None = None,
        angles: tuple[float, ...] | None = None,
        scales: tuple[float, ...] | None = None,
    ) -> DenseResult | None:
        """The trusted dense position of ``image`` (RGB at ``query_gsd`` metres per pixel, default the
        locator's), searched at ``angles`` (the stage's conf when None) and refined over ``scales``; None when
        there is no distinct structural match (the caller falls back to local features)."""
        query_gsd = self.query_gsd if query_gsd is None else check_query_gsd(query_gsd)
        if query_gsd is None:
            raise AerolocError("the dense stage needs the query's ground resolution")
        map_factor, query_factor = self.factors(query_gsd)
        found = self.region(tiles, map_factor)
        if found is None:
            return None
        region, col0, row0 = found
        match = region.locate(resize(image, query_factor), angles, scales)
        if match is None or not match.trusted(region.conf):
            return None
        col, row = col0 + match.x / map_factor, row0 + match.y / map_factor
        lat, lon = self.map.pixel_to_latlon(col, row)
        return DenseResult(match, float(col), float(row), float(lat), float(lon), query_gsd, self.map_gsd)
