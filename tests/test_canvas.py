"""A photo on a black canvas (padded, letterboxed, turned with black corners) is cut to its centred window of
imagery before localization (aeroloc.core.canvas): the window holds no canvas, keeps the photo's centre, and leaves
every image whose corners are not all canvas as it is. End to end, a window of the real NAIP map on such a canvas
is placed within a map pixel, and a flight's pose read from the fix's homography at the whole image's centre
lands on the same place."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from aeroloc.core import geo
from aeroloc.core.canvas import photo_window
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
    assert photo_window(photo) is None
    # ground missing on one side only (a flight frame at the edge of the imagery): two corners are not canvas
    half = photo.copy()
    half[:, : photo.shape[1] // 3] = 0
    assert photo_window(half) is None


def test_a_centred_padding_is_cut_back_to_the_photo_exactly(photo):
    w = photo_window(_padded(photo, 40, 40, 90, 90))
    assert (w.x0, w.y0) == (90, 40)
    assert np.array_equal(w.cut(_padded(photo, 40, 40, 90, 90)), photo)


def test_an_uneven_padding_keeps_the_photo_centre_and_no_canvas(photo):
    image = _padded(photo, 10, 50, 0, 0)  # letterbox bars of unequal height
    w = photo_window(image)
    cut = w.cut(image)
    h = image.shape[0]
    assert (w.y0, w.x0) == (50, 0)  # the thicker bar sets the symmetric margin
    assert np.array_equal(cut, photo[40:])  # photo rows only: the thin bar's side gives up 40 of them
    # the window's centre is the image's centre, to the pixel
    assert w.y0 + cut.shape[0] / 2 == pytest.approx(h / 2)


def test_a_turned_photo_is_cut_to_a_centred_window_of_its_own_pixels(photo):
    image, own, _ = turned(photo, 37.0, "black")
    w = photo_window(image)
    assert w is not None
    window_own = w.cut(own)
    assert window_own.mean() > 0.99  # its own pixels, but for the erosion of the mask's edge
    assert abs(w.x0 + (image.shape[1] - 2 * w.x0) / 2 - image.shape[1] / 2) < 1e-9
    # the largest such window of a 37-degree turn holds about half the photo
    assert 0.35 < w.cut(image).size / photo.size < 0.7


def test_a_jpeg_canvas_and_dark_ground_inside_the_photo(photo):
    padded = _padded(photo, 30, 30, 30, 30)
    padded[200:260, 300:380] = 0  # black ground inside the photo is not canvas
    buf = io.BytesIO()
    Image.fromarray(padded).save(buf, format="JPEG", quality=80)
    jpeg = np.asarray(Image.open(buf).convert("RGB"))
    w = photo_window(jpeg)
    assert 30 <= w.x0 <= 33 and 30 <= w.y0 <= 33  # the canvas and the JPEG fringe along its edge


def test_an_all_black_image_has_no_window():
    assert photo_window(np.zeros((300, 400, 3), np.uint8)) is None


def _map_window(naip_map, heading: float, side: int):
    """A window of the NAIP map at ``heading`` (exact geometry) and its centre's lat/lon."""
    import rasterio
    from pyproj import Transformer
    from tests.test_localize import _cut_at_heading

    with rasterio.open(naip_map) as ds:
        image = np.ascontiguousarray(ds.read([1, 2, 3]).transpose(1, 2, 0))
        cx, cy = 0.41 * ds.width + 0.2, 0.47 * ds.height + 0.6
        x, y = ds.transform @ (cx, cy)
        lon, lat = Transformer.from_crs(ds.crs, "EPSG:4326", always_xy=True).transform(x, y)
    return _cut_at_heading(image, cx, cy, heading, side), lat, lon


@pytest.mark.slow
def test_a_map_window_on_a_black_canvas_is_placed_within_a_map_pixel(naip_db, naip_map):
    from aeroloc.flight.calibration import pose_from_homography
    from aeroloc.localization.localizer import Localizer
    from aeroloc.localization.options import LocalizeOptions
    from aeroloc.retrieval.database import Database

    db = Database(naip_db)
    localizer = Localizer(db, LocalizeOptions(method="xfeat-vlad", rerank="xfeat-lighterglue"), "cpu")
    cut, lat, lon = _map_window(naip_map, 0.0, 240)
    for image in (_padded(cut, 60, 60, 130, 130), turned(cut, 30.0, "black")[0]):
        res = localizer("canvas", image)
        assert res.status.startswith("localized"), res.status
        assert geo.geodesic_distance(lat, lon, res.lat, res.lon) < 5.0  # a map pixel
        # a flight's pose reads the fix's homography at the whole image's centre (measured 0.3 and 0.6 m off)
        assert res.best is not None and res.best.H is not None, res.status
        tile = db.by_id[res.best.tile_id]
        pose = pose_from_homography(res.best.H, (image.shape[1], image.shape[0]), tile.col, tile.row)
        plat, plon = localizer.map.pixel_to_latlon(pose.x, pose.y)
        assert geo.geodesic_distance(res.lat, res.lon, plat, plon) < 5.0
