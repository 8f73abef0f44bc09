"""Turned descriptors (``aeroloc build --global-turns``): every tile also described at the seven other turns, a
photo of unknown heading searched upright against them, its upright and turned rankings interleaved. On real NAIP
tiles (a copy of ``naip_db``)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from aeroloc.core.frames import TILE_TURNS, inverse_turn, rotation_angle
from aeroloc.localization.localizer import Localizer
from aeroloc.localization.options import LocalizeOptions
from aeroloc.maps.windows import turned_windows
from aeroloc.retrieval.database import TURNS_DIR, Database, build_global
from aeroloc.retrieval.descriptors import describe_image
from aeroloc.retrieval.retriever import TURNED_LEAD, Retriever

METHOD = "xfeat-vlad"  # what naip_db was built with


@pytest.fixture(scope="module")
def turned_db(naip_db, naip_map, tmp_path_factory):
    """naip_db copied, then ``aeroloc build --global-turns`` on it (the upright descriptors are reused)."""
    import contextlib
    import io

    from aeroloc.cli import main

    folder = tmp_path_factory.mktemp("turned-descriptors") / "db"
    shutil.copytree(naip_db, folder)
    out = io.StringIO()
    argv = ["build", str(naip_map), "--zoom", "1", "--overlap", "0.5", "--out", str(folder), "--method", METHOD]
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        assert main([*argv, "--global-turns", "--device", "cpu"]) == 0
    db = Database(folder)
    assert f"turned descriptors {METHOD}: {len(db.tiles) * 7} ({len(db.tiles)} tiles x 7 turns)" in out.getvalue()
    assert f"descriptors {METHOD}: cached" in out.getvalue()
    return db


def _turns_dir(db):
    return db.global_dir(METHOD)[1] / TURNS_DIR


def test_a_quarter_turned_window_is_the_tile_turned_and_every_view_has_the_tiles_size(naip_db):
    db = Database(naip_db)
    m = db.source.map()
    inside = [
        t for t in db.tiles if t.col > 0 and t.row > 0 and t.col + t.width < m.width and t.row + t.height < m.height
    ]
    assert inside
    for t in inside[:3]:
        views = list(turned_windows(m, [t], [rotation_angle(k) for k in range(8)]))
        up = db.tile_image(t.id)
        for k in range(4):  # exact: the same pixels, turned
            assert np.array_equal(views[k], np.rot90(up, k)), (t.id, k)
        assert all(v.shape == up.shape for v in views)
    corner = db.tiles[0]  # at the map's top-left: a diagonal view reaches beyond the map, which reads black
    diag = next(turned_windows(m, [corner], [45.0]))
    assert (diag.reshape(-1, 3).max(1) == 0).any()


def test_turned_windows_of_the_seeds_rectangular_raw_tiles_keep_their_size(naip_map, tmp_path):
    """The seed's map format: a tile folder of 1280 x 1230 raw tiles; at zoom 1 a tile is a raw tile."""
    from _mapfolders import build_seed_folder
    from aeroloc.maps.sources import open_map
    from aeroloc.maps.tiling import TileGrid

    seed = build_seed_folder(tmp_path / "seed", naip_map, 2, 2, 1280, 1230, res_m=1.4663, upsample=5)
    m = open_map(seed.path)
    tiles = list(TileGrid(m, 1.0, 0.0))
    assert {(t.width, t.height) for t in tiles} == {(1280, 1230)}
    views = list(turned_windows(m, tiles[:1], [rotation_angle(k) for k in TILE_TURNS]))
    assert all(v.shape == (1230, 1280, 3) for v in views)
    up = m.read(tiles[0].col, tiles[0].row, 1280, 1230)[0]
    assert np.array_equal(views[TILE_TURNS.index(2)], np.rot90(up, 2))  # a half turn of a rectangle is exact


def test_the_turned_store_holds_every_tile_at_the_seven_turns_in_order(turned_db):
    store = np.load(_turns_dir(turned_db) / "descriptors.npy")
    n = len(turned_db.tiles)
    assert store.shape[0] == n * len(TILE_TURNS)
    index = turned_db.load_turned(METHOD)
    assert index is not None and index.ntotal == n * len(TILE_TURNS)
    ret = Retriever(turned_db, METHOD)
    m = turned_db.source.map()
    for i, k in ((3, 1), (17, 5), (n - 1, 7)):  # row i * 7 + k - 1 is tile i at rotation index k
        view = next(turned_windows(m, [turned_db.tiles[i]], [rotation_angle(k)]))
        d = describe_image(ret.model, view, "cpu")[0][0]
        row = store[i * len(TILE_TURNS) + k - 1].astype(np.float32)
        assert float(row @ d) > 0.99, (i, k)


def test_a_finished_turned_build_is_reused_and_an_interrupted_one_resumes_to_the_same_bytes(turned_db):
    folder = _turns_dir(turned_db)
    before = (folder / "descriptors.npy").read_bytes()
    stamp = (folder / "descriptors.npy").stat().st_mtime_ns
    build_global(turned_db, METHOD, progress=False, turns=True)
    assert (folder / "descriptors.npy").stat().st_mtime_ns == stamp  # nothing redone
    # interrupted: the store never finished and its last shard never written
    (folder / "meta.json").unlink()
    (folder / "descriptors.npy").unlink()
    shard = sorted((folder / "shards").glob("*.npy"))[-1]
    shard.unlink()
    shard.with_suffix(".done").unlink()
    assert turned_db.load_turned(METHOD) is None  # an unfinished store is not searched
    build_global(turned_db, METHOD, progress=False, turns=True)
    assert (folder / "descriptors.npy").read_bytes() == before


def test_a_turned_copy_of_a_tile_is_retrieved_and_the_upright_top_1_stays_first(turned_db):
    ret = Retriever(turned_db, METHOD)
    m = turned_db.source.map()
    t = turned_db.tiles[17]
    photo = next(turned_windows(m, [t], [rotation_angle(5)]))  # the tile as a camera turned 135° sees it
    upright = ret(photo, 10)
    fused = ret(photo, 10, turned=True)
    assert fused.tile_ids[0] == upright.tile_ids[0]  # a north-up photo's best upright match keeps its place
    assert t.id in fused.tile_ids[:2]
    assert fused.scores[fused.tile_ids.index(t.id)] > 0.99  # its turned view is the photo
    # the union of both top-10s, no repeats: the turned tiles add candidates and never drop an upright one,
    # and only the turned ranking's lead comes before the upright top-10's last tile
    assert len(fused.tile_ids) == len(set(fused.tile_ids)) <= 20 and set(upright.tile_ids) <= set(fused.tile_ids)
    last_upright = max(fused.tile_ids.index(u) for u in upright.tile_ids)
    assert sum(f not in upright.tile_ids for f in fused.tile_ids[:last_upright]) <= TURNED_LEAD
    desc, _ = ret.describe(photo)
    assert ret.fuse_turned(desc, upright, 10).tile_ids == fused.tile_ids[:10]  # cut at N: its first N
    plain = Retriever(Database(turned_db.folder), METHOD)
    assert plain(photo, 10).tile_ids == upright.tile_ids  # ``turned`` off: the upright ranking as before


def test_the_turned_retrieval_scores_each_tile_at_each_turn_it_found_it_at(turned_db):
    """A photo of tile 17 taken by a camera turned 135°: its turned retrieval scores that tile best at the rotation
    that sets the photo upright (what the re-ranker screens first), and every upright score is rotation 0's."""
    ret = Retriever(turned_db, METHOD)
    t = turned_db.tiles[17]
    photo = next(turned_windows(turned_db.source.map(), [t], [rotation_angle(5)]))
    upright, fused = ret(photo, 10), ret(photo, 10, turned=True)
    scores = fused.turn_scores[t.id]
    assert max(scores, key=scores.get) == inverse_turn(5) and scores[inverse_turn(5)] > 0.99, scores
    assert all(fused.turn_scores[u][0] == s for u, s in zip(upright.tile_ids, upright.scores))
    assert set(fused.turn_scores) == set(fused.tile_ids) and upright.turn_scores is None


def test_the_localizer_fuses_only_when_the_heading_is_unknown(turned_db):
    m = turned_db.source.map()
    photo = next(turned_windows(m, [turned_db.tiles[17]], [rotation_angle(5)]))
    ret = Retriever(turned_db, METHOD)
    unknown = Localizer(turned_db, LocalizeOptions(method=METHOD, rerank=None, top_n=10))("p", photo)
    assert unknown.retrieved == ret(photo, 10, turned=True).tile_ids
    north = Localizer(turned_db, LocalizeOptions(method=METHOD, rerank=None, top_n=10, north_up=True))("p", photo)
    assert north.retrieved == ret(photo, 10).tile_ids


def test_aeroloc_retrieve_interleaves_the_turned_ranking_unless_north_up(turned_db, tmp_path):
    import csv

    import cv2

    from aeroloc.cli import main

    t = turned_db.tiles[17]
    photo = next(turned_windows(turned_db.source.map(), [t], [rotation_angle(5)]))
    cv2.imwrite(str(tmp_path / "p.png"), cv2.cvtColor(photo, cv2.COLOR_RGB2BGR))
    (tmp_path / "queries.csv").write_text("name,lat,lon\np.png,0,0\n")
    ret = Retriever(turned_db, METHOD)
    desc, _ = ret.describe(photo)
    for flags, want in (([], ret.fuse_turned(desc, ret(photo, 10), 10)), (["--north-up"], ret(photo, 10))):
        out = tmp_path / f"r{len(flags)}.csv"
        assert main(["retrieve", str(turned_db.folder), str(tmp_path / "queries.csv"), "--out", str(out)] + flags) == 0
        row = next(csv.DictReader(out.open()))
        assert row["top_tiles"].split(";") == want.tile_ids
    assert t.id in ret(photo, 10, turned=True).tile_ids[:2]


def test_aeroloc_retrieve_refuses_north_up_with_a_rotation_search_in_one_line(turned_db, tmp_path, capsys):
    from aeroloc.cli import main

    args = ["retrieve", str(turned_db.folder), str(tmp_path / "none.csv"), "--out", str(tmp_path / "r.csv")]
    assert main([*args, "--north-up", "--rotations", "4"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--north-up and --rotations > 1 contradict" in err
    assert not (tmp_path / "r.csv").exists()
