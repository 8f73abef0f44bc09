"""The tracking loop: one flight's frames in, one track point per frame out.

Per frame: odometry against the previous frame moves the pose (or the filter coasts on its velocity); the frame
is matched against the map window around the prediction (:mod:`aeroloc.flight.window_fix`) and the fix goes
through the filter's gate (:mod:`aeroloc.flight.filter`). At the start, and whenever the track is lost, the
single-image pipeline (``Localizer``) searches the whole map, with the self-calibrated ground resolution and
heading as priors once there was a fix. ``source`` says what placed each point: ``global fix``, ``tracked``
(a windowed fix, or odometry from a fix without a break), ``coasted`` (the motion model alone, or odometry carried
on from a coasted position: no map evidence since the break) or ``lost`` (no position).
"""

from __future__ import annotations

import ctypes
import itertools
import math
import time
from dataclasses import dataclass, field, replace

import numpy as np

from aeroloc.core.priors import Priors
from aeroloc.flight.calibration import BaselineScale, Pose, pose_from_dense, pose_from_homography, turn_difference
from aeroloc.flight.filter import Estimate, FilterConfig, PositionFilter, _turned
from aeroloc.flight.frames import FrameRef
from aeroloc.flight.odometry import Odometry
from aeroloc.flight.window_fix import WindowConfig, WindowMatcher

COLUMNS = ["name", "time", "lat", "lon", "status", "sigma_m", "source", "heading_deg", "yaw_deg", "gsd_m", "ms"]
SOURCES = ("global fix", "tracked", "coasted", "lost")


@dataclass(frozen=True)
class TrackConfig:
    filter: FilterConfig = field(default_factory=FilterConfig)
    window: WindowConfig = field(default_factory=WindowConfig)
    blank_std: float = 3.0  # a frame whose grey levels vary less than this is blank (black, lens cap, fog)
    relocalize_heading_dps: float = 10.0  # heading prior after a loss widens by this per second lost
    fix_every: int = 2  # while the uncertainty is below a fix's, a windowed fix on every n-th frame only
    anchor_after: int = 3  # this many rejected fixes in a row that agree with each other re-anchor the track,
    # only while the odometry's scale is unconfirmed (no metadata, no baseline yet: the filter's sigma may be too
    # small); with it, 3 fixes of 95 %-overlapping frames agreeing are no evidence (NAIP telemetry flight: they
    # moved a track 6 m off to 49 m off)
    anchor_spread_px: float = 2.0  # ... agreeing within max(10 m, this many map px)
    anchor_score: float = 0.3  # ... each scoring at least this (NAIP: fixes under 0.3 were 10-45 m off, median 18 m,
    # and three of them, 95 % overlapping frames over the same changed lake shore, 'agreed' on a place 45 m off)
    fix_score_ref: float = 0.4  # a windowed fix's sigma is the filter's fix sigma x (this / score)^fix_score_pow,
    fix_score_pow: float = 1.5  # never less: NAIP fixes at 0.45+ were 3 m off (median), at 0.30-0.35 5-18 m (a
    # power of 3 made the track slow to come back after biased stretches: 0.67 within 10 m vs 0.75 at 1.5)
    scale_score: float = 0.35  # fixes at least this good measure the odometry's scale over long baselines
    scale_fix_score: float = 0.3  # without metadata, accepted fixes at least this good nudge the ground resolution
    # (until a baseline confirms it)
    scale_fix_k: float = 0.1  # ... this share of the way to their refined scale (in log), times the fix's weight
    # (fix sigma at fix_score_ref / its own, squared: a peak scoring 0.3 moves it 0.42 of that; at 0.4 and above all)
    scale_first_fixes: int = 3  # ... the first this many after a global fix refined over scale_first_ladder and
    scale_first_k: float = 0.5  # ... taken this share of the way (NAIP: the pipeline's first fix 8 % small, k = 0.1
    # from the tracking ladder left it 3-4 % small for 30 frames, the track 20-29 m off over changed ground)
    scale_first_ladder: tuple[float, ...] = (0.85, 0.88, 0.91, 0.94, 0.97, 1.03, 1.06, 1.09, 1.12, 1.15)
    turn_fix_score: float = 0.3  # accepted fixes at least this good nudge the heading (weaker ones sat on changed
    # ground: NAIP seed-4 flight, fixes of 0.21-0.28 turned a heading 0.2 deg off to 2.5 deg off in 16 frames)
    near_scale_k: float = 0.5  # a re-localization around the prediction: this share of the way to its scale (the
    # aircraft may have climbed or descended while the frames were missing)
    pipeline_every: int = 2  # while lost: the full single-image pipeline on every n-th frame only (seconds each;
    # it was every 10th: szada-hu seed 2 stayed lost 37 frames after its outage while the dense stage over the
    # whole map took 13-21 s a frame and found nothing, and the pipeline placed the second frame 1.1 m off)
    wide_pipeline_every: int = 3  # a frame searched around the estimate after an outage and not found there: the
    # pipeline too, on the first such frame and every n-th after (levir-tx seed 2: a 180° turn made while blind put
    # the truth beyond the search's reach for 10 frames, and the dense stage over the whole map took 15-30 s a
    # frame and found nothing, while the pipeline placed each of those frames within 2 m in 0.2-0.7 s)
    dense_every: int = 3  # ... and the whole-map dense search on every n-th (the first lost frame included)
    near_share: float = 0.5  # while lost: first search around the last estimate carried on at its velocity, as
    # far as this share of the speed bound x the time since (the coasting model), or the whole bound around the
    # last fix when no velocity is known (a resumed run)
    near_min_m: float = 100.0  # ... at least this far (a track lost to rejected fixes was off by tens of metres)
    near_max_px: int = 1200  # working px of the largest such window (beyond: the whole-map search)
    wide_sigma_m: float = 50.0  # while tracking, an uncertainty beyond this (or a window too large for the tracking
    # window) is searched as widely as a lost track (every heading since the turn was last measured); the tracking
    # window's ±4° and its distinctness rule are for a known heading (NAIP: after a 15 s outage, sigma 470 m, the
    # window clipped by the map's edge still fitted)
    wide_reach_sigmas: float = 1.0  # the search around the estimate reaches this many sigmas of it
    near_inner: float = 0.5  # a peak not distinct over the whole reach is taken when it is distinct within this
    # share of it and is the whole reach's best too: its rivals are all farther from the prediction (less likely)
    near_ratio: float = 1.4  # distinctness asked of a fix found that way (the dense stage's global rule: at 1.2 an
    # ambiguous NAIP field pattern gave a fix 500 m off, which the next, 97 %-overlapping frame 'confirmed')
    vote_frames: int = 12  # ... or the best peak, not distinct, when the best peaks of the last searched frames
    # in a row (at most this many, each scoring >= vote_score), carried on by the odometry, agree, at least
    # vote_frames_min of them, and are distinct together as one frame must be alone (near_ratio), each frame's
    # ratio counting only for the share of the footprint it shows anew (Tracker._vote)
    vote_frames_min: int = 3
    vote_score: float = 0.3  # ... each scoring at least this
    near_confirm: bool = True  # ... or the best peak (scoring >= vote_score) of one frame when local features
    # confirm it (Tracker._confirmed)
    vote_m: float = 15.0  # ... within max(this, 3 map px)
    vote_turn_deg: float = 6.0  # ... and this turn
    trim_native: bool = True  # after a whole-map search, native heap returned to the system (glibc malloc_trim)
    trim_every: int = 500  # ... and every this many frames (aeroloc.flight.run.track_flight; 0: never)
    confirm_below: float = 0.35  # a windowed fix scoring below this is checked by local features
    # (aeroloc.flight.confirm_fix) on every ``confirm_every``-th such fix (~0.1-0.2 s each), and so is each of the
    # first ``confirm_first`` fixes after a re-localization, whatever its score; confirmed with ``confirm_inliers``,
    # it is placed where they put the frame, pulls the track as a fix scoring fix_score_ref would, and moves the
    # heading and (without metadata, before a baseline) the ground resolution ``confirm_k`` of the way to theirs
    confirm_every: int = 5  # 0: off
    confirm_first: int = 3
    confirm_inliers: int = 40  # (windows without the frame's ground: <= 15 in the sweep's confirmations)
    confirm_k: float = 0.5


@dataclass
class TrackPoint:
    name: str
    time: float
    lat: float
    lon: float
    status: str
    sigma_m: float
    source: str
    heading_deg: float = math.nan  # the pose's turn (project convention), for resuming and the dense stage
    yaw_deg: float = math.nan  # compass bearing of the frame's top
    gsd_m: float = math.nan
    ms: float = 0.0

    @property
    def localized(self) -> bool:
        return math.isfinite(self.lat) and math.isfinite(self.lon)

    def row(self) -> dict[str, str]:
        def num(v, fmt):
            return format(v, fmt) if math.isfinite(v) else ""

        return {
            "name": self.name,
            "time": f"{self.time:.3f}",
            "lat": num(self.lat, ".8f"),
            "lon": num(self.lon, ".8f"),
            "status": self.status,
            "sigma_m": num(self.sigma_m, ".2f"),
            "source": self.source,
            "heading_deg": num(self.heading_deg, ".2f"),
            "yaw_deg": num(self.yaw_deg, ".2f"),
            "gsd_m": num(self.gsd_m, ".4f"),
            "ms": f"{self.ms:.1f}",
        }

    @classmethod
    def from_row(cls, r: dict) -> TrackPoint:
        def f(k):
            v = (r.get(k) or "").strip()
            return float(v) if v else math.nan

        return cls(
            r["name"],
            f("time"),
            f("lat"),
            f("lon"),
            r.get("status", ""),
            f("sigma_m"),
            r.get("source", ""),
            f("heading_deg"),
            f("yaw_deg"),
            f("gsd_m"),
            f("ms") if r.get("ms") else 0.0,
        )


def release_native_memory() -> None:
    """Give the C heap's free pages back to the system (glibc ``malloc_trim(0)``; elsewhere nothing): the
    whole-map searches of a lost track allocate and free large native arrays (FFT spectra, model buffers), and
    the freed pages otherwise stay in the process (RSS grew ~100 MB per 100 lost frames)."""
    global _libc
    if _libc is None:
        try:
            _libc = ctypes.CDLL("libc.so.6")
            _libc.malloc_trim.argtypes = [ctypes.c_size_t]
        except (OSError, AttributeError):
            _libc = False
    if _libc:
        _libc.malloc_trim(0)


_libc = None


class Tracker:
    """Frames in time order -> :class:`TrackPoint`; ``localizer`` is a :class:`aeroloc.localization.Localizer`
    (its map is the map tracked on)."""

    def __init__(self, localizer, config: TrackConfig | None = None):
        self.cfg = config or TrackConfig()
        self.localizer = localizer
        self.map = localizer.map
        if self.map is None:
            from aeroloc.core.errors import AerolocError

            raise AerolocError("tracking needs the database's map file (it could not be opened)")
        self.gsd = self.map.resolution_m
        self.matcher = WindowMatcher(self.map, self.cfg.window)
        self.odo = Odometry()
        self.filter = PositionFilter(self.cfg.filter)
        self.pose: Pose | None = None
        self.calibration: Pose | None = None  # the last fixed pose: ground resolution and heading to carry
        self.prev_time: float | None = None
        self.lost_since: float | None = None
        self.rejected: list[tuple[float, float]] = []  # offsets fix - prediction (m) of the fixes rejected in a row
        self.frames_since_fix = 0
        self.weak_fixes = 0  # weak windowed fixes since the last local-feature check of one (confirm_every)
        self.checks_left = 0  # windowed fixes still to check by local features since a re-localization
        self.baseline = BaselineScale()  # the odometry's scale from fix-to-fix baselines (frames without a height)
        self.metric = False  # whether this frame's scale came from its own metadata
        self.scale_settled = False  # a baseline confirmed the scale since the last global fix (fixes stop nudging it)
        self.scale_fixes = 0  # windowed fixes that nudged the scale since the last global fix
        self.lost_frames = 0
        self.wide_frames = 0  # frames in a row searched around the estimate (after an outage) without a fix
        self.cal_time: float | None = None  # when the calibration was last confirmed by a fix
        self.turn_time: float | None = None  # the last frame whose step the heading's uncertainty accounts for (an
        # odometry step, a coasted step, a fix); frames not tracked since (a lost track) add their time too
        self.unseen_turn_s = 0.0  # seconds coasted (no odometry step) since a fix last measured the heading: the
        # odometry measures turns relative to the pose, so a turn made while blind stays in the heading until a fix
        self.candidates: list[tuple[Pose, float, int, float, float]] = []  # recent searched frames' best peaks
        # (carried on by the odometry), their scores, ages in frames, ratios and the footprints flown since
        self._compass_last: float | None = None  # the previous frame's compass heading (telemetry)
        self.compass_step: float | None = None  # the turn it measured to this frame
        self.dead: tuple[Estimate, float, float] | None = None  # the filter's estimate when the track was lost, when,
        # and the pose's turn then
        self.anchored = False  # whether the position is tied to a map fix by odometry alone since: a coasted step
        # breaks the chain (odometry measures relative motion), so the odometry after it places nothing on the map
        # until the next fix and its points are "coasted" (levir-tx flight without metadata: two frames after an
        # outage carried from an estimate 160 m off, sigma 126 m, were reported as tracked)

    # --- resuming ---------------------------------------------------------------------------------------------
    def restore(self, points: list[TrackPoint]) -> None:
        """Continue after ``points`` (a resumed run's finished rows): the last position, pose and velocity, or,
        when the track was lost there, the last fix's calibration for the re-localization."""
        if not points:
            return
        last = points[-1]
        self.prev_time = last.time
        fixed = next((p for p in reversed(points) if p.localized and math.isfinite(p.gsd_m)), None)
        if fixed is None:
            return
        col, row = self.map.latlon_to_pixel(fixed.lat, fixed.lon)
        self.calibration = Pose(float(col), float(row), fixed.heading_deg, fixed.gsd_m / self.gsd)
        self.cal_time = self.turn_time = fixed.time
        self.unseen_turn_s = 0.0
        if fixed is not last:
            self.lost_since = last.time
            return
        self.pose = self.calibration
        self.anchored = last.source in ("global fix", "tracked")
        self.filter.reset(float(col) * self.gsd, float(row) * self.gsd, last.sigma_m)
        prev = points[-2] if len(points) > 1 else None
        if prev is not None and prev.localized and last.time > prev.time:
            pc, pr = self.map.latlon_to_pixel(prev.lat, prev.lon)
            dt = last.time - prev.time
            self.filter.est.vx = (float(col) - float(pc)) * self.gsd / dt
            self.filter.est.vy = (float(row) - float(pr)) * self.gsd / dt

    # --- one frame ----------------------------------------------------------------------------------------------
    def __call__(self, ref: FrameRef, image: np.ndarray | None) -> TrackPoint:
        t0 = time.perf_counter()
        dt = 0.0 if self.prev_time is None else ref.time - self.prev_time
        self.prev_time = ref.time
        self.compass_step = self._compass_turn(ref)
        unusable = self._unusable(image)
        blank = unusable is not None or float(image[::4, ::4].std()) < self.cfg.blank_std
        step = None if blank else self.odo(image)
        if blank:
            self.odo.reset()
        self._carry_candidates(step, None if image is None else (image.shape[1], image.shape[0]))
        if self.filter.est is not None and self.pose is not None:
            point = self._track(ref, image, blank, step, dt, unusable)
        elif blank:
            point = self._point(ref, "lost", unusable or "blank frame")
        else:
            point = self._relocalize(ref, image)
        point.ms = (time.perf_counter() - t0) * 1000
        return point

    def _unusable(self, image) -> str | None:
        """Why a frame can't be matched at all, or None: undecodable, or too small or too elongated for the
        window's working size (a frame is a blank one then: coasted through, never matched; a 6000x240 px strip
        ended the whole track with an OpenCV error in the dense stage)."""
        from aeroloc.localization.screening import too_small

        if image is None:
            return "undecodable frame"
        why = too_small(image.shape[1], image.shape[0], self.cfg.window.work_side)
        return None if why is None else f"unusable frame: {why}"

    def _track(self, ref: FrameRef, image, blank: bool, step, dt: float, unusable: str | None = None) -> TrackPoint:
        size = None if image is None else (image.shape[1], image.shape[0])
        own = self._own_gsd(ref, size)
        self.metric = own is not None  # this frame's scale is its own metadata's, so its step's scale is checked
        moved = False
        if step is not None:
            new = self.pose.moved(step.A, size)
            before = (self.filter.est.x, self.filter.est.y)
            turn = turn_difference(new.turn_deg - self.pose.turn_deg)
            dx, dy = (new.x - self.pose.x) * self.gsd, (new.y - self.pose.y) * self.gsd
            # off the map's chain (coasted since a fix), the heading carries the turns made while blind: a drone
            # that turned 180° in a 15 s outage (levir-tx seed 2) flew its odometry steps backwards, 6 m a frame
            # away from the truth, while the sigma stood at 125 m and the search reached no farther
            blind_turn = 0.0 if self.anchored else self._blind_turn_deg()
            self.filter.predict_odometry(dx, dy, dt, turn, self.metric or self.baseline.checked, blind_turn)
            moved = (self.filter.est.x - before[0]) ** 2 + (self.filter.est.y - before[1]) ** 2 > 0
            self.pose = new if moved else self.pose
            if moved:
                self.baseline.moved(self.filter.est.x - before[0], self.filter.est.y - before[1])
                self.turn_time = ref.time
        compass = self.compass_step
        if not moved:  # the velocity turns on at the last turn rate, the heading is kept (a drone's camera need not
            # point where it flies: Toledo photos turned with the coasted velocity missed the ±4° window); with a
            # compass in the telemetry both follow the turn it measured (dead reckoning through black frames)
            if compass is None:
                self.filter.predict_coast(dt)
                self.unseen_turn_s += max(0.0, dt)
            else:
                self.filter.predict_coast(dt, compass, ref.priors.heading_tol_deg)
                self.pose = replace(self.pose, turn_deg=self.pose.turn_deg + compass)
            self.baseline.broken()
            self.turn_time = ref.time  # this step's time is in unseen_turn_s now (or its turn was the compass's)
            self.anchored = False
        e = self.filter.est
        scale = own / self.gsd if own is not None else self.pose.scale
        self.pose = Pose(e.x / self.gsd, e.y / self.gsd, self.pose.turn_deg, scale)
        reason = unusable or ("blank frame" if blank else "")
        source = "tracked" if moved and self.anchored else "coasted"
        self.frames_since_fix += 1
        due = self.frames_since_fix >= self.cfg.fix_every or e.sigma > self.cfg.filter.fix_sigma_m
        searched = False  # whether this frame was already searched around the estimate as widely as when lost
        if not blank and due:
            if e.sigma <= self.cfg.wide_sigma_m and self.matcher.fits(size, self.pose, e.sigma / self.gsd):
                self.wide_frames = 0
                status, fixed = self._window_fix(image, size)
            else:
                status, fixed = self._wide_fix(ref, image, size)
                searched = True
            self.anchored = self.anchored or fixed
            source = "tracked" if (moved and self.anchored) or fixed else "coasted"
            reason = status
        if self.filter.lost_now(blind=blank):
            self.dead = (replace(self.filter.est), ref.time, self.pose.turn_deg)
            self.filter.lose()
            self.pose, self.lost_since = None, ref.time
            if not blank:
                return self._relocalize(ref, image, f"track lost ({reason}); ", searched)
            return self._point(ref, "lost", f"track lost ({reason})")
        return self._point(ref, source, reason or ("odometry" if moved else "coasting"))

    def _compass_turn(self, ref: FrameRef) -> float | None:
        """The turn (degrees, the content's, the project's convention) the telemetry's compass measured since the
        previous frame, None without a compass reading on both. A compass errs by up to its tolerance, but its
        error wanders slowly, so its turns over seconds are what dead reckoning needs."""
        now = ref.priors.heading_deg
        prev = self._compass_last
        self._compass_last = now
        if now is None or prev is None:
            return None
        return turn_difference(now - prev)

    def _own_gsd(self, ref: FrameRef, size) -> float | None:
        """The frame's ground resolution from its own metadata (a telemetry height and the lens: known only once
        the frame's width is), metres; None without."""
        if size is None:
            return None
        gsd = ref.priors.with_image_width(size[0]).gsd_m
        return gsd if gsd is not None and gsd > 0 else None

    def _wide_fix(self, ref: FrameRef, image, size) -> tuple[str, bool]:
        """The frame searched around the estimate when its uncertainty is too large for the tracking window
        (after black frames, missing frames, photos far apart): as widely as after a loss (every heading the time
        since the last measured turn allows, the reach the uncertainty), so the track is back on the first frame
        that shows the ground instead of being lost first. A fix resets the filter there."""
        e = self.filter.est
        self.frames_since_fix = 0
        priors = self._priors(ref, size[0])
        reach = max(self.cfg.wide_reach_sigmas * e.sigma, self.cfg.near_min_m)
        pose, status = self._near(ref, image, priors, e.x, e.y, reach, self.pose.turn_deg)
        status = status.replace("re-localized near", "re-localized around").replace("the prediction", "the estimate")
        if pose is None and self.wide_frames % self.cfg.wide_pipeline_every == 0:
            pose, why = self._pipeline_within(ref, image, priors)
            status += f"; {why}"
        self.wide_frames += 1
        if pose is None:
            self.filter.misses += 1
            return status, False
        self.wide_frames = 0
        v = _turned(e.vx, e.vy, -math.radians(turn_difference(pose.turn_deg - self.pose.turn_deg)))
        self.filter.reset(pose.x * self.gsd, pose.y * self.gsd, self.cfg.filter.global_sigma_m)
        self.filter.est.vx, self.filter.est.vy = v
        self.pose = self.calibration = pose
        self.cal_time = self.turn_time = ref.time
        self.unseen_turn_s = 0.0
        self.rejected.clear()
        self.candidates.clear()
        self.baseline.broken()
        self.baseline.checked = self.scale_settled = False
        self.scale_fixes = 0
        self.checks_left = self.cfg.confirm_first
        return status, True

    def _pipeline_within(self, ref: FrameRef, image, priors: Priors) -> tuple[Pose | None, str]:
        """The single-image pipeline's fix of a frame searched in vain around the estimate, kept only where the
        aircraft can be: within the speed bound x the time since the last fix of that fix (at least
        ``near_min_m``). The search around the estimate trusts the coasted position to a sigma; after a turn made
        while blind the aircraft can be farther from it than that, never farther from its last fix."""
        pose, status = self._pipeline(ref, image, priors)
        cal = self.calibration
        if pose is None or cal is None or self.cal_time is None:
            return pose, status
        bound = max(self.cfg.near_min_m, self.cfg.filter.speed_max_mps * max(0.0, ref.time - self.cal_time))
        d = math.hypot(pose.x - cal.x, pose.y - cal.y) * self.gsd
        if d > bound:
            return None, f"the pipeline's fix {d:.0f} m from the last fix is beyond reach ({bound:.0f} m)"
        return pose, f"{status}, {d:.0f} m from the last fix"

    def _pipeline(self, ref: FrameRef, image, priors: Priors) -> tuple[Pose | None, str]:
        """The single-image pipeline (:class:`aeroloc.localization.Localizer`) on one frame: (pose, status); the
        pose's scale the frame's own metadata's when it has one."""
        size = (image.shape[1], image.shape[0])
        loc = self.localizer(ref.name, image, priors=priors)
        pose = self._pose_of(loc, size) if loc.localized else None
        if pose is None and loc.localized:  # a fix without a turn or scale (the sweep's): found in a window
            pose = self._pose_at(loc, image, priors)
        if self.cfg.trim_native:
            release_native_memory()
        own = self._own_gsd(ref, size)
        if pose is not None and own is not None:  # the frame's metadata, not the match's coarse scale ladder
            pose = replace(pose, scale=own / self.gsd)
        return pose, loc.status or "not localized"

    def _window_fix(self, image, size) -> tuple[str, bool]:
        """Match the frame around the prediction and gate the fix; (status, whether a fix was fused)."""
        from aeroloc.flight.calibration import blend

        at_scale = self.pose.scale
        first = not self.metric and not self.scale_settled and self.scale_fixes < self.cfg.scale_first_fixes
        wide = self.cfg.scale_first_ladder if first else None
        fix = self.matcher(image, self.pose, self.filter.est.sigma / self.gsd, scales=wide)
        self.frames_since_fix = 0
        if fix is None:
            self.filter.misses += 1
            return "odometry (no distinct match in the window)", False
        self.filter.misses = 0
        checked, n_checked = self._confirmed_fix(image, fix)
        if checked is not None:  # local features placed the frame: there, as trusted as a fix of fix_score_ref
            fix = replace(fix, x=checked.x, y=checked.y)
        sigma_fix = self._fix_sigma(self.cfg.fix_score_ref if checked is not None else fix.score)
        e = self.filter.est
        offset = (fix.x * self.gsd - e.x, fix.y * self.gsd - e.y)
        ok, d = self.filter.update(fix.x * self.gsd, fix.y * self.gsd, sigma_fix)
        if not ok:
            status = f"fix rejected: {d:.0f} m from the prediction (gate {self.filter.gate(sigma_fix):.0f} m)"
            checked = self.metric or self.baseline.checked  # the odometry's scale, so the filter's sigma, honest
            if checked or fix.score < self.cfg.anchor_score or not self._reanchor(offset, fix, sigma_fix):
                return status, False
            self.baseline.broken()
            status = f"re-anchored: {self.cfg.anchor_after} rejected fixes agreed ({d:.0f} m from the prediction)"
        else:
            self.rejected.clear()
            status = f"window fix (score {fix.score:.2f}, {d:.1f} m from the prediction)"
            if checked is not None:
                status = status[:-1] + f", confirmed by {n_checked} local-feature inliers)"
            if fix.score >= self.cfg.scale_score and not self.metric:
                k = self.baseline.fix(fix.x * self.gsd, fix.y * self.gsd)
                if k is not None:
                    self.scale_settled = self.scale_settled or self.baseline.checked
                    self.pose = replace(self.pose, scale=self.pose.scale * k)
                    status += f", scale x{k:.3f} from the baseline"
        e = self.filter.est
        # the heading nudged, and without metadata the ground resolution until the first baseline after a global
        # fix confirms it: the dense refinement's scale comes in 3 % steps (0.94-1.06) and is noisy frame to frame,
        # unbiased over a flight (NAIP, 42 frames placed at the true pose: median found / true 1.000; given 4 % too
        # small or large, 0.989 and 1.009) but not over changed ground (NAIP frames 80-130, lake shores: it pulled
        # a confirmed scale 2.6 % low, the track 34 m off), so a small share per fix carries a scale that was wrong
        # after a gap (+4 %) back to the truth within ~10 fixes, and the baselines keep it after
        scale = None
        if ok and not self.metric and not self.scale_settled and fix.score >= self.cfg.scale_fix_score:
            scale = self.pose.scale * (fix.scale / at_scale)
        turn = fix.turn_deg if fix.score >= self.cfg.turn_fix_score else None
        self.pose = blend(self.pose, e.x / self.gsd, e.y / self.gsd, turn, None, k=0.1)
        if ok and checked is not None:  # the local features' heading and scale, measured, not a 3 %-step ladder's
            cal = not self.metric and not self.scale_settled
            self.pose = blend(self.pose, self.pose.x, self.pose.y, checked.turn_deg, None, k=self.cfg.confirm_k)
            if cal:
                self.pose = blend(self.pose, self.pose.x, self.pose.y, None, checked.scale, k=self.cfg.confirm_k)
            scale = None
        if scale is not None:
            # a weak peak pulls the scale less, as it pulls the position less (its sigma, _fix_sigma): inverse variance
            weight = (self._fix_sigma(1.0) / self._fix_sigma(fix.score)) ** 2
            k = self.cfg.scale_first_k if first else self.cfg.scale_fix_k * weight
            self.pose = blend(self.pose, self.pose.x, self.pose.y, None, scale, k=k)
            self.scale_fixes += 1
        self.calibration, self.cal_time, self.turn_time = self.pose, self.prev_time, self.prev_time
        self.unseen_turn_s = 0.0
        return status, True

    def _confirmed_fix(self, image, fix) -> tuple[Pose | None, int]:
        """The frame's pose by local features around a windowed ``fix`` (aeroloc.flight.confirm_fix) and their
        inliers, on the first ``confirm_first`` fixes after a re-localization and then every ``confirm_every``-th
        fix scoring under ``confirm_below``; (None, 0) otherwise."""
        reranker = self.localizer.reranker
        if reranker is None or not self.cfg.confirm_every:
            return None, 0
        if self.checks_left > 0:  # just re-localized: the carried heading and scale are the least sure
            self.checks_left -= 1
        elif fix.score >= self.cfg.confirm_below:
            return None, 0
        else:
            self.weak_fixes += 1
            if self.weak_fixes < self.cfg.confirm_every:
                return None, 0
        self.weak_fixes = 0
        from aeroloc.flight.confirm_fix import confirmed_pose
        from aeroloc.localization.alignment import reach_m

        reach_px = reach_m(self.gsd) / self.gsd
        pose, n = confirmed_pose(reranker, self.map, image, fix, self.cfg.confirm_inliers, reach_px)
        return pose, n

    def _fix_sigma(self, score: float) -> float:
        """A windowed fix's error (metres, 1 sigma) from its own correlation score: weak peaks are the ones that
        sat on changed ground, so they pull the track less."""
        f = self.cfg.filter
        base = max(f.fix_sigma_min_m, f.fix_sigma_px * self.gsd)
        return base * max(1.0, (self.cfg.fix_score_ref / max(score, 1e-3)) ** self.cfg.fix_score_pow)

    def _reanchor(self, offset: tuple[float, float], fix, sigma_fix: float) -> bool:
        """Rejected fixes that keep the same offset from the prediction are the odometry drifting, not the fixes
        being wrong (wrong fixes scatter): after ``anchor_after`` of them agreeing, the track moves to the fix."""
        self.rejected.append(offset)
        last = self.rejected[-self.cfg.anchor_after :]
        if len(last) < self.cfg.anchor_after:
            return False
        spread = max(10.0, self.cfg.anchor_spread_px * self.gsd)
        xs, ys = [o[0] for o in last], [o[1] for o in last]
        if max(xs) - min(xs) > spread or max(ys) - min(ys) > spread:
            return False
        self.rejected.clear()
        v = (self.filter.est.vx, self.filter.est.vy)
        self.filter.reset(fix.x * self.gsd, fix.y * self.gsd, 2 * sigma_fix)
        self.filter.est.vx, self.filter.est.vy = v
        return True

    def _priors(self, ref: FrameRef, width: int) -> Priors:
        """The frame's own priors, else the carried calibration: ground resolution ±25 %, heading widening with
        the time since the last fix (the aircraft may have turned meanwhile)."""
        p = ref.priors.with_image_width(width)  # a camera's height and lens give a resolution only with the width
        cal = self.calibration
        if cal is None:
            return p
        lost_s = 0.0 if self.cal_time is None else max(0.0, ref.time - self.cal_time)
        gsd = p.gsd_m if p.gsd_m is not None else cal.gsd_m(self.gsd)
        heading, tol = p.heading_deg, p.heading_tol_deg
        if heading is None:
            heading, tol = cal.turn_deg % 360.0, min(180.0, 15.0 + self.cfg.relocalize_heading_dps * lost_s)
        return Priors(
            gsd_m=gsd,
            heading_deg=heading,
            heading_tol_deg=tol,
            width_px=width,
            gsd_source="carried",
            heading_source="carried",
        )

    def _relocalize(self, ref: FrameRef, image, note: str = "", searched: bool = False) -> TrackPoint:
        """A fix without a prediction: first around the last fix (as far as the aircraft can have flown), then
        the dense stage over the whole map when a ground resolution is known (the frame's prior or the carried
        calibration) on every ``dense_every``-th lost frame, and the full single-image pipeline at the start and on
        every ``pipeline_every``-th lost frame (both cost seconds a frame: the frames between report lost at once).
        ``searched``: this frame was already searched around the estimate (:meth:`_wide_fix`)."""
        size = (image.shape[1], image.shape[0])
        priors = self._priors(ref, size[0])
        self.lost_frames += 1
        pose, status = None, "not localized"
        if self.calibration is not None and self.cal_time is not None and not searched:
            pose, status = self._near_last_fix(ref, image, priors)
        dense_due = (self.lost_frames - 1) % self.cfg.dense_every == 0
        whole_map = False
        if pose is None and dense_due and priors.gsd_m is not None and self.localizer.dense is not None:
            pose, status = self._dense_global(image, priors)
            whole_map = True
        if pose is None and (self.calibration is None or self.lost_frames % self.cfg.pipeline_every == 0):
            pose, status = self._pipeline(ref, image, priors)
        elif whole_map and self.cfg.trim_native:
            release_native_memory()
        if pose is None:
            return self._point(ref, "lost", note + status)
        own = self._own_gsd(ref, size)
        if own is not None:  # the frame's metadata, not the match's coarse scale ladder
            pose = replace(pose, scale=own / self.gsd)
        self.pose = self.calibration = pose
        self.lost_since, self.lost_frames, self.cal_time, self.dead = None, 0, ref.time, None
        self.wide_frames = 0
        self.turn_time, self.unseen_turn_s = ref.time, 0.0
        self.rejected.clear()
        self.candidates.clear()
        self.baseline.broken()
        self.baseline.checked = self.scale_settled = False
        self.scale_fixes = 0
        self.checks_left = self.cfg.confirm_first
        self.filter.reset(pose.x * self.gsd, pose.y * self.gsd, self.cfg.filter.global_sigma_m)
        self.anchored = True
        return self._point(ref, "global fix", note + status)

    def _near_prediction(self, t: float) -> tuple[float, float, float]:
        """(x, y, reach) metres: where the aircraft can be at ``t`` since the track was lost, the last estimate
        carried on at its velocity within the coasting model's uncertainty; without one (a resumed run) the last
        fix within the whole speed bound."""
        f = self.cfg.filter
        if self.dead is not None:
            e, t0, _ = self.dead
            dt = max(0.0, t - t0)
            reach = max(e.sigma, self.cfg.near_min_m) + self.cfg.near_share * f.speed_max_mps * dt
            return e.x + e.vx * dt, e.y + e.vy * dt, reach
        cal = self.calibration
        reach = max(self.cfg.near_min_m, f.speed_max_mps * max(0.0, t - self.cal_time))
        return cal.x * self.gsd, cal.y * self.gsd, reach

    def _near_last_fix(self, ref: FrameRef, image, priors: Priors) -> tuple[Pose | None, str]:
        """The frame searched around the predicted position (:meth:`_near_prediction`) before any whole-map
        search (:meth:`_near`), the turn carried on at the last turn rate."""
        x, y, reach_m = self._near_prediction(ref.time)
        if self.dead is not None:
            e, t0, turn = self.dead
            turn -= e.turn_dps * max(0.0, ref.time - t0)
        else:
            turn = self.calibration.turn_deg
        return self._near(ref, image, priors, x, y, reach_m, turn)

    def heading_tolerance(self, now: float) -> float:
        """Degrees the carried heading may be off at time ``now``: 15° + ``relocalize_heading_dps`` x (the seconds
        since the turn was last measured + those coasted since a fix last measured the heading), at most 180°."""
        since = self.turn_time if self.turn_time is not None else self.cal_time
        unmeasured = 0.0 if since is None else self.cfg.relocalize_heading_dps * max(0.0, now - since)
        return min(180.0, 15.0 + self._blind_turn_deg() + unmeasured)

    def _blind_turn_deg(self) -> float:
        """Degrees the aircraft may have turned in the seconds coasted since a fix last measured the heading."""
        return self.cfg.relocalize_heading_dps * self.unseen_turn_s

    def _near(
        self, ref: FrameRef, image, priors: Priors, x: float, y: float, reach_m: float, turn: float
    ) -> tuple[Pose | None, str]:
        """The frame searched within ``reach_m`` of (``x``, ``y``) metres, at every heading the frame's own prior
        allows, else around ``turn`` within 15° + ``relocalize_heading_dps`` x the seconds since the turn was last
        measured (and those coasted since a fix last measured the heading: levir-tx flight without metadata, after a
        15 s outage in a turn, the heading was 22° off and odometry steps kept resetting the search to ±15° around
        it), the ground resolution the frame's own (or carried); a best peak with a rival elsewhere in the
        reach is taken when it is also distinct within ``near_inner`` of it."""
        cal, k = self.calibration, self.cfg.window.sigma_k
        scale = priors.gsd_m / self.gsd if priors.gsd_m is not None else cal.scale
        pose = Pose(x / self.gsd, y / self.gsd, turn, scale)
        if ref.priors.heading_deg is None:
            priors = replace(priors, heading_deg=turn % 360.0, heading_tol_deg=self.heading_tolerance(ref.time))
        angles = priors.heading_search() or (turn,)

        def search(reach: float, ratio: float):
            return self.matcher(image, pose, reach / k / self.gsd, angles, self.cfg.near_max_px, ratio)

        fix, where = search(reach_m, 1.0), ""
        if fix is not None and not fix.ratio >= self.cfg.near_ratio:
            best = fix
            inner = search(reach_m * self.cfg.near_inner, self.cfg.near_ratio)
            same = inner is not None and math.hypot(inner.x - fix.x, inner.y - fix.y) * self.gsd <= max(
                10.0, 2 * self.gsd
            )
            fix, where = (inner, f", distinct within {reach_m * self.cfg.near_inner:.0f} m") if same else (None, "")
            agree = self._vote(Pose(best.x, best.y, best.turn_deg, scale), best.score, best.ratio)
            if fix is None and agree:
                fix, where = best, f", the best peak of {agree} frames in a row"
            elif fix is None and (n := self._confirmed(image, best)):
                fix, where = best, f", confirmed by {n} local-feature inliers"
                self.candidates.clear()
        if fix is None:
            return None, f"not localized: nothing distinct within {reach_m:.0f} m of the prediction"
        status = (
            f"re-localized near the prediction (score {fix.score:.2f}, ratio {fix.ratio:.2f}, {reach_m:.0f} m{where})"
        )
        scale = pose.scale
        if self._own_gsd(ref, (image.shape[1], image.shape[0])) is None:
            scale *= (fix.scale / pose.scale) ** self.cfg.near_scale_k
        return Pose(fix.x, fix.y, fix.turn_deg, scale), status

    def _confirmed(self, image, peak) -> int:
        """Inliers with which local features confirm a searched frame's best but not distinct peak (0 when they
        do not): the frame turned to the peak's heading against the map window the peak says it covers, at its
        scale, aligned within max(25 m, 10 map px) of it (the whole-map sweep's confirmation,
        aeroloc.localization.sweep_stage.confirm, and its inlier floor). The correlation's ratio weighs the peak
        against every placement in a reach of hundreds of metres at every heading; local features test the
        one place independently (levir-tx without metadata after its outage: the truth was the best peak of 7
        frames in a row at ratios 1.05-1.10 before four of them agreed)."""
        loc = self.localizer
        if not self.cfg.near_confirm or peak.score < self.cfg.vote_score or loc.reranker is None:
            return 0
        from aeroloc.localization.alignment import reach_m
        from aeroloc.localization.sweep_stage import confirm
        from aeroloc.matching.sweep import SWEEP_DEFAULTS, Hypothesis

        conf = loc.sweep.conf if loc.sweep is not None else SWEEP_DEFAULTS
        h = Hypothesis(peak.x, peak.y, peak.turn_deg, peak.scale, peak.score)
        fix, n = confirm(
            loc.reranker, self.map, image, h, reach_m(self.gsd), conf["confirm_inliers"], conf["confirm_screen_min"]
        )
        return n if fix is not None else 0

    def _vote(self, pose: Pose, score: float, ratio: float = 1.0) -> int:
        """Record a searched frame's best but not distinct peak; the number of frames whose best peaks decide it
        (else 0): the last searched frames in a row (this one the last), their peaks carried to this frame by the
        odometry, each scoring at least ``vote_score``, agreeing within ``vote_m`` and ``vote_turn_deg``, at least
        ``vote_frames_min`` of them, and distinct together as one frame must be alone: their ratios multiplied
        reach ``near_ratio``, each frame's (but the first's) raised to the share of a footprint flown since the
        frame before it (:func:`new_ground_evidence`).

        Why the share: consecutive frames overlap 90-97 %, so their peaks, ties included, agree with each other
        whatever the truth, and their ratios are one image's evidence counted again. Counted whole, four NAIP
        frames after an outage (ratios 1.13, 1.13, 1.02, 1.01, x1.31, 3 % of a footprint apart) agreed on a
        place 540 m off (70 wrong frames on the telemetry flight), and szada-hu's (x1.10) on one 147 m off. A
        single best peak not distinct is placed by local features instead (:meth:`_confirmed`), an independent
        test of the one place."""
        self.candidates.append((pose, score, 0, ratio, 0.0))
        tol = max(self.cfg.vote_m, 3 * self.gsd) / self.gsd
        run = []  # the frames in a row, this one first, whose best peaks agree with this one's
        for c, sc, _, r, flown in reversed(self.candidates):
            near = math.hypot(c.x - pose.x, c.y - pose.y) <= tol
            if not (
                sc >= self.cfg.vote_score
                and near
                and abs(turn_difference(c.turn_deg - pose.turn_deg)) <= self.cfg.vote_turn_deg
            ):
                break
            run.append((r, flown))
        n = len(run)
        if n < self.cfg.vote_frames_min or new_ground_evidence(run[::-1]) < math.log(self.cfg.near_ratio):
            return 0
        self.candidates.clear()
        return n

    def _carry_candidates(self, step, size) -> None:
        """The recent frames' best peaks moved on with this frame's odometry step, with the share of a footprint
        the frame moved (dropped without a step, or once older than ``vote_frames`` frames)."""
        if not self.candidates:
            return
        if step is None:
            self.candidates.clear()
            return
        w, h = size
        cx, cy = w / 2.0, h / 2.0
        shift = math.hypot(*(step.A @ np.array([cx, cy, 1.0]) - np.array([cx, cy]))) / max(w, h)
        self.candidates = [
            (c.moved(step.A, size), sc, age + 1, r, flown + shift)
            for c, sc, age, r, flown in self.candidates
            if age + 1 < self.cfg.vote_frames
        ]

    def _dense_global(self, image, priors: Priors) -> tuple[Pose | None, str]:
        """The dense stage over the whole map (or the retrieved tiles' region when the map is too large) at the
        known ground resolution (±15 % in scale) and the headings the prior allows."""
        from aeroloc.localization.dense_stage import scale_ladder

        dense = self.localizer.dense
        work = max(priors.gsd_m, self.gsd)
        f = self.gsd / work
        tiles = []
        if self.map.width * self.map.height * f * f > dense.max_region_px:
            tiles = [
                self.localizer.db.by_id[t] for t in self.localizer.retriever(image, 20, heading=priors.heading).tile_ids
            ]
        d = dense.locate(image, tiles, priors.gsd_m, priors.heading_search(), scale_ladder(0.15))
        if d is None:
            return None, "not localized: no distinct dense match over the map"
        return pose_from_dense(d, self.gsd), d.status()

    def _pose_at(self, loc, image, priors: Priors) -> Pose | None:
        """The pose of a global fix whose transform is not a tile's or the dense stage's (the sweep's): the frame
        matched in a small window around it at the headings the sweep's placement or the prior allows (all when
        neither) and the known, carried or placed ground resolution; the sweep's own placement (heading and scale,
        confirmed by local features) when that window match is not distinct. Before, such a fix was dropped:
        levir-tx flight without metadata, frame 229 lost although the sweep placed it 1.6 m from its candidate
        with 57 inliers."""
        cal, h = self.calibration, getattr(loc, "placement", None)
        known = [priors.gsd_m / self.gsd if priors.gsd_m is not None else None]
        known += [cal.scale if cal is not None else None, h.scale if h is not None else None]
        scale = next((k for k in known if k is not None), None)  # the frame's own, the carried, the sweep's
        if scale is None:
            return None
        col, row = self.map.latlon_to_pixel(loc.lat, loc.lon)
        if h is not None:  # the sweep's heading: its 10° steps, refined
            angles = tuple(float(h.angle + d) for d in range(-12, 13, 3))
        else:
            angles = priors.heading_search() or tuple(range(-180, 180, 6))
        m = self.cfg.window.sigma_k
        fix = self.matcher(image, Pose(float(col), float(row), 0.0, scale), 25.0 / m / self.gsd, angles)
        if fix is not None:
            return Pose(fix.x, fix.y, fix.turn_deg, scale)
        return None if h is None else Pose(float(col), float(row), float(h.angle), scale)

    def _pose_of(self, loc, size) -> Pose | None:
        """The pose a global fix gives: centre from its lat/lon, turn and scale from the dense match or the
        local-feature homography."""
        col, row = self.map.latlon_to_pixel(loc.lat, loc.lon)
        if loc.dense is not None:
            p = pose_from_dense(loc.dense, self.gsd)
        elif loc.best is not None and loc.best.H is not None:
            tile = self.localizer.db.by_id[loc.best.tile_id]
            p = pose_from_homography(loc.best.H, size, tile.col, tile.row)
        else:
            return None
        return None if p is None else Pose(float(col), float(row), p.turn_deg, p.scale)

    def _point(self, ref: FrameRef, source: str, status: str) -> TrackPoint:
        if source == "lost" or self.filter.est is None or self.pose is None:
            return TrackPoint(ref.name, ref.time, math.nan, math.nan, status, math.nan, "lost")
        lat, lon = self.map.pixel_to_latlon(self.pose.x, self.pose.y)
        p = self.pose
        return TrackPoint(
            ref.name,
            ref.time,
            float(lat),
            float(lon),
            status,
            self.filter.reported_sigma,
            source,
            p.turn_deg % 360.0,
            p.yaw_deg(),
            p.gsd_m(self.gsd),
        )


def new_ground_evidence(run: list[tuple[float, float]]) -> float:
    """The log-distinctness of frames that agree, oldest first, each ``(ratio, footprints flown since it)``: the
    first frame's log-ratio whole, each later one's times the share of a footprint flown since the frame before
    it (at most 1). Overlapping views are one view's evidence; views of new ground add theirs."""
    if not run:
        return 0.0
    total = math.log(max(run[0][0], 1.0))
    for (_, before), (r, flown) in itertools.pairwise(run):
        total += min(1.0, max(0.0, before - flown)) * math.log(max(r, 1.0))
    return total
