"""The other-date image a simulated flight flies over, composed from a query set's georeferenced crops.

The shared sets hold a map of one date and crops of other dates, each with its exact ground footprint (centre,
heading, and ``footprint_m`` or ``gsd_m``); there is no full other-date mosaic. Each crop is warped into the map's
pixel grid (at ``factor`` times the map's resolution) by the similarity its footprint defines; where crops overlap
the later one in the file wins, so the composite is a patchwork of other-date crops (seams included) and never
contains a pixel of the map's own date. ``coverage`` says where it has content.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from aeroloc.core.errors import AerolocError
from aeroloc.core.images import read_image


@dataclass
class Composite:
    image: np.ndarray  # RGB uint8, map grid x factor
    coverage: np.ndarray  # bool: pixels painted by some crop
    factor: float  # composite px per map px
    gsd_m: float  # metres per composite pixel
    dates: list[str]  # the crops' dates (or scenes), for the report

    def to_map_px(self, x: float, y: float) -> tuple[float, float]:
        return x / self.factor, y / self.factor


def crop_to_map(turn_deg: float, scale: float, centre_map: tuple[float, float], size: tuple[int, int]):
    """2x3 affine: crop pixel (pixel-edge origin) -> map pixel, for a crop whose content is turned ``turn_deg``
    clockwise from the north-up map (the sets' ``heading_deg`` and the dense stage's angle: measured on NAIP
    dev-rotated, this sign gives CFOG correlations 0.33-0.45 with the map, the other -0.02-0.2) and whose pixel
    is ``scale`` map pixels; the crop centre lands on ``centre_map``."""
    t = math.radians(turn_deg)
    rot = np.array([[math.cos(t), math.sin(t)], [-math.sin(t), math.cos(t)]]) * scale
    w, h = size
    shift = np.asarray(centre_map, float) - rot @ np.array([w / 2.0, h / 2.0])
    return np.hstack([rot, shift[:, None]])


def index_frame(a: np.ndarray) -> np.ndarray:
    """``a`` (pixel-edge coordinates on both sides, the georeference's frame) as OpenCV's warps read it: pixel
    indices, index = edge - 0.5. Without this step a turned or scaled crop lands up to a pixel off its footprint."""
    a = np.array(a, float)
    a[:, 2] += a[:, :2] @ np.full(2, 0.5) - 0.5
    return a


def compose(map_, queries, factor: float = 2.0, max_px: int = 6000) -> Composite:
    """The crops of ``queries`` (aeroloc.core.queries.Query with truth lat/lon, heading, ground resolution)
    painted into ``map_``'s grid at ``factor`` x its resolution."""
    w, h = int(round(map_.width * factor)), int(round(map_.height * factor))
    if max(w, h) > max_px:
        raise AerolocError(f"composite of {w}x{h} px is too large; lower the factor (max side {max_px} px)")
    out = np.zeros((h, w, 3), np.uint8)
    cover = np.zeros((h, w), bool)
    map_gsd = map_.resolution_m
    dates = []
    for q in queries:
        gsd = q.truth_gsd_m
        if gsd is None or q.heading_deg is None or not q.has_truth:
            raise AerolocError(f"{q.origin}: a composite needs each crop's lat, lon, heading_deg and ground resolution")
        img = read_image(q.path)
        col, row = map_.latlon_to_pixel(q.lat, q.lon)
        A = crop_to_map(
            q.heading_deg,
            gsd / map_gsd * factor,
            (float(col) * factor, float(row) * factor),
            (img.shape[1], img.shape[0]),
        )
        ih, iw = img.shape[:2]
        corners = np.array([[0, 0, 1], [iw, 0, 1], [iw, ih, 1], [0, ih, 1]], float) @ A.T
        c0, r0 = np.maximum(np.floor(corners.min(0)).astype(int), 0)
        c1, r1 = np.minimum(np.ceil(corners.max(0)).astype(int), [w, h])
        if c1 <= c0 or r1 <= r0:
            continue
        A = index_frame(A) - [[0, 0, c0], [0, 0, r0]]  # warp into the crop's bounding box only
        size = (int(c1 - c0), int(r1 - r0))
        warped = cv2.warpAffine(img, A, size, flags=cv2.INTER_LINEAR, borderValue=0)
        inside = cv2.warpAffine(np.ones((ih, iw), np.uint8), A, size, flags=cv2.INTER_NEAREST)
        inside = cv2.erode(inside, np.ones((3, 3), np.uint8)) > 0  # no half-blended rim
        out[r0:r1, c0:c1][inside] = warped[inside]
        cover[r0:r1, c0:c1] |= inside
        dates.append(str(q.extra.get("date") or q.extra.get("scene") or ""))
    return Composite(out, cover, factor, map_gsd / factor, dates)
