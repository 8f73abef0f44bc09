"""metrics.py and `aeroloc evaluate` on hand-made tiles and results: inclusive boundaries, out-of-map queries,
not-localized and missing rows, recall fractions and error statistics computed by hand."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
from affine import Affine
from pyproj import Geod, Transformer

from aeroloc.bench.metrics import evaluate, first_hit, tile_contains
from aeroloc.cli import main
from aeroloc.core.errors import AerolocError
from aeroloc.core.queries import Query
from aeroloc.localization.results import Localization, read_localizations
from aeroloc.maps.tiling import CSV_COLUMNS, Tile, tile_row

UTM = "EPSG:26914"
_to_ll = Transformer.from_crs(UTM, "EPSG:4326", always_xy=True)
_geod = Geod(ellps="WGS84")


def utm_latlon(e, n):
    lon, lat = _to_ll.transform(e, n)
    return lat, lon


def _tile(tid, e0, n0, size=100):
    """A size x size tile of 5 m pixels whose top-left corner is (e0, n0) in UTM 14N."""
    return Tile(tid, 0, 0, size, size, Affine(5.0, 0.0, e0, 0.0, -5.0, n0), UTM, f"images/{tid}.png")


# A | B   (each 500 m x 500 m)
# C
A = _tile("A", 490000.0, 5210000.0)
B = _tile("B", 490500.0, 5210000.0)
C = _tile("C", 490000.0, 5209500.0)
TILES = [A, B, C]

TRUTH_UTM = {
    "q0": (490260.0, 5209750.0),  # in A, 10 m east of its centre
    "q1": (490100.0, 5209900.0),  # in A only
    "q2": (490300.0, 5209200.0),  # in C only
    "q3": (490500.0, 5209750.0),  # exactly on the A|B edge
    "q4": (490500.0, 5209500.0),  # the corner shared by A, B and C
    "q5": (490200.0, 5209800.0),  # in A; missing from the results
    "q6": (489990.0, 5209750.0),  # 10 m west of A: outside every tile
}
TRUTH = {k: utm_latlon(*v) for k, v in TRUTH_UTM.items()}
# estimate = truth moved this many metres (geodesic) towards azimuth 30°; None = not localized
ERRORS = {"q0": 5.0, "q1": 20.0, "q2": 40.0, "q3": 60.0, "q4": None, "q6": 150.0}
TOPS = {"q0": ["A"], "q1": ["B", "A"], "q2": ["B"], "q3": ["B"], "q4": ["C"], "q6": ["A", "B", "C"]}


def _results():
    out = []
    for name, err in ERRORS.items():
        lat, lon = TRUTH[name]
        if err is None:
            out.append(Localization(name, math.nan, math.nan, top_tiles=list(TOPS[name])))
        else:
            lon2, lat2, _ = _geod.fwd(lon, lat, 30.0, err)
            out.append(Localization(name, lat2, lon2, top_tiles=list(TOPS[name])))
    out.append(Localization("not_a_query", 47.0, -99.0, top_tiles=["A"]))  # ignored: no ground truth for it
    return out


def _queries():
    return [Query(n, None, lat, lon) for n, (lat, lon) in TRUTH.items()]


def test_shared_boundaries_count_for_both_tiles():
    lat, lon = TRUTH["q3"]
    assert tile_contains(A, lat, lon) and tile_contains(B, lat, lon) and not tile_contains(C, lat, lon)
    lat, lon = TRUTH["q4"]
    assert all(tile_contains(t, lat, lon) for t in TILES)
    tiles = {t.id: t for t in TILES}
    assert first_hit(("A",), tiles, *TRUTH["q3"]) == 0 and first_hit(("B",), tiles, *TRUTH["q3"]) == 0
    assert first_hit(("C", "B"), tiles, *TRUTH["q3"]) == 1


def test_a_millimetre_outside_is_outside():
    for e, n in [
        (490000.0 - 1e-3, 5209750.0),
        (490500.0 + 1e-3, 5209750.0),
        (490250.0, 5210000.0 + 1e-3),
        (490250.0, 5209500.0 - 1e-3),
    ]:
        assert not tile_contains(A, *utm_latlon(e, n))
    tiles = {t.id: t for t in TILES}
    assert first_hit(("A", "B", "C", "unknown"), tiles, *TRUTH["q6"]) is None


def test_evaluate_on_hand_made_cases():
    m = evaluate(_results(), _queries(), TILES, thresholds=(10, 25, 50, 100, 300))
    n = 7
    assert m["n_queries"] == n
    # VPR: top-1 hits are q0 (A), q3 (B, on the edge), q4 (C, on the corner; not localized does not matter);
    # q1 is found at rank 2; q2 (wrong tile), q5 (missing) and q6 (outside the map) never.
    assert m["vpr_recall@1"] == pytest.approx(3 / n)
    assert m["vpr_recall@5"] == pytest.approx(4 / n)
    assert m["vpr_recall@10"] == pytest.approx(4 / n)
    # georeference: errors 5, 20, 40, 60, 150 m; q4 not localized, q5 missing
    assert m["georef_recall@10m"] == pytest.approx(1 / n)
    assert m["georef_recall@25m"] == pytest.approx(2 / n)
    assert m["georef_recall@50m"] == pytest.approx(3 / n)
    assert m["georef_recall@100m"] == pytest.approx(4 / n)
    assert m["georef_recall@300m"] == pytest.approx(5 / n)
    assert m["median_error_m"] == pytest.approx(40.0, abs=1e-6)
    assert m["p90_error_m"] == pytest.approx(60 + 0.6 * 90, abs=1e-6)  # linear interpolation at index 3.6
    assert m["not_localized"] == pytest.approx(2 / n)
    assert m["missing_results"] == 1
    # distance recall: top-1 centre within 25 m only for q0 (10 m); within 300 m also q3 (B centre 250 m away)
    # and q6 (A centre 260 m away); q4's C centre is 354 m away.
    assert m["dist_recall@1@25m"] == pytest.approx(1 / n)
    assert m["dist_recall@1@300m"] == pytest.approx(3 / n)
    per = {p["name"]: p for p in m["per_query"]}
    assert per["q1"]["vpr_rank"] == 1 and per["q6"]["vpr_rank"] is None and per["q5"]["error_m"] == math.inf
    for k, v in m.items():
        if "recall" in k or k == "not_localized":
            assert 0 <= v <= 1, k


def test_all_missing_and_no_tiles():
    m = evaluate([], _queries(), None)
    assert not any(k.startswith("vpr_recall") for k in m)
    assert m["georef_recall@50m"] == 0 and m["not_localized"] == 1 and m["median_error_m"] is None
    with pytest.raises(AerolocError, match="ground-truth"):
        evaluate([], [Query("x", None)], TILES)


def test_recall_keys_follow_the_list_length():
    res = [Localization("q0", math.nan, math.nan, top_tiles=["B"] * 11 + ["A"])]
    m = evaluate(res, _queries(), TILES)
    assert m["vpr_recall@10"] == 0 and m["vpr_recall@12"] == pytest.approx(1 / 7)


# --- files and the CLI -------------------------------------------------------------------------------------
def _write_case(tmp_path):
    db = tmp_path / "db"
    db.mkdir()
    with open(db / "tiles.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=CSV_COLUMNS)
        w.writeheader()
        w.writerows(tile_row(t) for t in TILES)
    with open(tmp_path / "truth.csv", "w", newline="") as f:
        f.write("name,lat,lon\n")
        for name, (lat, lon) in TRUTH.items():
            f.write(f"{name},{lat!r},{lon!r}\n")
    with open(tmp_path / "results.csv", "w", newline="") as f:
        f.write("name,lat,lon,top_tiles\n")
        for r in _results():
            lat = "" if math.isnan(r.lat) else repr(r.lat)
            lon = "" if math.isnan(r.lon) else repr(r.lon)
            f.write(f"{r.name},{lat},{lon},{';'.join(r.top_tiles)}\n")
    return db


def test_read_localizations(tmp_path):
    _write_case(tmp_path)
    res = {r.name: r for r in read_localizations(tmp_path / "results.csv")}
    assert res["q1"].top_tiles == ["B", "A"] and not res["q4"].localized and res["q0"].localized
    (tmp_path / "bad.csv").write_text("name,lat\nq0,1\n")
    with pytest.raises(AerolocError, match=r"bad.csv: missing columns \['lon'\]"):
        read_localizations(tmp_path / "bad.csv")
    (tmp_path / "bad2.csv").write_text("name,lat,lon\nq0,47.0,west\n")
    with pytest.raises(AerolocError, match=r"bad2.csv:2"):
        read_localizations(tmp_path / "bad2.csv")
    with pytest.raises(AerolocError, match=r"none\.csv"):
        read_localizations(tmp_path / "none.csv")


def test_cli_evaluate_writes_the_documented_json(tmp_path, capsys):
    db = _write_case(tmp_path)
    out = tmp_path / "m" / "metrics.json"
    rc = main(
        [
            "evaluate",
            str(tmp_path / "results.csv"),
            "--truth",
            str(tmp_path / "truth.csv"),
            "--tiles",
            str(db),
            "--json",
            str(out),
        ]
    )
    assert rc == 0
    m = json.loads(out.read_text())
    for key in (
        "vpr_recall@1",
        "vpr_recall@5",
        "vpr_recall@10",
        "georef_recall@10m",
        "georef_recall@25m",
        "georef_recall@50m",
        "georef_recall@100m",
        "median_error_m",
        "not_localized",
    ):
        assert key in m, key
    assert m["vpr_recall@1"] == pytest.approx(3 / 7) and m["georef_recall@50m"] == pytest.approx(3 / 7)
    assert m["median_error_m"] == pytest.approx(40.0, abs=1e-6) and m["not_localized"] == pytest.approx(2 / 7)
    table = capsys.readouterr().out
    assert "vpr_recall@1" in table and "georef_recall@50m" in table
    # other thresholds
    rc = main(
        [
            "evaluate",
            str(tmp_path / "results.csv"),
            "--truth",
            str(tmp_path / "truth.csv"),
            "--tiles",
            str(db),
            "--thresholds",
            "30,300",
            "--json",
            str(out),
        ]
    )
    m = json.loads(out.read_text())
    assert rc == 0 and m["georef_recall@30m"] == pytest.approx(2 / 7) and "georef_recall@50m" not in m
    assert np.isclose(m["georef_recall@300m"], 5 / 7)


@pytest.mark.parametrize(
    "args,match",
    [
        (["--thresholds", "10,abc"], "--thresholds"),
        (["--thresholds", "-5"], "positive"),
        (["--tiles", "NOWHERE"], "tiles.csv"),
    ],
)
def test_cli_evaluate_errors(tmp_path, capsys, args, match):
    db = _write_case(tmp_path)
    argv = ["evaluate", str(tmp_path / "results.csv"), "--truth", str(tmp_path / "truth.csv"), "--tiles", str(db)]
    if "--tiles" in args:
        argv = argv[:-2]
        args = ["--tiles", str(tmp_path / args[1])]
    rc = main(argv + args)
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("aeroloc evaluate: error: ") and match in err
    assert len(err.strip().splitlines()) == 1
