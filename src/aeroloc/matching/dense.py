"""Dense structural matching: where a query of known scale and rough heading lies on the map.

Local features describe texture, and texture is what changes between seasons and years (crops, water levels,
colours), so cross-season satellite queries can share almost no matchable keypoints with the map although field
boundaries, roads and shorelines still coincide. CFOG (channel features of orientated gradients; Ye et al.,
"Fast and robust matching for multimodal remote sensing image registration", IEEE TGRS 2019) describes every
pixel by its gradient magnitude in a few orientation bins, polarity-free (a shoreline is a shoreline whether the
water is darker or lighter than the field), smoothed and normalised per pixel. Matching is a normalised
cross-correlation (the channels together) over every position of a search region (FFT, the region's spectra
computed once) at a few headings around north or all around, so it needs the query's ground resolution (scale).

The answer is trusted only when its correlation peak is both high and distinct: ``score`` (normalised
correlation) above ``min_score`` and ``ratio`` (best peak over the best peak a query footprint away) above
``min_ratio``. A query outside the searched region, or with no shared structure, has no distinct peak.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from aeroloc.core.frames import resize

DEFAULTS = {
    "bins": 6,  # orientation bins over 0-180° (polarity-free)
    "grad_sigma": 1.0,  # px: smoothing before the gradient (JPEG noise)
    "sigma": 1.5,  # px: spatial smoothing of each orientation channel
    "angles": (-15.0, -7.5, 0.0, 7.5, 15.0),  # turns of the query searched, degrees (see DenseMatch.angle)
    # acceptance, measured on NAIP: the 120 dev queries scored >= 0.24 with ratios >= 1.27 (118 of them >= 1.4),
    # all placed within 10 m; wrong answers (each dev and dev-rotated query searched with its true area masked, and
    # the 31 dev-rotated queries turned beyond the searched headings) scored <= 0.25 with ratios <= 1.33
    "min_score": 0.2,
    "min_ratio": 1.4,
    "exclusion": 0.5,  # the second peak is sought this many query sides away from the best one
    "scales": (0.9, 0.95, 1.0, 1.05, 1.1),  # refined around the peak: the query resolution's uncertainty
}


ANY_HEADING = tuple(float(a) for a in np.arange(-180.0, 180.0, 7.5))  # heading unknown: 48 headings


def heading_angles(conf: dict | None, north_up: bool) -> dict:
    """``conf`` with the headings to search: around north (``DEFAULTS``) when the queries are north-up, else
    every 7.5° (about 10x the time). On NAIP dev-rotated (any heading) the full circle placed all 40 queries
    within 15 m; 30 of them distinctly enough to be trusted, against 0 of the same searches with the true area
    masked."""
    out = {**DEFAULTS, **(conf or {})}
    if not north_up and "angles" not in (conf or {}):  # headings the caller chose are kept
        out["angles"] = ANY_HEADING
    return out


@dataclass
class DenseMatch:
    x: float  # query centre in region pixels (pixel-edge origin), sub-pixel
    y: float
    angle: float  # degrees the query's content is turned clockwise from the map (undone by OpenCV's rotation by it)
    score: float
    ratio: float
    scale: float = 1.0  # the query's size on the map relative to the given resolution (local refinement)

    def trusted(self, conf: dict) -> bool:
        return self.score >= conf["min_score"] and self.ratio >= conf["min_ratio"]


def orientation_features(rgb: np.ndarray, conf: dict = DEFAULTS) -> np.ndarray:
    """CFOG descriptor image: H x W x bins float32, unit L2 norm per pixel (flat areas near zero).

    Per orientation bin: |cos t gx + sin t gy| blurred, then each bin smoothed with its two neighbours (circular),
    then the per-pixel norm. Computed in float64 (the bins' angles are float64) one bin plane at a time: the same
    operations in the same order as on the H x W x bins stack, so the same bits, at ~0.65x the time (stacking,
    rolling and reducing the bins' last axis was half of it: 31 -> 20 ms for a 440 px refinement window)."""
    g = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32) if rgb.ndim == 3 else rgb.astype(np.float32)
    g = cv2.GaussianBlur(g, (0, 0), conf["grad_sigma"])
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3).astype(np.float64)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3).astype(np.float64)
    n = conf["bins"]
    chans = []
    for k in range(n):
        t = np.pi * k / n
        a = np.cos(t) * gx
        a += np.sin(t) * gy
        chans.append(cv2.GaussianBlur(np.abs(a, out=a), (0, 0), conf["sigma"]))
    smooth = []  # (previous + 2 x this) + next, / 4: smoothing across the (circular) orientation
    for k in range(n):
        v = 2 * chans[k]
        v += chans[k - 1]
        v += chans[(k + 1) % n]
        v /= 4
        smooth.append(v)
    sq = smooth[0] * smooth[0]
    for v in smooth[1:]:
        sq += v * v
    norm = np.sqrt(sq)
    eps = 1e-3 * float(norm.mean())
    norm += eps  # (norm + eps) + 1e-12, in that order
    norm += 1e-12
    out = np.empty((*g.shape, n), np.float32)
    for k, v in enumerate(smooth):
        out[..., k] = v / norm
    return out


def _rotated_inner(image: np.ndarray, angle: float) -> np.ndarray:
    """``image`` rotated ``angle`` degrees counter-clockwise about its centre, cropped to the centred square-ish
    part with no border pixels (so the border does not correlate with anything)."""
    h, w = image.shape[:2]
    if angle == 0:
        return image
    R = cv2.getRotationMatrix2D((w / 2 - 0.5, h / 2 - 0.5), angle, 1.0)
    rot = cv2.warpAffine(image, R, (w, h), flags=cv2.INTER_LINEAR)
    c, s = abs(np.cos(np.radians(angle))), abs(np.sin(np.radians(angle)))
    # largest axis-aligned rectangle of the same aspect inside the rotated one
    k = min(w / (w * c + h * s), h / (w * s + h * c))
    mw, mh = int(np.ceil(w * (1 - k) / 2)) + 1, int(np.ceil(h * (1 - k) / 2)) + 1
    return rot[mh : h - mh, mw : w - mw]


def _subpixel(res: np.ndarray, y: int, x: int) -> tuple[float, float]:
    """Parabolic peak interpolation along each axis."""

    def off(a, b, c):
        d = a - 2 * b + c
        return 0.0 if d >= 0 else float(np.clip(0.5 * (a - c) / d, -0.5, 0.5))

    dx = off(res[y, x - 1], res[y, x], res[y, x + 1]) if 0 < x < res.shape[1] - 1 else 0.0
    dy = off(res[y - 1, x], res[y, x], res[y + 1, x]) if 0 < y < res.shape[0] - 1 else 0.0
    return y + dy, x + dx


def _box_sums(integral: np.ndarray, h: int, w: int) -> np.ndarray:
    """Sums over every h x w window (top-left offsets) from a (H+1) x (W+1) integral image."""
    return integral[h:, w:] - integral[:-h, w:] - integral[h:, :-w] + integral[:-h, :-w]


class Correlator:
    """Normalised cross-correlation of a multi-channel template at every position of a multi-channel region: the
    channels are one vector per pixel (zero-mean per channel), so one score in [-1, 1] per placement.

    The region's spectra (FFT, padded to a fast length no smaller than the region: 'valid' placements never wrap)
    and integral images are computed once; a template then costs one FFT per channel and one inverse FFT."""

    def __init__(self, region_f: np.ndarray):
        from scipy import fft

        self.H, self.W, self.C = region_f.shape
        self.P, self.Q = fft.next_fast_len(self.H, real=True), fft.next_fast_len(self.W, real=True)
        f = np.moveaxis(region_f, -1, 0)
        self.spectra = fft.rfft2(f.astype(np.float32), s=(self.P, self.Q), workers=-1)  # complex64
        sq = np.zeros((self.H + 1, self.W + 1), np.float64)
        self.sums = []
        for k in range(self.C):
            s, s2 = cv2.integral2(np.ascontiguousarray(f[k], dtype=np.float64))
            self.sums.append(s)
            sq += s2
        self.squares = sq
        self._spread: dict[tuple[int, int], np.ndarray] = {}  # per template size: sqrt of the windows' variance sums

    def __call__(self, query_f: np.ndarray) -> np.ndarray | None:
        """Scores of every placement (top-left offsets, (H-h+1) x (W-w+1)); None when the template does not fit."""
        from scipy import fft

        h, w = query_f.shape[:2]
        if h > self.H or w > self.W or h < 8 or w < 8:
            return None
        q = np.moveaxis(query_f, -1, 0)
        q = (q - q.mean(axis=(1, 2), keepdims=True)).astype(np.float32)
        qnorm = float(np.sqrt((q.astype(np.float64) ** 2).sum()))
        qs = fft.rfft2(q[:, ::-1, ::-1], s=(self.P, self.Q), workers=-1)  # convolution with the flipped template
        num = fft.irfft2((self.spectra * qs).sum(0), s=(self.P, self.Q), workers=-1)[h - 1 : self.H, w - 1 : self.W]
        spread = self._spread.get((h, w))
        if spread is None:  # the same for every template of this size (e.g. headings of opposite sign)
            var = _box_sums(self.squares, h, w) - sum(_box_sums(s, h, w) ** 2 for s in self.sums) / (h * w)
            if len(self._spread) >= 8:  # bounded: a whole-map region serves every query of a run
                self._spread.pop(next(iter(self._spread)))
            spread = self._spread[(h, w)] = np.sqrt(np.maximum(var, 0.0)).astype(np.float32)
        den = qnorm * spread
        return np.where(den > 1e-6, num / np.maximum(den, 1e-6), 0.0).astype(np.float32)


def correlate(region_f: np.ndarray, query_f: np.ndarray) -> np.ndarray | None:
    """:class:`Correlator` for a one-off region (the refinement's small windows)."""
    return Correlator(region_f)(query_f)


class DenseRegion:
    """A map region at the working ground resolution, described once (CFOG) for many :meth:`locate` calls."""

    def __init__(self, rgb: np.ndarray, valid: np.ndarray | None = None, conf: dict | None = None):
        self.conf = {**DEFAULTS, **(conf or {})}
        self.shape = rgb.shape[:2]
        # integral image of the no-data pixels, once per region; None when there are none
        self.invalid = None if valid is None or valid.all() else cv2.integral((~valid).astype(np.uint8))
        self.features = orientation_features(rgb, self.conf)
        self.correlator = Correlator(self.features)

    def locate(self, query: np.ndarray, angles=None, scales=None) -> DenseMatch | None:
        """Where ``query`` (RGB at the region's ground resolution) lies: every heading of ``angles`` (default
        ``conf["angles"]``) at every position (score and distinctness), then the peak refined locally, first over
        ±half an angle step, then over ``scales`` (default ``conf["scales"]``, for a query resolution known to a
        few per cent: off by 10 %, the global peak still lands on the right place but its centre 25-60 m off).
        None when the query does not fit."""
        conf = self.conf
        angles = conf["angles"] if angles is None else angles
        best = _search(self.correlator, query, angles, conf, self.invalid)
        if best is None:
            return None
        step = _angle_step(angles)
        found = best
        for a in (best.angle - step / 2, best.angle + step / 2) if step else ():
            found = self._refine(query, found, best, a, 1.0)
        turned = found.angle
        for sc in conf["scales"] if scales is None else scales:
            if sc != 1.0:
                found = self._refine(query, found, best, turned, sc)
        return found

    def _refine(self, query: np.ndarray, found: DenseMatch, peak: DenseMatch, angle: float, scale: float) -> DenseMatch:
        """``found``, or the query at ``angle`` and ``scale`` placed near ``peak`` if that scores higher."""
        q = _rotated_inner(resize(query, scale), angle)
        h, w = q.shape[:2]
        # every placement whose centre is within m px of the peak: 2 px, plus what the scale change moves
        m = 2 + int(np.ceil(abs(1 - scale) * max(h, w) / 2))
        x0, y0 = max(0, int(round(peak.x - w / 2)) - m), max(0, int(round(peak.y - h / 2)) - m)
        x1, y1 = min(self.shape[1], x0 + w + 2 * m), min(self.shape[0], y0 + h + 2 * m)
        res = correlate(self.features[y0:y1, x0:x1], orientation_features(q, self.conf))
        if res is None:
            return found
        if self.invalid is not None:  # the integral's window starts one row and column before its first pixel
            res = np.where(_placement_valid(self.invalid[y0 : y1 + 1, x0 : x1 + 1], (h, w)), res, -1.0)
        y, x = np.unravel_index(int(res.argmax()), res.shape)
        if res[y, x] <= found.score:
            return found
        sy, sx = _subpixel(res, y, x)
        return DenseMatch(x0 + sx + w / 2, y0 + sy + h / 2, angle, float(res[y, x]), peak.ratio, scale)


def _angle_step(angles) -> float:
    a = sorted(angles)
    return float(min(np.diff(a))) if len(a) > 1 else 0.0


def _search(
    correlator: Correlator, query: np.ndarray, angles, conf: dict, invalid: np.ndarray | None = None
) -> DenseMatch | None:
    """The best placement of ``query`` (RGB, at the region's ground resolution) in the region of ``correlator``,
    over ``angles``; None when the query is larger than the region at every heading.

    ``invalid`` (integral image of the region's no-data pixels) excludes placements that would cover any."""
    best = None  # (score, angle, response, shape)
    peaks = None  # per query-centre pixel: the best score over the headings so far (memory: one region)
    for a in angles:
        q = _rotated_inner(query, a)
        res = correlator(orientation_features(q, conf))
        if res is None:
            continue
        if invalid is not None:
            res = np.where(_placement_valid(invalid, q.shape[:2]), res, -1.0).astype(np.float32)
        if peaks is None:
            peaks = np.full((correlator.H, correlator.W), -1.0, np.float32)
        oy, ox = q.shape[0] // 2, q.shape[1] // 2  # a placement's top-left offset -> its centre pixel
        view = peaks[oy : oy + res.shape[0], ox : ox + res.shape[1]]
        np.maximum(view, res, out=view)
        if best is None or res.max() > best[0]:
            best = (float(res.max()), a, res, q.shape[:2])
    if best is None:
        return None
    score, angle, res, (h, w) = best
    y, x = np.unravel_index(int(res.argmax()), res.shape)
    # the strongest peak a footprint away from the best centre, over every heading
    r = conf["exclusion"] * max(h, w)
    yy, xx = np.ogrid[: peaks.shape[0], : peaks.shape[1]]
    far = (yy - (y + h // 2)) ** 2 + (xx - (x + w // 2)) ** 2 > r * r
    second = float(peaks[far].max()) if far.any() else -1.0
    sy, sx = _subpixel(res, y, x)
    ratio = score / second if second > 1e-6 else float("inf")
    return DenseMatch(sx + w / 2, sy + h / 2, angle, score, ratio)


def _placement_valid(invalid: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """For every top-left offset, whether the placed query covers only valid pixels (``invalid``: integral image
    of the no-data pixels)."""
    return _box_sums(invalid, *shape) < 0.5
