"""The any-heading, any-scale sweep: the whole map correlated against a query at every (heading, scale)
hypothesis the priors allow, coarse to fine (CFOG structure, as :mod:`aeroloc.matching.dense`).

Why: local features (XFeat + LighterGlue) break beyond ~35-45° of residual rotation and the tile-box dense stage
needs the query's exact ground resolution. Shrunk to a template of a few dozen pixels, the structure that
survives years (roads, field edges, outlines of buildings) is still there, and one FFT correlation per hypothesis
over a coarse map level is cheap enough to try every heading and scale. The candidates it returns (position,
heading, scale) are hypotheses: the caller confirms them with local features at that heading and scale
(measured in ``experiments/research/any-heading``: with exact priors 92-100 % of the best candidates lie within
t on every shared set, but the sweep's own scores do not separate right from wrong answers).

Two choices that made it work (see the research notes):
- a *disk* template: a square query turned 45° keeps 52 % of its area in an axis-aligned crop, its inscribed disk
  keeps 79 % at every heading, and the map's statistics under a disk are computed once per disk size;
- one coarse level per query, chosen by a pixel budget (cost ~ hypotheses x level pixels: few hypotheses buy a
  finer level), and coarse peaks ranked by their standard score in each hypothesis's response (a small template
  reaches a high raw correlation anywhere by chance).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from aeroloc.core.frames import resize
from aeroloc.matching.dense import DEFAULTS as DENSE_DEFAULTS
from aeroloc.matching.dense import _placement_valid, _subpixel, orientation_features

SWEEP_DEFAULTS = {
    "heading_step": 10.0,  # degrees between heading hypotheses when the heading is unknown
    "scale_step": 1.26,  # ratio between scale hypotheses (query gsd / map gsd)
    "scale_range": (0.25, 2.0),  # searched when the ground resolution is unknown: 4x finer .. 2x coarser
    "coarse_budget": 2_500_000,  # hypotheses x coarse-level pixels
    "coarse_px": (60_000, 1_000_000),  # the coarse level's size bounds
    "template": 32,  # px: the footprint's least size on the coarse level
    "template_max": 96,  # px: no finer coarse level than this footprint (costs time, adds nothing)
    "candidates": 4,  # distinct coarse peaks kept
    "refined": 3,  # of which refined
    "refine_template": 64,  # px: the footprint at the refinement level
    # px: the best candidate's last refinement (0: none). Off: the local-feature confirmation places the query to
    # a pixel anyway, and without it (and with one round) the sweep costs half (rough priors, levir-tx/szada-hu
    # any, 12 queries each: 0.56-0.60 -> 0.30-0.32 s CPU, the same candidates within reach: 10/12 and 9/12)
    "final_template": 0,
    "rounds": 1,  # refinement rounds per level (steps halved every round)
    "exclusion": 0.5,  # candidates are distinct when farther apart than this many footprints
    "max_map_px": 40_000_000,
    "confirm": 2,  # candidates offered to the local-feature confirmation (aeroloc.localization.sweep_stage)
    "confirm_inliers": 20,  # inliers a confirmation needs (windows without the query's ground: mostly <= 15)
    # the learned matcher runs only when the cheap screen finds this many: over 34 candidates of levir-tx and
    # szada-hu, right windows screened 13-115 (but one, matched to 16 < 20 anyway), wrong ones 5-38
    "confirm_screen_min": 10,
    # a confirmed candidate is kept only when no other candidate far from it confirms with at least 1/this
    # of its inliers: on szada-hu farmland a field 542 m from the truth gave 32 inliers, the truth 21
    "rival_margin": 2.0,
}
LEVEL_RATIO = 2 ** (1 / 3)  # between pyramid levels
FFT_WORKERS = 1  # one thread: the per-query work is small and the machine's cores serve other queries


@dataclass(frozen=True)
class Hypothesis:
    """A placement of the query on the map: its centre (map px, pixel-edge origin), the OpenCV angle (degrees,
    counter-clockwise; = the heading clockwise from north) that turns the query map-aligned, and its scale (map
    px per query px); ``score`` the disk NCC at ``factor`` map px per level px."""

    col: float
    row: float
    angle: float
    scale: float
    score: float
    factor: float = 1.0

    def distance(self, other: Hypothesis) -> float:
        return math.hypot(self.col - other.col, self.row - other.row)


@dataclass(frozen=True)
class SweepResult:
    """Refined candidates, best first; ``ratio`` = best score / best score a footprint away (like with like:
    both refined); ``n_hypotheses`` the coarse search's size."""

    candidates: tuple[Hypothesis, ...]
    ratio: float
    n_hypotheses: int
    stats: dict = field(default_factory=dict)

    @property
    def best(self) -> Hypothesis:
        return self.candidates[0]


class DiskCorrelator:
    """NCC of a *disk* template at every placement of a multi-channel region (FFT); only the template's
    inscribed disk is compared, so every heading of a square template sees the same map statistics."""

    def __init__(self, region_f: np.ndarray):
        from scipy import fft

        self.H, self.W, _ = region_f.shape
        self.P, self.Q = fft.next_fast_len(self.H, real=True), fft.next_fast_len(self.W, real=True)
        f = np.moveaxis(region_f, -1, 0).astype(np.float32)
        self.spectra = fft.rfft2(f, s=(self.P, self.Q), workers=FFT_WORKERS)
        self.sq_spectrum = fft.rfft2((f**2).sum(0), s=(self.P, self.Q), workers=FFT_WORKERS)
        self._spread: dict[int, np.ndarray] = {}

    @staticmethod
    def disk(d: int) -> np.ndarray:
        yy, xx = np.mgrid[:d, :d] - (d - 1) / 2
        return (xx**2 + yy**2 <= (d / 2) ** 2).astype(np.float32)

    def spread(self, d: int) -> np.ndarray:
        """Per placement: the root of the map's summed per-channel variance under the disk (times its area)."""
        from scipy import fft

        s = self._spread.get(d)
        if s is None:
            D = self.disk(d)
            Ds = fft.rfft2(D[::-1, ::-1], s=(self.P, self.Q), workers=FFT_WORKERS)
            rows, cols = slice(d - 1, self.H), slice(d - 1, self.W)
            sums = fft.irfft2(self.spectra * Ds, s=(self.P, self.Q), workers=FFT_WORKERS)[:, rows, cols]
            sq = fft.irfft2(self.sq_spectrum * Ds, s=(self.P, self.Q), workers=FFT_WORKERS)[rows, cols]
            var = sq - (sums.astype(np.float64) ** 2).sum(0) / float(D.sum())
            s = np.sqrt(np.maximum(var, 0)).astype(np.float32)
            if len(self._spread) > 24:
                self._spread.pop(next(iter(self._spread)))
            self._spread[d] = s
        return s

    def __call__(self, query_f: np.ndarray) -> np.ndarray | None:
        """Scores of the d x d x C template ``query_f`` at every top-left offset; None when it doesn't fit."""
        from scipy import fft

        d = query_f.shape[0]
        if d > self.H or d > self.W or d < 8:
            return None
        D = self.disk(d)
        q = np.moveaxis(query_f, -1, 0).astype(np.float32)
        q = (q - (q * D).sum(axis=(1, 2), keepdims=True) / float(D.sum())) * D
        qnorm = float(np.sqrt((q.astype(np.float64) ** 2).sum()))
        # the zero-padded template's 2-D FFT, pruned: along rows first (its d rows only), then along columns
        qs = fft.rfft(q[:, ::-1, ::-1], n=self.Q, axis=-1, workers=FFT_WORKERS)
        qs = fft.fft(qs, n=self.P, axis=-2, workers=FFT_WORKERS)
        num = fft.irfft2(np.einsum("cij,cij->ij", self.spectra, qs), s=(self.P, self.Q), workers=FFT_WORKERS)
        num = num[d - 1 : self.H, d - 1 : self.W]
        den = qnorm * self.spread(d)
        return np.where(den > 1e-6, num / np.maximum(den, 1e-6), 0.0).astype(np.float32)


@dataclass
class Level:
    """The map at ``factor`` map px per level px: CFOG features, no-data integral image, whole-level correlator."""

    factor: float
    features: np.ndarray
    invalid: np.ndarray | None
    _correlator: DiskCorrelator | None = None

    @property
    def pixels(self) -> int:
        return int(self.features.shape[0] * self.features.shape[1])

    @property
    def correlator(self) -> DiskCorrelator:
        if self._correlator is None:
            self._correlator = DiskCorrelator(self.features)
        return self._correlator

    def valid_placements(self, res: np.ndarray, d: int, y0: int = 0, x0: int = 0) -> np.ndarray:
        """``res`` with placements that touch no-data set to -1 (offsets relative to (``y0``, ``x0``))."""
        if self.invalid is None:
            return res
        inv = self.invalid[y0 : y0 + res.shape[0] + d, x0 : x0 + res.shape[1] + d]
        return np.where(_placement_valid(inv, (d, d)), res, -1.0)


class MapPyramid:
    """The map's CFOG pyramid (levels 2^(k/3) apart), each level described on first use and kept."""

    def __init__(self, rgb: np.ndarray, valid: np.ndarray, conf: dict | None = None):
        self.conf = {**SWEEP_DEFAULTS, **(conf or {})}
        self.rgb, self.valid = rgb, valid
        self.height, self.width = rgb.shape[:2]
        n = max(1, math.ceil(math.log(max(self.width, self.height) / 64) / math.log(LEVEL_RATIO)) + 1)
        self.factors = tuple(LEVEL_RATIO**k for k in range(n))
        self._levels: dict[float, Level] = {}

    def level(self, factor: float) -> Level:
        L = self._levels.get(factor)
        if L is None:
            rgb = self.rgb if factor == 1 else resize(self.rgb, 1 / factor)
            valid = self.valid if factor == 1 else resize(self.valid.astype(np.uint8), 1 / factor, True) > 0
            invalid = None if valid.all() else cv2.integral((~valid).astype(np.uint8))
            L = self._levels[factor] = Level(factor, orientation_features(rgb, DENSE_DEFAULTS), invalid)
        return L

    def pixels_at(self, factor: float) -> int:
        return int(round(self.width / factor) * round(self.height / factor))

    def nearest(self, want: float) -> Level:
        """The level whose factor is nearest ``want`` (log scale)."""
        return self.level(min(self.factors, key=lambda f: abs(math.log(f / max(want, 1e-9)))))

    def coarse(self, footprint_px: float, n_hypotheses: int) -> Level:
        """The level for the whole-map search: the finest whose pixels fit the budget for ``n_hypotheses`` and
        where the footprint is at most ``template_max`` px, but not so coarse that it is under ``template`` px."""
        c = self.conf
        lo, hi = c["coarse_px"]
        budget = int(min(hi, max(lo, c["coarse_budget"] / max(1, n_hypotheses))))
        fits = [f for f in self.factors if self.pixels_at(f) <= budget and footprint_px / f <= c["template_max"] * 1.12]
        f = min(fits) if fits else max(self.factors)
        if footprint_px / f < c["template"] / 1.12:
            return self.nearest(footprint_px / c["template"])
        return self.level(f)


def turned(query: np.ndarray, scale: float, angle: float) -> np.ndarray:
    """The query resized by ``scale``, cut to its centred square and turned ``angle`` degrees (OpenCV,
    counter-clockwise) on the same square (the corners that leave it lie outside the compared disk)."""
    q = resize(query, scale)
    h, w = q.shape[:2]
    d = min(h, w)
    q = q[(h - d) // 2 : (h - d) // 2 + d, (w - d) // 2 : (w - d) // 2 + d]
    if angle % 360 == 0:
        return q
    R = cv2.getRotationMatrix2D((d / 2 - 0.5, d / 2 - 0.5), angle, 1.0)
    return cv2.warpAffine(q, R, (d, d), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def hypotheses(angles: tuple[float, ...], scale_lo: float, scale_hi: float, step: float) -> tuple[list, list]:
    """Heading and scale ladders: ``angles`` as given, scales geometric from ``scale_lo`` to ``scale_hi`` at most
    ``step`` apart (each rung the centre of its step)."""
    n = max(1, math.ceil(math.log(scale_hi / scale_lo) / math.log(step) - 1e-9))
    if n == 1:
        return list(angles), [math.sqrt(scale_lo * scale_hi)]
    r = (scale_hi / scale_lo) ** (1 / n)
    return list(angles), [scale_lo * r ** (k + 0.5) for k in range(n)]


def _top_peaks(peaks: np.ndarray, k: int, radius: float) -> list[tuple[int, int]]:
    p = peaks.copy()
    out = []
    r = max(1, int(round(radius)))
    for _ in range(k):
        y, x = np.unravel_index(int(p.argmax()), p.shape)
        if p[y, x] <= -1:
            break
        out.append((int(y), int(x)))
        p[max(0, y - r) : y + r + 1, max(0, x - r) : x + r + 1] = -1
    return out


def coarse_search(pyr: MapPyramid, query: np.ndarray, angles: list, scales: list) -> list[Hypothesis]:
    """Distinct peaks over every (heading, scale) hypothesis at one coarse level, ranked by the standard score of
    each hypothesis's response (comparable across template sizes)."""
    side = max(query.shape[:2])
    L = pyr.coarse(side * math.sqrt(min(scales) * max(scales)), len(angles) * len(scales))
    f = L.factor
    H, W = L.features.shape[:2]
    peaks = np.full((H, W), -1.0, np.float32)
    arg = np.zeros((H, W, 2), np.float32)
    for s in scales:
        for a in angles:
            q = turned(query, s / f, a)
            res = L.correlator(orientation_features(q, DENSE_DEFAULTS)) if min(q.shape[:2]) >= 8 else None
            if res is None:
                continue
            res = L.valid_placements(res, q.shape[0])
            ok = res > -1.0
            if not ok.any():
                continue
            mu, sd = float(res[ok].mean()), float(res[ok].std()) + 1e-6
            res = np.where(ok, (res - mu) / sd / 10.0, -1.0)
            o = q.shape[0] // 2
            view = peaks[o : o + res.shape[0], o : o + res.shape[1]]
            better = res > view
            view[better] = res[better]
            arg[o : o + res.shape[0], o : o + res.shape[1]][better] = (a, s)
    k = pyr.conf["candidates"]
    found = [
        Hypothesis((x + 0.5) * f, (y + 0.5) * f, float(arg[y, x, 0]), float(arg[y, x, 1]), float(peaks[y, x]), f)
        for y, x in _top_peaks(peaks, k, radius=pyr.conf["exclusion"] * side * max(scales) / f)
    ]
    return _distinct(sorted(found, key=lambda h: -h.score), k, pyr.conf["exclusion"] * side)


def _distinct(cands: list[Hypothesis], k: int, radius_per_scale: float) -> list[Hypothesis]:
    kept: list[Hypothesis] = []
    for h in cands:
        if all(h.distance(o) > radius_per_scale * o.scale for o in kept):
            kept.append(h)
        if len(kept) >= k:
            break
    return kept


def local_search(pyr: MapPyramid, query: np.ndarray, h: Hypothesis, angles, scales, template: float) -> Hypothesis:
    """The best of ``angles`` x ``scales`` with the query centre within a quarter footprint of ``h``, at the
    level where the footprint is ~``template`` px; one window's spectra serve every hypothesis."""
    side = max(query.shape[:2])
    L = pyr.nearest(side * h.scale / template)
    f = L.factor
    Hh, Ww = L.features.shape[:2]
    dmax = side * max(scales) / f
    m = int(math.ceil(0.25 * dmax)) + 2
    cx, cy = h.col / f, h.row / f
    x0, y0 = max(0, int(round(cx - dmax / 2)) - m), max(0, int(round(cy - dmax / 2)) - m)
    x1, y1 = min(Ww, int(round(cx + dmax / 2)) + m + 1), min(Hh, int(round(cy + dmax / 2)) + m + 1)
    if min(x1 - x0, y1 - y0) < 8:
        return h
    corr = DiskCorrelator(L.features[y0:y1, x0:x1])
    best = None
    for s in scales:
        for a in angles:
            q = turned(query, s / f, a)
            d = q.shape[0]
            res = corr(orientation_features(q, DENSE_DEFAULTS))
            if res is None:
                continue
            res = L.valid_placements(res, d, y0, x0)
            yy, xx = np.ogrid[: res.shape[0], : res.shape[1]]
            near = (np.abs(x0 + xx + d / 2 - cx) <= m) & (np.abs(y0 + yy + d / 2 - cy) <= m)
            res = np.where(near, res, -1.0)
            y, x = np.unravel_index(int(res.argmax()), res.shape)
            if best is None or res[y, x] > best.score:
                sy, sx = _subpixel(res, y, x)
                best = Hypothesis((x0 + sx + d / 2) * f, (y0 + sy + d / 2) * f, a, s, float(res[y, x]), f)
    return best or h


def refine(pyr: MapPyramid, query, h: Hypothesis, a_step: float, s_step: float, templates, rounds: int):
    """Coarse to fine around ``h``: at each template size, heading ±a_step/2 and scale x/÷ sqrt(s_step), the
    steps halved every round. Returns the refined hypothesis and the final steps."""
    for t in templates:
        for _ in range(rounds):
            r = math.sqrt(s_step)
            angles = (h.angle - a_step / 2, h.angle, h.angle + a_step / 2)
            h = local_search(pyr, query, h, angles, (h.scale / r, h.scale, h.scale * r), t)
            a_step, s_step = a_step / 2, math.sqrt(s_step)
    return h, a_step, s_step


def sweep(pyr: MapPyramid, query: np.ndarray, angles, scale_lo: float, scale_hi: float) -> SweepResult | None:
    """The query's placements over the whole map, best first: ``angles`` (OpenCV degrees) and scales in
    [``scale_lo``, ``scale_hi``] map px per query px. None when no hypothesis fits the map."""
    c = pyr.conf
    finest = c["final_template"] or c["refine_template"]
    k = min(1.0, 1.6 * finest / max(query.shape[:2]))  # shrink once, not per hypothesis
    small = resize(query, k) if k < 1 else query
    a_step = _angle_step(angles)
    angles, scales = hypotheses(tuple(angles), scale_lo / k, scale_hi / k, c["scale_step"])
    s_step = (scale_hi / scale_lo) ** (1 / len(scales)) if len(scales) > 1 else max(1.0, scale_hi / scale_lo)
    coarse = coarse_search(pyr, small, angles, scales)
    if not coarse:
        return None
    refined = [
        refine(pyr, small, h, a_step, s_step, (c["refine_template"],), c["rounds"])[0] for h in coarse[: c["refined"]]
    ]
    refined.sort(key=lambda h: -h.score)
    best = refined[0]
    far = [h for h in refined[1:] if h.distance(best) > c["exclusion"] * max(small.shape[:2]) * best.scale]
    second = far[0].score if far else max((h.score for h in coarse[1:]), default=0.0)
    ratio = best.score / second if second > 1e-6 else math.inf
    if c["final_template"]:
        final_a, final_s = a_step / 2 ** (2 * c["rounds"]), s_step ** (0.5 ** (2 * c["rounds"]))
        best = refine(pyr, small, best, final_a, final_s, (c["final_template"],), 1)[0]
    out = [best, *(h for h in refined[1:])]
    full = tuple(Hypothesis(h.col, h.row, h.angle % 360.0, h.scale * k, h.score, h.factor) for h in out)
    return SweepResult(full, ratio, len(angles) * len(scales), {"coarse_score": coarse[0].score})


def _angle_step(angles) -> float:
    a = sorted(float(x) % 360.0 for x in angles)
    if len(a) < 2:
        return 4.0
    gaps = [b - x for x, b in itertools.pairwise(a)] + [a[0] + 360.0 - a[-1]]
    return max(4.0, min(g for g in gaps if g > 1e-9))
