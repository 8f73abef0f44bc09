"""Flight mode on real drone photos: the first Toledo photos in EXIF time order, tracked on the orthomosaic
(the first by the single-image pipeline, the rest by odometry and windowed fixes), scored against EXIF GPS."""

from __future__ import annotations

from dataclasses import replace

import pytest

from aeroloc.core import geo


@pytest.fixture(scope="module")
def toledo_db(toledo_map, tmp_path_factory):
    from aeroloc.localization.build import build_database

    folder = tmp_path_factory.mktemp("toledo-db")
    build_database(toledo_map, folder, tile_m=200.0, device="cpu")
    return folder


def test_toledo_photos_are_tracked_within_10_m(toledo_db, data_dir, tmp_path):
    from aeroloc.flight.filter import FilterConfig
    from aeroloc.flight.frames import load_flight
    from aeroloc.flight.run import track_flight
    from aeroloc.flight.tracker import TrackConfig
    from aeroloc.localization.localizer import Localizer
    from aeroloc.retrieval.database import Database

    photos = tmp_path / "photos"
    photos.mkdir()
    for p in sorted((data_dir / "toledo" / "photos").glob("1JI_*.JPG"))[:5]:
        (photos / p.name).symlink_to(p)
    flight = load_flight(photos)
    config = TrackConfig(filter=replace(FilterConfig(), speed_max_mps=15.0))
    points = track_flight(Localizer(Database(toledo_db)), flight, tmp_path / "track.csv", config)
    assert [p.name for p in points] == [f.name for f in flight.frames]
    assert points[0].source == "global fix"
    assert all(p.source == "tracked" for p in points[1:])  # no whole-map search after the first fix
    for p, f in zip(points, flight.frames, strict=True):
        assert p.localized
        assert float(geo.geodesic_distance(p.lat, p.lon, *f.truth)) <= 10.0
    # self-calibration: the drone's ground resolution (no metadata gives it) is carried and consistent
    gsd = [p.gsd_m for p in points]
    assert max(gsd) / min(gsd) < 1.1
