"""The tiles beside a retrieved one (aeroloc.localization.neighbours): the ring of 8 on real tile grids, and a
cross-season NAIP photo placed through a neighbour of the tile retrieval gave when its own tile was not given."""

from __future__ import annotations

import pytest

from aeroloc.bench.metrics import tile_contains
from aeroloc.core import geo
from aeroloc.core.images import read_image
from aeroloc.core.queries import load_queries
from aeroloc.localization.neighbours import Neighbourhood, neighbour_candidates
from aeroloc.maps.sources import open_map
from aeroloc.maps.tiling import TileGrid
from aeroloc.retrieval.database import Database


def _centre(t):
    return t.col + t.width / 2, t.row + t.height / 2


@pytest.mark.parametrize("overlap", [0.0, 0.5])
def test_an_inner_tile_has_the_ring_of_eight_beside_it_and_a_corner_tile_three(naip_map, overlap):
    grid = TileGrid(open_map(naip_map), 3.0, overlap)  # 85 px tiles: a grid with inner tiles at both overlaps
    tiles = list(grid)
    near = Neighbourhood(tiles)
    inner = [
        t
        for t in tiles
        if 2 <= t.col // grid.step_x <= len(grid.cols) - 3 and 2 <= t.row // grid.step_y <= len(grid.rows) - 3
    ]
    assert inner
    t = inner[0]
    ring = near.around(t)
    assert len(ring) == 8 and t not in ring
    steps = {
        (round((_centre(n)[0] - _centre(t)[0]) / grid.step_x), round((_centre(n)[1] - _centre(t)[1]) / grid.step_y))
        for n in ring
    }
    assert steps == {(i, j) for i in (-1, 0, 1) for j in (-1, 0, 1)} - {(0, 0)}
    # the map's corner tile: its three nearest are the ones right, below and diagonal, one step away
    corner = min(tiles, key=lambda x: (x.col, x.row))
    first = near.around(corner)[:3]
    steps = {
        (
            round((_centre(n)[0] - _centre(corner)[0]) / grid.step_x),
            round((_centre(n)[1] - _centre(corner)[1]) / grid.step_y),
        )
        for n in first
    }
    assert steps == {(1, 0), (0, 1), (1, 1)}


def _holders_by_scan(tiles, x, y):
    """The tiles holding (x, y), by a scan of every tile: what the dense fixes' lookup was before the buckets."""
    inside = [t for t in tiles if t.col <= x <= t.col + t.width and t.row <= y <= t.row + t.height]
    return sorted(inside, key=lambda t: (_centre(t)[0] - x) ** 2 + (_centre(t)[1] - y) ** 2)


@pytest.mark.parametrize("zoom,overlap", [(1.0, 0.5), (3.0, 0.0), (0.5, 0.75)])
def test_the_tiles_holding_a_point_are_those_a_scan_of_every_tile_finds(naip_map, zoom, overlap):
    """The buckets' answer for a dense fix's position is the scan's, in the same order (nearest centre first,
    ties in the tiles' order), on real NAIP grids, on points anywhere on and just off the map, on tile edges,
    and on a mixed list of rectangular tiles of two sizes (a database holding two zooms of 1280x1230 raw tiles)."""
    from types import SimpleNamespace

    import numpy as np

    m = open_map(naip_map)
    tiles = list(TileGrid(m, zoom, overlap))
    rect = [
        SimpleNamespace(id=f"{w}-{c}-{r}", col=c, row=r, width=w, height=h)
        for w, h in ((128, 123), (64, 61))
        for c in range(0, 512, w // 2)
        for r in range(0, 492, h // 2)
    ]
    rng = np.random.default_rng(0)
    for group, (width, height) in ((tiles, (m.width, m.height)), (rect, (512, 492))):
        near = Neighbourhood(group)
        points = [(x, y) for x, y in rng.uniform([-20, -20], [width + 20, height + 20], (300, 2))]
        points += [(t.col, t.row) for t in group[:20]] + [(t.col + t.width, t.row + t.height / 2) for t in group[:20]]
        holders = 0
        for x, y in points:
            got = near.containing(x, y)
            assert [t.id for t in got] == [t.id for t in _holders_by_scan(group, x, y)]
            holders += len(got)
        assert holders >= len(points)  # most points lie in some tile: the comparison is not of empty lists


def test_candidates_skip_what_was_tried_and_keep_the_seeds_order(naip_db):
    db = Database(naip_db)
    near = Neighbourhood(db.tiles)
    a, b = db.tiles[7], db.tiles[20]
    got = neighbour_candidates(near, db.by_id, [a.id, b.id], {a.id, b.id})
    ring_a = [t.id for t in near.around(a) if t.id != b.id]
    assert got[: len(ring_a)] == ring_a  # the first seed's ring first, nearest first
    assert a.id not in got and b.id not in got and len(got) == len(set(got))


@pytest.mark.slow
def test_a_photo_is_placed_through_the_neighbours_of_a_tile_that_does_not_hold_it(naip_db, naip_dev):
    """A 2012 photo (the pipeline tests' GOOD one: 350-450 inliers on its own tile) given only a neighbour of its
    tile, one that does not contain its centre, as the retrieved list: the stage re-ranks that tile's ring,
    which holds the photo's tile, and places it as the full pipeline does; switched off, nothing places it."""
    from aeroloc.localization.localizer import Localizer
    from aeroloc.localization.options import LocalizeOptions
    from aeroloc.localization.results import Localization

    db = Database(naip_db)
    q = next(q for q in load_queries(naip_dev) if q.name == "naip_20120731_n_018.jpg")

    def off_centre(t):  # the photo centre's distance from the tile's centre, tile px
        x, y = t.latlon_to_pixel(q.lat, q.lon)
        return (x - t.width / 2) ** 2 + (y - t.height / 2) ** 2

    own = min((t for t in db.tiles if tile_contains(t, q.lat, q.lon)), key=off_centre)
    near = Neighbourhood(db.tiles)
    seed = next(t for t in near.around(own) if not tile_contains(t, q.lat, q.lon))
    image = read_image(q.path)
    for on in (True, False):
        loc = Localizer(db, LocalizeOptions(method="xfeat-vlad", rerank="xfeat-lighterglue", neighbours=on), "cpu")
        out = Localization(q.name, retrieved=[seed.id], times_ms={})
        loc._neighbour_fix(image, [seed.id], [seed.id], 1, None, out)
        if on:
            assert out.status.startswith("localized"), out.status
            assert geo.geodesic_distance(q.lat, q.lon, out.lat, out.lon) < 25.0
            assert tile_contains(db.by_id[out.top_tiles[0]], q.lat, q.lon)
        else:
            assert not out.status.startswith("localized")


@pytest.mark.slow
def test_only_queries_without_priors_reach_the_neighbours(naip_db, data_dir, monkeypatch):
    """A photo from another city fails every stage against the NAIP map. Without priors it reaches the
    neighbour stage before the sweep; with a heading and ground-resolution prior it goes from the cascade
    straight to the sweep narrowed to them (the stage before it cost flight re-localizations their fix)."""
    from aeroloc.core.priors import Priors
    from aeroloc.localization.localizer import Localizer
    from aeroloc.localization.options import LocalizeOptions

    db = Database(naip_db)
    loc = Localizer(db, LocalizeOptions(method="xfeat-vlad", rerank="xfeat-lighterglue"), "cpu")
    image = read_image(data_dir / "toledo" / "photos" / "1JI_0064.JPG")
    calls = []
    real = Localizer._neighbour_fix

    def counted(self, *a, **k):
        calls.append(a[1])  # the retrieved tiles it was seeded from
        return real(self, *a, **k)

    monkeypatch.setattr(Localizer, "_neighbour_fix", counted)
    res = loc("toledo", image, top_n=5)
    assert res.status.startswith("not localized") and len(calls) == 1 and calls[0][:3] == res.retrieved[:3]
    calls.clear()
    res = loc("toledo", image, top_n=5, priors=Priors(gsd_m=5.0, heading_deg=0.0, heading_tol_deg=15.0))
    assert res.status.startswith("not localized") and calls == []
