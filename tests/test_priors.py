"""priors.py: per-query priors from the real query CSVs, EXIF and flags; truth kept apart; bad input is one line."""

from __future__ import annotations

import argparse
import csv
import math
from pathlib import Path

import pytest
from PIL import Image, TiffImagePlugin

from aeroloc.commands.priors_args import add_prior_arguments, priors_from_args
from aeroloc.core.errors import AerolocError
from aeroloc.core.priors import (
    PriorOverrides,
    Priors,
    apply_overrides,
    describe_priors,
    gsd_from_focal,
    gsd_from_hfov,
    hfov_from_35mm,
    perturbation,
)
from aeroloc.core.queries import Query, load_queries

N = 12  # rows of a real set used where all of it is not needed


@pytest.fixture(scope="session")
def levir_any(data_dir):
    return data_dir / "multi-region" / "levir-tx" / "any" / "queries.csv"


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _width(path):
    with Image.open(path) as im:
        return im.size[0]


def _slice(tmp_path, real_csv, n=N, extra_cols=None):
    """The first ``n`` rows of a real set in tmp_path (its images reached through a symlink, not copied), with
    ``extra_cols`` (column -> value per row, or one value for all) added."""
    rows = _rows(real_csv)[:n]
    for col, v in (extra_cols or {}).items():
        for i, r in enumerate(rows):
            r[col] = v[i] if isinstance(v, list) else v
    (tmp_path / "queries").symlink_to(real_csv.parent / "queries")
    out = tmp_path / "queries.csv"
    with open(out, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return out, rows


def _gap(a, b):
    return abs((a - b + 180.0) % 360.0 - 180.0)


# ------------------------------------------------------------------------------------------ the real sets' columns


def test_generated_set_truth_is_kept_but_not_a_prior_by_default(levir_any):
    rows = _rows(levir_any)
    qs = load_queries(levir_any)  # priors="auto"
    assert len(qs) == len(rows) == 40
    for q, r in zip(qs, rows):
        assert q.truth_heading_deg == q.heading_deg == float(r["heading_deg"])
        assert q.truth_gsd_m == float(r["gsd_m"])
        assert not q.priors.known and q.priors.gsd_range() is None and q.priors.heading_range() is None
        assert q.priors.width_px == _width(q.path)
        assert "gsd_m" not in q.extra and q.extra["footprint_m"] == r["footprint_m"]
    assert describe_priors(qs) == "priors: no ground resolution; no heading"


def test_the_localize_line_names_the_options_that_stand_in_for_missing_priors(levir_any):
    """--query-gsd and --north-up are run-wide defaults, not per-query priors: the line says both, so a run given
    them does not read "no ground resolution; no heading" alone."""
    from aeroloc.commands.localize import priors_line
    from aeroloc.localization.options import LocalizeOptions

    qs = load_queries(levir_any)[:N]
    assert priors_line(qs, LocalizeOptions()) == "priors: no ground resolution; no heading"
    line = priors_line(qs, LocalizeOptions(query_gsd=0.75, north_up=True))
    assert line.startswith("priors: no ground resolution; no heading; ")
    assert "--query-gsd 0.75 m for queries without their own" in line and "--north-up" in line


def test_csv_mode_reads_the_columns_as_priors(levir_any):
    rows = _rows(levir_any)[:N]
    qs = load_queries(levir_any, priors="csv")[:N]
    for q, r in zip(qs, rows):
        p = q.priors
        assert p.gsd_m == float(r["gsd_m"]) and p.gsd_tol == 0.25 and p.gsd_source == "gsd_m (csv)"
        assert p.heading_deg == float(r["heading_deg"]) % 360 and p.heading_tol_deg == 15.0
        assert p.heading_source == "heading_deg (csv)" and p.source("gsd_m") == "csv"
        assert p.gsd_range() == pytest.approx((0.75 * p.gsd_m, 1.25 * p.gsd_m))
        assert p.heading_range() == pytest.approx((p.heading_deg - 15, p.heading_deg + 15))


def test_exact_is_the_truth_and_naip_truth_gsd_is_footprint_over_width(levir_any, naip_dev):
    for q, r in zip(load_queries(levir_any, priors="exact")[:N], _rows(levir_any)):
        assert (q.priors.gsd_m, q.priors.heading_deg) == (float(r["gsd_m"]), float(r["heading_deg"]))
        assert q.priors.gsd_source == q.priors.heading_source.replace("heading_deg", "gsd_m") == "gsd_m (truth)"
        # the set's gsd_m is the footprint (rounded to 0.5 m) over the image width
        assert q.truth_gsd_m == pytest.approx(float(r["footprint_m"]) / _width(q.path), rel=5e-3)
    # naip-nd has no gsd_m column: its truth is footprint_m / width (5 m/px, the map's resolution)
    qs = load_queries(naip_dev, priors="exact")
    assert all(q.truth_gsd_m == pytest.approx(5.0, abs=1e-9) == q.priors.gsd_m for q in qs)
    assert all(not q.priors.known for q in load_queries(naip_dev))


def test_none_gives_no_priors_but_keeps_the_truth(levir_any, naip_dev):
    for path in (levir_any, naip_dev):
        qs = load_queries(path, priors="none")
        rows = _rows(path)
        assert all(not q.priors.known for q in qs)
        assert [q.truth_heading_deg for q in qs] == [float(r["heading_deg"]) for r in rows]
        assert all(q.has_truth and q.truth_gsd_m > 0 for q in qs)


def test_user_csv_heading_is_a_prior_by_default(tmp_path, levir_any):
    # the same rows without the generator's footprint_m column read as a user's flight log
    real = _rows(levir_any)[:N]
    (tmp_path / "queries").symlink_to(levir_any.parent / "queries")
    with open(tmp_path / "log.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["name", "lat", "lon", "heading_deg", "heading_tol_deg"])
        w.writerows([[r["name"], r["lat"], r["lon"], r["heading_deg"], 20] for r in real])
    qs = load_queries(tmp_path / "log.csv")
    for q, r in zip(qs, real):
        assert q.priors.heading_deg == float(r["heading_deg"]) and q.priors.heading_tol_deg == 20
        assert q.priors.gsd_m is None and q.truth_heading_deg == float(r["heading_deg"])


# --------------------------------------------------------------------------------------- ground resolution, derived


def test_gsd_from_height_and_field_of_view_or_focal_length(tmp_path, levir_any):
    alts = [40.0 + 7 * i for i in range(N)]
    path, _ = _slice(
        tmp_path,
        levir_any,
        extra_cols={
            "alt_agl_m": [str(a) for a in alts],
            "hfov_deg": ["" if i % 2 else "73.7" for i in range(N)],  # even rows: field of view
            "focal_mm": ["" if i % 2 == 0 else "8.8" for i in range(N)],  # odd rows: focal length + sensor
            "sensor_w_mm": ["" if i % 2 == 0 else "13.2" for i in range(N)],
            "gsd_m": "",  # the generator's gsd_m left out: the camera gives it
        },
    )
    for i, (q, a) in enumerate(zip(load_queries(path), alts)):
        w = _width(q.path)
        if i % 2 == 0:
            want = 2 * a * math.tan(math.radians(73.7) / 2) / w
            assert q.priors.gsd_from == "alt_agl_m+hfov_deg"
            assert q.priors.gsd_source == "alt_agl_m (csv) + hfov_deg (csv)"
        else:
            want = a * 13.2 / (8.8 * w)
            assert q.priors.gsd_from == "alt_agl_m+focal_mm+sensor_w_mm"
        assert abs(q.priors.gsd_m - want) < 1e-9 and q.priors.width_px == w
        assert q.priors.alt_agl_m == a
    assert gsd_from_hfov(100, 90, 200) == pytest.approx(1.0, abs=1e-12)
    assert gsd_from_focal(100, 10, 20, 200) == pytest.approx(1.0, abs=1e-12)


def test_given_and_derived_gsd_that_agree_are_accepted(tmp_path, levir_any):
    rows = _rows(levir_any)[:3]
    # alt such that alt + hfov 90° gives gsd_m x 1.2: inside ±25 %
    widths = [_width(levir_any.parent / "queries" / r["name"]) for r in rows]
    alts = [str(float(r["gsd_m"]) * 1.2 * w / 2) for r, w in zip(rows, widths)]
    path, _ = _slice(tmp_path, levir_any, 3, {"alt_agl_m": alts, "hfov_deg": "90"})
    for q, r in zip(load_queries(path, priors="csv"), rows):
        assert q.priors.gsd_m == float(r["gsd_m"]) and q.priors.gsd_from == "gsd_m"  # the given value is used


# ------------------------------------------------------------------------------------------------------ bad input


def _write_png(path, size=(200, 150)):
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", size, (40, 80, 120)).save(path)


@pytest.mark.parametrize(
    "col,value,match",
    [
        ("gsd_m", "fine", r"gsd_m 'fine' is not a number"),
        ("gsd_m", "nan", r"gsd_m 'nan' is not a finite number"),
        ("gsd_m", "0", r"gsd_m 0 must be > 0"),
        ("gsd_m", "-0.3", r"gsd_m -0.3 must be > 0"),
        ("alt_agl_m", "0", r"alt_agl_m 0 must be > 0 \(height above ground"),
        ("alt_agl_m", "-20", r"alt_agl_m -20 must be > 0"),
        ("alt_agl_m", "high", r"alt_agl_m 'high' is not a number"),
        ("hfov_deg", "0", r"hfov_deg 0 must be between 0 and 180"),
        ("hfov_deg", "180", r"hfov_deg 180 must be between 0 and 180"),
        ("hfov_deg", "-5", r"hfov_deg -5 must be between 0 and 180"),
        ("focal_mm", "0", r"focal_mm 0 must be > 0"),
        ("sensor_w_mm", "-1", r"sensor_w_mm -1 must be > 0"),
        ("heading_deg", "north", r"heading_deg 'north' is not a number"),
        ("heading_tol_deg", "-1", r"heading_tol_deg -1 must be between 0 and 180"),
        ("heading_tol_deg", "181", r"heading_tol_deg 181 must be between 0 and 180"),
        ("gsd_tol", "0", r"gsd_tol 0 must be between 0 and 1"),
        ("gsd_tol", "1", r"gsd_tol 1 must be between 0 and 1"),
        ("gsd_tol", "25", r"gsd_tol 25 must be between 0 and 1"),
    ],
)
def test_bad_prior_names_file_row_and_column(tmp_path, col, value, match):
    _write_png(tmp_path / "queries" / "a.png")
    _write_png(tmp_path / "queries" / "b.png")
    # the bad value on the second data row = line 3
    (tmp_path / "set.csv").write_text(f"name,lat,lon,{col}\na.png,47.0,-99.0,\nb.png,47.0,-99.0,{value}\n")
    for mode in ("auto", "none", "exact"):  # a bad cell is bad whatever becomes a prior
        with pytest.raises(AerolocError, match=r"set\.csv:3: " + match) as err:
            load_queries(tmp_path / "set.csv", priors=mode)
        assert "\n" not in str(err.value)


def test_contradicting_gsd_names_both_values(tmp_path):
    _write_png(tmp_path / "queries" / "a.png", (200, 150))
    # 2 * 100 m * tan(45°) / 200 px = 1.0 m/px against the 0.5 given
    (tmp_path / "set.csv").write_text("name,lat,lon,gsd_m,alt_agl_m,hfov_deg\na.png,47.0,-99.0,0.5,100,90\n")
    with pytest.raises(AerolocError) as err:
        load_queries(tmp_path / "set.csv")
    msg = str(err.value)
    assert msg.startswith(f"{tmp_path / 'set.csv'}:2: ") and "\n" not in msg
    assert "gsd_m (csv) = 0.5 m/px" in msg and "alt_agl_m (csv) = 100 m with hfov_deg (csv) = 90°" in msg
    assert "giving 1 m/px at 200 px wide" in msg and "gsd_tol 0.25" in msg
    # a wider tolerance lets them agree
    (tmp_path / "set.csv").write_text(
        "name,lat,lon,gsd_m,gsd_tol,alt_agl_m,hfov_deg\na.png,47.0,-99.0,0.8,0.3,100,90\n"
    )
    assert load_queries(tmp_path / "set.csv")[0].priors.gsd_m == 0.8
    # the two camera derivations contradicting each other
    (tmp_path / "set.csv").write_text(
        "name,lat,lon,alt_agl_m,hfov_deg,focal_mm,sensor_w_mm\na.png,47.0,-99.0,100,90,10,5\n"
    )
    with pytest.raises(
        AerolocError, match=r"set\.csv:2: alt_agl_m \(csv\) = 100 m with hfov_deg .* contradicts .*focal_mm"
    ):
        load_queries(tmp_path / "set.csv")


def test_unknown_mode(levir_any):
    with pytest.raises(AerolocError, match=r"priors mode 'truth' unknown \(one of auto, csv, none, exact, rough\)"):
        load_queries(levir_any, priors="truth")


# ------------------------------------------------------------------------------------------------ rough priors


def test_rough_is_deterministic_bounded_and_not_the_truth(levir_any, naip_dev):
    for path in (levir_any, naip_dev):
        a = load_queries(path, priors="rough", seed=7)
        b = load_queries(path, priors="rough", seed=7)
        c = load_queries(path, priors="rough", seed=8)
        assert [q.priors for q in a] == [q.priors for q in b]
        for qa, qc in zip(a, c):
            assert qa.priors.gsd_m != qc.priors.gsd_m and qa.priors.heading_deg != qc.priors.heading_deg
        for q in a:
            p = q.priors
            f = p.gsd_m / q.truth_gsd_m
            assert 0.8 <= f <= 1.25 and f != 1.0
            shift = _gap(p.heading_deg, q.truth_heading_deg)
            assert 0 < shift <= 15 + 1e-9 and 0 <= p.heading_deg < 360
            lo, hi = p.gsd_range()
            assert lo <= q.truth_gsd_m <= hi and p.heading_contains(q.truth_heading_deg)  # the tolerance holds
            assert p.gsd_source == "gsd_m (truth) + noise (seed 7)"
        factors = [q.priors.gsd_m / q.truth_gsd_m for q in a]
        assert min(factors) < 0.9 and max(factors) > 1.15  # spread over the range, not a constant


def test_perturbation_depends_on_the_query_not_its_order(levir_any):
    qs = load_queries(levir_any, priors="exact")
    fwd = apply_overrides(qs, PriorOverrides(perturb_seed=3))
    back = apply_overrides(qs[::-1][:10], PriorOverrides(perturb_seed=3))
    by_name = {q.name: q.priors for q in fwd}
    assert all(q.priors == by_name[q.name] for q in back)
    # rough = exact, then perturbed = auto, then the truth perturbed from the command line
    rough = load_queries(levir_any, priors="rough", seed=3)
    from_cli = apply_overrides(load_queries(levir_any), PriorOverrides(from_truth=True, perturb_seed="3"))
    for r, e, c in zip(rough, fwd, from_cli):
        assert r.priors.gsd_m == pytest.approx(e.priors.gsd_m) == pytest.approx(c.priors.gsd_m)
        assert r.priors.heading_deg == pytest.approx(e.priors.heading_deg) == pytest.approx(c.priors.heading_deg)
    f, s = perturbation(3, qs[0].name)
    assert rough[0].priors.gsd_m == pytest.approx(qs[0].truth_gsd_m * f, rel=1e-12)
    assert _gap(rough[0].priors.heading_deg, qs[0].truth_heading_deg) == pytest.approx(abs(s), abs=1e-9)


# ---------------------------------------------------------------------------------------------------------- EXIF


def test_toledo_photos_give_field_of_view_but_no_ground_resolution(data_dir):
    for qs in (load_queries(data_dir / "toledo" / "photos"), load_queries(data_dir / "toledo" / "queries.csv")):
        assert len(qs) == 57
        for q in qs:
            p = q.priors
            assert p.gsd_m is None and p.gsd_range() is None and p.alt_agl_m is None  # GPS altitude is not AGL
            assert q.alt_m is not None and q.alt_m > 0
            assert p.heading_deg is None  # DJI writes no GPSImgDirection
            assert p.hfov_deg == pytest.approx(2 * math.degrees(math.atan(36 / 40)), abs=1e-9)  # f35 = 20 mm
            assert p.focal_mm == pytest.approx(3.61) and p.sensor_w_mm is None and p.width_px == 1200
            assert p.source("hfov_deg") == "exif FocalLengthIn35mmFilm"
        assert "ground resolution unknown" in qs[0].priors.describe()
    # the pilot's height above ground makes it one, with EXIF's field of view
    (q,) = apply_overrides(qs[:1], PriorOverrides(alt_agl_m=100))
    assert abs(q.priors.gsd_m - 2 * 100 * (36 / 40) / 1200) < 1e-9  # tan(atan(36/40)) = 0.9
    assert q.priors.gsd_source == "--alt-agl + hfov_deg (exif FocalLengthIn35mmFilm)"


def test_exif_heading_and_35mm_focal_length(tmp_path):
    R = TiffImagePlugin.IFDRational
    exif = Image.Exif()
    exif[0x8769] = {0xA405: 50, 0x920A: R(8)}
    exif[0x8825] = {16: "T", 17: R(2705, 10)}
    Image.new("RGB", (400, 300)).save(tmp_path / "p.jpg", exif=exif)
    (q,) = load_queries(tmp_path)
    assert q.priors.heading_deg == 270.5 and q.priors.heading_source == "heading_deg (exif GPSImgDirection)"
    assert q.priors.hfov_deg == pytest.approx(hfov_from_35mm(50)) == pytest.approx(39.5977527, abs=1e-6)
    assert q.priors.focal_mm == 8.0 and q.priors.gsd_m is None
    # the CSV's values beat EXIF's; with the height above ground, the EXIF field of view gives the gsd
    (tmp_path / "set.csv").write_text("name,lat,lon,heading_deg,alt_agl_m\np.jpg,47.0,-99.0,10,50\n")
    (q,) = load_queries(tmp_path / "set.csv")
    assert q.priors.heading_deg == 10.0 and q.priors.heading_source == "heading_deg (csv)"
    assert abs(q.priors.gsd_m - 2 * 50 * math.tan(math.radians(hfov_from_35mm(50)) / 2) / 400) < 1e-9
    assert q.priors.gsd_source == "alt_agl_m (csv) + hfov_deg (exif FocalLengthIn35mmFilm)"
    assert not load_queries(tmp_path / "set.csv", priors="none")[0].priors.known


# -------------------------------------------------------------------------------------------------- CLI overrides


def _parse(argv):
    p = argparse.ArgumentParser()
    add_prior_arguments(p)
    return priors_from_args(p.parse_args(argv))


def test_flags_override_the_file(levir_any):
    qs = load_queries(levir_any, priors="csv")[:N]
    before = [q.priors for q in qs]
    assert apply_overrides(qs, _parse([])) == qs  # no flags: unchanged
    out = apply_overrides(qs, _parse(["--heading", "370", "--heading-tol", "30", "--gsd-tol", "0.1"]))
    for q, o in zip(qs, out):
        assert (
            o.priors.heading_deg == 10.0 and o.priors.heading_tol_deg == 30 and o.priors.heading_source == "--heading"
        )
        assert o.priors.gsd_m == q.priors.gsd_m and o.priors.gsd_tol == 0.1  # the file's gsd, a flag's tolerance
    assert [q.priors for q in qs] == before  # pure
    # --no-priors drops the file's, the flags still apply
    out = apply_overrides(qs, _parse(["--no-priors", "--gsd", "0.3"]))
    assert all(o.priors.gsd_m == 0.3 and o.priors.heading_deg is None and o.priors.gsd_source == "--gsd" for o in out)
    # a camera flag replaces the file's gsd_m: here the height above ground with the field of view
    out = apply_overrides(qs, _parse(["--alt-agl", "120", "--hfov", "80"]))
    for q, o in zip(qs, out):
        assert abs(o.priors.gsd_m - gsd_from_hfov(120, 80, _width(q.path))) < 1e-12
        assert o.priors.gsd_source == "--alt-agl + --hfov" and o.priors.heading_deg == q.priors.heading_deg
    # --priors-from-truth on the default (no-prior) load is exact
    exact = apply_overrides(load_queries(levir_any)[:N], _parse(["--priors-from-truth"]))
    assert [q.priors.gsd_m for q in exact] == [q.truth_gsd_m for q in qs]


def test_bad_flags_are_one_line_errors_naming_the_flag():
    for argv, match in [
        (["--gsd", "abc"], r"^--gsd: --gsd 'abc' is not a number$"),
        (["--alt-agl", "-3"], r"^--alt-agl: --alt-agl -3 must be > 0"),
        (["--hfov", "200"], r"^--hfov: --hfov 200 must be between 0 and 180"),
        (["--heading-tol", "190"], r"^--heading-tol: --heading-tol 190 must be between 0 and 180"),
        (["--gsd-tol", "1.5"], r"^--gsd-tol: --gsd-tol 1.5 must be between 0 and 1"),
        (["--perturb-priors", "x1"], r"^--perturb-priors 'x1' is not an integer seed$"),
    ]:
        with pytest.raises(AerolocError, match=match):
            _parse(argv)
    with pytest.raises(SystemExit):  # argparse: mutually exclusive
        _parse(["--no-priors", "--priors-from-truth"])
    with pytest.raises(AerolocError, match="exclude each other"):
        PriorOverrides(no_priors=True, from_truth=True)


def test_flags_that_contradict_each_other(tmp_path):
    _write_png(tmp_path / "queries" / "a.png", (200, 150))
    (tmp_path / "set.csv").write_text("name,lat,lon\na.png,47.0,-99.0\n")
    qs = load_queries(tmp_path / "set.csv")
    with pytest.raises(AerolocError, match=r"set\.csv:2: --gsd = 0.3 m/px contradicts --alt-agl = 100 m with --hfov"):
        apply_overrides(qs, _parse(["--gsd", "0.3", "--alt-agl", "100", "--hfov", "90"]))


# ------------------------------------------------------------------------------------------------------ helpers


def test_ranges_and_heading_search():
    assert Priors().gsd_range() is None and Priors().heading_range() is None and Priors().heading_search() is None
    p = Priors(gsd_m=0.4, gsd_tol=0.25, heading_deg=350.0, heading_tol_deg=15.0)
    assert p.gsd_range() == pytest.approx((0.3, 0.5)) and p.heading_range() == (335.0, 365.0)
    assert p.heading_contains(2.0) and p.heading_contains(-25.0) and not p.heading_contains(10.0)
    assert p.heading_search(7.5) == pytest.approx((-25.0, -17.5, -10.0, -2.5, 5.0))
    assert len(Priors(heading_deg=0.0, heading_tol_deg=180).heading_search(7.5)) == 48
    assert Priors(heading_deg=90.0, heading_tol_deg=0).heading_search() == (90.0,)


def test_with_image_width_rescales_or_derives():
    p = Priors(gsd_m=0.5, width_px=1200)
    assert p.with_image_width(600).gsd_m == pytest.approx(1.0) and p.with_image_width(1200) is p
    ghost = Query("ghost.png", Path("ghost.png"), origin="ghost.csv:2")  # require_images=False, the file absent
    q = apply_overrides([ghost], PriorOverrides(alt_agl_m=100, hfov_deg=90))[0].priors
    assert q.gsd_m is None and q.alt_agl_m == 100  # no image width yet
    assert q.with_image_width(400).gsd_m == pytest.approx(0.5, abs=1e-12)
