"""The flight table's figures (aeroloc.flight.metrics.score) on a hand-made track whose errors are known: metres
north of the truth, converted with the local metres per degree of latitude."""

import math

import pytest

from aeroloc.flight.metrics import score
from aeroloc.flight.tracker import TrackPoint

LAT, LON = 47.0, 19.0
M_PER_DEG_LAT = 111_195.0  # near 47° N, within 0.2 %


def point(i: int, north_m: float | None, source: str, status: str = "", ms: float = 100.0) -> TrackPoint:
    lat = math.nan if north_m is None else LAT + north_m / M_PER_DEG_LAT
    lon = math.nan if north_m is None else LON
    return TrackPoint(f"f{i}", i * 0.5, lat, lon, status, 5.0, source, ms=ms)


def test_shares_count_every_frame_after_the_first_fix_and_blank_frames_apart():
    pts = [
        point(0, None, "lost"),  # before the first fix: not counted
        point(1, 2.0, "global fix"),
        point(2, 3.0, "tracked"),
        point(3, 7.0, "tracked"),  # beyond t = 5 m, within 10 m
        point(4, 40.0, "coasted", "blank frame"),  # the motion model alone: a miss, but not a wrong fix
        point(5, 30.0, "tracked"),  # a wrong fix (> 25 m)
        point(6, None, "lost"),
        point(7, 1.0, "tracked"),
    ]
    truth = {p.name: (LAT, LON) for p in pts}
    s = score(pts, truth, map_gsd=1.5, gap_end_time=2.2)  # t = max(5, 3) = 5 m; the gap ends before frame 5
    assert s.first_fix_frame == 1
    assert s.within_t == pytest.approx(3 / 7)  # frames 1, 2, 7 of the 7 after the first fix
    assert s.within_t_seen == pytest.approx(3 / 6)  # the blank frame left out
    assert s.within_10m == pytest.approx(4 / 7)
    assert s.wrong == 1 and s.coasted == 1 and s.lost_after_first == 1
    assert s.recovery_frames == 3  # frames 5 (30 m), 6 (lost), 7 (1 m): back within t on the third
    assert s.fps_tracking == pytest.approx(10.0)
