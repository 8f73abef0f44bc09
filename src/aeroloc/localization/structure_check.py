"""The second confirmation of a sweep candidate: structure (CFOG correlation) at the candidate's own heading and
scale, searched over a map region around it, for queries where local features find nothing to match.

Why: on 5 m/px NAIP crops of other years (177 px across) XFeat + LighterGlue leave 0-8 inliers even with the
query turned exactly upright over the right window, while the sweep's candidate lies 4-17 m from the truth. The
dense stage's structure does match there (it places NAIP dev at Georef@10 m 0.99). What it lacks is a heading
and a scale; the sweep's candidate gives both.

The acceptance is the distinctness of the match against the same search where the query is not: ``ratio`` = the
best peak over the best peak at least half a footprint away, over every heading and position of a region of
``structure_region`` footprints around the candidate. The peak must also land within max(25 m, 10 map px) of the
candidate (two searches at different resolutions agree). Measured on the shared sets (``benchmarks/
structure_null.py``), see the constants below.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from aeroloc.core import geo
from aeroloc.core.frames import resize
from aeroloc.matching.dense import DenseMatch, DenseRegion
from aeroloc.matching.sweep import Hypothesis

STRUCTURE_DEFAULTS = {
    "structure": True,  # off: sweep candidates are confirmed by local features only
    "structure_px": 128,  # px: the query's side at the search's working resolution
    "structure_refine_px": 256,  # px: the side at the final placement (never finer than query or map)
    "structure_region": 2.0,  # footprints searched on each side of the candidate
    "structure_angles": (-6.0, -3.0, 0.0, 3.0, 6.0),  # degrees around the candidate's heading
    "structure_scales": (0.94, 1.0, 1.06),  # around the candidate's scale
    "structure_min_score": 0.2,
    "structure_min_ratio": 1.5,
    # footprints^2 over which the query's placements range in the region (e.g. 4 x 1): on levir-tx's 1024 px
    # tall map a wrong candidate at scale 2 (placements over 3.5 x 0.7 footprints) reached a ratio of 2.83
    "structure_min_span": 4.0,
}


@dataclass(frozen=True)
class StructureFix:
    """A candidate confirmed by structure: the query centre (map px, lat/lon), the match's score and ratio, and
    how far from the candidate it landed (m)."""

    col: float
    row: float
    lat: float
    lon: float
    score: float
    ratio: float
    agreement_m: float


def _working_factor(h: Hypothesis, side: int, px: float) -> float:
    """Map px -> working px: the query's footprint ``px`` across, never enlarging the map or the query."""
    footprint = h.scale * side
    return min(1.0, 1.0 / max(h.scale, 1e-9), px / max(footprint, 1e-9))


def _box(lo: float, hi: float, size: int) -> tuple[int, int]:
    """[lo, hi) shifted to lie inside [0, size) (clipped when longer), as whole pixels."""
    a, b = int(math.floor(lo)), int(math.ceil(hi))
    if a < 0:
        a, b = 0, b - a
    if b > size:
        a, b = max(0, a - (b - size)), size
    return a, b


def _search(image: np.ndarray, map_, h: Hypothesis, px: float, region_fp: float, angles, scales, min_span=0.0):
    """The best placement of ``image`` in the map region ``region_fp`` footprints around ``h`` (shifted to lie
    on the map) at working side ``px``: (match, map column, map row) or None, also when the placements range
    over less than ``min_span`` footprints^2."""
    fp = h.scale * max(image.shape[:2])
    mf = _working_factor(h, max(image.shape[:2]), px)
    half = (region_fp + 0.5) * fp
    c0, c1 = _box(h.col - half, h.col + half, map_.width)
    r0, r1 = _box(h.row - half, h.row + half, map_.height)
    span = max(0.0, (c1 - c0 - fp) / fp) * max(0.0, (r1 - r0 - fp) / fp)
    if min(c1 - c0, r1 - r0) * mf < 16 or span < min_span:
        return None
    rgb, valid = map_.read(c0, r0, c1 - c0, r1 - r0)
    region = DenseRegion(resize(rgb, mf), resize(valid.astype(np.uint8), mf, True) > 0)
    match: DenseMatch | None = region.locate(resize(image, h.scale * mf), angles, scales)
    if match is None:
        return None
    return match, c0 + match.x / mf, r0 + match.y / mf


def confirm_structure(map_, image: np.ndarray, h: Hypothesis, reach_m: float, conf: dict) -> StructureFix | None:
    """``h`` confirmed by structure (see the module), placed at the finer working resolution; None when the
    match is not distinct enough or lands away from ``h``."""
    angles = tuple(h.angle + d for d in conf["structure_angles"])
    # too little map around the candidate (placements over < structure_min_span footprints^2) can't tell a
    # distinct peak from a lone one
    c = conf
    found = _search(
        image, map_, h, c["structure_px"], c["structure_region"], angles, c["structure_scales"], c["structure_min_span"]
    )
    if found is None:
        return None
    match, col, row = found
    lat, lon = map_.pixel_to_latlon(col, row)
    hl = map_.pixel_to_latlon(h.col, h.row)
    agree = float(geo.geodesic_distance(hl[0], hl[1], lat, lon))
    if match.score < c["structure_min_score"] or match.ratio < c["structure_min_ratio"] or agree > reach_m:
        return None
    # the final placement: a footprint-wide window around the match, at the finer side, near its heading/scale
    placed = Hypothesis(col, row, match.angle, h.scale * match.scale, match.score)
    around = (match.angle - 1.5, match.angle, match.angle + 1.5)
    fine = _search(image, map_, placed, c["structure_refine_px"], 0.5, around, (0.97, 1.0, 1.03))
    if fine is not None and math.hypot(fine[1] - col, fine[2] - row) <= 0.25 * h.scale * max(image.shape[:2]):
        col, row = fine[1], fine[2]
        lat, lon = map_.pixel_to_latlon(col, row)
    return StructureFix(float(col), float(row), float(lat), float(lon), match.score, match.ratio, agree)
