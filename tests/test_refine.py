"""Map-window re-alignment (aeroloc.localization.window): the window geometry on hand-made homographies, and on real NAIP data a
weak tile match that passes once the query is matched against the map window its hypothesis covers."""

from __future__ import annotations

import numpy as np
import pytest

from aeroloc.core import geo
from aeroloc.localization.window import beyond_tile, query_window
from aeroloc.maps.sources import open_map
from aeroloc.retrieval.database import Database


@pytest.fixture(scope="module")
def db(naip_db):
    return Database(naip_db)


@pytest.fixture(scope="module")
def map_(db):
    return open_map(db.info["map"]["path"])


def _shift(dx, dy, s=1.0):
    return np.array([[s, 0, dx], [0, s, dy], [0, 0, 1.0]])


def test_beyond_tile_in_tile_sides(db):
    t = db.by_id["r001c001"]
    size = (t.width, t.height)
    assert beyond_tile(np.eye(3), size, t) == 0.0
    assert beyond_tile(_shift(0.25 * t.width, 0), size, t) == pytest.approx(0.25)
    assert beyond_tile(_shift(-0.1 * t.width, 0.4 * t.height), size, t) == pytest.approx(0.4)
    assert beyond_tile(_shift(0, 0, 0.5), size, t) == 0.0  # a query half the tile's size, inside it
    behind = np.array([[1, 0, 0], [0, 1, 0], [-0.01, 0, 1.0]])  # the right corners project behind the horizon
    assert beyond_tile(behind, size, t) == float("inf")


def test_query_window_covers_the_projection_with_a_margin_and_keeps_the_georeference(db, map_):
    t = db.by_id["r001c001"]
    size = (100, 80)
    w = query_window(map_, t, _shift(50, 60), size, margin=0.2)
    # corners at tile px (50, 60)-(150, 140) = map px (t.col + 50, t.row + 60) ...; grown by 20 / 16 px
    assert (w.tile.col, w.tile.row) == (t.col + 30, t.row + 44)
    assert (w.tile.width, w.tile.height) == (140, 112)
    assert w.image.shape == (112, 140, 3) and w.valid.all()
    # a window pixel and the tile pixel over the same ground have the same lat/lon (exact affine, no rounding)
    lat_w, lon_w = w.tile.pixel_to_latlon(20.5, 16.5)
    lat_t, lon_t = t.pixel_to_latlon(50.5, 60.5)
    assert geo.geodesic_distance(lat_w, lon_w, lat_t, lon_t) < 1e-6
    assert np.array_equal(w.image, map_.read(t.col + 30, t.row + 44, 140, 112)[0])


def test_query_window_is_clipped_to_the_map_and_refuses_unusable_projections(db, map_):
    t = db.by_id["r000c000"]
    w = query_window(map_, t, _shift(-40, -40), (100, 100))
    assert (w.tile.col, w.tile.row) == (0, 0) and (w.tile.width, w.tile.height) == (80, 80)
    assert query_window(map_, t, _shift(-500, -500), (100, 100)) is None  # entirely off the map
    assert query_window(map_, t, _shift(0, 0, 10.0), (t.width, t.height)) is None  # > 3 tile sides: not a view
    behind = np.array([[1, 0, 0], [0, 1, 0], [-0.01, 0, 1.0]])
    assert query_window(map_, t, behind, (t.width, t.height)) is None


@pytest.mark.slow
def test_weak_tile_match_passes_on_its_map_window(db, naip_dev):
    """naip_20120731_n_006 (725 m, 2012) against its true tile: LighterGlue finds < min_inliers similarity inliers
    on the 1280 m tile, but the window the hypothesis covers (query footprint + 20 %) holds the matches to localize
    it within 25 m; a wrong tile's hypothesis gives a window that does not pass."""
    from aeroloc.core.images import read_image
    from aeroloc.core.queries import load_queries
    from aeroloc.localization.alignment import align
    from aeroloc.localization.cascade import Candidate
    from aeroloc.localization.localizer import Localizer
    from aeroloc.localization.options import LocalizeOptions
    from aeroloc.matching.features import extract

    q = {q.name: q for q in load_queries(naip_dev)}["naip_20120731_n_006.jpg"]
    image = read_image(q.path)
    loc = Localizer(db, LocalizeOptions(method="xfeat-vlad", rerank="xfeat-lighterglue"), "cpu")
    rr = loc.reranker
    qf = extract(rr.extractor, image, rr.conf["query_side"])
    size = (image.shape[1], image.shape[0])
    results = {}
    for tile_id in ("r002c004", "r001c004"):  # the true tile; a neighbour 900 m off by its own hypothesis
        n, H, _, _ = rr.match_pair(qf, rr.tile_features([tile_id])[tile_id])
        assert 0 < n < rr.conf["min_inliers"], (tile_id, n)
        assert not align(H, n, size, db.by_id[tile_id], loc.map_size, rr.conf["min_inliers"]).localized
        c = Candidate(tile_id, 0, inliers=n, H=H)
        results[tile_id] = (loc._realign(image, c, qf), c)
    a, c = results["r002c004"]
    assert a is not None and a.localized and c.inliers >= rr.conf["min_inliers"]
    assert geo.geodesic_distance(q.lat, q.lon, a.lat, a.lon) < 25.0
    assert results["r001c004"][0] is None


def test_a_map_that_is_gone_turns_the_window_stage_off_with_a_warning(tmp_path, naip_map):
    from aeroloc.localization.window import open_map_for_refine

    assert open_map_for_refine(naip_map).width > 0
    with pytest.warns(UserWarning, match=r"map not found; weak matches are not re-matched on the map window"):
        assert open_map_for_refine(tmp_path / "moved.tif") is None
