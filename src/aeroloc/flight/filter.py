"""The position filter: a Kalman filter on the frame centre over the map, with outlier gating.

Why not a particle filter: every absolute fix here is a single verified peak (a dense correlation or a RANSAC
homography), not a multimodal likelihood, and the global re-localization already handles the one case a
particle cloud is for (not knowing where you are). With unimodal inputs a Kalman filter gives the same estimate
as a particle filter at a fraction of the cost (two numbers per frame, not thousands), which is what the
10 frames per second budget needs. The uncertainty is isotropic (one sigma, metres): odometry errors on a nadir
camera have no preferred direction.

Motion: the odometry step when there is one (its error grows with the distance moved), else the last velocity
over the time step, turned at the last turn rate (the frames' rotation: a camera fixed to an airframe that flies
where it points; a turn does not stop when the camera goes black), with an uncertainty growing at a share of the
speed bound (the aircraft may have changed its turn or speed). A fix is used only when it falls within the gate (``gate_sigmas`` of the combined uncertainty, at
least ``gate_floor_m``): one bad fix can't drag the track. Within the gate a fix far from the prediction counts for less
(``robust_sigmas``: beyond that many sigmas of the combined uncertainty its variance grows with the distance
squared, a Cauchy-like weight): a wrong fix just inside the gate would otherwise pull with its full gain. Too many rejected (or failed) fixes in a row, or an uncertainty
beyond ``lost_sigma_m``, and the track is lost: the tracker re-localizes globally.

The sigma a track reports (:attr:`PositionFilter.reported_sigma`) is never below the last fused fix's own: the
windowed fixes of overlapping frames see the same ground and share their errors (correlation 0.67 two frames
apart, 0.19 ten apart, on 1,054 NAIP fixes), so fusing them shrinks the filter's sigma without making the track
surer. The filter itself keeps the Kalman sigma for its gain and gate (with the fixes' sigma doubled instead the
NAIP tracks were no better, README #14).
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class FilterConfig:
    speed_max_mps: float = 60.0  # the speed bound: no aircraft step is larger than this x the time step
    coast_share: float = 0.5  # coasting: sigma grows by this share of the speed bound per second
    vo_rel: float = 0.02  # odometry: relative error of a step's length (with a height or the baseline scale: NAIP
    # steps 0.5-1 % off; 0.03 let biased fixes drag the track, 0.01 let the scale's drift through)
    vo_rel_unchecked: float = 0.04  # ... while the scale is a global fix's or carried over a gap, unchecked by a
    # baseline (NAIP, after an outage in which the aircraft climbed: +4 % and 3° off, the track lagged 10-13 m)
    vo_abs_m: float = 0.5  # odometry: error added per step, metres
    fix_sigma_m: float = 5.0  # while the uncertainty is beyond this, a windowed fix is sought on every frame
    # a windowed fix's error (1 sigma, before its score's weighting): this many map px, at least fix_sigma_min_m.
    # It was 5 m (NAIP's pixel) on every map: on the szada-hu (1.5 m/px) flight without metadata a fix 21 m from a
    # track 2.7 m sure passed the gate and moved it 7 m off (frames within t 0.972 -> 1.000 with 1 px, 2 m); NAIP's
    # 5 m/px map keeps its 5 m. The floor: two dates of imagery agree to ~2 m, not to a 0.5 m pixel (levir-tx
    # flights: median error 2.2 m; Toledo flight 1 against its GPS, 1 m floor: 3/10 within 5 m, 2 m: 5/10)
    fix_sigma_px: float = 1.0
    fix_sigma_min_m: float = 2.0
    global_sigma_m: float = 5.0
    gate_sigmas: float = 4.0
    gate_floor_m: float = 10.0
    # a fix farther than this many sigmas (of the combined uncertainty) counts as if its variance were (r / this)^2
    # larger (0: every fix inside the gate with its full gain). NAIP flights, 957 windowed fixes logged against the
    # truth: of those accepted 2-4 sigmas from the prediction, 18 of 64 lay nearer the truth than the prediction
    # (0 of 6 at 3.5-4), against 294 of 713 within 1 sigma
    robust_sigmas: float = 2.0
    max_rejects: int = 6  # fixes rejected in a row before the track counts as lost (with a confirmed odometry
    # scale only once the uncertainty is beyond miss_sigma_m too: NAIP telemetry flight, 6 fixes of overlapping
    # frames over changed ground 45-53 m off a track 6 m off lost it, and the re-localization took their place)
    lost_sigma_m: float = 150.0
    max_misses: int = 15  # windowed fixes failed in a row (no distinct match) before the track counts as lost,
    miss_sigma_m: float = 10.0  # ... once the uncertainty is beyond this too (NAIP: 18 frames over changed ground
    # without a distinct match while the odometry alone stayed within 5 m: lost on misses, then 200 frames lost)
    coast_max_m: float = 600.0  # blank frames coast on up to this uncertainty (a position with an honest sigma;
    # the first frame after them is searched around it), beyond it the track is lost
    max_unfixed_s: float = 20.0  # ... or at least 2 failed and no fix for this long (photos seconds apart)
    compass_speed_share: float = 0.2  # coasting on a compass's turns: the ground speed may change this much (wind,
    # throttle); the heading by the compass's tolerance


@dataclass
class Estimate:
    x: float  # metres east in the map's pixel frame (map px x map gsd)
    y: float  # metres south
    sigma: float  # metres, 1 sigma
    vx: float = 0.0  # m/s
    vy: float = 0.0
    turn_dps: float = 0.0  # the velocity's turn rate, degrees/s, positive from east towards south (map rows)


class PositionFilter:
    def __init__(self, config: FilterConfig | None = None):
        self.cfg = config or FilterConfig()
        self.est: Estimate | None = None
        self.rejects = 0
        self.misses = 0
        self.unfixed_s = 0.0  # seconds since the last fused fix
        self.checked = False  # whether the last odometry step's scale was confirmed (a height, a baseline)
        self.fix_sigma = 0.0  # the last fused fix's (or reset's) sigma: what the reported sigma never goes below

    @property
    def lost(self) -> bool:
        return self.lost_now(blind=False)

    def lost_now(self, blind: bool) -> bool:
        """Whether the track is lost; ``blind``: the frame showed nothing (black), so only an uncertainty beyond
        ``coast_max_m`` loses it (misses and rejections cannot grow without an image)."""
        e = self.est
        c = self.cfg
        if e is None:
            return True
        stale = self.misses >= 2 and self.unfixed_s > c.max_unfixed_s
        return (
            e.sigma > (c.coast_max_m if blind else c.lost_sigma_m)
            or (self.rejects >= c.max_rejects and (e.sigma > c.miss_sigma_m or not self.checked))
            or (self.misses >= c.max_misses and e.sigma > c.miss_sigma_m)
            or stale
        )

    @property
    def reported_sigma(self) -> float:
        """The track's uncertainty (metres, 1 sigma) as told to its users: the filter's, at least the last fix's
        (module docstring); NaN without a position."""
        return math.nan if self.est is None else max(self.est.sigma, self.fix_sigma)

    def reset(self, x: float, y: float, sigma: float) -> None:
        self.est, self.rejects, self.misses, self.unfixed_s = Estimate(x, y, sigma), 0, 0, 0.0
        self.fix_sigma = sigma

    def lose(self) -> None:
        self.est, self.rejects, self.misses, self.fix_sigma = None, 0, 0, 0.0

    def predict_odometry(
        self, dx: float, dy: float, dt: float, turn_deg: float = 0.0, checked: bool = True, heading_tol_deg: float = 0.0
    ) -> None:
        """Move by an odometry step (metres) in which the frame turned by ``turn_deg`` (the content's turn, the
        project's convention: the opposite of the aircraft's); the step also refreshes velocity and turn rate.
        ``checked``: whether the scale the step was measured at is confirmed (a height, a baseline).
        ``heading_tol_deg``: how far the heading the step is laid out at may be off (a turn made while blind):
        the step may point that much elsewhere, so the uncertainty grows by its length x sin(that), linearly (a
        heading error turns every step the same way)."""
        e, c = self.est, self.cfg
        self.unfixed_s += max(dt, 0.0)
        self.checked = checked
        d = math.hypot(dx, dy)
        if dt > 0 and d > c.speed_max_mps * dt * 1.5:  # an impossible step: the pair matched wrongly
            self.predict_coast(dt)
            return
        e.x, e.y = e.x + dx, e.y + dy
        e.sigma = math.hypot(e.sigma, (c.vo_rel if checked else c.vo_rel_unchecked) * d + c.vo_abs_m)
        e.sigma += d * math.sin(math.radians(min(max(heading_tol_deg, 0.0), 90.0)))
        if dt > 0:  # the old velocity turned with the aircraft, the step's chord by half its turn (an arc's end)
            a = -math.radians(turn_deg)
            ox, oy = _turned(e.vx, e.vy, a)
            nx, ny = _turned(dx / dt, dy / dt, a / 2)
            e.vx, e.vy = 0.5 * ox + 0.5 * nx, 0.5 * oy + 0.5 * ny
            e.turn_dps = 0.5 * e.turn_dps - 0.5 * turn_deg / dt

    def predict_coast(self, dt: float, turn_deg: float | None = None, turn_tol_deg: float = 0.0) -> None:
        """Carry the estimate on for ``dt`` seconds without an image step: along the last velocity turned at the
        last turn rate, the uncertainty growing at ``coast_share`` of the speed bound. ``turn_deg``: the turn a
        compass measured over the step instead (the content's turn, the project's convention), good to
        ``turn_tol_deg``: the velocity follows it, and the uncertainty grows only with what the compass leaves
        open, a heading off by its tolerance and the speed changing by ``compass_speed_share`` (never faster than
        without it)."""
        e, c = self.est, self.cfg
        self.unfixed_s += max(dt, 0.0)
        if turn_deg is not None and dt > 0:
            e.turn_dps = -turn_deg / dt
        a = math.radians(e.turn_dps * dt)
        cx, cy = _turned(e.vx, e.vy, a / 2)  # along the arc: the chord is the velocity turned by half the arc
        chord = math.sin(a / 2) / (a / 2) if abs(a) > 1e-9 else 1.0
        e.x, e.y = e.x + cx * dt * chord, e.y + cy * dt * chord
        speed = math.hypot(e.vx, e.vy)
        e.vx, e.vy = _turned(e.vx, e.vy, a)
        rate = c.coast_share * c.speed_max_mps  # linear: an unseen turn is a drift, not a random walk
        if turn_deg is not None:
            rate = min(rate, (math.sin(math.radians(min(turn_tol_deg, 90.0))) + c.compass_speed_share) * speed)
        e.sigma += rate * dt

    def gate(self, sigma_fix: float) -> float:
        """The largest distance (metres) from the prediction a fix may lie at."""
        return max(self.cfg.gate_floor_m, self.cfg.gate_sigmas * math.hypot(self.est.sigma, sigma_fix))

    def update(self, x: float, y: float, sigma_fix: float) -> tuple[bool, float]:
        """Fuse a fix (metres) if it passes the gate; (accepted, distance from the prediction)."""
        e = self.est
        d = math.hypot(x - e.x, y - e.y)
        if d > self.gate(sigma_fix):
            self.rejects += 1
            return False, d
        r = d / math.hypot(e.sigma, sigma_fix)
        var_fix = sigma_fix**2 * (max(1.0, r / self.cfg.robust_sigmas) ** 2 if self.cfg.robust_sigmas > 0 else 1.0)
        k = e.sigma**2 / (e.sigma**2 + var_fix)
        e.x, e.y = e.x + k * (x - e.x), e.y + k * (y - e.y)
        e.sigma = math.sqrt((1 - k) * e.sigma**2)
        self.rejects, self.unfixed_s, self.fix_sigma = 0, 0.0, sigma_fix
        return True, d


def _turned(x: float, y: float, a: float) -> tuple[float, float]:
    """(x, y) turned by ``a`` radians from east towards south (the map's pixel axes)."""
    return x * math.cos(a) - y * math.sin(a), x * math.sin(a) + y * math.cos(a)
