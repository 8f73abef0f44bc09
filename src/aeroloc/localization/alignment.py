"""Local alignment: the query centre through the verified homography into the best tile, then to lat/lon
through the tile's exact georeference. A weak or degenerate homography gives "not localized", never a guess."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aeroloc.core.frames import project_points
from aeroloc.maps.tiling import Tile


@dataclass
class Alignment:
    status: str  # "localized" or a reason it is not
    lat: float = float("nan")
    lon: float = float("nan")
    tile_xy: tuple[float, float] | None = None
    corners: np.ndarray | None = None  # the query's corners in map px where it was placed, when the aligner kept them

    @property
    def localized(self) -> bool:
        return self.status == "localized"


def reach_m(map_gsd: float | None) -> float:
    """How far apart two placements of one query may land and still be one place: max(25 m, 10 map px) (the
    agreement radius of the dense, sweep and structure confirmations, and the rival test's unit)."""
    return max(25.0, 10.0 * (map_gsd or 0.0))


def project(H: np.ndarray, x: float, y: float) -> tuple[float, float] | None:
    """(x, y) through ``H``; None when it goes to infinity."""
    xy, w = project_points(H, [(x, y)])
    if abs(w[0]) < 1e-12:
        return None
    return float(xy[0, 0]), float(xy[0, 1])


def align(
    H: np.ndarray | None,
    inliers: int,
    query_size: tuple[int, int],
    tile: Tile,
    map_size: tuple[int, int],
    min_inliers: int,
    max_outside: float = 0.5,
) -> Alignment:
    """``H`` maps query pixels (pixel-edge origin) to ``tile`` pixels; ``query_size`` = (w, h).

    Rejections: too few inliers, an insane homography (see aeroloc.matching.verify), the centre projected more than
    ``max_outside`` tile sides beyond the tile (extrapolation), or outside the map.
    """
    from aeroloc.matching.verify import homography_is_sane

    if H is None or inliers < min_inliers:
        return Alignment(f"not localized: {inliers} inliers < {min_inliers}")
    ok, reason = homography_is_sane(H, query_size)
    if not ok:
        return Alignment(f"not localized: degenerate homography ({reason})")
    w, h = query_size
    p = project(H, w / 2.0, h / 2.0)
    if p is None:
        return Alignment("not localized: centre projects to infinity")
    x, y = p
    m = max_outside
    if not (-m * tile.width <= x <= (1 + m) * tile.width and -m * tile.height <= y <= (1 + m) * tile.height):
        return Alignment("not localized: centre projects far outside the matched tile")
    mc, mr = tile.col + x, tile.row + y
    if not (0 <= mc <= map_size[0] and 0 <= mr <= map_size[1]):
        return Alignment("not localized: position outside the map")
    lat, lon = tile.pixel_to_latlon(x, y)
    return Alignment("localized", float(lat), float(lon), (x, y))
