"""A flight simulator: a nadir camera flown over an other-date composite (:mod:`aeroloc.flight.composite`).

The aircraft flies straight legs joined by coordinated turns (a constant turn rate), keeps to where the composite
has content (before each leg it picks the heading with the longest covered run ahead), climbs and descends
between legs (the ground resolution changes with the height), and loses a stretch of frames: the first half of
the gap is recorded black (a camera fault), the second half not at all (the rows are missing, so the times jump).

Written: ``frames/*.jpg``, ``frames.csv`` (``name,time``: what a camera gives, no position, no priors),
``telemetry.csv`` (``time,alt_agl_m,hfov_deg``: a barometric height and the lens, with ``compass_deg`` also
``heading_deg,heading_tol_deg``: a compass that errs within the tolerance; used only when asked) and
``truth.csv`` (``name,time,lat,lon,heading_deg,yaw_deg,gsd_m,alt_agl_m``) for scoring. ``heading_deg`` is the
project's convention (the content's turn from north-up, as the query sets and the dense stage use it);
``yaw_deg`` is the compass bearing the top of the frame points to.
"""

from __future__ import annotations

import csv
import functools
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from aeroloc.core.errors import AerolocError
from aeroloc.flight.composite import Composite, crop_to_map, index_frame


@dataclass(frozen=True)
class FlightPlan:
    frames: int = 300
    rate_hz: float = 2.0
    speed_mps: float = 40.0
    width: int = 480
    height: int = 360
    hfov_deg: float = 60.0
    alt_m: tuple[float, float] = (700.0, 950.0)  # height above ground, range flown
    leg_s: float = 25.0  # seconds of straight flight between turns
    turn_rate_dps: float = 6.0
    replan_s: float = 20.0  # a turn's worth of flight: a new leg when the coverage ahead ends within this (a
    # drone over small covered islands: shorter legs, faster turns, an earlier re-plan)
    gap_start: float = 0.6  # the lost stretch starts at this share of the flight
    gap_frames: int = 30
    seed: int = 0
    start: tuple[float, float] | None = None  # map px; default the most covered point
    return_to_cover: bool = True  # off the covered ground (no heading with a covered run: a turn carried the
    # aircraft out), head for the nearest covered point instead of re-planning at random every frame, which
    # random-walks the heading 3° a frame and parks the aircraft at the composite's edge (a 10,000-frame NAIP
    # flight: 86 % of its frames off the covered ground, most of them standing still on the edge; szada-hu seeds
    # 2 and 3: 90 frames after the outage 77-100 % no-data, nothing to localize). On by default since the
    # composite's half-pixel fix re-flew every path anyway.
    compass_deg: float | None = None  # a compass in the telemetry (heading_deg, heading_tol_deg = this): its error
    # wanders slowly within ±this (magnetic interference, calibration), drawn apart from the path (same flight)

    @functools.cached_property
    def _compass_phases(self) -> tuple[float, float]:
        """The compass error's two phases, seeded apart from the path's random draws."""
        p1, p2 = np.random.default_rng((self.seed, 1)).uniform(0.0, 2.0 * np.pi, 2)
        return float(p1), float(p2)

    def compass_error(self, t: float) -> float:
        """The compass's error at time ``t`` (degrees, within ±``compass_deg``): two slow sinusoids (periods
        120 s and 17 s) of seeded phases, 0 without a compass."""
        if not self.compass_deg:
            return 0.0
        p1, p2 = self._compass_phases
        w = 0.75 * math.sin(2.0 * math.pi * t / 120.0 + p1) + 0.25 * math.sin(2.0 * math.pi * t / 17.0 + p2)
        return self.compass_deg * w

    def gsd(self, alt: float) -> float:
        return 2.0 * alt * math.tan(math.radians(self.hfov_deg) / 2.0) / self.width

    def check(self) -> None:
        if self.frames < 2 or self.rate_hz <= 0 or self.speed_mps <= 0 or self.width < 32 or self.height < 32:
            raise AerolocError("a flight needs >= 2 frames, a positive rate and speed, and frames >= 32 px")
        if not 0 <= self.gap_frames < self.frames:
            raise AerolocError(f"gap of {self.gap_frames} frames does not fit a {self.frames}-frame flight")
        if self.compass_deg is not None and not 0 <= self.compass_deg <= 180:
            raise AerolocError(f"a compass error of ±{self.compass_deg}° is outside 0-180°")


@dataclass
class State:
    x: float  # composite px
    y: float
    yaw: float  # degrees clockwise from north: where the aircraft (and the top of the frame) points
    alt: float


def _free_run(safe: np.ndarray, s: State, yaw: float, step_px: float, n: int) -> int:
    """How many steps of ``step_px`` along ``yaw`` stay on safe ground."""
    dx, dy = math.sin(math.radians(yaw)) * step_px, -math.cos(math.radians(yaw)) * step_px
    for k in range(1, n + 1):
        x, y = int(round(s.x + dx * k)), int(round(s.y + dy * k))
        if not (0 <= y < safe.shape[0] and 0 <= x < safe.shape[1]) or not safe[y, x]:
            return k - 1
    return n


def _new_leg(safe: np.ndarray, s: State, rng, step_px: float, n: int, cover_px: np.ndarray | None = None) -> float:
    """The heading of the next leg: the longest covered run among turns of 30-150° either way (ties broken at
    random), so the path has real turns and stays over the composite. With ``cover_px`` (x, y of covered points)
    and no covered run at all, the bearing to the nearest of them."""
    turns = rng.permutation(np.r_[np.arange(-150, -29, 15), np.arange(30, 151, 15)])
    runs = [(_free_run(safe, s, s.yaw + t, step_px, n), t) for t in turns]
    best = max(r for r, _ in runs)
    if best == 0 and cover_px is not None:
        x, y = cover_px[np.argmin((cover_px[:, 0] - s.x) ** 2 + (cover_px[:, 1] - s.y) ** 2)]
        return s.yaw + (math.degrees(math.atan2(x - s.x, s.y - y)) - s.yaw + 180.0) % 360.0 - 180.0
    return s.yaw + next(t for r, t in runs if r == best)


def fly(plan: FlightPlan, comp: Composite):
    """Yields (index, time_s, State) for every frame of the plan (the gap included)."""
    plan.check()
    rng = np.random.default_rng(plan.seed)
    half = 0.5 * plan.gsd(max(plan.alt_m)) * math.hypot(plan.width, plan.height) / 2 / comp.gsd_m
    dist = cv2.distanceTransform(np.pad(comp.coverage, 1).astype(np.uint8), cv2.DIST_L2, 5)[1:-1, 1:-1]
    safe = dist > 0.8 * half
    if not safe.any():
        raise AerolocError("the composite has no area large enough for the frames; fly lower or use smaller frames")
    cover_px = None
    if plan.return_to_cover:  # every 4th pixel of the covered ground, as x, y
        ys, xs = np.nonzero(safe[::4, ::4])
        cover_px = np.stack([xs * 4.0, ys * 4.0], axis=1)
    if plan.start is not None:
        x0, y0 = plan.start[0] * comp.factor, plan.start[1] * comp.factor
    else:
        y0, x0 = np.unravel_index(int(dist.argmax()), dist.shape)
    dt = 1.0 / plan.rate_hz
    step = plan.speed_mps * dt / comp.gsd_m
    s = State(float(x0), float(y0), float(rng.uniform(0, 360)), float(np.mean(plan.alt_m)))
    lookahead = int(plan.leg_s * plan.rate_hz)
    target_yaw, target_alt = s.yaw, s.alt
    leg_left = 0
    for i in range(plan.frames):
        yield i, i * dt, State(s.x, s.y, s.yaw % 360.0, s.alt)
        ahead = int(plan.replan_s * plan.rate_hz)  # re-plan before the coverage ends
        if leg_left <= 0 or _free_run(safe, s, target_yaw, step, ahead) < ahead:
            target_yaw = _new_leg(safe, s, rng, step, lookahead, cover_px)
            target_alt = float(rng.uniform(*plan.alt_m))
            leg_left = lookahead
        leg_left -= 1
        turn = (target_yaw - s.yaw + 180.0) % 360.0 - 180.0
        s.yaw += float(np.clip(turn, -plan.turn_rate_dps * dt, plan.turn_rate_dps * dt))
        s.alt += float(np.clip(target_alt - s.alt, -5.0 * dt, 5.0 * dt))  # 5 m/s climb or descent
        nx = s.x + math.sin(math.radians(s.yaw)) * step
        ny = s.y - math.cos(math.radians(s.yaw)) * step
        if 0 <= int(ny) < safe.shape[0] and 0 <= int(nx) < safe.shape[1]:
            s.x, s.y = nx, ny


def render(comp: Composite, plan: FlightPlan, s: State) -> np.ndarray:
    """The nadir frame at ``s``: the composite resampled to the frame's ground resolution and turned with the
    aircraft (its content turned ``-yaw`` from north-up, the top of the frame pointing along the flight)."""
    scale = plan.gsd(s.alt) / comp.gsd_m
    A = index_frame(crop_to_map(-s.yaw, scale, (s.x, s.y), (plan.width, plan.height)))
    return cv2.warpAffine(
        comp.image, A, (plan.width, plan.height), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderValue=0
    )


TRUTH_COLUMNS = ["name", "time", "lat", "lon", "heading_deg", "yaw_deg", "gsd_m", "alt_agl_m"]


def write_flight(out, map_, comp: Composite, plan: FlightPlan, quality: int = 90) -> int:
    """Fly ``plan`` and write the flight folder ``out``; returns the number of frames recorded (rows of
    frames.csv)."""
    from aeroloc.core.images import write_image

    out = Path(out)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    g0 = int(round(plan.gap_start * plan.frames))
    black = range(g0, g0 + plan.gap_frames // 2)
    missing = range(g0 + plan.gap_frames // 2, g0 + plan.gap_frames)
    n = 0
    with (
        open(out / "frames.csv", "w", newline="") as ff,
        open(out / "telemetry.csv", "w", newline="") as tf,
        open(out / "truth.csv", "w", newline="") as gf,
    ):
        frames, tele, truth = csv.writer(ff), csv.writer(tf), csv.writer(gf)
        frames.writerow(["name", "time"])
        compass = plan.compass_deg is not None
        tele.writerow(["time", "alt_agl_m", "hfov_deg"] + (["heading_deg", "heading_tol_deg"] if compass else []))
        truth.writerow(TRUTH_COLUMNS)
        for i, t, s in fly(plan, comp):
            row = [f"{t:.3f}", f"{s.alt:.1f}", plan.hfov_deg]
            if compass:  # the content's turn (project convention) as the erring compass reads the yaw
                row += [f"{(-(s.yaw + plan.compass_error(t))) % 360.0:.2f}", plan.compass_deg]
            tele.writerow(row)
            if i in missing:
                continue
            name = f"frame_{i:06d}.jpg"
            img = render(comp, plan, s)
            if i in black:
                img = np.zeros_like(img)
            write_image(out / "frames" / name, img, quality=quality)
            lat, lon = map_.pixel_to_latlon(*comp.to_map_px(s.x, s.y))
            frames.writerow([name, f"{t:.3f}"])
            heading = (-s.yaw) % 360.0
            row = [name, f"{t:.3f}", f"{float(lat):.9f}", f"{float(lon):.9f}", f"{heading:.2f}", f"{s.yaw:.2f}"]
            truth.writerow(row + [f"{plan.gsd(s.alt):.4f}", f"{s.alt:.1f}"])
            n += 1
    return n
