"""tiling.py invariants over a grid of zooms x overlaps, on the real NAIP GeoTIFF and on a seed-format tile
folder built from real pixels: full coverage, overlap step, edge snapping, tile count formula, exact corners;
and the on-disk database: images equal the map, resume, cache hit, interrupted builds are completed; tiles as
windows: the same tiles.csv without images, windows cut from band reads equal to the map's own reads and to the
PNGs, a changed map refused."""

from __future__ import annotations

import csv
import math
from dataclasses import replace

import numpy as np
import pytest
from PIL import Image

from _mapfolders import build_seed_folder
from aeroloc.core.errors import AerolocError
from aeroloc.maps import tiling
from aeroloc.maps.sources import open_map
from aeroloc.maps.tiling import TileGrid, load_info, load_tiles, tile_count, write_tiles

ZOOMS = [0.5, 1, 1.5, 2, 3]
OVERLAPS = [0, 0.25, 0.5, 0.75]


@pytest.fixture(scope="module")
def naip(naip_map):
    return open_map(naip_map)


@pytest.fixture(scope="module")
def seed(tmp_path_factory, naip_map):
    s = build_seed_folder(tmp_path_factory.mktemp("seed") / "seed", naip_map)
    return s, open_map(s.path)


def _check_axis(starts, length, side, step):
    assert starts[0] == 0
    assert starts[-1] + side == length  # snapped to the edge, never past it
    diffs = np.diff(starts)
    assert (diffs[:-1] == step).all() if len(diffs) > 1 else True
    if len(diffs):
        assert 0 < diffs[-1] <= step  # the snapped last one is the only shorter step
    assert len(starts) == 1 + math.ceil((length - side) / step)  # the count formula, independently
    assert len(starts) == tile_count(length, side, step)


def _check_grid(m, zoom, overlap, base, base_h=None):
    """``base`` x ``base_h`` (default square) is the zoom-1 tile; sides and steps are per axis."""
    base_h = base if base_h is None else base_h
    g = TileGrid(m, zoom, overlap)
    w, h = round(base / zoom), round(base_h / zoom)
    sx, sy = round(w * (1 - overlap)), round(h * (1 - overlap))
    assert (g.tile_w, g.tile_h, g.step_x, g.step_y) == (w, h, sx, sy)
    if w == h:
        assert (g.side, g.step) == (w, sx)
    _check_axis(g.cols, m.width, w, sx)
    _check_axis(g.rows, m.height, h, sy)
    tiles = list(g)
    assert len(tiles) == len(g) == tile_count(m.width, w, sx) * tile_count(m.height, h, sy)
    assert len({t.id for t in tiles}) == len(tiles)
    covered = np.zeros((m.height, m.width), np.int32)
    for t in tiles:
        assert (t.width, t.height) == (w, h)
        assert t.col + w <= m.width and t.row + h <= m.height
        covered[t.row : t.row + h, t.col : t.col + w] += 1
    assert covered.min() >= 1  # every map pixel is covered
    # corner coordinates are the map's pixel edges (vectorised reference through the map's georeference)
    cols = np.array([t.col for t in tiles], float)
    rows = np.array([t.row for t in tiles], float)
    tl_lat, tl_lon = m.pixel_to_latlon(cols, rows)
    br_lat, br_lon = m.pixel_to_latlon(cols + w, rows + h)
    got = np.array([[*t.corners_latlon[0], *t.corners_latlon[1]] for t in tiles])
    np.testing.assert_allclose(got, np.stack([tl_lat, tl_lon, br_lat, br_lon], 1), atol=1e-11, rtol=0)
    # outer edges: the first tile starts at the map corner, the last ends at the opposite one
    lat, lon = m.pixel_to_latlon([0, m.width], [0, m.height])
    assert got[0, :2] == pytest.approx([lat[0], lon[0]], abs=1e-12)
    assert got[-1, 2:] == pytest.approx([lat[1], lon[1]], abs=1e-12)
    return g, tiles


@pytest.mark.parametrize("zoom", ZOOMS)
@pytest.mark.parametrize("overlap", OVERLAPS)
def test_grid_invariants_on_naip(naip, zoom, overlap):
    _check_grid(naip, zoom, overlap, tiling.DEFAULT_BASE_PX)


@pytest.mark.parametrize("zoom", ZOOMS)
@pytest.mark.parametrize("overlap", OVERLAPS)
def test_grid_invariants_on_seed_folder(seed, zoom, overlap):
    s, m = seed
    assert m.base_tile_size == (64, 48)
    g, tiles = _check_grid(m, zoom, overlap, 64, 48)  # 64 x 48 raw tiles give 64/zoom x 48/zoom tiles
    if zoom == 1 and overlap == 0:  # zoom 1 without overlap is exactly the raw tiles, corners the metadata's
        assert g.cols == [0, 64, 128, 192] and g.rows == [0, 48, 96]
        for t in tiles:
            (tl_lat, tl_lon), (br_lat, br_lon) = t.corners_latlon
            assert [tl_lat, tl_lon, br_lat, br_lon] == pytest.approx(s.corners[(t.row // 48, t.col // 64)], abs=1e-10)
            rgb, _ = m.read(t.col, t.row, t.width, t.height)
            np.testing.assert_array_equal(rgb, s.image[t.row : t.row + 48, t.col : t.col + 64])


def test_point_just_outside_a_tile_is_outside(naip):
    g = TileGrid(naip, 1.5, 0.5)
    t = list(g)[len(g) // 2]
    # map pixels a hair outside each edge of the tile
    probes = [
        (t.col - 0.01, t.row + 5),
        (t.col + t.width + 0.01, t.row + 5),
        (t.col + 5, t.row - 0.01),
        (t.col + 5, t.row + t.height + 0.01),
    ]
    for c, r in probes:
        lat, lon = naip.pixel_to_latlon(c, r)
        x, y = t.latlon_to_pixel(lat, lon)
        assert float(x) == pytest.approx(c - t.col, abs=1e-6) and float(y) == pytest.approx(r - t.row, abs=1e-6)
        assert not (0 <= x <= t.width and 0 <= y <= t.height)
    lat, lon = t.centre_latlon
    assert naip.latlon_to_pixel(lat, lon) == pytest.approx((t.col + t.width / 2, t.row + t.height / 2), abs=1e-6)


def test_tile_m_sets_the_base_in_metres(naip):
    g = TileGrid(naip, 1, 0, tile_m=1000)
    assert g.side == round(1000 / naip.resolution_m) == 200
    g2 = TileGrid(naip, 2, 0, tile_m=1000)
    assert g2.side == 100


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"zoom": 0}, "zoom"),
        ({"zoom": -1}, "zoom"),
        ({"zoom": float("nan")}, "zoom"),
        ({"overlap": -0.1}, "overlap"),
        ({"overlap": 1.0}, "overlap"),
        ({"overlap": 1.5}, "overlap"),
        ({"zoom": 0.25}, "larger than"),  # 1024 px tiles on a 934x723 map
        ({"tile_m": 0}, "tile-m"),
        ({"tile_m": 5000}, "larger than"),
    ],
)
def test_bad_grid_parameters(naip, kwargs, match):
    with pytest.raises(AerolocError, match=match):
        TileGrid(naip, **{"zoom": 1, "overlap": 0, **kwargs})


def test_tile_larger_than_seed_map(seed):
    _, m = seed
    TileGrid(m, 0.4, 0)  # 160 x 120 px tiles fit the 256 x 144 mosaic
    with pytest.raises(AerolocError, match=r"tiles of 213x160 px .* larger than the 256x144 map"):
        TileGrid(m, 0.3, 0)


# --- on-disk database --------------------------------------------------------------------------------------
def _read_csv(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _assert_database_matches_map(out, m, zoom, overlap):
    rows = _read_csv(out / "tiles.csv")
    for col in ["tile", "path", "tl_lat", "tl_lon", "br_lat", "br_lon", "width", "height", "crs", "a", "f"]:
        assert col in rows[0]
    g = TileGrid(m, zoom, overlap)
    assert len(rows) == len(g)
    for row, t in zip(rows, g):
        assert row["tile"] == t.id and not row["path"].startswith("/")
        img = np.asarray(Image.open(out / row["path"]).convert("RGB"))
        ref, _ = m.read(t.col, t.row, t.width, t.height)
        np.testing.assert_array_equal(img, ref)
        (tl_lat, tl_lon), (br_lat, br_lon) = t.corners_latlon
        assert [float(row[k]) for k in ("tl_lat", "tl_lon", "br_lat", "br_lon")] == pytest.approx(
            [tl_lat, tl_lon, br_lat, br_lon], abs=1e-9
        )
    loaded = load_tiles(out)
    for a, b in zip(loaded, g):
        assert (a.id, a.col, a.row, a.width, a.height, a.crs) == (b.id, b.col, b.row, b.width, b.height, b.crs)
        assert a.transform.almost_equals(b.transform, precision=1e-9)
    return rows


def test_write_tiles_renders_the_map_and_caches(tmp_path, seed):
    s, m = seed
    out = tmp_path / "db"
    report = write_tiles(s.path, out, zoom=1.5, overlap=0.5, progress=False, write_images=True)
    assert not report.cached and report.n_tiles == len(TileGrid(m, 1.5, 0.5))
    _assert_database_matches_map(out, m, 1.5, 0.5)
    grid = load_info(out)["grid"]
    assert (grid["width_px"], grid["height_px"], grid["step_x_px"], grid["step_y_px"]) == (43, 32, 22, 16)
    assert report.tile_px == (43, 32) and report.step_px == (22, 16)
    mtimes = {p: p.stat().st_mtime_ns for p in (out / "images").iterdir()}
    again = write_tiles(s.path, out, zoom=1.5, overlap=0.5, progress=False, write_images=True)
    assert again.cached is True and again == replace(report, cached=True)
    assert {p: p.stat().st_mtime_ns for p in (out / "images").iterdir()} == mtimes
    # another configuration in the same folder replaces the database instead of mixing them
    write_tiles(s.path, out, zoom=2, overlap=0, progress=False, write_images=True)
    _assert_database_matches_map(out, m, 2, 0)
    assert len(list((out / "images").iterdir())) == len(TileGrid(m, 2, 0))


def crash_image_writes_after(n: int, monkeypatch):
    """Make the n+1-th tile image write raise KeyboardInterrupt (an interrupted build); returns the real writer."""
    import aeroloc.core.images

    real_write, calls = aeroloc.core.images.write_image, []

    def crash(path, image, **kw):
        if len(calls) == n:
            raise KeyboardInterrupt
        calls.append(path)
        real_write(path, image, **kw)

    monkeypatch.setattr(aeroloc.core.images, "write_image", crash)
    return real_write


def test_interrupted_build_is_completed_not_trusted(tmp_path, seed, monkeypatch):
    import aeroloc.core.images

    s, m = seed
    out = tmp_path / "db"
    real_write = crash_image_writes_after(5, monkeypatch)
    with pytest.raises(KeyboardInterrupt):
        write_tiles(s.path, out, zoom=1, overlap=0.5, progress=False, write_images=True)
    monkeypatch.setattr(aeroloc.core.images, "write_image", real_write)
    assert not (out / "tiles.csv").exists()  # nothing looks complete
    assert len(list((out / "images").glob("*.png"))) == 5
    assert not list(out.rglob("*.part"))
    with pytest.raises(AerolocError, match=r"tiles\.csv"):
        load_tiles(out)
    kept = {p: p.stat().st_mtime_ns for p in (out / "images").glob("*.png")}
    report = write_tiles(s.path, out, zoom=1, overlap=0.5, progress=False, write_images=True)
    assert not report.cached
    _assert_database_matches_map(out, m, 1, 0.5)
    assert all(p.stat().st_mtime_ns == t for p, t in kept.items())  # resumed: finished tiles were kept


def test_interrupted_build_then_other_parameters(tmp_path, seed, monkeypatch):
    """Images left by an interrupted build of another configuration must not be reused as this one's."""
    import aeroloc.core.images

    s, m = seed
    out = tmp_path / "db"
    real_write = crash_image_writes_after(5, monkeypatch)
    with pytest.raises(KeyboardInterrupt):
        write_tiles(s.path, out, zoom=1, overlap=0, progress=False, write_images=True)
    monkeypatch.setattr(aeroloc.core.images, "write_image", real_write)
    write_tiles(s.path, out, zoom=1, overlap=0.5, progress=False, write_images=True)  # same tile size, other windows
    _assert_database_matches_map(out, m, 1, 0.5)
    write_tiles(s.path, out, zoom=2, overlap=0.5, progress=False, write_images=True)
    _assert_database_matches_map(out, m, 2, 0.5)


def test_write_tiles_on_naip(tmp_path, naip_map, naip):
    # zoom 2 -> 128 px tiles; overlap 0.25 -> step 96: 1 + ceil((934-128)/96) = 10 columns,
    # 1 + ceil((723-128)/96) = 8 rows, the last ones snapped to start at 934-128 = 806 and 723-128 = 595.
    out = tmp_path / "naip"
    report = write_tiles(naip_map, out, zoom=2, overlap=0.25, progress=False, write_images=True)
    assert report.n_tiles == 80 and (report.grid["n_cols"], report.grid["n_rows"]) == (10, 8)
    assert report.tile_px == (128, 128) and report.step_px == (96, 96)
    # tiles.json is the report (square grids keep the one-side keys)
    assert load_info(out) == report.to_json()
    assert list(report.to_json()) == ["map", "grid", "n_tiles", "format", "images", "build_s", "image_bytes"]
    assert (report.grid["side_px"], report.grid["step_px"], report.grid["base_px"]) == (128, 96, 256.0)
    rows = _assert_database_matches_map(out, naip, 2, 0.25)
    assert (int(rows[-1]["col"]), int(rows[-1]["row"])) == (806, 595)
    assert rows[0]["crs"] == "EPSG:26914"


# --- tiles as windows ----------------------------------------------------------------------------------------
def test_windows_database_has_the_same_tiles_csv_and_no_images(tmp_path, naip_map):
    from aeroloc.maps.tilesource import TileSource

    png, win = tmp_path / "png", tmp_path / "win"
    write_tiles(naip_map, png, zoom=2, overlap=0.5, progress=False, write_images=True)
    report = write_tiles(naip_map, win, zoom=2, overlap=0.5, progress=False)
    assert (win / "tiles.csv").read_bytes() == (png / "tiles.csv").read_bytes()  # same columns, same values
    assert not (win / "images").exists() and report.images is False and report.image_bytes == 0
    ref = load_info(win)["map"]
    assert {"path", "width", "height", "crs", "transform", "content_xxh3"} <= set(ref)
    a, b = TileSource(png), TileSource(win)
    assert a.has_images and not b.has_images
    n = len(load_tiles(win))
    for x, y in zip(a.images(0, n), b.images(0, n)):  # PNG round trip is lossless: equal pixels
        np.testing.assert_array_equal(x, y)
    assert write_tiles(naip_map, win, zoom=2, overlap=0.5, progress=False).cached


@pytest.mark.parametrize("zoom,overlap", [(1.5, 0.5), (3, 0.75), (2, 0)])
def test_band_reads_cut_the_same_pixels_as_window_reads(seed, zoom, overlap):
    from aeroloc.maps.windows import read_windows

    _, m = seed
    tiles = list(TileGrid(m, zoom, overlap))
    for s0, s1 in [(0, len(tiles)), (3, 11), (5, 6)]:  # whole grid, a run across rows, one tile
        for t, got in zip(tiles[s0:s1], read_windows(m, tiles[s0:s1]), strict=True):
            ref, _ = m.read(t.col, t.row, t.width, t.height)
            np.testing.assert_array_equal(got, ref)


def test_a_changed_map_is_refused(tmp_path, naip_map):
    import shutil

    import rasterio

    from aeroloc.maps.tilesource import TileSource

    m = tmp_path / "map.tif"
    shutil.copy(naip_map, m)
    write_tiles(m, tmp_path / "db", zoom=2, overlap=0, progress=False)
    TileSource(tmp_path / "db").image(0)
    with rasterio.open(m, "r+") as ds:  # same size, CRS and transform; other pixels
        ds.write(255 - ds.read())
    with pytest.raises(AerolocError, match="pixels changed since the tile grid was made"):
        TileSource(tmp_path / "db").image(0)
    shutil.copy(tmp_path / "db" / "tiles.json", tmp_path / "tiles.json")
    info = load_info(tmp_path / "db")
    info["map"]["width"] = 1000
    (tmp_path / "db" / "tiles.json").write_text(__import__("json").dumps(info))
    with pytest.raises(AerolocError, match=r"changed since the tile grid was made \(width 1000 -> 934\)"):
        TileSource(tmp_path / "db").image(0)


@pytest.mark.parametrize("which", ["naip", "seed"])
def test_tiles_csv_written_from_lists_has_the_bytes_of_the_dict_writer(which, naip, seed, tmp_path):
    """tiles.csv is written from plain row lists (no per-tile dict, for 10^7-tile grids): the file has the
    bytes the per-tile ``tile_row`` dicts give through csv.DictWriter, on a GeoTIFF and on a tile folder."""
    m = naip if which == "naip" else seed[1]
    write_tiles(m, tmp_path / "db", 2.5, 0.5, progress=False)
    rows = [tiling.tile_row(t) for t in TileGrid(m, 2.5, 0.5)]
    with open(tmp_path / "want.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=tiling.CSV_COLUMNS)
        w.writeheader()
        w.writerows(rows)
    assert len(rows) > 20
    assert (tmp_path / "db" / tiling.TILES_CSV).read_bytes() == (tmp_path / "want.csv").read_bytes()


def test_tiles_csv_of_a_rotated_map_in_blocks_has_the_bytes_of_the_dict_writer(tmp_path, naip_map):
    """A map whose transform turns (b, d != 0: no offset repeats along a grid row or column) and a grid
    written a few rows at a time give the bytes of the per-tile dicts through csv.DictWriter."""
    import rasterio
    from affine import Affine

    with rasterio.open(naip_map) as src:
        data, crs, t = src.read(window=((0, 300), (0, 400))), src.crs, src.transform
    cos, sin = math.cos(0.3), math.sin(0.3)
    turned = Affine(t.a * cos, t.a * sin, t.c, t.a * sin, -t.a * cos, t.f)
    path = tmp_path / "turned.tif"
    profile = {"driver": "GTiff", "width": 400, "height": 300, "count": 3, "dtype": "uint8"}
    with rasterio.open(path, "w", crs=crs, transform=turned, **profile) as dst:
        dst.write(data)
    m = open_map(path)
    grid = TileGrid(m, 4, 0.5)
    assert len(grid.rows) > 3 and len(grid.cols) > 3
    for per_block in (len(grid.cols), 3 * len(grid.cols) + 1, 10**6):  # one grid row, 3 rows, all at once
        got = "".join(grid.csv_chunks(tiles_per_chunk=per_block))
        rows = [tiling.tile_row(t) for t in grid]
        with open(tmp_path / "want.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=tiling.CSV_COLUMNS)
            w.writeheader()
            w.writerows(rows)
        assert got.encode() == (tmp_path / "want.csv").read_bytes()
    by_row = {}
    for r in rows:
        by_row.setdefault(r["row"], set()).add(r["c"])
    assert all(len(v) > 1 for v in by_row.values()) and len({r["c"] for r in rows if r["col"] == 0}) > 1


@pytest.fixture
def hash_cache(tmp_path, monkeypatch):
    """A private hash cache, and no settling age, so a test need not wait 2 s for a file to be cacheable."""
    from aeroloc.maps import windows

    monkeypatch.setenv("AEROLOC_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(windows, "HASH_CACHE_MIN_AGE_S", 0.0)
    return windows


def test_a_map_hashed_before_is_not_read_again_until_it_changes(tmp_path, naip_map, hash_cache, monkeypatch):
    """The content hash of an unchanged map is reused (no pixels read); rewriting the file in place with the
    same size, CRS and transform and then restoring its mtime is still refused: the cache key holds the ctime,
    which writing sets and no call sets back."""
    import os
    import time

    import rasterio

    from aeroloc.maps.sources import GeoTiffMap
    from aeroloc.maps.tilesource import TileSource

    m = tmp_path / "map.tif"
    with rasterio.open(naip_map) as src:  # uncompressed: a rewrite of the pixels keeps the file's size
        profile = {**src.profile, "compress": None, "tiled": False}
        with rasterio.open(m, "w", **profile) as dst:
            dst.write(src.read())
    with monkeypatch.context() as mp:  # changed within the settling age before the read: not cached
        mp.setattr(hash_cache, "HASH_CACHE_MIN_AGE_S", 3600.0)
        fresh = hash_cache.content_hash(open_map(m), TileGrid(open_map(m), 2, 0))
    assert not hash_cache.hash_cache_dir().exists()
    write_tiles(m, tmp_path / "db", zoom=2, overlap=0, progress=False)
    assert load_info(tmp_path / "db")["map"]["content_xxh3"] == fresh
    assert len(list(hash_cache.hash_cache_dir().iterdir())) == 1

    def no_read(*a, **k):
        raise AssertionError("the map was read again")

    with monkeypatch.context() as mp:
        mp.setattr(GeoTiffMap, "_read", no_read)
        assert hash_cache.content_hash(open_map(m), TileGrid(open_map(m), 2, 0)) == fresh
    TileSource(tmp_path / "db").image(0)
    st = os.stat(m)
    time.sleep(0.05)  # a later timestamp tick for the rewrite
    with rasterio.open(m, "r+") as ds:
        ds.write(255 - ds.read())
    os.utime(m, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert (os.stat(m).st_size, os.stat(m).st_mtime_ns) == (st.st_size, st.st_mtime_ns)
    with pytest.raises(AerolocError, match="pixels changed since the tile grid was made"):
        TileSource(tmp_path / "db").image(0)


def test_a_changed_raw_tile_of_a_folder_map_is_refused_after_caching(tmp_path, naip_map, hash_cache):
    """A tile-folder map: its hash is cached after the first grid; overwriting one raw tile file (same size)
    changes its ctime, so the next open hashes again and refuses."""
    import os
    import time

    from aeroloc.maps.tilesource import TileSource

    s = build_seed_folder(tmp_path / "seed", naip_map)
    write_tiles(s.path, tmp_path / "db", zoom=2, overlap=0, progress=False)
    write_tiles(s.path, tmp_path / "db2", zoom=3, overlap=0, progress=False)
    assert len(list(hash_cache.hash_cache_dir().iterdir())) == 1  # one map, one entry for both grids
    TileSource(tmp_path / "db").image(0)
    raw = sorted(s.path.glob("tile_*.png"))[0]
    data = bytearray(raw.read_bytes())
    data[-20] ^= 0xFF  # inside the last chunk's CRC: same size, other bytes
    st = os.stat(raw)
    time.sleep(0.05)  # a later timestamp tick for the rewrite
    raw.write_bytes(bytes(data))
    os.utime(raw, ns=(st.st_atime_ns, st.st_mtime_ns))
    with pytest.raises(AerolocError, match="pixels changed since the tile grid was made"):
        TileSource(tmp_path / "db").image(0)


def test_the_hash_cache_lives_beside_the_weights_cache(monkeypatch, tmp_path):
    """$AEROLOC_CACHE, else $XDG_CACHE_HOME/aeroloc: the same root as the weights cache."""
    from aeroloc.core.weights import cache_dir
    from aeroloc.maps.windows import hash_cache_dir

    for env in ({"AEROLOC_CACHE": str(tmp_path / "a")}, {"XDG_CACHE_HOME": str(tmp_path / "x")}):
        monkeypatch.delenv("AEROLOC_CACHE", raising=False)
        monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
        for k, v in env.items():
            monkeypatch.setenv(k, v)
        assert hash_cache_dir() == cache_dir().parent / "map-hashes"


def test_a_grid_made_before_xxh3_is_still_checked_with_its_sha1(tmp_path, naip_map, hash_cache):
    """tiles.json of grids made before 2026-12-05 records SHA-1 (``content_sha1``): such a database still opens
    when its map is unchanged, and is refused when the recorded pixels are not the map's."""
    import json

    from aeroloc.maps.tilesource import TileSource

    db = tmp_path / "db"
    write_tiles(naip_map, db, zoom=2, overlap=0, progress=False)
    meta = json.loads((db / "tiles.json").read_text())
    m, grid = open_map(naip_map), TileGrid(open_map(naip_map), 2, 0)
    sha1 = hash_cache.content_hash(m, grid, "sha1")
    assert len(sha1) == 40 and sha1 != meta["map"].pop("content_xxh3")
    for recorded, ok in ((sha1, True), ("0" * 40, False)):
        meta["map"]["content_sha1"] = recorded
        (db / "tiles.json").write_text(json.dumps(meta))
        if ok:
            assert TileSource(db).image(0).shape[2] == 3
        else:
            with pytest.raises(AerolocError, match="pixels changed since the tile grid was made"):
                TileSource(db).image(0)
