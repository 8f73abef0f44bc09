"""Turned tiles (``aeroloc build --local-turns``): a photo of unknown heading is extracted once, upright, and
screened against the tiles turned back, on real NAIP data (a copy of ``naip_db`` whose tiles get their turns)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from aeroloc.core import geo
from aeroloc.core.frames import inverse_turn, turned
from aeroloc.core.images import read_image
from aeroloc.core.queries import load_queries
from aeroloc.localization.alignment import align
from aeroloc.localization.cascade import Reranker
from aeroloc.matching.features import DIAGONAL, rotation_angle
from aeroloc.retrieval.database import Database
from aeroloc.retrieval.retriever import Retriever

QUERY = "naip_20120731_n_018.jpg"  # a true tile at retrieval rank 1 (see test_rerank_cascade.py)


def test_the_inverse_turn_undoes_every_rotation_index():
    for k in range(2 * DIAGONAL):
        assert (rotation_angle(k) + rotation_angle(inverse_turn(k))) % 360.0 == 0.0, k
        assert inverse_turn(inverse_turn(k)) == k


@pytest.fixture(scope="module")
def turned_db(naip_db, tmp_path_factory):
    """naip_db copied, its tiles' features built at the seven other turns too."""
    from aeroloc.matching.features import build_local

    folder = tmp_path_factory.mktemp("turned") / "db"
    shutil.copytree(naip_db, folder)
    db = Database(folder)
    report = build_local(db, "xfeat-lighterglue", "cpu", progress=False, turns=True)
    assert not report.cached
    again = build_local(db, "xfeat-lighterglue", "cpu", progress=False, turns=True)
    assert again.cached  # resumable: nothing left to do
    return db


@pytest.fixture(scope="module")
def query(naip_dev):
    q = {q.name: q for q in load_queries(naip_dev)}[QUERY]
    return q, read_image(q.path)


def _place(db, rr: Reranker, image, tile_ids):
    res = rr(image, tile_ids, 1)
    best = res.candidates[0]
    m = db.info["map"]
    size = (image.shape[1], image.shape[0])
    a = align(best.H, best.score, size, db.by_id[best.tile_id], (int(m["width"]), int(m["height"])), 30)
    return res, best, a


@pytest.mark.slow
@pytest.mark.parametrize("turn", ["quarter", "diagonal"])
def test_a_turned_photo_is_found_against_turned_tiles_with_one_extraction(turned_db, query, turn, monkeypatch):
    """The same photo turned a quarter (or 45° off every quarter) with the heading unknown: screened upright
    against turned tiles, it is found at the same rotation and tile as when the photo itself is turned, placed
    within metres of it and of the truth, and the photo is extracted once for all its screens."""
    q, image = query
    tile_ids = Retriever(turned_db, "xfeat-vlad", "cpu")(image, 10).tile_ids
    plain = Reranker(turned_db, "xfeat-lighterglue", "cpu", {"turned_tiles": False})
    if turn == "quarter":
        photo = np.ascontiguousarray(np.rot90(image, 1))
    else:  # 45° off north-up, from the photo's own turn against the map (it is not exactly north-up)
        H = plain(image, tile_ids, 1).candidates[0].H
        photo = turned(image, -45.0 - np.degrees(np.arctan2(H[1, 0], H[0, 0])))[0]
    fast = Reranker(turned_db, "xfeat-lighterglue", "cpu")
    assert plain.turns is None and fast.turns is not None and len(fast._turned) == len(turned_db.tiles)
    calls = []
    real = fast.extractor.extract
    monkeypatch.setattr(fast.extractor, "extract", lambda im, mask=None: calls.append(im.shape) or real(im, mask=mask))
    r0, b0, a0 = _place(turned_db, plain, photo, tile_ids)
    r1, b1, a1 = _place(turned_db, fast, photo, tile_ids)
    assert a0.localized and a1.localized, (a0.status, a1.status)
    assert (b1.tile_id, b1.rot_k) == (b0.tile_id, b0.rot_k) and b1.rot_k != 0
    # the upright photo for every screen; turned only for the matcher, when it ran
    assert len(calls) == len(r1.query) <= 1 + r1.n_verified and 0 in r1.query
    assert len(r0.query) > len(r1.query)  # without turned tiles the photo was turned for its screens too
    assert geo.geodesic_distance(a0.lat, a0.lon, a1.lat, a1.lon) < 5.0
    assert geo.geodesic_distance(q.lat, q.lon, a1.lat, a1.lon) < 25.0
    # later steps that need the photo at the candidate's rotation get it extracted then
    expected = len(calls) + (b1.rot_k not in r1.query)
    assert r1.query_at(b1.rot_k)["rot_k"] == b1.rot_k and len(calls) == expected


def test_local_turns_without_a_reranker_is_refused_in_one_line(naip_map, tmp_path, capsys):
    from aeroloc.cli import main

    code = main(["build", str(naip_map), "--out", str(tmp_path / "db"), "--local-turns"])
    err = capsys.readouterr().err.strip()
    assert code != 0 and "--local-turns needs --local" in err and "\n" not in err
    assert not (tmp_path / "db").exists()  # refused before anything was built


def test_screens_of_an_unknown_heading_go_upright_on_the_probe_then_by_turn_score():
    """The probe's candidates upright first (a north-up photo settles there), then every (candidate, turn) the
    turned retrieval scored, best first; ties by retrieval rank; no pair twice, no exact-angle key."""
    from aeroloc.localization.cascade import Candidate, turn_score_pairs

    cands = [Candidate(t, i) for i, t in enumerate("abcd")]
    scores = {"a": {0: 0.5, 3: 0.9}, "b": {0: 0.7, 6: 0.9}, "c": {2: 0.95}, "d": {0: 0.4, 9: 1.0}}
    pairs = [(c.tile_id, k) for c, k in turn_score_pairs(cands[:2], cands, scores)]
    assert pairs == [("a", 0), ("b", 0), ("c", 2), ("a", 3), ("b", 6), ("d", 0)]
