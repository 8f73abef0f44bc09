"""geo.py against values computed independently: closed-form Web Mercator, a Krüger-series transverse
Mercator written here (Karney 2011, 4th order), Vincenty's inverse formula written here, published constants."""

from __future__ import annotations

import math

import numpy as np
import pytest
from affine import Affine
from pyproj import Transformer

from aeroloc.core import geo
from aeroloc.core.errors import AerolocError

# --- ellipsoids ---------------------------------------------------------------------------------------------
WGS84_A, WGS84_F = 6378137.0, 1 / 298.257223563
GRS80_A, GRS80_F = 6378137.0, 1 / 298.257222101  # NAD83, the datum of the NAIP map (EPSG:26914)


# --- Web Mercator ------------------------------------------------------------------------------------------
def _merc_lat(y_frac: float) -> float:
    """Latitude of the tile-row edge at fraction y_frac of the world height (0 = north edge)."""
    return math.degrees(math.atan(math.sinh(math.pi * (1 - 2 * y_frac))))


def test_z0_tile_is_the_whole_mercator_world():
    # The only z=0 tile spans lon -180..180 and lat ±atan(sinh(pi)) = ±85.0511287798066°.
    north, west, south, east = geo.xyz_tile_bounds(0, 0, 0)
    assert north == pytest.approx(85.0511287798066, abs=1e-12)
    assert south == pytest.approx(-85.0511287798066, abs=1e-12)
    assert (west, east) == (pytest.approx(-180.0, abs=1e-12), pytest.approx(180.0, abs=1e-12))


@pytest.mark.parametrize(
    "x,y,expected",
    [
        # z=1 splits the world at the equator and the Greenwich meridian.
        (0, 0, (85.0511287798066, -180.0, 0.0, 0.0)),
        (1, 0, (85.0511287798066, 0.0, 0.0, 180.0)),
        (0, 1, (0.0, -180.0, -85.0511287798066, 0.0)),
        (1, 1, (0.0, 0.0, -85.0511287798066, 180.0)),
    ],
)
def test_z1_tiles_split_at_equator_and_greenwich(x, y, expected):
    assert geo.xyz_tile_bounds(1, x, y) == pytest.approx(expected, abs=1e-12)


def test_z10_tile_edges_by_hand():
    # z=10 has 1024 columns of 360/1024 = 0.3515625° each. Tile x=229 holds the NAIP map (lon -99.15):
    #   west = 229 * 0.3515625 - 180 = -99.4921875, east = 230 * 0.3515625 - 180 = -99.140625.
    # Rows: lat = atan(sinh(pi * (1 - 2 y / 1024))); y = 360 gives the edge at
    #   atan(sinh(pi * 304/1024)) = atan(sinh(0.932660...)) = atan(1.0739...) = 47.0402°
    # and y = 361 (its south edge) = atan(sinh(pi * 302/1024)).
    north, west, south, east = geo.xyz_tile_bounds(10, 229, 360)
    assert west == pytest.approx(-99.4921875, abs=1e-12)
    assert east == pytest.approx(-99.140625, abs=1e-12)
    assert north == pytest.approx(_merc_lat(360 / 1024), abs=1e-11)
    assert south == pytest.approx(_merc_lat(361 / 1024), abs=1e-11)
    assert north == pytest.approx(47.0402, abs=1e-4)
    # The tile of a point inside it is that tile, and the NAIP map centre lies in it.
    assert geo.latlon_to_tile(47.02, -99.15, 10) == (229, 360)
    # A tile at the equator/Greenwich corner: x=512, y=511 has south edge 0 and west edge 0.
    n2, w2, s2, e2 = geo.xyz_tile_bounds(10, 512, 511)
    assert (w2, s2) == (pytest.approx(0.0, abs=1e-12), pytest.approx(0.0, abs=1e-12))
    assert e2 == pytest.approx(0.3515625, abs=1e-12)
    assert n2 == pytest.approx(_merc_lat(511 / 1024), abs=1e-12)


def test_mercator_matches_pyproj_epsg3857():
    rng = np.random.default_rng(0)
    lat, lon = rng.uniform(-85, 85, 200), rng.uniform(-180, 180, 200)
    x, y = geo.mercator_from_latlon(lat, lon)
    px, py = Transformer.from_crs("EPSG:4326", "EPSG:3857", always_xy=True).transform(lon, lat)
    np.testing.assert_allclose(x, px, atol=1e-6)
    np.testing.assert_allclose(y, py, atol=1e-6)
    lat2, lon2 = geo.latlon_from_mercator(x, y)
    np.testing.assert_allclose(lat2, lat, atol=1e-11)
    np.testing.assert_allclose(lon2, lon, atol=1e-11)


@pytest.mark.parametrize("zoom", [0, 1, 7, 15, 19])
def test_global_pixel_round_trip(zoom):
    rng = np.random.default_rng(zoom)
    lat, lon = rng.uniform(-85, 85, 500), rng.uniform(-180, 180, 500)
    px, py = geo.latlon_to_global_px(lat, lon, zoom)
    size = 256 * 2**zoom
    assert np.all((px >= 0) & (px <= size) & (py >= 0) & (py <= size))
    lat2, lon2 = geo.global_px_to_latlon(px, py, zoom)
    np.testing.assert_allclose(lat2, lat, atol=1e-10)
    np.testing.assert_allclose(lon2, lon, atol=1e-10)
    # (0, 0) is the world centre; y grows southwards.
    cx, cy = geo.latlon_to_global_px(0.0, 0.0, zoom)
    assert (float(cx), float(cy)) == pytest.approx((size / 2, size / 2), abs=1e-9)
    _, ys = geo.latlon_to_global_px(np.array([10.0, -10.0]), np.array([0.0, 0.0]), zoom)
    assert ys[0] < size / 2 < ys[1]


def test_mercator_transform_puts_tile_corners_on_xyz_bounds():
    # A mosaic whose top-left is tile (12, 918, 1441): its pixel (256, 256) is the SE corner of that tile.
    tr = geo.mercator_transform(12, 918, 1441)
    north, west, south, east = geo.xyz_tile_bounds(12, 918, 1441)
    x, y = geo.pixel_to_world(tr, [0, 256], [0, 256])
    lat, lon = geo.latlon_from_mercator(x, y)
    np.testing.assert_allclose([lat[0], lon[0], lat[1], lon[1]], [north, west, south, east], atol=1e-11)


@pytest.mark.parametrize(
    "x,y,z,key",
    [
        (3, 5, 3, "213"),  # the example in Microsoft's "Bing Maps Tile System" article
        (0, 0, 1, "0"),
        (1, 0, 1, "1"),
        (0, 1, 1, "2"),
        (1, 1, 1, "3"),
        (0, 0, 0, ""),
        (1023, 1023, 10, "3" * 10),
        (229, 360, 10, "0213302101"),  # 229 = 0b0011100101, 360 = 0b0101101000 -> digit = xbit + 2 ybit
    ],
)
def test_quadkey(x, y, z, key):
    assert geo.quadkey(x, y, z) == key


# --- transverse Mercator written here (Krüger series to n^4, Karney 2011 eqs. 11, 35, 36) ----------------
def _tm_coeffs(f):
    n = f / (2 - f)
    A = 1 / (1 + n) * (1 + n**2 / 4 + n**4 / 64)
    alpha = [
        n / 2 - 2 * n**2 / 3 + 5 * n**3 / 16 + 41 * n**4 / 180,
        13 * n**2 / 48 - 3 * n**3 / 5 + 557 * n**4 / 1440,
        61 * n**3 / 240 - 103 * n**4 / 140,
        49561 * n**4 / 161280,
    ]
    beta = [
        n / 2 - 2 * n**2 / 3 + 37 * n**3 / 96 - n**4 / 360,
        n**2 / 48 + n**3 / 15 - 437 * n**4 / 1440,
        17 * n**3 / 480 - 37 * n**4 / 840,
        4397 * n**4 / 161280,
    ]
    delta = [
        2 * n - 2 * n**2 / 3 - 2 * n**3 + 116 * n**4 / 45,
        7 * n**2 / 3 - 8 * n**3 / 5 - 227 * n**4 / 45,
        56 * n**3 / 15 - 136 * n**4 / 35,
        4279 * n**4 / 630,
    ]
    return n, A, alpha, beta, delta


def utm_forward(lat, lon, zone, a=WGS84_A, f=WGS84_F):
    n, A, alpha, _, _ = _tm_coeffs(f)
    k0, lon0 = 0.9996, math.radians(-183 + 6 * zone)
    phi, dl = math.radians(lat), math.radians(lon) - lon0
    c = 2 * math.sqrt(n) / (1 + n)
    t = math.sinh(math.atanh(math.sin(phi)) - c * math.atanh(c * math.sin(phi)))
    xi_, eta_ = math.atan2(t, math.cos(dl)), math.atanh(math.sin(dl) / math.sqrt(1 + t * t))
    xi = xi_ + sum(al * math.sin(2 * j * xi_) * math.cosh(2 * j * eta_) for j, al in enumerate(alpha, 1))
    eta = eta_ + sum(al * math.cos(2 * j * xi_) * math.sinh(2 * j * eta_) for j, al in enumerate(alpha, 1))
    return 500000 + k0 * a * A * eta, k0 * a * A * xi


def utm_inverse(e, nn, zone, a=GRS80_A, f=GRS80_F):
    _n, A, _, beta, delta = _tm_coeffs(f)
    k0, lon0 = 0.9996, math.radians(-183 + 6 * zone)
    xi, eta = nn / (k0 * a * A), (e - 500000) / (k0 * a * A)
    xi_ = xi - sum(b * math.sin(2 * j * xi) * math.cosh(2 * j * eta) for j, b in enumerate(beta, 1))
    eta_ = eta - sum(b * math.cos(2 * j * xi) * math.sinh(2 * j * eta) for j, b in enumerate(beta, 1))
    chi = math.asin(math.sin(xi_) / math.cosh(eta_))
    phi = chi + sum(d * math.sin(2 * j * chi) for j, d in enumerate(delta, 1))
    return math.degrees(phi), math.degrees(lon0 + math.atan2(math.sinh(eta_), math.cos(xi_)))


def test_utm_central_meridian_at_equator_is_false_easting():
    # UTM 14N: central meridian -183 + 6*14 = -99°; on it at the equator E = 500000 m, N = 0 exactly.
    x, y = geo.latlon_to_crs(0.0, -99.0, "EPSG:32614")
    assert float(x) == pytest.approx(500000.0, abs=1e-6)
    assert float(y) == pytest.approx(0.0, abs=1e-6)
    lat, lon = geo.crs_to_latlon(500000.0, 0.0, "EPSG:32614")
    assert (float(lat), float(lon)) == pytest.approx((0.0, -99.0), abs=1e-12)


def test_utm_forward_matches_krueger_series():
    # Points of the NAIP footprint and around the zone: agree to < 1 mm.
    pts = [(47.004, -99.186), (47.037, -99.124), (47.02, -99.0), (0.5, -101.9), (60.0, -96.2), (-33.0, -98.0)]
    for lat, lon in pts:
        zone = 14 if lat >= 0 else None
        crs = "EPSG:32614" if zone else "EPSG:32714"
        e, n = utm_forward(lat, lon, 14)
        if not zone:
            n += 10_000_000  # southern hemisphere false northing
        x, y = geo.latlon_to_crs(lat, lon, crs)
        assert float(x) == pytest.approx(e, abs=1e-3), (lat, lon)
        assert float(y) == pytest.approx(n, abs=1e-3), (lat, lon)


def test_naip_geotiff_corner_to_wgs84(naip_map):
    # The NAIP map's top-left corner is (485899, 5209246) in NAD83 / UTM 14N (EPSG:26914); NAD83 -> WGS84 is
    # the null transform at this precision, so the Krüger inverse on GRS80 gives the WGS84 position.
    import rasterio

    with rasterio.open(naip_map) as ds:
        tr, crs = ds.transform, ds.crs
    assert (tr.c, tr.f) == (485899.0, 5209246.0)
    lat_ref, lon_ref = utm_inverse(485899.0, 5209246.0, 14)
    lat, lon = geo.crs_to_latlon(485899.0, 5209246.0, crs)
    assert float(lat) == pytest.approx(lat_ref, abs=2e-8)  # ~2 mm
    assert float(lon) == pytest.approx(lon_ref, abs=2e-8)
    assert 47.036 < lat_ref < 47.037 and -99.186 < lon_ref < -99.185  # the corner named in the data README
    # ... and back.
    x, y = geo.latlon_to_crs(lat, lon, crs)
    assert (float(x), float(y)) == pytest.approx((485899.0, 5209246.0), abs=1e-6)


def test_crs_round_trip_is_vectorised():
    rng = np.random.default_rng(1)
    lat, lon = rng.uniform(46, 48, 100), rng.uniform(-102, -96, 100)
    x, y = geo.latlon_to_crs(lat, lon, "EPSG:26914")
    assert x.shape == (100,)
    lat2, lon2 = geo.crs_to_latlon(x, y, "EPSG:26914")
    np.testing.assert_allclose(lat2, lat, atol=1e-10)
    np.testing.assert_allclose(lon2, lon, atol=1e-10)


def test_unreadable_crs_is_aeroloc_error():
    with pytest.raises(AerolocError, match="coordinate reference system"):
        geo.parse_crs("EPSG:999999")
    with pytest.raises(AerolocError):
        geo.latlon_to_crs(47.0, -99.0, "not a crs")


def test_affine_pixel_world_round_trip():
    tr = Affine(5.0, 0.0, 485899.0, 0.0, -5.0, 5209246.0)
    x, y = geo.pixel_to_world(tr, [0, 934, 10.5], [0, 723, 3.25])
    np.testing.assert_allclose(x, [485899.0, 485899.0 + 4670, 485899.0 + 52.5])
    np.testing.assert_allclose(y, [5209246.0, 5209246.0 - 3615, 5209246.0 - 16.25])
    c, r = geo.world_to_pixel(tr, x, y)
    np.testing.assert_allclose(c, [0, 934, 10.5], atol=1e-9)
    np.testing.assert_allclose(r, [0, 723, 3.25], atol=1e-9)


# --- geodesics ---------------------------------------------------------------------------------------------
def vincenty_inverse(lat1, lon1, lat2, lon2, a=WGS84_A, f=WGS84_F):
    """Vincenty (1975) inverse, written here from the paper; ~0.5 mm on non-antipodal pairs."""
    b = a * (1 - f)
    L = math.radians(lon2 - lon1)
    U1, U2 = math.atan((1 - f) * math.tan(math.radians(lat1))), math.atan((1 - f) * math.tan(math.radians(lat2)))
    sU1, cU1, sU2, cU2 = math.sin(U1), math.cos(U1), math.sin(U2), math.cos(U2)
    lam = L
    for _ in range(200):
        sl, cl = math.sin(lam), math.cos(lam)
        ss = math.hypot(cU2 * sl, cU1 * sU2 - sU1 * cU2 * cl)
        if ss == 0:
            return 0.0
        cs = sU1 * sU2 + cU1 * cU2 * cl
        sigma = math.atan2(ss, cs)
        sa = cU1 * cU2 * sl / ss
        c2a = 1 - sa * sa
        c2sm = cs - 2 * sU1 * sU2 / c2a if c2a else 0.0
        C = f / 16 * c2a * (4 + f * (4 - 3 * c2a))
        lam_prev = lam
        lam = L + (1 - C) * f * sa * (sigma + C * ss * (c2sm + C * cs * (-1 + 2 * c2sm**2)))
        if abs(lam - lam_prev) < 1e-13:
            break
    u2 = c2a * (a * a - b * b) / (b * b)
    A = 1 + u2 / 16384 * (4096 + u2 * (-768 + u2 * (320 - 175 * u2)))
    B = u2 / 1024 * (256 + u2 * (-128 + u2 * (74 - 47 * u2)))
    ds = B * ss * (c2sm + B / 4 * (cs * (-1 + 2 * c2sm**2) - B / 6 * c2sm * (-3 + 4 * ss**2) * (-3 + 4 * c2sm**2)))
    return b * A * (sigma - ds)


def test_one_degree_of_longitude_on_the_equator():
    # Along the equator the geodesic is the equator itself: 2 pi a / 360 = 111319.490793 m.
    assert geo.geodesic_distance(0.0, 0.0, 0.0, 1.0) == pytest.approx(2 * math.pi * WGS84_A / 360, abs=1e-3)
    assert geo.geodesic_distance(0.0, 0.0, 0.0, 1.0) == pytest.approx(111319.490793, abs=1e-3)


def test_quarter_meridian_and_antipodes():
    # WGS84 quarter meridian (equator -> pole) = 10001965.729 m; antipodal equator points join via a pole.
    assert geo.geodesic_distance(0.0, 0.0, 90.0, 0.0) == pytest.approx(10001965.729, abs=5e-3)
    assert geo.geodesic_distance(0.0, 0.0, 0.0, 180.0) == pytest.approx(2 * 10001965.729, abs=1e-2)


def test_flinders_peak_to_buninyong():
    # Vincenty's worked example as published by Geoscience Australia (GRS80 ~ WGS84 here): 54972.271 m.
    lat1 = -(37 + 57 / 60 + 3.72030 / 3600)
    lon1 = 144 + 25 / 60 + 29.52440 / 3600
    lat2 = -(37 + 39 / 60 + 10.15610 / 3600)
    lon2 = 143 + 55 / 60 + 35.38390 / 3600
    assert geo.geodesic_distance(lat1, lon1, lat2, lon2) == pytest.approx(54972.271, abs=5e-3)


def test_geodesic_matches_vincenty_to_a_centimetre():
    rng = np.random.default_rng(2)
    lat1, lon1 = rng.uniform(-80, 80, 50), rng.uniform(-180, 180, 50)
    lat2, lon2 = lat1 + rng.uniform(-30, 30, 50).clip(-80 - lat1, 80 - lat1), lon1 + rng.uniform(-60, 60, 50)
    d = geo.geodesic_distance(lat1, lon1, lat2, lon2)
    assert isinstance(d, np.ndarray) and d.shape == (50,)
    ref = [vincenty_inverse(*p) for p in zip(lat1, lon1, lat2, lon2)]
    np.testing.assert_allclose(d, ref, atol=1e-2, rtol=0)
    # Short distances on the NAIP map: metres-scale pairs
    d_short = geo.geodesic_distance(47.02, -99.15, 47.02 + 1e-4, -99.15 + 1e-4)
    assert isinstance(d_short, float)
    assert d_short == pytest.approx(vincenty_inverse(47.02, -99.15, 47.02 + 1e-4, -99.15 + 1e-4), abs=1e-4)


def test_geodesic_broadcasts_one_point_against_many():
    d = geo.geodesic_distance(47.0, -99.0, np.array([47.0, 47.001, 47.0]), np.array([-99.0, -99.0, -99.001]))
    assert d.shape == (3,) and d[0] == 0.0
    assert d[1] == pytest.approx(vincenty_inverse(47.0, -99.0, 47.001, -99.0), abs=1e-4)
    assert d[2] == pytest.approx(vincenty_inverse(47.0, -99.0, 47.0, -99.001), abs=1e-4)


def test_offset_latlon_moves_by_the_requested_metres():
    lat, lon = geo.offset_latlon(47.02, -99.15, 30.0, 40.0)
    assert geo.geodesic_distance(47.02, -99.15, lat, lon) == pytest.approx(50.0, abs=1e-6)
    lat_e, lon_e = geo.offset_latlon(47.02, -99.15, 100.0, 0.0)
    assert float(lon_e) > -99.15 and float(lat_e) == pytest.approx(47.02, abs=1e-6)
