"""Absolute fixes from the map around the predicted position only: the dense stage on a window.

The window is the predicted footprint grown by the position uncertainty (``sigma_k`` sigmas, at least
``min_margin`` of the footprint), so the work per frame does not depend on the map's size. Frame and window are
brought to one working resolution, the coarser of the frame's (its pose's scale), the map's, and the footprint
over ``work_side`` px: a structural (CFOG) correlation needs shapes, not pixels, and this keeps a frame at
~``work_side`` px whatever its size. The headings searched are the pose's turn ± ``turn_span``, the scales its
scale ± ``scale_span`` (the self-calibrated ground resolution). The map is kept downscaled in memory at the
working resolution when it fits (``cache_px``), else every window is read from the file.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from aeroloc.core.frames import resize
from aeroloc.flight.calibration import Pose
from aeroloc.matching.dense import DEFAULTS, DenseRegion


@dataclass(frozen=True)
class WindowConfig:
    work_side: int = 240
    sigma_k: float = 3.0
    min_margin: float = 0.15
    max_window_px: int = 700  # working px: a window wider than this is a global search's job
    turn_span: float = 4.0
    scales: tuple[float, ...] = (0.94, 0.97, 1.03, 1.06)
    min_score: float = 0.2
    broad_score: float = 0.25  # a window wider than half a footprint around the frame: a stricter score (Toledo:
    # a fix at 0.20 in a window grown by coasting was 47 m off)
    min_ratio: float = 1.3  # only when the window holds a second peak a half footprint away
    cache_px: int = 16_000_000


@dataclass
class WindowFix:
    x: float  # frame centre, map px
    y: float
    turn_deg: float
    scale: float  # map px per frame px
    score: float
    ratio: float
    window_px: tuple[int, int]


class WindowMatcher:
    def __init__(self, map_, config: WindowConfig | None = None):
        self.map = map_
        self.cfg = config or WindowConfig()
        self.map_gsd = map_.resolution_m
        self._cache: tuple[float, np.ndarray, np.ndarray] | None = None  # (factor, rgb, valid)
        self.conf = {**DEFAULTS}

    def _levels(self, pose: Pose, size: tuple[int, int]) -> float:
        """Map px -> working px (<= 1), quantised to powers of 2**0.25 so the cached map is reused."""
        foot_m = max(size) * pose.scale * self.map_gsd
        work = max(self.map_gsd, pose.scale * self.map_gsd, foot_m / self.cfg.work_side)
        f = self.map_gsd / work
        return float(2.0 ** (math.floor(math.log2(f) * 4) / 4))

    def _read(self, c0: int, r0: int, c1: int, r1: int, f: float):
        m = self.map
        if m.width * m.height * f * f <= self.cfg.cache_px:
            if self._cache is None or self._cache[0] != f:
                rgb, valid = m.read(0, 0, m.width, m.height)
                self._cache = (f, resize(rgb, f), resize(valid.astype(np.uint8), f, True) > 0)
            _, rgb, valid = self._cache
            a0, b0 = int(c0 * f), int(r0 * f)
            a1, b1 = int(math.ceil(c1 * f)), int(math.ceil(r1 * f))
            return rgb[b0:b1, a0:a1], valid[b0:b1, a0:a1], a0 / f, b0 / f
        rgb, valid = m.read(c0, r0, c1 - c0, r1 - r0)
        return resize(rgb, f), resize(valid.astype(np.uint8), f, True) > 0, float(c0), float(r0)

    def window(self, pose: Pose, size: tuple[int, int], sigma_px: float):
        """(c0, r0, c1, r1) map px of the window to search, None when it is off the map or too large."""
        foot = pose.footprint(size)
        side = max(size) * pose.scale
        margin = max(self.cfg.sigma_k * sigma_px, self.cfg.min_margin * side)
        (x0, y0), (x1, y1) = foot.min(0) - margin, foot.max(0) + margin
        c0, r0 = max(0, int(math.floor(x0))), max(0, int(math.floor(y0)))
        c1, r1 = min(self.map.width, int(math.ceil(x1))), min(self.map.height, int(math.ceil(y1)))
        if c1 - c0 < 16 or r1 - r0 < 16:
            return None
        return c0, r0, c1, r1

    def fits(self, size: tuple[int, int], pose: Pose, sigma_px: float, max_px: int | None = None) -> bool:
        """Whether the window around ``pose`` for ``sigma_px`` is on the map and at most ``max_px`` (default
        ``max_window_px``) working px wide: beyond, a wider search's job."""
        box = self.window(pose, size, sigma_px)
        if box is None:
            return False
        f = self._levels(pose, size)
        return max(box[2] - box[0], box[3] - box[1]) * f <= (max_px or self.cfg.max_window_px)

    def __call__(
        self,
        image: np.ndarray,
        pose: Pose,
        sigma_px: float,
        angles=None,
        max_px: int | None = None,
        min_ratio: float | None = None,
        scales: tuple[float, ...] | None = None,
    ) -> WindowFix | None:
        """The frame placed in the window around ``pose``; None when nothing distinct was found there.
        ``angles`` (default the pose's turn ± ``turn_span``), ``max_px`` and ``min_ratio`` widen the search for a
        re-localization around the last position; ``scales`` (default ``scales`` of the config) the refinement's."""
        size = (image.shape[1], image.shape[0])
        if not self.fits(size, pose, sigma_px, max_px):
            return None
        box = self.window(pose, size, sigma_px)
        f = self._levels(pose, size)
        rgb, valid, ox, oy = self._read(*box, f)
        qk = pose.scale * f  # frame px -> working px
        query = cv2.resize(image, None, fx=qk, fy=qk, interpolation=cv2.INTER_AREA)
        region = DenseRegion(rgb, valid, self.conf)
        c = self.cfg
        t = pose.turn_deg
        angles = (t - c.turn_span, t, t + c.turn_span) if angles is None else angles
        m = region.locate(query, angles=angles, scales=c.scales if scales is None else scales)
        ratio = c.min_ratio if min_ratio is None else min_ratio
        broad = self.cfg.sigma_k * sigma_px > 0.5 * max(size) * pose.scale  # the window holds other placements
        score = c.broad_score if broad else c.min_score
        if m is None or m.score < score or (math.isfinite(m.ratio) and m.ratio < ratio):
            return None
        return WindowFix(
            ox + m.x / f, oy + m.y / f, m.angle, pose.scale * m.scale, m.score, m.ratio, (rgb.shape[1], rgb.shape[0])
        )
