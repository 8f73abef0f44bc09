"""maps.py: GeoTIFF windows equal rasterio's own read, alpha -> valid mask, exact georeference; seed and XYZ
tile folders built here from real pixels mosaic exactly and sit where their metadata says; bad input is an
AerolocError that names the file."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
from affine import Affine
from pyproj import Transformer
from rasterio.windows import Window

from _mapfolders import build_seed_folder, build_xyz_folder, xyz_bounds
from aeroloc.core.errors import AerolocError
from aeroloc.maps.sources import GeoTiffMap, TileFolderMap, open_map


# --- GeoTIFF ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "window", [(0, 0, 50, 40), (300, 200, 171, 171), (934 - 64, 723 - 33, 64, 33), (0, 0, 934, 723), (933, 722, 1, 1)]
)
def test_naip_windows_equal_rasterio_read(naip_map, window):
    m = open_map(naip_map)
    assert isinstance(m, GeoTiffMap) and (m.width, m.height) == (934, 723)
    col, row, w, h = window
    rgb, valid = m.read(col, row, w, h)
    with rasterio.open(naip_map) as ds:
        ref = np.moveaxis(ds.read([1, 2, 3], window=Window(col, row, w, h)), 0, -1)
    assert rgb.shape == (h, w, 3) and rgb.dtype == np.uint8 and valid.shape == (h, w)
    np.testing.assert_array_equal(rgb, ref)
    assert valid.all()  # NAIP has no no-data pixels


def test_naip_georeference(naip_map):
    m = open_map(naip_map)
    assert m.crs == "EPSG:26914"
    assert m.transform == Affine(5.0, 0.0, 485899.0, 0.0, -5.0, 5209246.0)
    # 5 m of UTM grid near the central meridian is 5 m / k with k ~ 0.9996: geodesic pixel size ~ 5.002 m.
    assert m.resolution_m == pytest.approx(5.0 / 0.9996, rel=2e-4)
    south, west, north, east = m.bounds_latlon()
    assert (south, west, north, east) == pytest.approx((47.004, -99.186, 47.037, -99.124), abs=1.5e-3)


def test_pixel_latlon_round_trip_and_independent_check(naip_map):
    m = open_map(naip_map)
    rng = np.random.default_rng(3)
    col, row = rng.uniform(-50, 984, 300), rng.uniform(-50, 773, 300)  # also outside the map
    lat, lon = m.pixel_to_latlon(col, row)
    c2, r2 = m.latlon_to_pixel(lat, lon)
    np.testing.assert_allclose(c2, col, atol=1e-6)
    np.testing.assert_allclose(r2, row, atol=1e-6)
    # Independent: rasterio's affine + pyproj.
    x, y = 485899.0 + 5 * col, 5209246.0 - 5 * row
    lon_ref, lat_ref = Transformer.from_crs("EPSG:26914", "EPSG:4326", always_xy=True).transform(x, y)
    np.testing.assert_allclose(lat, lat_ref, atol=1e-11)
    np.testing.assert_allclose(lon, lon_ref, atol=1e-11)


def test_contains_latlon_is_inclusive_and_exact(naip_map):
    m = open_map(naip_map)
    lat, lon = m.pixel_to_latlon([0, 934, 467, -1e-3, 934.001, 467], [0, 723, 361, 10, 10, 723.001])
    inside = m.contains_latlon(lat, lon)
    # corners exactly on the edge count (up to float noise on the round trip); just outside does not
    assert list(inside[1:3]) == [True, True] and not inside[3:].any()
    c, r = m.latlon_to_pixel(lat[0], lon[0])
    assert abs(float(c)) < 1e-6 and abs(float(r)) < 1e-6


def test_toledo_alpha_is_the_valid_mask(toledo_map):
    m = open_map(toledo_map)
    assert m.crs == "EPSG:32617" and (m.width, m.height) == (708, 801)
    rgb, valid = m.read(0, 0, m.width, m.height)
    with rasterio.open(toledo_map) as ds:
        ref = ds.read()
    alpha_ok = ref[3] > 0
    np.testing.assert_array_equal(valid, alpha_ok)
    assert 0 < (~valid).sum() < valid.size  # the orthomosaic has transparent borders
    np.testing.assert_array_equal(rgb[valid], np.moveaxis(ref[:3], 0, -1)[valid])
    assert (rgb[~valid] == 0).all()
    # a window entirely in the transparent corner region is all invalid
    ys, xs = np.nonzero(~alpha_ok)
    y, x = ys[0], xs[0]
    _, v = m.read(int(x), int(y), 1, 1)
    assert not v.any()


def test_window_outside_the_map_is_an_error(naip_map):
    m = open_map(naip_map)
    for win in [(-1, 0, 10, 10), (930, 0, 10, 10), (0, 720, 10, 10), (0, 0, 0, 5)]:
        with pytest.raises(AerolocError, match="outside"):
            m.read(*win)


# --- seed tile folder -------------------------------------------------------------------------------------
def test_seed_folder_opens_and_mosaics_exactly(tmp_path, naip_map):
    s = build_seed_folder(tmp_path / "seed", naip_map)
    m = open_map(s.path)
    assert isinstance(m, TileFolderMap)
    assert (m.width, m.height) == (4 * 64, 3 * 48) and m.base_tile_px == 64
    assert m.crs == "EPSG:3857"
    full, valid = m.read(0, 0, m.width, m.height)
    np.testing.assert_array_equal(full, s.image)
    assert valid.all()
    # a window across the four tiles meeting at (col 128, row 48)
    win, _ = m.read(128 - 7, 48 - 5, 20, 13)
    top = np.concatenate([s.image[43:48, 121:128], s.image[43:48, 128:141]], axis=1)
    bottom = np.concatenate([s.image[48:56, 121:128], s.image[48:56, 128:141]], axis=1)
    np.testing.assert_array_equal(win, np.concatenate([top, bottom], axis=0))
    # opening through the metadata file itself is the same map
    m2 = open_map(s.path / "map_metadata.txt")
    assert m2.transform == m.transform and (m2.width, m2.height) == (m.width, m.height)


def test_seed_folder_corners_are_where_the_metadata_says(tmp_path, naip_map):
    s = build_seed_folder(tmp_path / "seed", naip_map)
    m = open_map(s.path)
    for (r, c), (tl_lat, tl_lon, br_lat, br_lon) in s.corners.items():
        lat, lon = m.pixel_to_latlon([c * s.tile_w, (c + 1) * s.tile_w], [r * s.tile_h, (r + 1) * s.tile_h])
        np.testing.assert_allclose([lat[0], lon[0], lat[1], lon[1]], [tl_lat, tl_lon, br_lat, br_lon], atol=1e-10)
    # 7.25 Mercator metres per pixel = 7.25 cos(lat) ground metres
    assert m.resolution_m == pytest.approx(7.25 * np.cos(np.radians(47.03 - 0.002)), rel=1e-3)
    # a point just outside the mosaic's west edge is outside (no abs())
    lat, lon = m.pixel_to_latlon(-0.01, 10)
    c, _ = m.latlon_to_pixel(lat, lon)
    assert float(c) == pytest.approx(-0.01, abs=1e-6)
    assert not m.contains_latlon(lat, lon)


def test_xyz_folder_opens_mosaics_and_georeferences(tmp_path, naip_map):
    folder = tmp_path / "xyz"
    image = build_xyz_folder(folder, naip_map, skip={(3681, 5762)})
    m = open_map(folder)
    assert isinstance(m, TileFolderMap) and (m.width, m.height) == (3 * 64, 2 * 64)
    rgb, valid = m.read(0, 0, m.width, m.height)
    np.testing.assert_array_equal(rgb[:64], image[:64])
    np.testing.assert_array_equal(rgb[64:, :128], image[64:, :128])
    assert valid[:, :128].all() and valid[:64].all()
    # the missing tile (x=3681, y=5762) reads as no-data
    assert not valid[64:, 128:].any() and (rgb[64:, 128:] == 0).all()
    for r in range(2):
        for c in range(3):
            north, west, south, east = xyz_bounds(14, 3679 + c, 5761 + r)
            lat, lon = m.pixel_to_latlon([c * 64, (c + 1) * 64], [r * 64, (r + 1) * 64])
            np.testing.assert_allclose([lat[0], lon[0], lat[1], lon[1]], [north, west, south, east], atol=1e-10)


def test_xyz_folder_with_several_zooms_needs_a_manifest(tmp_path, naip_map):
    folder = tmp_path / "xyz"
    build_xyz_folder(folder, naip_map, z=14)
    build_xyz_folder(folder, naip_map, z=13, x0=1839, y0=2880, n_cols=1, n_rows=1)
    with pytest.raises(AerolocError, match="several zoom levels"):
        open_map(folder)
    (folder / "manifest.json").write_text(json.dumps({"layout": "xyz", "zoom": 13}))
    m = open_map(folder)
    assert (m.width, m.height) == (64, 64)
    lat, lon = m.pixel_to_latlon(0, 0)
    north, west, _, _ = xyz_bounds(13, 1839, 2880)
    assert (float(lat), float(lon)) == pytest.approx((north, west), abs=1e-10)


# --- bad input --------------------------------------------------------------------------------------------
def test_missing_map(tmp_path):
    with pytest.raises(AerolocError, match=r"nope\.tif"):
        open_map(tmp_path / "nope.tif")
    with pytest.raises(AerolocError, match=r"nope\.tif"):
        GeoTiffMap(tmp_path / "nope.tif")


def test_text_file_renamed_tif(tmp_path):
    p = tmp_path / "fake.tif"
    p.write_text("this is not a raster\n")
    with pytest.raises(AerolocError, match=r"fake\.tif"):
        open_map(p)


def test_geotiff_without_crs(tmp_path):
    p = tmp_path / "nocrs.tif"
    with rasterio.open(
        p, "w", driver="GTiff", width=8, height=8, count=3, dtype="uint8", transform=Affine(1, 0, 100, 0, -1, 200)
    ) as ds:
        ds.write(np.zeros((3, 8, 8), np.uint8))
    with pytest.raises(AerolocError, match=r"nocrs.tif.*coordinate reference system"):
        open_map(p)


def test_empty_folder_is_not_a_map(tmp_path):
    with pytest.raises(AerolocError, match="not a map"):
        open_map(tmp_path)


def test_bad_manifest(tmp_path):
    (tmp_path / "manifest.json").write_text("{broken")
    with pytest.raises(AerolocError, match=r"manifest\.json"):
        open_map(tmp_path)


def _rewrite_metadata(folder, edit):
    meta = folder / "map_metadata.txt"
    lines = meta.read_text().splitlines()
    meta.write_text("\n".join(edit(lines)) + "\n")


def test_metadata_rows_not_a_grid(tmp_path, naip_map):
    s = build_seed_folder(tmp_path / "seed", naip_map)
    _rewrite_metadata(s.path, lambda ls: ls[:-1])  # 11 rows cannot be a grid of 4 columns
    with pytest.raises(AerolocError, match=r"map_metadata.txt.*grid"):
        open_map(s.path)


def test_metadata_rows_out_of_order(tmp_path, naip_map):
    s = build_seed_folder(tmp_path / "seed", naip_map)
    _rewrite_metadata(s.path, lambda ls: [ls[0], ls[2], ls[1], *ls[3:]])  # columns 0 and 1 swapped
    with pytest.raises(AerolocError, match=r"map_metadata.txt.*tile_0_0.png \(row 0, column 1\)"):
        open_map(s.path)
    s = build_seed_folder(tmp_path / "seed2", naip_map)
    _rewrite_metadata(s.path, lambda ls: [ls[0], *ls[5:9], *ls[1:5], *ls[9:]])  # rows 0 and 1 swapped
    with pytest.raises(AerolocError, match=r"map_metadata.txt.*row-major"):
        open_map(s.path)


@pytest.mark.parametrize("bad_line", ["tile_0_1.png 47.03 -99.17", "tile_0_1.png", "tile_0_1.png a b c d"])
def test_metadata_row_with_missing_or_bad_columns(tmp_path, naip_map, bad_line):
    s = build_seed_folder(tmp_path / "seed", naip_map)
    _rewrite_metadata(s.path, lambda ls: [ls[0], ls[1], bad_line, *ls[3:]])
    with pytest.raises(AerolocError, match=r"map_metadata.txt:3"):
        open_map(s.path)


def test_metadata_lists_a_missing_tile(tmp_path, naip_map):
    s = build_seed_folder(tmp_path / "seed", naip_map)
    (s.path / "tile_2_3.png").unlink()
    with pytest.raises(AerolocError, match=r"tile_2_3\.png"):
        open_map(s.path)


def test_corrupt_tile_image(tmp_path, naip_map):
    s = build_seed_folder(tmp_path / "seed", naip_map)
    (s.path / "tile_0_0.png").write_bytes(b"\x89PNG garbage")
    with pytest.raises(AerolocError, match=r"tile_0_0\.png"):
        open_map(s.path)
    s = build_seed_folder(tmp_path / "seed2", naip_map)
    (s.path / "tile_1_2.png").write_bytes(b"\x89PNG garbage")
    m = open_map(s.path)  # only the first tile is opened up front; the bad one fails when read
    m.read(0, 0, 64, 48)
    with pytest.raises(AerolocError, match=r"tile_1_2\.png"):
        m.read(100, 40, 60, 20)


def test_tile_of_another_size(tmp_path, naip_map):
    from PIL import Image

    s = build_seed_folder(tmp_path / "seed", naip_map)
    Image.fromarray(np.zeros((10, 10, 3), np.uint8)).save(s.path / "tile_1_1.png")
    m = open_map(s.path)
    with pytest.raises(AerolocError, match=r"tile_1_1.png.*expected 64x48"):
        m.read(0, 0, m.width, m.height)


def test_metadata_grid_with_uneven_spacing(tmp_path, naip_map):
    """Shared edges but one column twice as wide on the ground: one affine transform cannot georeference it."""
    s = build_seed_folder(tmp_path / "seed", naip_map)

    def widen_column_1(lines):
        out = [lines[0]]
        for ln in lines[1:]:
            name, tl_lat, tl_lon, br_lat, br_lon = ln.split()
            _r, c = map(int, name[5:-4].split("_"))
            w = s.corners[(0, 1)][3] - s.corners[(0, 1)][1]  # column width in degrees
            shift = lambda lon, col, w=w: float(lon) + (w if col >= 2 else 0.0)  # noqa: E731
            out.append(f"{name} {tl_lat} {shift(tl_lon, c):.12f} {br_lat} {shift(br_lon, c + 1):.12f}")
        return out

    _rewrite_metadata(s.path, widen_column_1)
    with pytest.raises(AerolocError, match=r"map_metadata.txt: tile .* off an evenly spaced grid"):
        open_map(s.path)
