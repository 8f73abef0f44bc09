"""Rectangular raw tiles (the seed's 1280x1230 px, width x height): tiles are (raw width / zoom) x
(raw height / zoom) with a step of (1 - overlap) of each side, as aero-vloc cuts them. Zoom 1 without overlap
is exactly the raw tiles (same pixels, corners = map_metadata.txt's); every zoom x overlap covers the map, the
last row/column snapped to its edge; every tile's corners agree with pixel -> lat/lon.

The seed-format folders are real NAIP pixels enlarged 5x (bilinear) to 1280x1230 tiles, on made-up Web Mercator
corners; the expected coordinates come from the Mercator formulas in tests/_mapfolders.py, not aeroloc.core.geo.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math

import numpy as np
import pytest
from PIL import Image

from _mapfolders import build_seed_folder
from aeroloc.core.errors import AerolocError
from aeroloc.maps.sources import open_map
from aeroloc.maps.tiling import TileGrid, TilesReport, load_info, load_tiles, write_tiles

RAW_W, RAW_H = 1280, 1230
RES_M = 1.4663  # Web Mercator m/px of 1 m ground pixels at 47 N (NAIP's 5 m enlarged 5x)
ZOOMS = [0.5, 1, 1.5, 2, 2.5, 3]
OVERLAPS = [0, 0.25, 0.5, 0.75]


def _seed(tmp_path_factory, naip_map, name, n_rows, n_cols):
    folder = tmp_path_factory.mktemp(name) / "seed"
    s = build_seed_folder(folder, naip_map, n_rows, n_cols, RAW_W, RAW_H, res_m=RES_M, upsample=5)
    return s, open_map(s.path)


@pytest.fixture(scope="module")
def seed_2x1(tmp_path_factory, naip_map):
    """Two raw tiles side by side: a 2560 x 1230 map (the case that failed with square tiles)."""
    return _seed(tmp_path_factory, naip_map, "seed2x1", 1, 2)


@pytest.fixture(scope="module")
def seed_3x2(tmp_path_factory, naip_map):
    """Three columns by two rows of raw tiles: 3840 x 2460, big enough for zoom 0.5 (2560 x 2460 tiles)."""
    return _seed(tmp_path_factory, naip_map, "seed3x2", 2, 3)


def _tiles_cli(*args) -> str:
    from aeroloc.cli import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        assert main(["tiles", *map(str, args)]) == 0
    return out.getvalue()


def _read_csv(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _assert_raw_tiles(s, db):
    """``db`` holds exactly the raw tiles: one per raw tile, same pixels, corners = map_metadata's."""
    rows = _read_csv(db / "tiles.csv")
    assert len(rows) == s.n_rows * s.n_cols
    from aeroloc.retrieval.database import Database

    database = Database(db)  # the pixels the pipeline reads: windows of the map (no PNGs by default)
    for i, row in enumerate(rows):
        r, c = divmod(i, s.n_cols)
        assert (int(row["width"]), int(row["height"])) == (RAW_W, RAW_H)
        assert (int(row["col"]), int(row["row"])) == (c * RAW_W, r * RAW_H)
        got = database.tile_image(row["tile"])
        raw = np.asarray(Image.open(s.path / f"tile_{r}_{c}.png").convert("RGB"))
        np.testing.assert_array_equal(got, raw)
        # tiles.csv has 9 decimals: each corner is the metadata's, to that precision
        written = [float(row[k]) for k in ("tl_lat", "tl_lon", "br_lat", "br_lon")]
        assert written == pytest.approx(s.corners[(r, c)], abs=5.1e-10)
    for t in load_tiles(db):
        r, c = t.row // RAW_H, t.col // RAW_W
        (tl_lat, tl_lon), (br_lat, br_lon) = t.corners_latlon
        assert [tl_lat, tl_lon, br_lat, br_lon] == pytest.approx(s.corners[(r, c)], abs=1e-11)
    return rows


def test_zoom1_is_the_raw_tiles_on_a_2x1_map(tmp_path, seed_2x1):
    s, m = seed_2x1
    assert (m.width, m.height) == (2 * RAW_W, RAW_H) and m.base_tile_size == (RAW_W, RAW_H)
    db = tmp_path / "db"
    out = _tiles_cli(s.path, "--zoom", "1", "--overlap", "0", "--out", db)
    assert "2 tiles (1 rows x 2 cols) of 1280x1230 px" in out and "step 1280x1230 px" in out, out
    _assert_raw_tiles(s, db)
    grid = load_info(db)["grid"]
    assert (grid["width_px"], grid["height_px"], grid["step_x_px"], grid["step_y_px"]) == (1280, 1230, 1280, 1230)
    assert grid["base_px"] == [1280.0, 1230.0] and "side_px" not in grid


def test_zoom1_is_the_raw_tiles_on_a_3x2_map(seed_3x2):
    s, m = seed_3x2
    g = TileGrid(m, 1, 0)
    assert (g.cols, g.rows) == ([0, 1280, 2560], [0, 1230])
    for t in g:
        r, c = t.row // RAW_H, t.col // RAW_W
        assert (t.col, t.row, t.width, t.height) == (c * RAW_W, r * RAW_H, RAW_W, RAW_H)
        (tl_lat, tl_lon), (br_lat, br_lon) = t.corners_latlon
        assert [tl_lat, tl_lon, br_lat, br_lon] == pytest.approx(s.corners[(r, c)], abs=1e-11)
        rgb, _ = m.read(t.col, t.row, t.width, t.height)
        np.testing.assert_array_equal(rgb, np.asarray(Image.open(s.path / f"tile_{r}_{c}.png").convert("RGB")))


def _check_axis(starts, length, side, step):
    assert starts[0] == 0 and starts[-1] + side == length  # snapped to the edge, never past it
    diffs = np.diff(starts)
    assert (diffs[:-1] == step).all()
    if len(diffs):
        assert 0 < diffs[-1] <= step  # the snapped last one is the only shorter step
    assert len(starts) == 1 + math.ceil((length - side) / step)


@pytest.mark.parametrize("zoom", ZOOMS)
@pytest.mark.parametrize("overlap", OVERLAPS)
def test_every_zoom_and_overlap_covers_the_map(seed_3x2, zoom, overlap):
    s, m = seed_3x2
    g = TileGrid(m, zoom, overlap)
    w, h = round(RAW_W / zoom), round(RAW_H / zoom)
    sx, sy = round(w * (1 - overlap)), round(h * (1 - overlap))
    assert (g.tile_w, g.tile_h, g.step_x, g.step_y) == (w, h, sx, sy)
    _check_axis(g.cols, m.width, w, sx)
    _check_axis(g.rows, m.height, h, sy)
    tiles = list(g)
    assert len(tiles) == len(g) == len(g.cols) * len(g.rows)
    covered = np.zeros((m.height, m.width), bool)
    for t in tiles:
        assert (t.width, t.height) == (w, h)
        assert t.col >= 0 and t.row >= 0 and t.col + w <= m.width and t.row + h <= m.height
        covered[t.row : t.row + h, t.col : t.col + w] = True
    assert covered.all()
    # every tile's corners are its outer pixel edges, by the Mercator formulas the metadata came from
    for t in tiles:
        (tl_lat, tl_lon), (br_lat, br_lon) = t.corners_latlon
        assert (tl_lat, tl_lon) == pytest.approx(s.pixel_to_latlon(t.col, t.row), abs=1e-11)
        assert (br_lat, br_lon) == pytest.approx(s.pixel_to_latlon(t.col + w, t.row + h), abs=1e-11)
    # the first and last tiles start and end at the map corners; pixels inside a tile are the map's
    assert tiles[0].corners_latlon[0] == pytest.approx(s.corners[(0, 0)][:2], abs=1e-11)
    assert tiles[-1].corners_latlon[1] == pytest.approx(s.corners[(s.n_rows - 1, s.n_cols - 1)][2:], abs=1e-11)
    for t in (tiles[0], tiles[len(tiles) // 2], tiles[-1]):
        rgb, valid = m.read(t.col, t.row, t.width, t.height)
        assert valid.all()
        np.testing.assert_array_equal(rgb, s.image[t.row : t.row + h, t.col : t.col + w])


def test_tile_pixels_to_latlon_inside_a_tile(seed_3x2):
    s, m = seed_3x2
    t = list(TileGrid(m, 1.5, 0.5))[7]
    xs, ys = np.array([0, 10.5, t.width, 400.25]), np.array([0, 3.0, t.height, 700.75])
    lat, lon = t.pixel_to_latlon(xs, ys)
    for x, y, a, b in zip(xs, ys, lat, lon):
        assert (a, b) == pytest.approx(s.pixel_to_latlon(t.col + x, t.row + y), abs=1e-11)
    back = t.latlon_to_pixel(lat, lon)
    np.testing.assert_allclose(np.stack(back), np.stack([xs, ys]), atol=1e-5)


def test_rectangular_database_on_disk(tmp_path, seed_2x1):
    s, _ = seed_2x1
    db = tmp_path / "db"
    report = write_tiles(s.path, db, zoom=1.5, overlap=0.25, progress=False)
    assert isinstance(report, TilesReport) and not report.cached
    assert report.tile_px == (853, 820) and report.step_px == (640, 615)
    assert (report.grid["n_cols"], report.grid["n_rows"]) == (4, 2) and report.n_tiles == 8
    assert json.loads((db / "tiles.json").read_text()) == report.to_json()
    rows = _read_csv(db / "tiles.csv")
    assert [(int(r["col"]), int(r["row"])) for r in rows][-2:] == [(1280, 410), (2560 - 853, 1230 - 820)]
    from aeroloc.retrieval.database import Database

    database = Database(db)
    for row, t in zip(rows, load_tiles(db)):
        img = database.tile_image(row["tile"])
        assert img.shape == (820, 853, 3)
        np.testing.assert_array_equal(img, s.image[t.row : t.row + 820, t.col : t.col + 853])
        tl, br = s.pixel_to_latlon(t.col, t.row), s.pixel_to_latlon(t.col + 853, t.row + 820)
        corners = [float(row[k]) for k in ("tl_lat", "tl_lon", "br_lat", "br_lon")]
        assert corners == pytest.approx([*tl, *br], abs=5.1e-10)
    again = write_tiles(s.path, db, zoom=1.5, overlap=0.25, progress=False)
    assert again.cached and again.grid == report.grid and again.image_bytes == report.image_bytes


def test_rectangular_grid_has_no_single_side(seed_2x1):
    _, m = seed_2x1
    g = TileGrid(m, 2, 0.5)
    assert (g.tile_w, g.tile_h, g.step_x, g.step_y) == (640, 615, 320, 308)
    with pytest.raises(AerolocError, match="not square"):
        g.side  # noqa: B018
    with pytest.raises(AerolocError, match=r"tiles of 2560x2460 px .* larger than the 2560x1230 map"):
        TileGrid(m, 0.5, 0)  # twice the raw height does not fit one row of raw tiles
