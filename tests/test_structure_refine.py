"""Structure refinement of a local-feature fix (aeroloc.localization.structure_refine) on real NAIP queries: a fix
metres off is pulled onto the structure at its own heading and scale; one beyond the reach, or on a query without
structure, is left alone."""

from __future__ import annotations

import math

import numpy as np
import pytest

from aeroloc.core import geo
from aeroloc.core.images import read_image
from aeroloc.core.queries import load_queries
from aeroloc.localization.dense_stage import DenseMapLocator
from aeroloc.localization.structure_refine import placement_of, refine_fix
from aeroloc.maps.sources import open_map


@pytest.fixture(scope="module")
def dense(naip_map):
    return DenseMapLocator(open_map(naip_map))


@pytest.fixture(scope="module")
def queries(naip_dev):
    return load_queries(naip_dev, priors="exact")[::30]  # four years' crops


def _moved(lat, lon, east_m, north_m):
    """(lat, lon) moved ``east_m`` east and ``north_m`` north."""
    dlat = north_m / 111_320.0
    return lat + dlat, lon + east_m / (111_320.0 * math.cos(math.radians(lat)))


def test_a_fix_metres_off_is_pulled_onto_the_structure(dense, queries):
    """The truth moved 15 m (3 map px) is brought back within 5 m at the query's own heading and scale (1.0:
    the crops are cut at the map's 5 m/px)."""
    for q in queries:
        image = read_image(q.path)
        lat, lon = _moved(q.lat, q.lon, 12.0, -9.0)
        r = refine_fix(dense, image, lat, lon, q.truth_heading_deg, 1.0)
        assert r is not None, q.name
        assert geo.geodesic_distance(q.lat, q.lon, r.lat, r.lon) < 5.0, (q.name, r)
        assert r.moved_m == pytest.approx(geo.geodesic_distance(lat, lon, r.lat, r.lon))


def test_a_fix_beyond_the_reach_or_without_structure_is_left_alone(dense, queries):
    """The structure's peak 200 m away (beyond max(25 m, 10 map px) = 50 m) is not taken, and a flat grey query
    has no peak to move to."""
    q = queries[0]
    image = read_image(q.path)
    lat, lon = _moved(q.lat, q.lon, 200.0, 0.0)
    r = refine_fix(dense, image, lat, lon, q.truth_heading_deg, 1.0)
    assert r is None or geo.geodesic_distance(lat, lon, r.lat, r.lon) <= 50.0
    assert r is None or geo.geodesic_distance(q.lat, q.lon, r.lat, r.lon) > 100.0  # not the far truth
    flat = np.full_like(image, 128)
    assert refine_fix(dense, flat, q.lat, q.lon, 0.0, 1.0) is None


def test_the_placement_of_a_transform_is_its_heading_and_scale():
    """A query turned 30° clockwise from north (OpenCV undoes it by +30°) at 2 map px per query px."""
    t = math.radians(-30.0)  # query -> map: turned back counter-clockwise as displayed (y down)
    H = np.array([[2 * math.cos(t), -2 * math.sin(t), 5.0], [2 * math.sin(t), 2 * math.cos(t), 7.0], [0, 0, 1]])
    angle, scale = placement_of(H)
    assert angle == pytest.approx(30.0) and scale == pytest.approx(2.0)
