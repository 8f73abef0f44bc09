"""End to end on real data: NAIP cross-season queries localized within metres by retrieval (xfeat-vlad) +
re-ranking (XFeat + LighterGlue) + homography alignment; images from elsewhere are "not localized"; the results
CSV resumes after an interruption and a finished run of the same configuration is reused."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from _windows import cut_at_heading
from aeroloc.bench.metrics import tile_contains
from aeroloc.core import geo
from aeroloc.core.images import read_image
from aeroloc.core.queries import load_queries
from aeroloc.retrieval.database import Database

METHOD, RERANK = "xfeat-vlad", "xfeat-lighterglue"
# Chosen after localizing the 48 queries of 2012 and 2014 (and a few others) against this 35-tile database:
# 38/48 localized, all within 17 m. These three (one each from 2012, 2014 and 2015) have a true tile at
# retrieval rank 1 and 350-450 verified inliers; errors measured 1.4 m, 1.5 m and 1.9 m.
GOOD = ["naip_20120731_n_018.jpg", "naip_20140720_n_023.jpg", "naip_20150926_n_006.jpg"]


@pytest.fixture(scope="module")
def db(naip_db):
    return Database(naip_db)


@pytest.fixture(scope="module")
def queries(naip_dev):
    return {q.name: q for q in load_queries(naip_dev)}


@pytest.fixture(scope="module")
def localizer(db):
    from aeroloc.localization.localizer import Localizer
    from aeroloc.localization.options import LocalizeOptions

    return Localizer(db, LocalizeOptions(method=METHOD, rerank=RERANK), "cpu")


@pytest.mark.slow
def test_cross_season_queries_localize_within_25_m(localizer, db, queries):
    for name in GOOD:
        q = queries[name]
        res = localizer(name, read_image(q.path), top_n=10)
        assert any(tile_contains(db.by_id[t], q.lat, q.lon) for t in res.retrieved[:3]), f"{name}: retrieval"
        assert res.status == "localized", f"{name}: {res.status}"
        assert res.inliers >= localizer.reranker.conf["min_inliers"]
        err = geo.geodesic_distance(q.lat, q.lon, res.lat, res.lon)
        assert err < 25.0, f"{name}: {err:.1f} m from the truth"
        assert set(res.times_ms) >= {"descriptor", "search", "local_features", "rerank", "align"}
        # 350-450 inliers: a confident fix whose stated uncertainty is a few map pixels (5 m/px), not metres-free
        assert 0.5 <= res.confidence <= 1.0, res.confidence
        assert 2.5 <= res.sigma_m <= 25.0, res.sigma_m
        assert float(res.row()["confidence"]) == pytest.approx(res.confidence, abs=1e-3)


@pytest.mark.slow
def test_a_fix_under_the_confidence_floor_is_not_localized(db, queries):
    from aeroloc.localization.localizer import Localizer
    from aeroloc.localization.options import LocalizeOptions

    q = queries[GOOD[0]]
    strict = Localizer(db, LocalizeOptions(method=METHOD, rerank=RERANK, min_confidence=0.99999), "cpu")
    res = strict(q.name, read_image(q.path), top_n=10)
    assert res.status.startswith("not localized: confidence "), res.status
    assert not res.localized and res.confidence is None and res.row()["lat"] == ""
    with pytest.raises(Exception, match="min-confidence must be in"):
        LocalizeOptions(min_confidence=1.5)


@pytest.mark.slow
def test_images_not_in_the_map_are_not_localized(localizer, data_dir, queries):
    """A Toledo drone photo (another city) and a mirrored NAIP query (no rotation undoes a mirror) against the
    NAIP map; measured 0 and 12 verified inliers (the threshold is 35)."""
    toledo = read_image(data_dir / "toledo" / "photos" / "1JI_0064.JPG")
    mirrored = np.ascontiguousarray(read_image(queries["naip_20120731_n_018.jpg"].path)[:, ::-1])
    for name, image in [("toledo", toledo), ("mirrored", mirrored)]:
        res = localizer(name, image, top_n=5)
        assert res.status.startswith("not localized"), f"{name}: {res.status} ({res.inliers} inliers)"
        assert math.isnan(res.lat) and math.isnan(res.lon)
        assert res.row()["lat"] == "" and res.row()["lon"] == ""


@pytest.mark.slow
def test_results_csv_resumes_and_a_finished_run_is_reused(db, queries, tmp_path, monkeypatch):
    import aeroloc.localization.localizer as localizer_mod
    import aeroloc.localization.run as loc
    from aeroloc.localization.options import LocalizeOptions

    opts = LocalizeOptions(top_n=3, method=METHOD, rerank=RERANK)
    opts4 = LocalizeOptions(top_n=4, method=METHOD, rerank=RERANK)

    qs = [queries[n] for n in GOOD[:2]]
    out = tmp_path / "results.csv"
    part = tmp_path / "results.csv.part"
    real_call = localizer_mod.Localizer.__call__
    calls = []

    def killed_after_one(self, name, *a, **kw):
        if calls:
            raise KeyboardInterrupt("simulated kill after one query")
        calls.append(name)
        return real_call(self, name, *a, **kw)

    monkeypatch.setattr(localizer_mod.Localizer, "__call__", killed_after_one)
    with pytest.raises(KeyboardInterrupt):
        loc.localize_queries(db, qs, out, opts, device="cpu", progress=False)
    assert not out.exists() and part.is_file()
    with open(part, newline="") as f:
        first = list(csv.DictReader(f))
    assert [r["name"] for r in first] == [GOOD[0]] and first[0]["status"] == "localized"

    calls.clear()

    def counted(self, name, *a, **kw):
        calls.append(name)
        return real_call(self, name, *a, **kw)

    monkeypatch.setattr(localizer_mod.Localizer, "__call__", counted)
    rows = loc.localize_queries(db, qs, out, opts, device="cpu", progress=False)
    assert calls == [GOOD[1]]  # the first query was not recomputed
    assert [r.name for r in rows] == GOOD[:2] and rows[0].row() == first[0]
    assert out.is_file() and not part.exists()
    with open(out, newline="") as f:
        on_disk = list(csv.DictReader(f))
    assert on_disk == [r.row() for r in rows] and all(r["status"] == "localized" for r in on_disk)
    for r in on_disk:
        q = queries[r["name"]]
        assert geo.geodesic_distance(q.lat, q.lon, float(r["lat"]), float(r["lon"])) < 25.0

    class Boom(Exception):
        pass

    def no_localizer(*a, **kw):
        raise Boom("the pipeline was run again")

    monkeypatch.setattr(loc, "Localizer", no_localizer)
    again = loc.localize_queries(db, qs, out, opts, device="cpu", progress=False)
    assert again == rows  # same configuration finished before: read back, nothing rerun
    with pytest.raises(Boom):  # another configuration (top-N) must not reuse those rows
        loc.localize_queries(db, qs, out, opts4, device="cpu", progress=False)


@pytest.mark.slow
def test_a_strip_too_thin_for_the_matchers_is_not_localized_and_the_run_goes_on(db, queries, tmp_path, monkeypatch):
    """A 30x-wide strip of a real photo (256 x 7680 px) shrinks to 17 px on its short side at the matchers'
    512 px working size. It is refused with that reason, and the next photo of the run is still placed. Before,
    the extractor's error ended the whole run, and a resumed run met the same photo and stopped again. With the
    up-front check bypassed the extractor's own error becomes that query's status, not the run's end."""
    import cv2

    import aeroloc.localization.run as loc
    import aeroloc.localization.screening as screening
    from aeroloc.localization.options import LocalizeOptions

    good = queries[GOOD[0]]
    photo = read_image(good.path)
    cv2.imwrite(str(tmp_path / "strip.png"), np.tile(photo, (1, 30, 1))[..., ::-1])
    cv2.imwrite(str(tmp_path / GOOD[0]), photo[..., ::-1])
    (tmp_path / "q.csv").write_text(f"name,lat,lon\nstrip.png,{good.lat},{good.lon}\n{GOOD[0]},{good.lat},{good.lon}\n")
    qs = load_queries(tmp_path / "q.csv")
    opts = LocalizeOptions(top_n=3, method=METHOD, rerank=RERANK)
    strip, placed = loc.localize_queries(db, qs, tmp_path / "a.csv", opts, device="cpu", progress=False)
    assert strip.status.startswith("not localized") and "512 px working size" in strip.status, strip.status
    assert placed.status == "localized"
    assert geo.geodesic_distance(good.lat, good.lon, placed.lat, placed.lon) < 25.0
    monkeypatch.setattr(screening, "refusal", lambda *a, **k: None)  # read at each call by Localizer.__call__
    strip, placed = loc.localize_queries(db, qs, tmp_path / "b.csv", opts, device="cpu", progress=False)
    assert strip.status.startswith("not localized: image of") and "too small for local features" in strip.status
    assert placed.status == "localized"
    # an error of the database or the map is not one query's: it still ends the run (a finished run is reused,
    # so a transient fault recorded as "not localized" would be reused with it)
    from aeroloc.core.errors import AerolocError
    from aeroloc.localization.localizer import Localizer

    def broken_store(self, name, *a, **kw):
        raise AerolocError("the feature store is corrupt")

    monkeypatch.setattr(Localizer, "__call__", broken_store)
    with pytest.raises(AerolocError, match="feature store is corrupt"):
        loc.localize_queries(db, qs, tmp_path / "c.csv", opts, device="cpu", progress=False)
    assert not (tmp_path / "c.csv").exists()


def test_options_and_the_cli_refuse_contradicting_heading_options(naip_dev, tmp_path):
    import subprocess
    import sys

    from aeroloc.core.errors import AerolocError
    from aeroloc.localization.options import LocalizeOptions

    north = LocalizeOptions(north_up=True, rerank_overrides={"max_verify": 2})
    assert north.cascade_overrides() == {"max_verify": 2, "rotations": [0]}
    assert LocalizeOptions(rotations=4).cascade_overrides() is None
    with pytest.raises(AerolocError, match="north-up queries need no rotation search"):
        LocalizeOptions(north_up=True, rotations=4)
    with pytest.raises(AerolocError, match=r"unknown re-ranker option\(s\) \['refine_runner_up'\]"):
        LocalizeOptions(rerank_overrides={"refine_runner_up": 0})  # misspelt: refine_runners_up
    for threads in (0, -2, 1.5, "2", True):
        with pytest.raises(AerolocError, match=r"screen_threads must be None or an integer >= 1, got "):
            LocalizeOptions(rerank_overrides={"screen_threads": threads})
    assert LocalizeOptions(rerank_overrides={"screen_threads": 1}).cascade_conf()["screen_threads"] == 1
    for key in ("tile_cache", "weak_screen_turns", "weak_screen_min", "turn_score_screens"):
        for bad in (-1, 2.5, "3", None, False):
            with pytest.raises(AerolocError, match=rf"{key} must be an integer >= 0, got "):
                LocalizeOptions(rerank_overrides={key: bad})
    assert LocalizeOptions(rerank_overrides={"tile_cache": 0}).cascade_conf()["tile_cache"] == 0
    for bad in (-1, 2.5, "30", False):
        with pytest.raises(AerolocError, match=r"accept_agreed must be None or an integer >= 0, got "):
            LocalizeOptions(rerank_overrides={"accept_agreed": bad})
    assert LocalizeOptions(rerank_overrides={"accept_agreed": None}).cascade_conf()["accept_agreed"] is None
    for bad in (0.5, -2, "2", None, True):
        with pytest.raises(AerolocError, match=r"agreed_margin must be a number >= 1, got "):
            LocalizeOptions(rerank_overrides={"agreed_margin": bad})
    for key in ("diagonals", "screen", "turned_tiles", "own_angle_rescreen"):
        for bad in ("false", 0, None):
            with pytest.raises(AerolocError, match=rf"{key} must be true or false, got "):
                LocalizeOptions(rerank_overrides={key: bad})
    assert LocalizeOptions(rerank_overrides={"own_angle_rescreen": False}).cascade_conf()["own_angle_rescreen"] is False
    for key in ("geometry", "screen_geometry"):
        with pytest.raises(AerolocError, match=rf"{key} must be one of homography, similarity, got 'affine'"):
            LocalizeOptions(rerank_overrides={key: "affine"})
    assert LocalizeOptions(rerank_overrides={"screen_geometry": "homography"}).cascade_conf()["screen_geometry"] == (
        "homography"
    )
    out = tmp_path / "r.csv"
    p = subprocess.run(
        [
            sys.executable,
            "-m",
            "aeroloc.cli",
            "localize",
            str(tmp_path),
            str(naip_dev),
            "--north-up",
            "--rotations",
            "4",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    lines = [line for line in p.stderr.splitlines() if line.strip()]
    assert p.returncode == 2 and "Traceback" not in p.stderr + p.stdout
    assert len(lines) == 1 and "--north-up and --rotations > 1 contradict each other" in lines[0], lines
    assert not out.exists()


@pytest.mark.slow
def test_north_up_costs_one_extraction_and_a_turned_query_is_not_localized(db, queries, monkeypatch):
    """With the heading known, the re-ranker extracts the query once; a query that is in fact turned by a quarter
    finds no verified match at the upright heading and is reported "not localized", not put somewhere wrong."""
    from aeroloc.localization.localizer import Localizer
    from aeroloc.localization.options import LocalizeOptions

    loc = Localizer(db, LocalizeOptions(method=METHOD, rerank=RERANK, north_up=True), "cpu")
    calls = []
    real = loc.reranker.extractor.extract
    monkeypatch.setattr(loc.reranker.extractor, "extract", lambda im, mask=None: calls.append(1) or real(im, mask=mask))
    q = queries[GOOD[0]]
    image = read_image(q.path)
    res = loc(q.name, image, top_n=10)
    assert res.status == "localized" and geo.geodesic_distance(q.lat, q.lon, res.lat, res.lon) < 25.0
    assert len(calls) == 1
    turned = loc(q.name, np.ascontiguousarray(np.rot90(image, 1)), top_n=10)
    assert turned.status.startswith("not localized"), (turned.status, turned.inliers)


@pytest.mark.slow
def test_numpy_blas_runs_single_threaded_while_localizing(localizer, queries, monkeypatch):
    """Spinning OpenBLAS threads between the screen's numpy products took the cores from torch (the descriptor
    ~3x slower on 2 cores): during a localization numpy's BLAS has one thread, and its setting comes back after."""
    from threadpoolctl import threadpool_info

    def blas_threads():
        return {i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}

    before = blas_threads()
    seen = []
    real = localizer.reranker.__class__.__call__

    def spy(self, *a, **kw):
        seen.append(blas_threads())
        return real(self, *a, **kw)

    monkeypatch.setattr(localizer.reranker.__class__, "__call__", spy)
    q = queries[GOOD[0]]
    res = localizer(q.name, read_image(q.path), top_n=5)
    assert res.status == "localized"
    assert seen == [{1}]
    assert blas_threads() == before


def test_a_blas_loaded_after_the_first_localization_is_single_threaded_too():
    """The BLAS libraries are scanned again when modules were imported since the last scan: scipy's own OpenBLAS,
    imported after the first localization, kept 2 threads (found when the whole suite ran in one process). In a
    fresh interpreter, so the import order is the one described."""
    import subprocess
    import sys

    code = (
        "import numpy\n"
        "from threadpoolctl import threadpool_info\n"
        "from aeroloc.core.device import single_threaded_blas\n"
        "with single_threaded_blas():\n"
        "    pass\n"
        "import scipy.linalg\n"
        "with single_threaded_blas():\n"
        "    print(sorted({i['num_threads'] for i in threadpool_info() if i['user_api'] == 'blas'}),"
        " len([i for i in threadpool_info() if i['user_api'] == 'blas']))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out[0] == "[1]", out
    assert int(out[1]) >= 2, out  # numpy's and scipy's OpenBLAS both seen (else the test shows nothing)


@pytest.mark.slow
@pytest.mark.parametrize("heading", [0.0, 90.0, 137.0, 200.0])
def test_a_window_cut_from_the_map_at_any_heading_is_placed_without_bias(localizer, naip_map, heading):
    """The geometry chain (turns, working resolution, keypoint frames, tile georeference) adds no offset: a
    window of the map itself, cut at a heading with exact geometry, is placed within a fifth of a map pixel
    (measured 0.04-0.3 m at 5 m/px on 16 such windows). A half-pixel slip anywhere would cost >= 2.5 m."""
    import rasterio
    from pyproj import Transformer

    with rasterio.open(naip_map) as ds:
        image = np.ascontiguousarray(ds.read([1, 2, 3]).transpose(1, 2, 0))
        cx, cy = 0.37 * ds.width + 0.3, 0.55 * ds.height + 0.7
        x, y = ds.transform @ (cx, cy)
        lon, lat = Transformer.from_crs(ds.crs, "EPSG:4326", always_xy=True).transform(x, y)
    res = localizer("cut", cut_at_heading(image, cx, cy, heading, 200))
    assert res.status.startswith("localized"), res.status
    assert geo.geodesic_distance(lat, lon, res.lat, res.lon) < 1.0
