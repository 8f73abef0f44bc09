"""queries.py: the three query-set shapes on real data and hand-made files; bad files are AerolocErrors; truth
and priors kept apart (the priors themselves: test_priors.py)."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest
from PIL import Image, TiffImagePlugin

from aeroloc.core.errors import AerolocError
from aeroloc.core.queries import exif_gps, load_queries


def _csv_rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_naip_csv_with_images_in_queries_folder(naip_dev):
    qs = load_queries(naip_dev)
    rows = _csv_rows(naip_dev)
    assert len(qs) == len(rows) == 120
    for q, r in zip(qs, rows):
        assert q.name == r["name"] and q.path == naip_dev.parent / "queries" / r["name"] and q.path.is_file()
        assert (q.lat, q.lon) == (float(r["lat"]), float(r["lon"]))
        assert q.heading_deg == float(r["heading_deg"]) and q.alt_m is None and q.has_truth
        assert q.extra["footprint_m"] == r["footprint_m"] and q.extra["date"] == r["date"]
    # the folder holding queries.csv is the same query set
    assert [(q.name, q.lat, q.lon) for q in load_queries(naip_dev.parent)] == [(q.name, q.lat, q.lon) for q in qs]


def test_truth_is_kept_apart_from_priors(naip_dev, toledo_queries):
    qs = load_queries(naip_dev)
    rows = _csv_rows(naip_dev)
    for i, (q, r) in enumerate(zip(qs, rows)):
        assert q.truth_heading_deg == q.heading_deg == float(r["heading_deg"]) and q.truth_gsd_m == 5.0
        assert not q.priors.known and q.origin == f"{naip_dev}:{i + 2}"  # generated set: no truth as prior
    assert all(q.priors.heading_deg == q.truth_heading_deg % 360 for q in load_queries(naip_dev, priors="exact"))
    # Toledo's alt_m is the GPS altitude above sea level: kept, never a height above ground
    assert all(q.alt_m and q.priors.alt_agl_m is None and q.priors.gsd_m is None for q in load_queries(toledo_queries))


def test_seed_queries_txt_priors_from_exif(tmp_path):
    exif = Image.Exif()
    exif[0x8769] = {0xA405: 24}
    (tmp_path / "queries").mkdir()
    Image.new("RGB", (64, 48)).save(tmp_path / "queries" / "q0.jpg", exif=exif)
    (tmp_path / "queries.txt").write_text("filename lon lat\nq0.jpg -99.15 47.02\n")
    (q,) = load_queries(tmp_path)
    assert q.priors.hfov_deg == pytest.approx(2 * math.degrees(math.atan(36 / 48))) and q.priors.width_px == 64
    assert q.priors.gsd_m is None and q.origin.endswith("queries.txt:2")
    assert load_queries(tmp_path, priors="none")[0].priors.hfov_deg is None


def test_toledo_csv_with_images_in_photos_folder(toledo_queries):
    qs = load_queries(toledo_queries)
    rows = _csv_rows(toledo_queries)
    assert len(qs) == len(rows) == 57
    assert all(q.path.parent == toledo_queries.parent / "photos" and q.path.is_file() for q in qs)
    assert [q.alt_m for q in qs] == [float(r["alt_m"]) for r in rows]
    assert qs[0].heading_deg is None and qs[0].extra["camera"] == rows[0]["camera"]


def test_exif_gps_folder_matches_the_csv(toledo_queries):
    qs = load_queries(toledo_queries.parent / "photos")
    ref = {r["name"]: r for r in _csv_rows(toledo_queries)}
    assert len(qs) == 57 and {q.name for q in qs} == set(ref)
    for q in qs:
        assert q.lat == pytest.approx(float(ref[q.name]["lat"]), abs=1e-6)
        assert q.lon == pytest.approx(float(ref[q.name]["lon"]), abs=1e-6)  # west: negative
        assert q.alt_m == pytest.approx(float(ref[q.name]["alt_m"]), abs=0.05)


def _write_image(path, gps=None):
    path.parent.mkdir(parents=True, exist_ok=True)
    exif = Image.Exif()
    if gps:
        exif[0x8825] = gps
    Image.new("RGB", (8, 8), (10, 20, 30)).save(path, exif=exif)


def test_exif_southern_eastern_hemisphere_and_no_gps(tmp_path):
    # 33° 51' 21.6" S, 151° 12' 36" E = (-33.856, 151.21); altitude ref 1 = below sea level
    R = TiffImagePlugin.IFDRational
    _write_image(
        tmp_path / "a.jpg",
        {1: "S", 2: (R(33), R(51), R(216, 10)), 3: "E", 4: (R(151), R(12), R(36)), 5: b"\x01", 6: R(125, 10)},
    )
    _write_image(tmp_path / "b.jpg")
    lat, lon, alt = exif_gps(tmp_path / "a.jpg")
    assert (lat, lon, alt) == pytest.approx((-33.856, 151.21, -12.5), abs=1e-9)
    assert exif_gps(tmp_path / "b.jpg") is None
    qs = load_queries(tmp_path)
    assert [q.name for q in qs] == ["a.jpg", "b.jpg"]
    assert qs[0].has_truth and not qs[1].has_truth and math.isnan(qs[1].lat)


def test_seed_queries_txt_is_longitude_first(tmp_path):
    for name in ("q0.png", "q1.png"):
        _write_image(tmp_path / "queries" / name)
    (tmp_path / "queries.txt").write_text("filename lon lat\nq0.png -99.15 47.02\n\nq1.png 8.5417 47.3769\n")
    qs = load_queries(tmp_path / "queries.txt")
    assert [(q.name, q.lat, q.lon) for q in qs] == [("q0.png", 47.02, -99.15), ("q1.png", 47.3769, 8.5417)]
    assert qs[0].path == tmp_path / "queries" / "q0.png"
    assert [q.name for q in load_queries(tmp_path)] == ["q0.png", "q1.png"]  # a folder with queries.txt


def test_seed_queries_txt_written_lat_first_is_caught(tmp_path):
    _write_image(tmp_path / "q0.png")
    (tmp_path / "queries.txt").write_text("filename lon lat\nq0.png 47.02 -99.15\n")  # lat, lon: wrong order
    with pytest.raises(AerolocError, match=r"queries.txt:2: latitude -99.15 out of range"):
        load_queries(tmp_path / "queries.txt")


def test_images_beside_the_csv(tmp_path):
    _write_image(tmp_path / "x.png")
    (tmp_path / "set.csv").write_text("name,lat,lon\nx.png,47.0,-99.0\n")
    (q,) = load_queries(tmp_path / "set.csv")
    assert q.path == tmp_path / "x.png" and (q.lat, q.lon) == (47.0, -99.0)


def test_truthless_rows_are_kept_without_truth(tmp_path):
    _write_image(tmp_path / "queries" / "x.png")
    (tmp_path / "set.csv").write_text("name,lat,lon\nx.png,,\n")
    (q,) = load_queries(tmp_path / "set.csv")
    assert not q.has_truth


def test_a_csv_of_photos_to_localize_needs_no_truth_columns(tmp_path):
    """A drone's photos have no truth: name and prior columns alone are a query set (the priors read, no truth)."""
    _write_image(tmp_path / "queries" / "x.png")
    (tmp_path / "set.csv").write_text("name,alt_agl_m,hfov_deg,heading_deg,heading_tol_deg\nx.png,120,60,30,15\n")
    (q,) = load_queries(tmp_path / "set.csv")
    assert not q.has_truth and math.isnan(q.lat)
    assert q.priors.heading_deg == 30 and q.priors.heading_tol_deg == 15 and q.priors.alt_agl_m == 120


@pytest.mark.parametrize(
    "text,match",
    [
        ("name,lat\nx.png,47.0\n", r"set.csv: missing columns \['lon'\]"),
        ("file,lat,lon\nx.png,47.0,-99.0\n", r"set.csv: missing columns \['name'\]"),
        ("name,lat,lon\nx.png,47.0,-99.0\nx.png,forty,-99.0\n", r"set.csv:3: lat 'forty' is not a number"),
        ("name,lat,lon\nx.png,-99.0,47.0\n", r"set.csv:2: latitude -99.0 out of range"),
        ("name,lat,lon\nx.png,47.0,200\n", r"set.csv:2: longitude 200.0 out of range"),
        ("name,lat,lon\nx.png,47.0,-99.0,extra\n", r"set.csv:2: the row does not have the header's 3 columns"),
        ("name,lat,lon\nx.png,47.0,-99.0\nx.png,47.0\n", r"set.csv:3: the row does not have the header's 3 columns"),
        ("name,lat,lon\n", r"set.csv: no queries"),
        ("name,lat,lon,heading_deg\nx.png,47.0,-99.0,north\n", r"set.csv:2: heading_deg 'north'"),
    ],
)
def test_bad_csv(tmp_path, text, match):
    _write_image(tmp_path / "x.png")
    (tmp_path / "set.csv").write_text(text)
    with pytest.raises(AerolocError, match=match):
        load_queries(tmp_path / "set.csv")


@pytest.mark.parametrize(
    "text,match",
    [
        ("filename lon lat\nq0.png -99.15\n", r"queries.txt:2: expected 'filename lon lat'"),
        ("filename lon lat\nq0.png -99.15 north\n", r"queries.txt:2: lat 'north' is not a number"),
        ("filename lon lat\n", r"queries.txt: no queries"),
    ],
)
def test_bad_seed_txt(tmp_path, text, match):
    _write_image(tmp_path / "q0.png")
    (tmp_path / "queries.txt").write_text(text)
    with pytest.raises(AerolocError, match=match):
        load_queries(tmp_path / "queries.txt")


def test_missing_image_and_missing_set(tmp_path):
    (tmp_path / "set.csv").write_text("name,lat,lon\nghost.png,47.0,-99.0\n")
    with pytest.raises(AerolocError, match=r"set.csv: image for query 'ghost.png' not found"):
        load_queries(tmp_path / "set.csv")
    assert load_queries(tmp_path / "set.csv", require_images=False)[0].name == "ghost.png"
    with pytest.raises(AerolocError, match=r"nothing\.csv"):
        load_queries(tmp_path / "nothing.csv")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(AerolocError, match="no images"):
        load_queries(empty)


def test_query_lat_lon_are_floats_not_strings(naip_dev):
    q = load_queries(naip_dev)[0]
    assert isinstance(q.lat, float) and isinstance(q.lon, float) and np.isfinite([q.lat, q.lon]).all()
