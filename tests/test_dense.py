"""The dense structural stage (aeroloc.matching.dense, aeroloc.localization.dense_stage) on real NAIP data: cross-season queries that local
features cannot match are placed within metres, a crop of the map is found to a fraction of a pixel, and what is
not on the map (or turned beyond the searched headings) gets no trusted answer."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from aeroloc.core import geo
from aeroloc.core.errors import AerolocError
from aeroloc.core.images import read_image
from aeroloc.core.queries import load_queries
from aeroloc.localization.dense_stage import DenseMapLocator, check_query_gsd
from aeroloc.maps.sources import open_map
from aeroloc.matching.dense import DEFAULTS, DenseRegion, orientation_features

# XFeat + LighterGlue found 4 and 5 verified matches on their true tiles (the lake of 2009 and the field of 2015
# look nothing like 2020's); the dense search measured 4.2 m and 3.4 m, scores 0.45 and 0.39, ratios 2.3 and 1.9.
HOPELESS_FOR_LOCAL = ["naip_20090818_n_013.jpg", "naip_20150926_n_000.jpg"]
NAIP_GSD = 5.0  # the dev queries are cut at the map's resolution (data README: 700-1400 m over 140-280 px)


@pytest.fixture(scope="module")
def naip(naip_map):
    return open_map(naip_map)


@pytest.fixture(scope="module")
def locator(naip):
    return DenseMapLocator(naip, NAIP_GSD)


@pytest.fixture(scope="module")
def queries(naip_dev):
    return {q.name: q for q in load_queries(naip_dev)}


def _heading_gap(a: float, b: float) -> float:
    """Degrees between two angles; NAIP's heading_deg measures the turn of the content that the match reports."""
    return abs((a - b + 180) % 360 - 180)


def test_features_ignore_contrast_polarity_and_are_unit_vectors(naip):
    """A shoreline is a shoreline whether the water is darker or lighter than the land: the negative of an image
    has the same features. Textured pixels carry unit-norm vectors, so bright and dull years weigh the same."""
    rgb, _ = naip.read(300, 200, 160, 120)
    f = orientation_features(rgb)
    assert f.shape == (120, 160, DEFAULTS["bins"]) and f.dtype == np.float32
    neg = orientation_features(255 - rgb)  # equal up to the grey conversion rounding to whole levels
    assert np.abs(neg - f).max() < 0.02 and np.median(np.abs(neg - f)) < 1e-3
    norms = np.linalg.norm(f, axis=-1)
    assert np.median(norms) > 0.95 and norms.max() < 1.0 + 1e-5
    dull = (rgb.astype(np.float32) * 0.3 + 40).astype(np.uint8)
    assert np.median(np.abs(orientation_features(dull) - f)) < 0.05


def _stacked_cfog(rgb: np.ndarray, conf: dict = DEFAULTS) -> np.ndarray:
    """CFOG as first written: the bins stacked H x W x bins, rolled and reduced along their axis."""
    g = cv2.GaussianBlur(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32), (0, 0), conf["grad_sigma"])
    gx, gy = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    n = conf["bins"]
    f = np.stack(
        [
            cv2.GaussianBlur(np.abs(np.cos(np.pi * k / n) * gx + np.sin(np.pi * k / n) * gy), (0, 0), conf["sigma"])
            for k in range(n)
        ],
        -1,
    )
    f = (np.roll(f, 1, -1) + 2 * f + np.roll(f, -1, -1)) / 4
    norm = np.linalg.norm(f, axis=-1, keepdims=True)
    f /= norm + 1e-3 * float(norm.mean()) + 1e-12
    return np.ascontiguousarray(f, dtype=np.float32)


def test_features_computed_bin_by_bin_are_the_same_bits_as_the_stacked_formula(naip, data_dir):
    """The bin-by-bin computation (faster) changes no bit: map windows with no-data, a photo, a tiny crop."""
    photo = read_image(data_dir / "multi-region" / "levir-tx" / "any" / "queries" / "levir_any_0_00.jpg")
    images = [naip.read(0, 0, 400, 300)[0], naip.read(500, 400, 300, 250)[0], photo, photo[:37, :53]]
    images.append(np.where(np.arange(photo.shape[1])[None, :, None] < 100, 0, photo).astype(np.uint8))
    for rgb in images:
        assert np.array_equal(orientation_features(rgb), _stacked_cfog(rgb)), rgb.shape


@pytest.mark.parametrize("angle", [0.0, 10.0])
def test_a_crop_of_the_map_is_found_to_a_pixel_and_its_heading_to_a_few_degrees(naip, angle):
    whole, valid = naip.read(0, 0, naip.width, naip.height)
    region = DenseRegion(whole, valid)
    cx, cy, side = 512.0, 371.0, 170  # the crop's centre (pixel edges) and size
    crop = whole[int(cy - side / 2) : int(cy + side / 2), int(cx - side / 2) : int(cx + side / 2)]
    if angle:  # the ground turned 10° clockwise, as in a NAIP query of heading_deg 10
        big = whole[int(cy - side) : int(cy + side), int(cx - side) : int(cx + side)]
        R = cv2.getRotationMatrix2D((side - 0.5, side - 0.5), -angle, 1.0)
        crop = cv2.warpAffine(big, R, (2 * side, 2 * side))[side // 2 : side // 2 + side, side // 2 : side // 2 + side]
    m = region.locate(crop)
    assert m is not None and m.trusted(region.conf)
    assert np.hypot(m.x - cx, m.y - cy) < (0.5 if not angle else 1.5), (m.x, m.y)
    assert abs(m.angle - angle) <= 3.75
    assert m.ratio > 2
    # the footprint drawn for --save-matches: the crop's corners on the map, in map pixels
    from aeroloc.localization.dense_stage import DenseResult

    corners = DenseResult(m, m.x, m.y, 0.0, 0.0).footprint((side, side), 1.0, 1.0)
    edge = np.array([[0, 0], [side, 0], [side, side], [0, side]], np.float64)
    if angle:  # the crop's corners taken back through the warp that made it
        inv = cv2.invertAffineTransform(R)
        edge = (edge + side // 2) @ inv[:, :2].T + inv[:, 2] + [cx - side, cy - side]
    else:
        edge = edge + [cx - side / 2, cy - side / 2]
    # exact but for the heading's quantisation (steps of 3.75°), which moves the corners by radius x angle
    tol = 1.0 + side / np.sqrt(2) * abs(np.radians(m.angle - angle))
    assert np.abs(corners - edge).max() < tol, (corners, edge)


@pytest.mark.slow
@pytest.mark.parametrize("name", HOPELESS_FOR_LOCAL)
def test_cross_season_queries_local_features_cannot_match_are_placed_within_metres(locator, queries, name):
    q = queries[name]
    d = locator.locate(read_image(q.path), [])
    assert d is not None, f"{name}: no trusted dense match"
    err = geo.geodesic_distance(q.lat, q.lon, d.lat, d.lon)
    assert err < 10.0, f"{name}: {err:.1f} m from the truth"
    assert _heading_gap(d.match.angle, q.heading_deg) < 5.0, (d.match.angle, q.heading_deg)
    assert d.status().startswith("localized (dense")


@pytest.mark.slow
def test_no_trusted_answer_when_the_true_place_is_masked_turned_or_elsewhere(naip, locator, queries, data_dir):
    """Three ways of not being on the searched map: the query's own area is no-data, the query is turned 90°
    (beyond the ±15° searched), or it is a drone photo of another city."""
    q = queries[HOPELESS_FOR_LOCAL[0]]
    image = read_image(q.path)
    whole, valid = naip.read(0, 0, naip.width, naip.height)
    col, row = naip.latlon_to_pixel(q.lat, q.lon)
    yy, xx = np.ogrid[: naip.height, : naip.width]
    masked = valid & ((yy - row) ** 2 + (xx - col) ** 2 >= (image.shape[0] / 2) ** 2)
    m = DenseRegion(whole, masked).locate(image)
    assert m is not None and not m.trusted(DEFAULTS), (m.score, m.ratio)
    assert locator.locate(np.ascontiguousarray(np.rot90(image)), []) is None
    toledo = read_image(data_dir / "toledo" / "photos" / "1JI_0064.JPG")
    elsewhere = DenseMapLocator(naip, 2.5)  # its 1200x900 px as if at 2.5 m/px: 600x450 px on the 5 m map
    assert elsewhere.locate(toledo, []) is None


def test_headings_searched_follow_what_is_known_of_the_heading():
    from aeroloc.matching.dense import ANY_HEADING, heading_angles

    assert heading_angles(None, True)["angles"] == DEFAULTS["angles"]
    assert heading_angles(None, False)["angles"] == ANY_HEADING
    assert len(ANY_HEADING) == 48 and ANY_HEADING[0] == -180.0 and np.allclose(np.diff(ANY_HEADING), 7.5)
    assert heading_angles({"angles": (0.0,)}, False)["angles"] == (0.0,)  # chosen headings are kept
    assert heading_angles({"min_ratio": 2.0}, True)["min_ratio"] == 2.0


@pytest.mark.slow
def test_a_query_at_an_unknown_heading_is_found_by_the_full_circle(naip, queries, naip_dev):
    """A dev-rotated query turned far from north (beyond the ±15° of a north-up search) is placed by the search
    over every heading, with its heading."""
    from aeroloc.matching.dense import heading_angles

    rotated = {q.name: q for q in load_queries(naip_dev.parent.parent / "dev-rotated" / "queries.csv")}
    q = rotated["naip_20090818_r_004.jpg"]  # heading 246°; a 2009 image (measured: 4.6 m, ratio 3.2)
    image = read_image(q.path)
    assert DenseMapLocator(naip, NAIP_GSD).locate(image, []) is None  # north-up search: nothing distinct
    d = DenseMapLocator(naip, NAIP_GSD, heading_angles(None, north_up=False)).locate(image, [])
    assert d is not None, f"{q.name} (heading {q.heading_deg}°): no trusted match"
    assert geo.geodesic_distance(q.lat, q.lon, d.lat, d.lon) < 15.0
    assert _heading_gap(d.match.angle, q.heading_deg) < 6.0, (d.match.angle, q.heading_deg)


def test_query_resolution_must_be_a_positive_number():
    assert check_query_gsd(None) is None and check_query_gsd("2.5") == 2.5
    for bad in (0, -1, "abc", float("nan"), float("inf")):
        with pytest.raises(AerolocError, match="metres per pixel"):
            check_query_gsd(bad)


def test_working_resolution_is_the_coarser_of_query_and_map(naip):
    fine_query = DenseMapLocator(naip, 0.5)  # a drone photo at 0.5 m/px on the 5 m map: the query is shrunk
    assert fine_query.map_factor == pytest.approx(1.0) and fine_query.query_factor == pytest.approx(0.1, rel=1e-3)
    coarse_query = DenseMapLocator(naip, 10.0)  # a 10 m/px query: the map is shrunk instead
    assert coarse_query.map_factor == pytest.approx(0.5, rel=1e-3) and coarse_query.query_factor == 1.0


def test_a_large_map_is_searched_over_the_best_tiles_that_fit(naip):
    """When the whole map exceeds the pixel budget, the region is the bounding box of the best-ranked tiles that
    fits it, and the position still comes back in map pixels."""
    from aeroloc.maps.tiling import TileGrid

    tiles = list(TileGrid(naip, 1.0, 0.5))
    a, b = tiles[5], tiles[6]  # neighbours along a row, half overlapping
    box = (
        min(a.col, b.col),
        min(a.row, b.row),
        max(a.col + a.width, b.col + b.width),
        max(a.row + a.height, b.row + b.height),
    )
    one = DenseMapLocator(naip, NAIP_GSD, max_region_px=a.width * a.height)  # room for one tile only
    region, col0, row0 = one.region([a, b])
    assert (col0, row0) == (a.col, a.row) and region.shape == (a.height, a.width)
    two = DenseMapLocator(naip, NAIP_GSD, max_region_px=(box[2] - box[0]) * (box[3] - box[1]))
    region, col0, row0 = two.region([a, b])
    assert (col0, row0) == box[:2] and region.shape == (box[3] - box[1], box[2] - box[0])
    assert one.region([]) is None


@pytest.mark.slow
def test_the_localizer_tries_the_dense_stage_first_and_falls_back_to_local_features(
    naip_db, queries, data_dir, tmp_path
):
    """With the queries' resolution given, a query that local features miss is localized by the dense stage (its
    re-ranked tiles start with one that contains it), and a photo from elsewhere still ends "not localized" after
    the local-feature fallback."""
    from aeroloc.bench.metrics import tile_contains
    from aeroloc.localization.localizer import Localizer
    from aeroloc.localization.options import LocalizeOptions
    from aeroloc.localization.run import localize_queries
    from aeroloc.retrieval.database import Database

    def options(**kw):  # north-up: the re-ranker at the upright heading, the dense stage within ±15°
        return LocalizeOptions(top_n=5, method="xfeat-vlad", rerank="xfeat-lighterglue", north_up=True, **kw)

    db = Database(naip_db)
    loc = Localizer(db, options(query_gsd=NAIP_GSD), "cpu")
    q = queries[HOPELESS_FOR_LOCAL[0]]
    res = loc(q.name, read_image(q.path), top_n=5)
    assert res.status.startswith("localized (dense"), res.status
    assert geo.geodesic_distance(q.lat, q.lon, res.lat, res.lon) < 10.0
    assert tile_contains(db.by_id[res.top_tiles[0]], q.lat, q.lon) and len(res.top_tiles) == 1
    assert res.times_ms["align"] > 0 and res.times_ms.get("local_features", 0) == 0
    # a finished run without the resolution is not reused for one with it (the resolution is in the run's key)
    out = tmp_path / "r.csv"
    assert localize_queries(db, [q], out, options(), "cpu", progress=False)[0].status.startswith("not localized")
    shots = tmp_path / "matches"
    row = localize_queries(db, [q], out, options(query_gsd=NAIP_GSD), "cpu", save_matches=shots, progress=False)[0]
    assert row.status.startswith("localized (dense")
    shot = read_image(shots / (q.name.rsplit(".", 1)[0] + ".jpg"))  # query | map with the footprint outlined
    assert shot.shape[0] == 480 and shot.shape[1] > 700
    toledo = Localizer(db, options(query_gsd=2.5), "cpu")
    res = toledo("toledo", read_image(data_dir / "toledo" / "photos" / "1JI_0064.JPG"), top_n=5)
    assert res.status.startswith("not localized") and np.isnan(res.lat), res.status


def test_the_cli_refuses_a_bad_query_resolution_before_any_work(naip_dev, tmp_path):
    import subprocess
    import sys

    out = tmp_path / "r.csv"
    p = subprocess.run(
        [
            sys.executable,
            "-m",
            "aeroloc.cli",
            "localize",
            str(tmp_path),
            str(naip_dev),
            "--query-gsd",
            "-5",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert p.returncode == 2 and "Traceback" not in p.stderr + p.stdout
    assert "metres per pixel" in p.stderr and "-5" in p.stderr
    assert not out.exists()


@pytest.mark.slow
def test_a_benchmark_configuration_with_a_query_resolution_runs_the_dense_stage(
    naip_map, naip_dev, tmp_path, monkeypatch
):
    """aeroloc.bench.pipeline end to end on 6 NAIP queries (query_gsd set): every one placed by the dense stage within
    15 m, and the total time and peak memory are the localizing run's, also when its results file is reused."""
    import types

    from aeroloc.bench.pipeline import run_config

    cfg = types.SimpleNamespace(
        map_path=str(naip_map),
        tile_m=None,
        queries_path=str(naip_dev),
        method="xfeat-vlad",
        reranker="xfeat-lighterglue",
        zoom=2.0,
        overlap=0.0,
        top_n=3,
        top_k=1,
        thresholds_m=(10, 25),
        device="cpu",
        max_queries=6,
        north_up=True,
        query_gsd=NAIP_GSD,
    )
    first = run_config(cfg, tmp_path)
    assert all(r["status"].startswith("localized (dense") for r in first["rows"]), [r["status"] for r in first["rows"]]
    assert max(r["error_m"] for r in first["rows"]) < 15.0
    import aeroloc.bench.pipeline

    monkeypatch.setattr(aeroloc.bench.pipeline, "peak_rss_mb", lambda: 1e9)  # this process: not the localizing run
    again = run_config(cfg, tmp_path)  # the results file is reused: no query runs again
    assert again["timing"]["localize_total_s"] == pytest.approx(first["timing"]["localize_total_s"])
    # and so is the memory of the run that localized, not this process's
    assert again["memory"]["peak_rss_mb"] == first["memory"]["peak_rss_mb"] < 1e9
    assert first["timing"]["localize_total_s"] == pytest.approx(first["timing"]["total_ms_per_query"] * 6 / 1000)


@pytest.mark.slow
@pytest.mark.parametrize("gsd, name", [(4.5, "naip_20120731_n_003.jpg"), (5.5, "naip_20150926_n_009.jpg")])
def test_a_query_resolution_ten_percent_off_is_corrected_locally(naip, queries, gsd, name):
    """Given 10 % off, the global search still finds the place but without the local scale refinement these
    centres were measured 27 m and 35 m off; with it they come back within metres."""
    q = queries[name]
    d = DenseMapLocator(naip, gsd).locate(read_image(q.path), [])
    assert d is not None
    assert geo.geodesic_distance(q.lat, q.lon, d.lat, d.lon) < 10.0
    assert d.match.scale == pytest.approx(NAIP_GSD / gsd, abs=0.06)  # 1.1 for 4.5 m/px, 0.9 for 5.5
