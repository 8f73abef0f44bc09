"""The any-heading, any-scale sweep: its disk correlation is the NCC it claims, turned queries keep their centre,
and on real Texas suburbs it finds a query's place, heading and scale with no prior at all."""

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from aeroloc.core import geo
from aeroloc.core.images import read_image
from aeroloc.core.queries import load_queries
from aeroloc.localization.screening import refusal
from aeroloc.localization.sweep_stage import SweepLocator, upright
from aeroloc.maps.sources import open_map
from aeroloc.matching.sweep import DiskCorrelator, hypotheses


def _brute_disk_ncc(region: np.ndarray, q: np.ndarray, y: int, x: int) -> float:
    d = q.shape[0]
    D = DiskCorrelator.disk(d).astype(bool)
    a = region[y : y + d, x : x + d][D].astype(np.float64)  # n x C
    b = q[D].astype(np.float64)
    a, b = a - a.mean(0), b - b.mean(0)
    return float((a * b).sum() / math.sqrt((a**2).sum() * (b**2).sum()))


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(8, 14))
def test_the_disk_correlation_is_the_ncc_over_the_inscribed_disk(seed, d):
    rng = np.random.default_rng(seed)
    region = rng.random((40, 37, 3)).astype(np.float32)
    q = rng.random((d, d, 3)).astype(np.float32)
    res = DiskCorrelator(region)(q)
    assert res.shape == (40 - d + 1, 37 - d + 1)
    for y, x in ((0, 0), (res.shape[0] - 1, res.shape[1] - 1), (5, 7)):
        assert res[y, x] == pytest.approx(_brute_disk_ncc(region, q, y, x), abs=1e-3)
    # the template cut from the region itself correlates perfectly where it was cut
    assert DiskCorrelator(region)(region[9 : 9 + d, 4 : 4 + d])[9, 4] == pytest.approx(1.0, abs=1e-4)


@pytest.mark.parametrize("angle", [0.0, 33.0, 90.0, 217.5])
def test_a_turned_query_keeps_its_centre_and_all_its_pixels(angle):
    img = np.zeros((60, 90, 3), np.uint8)
    img[28:32, 43:47] = 255  # a mark on the centre (45, 30)
    img[0, :] = img[-1, :] = 80  # a frame, so every pixel of the image is 'valid' content
    up, mask = upright(img, angle)
    H, W = up.shape[:2]
    ys, xs = np.nonzero(up[..., 0] > 200)
    assert abs(xs.mean() + 0.5 - W / 2) < 1.0 and abs(ys.mean() + 0.5 - H / 2) < 1.0
    assert 0.8 * 60 * 90 <= mask.sum() <= 60 * 90  # the image's own pixels (edge eroded), never the empty corners


def test_the_scale_ladder_spans_the_range_in_steps_no_larger_than_asked():
    angles, scales = hypotheses((0.0, 15.0), 0.25, 2.0, 1.26)
    assert angles == [0.0, 15.0]
    assert 0.25 < scales[0] < scales[-1] < 2.0
    assert all(b / a <= 1.26 + 1e-9 for a, b in itertools.pairwise(scales))
    assert hypotheses((0.0,), 0.5, 0.5, 1.26)[1] == [pytest.approx(0.5)]


@pytest.mark.slow
def test_the_sweep_finds_place_heading_and_scale_without_priors(data_dir):
    """Texas suburbs (LEVIR-CD, 0.5 m/px map of the later date, queries of the earlier date turned to any heading
    and 1.9-2.5x finer than the map): with neither heading nor ground resolution known the sweep's best candidate
    lies within 5 m, its heading within 10° and its scale within 15 % of the truth (measured: 1.5-3 m, 1-3°)."""
    loc = SweepLocator(open_map(data_dir / "multi-region/levir-tx/map.tif"))
    qs = {q.name: q for q in load_queries(data_dir / "multi-region/levir-tx/any/queries.csv", priors="auto")}
    for name in ("levir_any_0_01.jpg", "levir_any_0_04.jpg"):
        q = qs[name]
        image = read_image(q.path)
        res = loc.search(image, None)
        h = res.best
        lat, lon = loc.map.pixel_to_latlon(h.col, h.row)
        assert geo.geodesic_distance(lat, lon, q.lat, q.lon) < 5.0, (name, h)
        assert abs((h.angle - q.truth_heading_deg + 180) % 360 - 180) < 10.0, (name, h.angle, q.truth_heading_deg)
        true_scale = q.truth_gsd_m / loc.map_gsd
        assert h.scale == pytest.approx(true_scale, rel=0.15), (name, h.scale, true_scale)


@pytest.mark.slow
def test_a_heading_between_the_old_15_degree_steps_is_found_without_priors(data_dir):
    """NAIP 2009 against the 2020 map, heading 10.8°, no priors: at 15° steps the sweep's candidates lay 0.7-2.8 km
    off (the query's cross-year field pattern matches the truth only within a few degrees); at 10° steps its best
    lies within 25 m of the truth (measured 9 m), heading 10°, the map's own scale."""
    loc = SweepLocator(open_map(data_dir / "naip-nd/map_20200831.tif"))
    assert loc.conf["heading_step"] == 10.0
    qs = load_queries(data_dir / "naip-nd/dev/queries.csv", priors="auto")
    q = next(q for q in qs if q.name == "naip_20090818_n_014.jpg")
    h = loc.search(read_image(q.path), None).best
    lat, lon = loc.map.pixel_to_latlon(h.col, h.row)
    assert geo.geodesic_distance(lat, lon, q.lat, q.lon) < 25.0, h
    assert abs((h.angle - q.truth_heading_deg + 180) % 360 - 180) < 8.0 and h.scale == pytest.approx(1.0, rel=0.1), h


def test_queries_that_cannot_be_localized_say_why():
    rng = np.random.default_rng(0)
    photo = rng.integers(0, 255, (200, 300, 3), dtype=np.uint8)
    assert refusal(photo) is None
    assert "smaller than the 32 px" in refusal(photo[:20, :300])
    strip = rng.integers(0, 255, (40, 1000, 3), dtype=np.uint8)  # 40 px high: 20 px once 1000 px become 512
    assert refusal(strip) is None and refusal(photo, work_side=512) is None
    assert "its short side is 20 px" in refusal(strip, work_side=512)
    assert "100 % no-data" in refusal(np.zeros((200, 300, 3), np.uint8))
    assert "uniform" in refusal(np.full((200, 300, 3), 128, np.uint8))
    # the grey levels' spread is the same number as that of the mean over the channels, no-data left out
    from aeroloc.core.images import valid_mask
    from aeroloc.localization.screening import _grey

    for img in (photo, np.where(np.arange(photo.shape[1])[None, :, None] < 100, 0, photo).astype(np.uint8)):
        valid = valid_mask(img)
        assert float(_grey(img)[valid].std()) == float(img[valid].astype(np.float32).mean(axis=-1).std())
    from aeroloc.core.priors import Priors

    far = Priors(gsd_m=0.01, gsd_tol=0.25)  # 1 cm/px against a 5 m/px map: 500x finer
    assert "outside what the 5 m/px map" in refusal(photo, 5.0, far)
    assert refusal(photo, 5.0, Priors(gsd_m=2.0, gsd_tol=0.25)) is None
