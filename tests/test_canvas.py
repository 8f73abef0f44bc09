"""A photo on a black canvas (padded, letterboxed, turned with black corners) is seen as the photo alone before
localization (aeroloc.core.canvas): turned back upright when tilted, then cut to a centred window that holds no
canvas and keeps the photo's centre; every image whose corners are not all canvas is left as it is. End to end, a window of the real NAIP map on such a canvas
is placed within a map pixel, and a flight's pose read from the fix's homography at the whole image's centre
lands on the same place."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from _windows import cut_at_heading
from aeroloc.core import geo
from aeroloc.core.canvas import photo_view
from aeroloc.core.frames import turned
from aeroloc.core.images import read_image


def _padded(photo: np.ndarray, top: int, bottom: int, left: int, right: int) -> np.ndarray:
    h, w = photo.shape[:2]
    out = np.zeros((h + top + bottom, w + left + right, 3), np.uint8)
    out[top : top + h, left : left + w] = photo
    return out


@pytest.fixture(scope="module")
def photo(naip_dev) -> np.ndarray:
    from aeroloc.core.queries import load_queries

    q = next(q for q in load_queries(naip_dev) if q.name == "naip_20120731_n_018.jpg")
    return read_image(q.path)


def test_a_photo_without_a_canvas_is_left_as_it_is(photo):
    assert photo_view(photo) is None
    # ground missing on one side only (a flight frame at the edge of the imagery): two corners are not canvas
    half = photo.copy()
    half[:, : photo.shape[1] // 3] = 0
    assert photo_view(half) is None


def test_a_centred_padding_is_cut_back_to_the_photo_exactly(photo):
    v = photo_view(_padded(photo, 40, 40, 90, 90))
    assert (v.window.x0, v.window.y0, v.turn_deg) == (90, 40, 0.0)
    assert np.array_equal(v.image, photo)


def test_an_uneven_padding_keeps_the_photo_centre_and_no_canvas(photo):
    image = _padded(photo, 10, 50, 0, 0)  # letterbox bars of unequal height
    v = photo_view(image)
    assert (v.window.y0, v.window.x0) == (50, 0)  # the thicker bar sets the symmetric margin
    assert np.array_equal(v.image, photo[40:])  # photo rows only: the thin bar's side gives up 40 of them
    # the view's centre is the image's centre, to the pixel
    centre = v.to_view @ [image.shape[1] / 2, image.shape[0] / 2, 1]
    assert centre[:2] == pytest.approx([v.image.shape[1] / 2, v.image.shape[0] / 2])


@pytest.mark.parametrize("angle", [10.0, 37.0, 45.0, 137.0, 300.0])
def test_a_turned_photo_is_turned_back_and_cut_to_nearly_all_of_itself(photo, angle):
    image = turned(photo, angle, "black")[0]
    v = photo_view(image)
    residual = (angle + v.turn_deg) % 90.0  # turned back upright, up to quarter turns
    assert min(residual, 90.0 - residual) < 0.5
    assert v.image.size > 0.95 * photo.size  # measured 0.977-0.984 (the turned edges' blended pixels are dropped)
    # the same pixels about the same centre: the photo turned by the quarter turns left over
    k = round(((angle + v.turn_deg) % 360.0) / 90.0) % 4
    upright = np.rot90(photo, k)
    hh, ww = v.image.shape[:2]
    y0, x0 = (upright.shape[0] - hh) // 2, (upright.shape[1] - ww) // 2
    same = upright[y0 : y0 + hh, x0 : x0 + ww, 1].astype(float)
    assert np.corrcoef(same.ravel(), v.image[..., 1].astype(float).ravel())[0, 1] > 0.95  # measured 0.97-0.99
    centre = v.to_view @ [image.shape[1] / 2, image.shape[0] / 2, 1]
    assert centre[:2] == pytest.approx([ww / 2, hh / 2], abs=1e-6)


def test_a_jpeg_canvas_and_dark_ground_inside_the_photo(photo):
    padded = _padded(photo, 30, 30, 30, 30)
    padded[100:140, 100:160] = 0  # black ground inside the photo is not canvas
    buf = io.BytesIO()
    Image.fromarray(padded).save(buf, format="JPEG", quality=80)
    v = photo_view(np.asarray(Image.open(buf).convert("RGB")))
    assert v.turn_deg == 0.0
    assert 30 <= v.window.x0 <= 33 and 30 <= v.window.y0 <= 33  # the canvas and the JPEG fringe along its edge


def test_an_all_black_image_has_no_view():
    assert photo_view(np.zeros((300, 400, 3), np.uint8)) is None


def _map_window(naip_map, heading: float, side: int):
    """A window of the NAIP map at ``heading`` (exact geometry) and its centre's lat/lon."""
    import rasterio
    from pyproj import Transformer

    with rasterio.open(naip_map) as ds:
        image = np.ascontiguousarray(ds.read([1, 2, 3]).transpose(1, 2, 0))
        cx, cy = 0.41 * ds.width + 0.2, 0.47 * ds.height + 0.6
        x, y = ds.transform @ (cx, cy)
        lon, lat = Transformer.from_crs(ds.crs, "EPSG:4326", always_xy=True).transform(x, y)
    return cut_at_heading(image, cx, cy, heading, side), lat, lon


@pytest.mark.slow
def test_a_map_window_on_a_black_canvas_is_placed_within_a_map_pixel(naip_db, naip_map):
    """Padded, and turned with black corners: placed within a map pixel without priors and with the exact ones
    (turned 40°: heading 320, which the view, turned back, takes as 0; the prior taken the other way, 280, leaves
    it not localized), and the pose a flight reads at the whole image's centre lies on the fix, turned as the
    whole image is."""
    from aeroloc.core.priors import Priors
    from aeroloc.flight.calibration import pose_from_dense, pose_from_homography, turn_difference
    from aeroloc.localization.localizer import Localizer
    from aeroloc.localization.options import LocalizeOptions
    from aeroloc.retrieval.database import Database

    db = Database(naip_db)
    localizer = Localizer(db, LocalizeOptions(method="xfeat-vlad", rerank="xfeat-lighterglue"), "cpu")
    cut, lat, lon = _map_window(naip_map, 0.0, 240)
    cases = [
        (_padded(cut, 60, 60, 130, 130), 0.0, None),
        (turned(cut, 30.0, "black")[0], 330.0, None),
        (turned(cut, 40.0, "black")[0], 320.0, Priors(gsd_m=5.0, heading_deg=320.0, heading_tol_deg=5.0)),
    ]
    for image, heading, priors in cases:
        res = localizer("canvas", image, priors=priors)
        assert res.status.startswith("localized"), res.status
        assert geo.geodesic_distance(lat, lon, res.lat, res.lon) < 5.0  # a map pixel
        size = (image.shape[1], image.shape[0])
        if res.dense is not None:
            pose = pose_from_dense(res.dense, 5.0)
        else:
            assert res.best is not None and res.best.H is not None, res.status
            tile = db.by_id[res.best.tile_id]
            pose = pose_from_homography(res.best.H, size, tile.col, tile.row)
        plat, plon = localizer.map.pixel_to_latlon(pose.x, pose.y)
        assert geo.geodesic_distance(res.lat, res.lon, plat, plon) < 5.0  # measured 0.3-0.6 m
        assert abs(turn_difference(pose.turn_deg - heading)) < 3.0, (pose.turn_deg, res.status)


def test_the_priors_follow_the_view():
    """A view's pixels are the image's (its ground resolution unchanged, where a resize would rescale it), and its
    heading is the image's less the turn back."""
    from aeroloc.core.priors import Priors

    p = Priors(gsd_m=2.0, heading_deg=10.0).with_image_width(1000)
    v = p.for_view(600, -30.0)
    assert (v.gsd_m, v.width_px, v.heading_deg) == (2.0, 600, 40.0)
    assert v.with_image_width(600).gsd_m == 2.0  # the stages that ask at the view's width
    assert p.with_image_width(600).gsd_m == pytest.approx(2.0 * 1000 / 600)  # what the cut would have been taken for
    assert p.for_view(600, 20.0).heading_deg == 350.0


@pytest.mark.parametrize("quality", [95, 75, 50])
def test_a_turned_photo_saved_as_jpeg_is_turned_back_too(photo, quality):
    """JPEG's ringing along the turned edges makes the photo region ragged (this 256 px photo turned 37° and saved
    at quality 75 filled 0.966 of its tightest rectangle, under the first threshold of 0.97): it is still seen as
    a turned rectangle and turned back."""
    buf = io.BytesIO()
    Image.fromarray(turned(photo, 37.0, "black")[0]).save(buf, format="JPEG", quality=quality)
    v = photo_view(np.asarray(Image.open(buf).convert("RGB")))
    assert abs(v.turn_deg + 37.0) < 0.5
    assert v.image.size > 0.95 * photo.size
