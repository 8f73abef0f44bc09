"""Scoring a track against truth (issue #14's table): share within t after the first fix, wrong fixes, time to
first fix, frames per second while tracking, recovery after a gap.

``t = max(5 m, 2 map px)``, wrong = farther than ``max(25 m, 10 map px)``. Shares count every frame after the first
fix (a lost frame is a miss); ``within_t_seen`` only the frames that showed the ground (not blank or undecodable:
the camera gave nothing to place there, the motion model carries them, and they are scored apart). Wrong fixes
count the points an image placed (global fix, tracked); points the motion model placed (coasted: during
black frames, and odometry carried on from there until a map fix) are counted apart, with their errors against
their sigma.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass

from aeroloc.core import geo


@dataclass
class FlightScore:
    frames: int
    first_fix_frame: int | None
    first_fix_s: float  # wall-clock seconds from the start to the first fix (inclusive)
    within_t: float  # share of the frames after the first fix within t
    within_10m: float
    within_t_seen: float  # the same share over the frames that showed the ground (blank and undecodable ones left out)
    t_m: float
    wrong: int  # image-placed points farther than the wrong-fix bound
    coasted: int
    coasted_beyond_3sigma: int
    lost_after_first: int
    median_error_m: float
    fps_tracking: float  # 1000 / median ms of the frames placed by odometry / windowed fixes
    fps_overall: float  # frames after the first fix / their total time
    recovery_frames: int | None  # frames after the gap until within t (1 = the first frame after it)


def errors_m(points, truth: dict) -> list[float]:
    out = []
    for p in points:
        tr = truth.get(p.name)
        if tr is None or not p.localized:
            out.append(math.nan)
        else:
            out.append(float(geo.geodesic_distance(p.lat, p.lon, tr[0], tr[1])))
    return out


BLIND = ("blank frame", "undecodable frame")  # statuses of frames that show no ground


def score(points, truth: dict, map_gsd: float, gap_end_time: float | None = None) -> FlightScore:
    t, wrong_m = max(5.0, 2 * map_gsd), max(25.0, 10 * map_gsd)
    err = errors_m(points, truth)
    first = next((i for i, p in enumerate(points) if p.localized), None)
    after = range(first, len(points)) if first is not None else range(0)
    ok = [err[i] <= t for i in after]
    seen = [err[i] <= t for i in after if not points[i].status.startswith(BLIND)]
    placed = [i for i in after if points[i].source in ("global fix", "tracked")]
    coasted = [i for i in after if points[i].source == "coasted"]
    tracked_ms = [points[i].ms for i in after if points[i].source == "tracked"]
    rec = None
    if gap_end_time is not None:
        later = [i for i in after if points[i].time > gap_end_time]
        rec = next((k + 1 for k, i in enumerate(later) if err[i] <= t), None)
    total_ms = sum(points[i].ms for i in after)
    finite = [err[i] for i in after if math.isfinite(err[i])]
    return FlightScore(
        frames=len(points),
        first_fix_frame=first,
        first_fix_s=sum(p.ms for p in points[: (first or 0) + 1]) / 1000 if first is not None else math.nan,
        within_t=sum(ok) / len(ok) if ok else 0.0,
        within_10m=sum(err[i] <= 10.0 for i in after) / len(ok) if ok else 0.0,
        within_t_seen=sum(seen) / len(seen) if seen else 0.0,
        t_m=t,
        wrong=sum(err[i] > wrong_m for i in placed),
        coasted=len(coasted),
        coasted_beyond_3sigma=sum(err[i] > 3 * points[i].sigma_m for i in coasted),
        lost_after_first=sum(not points[i].localized for i in after),
        median_error_m=statistics.median(finite) if finite else math.nan,
        fps_tracking=1000.0 / statistics.median(tracked_ms) if tracked_ms else math.nan,
        fps_overall=1000.0 * len(ok) / total_ms if total_ms else math.nan,
        recovery_frames=rec,
    )
