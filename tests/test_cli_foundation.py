"""The foundation's commands as a user runs them (subprocesses): `aeroloc tiles` builds or fails with one
line and no traceback; `aeroloc evaluate` agrees exactly with the independent scorer in ../shared/tools."""

from __future__ import annotations

import csv
import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pyproj import Geod

from _mapfolders import build_seed_folder

BIN = Path(sys.executable).parent
AEROLOC = str(BIN / "aeroloc")
SCORER = Path(__file__).resolve().parents[2] / "shared" / "tools" / "score.py"


def run(*args, cwd=None):
    return subprocess.run([AEROLOC, *map(str, args)], capture_output=True, text=True, timeout=120, cwd=cwd)


# --- aeroloc tiles ------------------------------------------------------------------------------------------
def test_tiles_builds_a_database(tmp_path, naip_map):
    s = build_seed_folder(tmp_path / "seed", naip_map)
    out = tmp_path / "db"
    p = run("tiles", s.path, "--zoom", "2", "--overlap", "0.5", "--out", out, "--write-images")
    assert p.returncode == 0, p.stderr
    # the seed's raw tiles are 64 x 48 px, so zoom 2 cuts 32 x 24 px tiles (aero-vloc: raw size / zoom per axis),
    # step 16 x 12 on a 256 x 144 mosaic: 1 + ceil(224/16) = 15 columns, 1 + ceil(120/12) = 11 rows
    assert "165 tiles (11 rows x 15 cols) of 32x24 px" in p.stdout
    with open(out / "tiles.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 165 and all((out / r["path"]).is_file() for r in rows)
    assert {(r["width"], r["height"]) for r in rows} == {("32", "24")}
    again = run("tiles", s.path, "--zoom", "2", "--overlap", "0.5", "--out", out)
    assert again.returncode == 0 and "(cached)" in again.stdout


def _bad_inputs(tmp_path, naip_map):
    fake = tmp_path / "fake.tif"
    fake.write_text("not a raster")
    s = build_seed_folder(tmp_path / "seed", naip_map)
    lines = (s.path / "map_metadata.txt").read_text().splitlines()
    (s.path / "map_metadata.txt").write_text("\n".join(lines[:-1]) + "\n")  # 11 rows: not a grid
    return [
        ([tmp_path / "missing.tif"], "missing.tif"),
        ([fake], "fake.tif"),
        ([s.path], "map_metadata.txt"),
        ([naip_map, "--zoom", "0"], "zoom must be > 0"),
        ([naip_map, "--zoom", "-2"], "zoom must be > 0"),
        ([naip_map, "--overlap", "1"], "overlap must be in [0, 1)"),
        ([naip_map, "--overlap", "-0.5"], "overlap must be in [0, 1)"),
        ([naip_map, "--zoom", "0.2"], "larger than"),
        ([naip_map, "--tile-m", "20000"], "larger than"),
    ]


def test_tiles_bad_input_is_one_line_without_traceback(tmp_path, naip_map):
    for i, (args, needle) in enumerate(_bad_inputs(tmp_path, naip_map)):
        out = tmp_path / f"out{i}"
        p = run("tiles", *args, "--out", out)
        assert p.returncode != 0, args
        assert "Traceback" not in p.stderr, p.stderr
        lines = p.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("aeroloc tiles: error: "), p.stderr
        assert needle in lines[0], (needle, lines[0])
        assert not (out / "tiles.csv").exists()


def test_tiles_unparseable_number_is_an_argparse_error(tmp_path, naip_map):
    p = run("tiles", naip_map, "--zoom", "two", "--out", tmp_path / "o")
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert p.stderr.strip().splitlines()[-1].startswith("aeroloc tiles: error: argument --zoom")


# --- aeroloc evaluate vs ../shared/tools/score.py ----------------------------------------------------------
OFFSETS_M = [0.0, 3.0, 9.5, 12.0, 24.0, 30.0, 49.0, 75.0, 140.0, None]  # None: not localized


def _make_results(path, truth: list[tuple[str, float, float]], tiles_csv: Path, seed: int, drop: int = 3):
    """Results whose top tiles are sorted by distance from a noisy guess (so the truth tile is at varying
    ranks or absent) and whose positions are the truth moved by known offsets; every ``drop``-th query is
    missing from the file."""
    geod = Geod(ellps="WGS84")
    with open(tiles_csv, newline="") as f:
        tiles = list(csv.DictReader(f))
    ids = [t["tile"] for t in tiles]
    clat = np.array([(float(t["tl_lat"]) + float(t["br_lat"])) / 2 for t in tiles])
    clon = np.array([(float(t["tl_lon"]) + float(t["br_lon"])) / 2 for t in tiles])
    rng = np.random.default_rng(seed)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["name", "lat", "lon", "top_tiles"])
        for i, (name, lat, lon) in enumerate(truth):
            if i % drop == drop - 1:
                continue
            glon, glat, _ = geod.fwd(lon, lat, rng.uniform(0, 360), rng.uniform(0, 900))
            _, _, d = geod.inv(np.full(len(ids), glon), np.full(len(ids), glat), clon, clat)
            top = [ids[j] for j in np.argsort(d)[:20]]
            off = OFFSETS_M[i % len(OFFSETS_M)]
            if off is None:
                w.writerow([name, "", "", ";".join(top)])
            else:
                elon, elat, _ = geod.fwd(lon, lat, rng.uniform(0, 360), off)
                w.writerow([name, repr(float(elat)), repr(float(elon)), ";".join(top)])


def _score(results, truth_csv, db, map_path):
    p = subprocess.run(
        [str(BIN / "python"), str(SCORER), str(results), str(truth_csv), str(db), str(map_path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert p.returncode == 0, p.stderr
    text = p.stdout
    got = {f"vpr_recall@{k}": float(v) for k, v in re.findall(r"@(\d+): ([\d.]+)", text.split("Georef")[0])}
    got.update({f"georef_recall@{k}m": float(v) for k, v in re.findall(r"@([\d.]+)m: ([\d.]+)", text)})
    n, nl = map(int, re.search(r"queries: (\d+), not localized: (\d+)", text).groups())
    med, p90 = map(float, re.search(r"median ([\d.]+) m, p90 ([\d.]+) m", text).groups())
    return got, n, nl, med, p90


def _evaluate(results, truth_csv, db, tmp_path):
    out = tmp_path / "metrics.json"
    p = run("evaluate", results, "--truth", truth_csv, "--tiles", db, "--json", out)
    assert p.returncode == 0, p.stderr
    return json.loads(out.read_text())


def _assert_agree(ours, theirs):
    got, n, nl, med, p90 = theirs
    assert set(got) >= {"vpr_recall@1", "vpr_recall@5", "vpr_recall@10", "vpr_recall@20", "georef_recall@50m"}
    for k, v in got.items():
        assert f"{ours[k]:.3f}" == f"{v:.3f}", k
    assert ours["n_queries"] == n
    assert round(ours["not_localized"] * n) == nl
    assert f"{ours['median_error_m']:.2f}" == f"{med:.2f}" and f"{ours['p90_error_m']:.2f}" == f"{p90:.2f}"


def test_evaluate_agrees_with_independent_scorer_on_naip(tmp_path, naip_map, naip_dev):
    if not SCORER.is_file():
        pytest.skip(f"independent scorer not found at {SCORER}")
    db = tmp_path / "db"
    p = run("tiles", naip_map, "--zoom", "1.5", "--overlap", "0.5", "--out", db)
    assert p.returncode == 0, p.stderr
    with open(naip_dev, newline="") as f:
        truth = [(r["name"], float(r["lat"]), float(r["lon"])) for r in csv.DictReader(f)]
    results = tmp_path / "results.csv"
    _make_results(results, truth, db / "tiles.csv", seed=7)
    ours = _evaluate(results, naip_dev, db, tmp_path)
    theirs = _score(results, naip_dev, db, naip_map)
    _assert_agree(ours, theirs)
    # the case is not degenerate: partial recall, some misses, some not localized
    assert 0.05 < ours["vpr_recall@1"] < ours["vpr_recall@20"] < 1
    assert 0 < ours["georef_recall@10m"] < ours["georef_recall@100m"] < 1
    assert ours["missing_results"] == 40 and ours["not_localized"] > 40 / 120


def test_evaluate_agrees_with_independent_scorer_on_seed_folder(tmp_path, naip_map):
    if not SCORER.is_file():
        pytest.skip(f"independent scorer not found at {SCORER}")
    s = build_seed_folder(tmp_path / "seed", naip_map)
    db = tmp_path / "db"
    assert run("tiles", s.path, "--zoom", "3", "--overlap", "0.25", "--out", db).returncode == 0
    # truth: random points over the mosaic and a margin around it (outside points are never a VPR hit)
    (tl_lat, tl_lon, *_), (*_, br_lat, br_lon) = s.corners[(0, 0)], s.corners[(2, 3)]
    rng = np.random.default_rng(11)
    lat = rng.uniform(br_lat - 0.001, tl_lat + 0.001, 60)
    lon = rng.uniform(tl_lon - 0.001, br_lon + 0.001, 60)
    truth = [(f"p{i:02d}.jpg", float(a), float(b)) for i, (a, b) in enumerate(zip(lat, lon))]
    truth_csv = tmp_path / "truth.csv"
    truth_csv.write_text("name,lat,lon\n" + "".join(f"{n},{a!r},{b!r}\n" for n, a, b in truth))
    results = tmp_path / "results.csv"
    _make_results(results, truth, db / "tiles.csv", seed=5, drop=5)
    ours = _evaluate(results, truth_csv, db, tmp_path)
    _assert_agree(ours, _score(results, truth_csv, db, s.path))
    assert 0 < ours["vpr_recall@1"] < 1 and not math.isnan(ours["median_error_m"])
