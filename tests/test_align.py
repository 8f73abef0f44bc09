"""Alignment: a homography into a real NAIP tile gives the query centre's lat/lon exactly; weak or degenerate
homographies, and positions far from the tile or off the map, give "not localized" and NaN, never a guess."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pyproj import Transformer

from aeroloc.localization.alignment import align
from aeroloc.maps.tiling import load_info, load_tiles

QUERY = (200, 150)  # query image (w, h): centre (100, 75)
MIN_INLIERS = 35


@pytest.fixture(scope="module")
def grid(naip_tiles_db, naip_map):
    """The tiles of the NAIP database, the map size, and an independent pixel -> lat/lon of the whole map
    (rasterio's transform of the GeoTIFF + pyproj; not the tile's stored affine nor aeroloc.core.geo)."""
    import rasterio

    tiles = {t.id: t for t in load_tiles(naip_tiles_db)}
    info = load_info(naip_tiles_db)
    with rasterio.open(naip_map) as ds:
        transform, crs, size = ds.transform, ds.crs.to_wkt(), (ds.width, ds.height)
    assert (info["map"]["width"], info["map"]["height"]) == size
    to_wgs84 = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)

    def map_px_to_latlon(col, row):
        x = transform.a * col + transform.b * row + transform.c
        y = transform.d * col + transform.e * row + transform.f
        lon, lat = to_wgs84.transform(x, y)
        return lat, lon

    return tiles, size, map_px_to_latlon


def similarity(scale: float, tx: float, ty: float) -> np.ndarray:
    return np.array([[scale, 0, tx], [0, scale, ty], [0, 0, 1]], np.float64)


@pytest.mark.parametrize(
    "tile_id, scale, tx, ty",
    [
        ("r002c003", 1.0, 30.0, 40.0),  # interior tile, pure translation
        ("r002c003", 0.8, 12.5, 101.25),  # translation + scale
        ("r000c000", 1.3, 3.0, 7.0),  # top-left tile of the map
        ("r004c006", 0.7, 150.0, 180.0),  # bottom-right tile (snapped to the map edge)
    ],
)
def test_centre_maps_to_hand_computed_latlon(grid, tile_id, scale, tx, ty):
    tiles, size, map_px_to_latlon = grid
    tile = tiles[tile_id]
    a = align(similarity(scale, tx, ty), 200, QUERY, tile, size, MIN_INLIERS)
    assert a.localized and a.status == "localized"
    x, y = scale * QUERY[0] / 2 + tx, scale * QUERY[1] / 2 + ty  # the query centre in tile pixels
    assert a.tile_xy == pytest.approx((x, y), abs=1e-9)
    lat, lon = map_px_to_latlon(tile.col + x, tile.row + y)
    assert abs(a.lat - lat) < 1e-6 and abs(a.lon - lon) < 1e-6, (a.lat - lat, a.lon - lon)
    assert 47.0 < a.lat < 47.04 and -99.19 < a.lon < -99.12  # inside the NAIP footprint


def test_centre_just_outside_the_tile_is_extrapolated_not_clamped(grid):
    """A centre 60 px right of an interior tile is still on the map: its true position, no abs()/clamping."""
    tiles, size, map_px_to_latlon = grid
    tile = tiles["r002c003"]
    tx = tile.width + 60 - QUERY[0] / 2
    a = align(similarity(1.0, tx, 10.0), 200, QUERY, tile, size, MIN_INLIERS)
    assert a.localized
    lat, lon = map_px_to_latlon(tile.col + tile.width + 60, tile.row + 10 + QUERY[1] / 2)
    assert abs(a.lat - lat) < 1e-6 and abs(a.lon - lon) < 1e-6
    _inside_lat, inside_lon = tile.pixel_to_latlon(tile.width, 10 + QUERY[1] / 2)
    assert a.lon > inside_lon + 1e-4  # ~60 px x 5 m east of the tile's right edge


def _rejected(a):
    assert a.status.startswith("not localized"), a.status
    assert not a.localized and math.isnan(a.lat) and math.isnan(a.lon)
    return a.status


def test_too_few_inliers_and_no_homography(grid):
    tiles, size, _ = grid
    tile = tiles["r002c003"]
    assert "inliers" in _rejected(align(similarity(1, 30, 40), MIN_INLIERS - 1, QUERY, tile, size, MIN_INLIERS))
    _rejected(align(None, 500, QUERY, tile, size, MIN_INLIERS))
    assert align(similarity(1, 30, 40), MIN_INLIERS, QUERY, tile, size, MIN_INLIERS).localized  # boundary


def test_degenerate_homographies_are_rejected(grid):
    tiles, size, _ = grid
    tile = tiles["r002c003"]
    flip = np.array([[-1.0, 0, 200 + 30], [0, 1, 40], [0, 0, 1]])  # mirror image landing inside the tile
    assert "mirror" in _rejected(align(flip, 300, QUERY, tile, size, MIN_INLIERS))
    collapse = np.array([[1.0, 0, 30], [1.0, 0, 40], [0, 0, 1]])  # the whole query onto a line
    assert "degenerate" in _rejected(align(collapse, 300, QUERY, tile, size, MIN_INLIERS))
    tiny = similarity(0.01, 100, 100)  # 200 px of query onto 2 px of tile
    assert "scale" in _rejected(align(tiny, 300, QUERY, tile, size, MIN_INLIERS))
    shear = np.array([[1.0, 4.0, 0], [0, 1, 0], [0, 0, 1]])
    _rejected(align(shear, 300, QUERY, tile, size, MIN_INLIERS))
    horizon = np.array([[1.0, 0, 0], [0, 1, 0], [-0.01, 0, 1]])  # the query centre (x = 100) goes to infinity
    assert "horizon" in _rejected(align(horizon, 300, QUERY, tile, size, MIN_INLIERS))
    beyond = np.array([[1.0, 0, 0], [0, 1, 0], [-0.006, 0, 1]])  # the right edge (x = 200) beyond the horizon
    assert "horizon" in _rejected(align(beyond, 300, QUERY, tile, size, MIN_INLIERS))
    nan = similarity(1, 30, 40)
    nan[0, 2] = np.nan
    _rejected(align(nan, 300, QUERY, tile, size, MIN_INLIERS))


def test_centre_far_outside_the_tile_or_the_map_is_rejected(grid):
    tiles, size, _ = grid
    interior = tiles["r002c003"]
    far = similarity(1.0, 3 * interior.width, 0)  # three tile sides to the right: an extrapolation, not a fix
    assert "outside the matched tile" in _rejected(align(far, 300, QUERY, interior, size, MIN_INLIERS))
    far_up = similarity(1.0, 0, -interior.height)
    _rejected(align(far_up, 300, QUERY, interior, size, MIN_INLIERS))
    # the bottom-right tile touches the map edge: 60 px beyond its right side is within reach of the tile
    # check (half a side) but off the map
    edge = tiles["r004c006"]
    assert edge.col + edge.width == size[0] and edge.row + edge.height == size[1]
    off_map = similarity(1.0, edge.width + 60 - QUERY[0] / 2, 20)
    assert "outside the map" in _rejected(align(off_map, 300, QUERY, edge, size, MIN_INLIERS))
    off_bottom = similarity(1.0, 20, edge.height + 40 - QUERY[1] / 2)
    assert "outside the map" in _rejected(align(off_bottom, 300, QUERY, edge, size, MIN_INLIERS))
    top_left = tiles["r000c000"]
    off_left = similarity(1.0, -30 - QUERY[0] / 2, 50)
    assert "outside the map" in _rejected(align(off_left, 300, QUERY, top_left, size, MIN_INLIERS))


def _similar_pairs(n, n_outliers, seed=0):
    rng = np.random.default_rng(seed)
    p0 = rng.uniform(0, 400, (n, 2))
    ang, s, t = np.radians(12.0), 1.3, np.array([35.0, -20.0])
    R = s * np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    p1 = p0 @ R.T + t
    p1[:n_outliers] = rng.uniform(-100, 600, (n_outliers, 2))
    return p0, p1, R, t


def test_similarity_fallback_recovers_a_known_transform_despite_outliers():
    """verify.verify_similarity: the model used when a homography is degenerate must recover rotation/scale/shift."""
    from aeroloc.matching.verify import verify_similarity

    p0, p1, R, t = _similar_pairs(200, 40)  # 20 % outliers
    v = verify_similarity(p0, p1, threshold_px=2.0)
    assert v.inliers[40:].mean() > 0.95 and v.inliers[:40].mean() < 0.2 and v.n_inliers == v.inliers.sum()
    assert np.allclose(v.H[:2, :2], R, atol=1e-3) and np.allclose(v.H[:2, 2], t, atol=0.05)
    assert np.allclose(v.H[2], [0, 0, 1])


def test_similarity_finds_the_consensus_of_a_cross_season_pair():
    """At the ~7 % inlier ratio of a hard cross-season pair (30 right matches among 400) the 2-point similarity
    search still finds the transform, and too few matches give no model rather than an error."""
    from aeroloc.matching.verify import verify_similarity

    p0, p1, R, t = _similar_pairs(400, 370, seed=1)
    v = verify_similarity(p0, p1, threshold_px=2.0)
    assert v.inliers[370:].sum() >= 28 and v.inliers[:370].sum() <= 3
    assert np.allclose(v.H[:2, :2], R, atol=2e-3) and np.allclose(v.H[:2, 2], t, atol=0.5)
    one = verify_similarity(p0[:1], p1[:1])
    assert one.H is None and one.n_inliers == 0


def test_the_similarity_refit_recovers_a_nadir_view_from_a_screens_inliers():
    """Inliers a homography RANSAC kept (here: a 20° turn, scale 0.8 and a shift, 0.5 px noise, plus two pairs
    10 px off) give back the similarity: the query centre lands within a pixel of where the true transform puts it."""
    import cv2

    from aeroloc.matching.verify import similarity_on_inliers

    rng = np.random.default_rng(3)
    p0 = rng.uniform(0, 512, (60, 2))
    a, s, t = np.radians(20.0), 0.8, np.array([40.0, -25.0])
    R = s * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    p1 = p0 @ R.T + t + rng.normal(0, 0.5, p0.shape)
    p1[:2] += 10.0  # two inliers a 4 px RANSAC threshold would not have kept, but a refit must not follow
    H = similarity_on_inliers(p0, p1)
    assert H is not None and np.allclose(H[:2, :2], R, atol=0.01)
    centre = cv2.perspectiveTransform(np.array([[[256.0, 256.0]]]), H)[0, 0]
    assert np.linalg.norm(centre - (R @ [256.0, 256.0] + t)) < 1.0
    assert similarity_on_inliers(p0[:1], p1[:1]) is None  # one pair fixes no rotation and scale
