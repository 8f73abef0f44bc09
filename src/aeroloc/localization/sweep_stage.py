"""The sweep stage: any-heading, any-scale candidates over the whole map (:mod:`aeroloc.matching.sweep`), each
confirmed by local features at the candidate's own heading and scale.

Why two independent methods: the sweep's correlation places 92-100 % of queries right with exact priors on every
shared set, but its scores overlap between right and wrong answers. Local features matched with the query turned
to the candidate's heading (any angle, not only quarter turns) against the map window the candidate says the
query covers, at the candidate's scale, confirm a right candidate with many inliers; a wrong candidate's window
shares no structure with the query. A fix is kept only when both agree within max(25 m, 10 map px).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

from aeroloc.core import frames, geo
from aeroloc.core.images import valid_mask
from aeroloc.localization.alignment import Alignment, align, reach_m
from aeroloc.localization.results import AMBIGUOUS
from aeroloc.localization.structure_check import STRUCTURE_DEFAULTS, confirm_structure
from aeroloc.localization.window import Window
from aeroloc.maps.tiling import Tile, shifted
from aeroloc.matching.features import extract
from aeroloc.matching.sweep import SWEEP_DEFAULTS, Hypothesis, MapPyramid, SweepResult, sweep

QUARTER_FIRST_DEG = 30.0  # both turns are matched within this (the matchers bridge ~35-45° of rotation)


@dataclass(frozen=True)
class SweepFix:
    """A confirmed sweep candidate: the local-feature alignment, its inliers, the candidate it confirmed and how
    far apart the two put the query centre (m)."""

    alignment: Alignment
    inliers: int
    hypothesis: Hypothesis
    agreement_m: float
    rank: int


class SweepLocator:
    """The sweep over one map: the map read once, its pyramid described level by level on first use."""

    def __init__(self, map_, conf: dict | None = None):
        self.map = map_
        self.conf = {**SWEEP_DEFAULTS, **STRUCTURE_DEFAULTS, **(conf or {})}
        self.map_gsd = float(map_.resolution_m)
        self._pyramid: MapPyramid | None = None

    @property
    def fits(self) -> bool:
        """Whether the map is small enough to sweep whole (country-size maps are not: retrieval narrows them)."""
        return self.map.width * self.map.height <= self.conf["max_map_px"]

    @property
    def pyramid(self) -> MapPyramid:
        if self._pyramid is None:
            rgb, valid = self.map.read(0, 0, self.map.width, self.map.height)
            self._pyramid = MapPyramid(rgb, valid, self.conf)
        return self._pyramid

    def search(self, image: np.ndarray, priors=None) -> SweepResult | None:
        """Candidates for ``image``: headings ``heading_step`` apart within the prior's tolerance or over the full
        circle; scales (query gsd / map gsd) within the prior's ground-resolution range or the configured range."""
        p = priors.with_image_width(image.shape[1]) if priors is not None else None
        angles = p.heading_search(self.conf["heading_step"]) if p is not None else None
        if angles is None:
            angles = tuple(float(a) for a in np.arange(0.0, 360.0, self.conf["heading_step"]))
        rng = p.gsd_range() if p is not None else None
        lo, hi = (r / self.map_gsd for r in rng) if rng else self.conf["scale_range"]
        if hi <= 0:
            return None
        return sweep(self.pyramid, image, angles, max(lo, 1e-3), hi)


def upright(image: np.ndarray, angle: float) -> tuple[np.ndarray, np.ndarray]:
    """``image`` turned ``angle`` degrees (OpenCV, counter-clockwise) on a canvas that holds all of it, and the
    mask of its own pixels (aeroloc.core.frames.turned)."""
    out, mask, _ = frames.turned(image, angle)
    return out, mask


def footprint_window(map_, h: Hypothesis, size: tuple[int, int], margin: float = 0.25) -> Window | None:
    """The map window an upright query of ``size`` (w, h) covers when placed as ``h`` says, grown by ``margin``
    of its side; None when it falls off the map."""
    half_w, half_h = (0.5 + margin) * h.scale * size[0], (0.5 + margin) * h.scale * size[1]
    c0, r0 = max(0, int(math.floor(h.col - half_w))), max(0, int(math.floor(h.row - half_h)))
    c1 = min(map_.width, int(math.ceil(h.col + half_w)))
    r1 = min(map_.height, int(math.ceil(h.row + half_h)))
    if c1 - c0 < 16 or r1 - r0 < 16:
        return None
    image, valid = map_.read(c0, r0, c1 - c0, r1 - r0)
    tile = Tile(f"sweep@{c0},{r0}", c0, r0, c1 - c0, r1 - r0, shifted(map_.transform, c0, r0), map_.crs)
    return Window(tile, image, valid)


def confirm(
    reranker, map_, image: np.ndarray, h: Hypothesis, reach_m: float, min_inliers: int, screen_min: int = 0
) -> tuple[SweepFix | None, int]:
    """Local features of the query turned to ``h``'s heading against the window ``h`` says it covers, described
    at the query's own scale; a :class:`SweepFix` when the alignment has ``min_inliers`` and lands within
    ``reach_m`` of ``h``, else None; and the most inliers found.

    Two turns are tried: the exact one, then the nearest quarter turn (lossless); when the quarter turn leaves at
    most ``QUARTER_FIRST_DEG`` of rotation both are matched and the one with more inliers is kept. On small 5 m/px NAIP crops the resampling of an exact turn
    left 3-6 inliers where the unresampled query, 14-36° off, had 48-104, and even a 2-12° exact turn cost
    inliers and precision (NAIP dev, rough priors: 37-55 inliers and 12-18 m off, against 76-88 and 3.5-9.5 m);
    a quarter turn 14-29° off was the less precise one on two dev-rotated crops. The learned matcher runs only on pairs whose
    cheap screen finds ``screen_min`` inliers."""
    k = round(h.angle / 90.0) % 4
    quarter = np.ascontiguousarray(np.rot90(image, k))
    both = abs((h.angle - 90.0 * k + 180.0) % 360.0 - 180.0) <= QUARTER_FIRST_DEG
    best, most = None, 0
    for turned in (upright(image, h.angle), (quarter, valid_mask(quarter))):
        fix, n = _confirm_turned(reranker, map_, h, reach_m, (min_inliers, screen_min), turned)
        if fix is not None and (best is None or fix.inliers > best.inliers):
            best = fix
        most = max(most, n)
        if best is not None and not both:
            break
    return best, (best.inliers if best is not None else most)


def match_on_window(reranker, qf: dict, window: Window, scale: float, size: tuple[int, int], screen_min: int):
    """(inliers, transform: query px -> window px) of query features ``qf`` (described at ``query_side``; the query
    ``size`` px at ``scale`` map px each) against ``window`` described at the same density: the cheap screen
    first (mutual nearest neighbours + RANSAC), the re-ranker's learned matcher only when the screen is not
    clear (below ``accept_screen``). The transform is None when the screen stays under ``screen_min``."""
    conf = reranker.conf
    # the window at the query's density: ``side`` px across the query's footprint of scale * max(size) map px
    w_side = max(16, round(max(window.image.shape[:2]) * int(conf["query_side"]) / (scale * max(size))))
    wf = extract(reranker.extractor, window.image, w_side, 0, mask=window.valid)
    n, H, _n_matches, _vis = reranker.screen_pair(qf, wf)
    if n < screen_min:
        return n, None
    if conf["accept_screen"] is None or n < conf["accept_screen"]:
        n, H, _n_matches, _vis = reranker.match_pair(qf, wf)
    return n, H


def _confirm_turned(reranker, map_, h: Hypothesis, reach_m: float, floors: tuple[int, int], turned):
    """One confirmation of ``h`` with the query already turned: ``turned`` = (image, mask of its own pixels);
    ``floors`` = (inliers an alignment needs, screen inliers the learned matcher needs)."""
    min_inliers, screen_min = floors
    up, mask = turned
    size = (up.shape[1], up.shape[0])
    window = footprint_window(map_, h, size)
    if window is None:
        return None, 0
    qf = extract(reranker.extractor, up, int(reranker.conf["query_side"]), 0, mask=mask)
    n, H = match_on_window(reranker, qf, window, h.scale, size, screen_min)
    if H is None:
        return None, n
    a = align(H, n, size, window.tile, (map_.width, map_.height), min_inliers)
    if not a.localized:
        return None, n
    lat, lon = map_.pixel_to_latlon(h.col, h.row)
    d = float(geo.geodesic_distance(lat, lon, a.lat, a.lon))
    return (SweepFix(a, n, h, d, 0) if d <= reach_m else None), n


def accept_fix(locator: SweepLocator, reranker, image: np.ndarray, priors=None):
    """The first of the sweep's best ``confirm`` candidates that local features or structure confirm, and why it
    was accepted: (fix, why); (None, why not) when another candidate far away is confirmed too (a repeated
    pattern); None when none is.

    The rule: the query, turned and scaled as the candidate says, aligns on the candidate's map window with at
    least ``confirm_inliers`` inliers and within max(25 m, 10 map px) of the candidate. Over the shared sets,
    windows that do not contain the query's ground gave 0-15 inliers (the same search where the query is not),
    right ones 14-118, but a repeated field 542 m away 32 (hence the rival test); an alignment on a window that only overlaps the query's ground lands at the true place,
    away from its candidate, and is refused by the agreement test. When local features find too little, the
    candidate's structure is checked instead (aeroloc.localization.structure_check)."""
    res = locator.search(image, priors)
    if res is None:
        return None
    c = locator.conf
    reach = reach_m(locator.map_gsd)
    cands = res.candidates[: c["confirm"]]
    for rank, h in enumerate(cands):
        fix, n = confirm(reranker, locator.map, image, h, reach, c["confirm_inliers"], c["confirm_screen_min"])
        if fix is not None:
            why = f"confirmed by {n} local-feature inliers, {fix.agreement_m:.1f} m from candidate {rank + 1}"
            fix = SweepFix(fix.alignment, fix.inliers, fix.hypothesis, fix.agreement_m, rank)
        else:
            s = confirm_structure(locator.map, image, h, reach, c) if c["structure"] else None
            if s is None:
                continue
            fix = SweepFix(Alignment("localized", s.lat, s.lon), 0, h, s.agreement_m, rank)
            why = f"structure confirmed: score {s.score:.2f}, ratio {s.ratio:.2f}, {s.agreement_m:.1f} m from candidate {rank + 1}"
        rival = _rival(locator, reranker, image, fix, cands[rank + 1 :], reach)
        return (fix, why) if rival is None else (None, rival)
    return None


def _rival(locator: SweepLocator, reranker, image, fix: SweepFix, others, reach_m: float) -> str | None:
    """Why ``fix`` is ambiguous, or None: another candidate far from it (> 2 reaches) is confirmed by local
    features (exact turn) with at least 1/``rival_margin`` of its inliers (a structural fix: with any). Two
    far-apart places that both match are a repeated pattern, not a fix."""
    c = locator.conf
    floors = (c["confirm_inliers"], c["confirm_screen_min"])
    for h in others:
        if fix.hypothesis.distance(h) * locator.map_gsd <= 2 * reach_m:
            continue
        rival, n = _confirm_turned(reranker, locator.map, h, reach_m, floors, upright(image, h.angle))
        if rival is not None and n * c["rival_margin"] >= fix.inliers:
            apart = fix.hypothesis.distance(h) * locator.map_gsd
            return f"{AMBIGUOUS} ({fix.inliers} and {n} local-feature inliers, {apart:.0f} m apart)"
    return None


def open_sweep(map_, conf: dict | None = None) -> SweepLocator | None:
    """The sweep for ``map_``, or None (with a warning) when the map is too large to sweep whole."""
    if map_ is None:
        return None
    loc = SweepLocator(map_, conf)
    if not loc.fits:
        warnings.warn(
            f"map of {map_.width}x{map_.height} px is larger than the sweep's {loc.conf['max_map_px']} px: "
            "queries with unknown heading rely on retrieval and quarter-turn local features",
            stacklevel=2,
        )
        return None
    return loc
