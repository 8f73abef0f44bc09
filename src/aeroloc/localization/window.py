"""Map-window re-alignment: match the query against the map around its first estimate instead of one tile.

A tile is the retrieval unit, not the query's footprint: a query larger than a tile, or centred near a tile's
edge, shares only part of its area with the best tile, so its matches are few and the centre is extrapolated.
When the best tile's verified match is weak (too few inliers to trust, but a hypothesis), the window of the map
that the hypothesis says the query covers (plus a margin) is read from the map, described at the tiles' working
scale and matched again. The same inlier threshold decides; a wrong hypothesis gives a window that shares no
more with the query than any wrong tile does, so it stays "not localized".
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from aeroloc.core.frames import project_points
from aeroloc.maps.tiling import Tile, shifted


def open_map_for_refine(path):
    """The map to cut windows from, or None with a warning: without it weak matches stay "not localized" (the
    tiles alone still localize every query they did before), so results differ from a run that had the map."""
    from aeroloc.core.errors import AerolocError
    from aeroloc.maps.sources import open_map

    try:
        return open_map(path)
    except AerolocError as exc:
        warnings.warn(
            f"{exc}; weak matches are not re-matched on the map window (aeroloc.localization.window)", stacklevel=2
        )
        return None


@dataclass
class Window:
    tile: Tile  # a virtual tile: the window's pixels and exact georeference
    image: np.ndarray
    valid: np.ndarray


def _projected_corners(H: np.ndarray, query_size: tuple[int, int]) -> np.ndarray | None:
    w, h = query_size
    xy, ws = project_points(H, [(0, 0), (w, 0), (w, h), (0, h)])
    if not np.isfinite(ws).all() or (ws <= 1e-9).any() or not np.isfinite(xy).all():
        return None
    return xy


def footprint_in_map(H: np.ndarray, query_size: tuple[int, int], tile: Tile) -> np.ndarray | None:
    """The query's corners (4 x 2, map px) through ``H`` (query px -> ``tile`` px); None when unusable."""
    xy = _projected_corners(H, query_size)
    return None if xy is None else xy + [tile.col, tile.row]


def footprint_at(col: float, row: float, angle_deg: float, k: float, query_size: tuple[int, int]) -> np.ndarray:
    """The query's corners (top-left, top-right, bottom-right, bottom-left; map px) placed with its centre at
    ``col, row``, turned by ``angle_deg`` (the content's clockwise turn from north-up, applied as OpenCV's
    rotation) and scaled by ``k`` map px per query px: a dense or sweep placement's footprint."""
    w, h = query_size
    t = np.radians(angle_deg)
    rot = np.array([[np.cos(t), np.sin(t)], [-np.sin(t), np.cos(t)]])
    corners = np.array([[-w, -h], [w, -h], [w, h], [-w, h]], np.float64) / 2 * k
    return corners @ rot.T + [col, row]


def beyond_tile(H: np.ndarray, query_size: tuple[int, int], tile: Tile) -> float:
    """How far the query's projected footprint reaches beyond ``tile``, in tile sides (0 = inside; inf when
    the projection is unusable)."""
    xy = _projected_corners(H, query_size)
    if xy is None:
        return float("inf")
    out = np.maximum(np.maximum(-xy, xy - [tile.width, tile.height]), 0) / [tile.width, tile.height]
    return float(out.max())


def query_window(
    map_, tile: Tile, H: np.ndarray, query_size: tuple[int, int], margin: float = 0.2, max_sides: float = 3.0
) -> Window | None:
    """The map window covering the query's corners projected through ``H`` (query px -> ``tile`` px), grown by
    ``margin`` of its size on every side and clipped to the map; None when the projection is unusable (behind
    the horizon, empty after clipping, or larger than ``max_sides`` tile sides)."""
    xy = _projected_corners(H, query_size)
    if xy is None:
        return None
    xy = xy + [tile.col, tile.row]
    (x0, y0), (x1, y1) = xy.min(0), xy.max(0)
    mx, my = margin * (x1 - x0), margin * (y1 - y0)
    c0, r0 = max(0, int(np.floor(x0 - mx))), max(0, int(np.floor(y0 - my)))
    c1, r1 = min(map_.width, int(np.ceil(x1 + mx))), min(map_.height, int(np.ceil(y1 + my)))
    if c1 - c0 < 16 or r1 - r0 < 16 or max(c1 - c0, r1 - r0) > max_sides * max(tile.width, tile.height):
        return None
    image, valid = map_.read(c0, r0, c1 - c0, r1 - r0)
    vt = Tile(f"{tile.id}@window", c0, r0, c1 - c0, r1 - r0, shifted(map_.transform, c0, r0), map_.crs)
    return Window(vt, image, valid)
