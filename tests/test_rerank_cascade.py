"""The re-ranking cascade on real NAIP data (``naip_db``: 35 tiles, xfeat-lighterglue features): an upright query
whose first candidate is clearly right costs one query extraction and no matcher; the same query turned by a
quarter is found at the matching rotation and lands where the upright one did; the doubt rule and the query
shrinking of the retriever, on hand-made inputs."""

from __future__ import annotations

import numpy as np
import pytest

from aeroloc.core import geo
from aeroloc.core.errors import AerolocError
from aeroloc.core.images import read_image
from aeroloc.core.queries import load_queries
from aeroloc.localization.alignment import align
from aeroloc.localization.cascade import Candidate, Reranker
from aeroloc.retrieval.database import Database
from aeroloc.retrieval.retriever import Retriever

# 2012 query with a true tile at retrieval rank 1 and ~450 verified inliers (see test_localize.py)
QUERY = "naip_20120731_n_018.jpg"


@pytest.fixture(scope="module")
def db(naip_db):
    return Database(naip_db)


@pytest.fixture(scope="module")
def reranker(db):
    return Reranker(db, "xfeat-lighterglue", "cpu")


@pytest.fixture(scope="module")
def query(naip_dev):
    q = {q.name: q for q in load_queries(naip_dev)}[QUERY]
    return q, read_image(q.path)


@pytest.fixture
def count_extractions(reranker, monkeypatch):
    calls = []
    real = reranker.extractor.extract

    def counting(image, mask=None):
        calls.append(image.shape)
        return real(image, mask=mask)

    monkeypatch.setattr(reranker.extractor, "extract", counting)
    return calls


def _localize(db, reranker, image, tile_ids):
    from aeroloc.localization.alignment import align

    best = reranker(image, tile_ids, 1).candidates[0]
    m = db.info["map"]
    a = align(
        best.H,
        best.score,
        (image.shape[1], image.shape[0]),
        db.by_id[best.tile_id],
        (int(m["width"]), int(m["height"])),
        reranker.conf["min_inliers"],
    )
    return best, a


@pytest.mark.slow
def test_upright_query_costs_one_extraction_and_no_matcher(db, reranker, query, count_extractions):
    _q, image = query
    tile_ids = Retriever(db, "xfeat-vlad", "cpu")(image, 10).tile_ids
    res = reranker(image, tile_ids, 1)
    best = res.candidates[0]
    assert best.screen >= reranker.conf["accept_screen"], best  # a clear screen ...
    assert res.n_verified == 0 and best.inliers == -1  # ... is trusted without LighterGlue
    assert len(count_extractions) == 1  # the upright rotation only
    assert res.n_screened <= 3 + reranker.conf["after_exit"]  # the early exit, then the few screened after it
    # placed by the similarity refitted on the screen's inliers (no perspective terms fitted to noise)
    H = best.H / best.H[2, 2]
    assert H[2, 0] == H[2, 1] == 0.0
    assert H[0, 0] == pytest.approx(H[1, 1]) and H[0, 1] == pytest.approx(-H[1, 0])


@pytest.mark.slow
def test_quarter_turned_query_is_found_at_its_rotation_and_lands_on_the_same_spot(db, reranker, query):
    q, image = query
    tile_ids = Retriever(db, "xfeat-vlad", "cpu")(image, 10).tile_ids
    _best0, a0 = _localize(db, reranker, image, tile_ids)
    turned = np.ascontiguousarray(np.rot90(image, 1))  # turned 90° counter-clockwise
    best1, a1 = _localize(db, reranker, turned, tile_ids)  # same candidates: this tests re-ranking only
    assert a0.localized and a1.localized, (a0.status, a1.status)
    assert best1.rot_k == 3  # a quarter turn clockwise undoes it
    assert geo.geodesic_distance(a0.lat, a0.lon, a1.lat, a1.lon) < 5.0
    assert geo.geodesic_distance(q.lat, q.lon, a1.lat, a1.lon) < 25.0


@pytest.mark.slow
def test_diagonal_query_is_matched_at_its_diagonal_and_lands_on_the_same_spot(db, reranker, query):
    """A photo 45° off every quarter turn: the diagonal that undoes it (rotation 4: 45° counter-clockwise)
    screens far more inliers than the upright rotation, and the cascade with the heading unknown places it
    where the upright photo is."""
    from aeroloc.core.frames import turned

    _q, image = query
    tile_ids = Retriever(db, "xfeat-vlad", "cpu")(image, 10).tile_ids
    best0, a0 = _localize(db, reranker, image, tile_ids)
    # the photo's own turn against the map (it is not exactly north-up), so that the turned one is 45° off
    own = np.degrees(np.arctan2(best0.H[1, 0], best0.H[0, 0]))
    diagonal = turned(image, -45.0 - own)[0]  # the content 45° clockwise of north-up
    at = {k: reranker(diagonal, tile_ids, 1, rotations=[k]).candidates[0] for k in (0, 3, 4)}
    assert at[4].rot_k == 4 and at[4].screen >= 2 * max(at[0].screen, at[3].screen), at
    _best, a = _localize(db, reranker, diagonal, tile_ids)
    assert a.localized, a.status
    assert geo.geodesic_distance(a0.lat, a0.lon, a.lat, a.lon) < 10.0


@pytest.mark.slow
def test_a_screen_fits_the_nadir_similarity_without_magsac_and_ranks_as_the_homography_did(
    db, reranker, query, monkeypatch
):
    """The screen counts the inliers of a 2-point similarity RANSAC (``screen_geometry`` "similarity"), not a
    MAGSAC homography: on the true tile both models give a clear screen that places the photo on the same spot,
    and tiles a tile diagonal or more from the truth stay below what settles a heading under both."""
    from aeroloc.matching import verify
    from aeroloc.matching.features import extract

    q, image = query
    tile_ids = Retriever(db, "xfeat-vlad", "cpu")(image, 10).tile_ids
    tfs = reranker.tile_features(tile_ids)
    qf = extract(reranker.extractor, image, reranker.conf["query_side"], 0)
    assert reranker.conf["screen_geometry"] == "similarity"
    homography = Reranker(db, "xfeat-lighterglue", "cpu", {"screen_geometry": "homography"})
    by_h = {t: homography.screen_pair(qf, tfs[t]) for t in tile_ids}

    def no_magsac(*_a, **_k):
        raise AssertionError("the similarity screen fitted a homography")

    monkeypatch.setattr(verify, "verify_homography", no_magsac)
    similarity = Reranker(db, "xfeat-lighterglue", "cpu", {"screen_homography_min": None})  # no homography top-up
    by_s = {t: similarity.screen_pair(qf, tfs[t]) for t in tile_ids}
    best_s, best_h = (max(tile_ids, key=lambda t: by[t][0]) for by in (by_s, by_h))
    assert best_s == best_h
    assert min(by_s[best_s][0], by_h[best_h][0]) >= reranker.conf["accept_screen"], (by_s[best_s][0], by_h[best_h][0])
    m = db.info["map"]
    placed = [
        align(
            by[best_s][1],
            by[best_s][0],
            (image.shape[1], image.shape[0]),
            db.by_id[best_s],
            (int(m["width"]), int(m["height"])),
            20,
        )
        for by in (by_s, by_h)
    ]
    assert all(a.localized for a in placed)
    assert geo.geodesic_distance(placed[0].lat, placed[0].lon, placed[1].lat, placed[1].lon) < 5.0
    assert geo.geodesic_distance(q.lat, q.lon, placed[0].lat, placed[0].lon) < 25.0
    corners = db.by_id[best_s].corners_latlon
    diagonal_m = geo.geodesic_distance(*corners[0], *corners[1])
    far = [t for t in tile_ids if geo.geodesic_distance(q.lat, q.lon, *db.by_id[t].centre_latlon) > diagonal_m]
    assert far, "the test needs candidates away from the truth"
    assert max(by[t][0] for by in (by_s, by_h) for t in far) < reranker.conf["min_screen"]


def test_a_strong_similarity_screen_is_topped_up_by_the_homography_and_a_weak_one_is_not(
    db, reranker, query, monkeypatch
):
    """A similarity screen of at least ``screen_homography_min`` inliers also fits the homography and keeps the
    larger count (tilted photos hold more inliers under a homography); a weaker one fits no homography; an insane
    homography in the top-up counts nothing rather than refitting the similarity the screen already has."""
    from aeroloc.matching import verify
    from aeroloc.matching.features import extract

    _, image = query
    tile_ids = Retriever(db, "xfeat-vlad", "cpu")(image, 10).tile_ids
    tfs = reranker.tile_features(tile_ids)
    qf = extract(reranker.extractor, image, reranker.conf["query_side"], 0)
    least = reranker.conf["screen_homography_min"]
    sim_only = Reranker(db, "xfeat-lighterglue", "cpu", {"screen_homography_min": None})
    hom_only = Reranker(db, "xfeat-lighterglue", "cpu", {"screen_geometry": "homography"})
    sims = {t: sim_only.screen_pair(qf, tfs[t])[0] for t in tile_ids}
    strong = [t for t in tile_ids if sims[t] >= least]
    weak = [t for t in tile_ids if sims[t] < least]
    assert strong and weak, sims
    for t in strong:  # RANSAC and MAGSAC are seeded alike on every call: the counts are reproducible
        assert reranker.screen_pair(qf, tfs[t])[0] == max(sims[t], hom_only.screen_pair(qf, tfs[t])[0])
    calls = {"homography": 0, "similarity": 0}
    for name in calls:
        real = getattr(verify, f"verify_{name}")

        def counted(*a, _real=real, _name=name, **k):
            calls[_name] += 1
            return _real(*a, **k)

        monkeypatch.setattr(verify, f"verify_{name}", counted)
    for t in weak:
        assert reranker.screen_pair(qf, tfs[t])[0] == sims[t]
    assert calls["homography"] == 0
    monkeypatch.setattr(verify, "homography_is_sane", lambda *a, **k: (False, "made insane"))
    calls.update(homography=0, similarity=0)
    assert reranker.screen_pair(qf, tfs[strong[0]])[0] == sims[strong[0]]
    assert calls == {"homography": 1, "similarity": 1}


def test_diagonal_features_map_back_to_the_original_frame(reranker, query):
    """Keypoints extracted on the query turned by each diagonal, mapped back by to_original, meet the same
    query's upright keypoints: a similarity fitted between them is the identity, its shift within 2 px as for the
    lossless quarter turns (XFeat's keypoints move 0.6-1.7 px on this 256 px query when its grid turns)."""
    from aeroloc.matching.features import extract, rotation_angle, to_original
    from aeroloc.matching.verify import verify_similarity

    _q, image = query
    f0 = extract(reranker.extractor, image, 512, 0)
    for k in range(1, 8):
        fk = extract(reranker.extractor, image, 512, k)
        assert rotation_angle(k) == 90.0 * (k % 4) + (45.0 if k >= 4 else 0.0)
        assert fk["scale"] == pytest.approx(f0["scale"])  # the ground keeps its density against the tiles
        p0, pk = to_original(f0), to_original(fk)
        d = np.linalg.norm(p0[:, None, :] - pk[None, :, :], axis=2)
        pairs = np.stack([np.arange(len(p0)), d.argmin(1)], 1)[d.min(1) < 3.0]
        assert len(pairs) > 200, k
        v = verify_similarity(p0, pk, pairs, threshold_px=1.5)
        assert v.n_inliers > 300  # of nearest keypoints within 3 px (resampling moves some, others are not the same)
        assert np.allclose(v.H, np.eye(3), atol=np.array([[0.01, 0.01, 2.0], [0.01, 0.01, 2.0], [0, 0, 0]])), v.H


def test_doubt_rule_overrules_a_weak_screen_only_where_configured(reranker):
    """The default scores the matcher by similarity inliers, on which wrong tiles stay <= 24 < min_inliers, so it
    trusts the matcher alone; a homography-scored setup (where a wrong Toledo tile reached 41) can still require
    a confident matcher when the screen was weak."""
    c = reranker.conf
    assert c["geometry"] == "similarity" and c["min_inliers"] >= 30
    assert reranker.doubt(Candidate("t", 0, screen=3, inliers=c["min_inliers"])) is None
    strict = {**c, "min_screen": 20, "confident_inliers": 80}
    old, reranker.conf = reranker.conf, strict
    try:
        assert "screen found 18 inliers" in reranker.doubt(Candidate("t", 0, screen=18, inliers=41))
        assert reranker.doubt(Candidate("t", 0, screen=18, inliers=80)) is None
        assert reranker.doubt(Candidate("t", 0, screen=20, inliers=35)) is None
        assert reranker.doubt(Candidate("t", 0, screen=c["accept_screen"])) is None  # screen only: min_inliers decides
    finally:
        reranker.conf = old


def test_a_screen_turn_is_asked_for_only_where_the_screen_settled_a_heading_far_from_the_turn_tried(reranker):
    """``_screen_angle``: the OpenCV angle that turns the query map-aligned by a candidate's screen transform, when
    the screen reached ``min_screen`` and the angle lies ``screen_turn_min_deg`` or more off the turn screened
    (its rotation plus the prior's turn); None otherwise, and for a transform with no finite angle."""

    def screened(angle_deg: float, screen: int, rot_k: int) -> Candidate:
        t = np.radians(-angle_deg)  # placement_of: the angle turning the query onto the map undoes H's rotation
        H = np.array([[np.cos(t), -np.sin(t), 5.0], [np.sin(t), np.cos(t), 7.0], [0.0, 0.0, 1.0]])
        return Candidate("t", 0, screen=screen, rot_k=rot_k, H=H)

    floor = reranker.conf["min_screen"]
    assert reranker._screen_angle(screened(65.0, floor, 1), 0.0) == pytest.approx(65.0)  # 25° off the 90° turn
    assert reranker._screen_angle(screened(85.0, floor, 1), 0.0) is None  # 5° off: the matcher bridges it
    assert reranker._screen_angle(screened(65.0, floor - 1, 1), 0.0) is None  # no heading settled
    assert reranker._screen_angle(screened(65.0, floor, 0), 60.0) is None  # the prior's turn counts
    assert reranker._screen_angle(screened(65.0, floor, 0), 30.0) == pytest.approx(65.0)
    nan = screened(65.0, floor, 1)
    nan.H = np.full((3, 3), np.nan)
    assert reranker._screen_angle(nan, 0.0) is None


def test_retriever_shrinks_queries_larger_than_a_tile(db):
    side = max(max(t.width, t.height) for t in db.tiles)
    r = Retriever(db, "xfeat-vlad", "cpu", query_scale=1.0)
    big = np.zeros((3 * side, 4 * side, 3), np.uint8)
    assert r.shrink(big).shape == (round(0.75 * side), side, 3)
    small = np.zeros((side - 10, side // 2, 3), np.uint8)
    assert r.shrink(small) is small
    default = Retriever(db, "xfeat-vlad", "cpu")  # 1.5 tile sides: a query at the map's resolution stays as it is
    assert default.shrink(big).shape[1] == round(1.5 * side)
    assert default.shrink(np.zeros((side, round(1.4 * side), 3), np.uint8)).shape == (side, round(1.4 * side), 3)
    assert Retriever(db, "xfeat-vlad", "cpu", query_scale=None).shrink(big) is big
    with pytest.raises(AerolocError, match="query_scale must be > 0"):
        Retriever(db, "xfeat-vlad", "cpu", query_scale=0)


def test_every_probe_candidate_is_screened_at_the_turn_where_one_exits_early():
    """An early exit at a turn screens the probe's other candidates at that turn too. The screens after an exit
    take only unvisited candidates, so a probe candidate screened at an earlier turn and skipped at the exit's
    turn kept its weak count (szada_any_0_05: a field the map shows twice exited at 40 inliers at rank 1, the
    true tile at rank 2 kept 11 from the upright turn though it screens 82 at the exit's)."""
    from aeroloc.localization.cascade import Screens
    from aeroloc.matching.registry import rerank_conf

    rr = Reranker.__new__(Reranker)
    rr.conf = rerank_conf("xfeat-lighterglue")
    counts = {("a", 1): 5, ("b", 1): 5, ("c", 1): 5, ("a", 0): 8, ("b", 0): 40, ("c", 0): 82, ("d", 0): 3}
    asked = []

    def screen_pair(k, tile):
        asked.append((tile, k))
        return counts.get((tile, k), 0), np.eye(3), 10, None

    cands = [Candidate(t, i) for i, t in enumerate("abcd")]
    tfs = {t: t for t in "abcd"}
    n = rr._screen(cands, [1, 0], Screens(screen_pair, lambda t, k: (k, tfs[t]), None), None)
    assert n == len(asked) and ("c", 0) in asked
    by_id = {c.tile_id: c for c in cands}
    assert by_id["c"].screen == 82 and by_id["c"].rot_k == 0
    assert by_id["b"].screen == 40 and by_id["d"].screen == 3  # the exit, then the unvisited screened after it


@pytest.mark.slow
def test_screens_computed_ahead_on_a_second_thread_change_no_result(db, query):
    """The screens run ahead of the cascade's order on a second thread (aeroloc.localization.cascade.Screens)
    where the process has two: a photo turned a quarter with the heading unknown (the probe at several turns,
    the later candidates, the screens after an early exit) gets the same candidates, screen and matcher
    counts, transforms and number of screens with one thread and with two."""
    _q, image = query
    photo = np.ascontiguousarray(np.rot90(image, 1))  # a quarter turn: the probe tries other turns first
    tile_ids = Retriever(db, "xfeat-vlad", "cpu")(image, 20).tile_ids
    runs = []
    for threads in (1, 2):
        rr = Reranker(db, "xfeat-lighterglue", "cpu", {"screen_threads": threads})
        assert (rr._screen_pool() is None) == (threads == 1)
        runs.append(rr(photo, tile_ids, 0))
    one, two = runs
    assert one.n_screened == two.n_screened and one.n_screened > len(tile_ids) // 2
    assert [(c.tile_id, c.screen, c.inliers, c.rot_k) for c in one.ranked] == [
        (c.tile_id, c.screen, c.inliers, c.rot_k) for c in two.ranked
    ]
    for a, b in zip(one.ranked, two.ranked):
        assert (a.H is None and b.H is None) or np.array_equal(a.H, b.H)
    assert one.ranked[0].screen >= 40 and one.ranked[0].rot_k == 3


def test_a_screen_started_ahead_and_not_asked_for_is_dropped():
    """Screens: what the caller asks for is what it gets (computed ahead or on demand, the same function of
    the two feature sets); screens started ahead that the cascade's order never reaches are cancelled or
    waited for by close(), so nothing runs on into the next stage; a pair the caller has had is never started
    ahead again (the turn-score order screens pairs before the probe's loop, which skips them)."""
    from concurrent.futures import ThreadPoolExecutor

    from aeroloc.localization.cascade import Screens

    calls = []

    def screen_pair(qf, tf):
        calls.append((qf, tf))
        return (qf * 10 + tf, None, 0, None)

    with ThreadPoolExecutor(2) as pool:
        tfs = {"a": 1, "b": 2, "c": 3, "d": 4}
        s = Screens(screen_pair, lambda t, k: (k, tfs[t]), pool, lambda t, k: k == 0)
        s.ahead([("a", 0), ("b", 0), ("c", 5)])
        assert s("b", 0)[0] == 2 and s("a", 0)[0] == 1 and s("a", 1)[0] == 11  # the last one on demand
        s.close()
        assert not s._ahead and len(calls) <= 4
        assert s("c", 5)[0] == 53  # dropped: computed again when asked for after all
        s.ahead([("d", 0), ("c", 7), ("b", 0)], guess=True)  # a guess starts only the cheap pairs, never one had
        assert set(s._ahead) == {("d", 0)} and ("b", 0) in s.asked
        s.close()
    assert Screens(screen_pair, lambda t, k: (k, 1), None)("a", 2)[0] == 21


def test_tile_features_kept_decoded_are_the_stored_ones_and_bounded(db):
    """The re-ranker keeps the last ``tile_cache`` tiles' features decoded between queries: what it returns
    equals a fresh read of the store, and it never holds more than the bound (or one call's tiles)."""
    r = Reranker(db, "xfeat-lighterglue", "cpu", conf={"tile_cache": 3})
    ids = [t.id for t in db.tiles[:6]]
    first = r.tile_features(ids[:4])
    assert len(r._tile_cache) == 4  # one call's tiles are all kept, whatever the bound
    again = r.tile_features(ids[2:6])
    assert len(r._tile_cache) == 4 and list(r._tile_cache)[-1] == ids[5]
    with r.store.reader() as reader:
        for t in ids[2:4]:
            fresh = reader.get(t)
            assert again[t] is first[t]  # read once, kept
            assert fresh.keys() == again[t].keys()
            assert all(np.array_equal(fresh[k], again[t][k]) for k in fresh)
    r.tile_features(ids[:1])
    assert len(r._tile_cache) <= 4 and ids[0] in r._tile_cache


@pytest.mark.slow
def test_candidates_screened_below_the_weak_floor_are_not_matched(db, query):
    """A real photo against wrong tiles only (centres > 2 km from its truth): their screens stay weak, and those
    below ``weak_screen_min`` are never handed to the matcher (it never made such a pass); with the floor at 0 the
    same best-screened candidates are matched, so the floor is what spared them. Nothing passes either way."""
    q, image = query
    far = [
        t.id
        for t in db.tiles
        if geo.geodesic_distance(q.lat, q.lon, *t.pixel_to_latlon(t.width / 2, t.height / 2)) > 2000
    ][:8]
    runs = {}
    for floor in (12, 0):
        rr = Reranker(db, "xfeat-lighterglue", "cpu", conf={"weak_screen_min": floor})
        res = rr(image, far, 0)
        best = sorted((c for c in res.ranked if c.screen >= 0), key=lambda c: (-c.screen, c.retrieval_rank))
        runs[floor] = (res, best[: rr.conf["max_verify"]])
    res, top = runs[12]
    below = [c for c in top if c.screen < 12]
    assert below, [c.screen for c in top]  # the case the floor is for
    assert all(c.inliers == -1 for c in below) and res.n_verified == len(top) - len(below)
    assert not any(c.inliers >= rr.conf["min_inliers"] for c in res.ranked)
    res0, top0 = runs[0]
    assert [c.tile_id for c in top0] == [c.tile_id for c in top]  # the screens do not depend on the floor
    assert res0.n_verified == len(top0) and all(c.inliers >= 0 for c in top0)


@pytest.mark.slow
def test_with_a_known_heading_a_weak_screen_still_goes_to_the_matcher(tmp_path, data_dir):
    """The demo's NAIP database (256 px tiles, `--north-up --query-gsd 5`): naip_20100629_n_018's true tile
    screens only 11 inliers, below the weak floor, yet LighterGlue finds ~51 there and places it within 10 m. The
    floor spares matcher runs where the heading is unknown (weak screens at wrong turns); with the heading known
    the screen is at the right turn and it is not applied, so the demo's Georef@10 m stays 0.99."""
    from types import SimpleNamespace

    from aeroloc.commands.demo import DEMO_SETS, _database, _options
    from aeroloc.localization.localizer import Localizer

    _, map_rel, q_rel, zoom, overlap, tile_m, north_up, query_gsd = DEMO_SETS[0]
    db = _database(data_dir / map_rel, tmp_path / "naip", zoom, overlap, tile_m, "xfeat-lighterglue", "cpu")
    loc = Localizer(db, _options(SimpleNamespace(top_n=20), "xfeat-lighterglue", north_up, query_gsd))
    q = {q.name: q for q in load_queries(data_dir / q_rel)}["naip_20100629_n_018.jpg"]
    res = loc(q.name, read_image(q.path), priors=q.priors)
    assert res.localized and geo.geodesic_distance(q.lat, q.lon, res.lat, res.lon) < 10.0, res.status
    assert res.best.screen < loc.reranker.conf["weak_screen_min"] <= res.best.inliers, (res.best.screen, res.inliers)
